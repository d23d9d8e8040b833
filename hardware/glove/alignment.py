"""Putting glove frames (~100 Hz) on the control loop's samples (1 kHz), on one host clock.

The loop saw, at each of its samples, the newest frame that had *arrived* by then (zero-order
hold on host arrival times), so that is what ``align_zoh`` reconstructs by default, together
with each sample's frame age. The device timestamps are used to describe the clocks:

    host_s ~= offset_s + (1 + drift_ppm * 1e-6) * device_s + latency

where device_s is the unwrapped device time in seconds and latency >= 0 is transport delay
(serial buffering, USB polling, thread scheduling). The lower envelope of host - device is the
zero-latency line: its windowed minima are fitted by least squares (a running minimum that also
follows drift). ``timebase="device"`` places each frame on that line instead of its arrival
time, which removes arrival jitter for offline analysis (it is no longer what the loop saw).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from steerlab.hardware.glove.protocol import DEVICE_TIME_MODULUS


def unwrap_device_time(device_time_us: ArrayLike, modulus: int = DEVICE_TIME_MODULUS) -> NDArray:
    """Wrapped device timestamps (us) -> continuous seconds, starting at the first raw value.

    Assumes consecutive frames are less than one wrap apart (71.6 min for uint32 us).
    """
    raw = np.asarray(device_time_us, dtype=np.int64)
    if raw.ndim != 1:
        raise ValueError("device_time_us must be one-dimensional")
    if raw.size == 0:
        return np.zeros(0)
    steps = np.diff(raw) % modulus
    return (raw[0] + np.concatenate(([0], np.cumsum(steps)))) * 1e-6


@dataclass(frozen=True)
class ClockFit:
    """host_s ~= offset_s + (1 + drift_ppm * 1e-6) * device_s, plus latency >= 0."""

    offset_s: float
    drift_ppm: float
    latency_median_s: float  # arrival delay above the fitted zero-latency line
    latency_max_s: float
    n_frames: int

    def device_to_host(self, device_s: ArrayLike) -> NDArray:
        return self.offset_s + (1.0 + self.drift_ppm * 1e-6) * np.asarray(device_s, float)


def fit_clock(host_s: ArrayLike, device_time_us: ArrayLike, window_s: float = 1.0) -> ClockFit:
    """Fit the zero-latency line through per-window minima of host - device.

    With less than two windows of data the drift cannot be seen and is reported as 0.
    """
    host = np.asarray(host_s, dtype=float)
    device = unwrap_device_time(device_time_us)
    if host.shape != device.shape:
        raise ValueError(f"host_s {host.shape} and device_time_us {device.shape} differ")
    if host.size == 0:
        raise ValueError("fit_clock needs at least one frame")
    if not window_s > 0:
        raise ValueError(f"window_s must be > 0, got {window_s}")
    diff = host - device
    window = np.floor((device - device[0]) / window_s).astype(np.int64)
    starts = np.flatnonzero(np.diff(window, prepend=-1))
    minima = np.minimum.reduceat(diff, starts)
    at = [
        s + int(np.argmin(diff[s:e])) for s, e in zip(starts, [*starts[1:], diff.size], strict=True)
    ]
    if len(at) >= 2:
        slope, intercept = np.polyfit(device[at], minima, 1)
    else:
        slope, intercept = 0.0, float(diff.min())
    latency = diff - (intercept + slope * device)
    # The line runs under the minima only on average; shift it onto the lowest one so that
    # latency is >= 0 and offset is the earliest possible arrival.
    shift = float(latency.min())
    latency -= shift
    # host = intercept + shift + (1 + slope) * device, so the drift is the slope.
    return ClockFit(
        offset_s=float(intercept + shift),
        drift_ppm=float(slope * 1e6),
        latency_median_s=float(np.median(latency)),
        latency_max_s=float(latency.max()),
        n_frames=int(host.size),
    )


@dataclass(frozen=True)
class AlignmentSummary:
    """Plain scalars, for storing as metadata next to the aligned channel."""

    timebase: str
    n_samples: int
    n_frames: int
    samples_before_first_frame: int
    age_mean_s: float  # over samples that have a frame
    age_max_s: float
    frame_interval_median_s: float  # host arrival intervals
    frame_interval_max_s: float
    clock_offset_s: float | None  # None without device timestamps
    clock_drift_ppm: float | None
    latency_median_s: float | None
    latency_max_s: float | None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class AlignedStream:
    values: NDArray  # (n_samples,) or (n_samples, k); NaN before the first frame
    age_s: NDArray  # sample time - time of the frame held; NaN before the first frame
    frame_index: NDArray  # index into the frames held at each sample; -1 before the first
    summary: AlignmentSummary
    clock: ClockFit | None


def align_zoh(
    sample_times_s: ArrayLike,
    frame_host_s: ArrayLike,
    frame_values: ArrayLike,
    *,
    frame_device_us: ArrayLike | None = None,
    timebase: Literal["host", "device"] = "host",
    clock_window_s: float = 1.0,
) -> AlignedStream:
    """Hold each frame's values from its time until the next frame's (zero-order hold).

    ``frame_host_s`` must be non-decreasing (arrival order). Frames received in one read share
    a host time; the later one wins. A sample exactly at a frame's time already holds it.
    """
    samples = np.asarray(sample_times_s, dtype=float)
    host = np.asarray(frame_host_s, dtype=float)
    values = np.asarray(frame_values, dtype=float)
    if samples.ndim != 1 or host.ndim != 1:
        raise ValueError("sample_times_s and frame_host_s must be one-dimensional")
    if values.shape[:1] != host.shape:
        raise ValueError(
            f"frame_values has {values.shape[:1]} rows but frame_host_s has {host.size}"
        )
    if np.any(np.diff(host) < 0):
        raise ValueError("frame_host_s must be non-decreasing (frames in arrival order)")

    clock = None
    if frame_device_us is not None and host.size:
        clock = fit_clock(host, frame_device_us, clock_window_s)
    if timebase == "device":
        if clock is None or frame_device_us is None:
            raise ValueError("timebase='device' needs frame_device_us")
        times = clock.device_to_host(unwrap_device_time(frame_device_us))
    elif timebase == "host":
        times = host
    else:
        raise ValueError(f"timebase must be 'host' or 'device', got {timebase!r}")

    index = np.searchsorted(times, samples, side="right") - 1
    held = index >= 0
    out = np.full((samples.size, *values.shape[1:]), np.nan)
    out[held] = values[index[held]]
    age = np.full(samples.size, np.nan)
    age[held] = samples[held] - times[index[held]]

    intervals = np.diff(host)
    summary = AlignmentSummary(
        timebase=timebase,
        n_samples=int(samples.size),
        n_frames=int(host.size),
        samples_before_first_frame=int(np.count_nonzero(~held)),
        age_mean_s=float(age[held].mean()) if held.any() else float("nan"),
        age_max_s=float(age[held].max()) if held.any() else float("nan"),
        frame_interval_median_s=float(np.median(intervals)) if intervals.size else float("nan"),
        frame_interval_max_s=float(intervals.max()) if intervals.size else float("nan"),
        clock_offset_s=None if clock is None else clock.offset_s,
        clock_drift_ppm=None if clock is None else clock.drift_ppm,
        latency_median_s=None if clock is None else clock.latency_median_s,
        latency_max_s=None if clock is None else clock.latency_max_s,
    )
    return AlignedStream(out, age, index, summary, clock)
