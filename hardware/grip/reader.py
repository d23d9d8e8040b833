"""What every grip source has: a reader thread, the newest reading, its age, the reader's error.

A grip source (:class:`hardware.interfaces.GripSource`: Steerlab's glove unit, an LSL stream, a
text-line device) reads its device in a thread of its own; the control loop only calls
``latest()``, and the engine asks :meth:`GripReader.problem` whether the trial must stop.
:class:`GripReader` keeps that bookkeeping once for all of them; a source subclasses it with

- ``_read_once()``: block (briefly: at most a few tens of ms, so ``close()`` is quick) for the
  device's next data and :meth:`_publish` the readings it completes;
- ``_interrupt()`` (optional): unblock a read in progress when closing;
- ``_release()``: close the device, once the reader thread has stopped;
- ``describe()``: the device in words, for messages ("LSL stream 'GripGlove'");
- ``stats()``: its counters, a dataclass with ``as_dict()`` and at least ``rate_hz``;
- optionally ``_stop_detail()``: the end of a stopped stream's abort message (by default
  " from <the device>"; a source adds what it saw go wrong: malformed lines, bad CRCs).

:class:`SerialGripReader` is that for a source on a serial port (Steerlab's glove unit, a
text-line device): it reads each burst of bytes whole and hands it to ``_handle(data)``.

The reader thread never dies silently: whatever it raises is stored in ``error``, passed to
``on_error`` and re-raised by ``check()``. A stream that merely went quiet has no error; the
engine watches ``age_s()`` for that (:meth:`problem`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any, Generic, TypedDict, TypeVar

from steerlab.hardware.interfaces import GripReading

log = logging.getLogger(__name__)

#: What a source keeps beside each reading: the raw frame, line or sample it came from.
Raw = TypeVar("Raw")


class GripSourceError(RuntimeError):
    """A grip source could not be opened, or its reader failed; the message names the device
    (``check()`` raises it with the original exception as ``__cause__``)."""


class ThreadOwner:
    """An object that runs one daemon thread (``_run``) from ``start()`` to ``close()``, then
    frees its device (``_release()``): a grip source's reader, a simulated device's writer."""

    #: the thread's name
    thread_name = "grip-thread"

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False

    def _run(self) -> None:
        raise NotImplementedError

    def _label(self) -> str:
        """Who owns the thread, in log messages."""
        return type(self).__name__

    def _interrupt(self) -> None:
        """Unblock the thread's wait in progress (close() calls it before joining)."""

    def _release(self) -> None:
        """Free the device; called once, after the thread stopped."""

    def start(self):
        if self._closed:
            raise RuntimeError(f"{type(self).__name__}: cannot start after close()")
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
            self._thread.start()
        return self

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the thread, then free the device. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        try:
            self._interrupt()
        except Exception:  # the device may already be gone; the read timeout covers us
            log.debug("%s: interrupting the thread failed", self._label(), exc_info=True)
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                # Freeing the device under a blocked read or write could let the thread use a
                # reused descriptor: leave the device to the (daemon) thread.
                log.warning("%s: thread did not stop within %.1f s", self._label(), timeout_s)
                return
        self._release()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()


