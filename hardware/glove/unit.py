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

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Protocol, Unpack

from steerlab.hardware.glove.calibration import GloveCalibration
from steerlab.hardware.glove.decoder import DecodeEvent, DecoderStats, GloveDecoder, GloveFrame
from steerlab.hardware.grip.reader import GripSourceError, SerialGripReader, SerialOptions
from steerlab.hardware.interfaces import GripReading


class SerialTransport(Protocol):
    """What the unit needs from a pyserial object (``cancel_read`` is used when present)."""

    timeout: float | None

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1) -> bytes: ...

    def close(self) -> None: ...


class GloveUnitError(GripSourceError):
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


class SerialGloveUnit(SerialGripReader[GloveFrame]):
    """Implements hardware.interfaces.GripSource over a serial transport.

    Sinks (``on_frame``, ``on_event``) run in the reader thread and must be quick; ``on_frame``
    sees every accepted frame, so a recorder that must not lose a sample subscribes there
    rather than polling ``latest()``. If a sink raises, the reader stops with that error.
    """

    thread_name = "glove-reader"
    sample_word = "frame"
    error_class = GloveUnitError
    reader_name = "glove reader"

    def __init__(
        self,
        port: SerialTransport,
        calibration: GloveCalibration,
        *,
        on_frame: FrameSink | None = None,
        on_event: Callable[[DecodeEvent], None] | None = None,
        **options: Unpack[SerialOptions],
    ) -> None:
        super().__init__(port, **options)
        self._calibration = calibration
        self._on_frame = on_frame
        self._decoder = GloveDecoder(clock=self._clock, on_event=on_event)

    @property
    def calibration(self) -> GloveCalibration:
        return self._calibration

    def describe(self) -> str:
        name = getattr(self._port, "port", None) or getattr(self._port, "name", None)
        return f"the glove unit on {name}" if isinstance(name, str) else "the glove unit"

    # -- data -----------------------------------------------------------------------------------

    def latest_frame(self) -> GloveFrame | None:
        """Newest raw frame (device time, raw counts, pressure maps if sent)."""
        newest = self._newest
        return None if newest is None else newest[0]

    def stats(self) -> GloveUnitStats:
        with self._lock:
            decoder = self._decoder.stats
        common = self._common_stats()
        return GloveUnitStats(**asdict(decoder), last_frame_age_s=self.age_s(), **common)

    def _failure(self) -> str:
        return f"glove unit failed: {self._error}"  # the benchmarks and the docs quote it

    def _stop_detail(self) -> str:
        crc = self.stats().crc_errors
        return f" ({crc} frames with a bad CRC so far)" if crc else ""

    # -- reader thread --------------------------------------------------------------------------

    def _handle(self, data: bytes) -> None:
        with self._lock:
            frames = self._decoder.feed(data)
            readings = [
                GripReading(
                    *self._calibration.to_newtons(frame.left_raw, frame.right_raw),
                    frame.host_time_s,
                    frame.sequence_ext,
                )
                for frame in frames
            ]
            self._publish(zip(frames, readings, strict=True))
        if self._on_frame is not None:
            for frame, reading in zip(frames, readings, strict=True):
                self._on_frame(frame, reading)
