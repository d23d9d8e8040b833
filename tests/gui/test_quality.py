"""The after-trial quality check against an independent numpy computation (Qt-free)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from scipy import signal

from steerlab.app.gui.quality import quality_check
from steerlab.protocols.protocol import parse_protocol
from steerlab.protocols.session import build_plan
from tests.helpers import fast_protocol_text


def _plan():
    text = fast_protocol_text(loop_rate_hz=200.0, run_in_s=0.5, periods=3)
    for key, value in {"period_s": "2.0", "n_bands": "8", "first_bin": "1",
                       "fade_in_s": "0.25", "fade_out_s": "0.25"}.items():  # fmt: skip
        text = re.sub(rf"(?m)^{key} = \S+", f"{key} = {value}", text)
    return build_plan(parse_protocol(text, "short.toml"), 1)


def _trial(noise_sd: float, seed: int = 0):
    plan = _plan()
    setup = plan.setup(plan.trials[1])  # BT or RT, whichever: the boundary is passed explicitly
    tp = np.array(setup.perturbation_nm)
    # A second-order admittance (rad/N·m) sampled at 200 Hz, plus remnant.
    b, a = signal.bilinear([0.05], [1 / (2 * np.pi * 2.0) ** 2, 0.8 / (2 * np.pi * 2.0), 1], 200.0)
    theta = signal.lfilter(b, a, tp) + noise_sd * np.random.default_rng(seed).standard_normal(
        len(tp)
    )
    return plan, setup, {"perturbation_torque_Nm": tp, "wheel_angle_rad": theta}


def _independent(plan, setup, tp, theta, n_received):
    """Coherence per band by an explicit DFT matrix, without the module's code paths."""
    d = plan.design
    p = int(round(d.period_s * setup.fs_hz))
    stop = min(setup.measured_stop, n_received)
    k = (stop - setup.measured_start) // p
    n = np.arange(p)
    e = np.exp(-2j * np.pi * np.outer(d.bins, n) / p) * (2.0 / p)
    segs_x = tp[setup.measured_start : setup.measured_start + k * p].reshape(k, p)
    segs_y = theta[setup.measured_start : setup.measured_start + k * p].reshape(k, p)
    fx, fy = segs_x @ e.T, segs_y @ e.T
    coh = []
    for band in sorted(set(d.band_of_bin.tolist())):
        cols = [i for i, bb in enumerate(d.band_of_bin) if bb == band]
        sxy = sum(np.conj(fx[r, c]) * fy[r, c] for r in range(k) for c in cols) / (k * len(cols))
        sxx = sum(abs(fx[r, c]) ** 2 for r in range(k) for c in cols) / (k * len(cols))
        syy = sum(abs(fy[r, c]) ** 2 for r in range(k) for c in cols) / (k * len(cols))
        coh.append(abs(sxy) / math.sqrt(sxx * syy))
    deg = np.degrees(theta[setup.measured_start : stop])
    return np.array(coh), k, deg


@pytest.mark.parametrize("boundary", [5.0, 0.0, math.inf])
def test_quality_figures_match_numpy(boundary):
    plan, setup, ch = _trial(noise_sd=0.01)
    n = setup.n_samples
    q = quality_check(
        ch, key="k", condition="X", status="complete", fs_hz=setup.fs_hz,
        measured_start=setup.measured_start, measured_stop=setup.measured_stop,
        design=plan.design, boundary_deg=boundary, n_planned=n, n_engine=n,
        loop_stats={"period_error_p50_ms": 0.01, "period_error_p99_ms": 0.2,
                    "period_error_max_ms": 0.4, "late_cycles": 0, "cycles": n},
    )  # fmt: skip
    coh, k, deg = _independent(plan, setup, ch["perturbation_torque_Nm"],
                               ch["wheel_angle_rad"], n)  # fmt: skip
    assert q.n_periods == k == 3
    np.testing.assert_allclose(q.coherence, coh, rtol=1e-10)
    assert 0.2 < q.coherence_median < 1.0  # the remnant lowers it, the perturbation dominates
    assert q.angle_rms_deg == pytest.approx(np.sqrt(np.mean(deg**2)), rel=1e-12)
    if math.isinf(boundary):
        assert q.outside_boundary_percent is None
    else:
        expected = 100.0 * np.mean(np.abs(deg) > boundary)
        assert q.outside_boundary_percent == pytest.approx(expected, rel=1e-12)
    assert q.lost_samples == 0 and q.n_measured == setup.measured_stop - setup.measured_start
    freqs = [plan.design.frequencies_hz[plan.design.band_of_bin == b].mean() for b in range(8)]
    np.testing.assert_allclose(q.band_frequencies_hz, freqs)
    labels = dict(q.rows())
    assert "p99 0.200" in labels["loop period error"]
    assert labels["late cycles"] == f"0 of {n} cycles late (worst 0.4 ms)"


