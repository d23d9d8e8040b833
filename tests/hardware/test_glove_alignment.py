from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from steerlab.hardware.glove.alignment import align_zoh, fit_clock, unwrap_device_time


def test_zoh_by_hand():
    frames_host = [0.010, 0.020, 0.020, 0.035]  # two frames arrived in one read at 0.020
    values = [1.0, 2.0, 3.0, 4.0]
    samples = [0.000, 0.010, 0.015, 0.020, 0.030, 0.036]
    aligned = align_zoh(samples, frames_host, values)
    assert_array_equal(aligned.values, [np.nan, 1.0, 1.0, 3.0, 3.0, 4.0])
    assert_array_equal(aligned.frame_index, [-1, 0, 0, 2, 2, 3])
    assert_allclose(aligned.age_s, [np.nan, 0.0, 0.005, 0.0, 0.010, 0.001], atol=1e-12)
    s = aligned.summary
    assert (s.n_samples, s.n_frames, s.samples_before_first_frame) == (6, 4, 1)
    assert s.age_max_s == pytest.approx(0.010)
    assert s.clock_offset_s is None and aligned.clock is None
    assert s.as_dict()["timebase"] == "host"


def test_zoh_two_columns():
    aligned = align_zoh([0.5, 1.5], [0.0, 1.0], [[1.0, 10.0], [2.0, 20.0]])
    assert_array_equal(aligned.values, [[1.0, 10.0], [2.0, 20.0]])


def test_zoh_refuses_unordered_frames():
    with pytest.raises(ValueError, match="non-decreasing"):
        align_zoh([0.0], [0.2, 0.1], [1.0, 2.0])
    with pytest.raises(ValueError, match="rows"):
        align_zoh([0.0], [0.1, 0.2], [1.0])


def test_unwrap_device_time_across_the_uint32_wrap():
    raw = [2**32 - 20_000, 2**32 - 10_000, 0, 10_000]
    assert_allclose(unwrap_device_time(raw), (2**32 - 20_000 + np.arange(4) * 10_000) * 1e-6)


def synthetic_stream(n=3000, drift_ppm=50.0, offset_s=123.4, start_us=2**32 - 5_000_000, seed=0):
    """100 Hz frames: exact device period, a drifting host clock, latency >= 1 ms with jitter.
    The device clock wraps 5 s in."""
    rng = np.random.default_rng(seed)
    device_s = (start_us + np.arange(n) * 10_000) * 1e-6
    latency = 0.001 + rng.exponential(0.002, n)
    latency[::50] = 0.001  # now and then a frame goes straight through
    # A serial line is FIFO: a frame never arrives before the one sent ahead of it.
    host = np.maximum.accumulate(offset_s + (1 + drift_ppm * 1e-6) * device_s + latency)
    device_us = (start_us + np.arange(n) * 10_000) % 2**32
    return host, device_us, device_s


def test_clock_fit_recovers_offset_and_drift():
    host, device_us, device_s = synthetic_stream()
    fit = fit_clock(host, device_us)
    assert fit.drift_ppm == pytest.approx(50.0, abs=1.0)
    # The zero-latency line sits at the fastest frames: the true offset plus their 1 ms.
    assert fit.offset_s == pytest.approx(123.4 + 0.001, abs=2e-4)
    assert 0.0 <= fit.latency_median_s < 0.003
    assert_allclose(fit.device_to_host(device_s), host, atol=0.03)
    assert np.all(host - fit.device_to_host(device_s) >= -1e-9)


def test_align_with_device_timestamps_and_device_timebase():
    host, device_us, _ = synthetic_stream(n=500)
    values = np.arange(500.0)
    samples = np.arange(host[0], host[-1], 0.001)  # the 1 kHz loop
    by_host = align_zoh(samples, host, values, frame_device_us=device_us)
    assert by_host.summary.clock_drift_ppm == pytest.approx(50.0, abs=5.0)
    assert by_host.summary.samples_before_first_frame == 0
    assert by_host.summary.age_max_s < 0.05
    by_device = align_zoh(samples, host, values, frame_device_us=device_us, timebase="device")
    # On the fitted line frames are evenly spaced, so no sample holds a frame longer than one
    # period (plus the drift over it).
    assert np.nanmax(by_device.age_s) < 0.0101
    assert set(by_device.summary.as_dict()) >= {"clock_offset_s", "clock_drift_ppm"}
    with pytest.raises(ValueError, match="needs frame_device_us"):
        align_zoh(samples, host, values, timebase="device")
