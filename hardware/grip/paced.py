"""The writer thread every simulated grip device runs: one sample every period, on schedule.

:class:`PacedWriter` samples at a fixed rate in host time, like a device's own clock. Behind
schedule by more than a second (the process was suspended) the device "keeps sampling", but
those samples are lost (``_skip(n)``) rather than sent as one huge burst. A subclass defines

- ``_emit(t)``: the sample at t (s since start), with whatever faults are due;
- ``_skip(n)``: n samples lost while the process was suspended;
- ``_flush()`` (optional): hand what ``_emit`` queued to the line;
- ``_hang_up_now()``: the device goes away (its pty closes, its LSL outlet is destroyed);
- ``_release()``: free the device once the writer has stopped.

Nothing here needs POSIX; the pty devices (:class:`hardware.grip.pty.PtyStreamer`) do.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from steerlab.hardware.grip.reader import ThreadOwner

log = logging.getLogger(__name__)

#: Behind schedule by more than this, samples are skipped rather than sent in a burst.
MAX_LAG_S = 1.0


class PacedWriter(ThreadOwner):
    """A simulated device's writer thread (see the module docstring)."""

    #: the writer thread's name, and the device in log messages
    thread_name = "grip-sim"
    sim_name = "simulated grip device"

    def __init__(
        self,
        *,
        host_period_s: float,
        clock: Callable[[], float] = time.monotonic,
        on_error: Callable[[BaseException], None] | None = None,
    ) -> None:
        super().__init__()
        self._host_period_s = host_period_s
        self._clock = clock
        self._on_error = on_error
        self._lock = threading.Lock()
        self._streaming = True
        self._hangup = threading.Event()
        self._hung_up = threading.Event()
        self._error: BaseException | None = None

    @property
    def error(self) -> BaseException | None:
        """What stopped the writer thread, or None."""
        return self._error

    # -- what a device defines --------------------------------------------------------------------

    def _emit(self, t: float) -> None:
        raise NotImplementedError

    def _skip(self, n: int) -> None:
        raise NotImplementedError

    def _flush(self) -> None:
        pass

    def _hang_up_now(self) -> None:
        raise NotImplementedError

    def _label(self) -> str:
        return self.sim_name

    # -- faults ---------------------------------------------------------------------------------

    def stop_streaming(self) -> None:
        """The device stops sending; it keeps counting, so resuming shows a gap."""
        with self._lock:
            self._streaming = False

    def resume_streaming(self) -> None:
        with self._lock:
            self._streaming = True

    def hang_up(self, timeout_s: float = 1.0) -> None:
        """The device goes away mid-stream. Returns once it is gone."""
        if self._thread is None or not self._thread.is_alive():
            self._hang_up_now()
            return
        self._hangup.set()
        if not self._hung_up.wait(timeout_s):
            raise TimeoutError(f"{self.sim_name} did not hang up")

    # -- writer thread --------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            t0 = self._clock()
            k = 0  # samples scheduled so far
            while not self._stop.is_set():
                if self._hangup.is_set():
                    self._hang_up_now()
                    self._hung_up.set()
                    return
                now = self._clock()
                due = t0 + k * self._host_period_s
                if now < due:
                    self._stop.wait(min(due - now, 0.02))
                    continue
                lag = int((now - due - MAX_LAG_S) / self._host_period_s)
                if lag > 0:
                    self._skip(lag)
                    k += lag
                    continue
                self._emit(due - t0)
                k += 1
                self._flush()
        except BaseException as exc:  # report everything: a dead simulator must not look quiet
            self._error = exc
            log.error("%s failed: %r", self.sim_name, exc)
            if self._on_error is not None:
                try:
                    self._on_error(exc)
                except Exception:
                    log.exception("%s: on_error callback raised", self.sim_name)
