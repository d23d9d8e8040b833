"""The loop's periodic steady state bin by bin (analysis.diagnosis.steady_state), checked
against the world's compiled kernel: the kernel, started from that steady state, must give
the same spectra to rounding, for every linear mechanism and form; its stability test must
agree with whether the kernel's simulation grows; and a model the route cannot take (limits
that clip, a perturbation that is not periodic, a nonlinear mechanism) is simulated.

The trials are the independent world's (benchmarks/otherworld.py, through the interchange
format), whose perturbation fades in over its first second."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from steerlab.analysis.diagnosis import simulate
from steerlab.analysis.diagnosis import steady_state as ss
from steerlab.analysis.diagnosis.data import prepare_study, transient_projector
from steerlab.benchmarks import _diagnose_otherworld as ow
from steerlab.hardware.safety import SafetyLimits
from steerlab.hardware.sim.mechanisms import (
    ActuatorLag,
    CoulombFriction,
    Mechanisms,
    ReflexDelay,
    StiffnessNonlinearity,
)
from steerlab.hardware.sim.physiology import ArmParams
from steerlab.protocols.datafile import load_study

ARM = ArmParams(I_i=0.08, b_i=1.5, k_i=300.0, b_c=3.0, k_c=400.0)

LINEAR = {
    "baseline": Mechanisms(),
    "reflex, 40 ms": Mechanisms(reflex_delay=ReflexDelay(k_p=8.0, k_v=1.5, delay_s=0.04)),
    "reflex, no delay, fast": Mechanisms(
        reflex_delay=ReflexDelay(
            k_p=5.0, k_v=1.0, delay_s=0.0, activation_hz=6.0, activation_zeta=1.0
        )
    ),  # fmt: skip
    "first-order lag": Mechanisms(actuator_lag=ActuatorLag(tau_s=0.012)),
    "second-order lag": Mechanisms(actuator_lag=ActuatorLag(tau_s=0.01, form="second_order")),
    "delay, a fraction": Mechanisms(actuator_lag=ActuatorLag(delay_s=0.013, form="delay")),
    "delay under a sample": Mechanisms(actuator_lag=ActuatorLag(delay_s=0.002, form="delay")),
    "viscous friction": Mechanisms(coulomb_friction=CoulombFriction(viscous_nms_per_rad=0.5)),
    "reflex and delayed motor and viscous": Mechanisms(
        reflex_delay=ReflexDelay(k_p=5.0, k_v=1.0, delay_s=0.06),
        actuator_lag=ActuatorLag(delay_s=0.009, form="delay"),
        coulomb_friction=CoulombFriction(viscous_nms_per_rad=0.3),
    ),
}


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    data = ow.make_study(tmp_path_factory.mktemp("ss") / "s", None, None, seed=3, small=True)
    t = prepare_study(load_study(data)).trials[0]
    # Steerlab's rig's limits, which the independent world's multisine (peak 7.8 N·m) stays
    # just clear of: the check on the command over a period is exercised.
    t.safety = SafetyLimits()
    return t


def _kernel(t, mech):
    """The kernel's spectra, simulated from the steady state (never the bin route)."""
    return simulate._spectra(t, simulate.simulate_trial(t, ARM, mech))


@pytest.mark.parametrize("name", list(LINEAR))
def test_bin_route_is_the_kernel_started_in_its_steady_state(trial, name):
    mech = LINEAR[name]
    pert = ss.perturbation(trial)
    assert pert is not None and 0 < pert.periodic_from < trial.start  # after the fade-in
    assert len(pert.driven) < len(trial.bins) // 10  # the multisine's lines only
    route = simulate._steady_spectra(trial, ARM, mech)
    assert route is not None, "a linear model clear of the limits takes the bin route"
    kernel = _kernel(trial, mech)
    assert np.max(np.abs(route - kernel)) < 1e-8 * np.max(np.abs(kernel))
    # And the kernel, started there, stays there: one period later it is where it began.
    out = simulate.simulate_trial(trial, ARM, mech)
    P = trial.stop - trial.start
    th = out["wheel_angle_rad"]
    m0 = pert.periodic_from
    assert np.max(np.abs(th[m0 + P : trial.n_sim] - th[m0 : trial.n_sim - P])) < 1e-9


