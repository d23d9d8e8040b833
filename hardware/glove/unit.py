"""SerialGloveUnit: the glove acquisition unit behind a serial transport.

The unit takes a ready serial object (``serial.Serial(path)``, ``serial_for_url("loop://")``, or
anything with the same read/in_waiting/timeout/close), so the lab, the simulated rig and the tests
all run this code. A reader thread feeds the decoder; the control loop only calls ``latest()``.

The reader thread never dies silently: whatever it raises (the serial port vanished, a sink
raised) is stored in ``error``, passed to ``on_error``, and re-raised by ``check()`` so the engine
can abort the trial with the reason. A unit whose stream merely went quiet has no error; the
engine watches ``stream_alive()`` / ``age_s()`` for that.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Protocol

from steerlab.hardware.glove.calibration import GloveCalibration
from steerlab.hardware.glove.decoder import DecodeEvent, DecoderStats, GloveDecoder, GloveFrame
from steerlab.hardware.interfaces import GripReading

log = logging.getLogger(__name__)


class SerialTransport(Protocol):
    """What the unit needs from a pyserial object (``cancel_read`` is used when present)."""

    timeout: float | None

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1) -> bytes: ...

    def close(self) -> None: ...


class GloveUnitError(RuntimeError):
    """The glove reader thread failed; ``__cause__`` is the original exception."""


@dataclass
class GloveUnitStats(DecoderStats):
    rate_hz: float = 0.0  # received frames per host second, over the last rate window
    last_frame_age_s: float | None = None  # None before the first frame
    running: bool = False
    error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


FrameSink = Callable[[GloveFrame, GripReading], None]


class SerialGloveUnit:
    """Implements hardware.interfaces.GloveUnit over a serial transport.

    Sinks (``on_frame``, ``on_event``) run in the reader thread and must be quick; ``on_frame``
    sees every accepted frame, so a recorder that must not lose a sample subscribes there
    rather than polling ``latest()``. If a sink raises, the reader stops with that error.
    """

    def __init__(
        self,
        port: SerialTransport,
        calibration: GloveCalibration,
        *,
        clock: Callable[[], float] = time.monotonic,
        on_frame: FrameSink | None = None,
        on_event: Callable[[DecodeEvent], None] | None = None,
        on_error: Callable[[BaseException], None] | None = None,
        read_timeout_s: float = 0.05,
        rate_window_s: float = 1.0,
        close_port: bool = True,
    ) -> None:
        if read_timeout_s <= 0:
            raise ValueError(f"read_timeout_s must be > 0, got {read_timeout_s}")
        self._port = port
        self._calibration = calibration
        self._clock = clock
        self._on_frame = on_frame
        self._on_error = on_error
        self._close_port = close_port
        self._rate_window_s = rate_window_s
        # A blocking read with no timeout would keep close() waiting for the next byte forever.
        if port.timeout is None or port.timeout > read_timeout_s:
            port.timeout = read_timeout_s
        self._decoder = GloveDecoder(clock=clock, on_event=on_event)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # One tuple, replaced whole, so readers never see a frame and a reading that disagree.
        self._newest: tuple[GloveFrame, GripReading] | None = None
        self._arrivals: deque[float] = deque(maxlen=4096)
        self._error: BaseException | None = None
        self._closed = False

    @property
    def calibration(self) -> GloveCalibration:
        return self._calibration

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> SerialGloveUnit:
        if self._closed:
            raise RuntimeError("SerialGloveUnit: cannot start after close()")
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="glove-reader", daemon=True)
            self._thread.start()
        return self

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the reader, then close the port (unless close_port=False). Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        cancel = getattr(self._port, "cancel_read", None)
        if cancel is not None:
            try:
                cancel()
            except Exception:  # the port may already be gone; the timeout covers us
                log.debug("cancel_read failed", exc_info=True)
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                # Closing the fd under a blocked read could let the reader read a reused
                # descriptor: leave the port to the (daemon) thread.
                log.warning("glove reader did not stop within %.1f s", timeout_s)
                return
        if self._close_port:
            self._port.close()

    def __enter__(self) -> SerialGloveUnit:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # -- data -----------------------------------------------------------------------------------

    def latest(self) -> GripReading | None:
        """Newest calibrated reading, or None before the first frame. Stays at the last value
        when the stream stops or the reader fails: check ``stream_alive()`` / ``error``."""
        newest = self._newest
        return None if newest is None else newest[1]

    def latest_frame(self) -> GloveFrame | None:
        """Newest raw frame (device time, raw counts, pressure maps if sent)."""
        newest = self._newest
        return None if newest is None else newest[0]

    def age_s(self) -> float | None:
        """Host seconds since the newest frame arrived; None before the first frame."""
        newest = self._newest
        return None if newest is None else self._clock() - newest[0].host_time_s

    def stream_alive(self, timeout_s: float = 0.1) -> bool:
        """True while the reader runs without error and a frame arrived within ``timeout_s``
        (10 nominal frame periods by default)."""
        age = self.age_s()
        return self.running and self._error is None and age is not None and age <= timeout_s

    @property
    def error(self) -> BaseException | None:
        """What stopped the reader thread, or None."""
        return self._error

    def check(self) -> None:
        """Raise GloveUnitError (from the original) if the reader thread failed."""
        if self._error is not None:
            raise GloveUnitError(f"glove reader failed: {self._error!r}") from self._error

    def stats(self) -> GloveUnitStats:
        now = self._clock()
        with self._lock:
            decoder = self._decoder.stats
            recent = [t for t in self._arrivals if t >= now - self._rate_window_s]
        span = recent[-1] - recent[0] if len(recent) >= 2 else 0.0
        error = self._error
        return GloveUnitStats(
            **asdict(decoder),
            rate_hz=(len(recent) - 1) / span if span > 0 else 0.0,
            last_frame_age_s=self.age_s(),
            running=self.running,
            error=None if error is None else repr(error),
        )

    # -- reader thread --------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                # Block (up to the port timeout) for one byte, then take whatever else is
                # already there, so a burst is decoded in one go with one host timestamp.
                data = self._port.read(1)
                if not data:
                    continue
                waiting = self._port.in_waiting
                if waiting:
                    data += self._port.read(waiting)
                self._handle(data)
        except BaseException as exc:  # the point of this thread: report everything
            self._fail(exc)

    def _handle(self, data: bytes) -> None:
        with self._lock:
            frames = self._decoder.feed(data)
            readings = []
            for frame in frames:
                left_n, right_n = self._calibration.to_newtons(frame.left_raw, frame.right_raw)
                reading = GripReading(left_n, right_n, frame.host_time_s, frame.sequence_ext)
                readings.append(reading)
                self._arrivals.append(frame.host_time_s)
            if frames:
                self._newest = (frames[-1], readings[-1])
        if self._on_frame is not None:
            for frame, reading in zip(frames, readings, strict=True):
                self._on_frame(frame, reading)

    def _fail(self, exc: BaseException) -> None:
        self._error = exc
        if self._stop.is_set():
            # Failing while being closed ends nothing the engine still runs: no callback.
            log.debug("glove reader stopped with %r during close", exc)
            return
        log.error("glove reader failed: %r", exc)
        if self._on_error is not None:
            try:
                self._on_error(exc)
            except Exception:
                log.exception("glove on_error callback raised")