def test_noise_free_coherence_is_one_and_noise_lowers_it():
    # A frequency-flat system: with H varying between a band's two bins, even a noise-free
    # band-averaged coherence is below 1 (Cauchy–Schwarz).
    plan, setup, ch = _trial(noise_sd=0.0)
    ch["wheel_angle_rad"] = 0.05 * ch["perturbation_torque_Nm"]
    common = dict(key="k", condition="X", status="complete", fs_hz=setup.fs_hz,
                  measured_start=setup.measured_start, measured_stop=setup.measured_stop,
                  design=plan.design, boundary_deg=5.0, n_planned=setup.n_samples,
                  n_engine=setup.n_samples)  # fmt: skip
    clean = quality_check(ch, **common)
    np.testing.assert_allclose(clean.coherence, 1.0, atol=1e-6)
    noisy = dict(ch)
    rng = np.random.default_rng(1)
    noisy["wheel_angle_rad"] = ch["wheel_angle_rad"] + 0.5 * rng.standard_normal(setup.n_samples)
    assert quality_check(noisy, **common).coherence_median < clean.coherence_median - 0.05


def test_aborted_trial_uses_what_arrived():
    plan, setup, ch = _trial(noise_sd=0.01)
    cut = setup.measured_start + int(1.5 * 400)  # one and a half periods
    part = {k: v[:cut] for k, v in ch.items()}
    q = quality_check(
        part, key="k", condition="X", status="aborted", fs_hz=setup.fs_hz,
        measured_start=setup.measured_start, measured_stop=setup.measured_stop,
        design=plan.design, boundary_deg=8.0, n_planned=setup.n_samples, n_engine=cut,
    )  # fmt: skip
    coh, k, deg = _independent(plan, setup, ch["perturbation_torque_Nm"],
                               ch["wheel_angle_rad"], cut)  # fmt: skip
    assert q.n_periods == k == 1
    np.testing.assert_allclose(q.coherence, coh, rtol=1e-10)
    assert q.n_received == cut and q.lost_samples == 0
    assert q.not_recorded == setup.n_samples - cut
    # An aborted trial lost nothing: what it never acquired is said to be not recorded.
    samples = dict(q.rows())["samples"]
    assert f"{setup.n_samples - cut} not recorded (aborted)" in samples
    assert "lost" not in samples
    assert q.n_measured == len(deg) == cut - setup.measured_start
    assert q.warnings[0] == "trial aborted"


def test_no_whole_period_gives_no_coherence():
    plan, setup, ch = _trial(noise_sd=0.01)
    cut = setup.measured_start + 100
    q = quality_check(
        {k: v[:cut] for k, v in ch.items()}, key="k", condition="X", status="aborted",
        fs_hz=setup.fs_hz, measured_start=setup.measured_start,
        measured_stop=setup.measured_stop, design=plan.design, boundary_deg=8.0,
        n_planned=setup.n_samples, n_engine=cut + 5,
    )  # fmt: skip
    assert q.n_periods == 0 and q.coherence.size == 0 and q.coherence_median is None
    assert any("engine counted" in w for w in q.warnings)


LATE_STATS = {"period_error_p50_ms": 0.01, "period_error_p99_ms": 2.8, "period_error_max_ms": 12.1,
              "late_cycles": 2830, "cycles": 51000, "late_threshold_ms": 0.5}  # fmt: skip


@pytest.mark.parametrize("steps_by_sample", [True, False])
def test_late_cycles_are_said_in_words_and_flagged_only_where_they_matter(steps_by_sample):
    plan, setup, ch = _trial(noise_sd=0.01)
    n = setup.n_samples
    stall = 1000.0 if steps_by_sample else 20.0
    q = quality_check(
        ch, key="k", condition="X", status="complete", fs_hz=setup.fs_hz,
        measured_start=setup.measured_start, measured_stop=setup.measured_stop,
        design=plan.design, boundary_deg=8.0, n_planned=n, n_engine=n,
        loop_stats=LATE_STATS | {"stall_limit_ms": stall}, steps_by_sample=steps_by_sample,
    )  # fmt: skip
    row = dict(q.rows())["late cycles"]
    assert row.startswith(
        f"2830 of 51000 cycles > 0.5 ms late (worst 12 ms; a trial aborts at {stall:.0f} ms)"
    ), row
    late_warnings = [w for w in q.warnings if "late" in w]
    if steps_by_sample:
        # The simulated world steps once per cycle: the data are the same, and it says so.
        assert "no recorded value changes" in row
        assert late_warnings == []
    else:
        assert "off its due time" in row
        (w,) = late_warnings
        assert w.startswith("2830 late loop cycles (5.5 %)")
        assert "close other programs" in w and "real-time priority" in w
