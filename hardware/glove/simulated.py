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

import errno
import fcntl
import logging
import os
import random
import threading
import time
import tty
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

from steerlab.hardware.glove import protocol as p
from steerlab.hardware.glove.calibration import GloveCalibration

log = logging.getLogger(__name__)

ForceSource = Callable[[float], tuple[float, float]]
"""t (s since start, host clock) -> (left_N, right_N)."""

MapSource = Callable[[float], tuple[Sequence[int] | bytes, Sequence[int] | bytes]]
"""t -> (left cells, right cells), CELLS_PER_GLOVE values 0..255 each."""

# Room for one whole frame beyond what the pty took, so frames are delayed, never torn.
_TX_LIMIT = 2 * p.MAX_FRAME_LEN
# Behind schedule by more than this (process suspended), the device "keeps sampling" but those
# frames are lost, rather than arriving as one huge burst.
_MAX_LAG_S = 1.0


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


class SimulatedGloveUnit:
    """Writes glove frames into a pty at ``rate_hz``; open ``port`` with serial.Serial."""

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
        self._source = source
        self._calibration = calibration
        self._pressure_map = pressure_map
        self._faults = faults or GloveFaults()
        self._rng = random.Random(seed)
        self._clock = clock
        self._on_error = on_error
        self._period_us = round(1e6 / rate_hz)
        # A device crystal fast by `ppm` puts its fixed-period frames closer together in host time.
        self._host_period_s = self._period_us * 1e-6 / (1.0 + clock_drift_ppm * 1e-6)
        self._sequence = start_sequence
        self._device_us = start_time_us

        self._lock = threading.Lock()
        self._one_shot = {"corrupt": 0, "crc_error": 0, "drop": 0, "out_of_range": 0}
        self._garbage: bytearray = bytearray()
        self._streaming = True
        self._hangup = threading.Event()
        self._hung_up = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._tx = bytearray()
        self._error: BaseException | None = None
        self._stats = SimulatedGloveStats()

        self._master, self._slave = os.openpty()
        try:
            # Raw from the start: bytes written before the reader configures the port must not
            # be echoed, turned into signals, or taken as XON/XOFF by the line discipline.
            tty.setraw(self._slave)
            flags = fcntl.fcntl(self._master, fcntl.F_GETFL)
            fcntl.fcntl(self._master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
            self._port = os.ttyname(self._slave)
        except BaseException:
            os.close(self._master)
            os.close(self._slave)
            raise
        self._master_open = True
        self._closed = False

    @property
    def port(self) -> str:
        """Device path of the pty slave, e.g. /dev/pts/3."""
        return self._port

    @property
    def error(self) -> BaseException | None:
        """What stopped the writer thread, or None."""
        return self._error

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def stats(self) -> SimulatedGloveStats:
        """A copy of the writer's counters."""
        return replace(self._stats)

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> SimulatedGloveUnit:
        if self._closed:
            raise RuntimeError("SimulatedGloveUnit: cannot start after close()")
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="glove-sim", daemon=True)
            self._thread.start()
        return self

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the writer and close both pty ends. A reader still attached then fails with
        an I/O error, as with an unplugged USB adapter: close the reader first. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("glove simulator did not stop within %.1f s", timeout_s)
                return  # leave the fds to the thread rather than close them under it
        self._close_master()
        os.close(self._slave)

    def __enter__(self) -> SimulatedGloveUnit:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

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

    def stop_streaming(self) -> None:
        """The line goes quiet; the device keeps counting, so resuming shows a gap."""
        with self._lock:
            self._streaming = False

    def resume_streaming(self) -> None:
        with self._lock:
            self._streaming = True

    def hang_up(self, timeout_s: float = 1.0) -> None:
        """Close the pty master mid-stream: the reader's next read fails (EIO), as when the
        unit is unplugged. Returns once the master is closed."""
        if self._thread is None or not self._thread.is_alive():
            self._close_master()
            return
        self._hangup.set()
        if not self._hung_up.wait(timeout_s):
            raise TimeoutError("glove simulator did not hang up")

    # -- writer thread --------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            t0 = self._clock()
            k = 0  # frames scheduled so far
            while not self._stop.is_set():
                if self._hangup.is_set():
                    self._close_master()
                    self._hung_up.set()
                    return
                now = self._clock()
                due = t0 + k * self._host_period_s
                if now < due:
                    self._stop.wait(min(due - now, 0.02))
                    continue
                lag_frames = int((now - due - _MAX_LAG_S) / self._host_period_s)
                if lag_frames > 0:
                    self._skip_frames(lag_frames)
                    k += lag_frames
                    continue
                self._emit(due - t0)
                k += 1
                self._flush()
        except BaseException as exc:  # report everything: a dead simulator must not look quiet
            self._error = exc
            log.error("glove simulator failed: %r", exc)
            if self._on_error is not None:
                try:
                    self._on_error(exc)
                except Exception:
                    log.exception("glove simulator on_error callback raised")

    def _skip_frames(self, n: int) -> None:
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

        if self._tx and len(self._tx) + len(garbage) + len(frame) > _TX_LIMIT:
            self._stats.overflows += 1
            return
        self._tx += garbage
        self._tx += frame
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
