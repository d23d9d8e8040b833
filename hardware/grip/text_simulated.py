"""A simulated text-line grip device: lines like ``1234,12.5000,13.1000`` into a pty.

For a simulated rig whose ``[glove] kind = "serial-text"``: the rig's real reader
(:class:`hardware.grip.text_source.TextGripSource`) opens the pty's ``port`` with
``serial.Serial`` exactly as it opens the lab's /dev/ttyACM0. Each line has the rig file's
columns, separator and time unit; the values are the simulated subject's grip in newtons, or
(``unit = "raw"``) the raw values the calibration maps back to them. Needs POSIX ptys.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from steerlab.hardware.grip.pty import PtyStreamer
from steerlab.hardware.grip.text_source import TIME_UNITS, TextGripConfig
from steerlab.hardware.grips import GripFunction

#: Bytes the pty may hold back before a line is lost (a reader that stopped reading).
_TX_LIMIT = 8192


class SimulatedTextDevice(PtyStreamer):
    """Writes one text line per sample at ``rate_hz`` into a pty; open ``port``."""

    thread_name = "grip-text-sim"
    sim_name = "simulated serial-text device"
    #: fault names :meth:`inject` knows (a simulated lab's glove faults)
    faults = ("glove_hang_up", "glove_stop", "bad_line")

    def __init__(
        self,
        grip: GripFunction,
        config: TextGripConfig,
        *,
        rate_hz: float = 100.0,
        decimals: int = 4,
        line_end: str = "\r\n",
        clock: Callable[[], float] = time.monotonic,
        on_error: Callable[[BaseException], None] | None = None,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        super().__init__(host_period_s=1.0 / rate_hz, tx_limit=_TX_LIMIT, clock=clock,
                         on_error=on_error)  # fmt: skip
        self._grip = grip
        self.config = config
        self._decimals = decimals
        self._line_end = line_end.encode("ascii")
        self._device_time_s = 0.0
        self._extra: list[bytes] = []
        self.lines_written = 0
        self.lines_skipped = 0  # not sent: stopped streaming, or suspended
        self.overflows = 0  # lost because nobody read the pty

    def send_line(self, text: str) -> None:
        """Write this line (its line end added) before the next sample."""
        with self._lock:
            self._extra.append(text.encode("ascii") + self._line_end)

    def inject(self, fault: str) -> None:
        """A simulated lab's glove fault (:attr:`faults`); ``bad_line``: one line with the
        later hand's column missing."""
        if fault == "glove_hang_up":
            self.hang_up()
        elif fault == "glove_stop":
            self.stop_streaming()
        elif fault == "bad_line":
            columns = self._columns(0.0, (0.0, 0.0))
            del columns[max(self.config.left, self.config.right) :]
            self.send_line(self._separator().join(columns))
        else:
            raise ValueError(f"unknown glove fault {fault!r} (known: {', '.join(self.faults)})")

    def _separator(self) -> str:
        return self.config.separator

    def _columns(self, device_time_s: float, values: tuple[float, float]) -> list[str]:
        c = self.config
        columns = ["0"] * (max(c.columns.values()) + 1)
        columns[c.left] = f"{values[0]:.{self._decimals}f}"
        columns[c.right] = f"{values[1]:.{self._decimals}f}"
        if c.time is not None and c.time_unit is not None:
            ticks = device_time_s / TIME_UNITS[c.time_unit]
            columns[c.time] = f"{ticks:.6f}" if c.time_unit == "s" else str(round(ticks))
        return columns

    def _skip(self, n: int) -> None:
        self._device_time_s += n * self._host_period_s
        self.lines_skipped += n

    def _emit(self, t: float) -> None:
        device_time = self._device_time_s
        self._device_time_s += self._host_period_s
        with self._lock:
            streaming = self._streaming
            extra, self._extra = self._extra, []  # lines sent on demand go out even when stopped
        data = b"".join(extra)
        if streaming:
            values = self.config.scale.from_newtons(*self._grip(t))
            line = self._separator().join(self._columns(device_time, values))
            data += line.encode("ascii") + self._line_end
        else:
            self.lines_skipped += 1
        if not data:
            return
        if not self._queue(data):
            self.overflows += 1
            return
        self.lines_written += streaming