class GripReader(ThreadOwner, Generic[Raw]):
    """The threaded bookkeeping shared by every grip source (see the module docstring)."""

    #: the reader thread's name
    thread_name = "grip-reader"
    #: what one reading is called in messages ("frame", "sample", "line")
    sample_word = "sample"
    #: the class ``check()`` raises, and what its message calls the reader (None: describe())
    error_class: type[GripSourceError] = GripSourceError
    reader_name: str | None = None

    def __init__(
        self,
        *,
        clock: Callable[[], float] = time.monotonic,
        on_error: Callable[[BaseException], None] | None = None,
        rate_window_s: float = 1.0,
    ) -> None:
        super().__init__()
        self._clock = clock
        self._on_error = on_error
        self._rate_window_s = rate_window_s
        self._lock = threading.Lock()
        # One tuple, replaced whole, so readers never see a raw item and a reading that disagree.
        self._newest: tuple[Raw, GripReading] | None = None
        self._arrivals: deque[float] = deque(maxlen=4096)
        self._error: BaseException | None = None

    # -- what a source defines ------------------------------------------------------------------

    def describe(self) -> str:
        """The device in words, for messages."""
        return type(self).__name__

    def _read_once(self) -> None:
        raise NotImplementedError

    def _label(self) -> str:
        return self.describe()

    def _stop_detail(self) -> str:
        """The end of the abort message of a stopped stream: which device, and what went wrong
        on the line if anything did."""
        return f" from {self.describe()}"

    def _failure(self) -> str:
        """Why the trial stops when the reader failed, naming the device."""
        return f"{self.describe()} failed: {self._error}"

    # -- data -----------------------------------------------------------------------------------

    def latest(self) -> GripReading | None:
        """Newest calibrated reading, or None before the first. Stays at the last value when
        the stream stops or the reader fails: check ``stream_alive()`` / ``error``."""
        newest = self._newest
        return None if newest is None else newest[1]

    def age_s(self) -> float | None:
        """Host seconds since the newest reading arrived; None before the first."""
        newest = self._newest
        return None if newest is None else self._clock() - newest[1].host_time_s

    def stream_alive(self, timeout_s: float = 0.1) -> bool:
        """True while the reader runs without error and a reading arrived within
        ``timeout_s``."""
        age = self.age_s()
        return self.running and self._error is None and age is not None and age <= timeout_s

    @property
    def error(self) -> BaseException | None:
        """What stopped the reader thread, or None."""
        return self._error

    def check(self) -> None:
        """Raise :attr:`error_class` (from the original) if the reader thread failed."""
        if self._error is not None:
            who = self.reader_name or self.describe()
            raise self.error_class(f"{who} failed: {self._error!r}") from self._error

    def problem(self, timeout_s: float) -> str | None:
        """A reason to stop the trial now: the reader failed, or no reading for longer than
        ``timeout_s`` (the rig file's ``[safety] glove_timeout_s``); None while all is well."""
        if self._error is not None:
            return self._failure()
        age = self.age_s()
        if age is None or age > timeout_s:
            since = "ever" if age is None else f"{age:.2f} s"
            return (
                f"glove stream stopped: no valid {self.sample_word} for {since}"
                f"{self._stop_detail()}"
            )
        return None

    def _rate_hz(self) -> float:
        """Readings per host second over the last rate window (call with the lock held)."""
        now = self._clock()
        recent = [t for t in self._arrivals if t >= now - self._rate_window_s]
        span = recent[-1] - recent[0] if len(recent) >= 2 else 0.0
        return (len(recent) - 1) / span if span > 0 else 0.0

    def _common_stats(self) -> dict[str, Any]:
        """The fields every source's stats share."""
        with self._lock:
            rate = self._rate_hz()
        error = self._error
        return {
            "rate_hz": rate,
            "running": self.running,
            "error": None if error is None else repr(error),
        }

    # -- reader thread --------------------------------------------------------------------------

    def _publish(self, items: Iterable[tuple[Raw, GripReading]]) -> None:
        """Make these (raw, reading) pairs, oldest first, the newest (call with the lock
        held)."""
        last = None
        for last in items:
            self._arrivals.append(last[1].host_time_s)
        if last is not None:
            self._newest = last

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                self._read_once()
        except BaseException as exc:  # the point of this thread: report everything
            self._fail(exc)

    def _fail(self, exc: BaseException) -> None:
        self._error = exc
        if self._stop.is_set():
            # Failing while being closed ends nothing the engine still runs: no callback.
            log.debug("%s: reader stopped with %r during close", self.describe(), exc)
            return
        log.error("%s: reader failed: %r", self.describe(), exc)
        if self._on_error is not None:
            try:
                self._on_error(exc)
            except Exception:
                log.exception("%s: on_error callback raised", self.describe())


class SerialOptions(TypedDict, total=False):
    """What a source on a serial port passes on to :class:`SerialGripReader`."""

    clock: Callable[[], float]
    on_error: Callable[[BaseException], None] | None
    read_timeout_s: float
    rate_window_s: float
    close_port: bool


class SerialGripReader(GripReader[Raw]):
    """A grip source on a serial transport (``serial.Serial``, a pty, ``loop://``, or anything
    with the same read/in_waiting/timeout/close; ``cancel_read`` is used when present). A
    subclass defines ``_handle(data)``: the bytes of one read, a burst taken whole."""

    def __init__(
        self,
        port: Any,
        *,
        clock: Callable[[], float] = time.monotonic,
        on_error: Callable[[BaseException], None] | None = None,
        read_timeout_s: float = 0.05,
        rate_window_s: float = 1.0,
        close_port: bool = True,
    ) -> None:
        if read_timeout_s <= 0:
            raise ValueError(f"read_timeout_s must be > 0, got {read_timeout_s}")
        super().__init__(clock=clock, on_error=on_error, rate_window_s=rate_window_s)
        self._port = port
        self._close_port = close_port
        # A blocking read with no timeout would keep close() waiting for the next byte forever.
        if port.timeout is None or port.timeout > read_timeout_s:
            port.timeout = read_timeout_s

    def _handle(self, data: bytes) -> None:
        raise NotImplementedError

    def _read_once(self) -> None:
        # Block (up to the port timeout) for one byte, then take whatever else is already
        # there, so a burst is handled in one go with one host timestamp.
        data = self._port.read(1)
        if not data:
            return
        waiting = self._port.in_waiting
        if waiting:
            data += self._port.read(waiting)
        self._handle(data)

    def _interrupt(self) -> None:
        cancel = getattr(self._port, "cancel_read", None)
        if cancel is not None:
            cancel()

    def _release(self) -> None:
        if self._close_port:
            self._port.close()
