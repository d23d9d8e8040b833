"""A simulated glove acquisition unit that speaks the real protocol into a pseudo-terminal.

The simulator owns a pty pair; ``port`` is the slave's device path, which the rig opens with
``serial.Serial(port)`` exactly like the real unit's /dev/ttyUSB*. The real SerialGloveUnit and
decoder therefore run in every simulated session (simulate at the transport, not beside it).

A writer thread samples ``source(t) -> (left_N, right_N)`` at ``rate_hz``, converts newtons to raw
counts with the inverse calibration, and writes frames. Faults come two ways: seeded random rates
(``GloveFaults``) for soak runs, and one-shot requests (``corrupt_next``, ``drop_next``, ...) for
tests that must know exactly what went wrong.

Like a UART, the simulator never waits for a listener: if the pty's buffer is full the frame is
lost (``stats().overflows``) and the receiver sees a sequence gap.
"""

from __future__ import annotations

import logging
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

from steerlab.hardware.glove import protocol as p
from steerlab.hardware.glove.calibration import GloveCalibration
from steerlab.hardware.grip.pty import PtyStreamer

log = logging.getLogger(__name__)

ForceSource = Callable[[float], tuple[float, float]]
"""t (s since start, host clock) -> (left_N, right_N)."""

MapSource = Callable[[float], tuple[Sequence[int] | bytes, Sequence[int] | bytes]]
"""t -> (left cells, right cells), CELLS_PER_GLOVE values 0..255 each."""

# Room for one whole frame beyond what the pty took, so frames are delayed, never torn.
_TX_LIMIT = 2 * p.MAX_FRAME_LEN


@dataclass(frozen=True)
class GloveFaults:
    """Per-frame probabilities of line and device faults (seeded by the simulator's seed)."""

    corrupt_byte: float = 0.0  # flip one random byte anywhere in the frame (sync included)
    crc_error: float = 0.0  # send a wrong CRC
    drop: float = 0.0  # device skips the frame: a sequence gap
    garbage: float = 0.0  # random bytes before the frame
    garbage_max_len: int = 32

    def __post_init__(self) -> None:
        for name in ("corrupt_byte", "crc_error", "drop", "garbage"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"GloveFaults.{name} must be a probability in 0..1, got {value}")
        if self.garbage_max_len < 1:
            raise ValueError(
                f"GloveFaults.garbage_max_len must be >= 1, got {self.garbage_max_len}"
            )


@dataclass
class SimulatedGloveStats:
    frames_sampled: int = 0  # sequence numbers used
    frames_written: int = 0  # frames handed to the pty (including deliberately damaged ones)
    frames_dropped: int = 0  # skipped on purpose (drop fault, stopped streaming, lag)
    overflows: int = 0  # lost because nobody read the pty
    faults_injected: int = 0  # corrupted, bad CRC, garbage, out-of-range


