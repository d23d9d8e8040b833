"""The independent world is right, checked against analytic truths and scipy (not Steerlab).

Expectations are written here from the physics, independently of the world's own matrices:

- Continuous admittance H(s) = 1/(b_c s + k_c) + 1/(I_i s² + b_i s + k_i).
- The exact sampled-data ("lifted") closed loop: the continuous wheel + arm state space written
  out below, discretised with ``scipy.signal.cont2discrete(method="zoh")`` (the command is held
  over a sample), closed with u_k = T_p,k − b_sw ω_k − k_sw θ_k. Its frequency responses from
  T_p,k to θ_k and T_d,k are exact at the sample instants for a noise-free world.

Why the hold does not bias θ/T_d but does show in the wheel equation: θ and T_d are both
outputs of the continuous arm driven by the same continuous wheel motion, so the hold's
half-sample delay e^{−sh/2} multiplies both and cancels in the ratio; only aliasing of the
staircase's images remains (≤ 2.2 % at 20 Hz for 250 Hz, computed below with the lifted model,
≤ 0.05 % at 2 kHz). The wheel equation T_p − T_d − (I s² + b s + k)θ instead compares the
rendered command with its held version: its residual is (1 − ZOH(jω))·U with
ZOH(jω) = (1 − e^{−jωh})/(jωh) ≈ e^{−jωh/2}, i.e. |residual/U| ≈ ωh/2 (25 % at 20 Hz, 250 Hz).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import cont2discrete, csd, welch

from steerlab.benchmarks.otherworld import DEFAULT_ARM, Multisine, World, simulate_trial

I_W, B_SW, K_SW = 0.3, 2.0, 4.2
PERIOD = 10.0  # short period: fast tests; the physics does not depend on it


def quiet_world(cond="BT12", fs=250.0, **kw):
    arm = {"I_i": 0.07} | DEFAULT_ARM[cond]
    base = dict(arm=arm, fs_hz=fs, remnant_rel=0.0, angle_noise_rad=0.0, torque_noise_Nm=0.0)
    return World(**(base | kw))


def admittance(arm, f):
    s = 2j * np.pi * np.asarray(f)
    return 1 / (arm["b_c"] * s + arm["k_c"]) + 1 / (arm["I_i"] * s**2 + arm["b_i"] * s + arm["k_i"])


def lifted_frf(arm, fs, f):
    """Exact sampled-data responses T_p,k → θ_k and T_p,k → T_d,k (noise-free, velocity read
    exactly, ZOH command computed from the reads at t_k)."""
    Ii, bi, ki, bc, kc = (arm[k] for k in ("I_i", "b_i", "k_i", "b_c", "k_c"))
    A = np.array(
        [
            [0, 1, 0, 0],
            [-kc / I_W, -bc / I_W, kc / I_W, bc / I_W],
            [0, 0, 0, 1],
            [kc / Ii, bc / Ii, -(kc + ki) / Ii, -(bc + bi) / Ii],
        ]
    )
    B = np.array([[0.0], [1 / I_W], [0.0], [0.0]])
    Ad, Bd, *_ = cont2discrete((A, B, np.eye(4), np.zeros((4, 1))), 1 / fs, method="zoh")
    Acl = Ad - Bd @ np.array([[K_SW, B_SW, 0.0, 0.0]])
    c_th = np.array([1.0, 0, 0, 0])
    c_td = np.array([kc, bc, -kc, -bc])
    g_th, g_td = [], []
    for z in np.exp(2j * np.pi * np.asarray(f) / fs):
        x = np.linalg.solve(z * np.eye(4) - Acl, Bd[:, 0])
        g_th.append(c_th @ x)
        g_td.append(c_td @ x)
    return np.array(g_th), np.array(g_td)


def csd_frf(rec, design, fs, n_periods=2):
    """θ/T_d at the excited bins by scipy.signal.csd with one whole period per segment."""
    n = int(round(design.period_s * fs))
    seg = slice(len(rec["time_s"]) - n_periods * n, None)
    kw = dict(fs=fs, window="boxcar", nperseg=n, noverlap=0, detrend=False)
    f, s_pt = csd(rec["perturbation_torque_Nm"][seg], rec["wheel_angle_rad"][seg], **kw)
    _, s_pd = csd(rec["perturbation_torque_Nm"][seg], rec["driver_torque_Nm"][seg], **kw)
    b = design.bins
    assert np.allclose(f[b], design.frequencies_hz)
    return f[b], s_pt[b] / s_pd[b]


@pytest.mark.parametrize("cond", ["RT", "PT"])
def test_closed_loop_admittance_matches_the_analytic_arm(cond):
    fs = 250.0
    d = Multisine.design(11, period_s=PERIOD)
    w = quiet_world(cond, fs)
    rec = simulate_trial(w, d, run_in_s=3.0, phase_offset_s=4.321, seed=1)
    f, H = csd_frf(rec, d, fs)
    Hc = admittance(w.arm, f)
    g_th, g_td = lifted_frf(w.arm, fs, f)
    # exact against the lifted sampled-data model (noise-free: only the decayed run-in remains)
    np.testing.assert_allclose(H, g_th / g_td, rtol=1e-5)
    # against the continuous admittance: within the aliasing the lifted model predicts
    alias = np.abs(g_th / g_td / Hc - 1)
    assert alias.max() < 0.025
    err = np.abs(H / Hc - 1)
    assert np.all(err <= alias + 1e-5)
    assert err[f < 5].max() < 2e-3
    # sign convention: S(Tp,θ)/S(Tp,Td) positive at low frequency
    assert H[0].real > 0 and abs(np.angle(H[0])) < 0.3


def test_aliasing_vanishes_at_a_high_sample_rate():
    fs = 2000.0
    d = Multisine.design(12, period_s=PERIOD)
    w = quiet_world("BT8", fs)
    rec = simulate_trial(w, d, run_in_s=2.0, seed=2)
    f, H = csd_frf(rec, d, fs)
    np.testing.assert_allclose(H, admittance(w.arm, f), rtol=1e-3)


def test_wheel_equation_residual_is_the_zero_order_hold():
    fs = 250.0
    d = Multisine.design(13, period_s=PERIOD)
    rec = simulate_trial(quiet_world("BT12", fs), d, run_in_s=3.0, seed=3)
    n = int(PERIOD * fs)

    def spec(x):
        return np.fft.rfft(x[-2 * n :].reshape(2, n), axis=1).mean(axis=0)[d.bins]

    tp, td, th = (
        spec(rec[c]) for c in ("perturbation_torque_Nm", "driver_torque_Nm", "wheel_angle_rad")
    )
    s = 2j * np.pi * d.frequencies_hz
    resid = tp - td - (I_W * s**2 + B_SW * s + K_SW) * th  # Table-1 wheel equation
    u = tp - (B_SW * s + K_SW) * th  # the rendered command
    zoh = (1 - np.exp(-s / fs)) / (s / fs)
    expected = 1 - zoh
    ratio = resid / u
    # the residual is the hold, not noise: |1 − ZOH| ≈ ωh/2 grows to 25 % at 20 Hz
    assert abs(ratio[-1]) > 0.2 and abs(ratio[0]) < 0.01
    np.testing.assert_allclose(ratio, expected, rtol=0.01)
    # and the exact lifted model gives the same residual
    g_th, g_td = lifted_frf(quiet_world("BT12").arm, fs, d.frequencies_hz)
    lifted = 1 - g_td - (I_W * s**2 + B_SW * s + K_SW) * g_th
    np.testing.assert_allclose(resid / tp, lifted, rtol=1e-4, atol=1e-6)


def test_finer_control_rate_shrinks_the_hold_residual():
    d = Multisine.design(14, period_s=PERIOD)
    out = {}
    for fs in (250.0, 1000.0):
        rec = simulate_trial(quiet_world("BT12", fs), d, run_in_s=2.0, seed=3)
        n = int(PERIOD * fs)
        sp = {
            c: np.fft.rfft(rec[c][-n:])[d.bins]
            for c in ("perturbation_torque_Nm", "driver_torque_Nm", "wheel_angle_rad")
        }
        s = 2j * np.pi * d.frequencies_hz
        th = sp["wheel_angle_rad"]
        r = (
            sp["perturbation_torque_Nm"]
            - sp["driver_torque_Nm"]
            - (I_W * s**2 + B_SW * s + K_SW) * th
        )
        out[fs] = np.abs(r / (sp["perturbation_torque_Nm"] - (B_SW * s + K_SW) * th))
    np.testing.assert_allclose(out[250.0] / out[1000.0], 4.0, rtol=0.05)  # ∝ h


def test_expm_and_solve_ivp_integrate_the_same_world():
    d = Multisine.design(15, period_s=PERIOD)
    kw = dict(arm={"I_i": 0.1} | DEFAULT_ARM["BT5"], fs_hz=200.0, remnant_order=2)
    a = simulate_trial(World(**kw, integrator="expm"), d, n_periods=1, run_in_s=1.0, seed=4)
    b = simulate_trial(World(**kw, integrator="solve_ivp"), d, n_periods=1, run_in_s=1.0, seed=4)
    for c in ("wheel_angle_rad", "driver_torque_Nm"):
        scale = np.abs(a[c]).max()
        np.testing.assert_allclose(a[c], b[c], atol=1e-6 * scale)
    np.testing.assert_allclose(a["true"]["remnant"], b["true"]["remnant"], atol=1e-8)


def test_difference_velocity_adds_the_expected_lag():
    """With a backward-difference velocity the damping term reads ω e^{−jωh/2}·sinc: θ/T_d is
    still the arm (the rig's rendering does not enter the ratio)."""
    fs = 250.0
    d = Multisine.design(16, period_s=PERIOD)
    w = quiet_world("BT8", fs, velocity_source="difference")
    rec = simulate_trial(w, d, run_in_s=3.0, seed=5)
    f, H = csd_frf(rec, d, fs)
    np.testing.assert_allclose(H, admittance(w.arm, f), rtol=0.03)


@pytest.mark.parametrize("order", [1, 2])
def test_remnant_level_and_corner(order):
    fs, corner, rel = 100.0, 0.5, 0.3
    d = Multisine.design(17, period_s=100.0)
    w = quiet_world("BT8", fs, remnant_rel=rel, remnant_corner_hz=corner, remnant_order=order)
    rec = simulate_trial(w, d, n_periods=4, run_in_s=5.0, seed=6)
    n = rec["true"]["remnant"][int(5 * fs) :]
    target = rel * 2.26
    # 400 s of a process with a 0.3 s correlation time: the variance is known to ≈ 4 %
    assert abs(n.var() / target**2 - 1) < 0.15
    f, p = welch(n, fs=fs, nperseg=4096)
    low = p[(f > 0.03) & (f < 0.1)].mean()
    at_corner = p[np.argmin(np.abs(f - corner))]
    at_4x = p[np.argmin(np.abs(f - 4 * corner))]
    np.testing.assert_allclose(at_corner / low, 0.5, rtol=0.3)  # −3 dB at the corner
    slope = 1 / (1 + 16) if order == 1 else 1 / (1 + 4**4)  # |H(4 f_c)|²
    np.testing.assert_allclose(at_4x / low, slope, rtol=0.4)


def test_a_steep_low_remnant_lowers_coherence_at_the_lowest_bands():
    """As in the paper: low coherence only at the lowest bands. Over two periods the excited
    bins sit on even DFT indices; the odd neighbours hold only remnant and sensor noise, so
    their power over the excited bins' power is the noise-to-signal ratio (1/coherence² − 1
    for small ratios). A second-order remnant at 0.05 Hz, twice the perturbation's SD."""
    fs = 250.0
    d = Multisine.design(18)  # the paper's 45 s period
    w = quiet_world("RT", fs, remnant_rel=2.0, remnant_corner_hz=0.05, remnant_order=2)
    rec = simulate_trial(w, d, run_in_s=3.0, seed=1)
    n = int(45 * fs)
    Y = np.fft.rfft(rec["wheel_angle_rad"][-2 * n :])
    k = 2 * d.bins
    nsr = 0.5 * (np.abs(Y[k - 1]) ** 2 + np.abs(Y[k + 1]) ** 2) / np.abs(Y[k]) ** 2
    f = d.frequencies_hz
    assert nsr[:4].mean() > 0.2  # the two lowest double bands
    assert nsr[(f > 2) & (f < 10)].max() < 0.05
    # the same world with the default remnant (0.25 × SD, 0.6 Hz, first order) stays coherent
    rec0 = simulate_trial(quiet_world("RT", fs, remnant_rel=0.25), d, run_in_s=3.0, seed=1)
    Y0 = np.fft.rfft(rec0["wheel_angle_rad"][-2 * n :])
    nsr0 = 0.5 * (np.abs(Y0[k - 1]) ** 2 + np.abs(Y0[k + 1]) ** 2) / np.abs(Y0[k]) ** 2
    assert nsr0[:4].mean() < 0.1


def test_multisine_design_follows_the_method():
    d = Multisine.design(19)
    assert len(d.bins) == 62 and np.all(d.bins[1::2] == d.bins[::2] + 1)  # 31 double bands
    assert d.frequencies_hz.max() == pytest.approx(20.0)
    fs = 100.0
    t = np.arange(int(45 * fs)) / fs
    x = d.value(t + 7.0)
    assert x.std() == pytest.approx(2.26, rel=1e-9)
    X = np.fft.rfft(x) / len(x) * 2
    power = np.abs(X) ** 2
    excited = np.zeros(len(power), bool)
    excited[d.bins] = True
    assert power[~excited].max() < 1e-20 * power.max()
    f = np.arange(len(power)) / 45.0
    full = power[excited & (f <= 0.7)]
    red = power[excited & (f > 0.7)]
    np.testing.assert_allclose(full, full[0])
    np.testing.assert_allclose(red / full[0], 0.1)
    # starting phase: value(t + offset) is the same signal shifted
    np.testing.assert_allclose(d.value(t + 45.0 + 7.0), x, atol=1e-9)


def test_sensor_noise_and_quantisation():
    d = Multisine.design(20, period_s=PERIOD)
    lsb_a, lsb_t = 2 * np.pi / 2**16, 0.01
    w = quiet_world("BT8", 200.0, angle_lsb_rad=lsb_a, torque_lsb_Nm=lsb_t, torque_noise_Nm=0.05)
    rec = simulate_trial(w, d, n_periods=1, run_in_s=1.0, seed=8)
    for c, lsb in (("wheel_angle_rad", lsb_a), ("driver_torque_Nm", lsb_t)):
        q = rec[c] / lsb
        np.testing.assert_allclose(q, np.round(q), atol=1e-6)
    # the torque noise is white with the requested SD (quantisation adds lsb²/12)
    e = rec["driver_torque_Nm"] - rec["true"]["Td"]
    assert e.std() == pytest.approx(np.sqrt(0.05**2 + lsb_t**2 / 12), rel=0.05)
    assert abs(np.corrcoef(e[:-1], e[1:])[0, 1]) < 0.05


def test_a_heavier_rig_changes_the_wheel_not_the_arm():
    """The rig's physical inertia enters the wheel equation (Table-1 residual grows as
    ΔI·ω²·θ) but not θ/T_d."""
    fs = 250.0
    d = Multisine.design(25, period_s=PERIOD)
    w = quiet_world("BT12", fs, wheel_inertia=0.4)
    rec = simulate_trial(w, d, run_in_s=2.0, n_periods=1, seed=9)
    f, H = csd_frf(rec, d, fs, n_periods=1)
    np.testing.assert_allclose(H[f < 5], admittance(w.arm, f[f < 5]), rtol=2e-3)
    n = int(PERIOD * fs)
    sp = {
        c: np.fft.rfft(rec[c][-n:])[d.bins]
        for c in ("perturbation_torque_Nm", "driver_torque_Nm", "wheel_angle_rad")
    }
    s = 2j * np.pi * f
    th = sp["wheel_angle_rad"]
    resid = (
        sp["perturbation_torque_Nm"] - sp["driver_torque_Nm"] - (I_W * s**2 + B_SW * s + K_SW) * th
    )
    u = sp["perturbation_torque_Nm"] - (B_SW * s + K_SW) * th
    zoh = (1 - np.exp(-s / fs)) / (s / fs)
    expected = (1 - zoh) * u + (0.4 - I_W) * s**2 * th
    np.testing.assert_allclose(resid, expected, rtol=0.01, atol=1e-3 * np.abs(u).max())


def _rec_spectra(rec, d, fs):
    n = int(round(d.period_s * fs))
    return {
        c: np.fft.rfft(rec[c][-n:])[d.bins]
        for c in ("perturbation_torque_Nm", "driver_torque_Nm", "wheel_angle_rad")
    }


@pytest.mark.parametrize("record_filter", ["none", "mean"])
def test_rig_loop_faster_than_the_recorder(record_filter):
    """The rig renders at 1 kHz, the recorder keeps 250 Hz: the hold is the 1 kHz one. With a
    boxcar recorder filter F (mean of the 4 cycles ending at the record instant) on angle and
    torque, but T_p recorded as commanded, θ/T_d is unchanged and the wheel residual becomes
    T_p (1 − F) + (1 − ZOH_1k)(F T_p − (b s + k) θ_rec)."""
    fs, m = 250.0, 4
    d = Multisine.design(26, period_s=PERIOD)
    w = quiet_world("BT12", fs, control_per_sample=m, record_filter=record_filter)
    rec = simulate_trial(w, d, run_in_s=2.0, n_periods=1, seed=10)
    assert len(rec["time_s"]) == int(12.0 * fs)
    sp = _rec_spectra(rec, d, fs)
    f = d.frequencies_hz
    s = 2j * np.pi * f
    H = sp["wheel_angle_rad"] / sp["driver_torque_Nm"]
    np.testing.assert_allclose(H, admittance(w.arm, f), rtol=2e-3)
    tp, td, th = sp["perturbation_torque_Nm"], sp["driver_torque_Nm"], sp["wheel_angle_rad"]
    resid = tp - td - (I_W * s**2 + B_SW * s + K_SW) * th
    hc = 1 / (fs * m)
    zoh = (1 - np.exp(-s * hc)) / (s * hc)
    F = (
        np.ones_like(s)
        if record_filter == "none"
        else np.exp(-s * hc * np.arange(m)[:, None]).mean(0)
    )
    expected = tp * (1 - F) + (1 - zoh) * (F * tp - (B_SW * s + K_SW) * th)
    np.testing.assert_allclose(resid, expected, rtol=0.01, atol=1e-3 * np.abs(tp).max())
    if record_filter == "none":  # 4× smaller than the 250 Hz rig's hold residual
        assert np.abs(resid / (tp - (B_SW * s + K_SW) * th))[-1] < 0.07
