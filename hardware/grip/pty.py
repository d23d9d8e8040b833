"""A simulated serial device: the writer thread of :mod:`.paced`, writing into a pseudo-terminal.

The simulated grip devices on a serial port (Steerlab's glove unit,
:class:`hardware.glove.simulated.SimulatedGloveUnit`; a text-line device,
:class:`hardware.grip.text_simulated.SimulatedTextDevice`) own a pty pair; the host opens its
slave's path with ``serial.Serial`` exactly as it opens the lab's /dev/ttyUSB0. Needs POSIX ptys.
"""

from __future__ import annotations

import errno
import fcntl
import os
import time
import tty
from collections.abc import Callable

from steerlab.hardware.grip.paced import PacedWriter


def raw_pty() -> tuple[int, int, str]:
    """A pty pair in raw mode, its master non-blocking: (master fd, slave fd, slave path)."""
    master, slave = os.openpty()
    try:
        # Raw from the start: bytes written before the reader configures the port must not
        # be echoed, turned into signals, or taken as XON/XOFF by the line discipline.
        tty.setraw(slave)
        flags = fcntl.fcntl(master, fcntl.F_GETFL)
        fcntl.fcntl(master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        return master, slave, os.ttyname(slave)
    except BaseException:
        os.close(master)
        os.close(slave)
        raise


class PtyStreamer(PacedWriter):
    """A simulated serial device: a :class:`~hardware.grip.paced.PacedWriter` whose samples
    go into a pty (open ``port`` with serial.Serial). ``_emit(t)`` queues each sample's bytes
    with :meth:`_queue`.

    Like a UART it never waits for a listener: past ``tx_limit`` bytes not taken by the pty,
    a sample is lost (``_queue`` returns False)."""

    thread_name = "pty-sim"
    sim_name = "simulated serial device"

    def __init__(
        self,
        *,
        host_period_s: float,
        tx_limit: int,
        clock: Callable[[], float] = time.monotonic,
        on_error: Callable[[BaseException], None] | None = None,
    ) -> None:
        super().__init__(host_period_s=host_period_s, clock=clock, on_error=on_error)
        self._tx_limit = tx_limit
        self._tx = bytearray()
        self._master, self._slave, self._port = raw_pty()
        self._master_open = True

    @property
    def port(self) -> str:
        """Device path of the pty slave, e.g. /dev/pts/3."""
        return self._port

    @property
    def address(self) -> str:
        """Where the host reaches the device: the pty's path."""
        return self._port

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the writer and close both pty ends. A reader still attached then fails with
        an I/O error, as with an unplugged USB adapter: close the reader first. Idempotent."""
        super().close(timeout_s)

    def hang_up(self, timeout_s: float = 1.0) -> None:
        """Close the pty master mid-stream: the reader's next read fails (EIO), as when the
        device is unplugged. Returns once the master is closed."""
        super().hang_up(timeout_s)

    def _hang_up_now(self) -> None:
        self._close_master()

    def _release(self) -> None:
        self._close_master()
        os.close(self._slave)

    def _queue(self, data: bytes) -> bool:
        """Queue ``data`` for the pty; False (nothing queued) when the pty is too far behind."""
        if self._tx and len(self._tx) + len(data) > self._tx_limit:
            return False
        self._tx += data
        return True

    def _flush(self) -> None:
        if not self._tx:
            return
        try:
            written = os.write(self._master, self._tx)
        except BlockingIOError:
            return  # pty buffer full: keep the bytes, later frames overflow
        except OSError as exc:
            # EIO: no slave side any more. Nothing the device could do either; keep streaming
            # into the void rather than fail, as a UART would.
            if exc.errno != errno.EIO:
                raise
            self._tx.clear()
            return
        del self._tx[:written]

    def _close_master(self) -> None:
        if self._master_open:
            self._master_open = False
            os.close(self._master)