class SimulatedGloveUnit(PtyStreamer):
    """Writes glove frames into a pty at ``rate_hz``; open ``port`` with serial.Serial."""

    thread_name = "glove-sim"
    sim_name = "glove simulator"
    #: fault names :meth:`inject` knows (a simulated lab's glove faults)
    faults = ("glove_hang_up", "glove_stop", "crc_storm")

    def __init__(
        self,
        source: ForceSource,
        calibration: GloveCalibration,
        *,
        rate_hz: float = p.NOMINAL_RATE_HZ,
        pressure_map: MapSource | None = None,
        faults: GloveFaults | None = None,
        seed: int = 0,
        start_sequence: int = 0,
        start_time_us: int = 0,
        clock_drift_ppm: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
        on_error: Callable[[BaseException], None] | None = None,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self._period_us = round(1e6 / rate_hz)
        # A device crystal fast by `ppm` puts its fixed-period frames closer together in host time.
        super().__init__(
            host_period_s=self._period_us * 1e-6 / (1.0 + clock_drift_ppm * 1e-6),
            tx_limit=_TX_LIMIT,
            clock=clock,
            on_error=on_error,
        )
        self._source = source
        self._calibration = calibration
        self._pressure_map = pressure_map
        self._faults = faults or GloveFaults()
        self._rng = random.Random(seed)
        self._sequence = start_sequence
        self._device_us = start_time_us
        self._one_shot = {"corrupt": 0, "crc_error": 0, "drop": 0, "out_of_range": 0}
        self._garbage: bytearray = bytearray()
        self._stats = SimulatedGloveStats()

    def stats(self) -> SimulatedGloveStats:
        """A copy of the writer's counters."""
        return replace(self._stats)

    def inject(self, fault: str) -> None:
        """A simulated lab's glove fault (:attr:`faults`)."""
        if fault == "glove_hang_up":
            self.hang_up()
        elif fault == "glove_stop":
            self.stop_streaming()
        elif fault == "crc_storm":
            self.crc_error_next(200)
        else:
            raise ValueError(f"unknown glove fault {fault!r} (known: {', '.join(self.faults)})")

    # -- one-shot faults ------------------------------------------------------------------------

    def corrupt_next(self, n: int = 1) -> None:
        """Flip one byte in each of the next n frames (sync and header included)."""
        self._request("corrupt", n)

    def crc_error_next(self, n: int = 1) -> None:
        """Send the next n frames with a wrong CRC."""
        self._request("crc_error", n)

    def drop_next(self, n: int = 1) -> None:
        """Skip the next n frames: the receiver sees a gap of n sequence numbers."""
        self._request("drop", n)

    def out_of_range_next(self, n: int = 1) -> None:
        """Send the next n frames with a left total above FORCE_RAW_MAX (valid CRC)."""
        self._request("out_of_range", n)

    def send_garbage(self, data: bytes) -> None:
        """Write these bytes before the next frame."""
        with self._lock:
            self._garbage += data

    # -- writer thread --------------------------------------------------------------------------

    def _skip(self, n: int) -> None:
        self._sequence += n
        self._device_us += n * self._period_us
        self._stats.frames_sampled += n
        self._stats.frames_dropped += n

    def _emit(self, t: float) -> None:
        """Sample the source at t and queue one frame, with whatever faults are due."""
        sequence, device_us = self._sequence, self._device_us
        self._sequence += 1
        self._device_us += self._period_us
        self._stats.frames_sampled += 1

        # Draw every random number every frame, so a seed gives the same random faults whatever
        # one-shot faults a test adds.
        rng, faults = self._rng, self._faults
        draws = [rng.random() for _ in range(5)]
        flip = rng.randint(1, 0xFF)
        random_garbage = rng.randbytes(rng.randint(1, faults.garbage_max_len))
        with self._lock:
            if not self._streaming:
                # One-shot faults wait for the line to come back.
                self._stats.frames_dropped += 1
                return
            drop = self._take("drop") or draws[0] < faults.drop
            if drop:
                self._stats.frames_dropped += 1
                return
            corrupt = self._take("corrupt") or draws[1] < faults.corrupt_byte
            bad_crc = self._take("crc_error") or draws[2] < faults.crc_error
            out_of_range = self._take("out_of_range")
            garbage = bytes(self._garbage)
            self._garbage.clear()
        if draws[3] < faults.garbage:
            garbage += random_garbage

        left_raw, right_raw = self._calibration.to_counts(*self._source(t))
        if out_of_range:
            left_raw = p.FORCE_RAW_MAX + 1
        cells = self._pressure_map(t) if self._pressure_map is not None else (None, None)
        frame = bytearray(
            p.encode_frame(sequence, device_us, left_raw, right_raw, *cells, validate=False)
        )
        if bad_crc:
            frame[-1] ^= 0xFF
        if corrupt:
            frame[int(draws[4] * len(frame))] ^= flip
        self._stats.faults_injected += bool(garbage) + corrupt + bad_crc + out_of_range

        if not self._queue(garbage + frame):
            self._stats.overflows += 1
            return
        self._stats.frames_written += 1

    def _take(self, fault: str) -> bool:
        if self._one_shot[fault] > 0:
            self._one_shot[fault] -= 1
            return True
        return False

    def _request(self, fault: str, n: int) -> None:
        if n < 0:
            raise ValueError(f"number of frames must be >= 0, got {n}")
        with self._lock:
            self._one_shot[fault] += n
