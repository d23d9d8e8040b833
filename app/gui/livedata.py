"""In-memory live data, written by the engine thread and read by the GUI thread. Qt-free.

The plots and the quality check read from here, never from the session file: re-reading a
growing HDF5 file slows down as it grows and contends with the writer for its locks.

The engine thread only copies each block into preallocated arrays under a lock held for
microseconds; the GUI thread takes copies under the same lock. Neither waits on the other for
longer than a copy, so a slow GUI drops frames and never delays the loop.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from steerlab.protocols import events as ev

#: Channels kept for the live plots (the loop sends more; they go to the file only).
LIVE_CHANNELS: tuple[str, ...] = (
    "time_s",
    "perturbation_torque_Nm",
    "driver_torque_Nm",
    "wheel_angle_rad",
    "grip_force_N",
    "grip_force_left_N",
    "grip_force_right_N",
)


class RingBuffer:
    """Fixed-capacity circular buffer of equally long channels."""

    def __init__(self, channels: tuple[str, ...], capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"ring buffer capacity must be ≥ 1, got {capacity}")
        self.channels = channels
        self.capacity = int(capacity)
        self._data = np.full((len(channels), self.capacity), np.nan)
        self._row = {c: i for i, c in enumerate(channels)}
        self.n_written = 0  # total samples ever written (monotonic)

    def write(self, block: dict[str, np.ndarray]) -> None:
        n = len(next(iter(block.values())))
        if n == 0:
            return
        cap = self.capacity
        if n > cap:  # only the newest capacity samples can be kept
            block = {k: np.asarray(v)[-cap:] for k, v in block.items()}
            self.n_written += n - cap
            n = cap
        start = self.n_written % cap
        first = min(n, cap - start)
        for c, i in self._row.items():
            v = block.get(c)
            if v is None:
                self._data[i, start : start + first] = np.nan
                self._data[i, : n - first] = np.nan
                continue
            v = np.asarray(v)
            self._data[i, start : start + first] = v[:first]
            self._data[i, : n - first] = v[first:]
        self.n_written += n

    def last(self, n: int) -> dict[str, np.ndarray]:
        """Copies of the newest ``min(n, available)`` samples, oldest first."""
        n = int(min(n, self.n_written, self.capacity))
        end = self.n_written % self.capacity
        if n <= end:
            out = self._data[:, end - n : end].copy()
        else:
            out = np.concatenate(
                [self._data[:, self.capacity - (n - end) :], self._data[:, :end]], axis=1
            )
        return {c: out[i] for c, i in self._row.items()}

    def latest(self, channel: str) -> float | None:
        if self.n_written == 0:
            return None
        return float(self._data[self._row[channel], (self.n_written - 1) % self.capacity])


@dataclass
class CapturedTrial:
    """One trial's samples as received from the engine, with what is needed to judge them."""

    key: str
    trial_index: int
    condition: str
    attributes: dict
    n_planned: int
    blocks: list[dict[str, np.ndarray]] = field(default_factory=list)
    n_received: int = 0
    ended: ev.TrialEnded | None = None

    def channels(self) -> dict[str, np.ndarray]:
        """The blocks concatenated (done on the GUI thread, never the engine's)."""
        if not self.blocks:
            return {c: np.zeros(0) for c in LIVE_CHANNELS}
        names = self.blocks[0].keys()
        return {c: np.concatenate([b[c] for b in self.blocks]) for c in names}


@dataclass(frozen=True)
class LiveSnapshot:
    key: str | None
    fs_hz: float
    n_written: int
    channels: dict[str, np.ndarray]


class LiveData:
    """Engine subscriber (call it with engine events on the engine thread).

    Keeps a ring buffer of the newest ``window_s`` seconds of the running trial, and every block
    of the running trial until the GUI takes it with :meth:`take_trial` after the trial ended.
    """

    def __init__(self, window_s: float = 30.0) -> None:
        self.window_s = window_s
        self._lock = threading.Lock()
        self._ring = RingBuffer(LIVE_CHANNELS, 1)
        self._key: str | None = None
        self._fs = 0.0
        self._capture: CapturedTrial | None = None
        self._finished: dict[str, CapturedTrial] = {}
        self.total_received = 0  # samples over all trials, for the live sample rate

    def __call__(self, event: object) -> None:
        if isinstance(event, ev.SamplesAcquired):
            with self._lock:
                if event.key == self._key:
                    self._ring.write(event.channels)
                    if self._capture is not None:
                        # The loop hands a fresh dict of fresh arrays per block: no copy needed.
                        self._capture.blocks.append(event.channels)
                        self._capture.n_received += event.n
                self.total_received += event.n
        elif isinstance(event, ev.TrialStarted):
            fs = float(event.attributes.get("fs_hz", 1000.0))
            ring = RingBuffer(LIVE_CHANNELS, max(1, int(round(self.window_s * fs))))
            cap = CapturedTrial(
                event.key, event.trial_index, event.condition, dict(event.attributes),
                event.n_planned,
            )  # fmt: skip
            with self._lock:
                self._ring, self._key, self._fs, self._capture = ring, event.key, fs, cap
        elif isinstance(event, ev.TrialEnded):
            with self._lock:
                if self._capture is not None and self._capture.key == event.key:
                    self._capture.ended = event
                    self._finished[event.key] = self._capture
                    self._capture = None
                    # Keep only the last few: a session is hours long.
                    while len(self._finished) > 3:
                        self._finished.pop(next(iter(self._finished)))

    # -- GUI thread --------------------------------------------------------------------------
    def snapshot(self, seconds: float) -> LiveSnapshot:
        with self._lock:
            n = int(round(seconds * self._fs)) if self._fs else 0
            return LiveSnapshot(self._key, self._fs, self._ring.n_written, self._ring.last(n))

    def latest(self, channel: str) -> float | None:
        with self._lock:
            return self._ring.latest(channel)

    def mean_of_last(self, channel: str, seconds: float) -> float | None:
        snap = self.snapshot(seconds)
        x = snap.channels.get(channel)
        if x is None or len(x) == 0:
            return None
        return float(np.mean(x))

    @property
    def n_written(self) -> int:
        return self._ring.n_written

    def take_trial(self, key: str) -> CapturedTrial | None:
        with self._lock:
            return self._finished.pop(key, None)