def _growth(t, mech) -> float:
    """How much the kernel's response, simulated as the fit simulates it, grows from the
    second half of the run-in to the segment's last second."""
    th = simulate.simulate_trial(t, ARM, mech)["wheel_angle_rad"]
    fs = int(t.fs_hz)
    early = np.nanmax(np.abs(th[t.start // 2 : t.start]))
    late = np.max(np.abs(th[t.stop - fs : t.stop]))
    with np.errstate(invalid="ignore"):
        return float(late / early) if np.isfinite(late) else np.inf


LAGS = {
    "no lag": ActuatorLag(),
    "first order": ActuatorLag(tau_s=0.012),
    "second order": ActuatorLag(tau_s=0.01, form="second_order"),
    "delay": ActuatorLag(delay_s=0.013, form="delay"),
}


@pytest.mark.parametrize("lag", list(LAGS))
def test_stability_test_agrees_with_the_kernel(trial, lag):
    """The reflex gain where the closed-loop matrix's spectral radius crosses 1 (bisection),
    with each lag form's states in the loop: just below it the kernel's simulation stays
    bounded, just above it grows; the bin route refuses the unstable model, and its
    simulation starts from rest, not on the periodic orbit of an unstable loop (which it
    would never leave: rounding would be all that seeds the growing mode)."""

    def mech(k_p: float) -> Mechanisms:
        return Mechanisms(
            reflex_delay=ReflexDelay(k_p=k_p, k_v=0.0, delay_s=0.06), actuator_lag=LAGS[lag]
        )

    def radius(k_p: float) -> float:
        A = ss.closed_loop_matrix(ss.loop(trial, ARM, mech(k_p)))
        return float(np.max(np.abs(np.linalg.eigvals(A))))

    lo, hi = 0.0, 5000.0
    assert radius(lo) < 1.0 < radius(hi)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if radius(mid) < 1.0 else (lo, mid)
    stable, unstable = mech(0.97 * lo), mech(1.03 * hi)
    assert _growth(trial, stable) < 3.0
    assert _growth(trial, unstable) > 1e3
    assert ss.is_stable(ss.loop(trial, ARM, stable))
    assert not ss.is_stable(ss.loop(trial, ARM, unstable))
    # (Just below the boundary the resonance is so large that the steady state would pass
    # the soft angle limit: that model is simulated too.)
    assert simulate._steady_spectra(trial, ARM, unstable) is None
    assert simulate.steady_start(trial, ARM, unstable).steady is None
    assert simulate.steady_start(trial, ARM, stable).steady is not None


def test_an_unstable_loop_is_simulated_from_rest_not_on_its_orbit(trial):
    """The periodic orbit an unstable loop would have, against what the fit sees: far apart
    (the simulation from rest grows into the rig's limits)."""
    unstable = Mechanisms(reflex_delay=ReflexDelay(k_p=2000.0, delay_s=0.06))
    lp = ss.loop(trial, ARM, unstable)
    assert not ss.is_stable(lp)
    pert = ss.perturbation(trial)
    orbit = ss.spectra(trial, ss.steady_state(lp, pert), pert)
    with np.errstate(all="ignore"):
        fitted = simulate.simulated_spectra(trial, ARM, unstable)[:4]
        assert not np.linalg.norm(fitted - orbit) <= 0.5 * np.linalg.norm(orbit)


def test_limits_that_clip_send_the_model_to_the_simulation(trial):
    pert = ss.perturbation(trial)
    tight = replace(trial, safety=SafetyLimits(max_torque_nm=0.5 * pert.peak))
    assert simulate._steady_spectra(tight, ARM, Mechanisms()) is None
    clipped = simulate.simulated_spectra(tight, ARM, Mechanisms())
    free = simulate.simulated_spectra(trial, ARM, Mechanisms())
    # The simulation clips: its excited lines are smaller than the unclipped steady state's.
    lines = np.flatnonzero(trial.excited)
    assert np.sum(np.abs(clipped[2, lines])) < 0.97 * np.sum(np.abs(free[2, lines]))
    # A slew limit the multisine's steps exceed, likewise.
    slow = replace(trial, safety=SafetyLimits(max_slew_nm_per_s=0.5 * pert.peak_step * trial.fs_hz))
    assert simulate._steady_spectra(slow, ARM, Mechanisms()) is None
    # And a soft angle limit whose fade the steady state's angle would reach.
    near = replace(trial, safety=SafetyLimits(soft_angle_limit_deg=2.0, fade_zone_deg=1.0))
    assert simulate._steady_spectra(near, ARM, Mechanisms()) is None
    wide = replace(trial, safety=SafetyLimits(soft_angle_limit_deg=90.0, fade_zone_deg=10.0))
    assert simulate._steady_spectra(wide, ARM, Mechanisms()) is not None


def test_a_perturbation_that_is_not_periodic_is_simulated_from_rest(trial):
    noisy = replace(trial, tp=trial.tp + np.random.default_rng(1).normal(0, 0.01, len(trial.tp)))
    assert ss.perturbation(noisy) is None
    assert simulate._steady_spectra(noisy, ARM, Mechanisms()) is None
    out = simulate.simulate_trial(noisy, ARM, Mechanisms())
    assert np.all(np.isfinite(out["wheel_angle_rad"]))  # from the first sample


def test_nonlinear_models_are_simulated_from_their_linear_parts_steady_state(trial):
    cubic = Mechanisms(stiffness_nonlinearity=StiffnessNonlinearity(k3_nm_per_rad3=200.0))
    assert not ss.is_linear_time_invariant(cubic)
    assert simulate._steady_spectra(trial, ARM, cubic) is None
    # A vanishing cubic term is the baseline, simulated: the bin route's prediction.
    tiny = Mechanisms(stiffness_nonlinearity=StiffnessNonlinearity(k3_nm_per_rad3=1e-9))
    kernel = _kernel(trial, tiny)
    route = simulate._steady_spectra(trial, ARM, Mechanisms())
    assert np.max(np.abs(route - kernel)) < 1e-8 * np.max(np.abs(kernel))
    # Dry friction: its linear part keeps the viscous term.
    dry = CoulombFriction(torque_nm=0.1, viscous_nms_per_rad=0.4)
    part = ss.linear_part(Mechanisms(coulomb_friction=dry))
    assert part.coulomb_friction.torque_nm == 0.0
    assert part.coulomb_friction.viscous_nms_per_rad == 0.4


def test_transient_projection_is_a_least_squares_fit_per_band(trial):
    project = transient_projector(trial)
    rng = np.random.default_rng(0)
    v = rng.normal(size=(2, len(trial.bins))) + 1j * rng.normal(size=(2, len(trial.bins)))
    expected = v.copy()
    for b in range(trial.n_bands):
        idx = np.flatnonzero(trial.band == b)
        A = np.vander(trial.bins[idx].astype(float), 2, increasing=True)
        for r in range(2):
            coef, *_ = np.linalg.lstsq(A, v[r, idx], rcond=None)
            expected[r, idx] -= A @ coef
    assert np.max(np.abs(project(v) - expected)) < 1e-12
