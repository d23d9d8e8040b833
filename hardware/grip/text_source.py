"""Grip force from a device that prints one text line per sample (``[glove] kind = "serial-text"``).

An FSR glove on a microcontroller typically prints ``millis(),left,right`` on its USB serial
port, 100 times a second. The rig file says which column is which (counted from 0), the
separator, the baud rate, whether the values are newtons or raw values (and then their
calibration), and which column, if any, is the device's own time::

    [glove]
    kind = "serial-text"
    port = "/dev/ttyACM0"
    baudrate = 115200
    separator = ","
    unit = "raw"
    time_unit = "ms"
    [glove.columns]
    time = 0
    left = 1
    right = 2
    [glove.calibration.left]
    gain = 0.05          # N = gain · (value − offset)
    offset = 12
    [glove.calibration.right]
    gain = 0.05
    offset = 9

How lines are read (:class:`TextGripSource`):

- a line ends with ``\\n``; a ``\\r`` before it and spaces around each column are ignored;
  a separator of ``" "`` or ``"\\t"`` splits on any run of spaces and tabs;
- the bytes before the first line end are dropped: the port may have been opened mid-line;
- an empty line is skipped (counted in ``empty_lines``);
- a line with a column missing, a column that is not a finite number, bytes that are not
  text, or no line end within 1024 bytes is a *bad line*: skipped, counted (``bad_lines``),
  logged with the device and the line's content, and kept as ``last_bad_line`` /
  ``last_bad_reason``. The reader goes on: one bad line costs one sample, never the stream.
  If the stream then stops (only bad lines, or none), the trial's abort message names the
  device and the last bad line;
- the device's time column, when there is one, is kept with each sample
  (:meth:`TextGripSource.latest_device_time_s`); a step back (the device restarted) is counted
  in ``time_steps_back``.

:class:`SimulatedTextDevice` writes such lines into a pty for a simulated rig.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import asdict, dataclass, replace
from typing import Any, ClassVar, NamedTuple, Unpack

from steerlab.hardware.grip.common import (
    Fields,
    ForceScale,
    force_scale,
    open_serial,
)
from steerlab.hardware.grip.reader import SerialGripReader, SerialOptions
from steerlab.hardware.grips import SIMULATED_PORT, GripFunction
from steerlab.hardware.interfaces import GripReading

log = logging.getLogger(__name__)

FIELDS = (
    "kind",
    "port",
    "baudrate",
    "separator",
    "unit",
    "time_unit",
    "columns",
    "calibration",
)
#: ``time_unit``: seconds per unit of the device's time column
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
COLUMN_ROLES = ("left", "right", "time")
#: A line longer than this without a line end is a bad line (a device sending binary, say).
MAX_LINE_BYTES = 1024
_WHITESPACE = (" ", "\t")


@dataclass(frozen=True)
class TextGripConfig:
    port: str
    baudrate: int
    separator: str
    left: int  # column of the left hand's value, from 0
    right: int
    time: int | None  # column of the device's time, or None
    time_unit: str | None  # a key of TIME_UNITS when there is a time column
    scale: ForceScale
    source: str = ""
    kind: ClassVar[str] = "serial-text"

    @property
    def simulated(self) -> bool:
        return self.port == SIMULATED_PORT

    @property
    def columns(self) -> dict[str, int]:
        out = {"left": self.left, "right": self.right}
        if self.time is not None:
            out["time"] = self.time
        return out

    def describe(self) -> dict[str, Any]:
        return {
            "glove_kind": self.kind,
            "glove_port": self.port,
            "glove_columns": self.columns,
            "glove_separator": self.separator,
            "glove_time_unit": self.time_unit,
            **self.scale.describe(),
        }

    def split(self, line: str) -> list[str]:
        if self.separator in _WHITESPACE:
            return line.split()
        return [column.strip() for column in line.split(self.separator)]

    def parse(self, line: str) -> tuple[float, float, float | None]:
        """(left, right, device time in s or None) of one line, as the device sent them;
        :class:`BadLine` saying what is wrong."""
        columns = self.split(line)
        values: dict[str, float] = {}
        for role, index in self.columns.items():
            if index >= len(columns):
                raise BadLine(
                    f"column {index} ({role}) is missing: the line has {len(columns)} "
                    f"column{'s' if len(columns) != 1 else ''}"
                )
            text = columns[index]
            try:
                value = float(text)
            except ValueError:
                raise BadLine(f"column {index} ({role}) is not a number: {text!r}") from None
            if not math.isfinite(value):
                raise BadLine(f"column {index} ({role}) is not a finite number: {text!r}")
            values[role] = value
        device_time = values.get("time")
        if device_time is not None and self.time_unit is not None:
            device_time *= TIME_UNITS[self.time_unit]
        return values["left"], values["right"], device_time


class BadLine(ValueError):
    """A line the device sent that is not a sample; the message says what is wrong."""


class TextSample(NamedTuple):
    line: str
    device_time_s: float | None


@dataclass
class TextGripStats:
    lines: int = 0  # good lines (samples)
    bad_lines: int = 0  # skipped: a column missing or not a number, not text, too long
    empty_lines: int = 0
    bytes_in: int = 0
    bytes_discarded: int = 0  # before the first line end, and in bad lines
    time_steps_back: int = 0  # the device's time column went back (a restart)
    last_bad_line: str | None = None
    last_bad_reason: str | None = None
    rate_hz: float = 0.0  # good lines per host second, over the last rate window
    last_line_age_s: float | None = None
    running: bool = False
    error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class TextGripSource(SerialGripReader[TextSample]):
    """A text-line grip device behind a serial transport (``serial.Serial``, a pty, ``loop://``),
    read by a thread of its own. See the module docstring for what is a good line."""

    thread_name = "grip-text-reader"
    sample_word = "line"

    def __init__(self, port: Any, config: TextGripConfig, **options: Unpack[SerialOptions]) -> None:
        super().__init__(port, **options)
        self.config = config
        self._buffer = bytearray()
        self._first_line = True  # not yet seen a line end: what comes before it may be cut
        self._stats = TextGripStats()
        self._recent_bad: deque[tuple[str, str]] = deque(maxlen=10)
        self._last_device_time: float | None = None

    def describe(self) -> str:
        name = getattr(self._port, "port", None) or self.config.port
        return f"serial-text device {name}"

    def latest_device_time_s(self) -> float | None:
        """The device's time of the newest sample (its time column, in s), or None."""
        newest = self._newest
        return None if newest is None else newest[0].device_time_s

    def recent_bad_lines(self) -> list[tuple[str, str]]:
        """The last few bad lines, (line, what is wrong), oldest first."""
        with self._lock:
            return list(self._recent_bad)

    def stats(self) -> TextGripStats:
        with self._lock:
            counts = replace(self._stats)
        return replace(counts, last_line_age_s=self.age_s(), **self._common_stats())

    def _stop_detail(self) -> str:
        st = self.stats()
        if not st.bad_lines:
            return super()._stop_detail()
        return (
            f" from {self.describe()} ({st.bad_lines} bad line{'s' if st.bad_lines != 1 else ''}"
            f" so far; the last: {st.last_bad_line!r}: {st.last_bad_reason})"
        )

    # -- reader thread --------------------------------------------------------------------------

    def _handle(self, data: bytes) -> None:
        """Split ``data`` into lines; publish the good ones, all at this host time."""
        now = self._clock()
        bad: list[tuple[int, str, str]] = []  # (its number, the line, what is wrong)
        with self._lock:
            st = self._stats
            st.bytes_in += len(data)
            self._buffer += data
            *lines, rest = self._buffer.split(b"\n")
            self._buffer = bytearray(rest)
            if lines and self._first_line:
                self._first_line = False
                st.bytes_discarded += len(lines.pop(0)) + 1
            items = []
            for raw in lines:
                if not raw.strip():
                    st.empty_lines += 1
                    continue
                try:
                    items.append(self._sample(raw, now))
                except BadLine as e:
                    bad.append(self._bad(raw, str(e)))
            if len(self._buffer) > MAX_LINE_BYTES:
                # No line end at all: not a line cut by the port's opening, a wrong device.
                self._first_line = False
                too_long = f"no line end within {MAX_LINE_BYTES} bytes"
                bad.append(self._bad(bytes(self._buffer), too_long))
                self._buffer.clear()
            self._publish(items)
        for n, line, reason in bad:
            if n <= 3 or n % 1000 == 0:  # the first few, then now and then: a log, not a flood
                log.warning("%s: bad line %d %r: %s", self.describe(), n, line, reason)

    def _sample(self, raw: bytes | bytearray, now: float) -> tuple[TextSample, GripReading]:
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise BadLine("not a text line (bytes outside ASCII)") from None
        left, right, device_time = self.config.parse(line)
        st = self._stats
        if device_time is not None:
            if self._last_device_time is not None and device_time < self._last_device_time:
                st.time_steps_back += 1
            self._last_device_time = device_time
        st.lines += 1
        left_n, right_n = self.config.scale.to_newtons(left, right)
        return TextSample(line, device_time), GripReading(left_n, right_n, now, st.lines)

    def _bad(self, raw: bytes | bytearray, reason: str) -> tuple[int, str, str]:
        line = raw.decode("ascii", errors="backslashreplace").strip()
        if len(line) > 80:
            line = line[:77] + "..."
        st = self._stats
        st.bad_lines += 1
        st.bytes_discarded += len(raw) + 1
        st.last_bad_line, st.last_bad_reason = line, reason
        self._recent_bad.append((line, reason))
        return st.bad_lines, line, reason


# -- the rig file's [glove] table -----------------------------------------------------------------

#: Characters of a number: a separator made of them would cut numbers apart.
_NUMBER_CHARS = set("0123456789.+-eE")


def text_config(table: dict[str, Any], source: str) -> TextGripConfig:
    """A ``[glove]`` table of ``kind = "serial-text"``, checked."""
    f = Fields(table, source, "glove", FIELDS)
    port = table.get("port")
    if not isinstance(port, str) or not port:
        raise f.fail("port", f'required: a serial device path or "{SIMULATED_PORT}"')
    baud = f.whole("baudrate", lo=1, default=115200)
    separator = f.text("separator", 'a non-empty string, e.g. "," or "\\t"', default=",")
    assert separator is not None
    if "\n" in separator or "\r" in separator:
        raise f.fail("separator", f"must not contain a line end, got {separator!r}")
    if set(separator) & _NUMBER_CHARS:
        raise f.fail(
            "separator", f"must not contain digits, '.', '+', '-' or 'e', got {separator!r}"
        )
    scale = force_scale(f)
    columns = f.subtable("columns")
    assert columns is not None
    c = Fields(columns, source, "glove.columns", COLUMN_ROLES)
    roles: dict[str, int] = {}
    for role in COLUMN_ROLES:
        if role == "time" and role not in columns:
            continue
        index = c.whole(role, lo=0)
        other = next((r for r, i in roles.items() if i == index), None)
        if other is not None:
            raise c.fail(role, f"column {index} is already {other}")
        roles[role] = index
    time_column = roles.get("time")
    time_unit = None
    if time_column is not None:
        time_unit = f.choice("time_unit", tuple(TIME_UNITS), "the unit of the device's time column")
    elif "time_unit" in table:
        raise f.fail("time_unit", "given without a time column ([glove.columns] time)")
    return TextGripConfig(
        port, baud, separator, roles["left"], roles["right"], time_column, time_unit, scale, source
    )


class _TextKind:
    name = "serial-text"

    def config(self, table: dict[str, Any], source: str) -> TextGripConfig:
        return text_config(table, source)

    def open(self, config: TextGripConfig) -> TextGripSource:
        port = open_serial(config.port, config.baudrate, "serial-text device")
        return TextGripSource(port, config).start()

    def simulate(self, config: TextGripConfig, grip: GripFunction):
        from steerlab.hardware.grip.text_simulated import SimulatedTextDevice

        return SimulatedTextDevice(grip, config)

    def at(self, config: TextGripConfig, address: str) -> TextGripConfig:
        return replace(config, port=address)


KIND = _TextKind()
