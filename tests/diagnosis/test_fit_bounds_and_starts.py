"""Two things a fit must not do at the edges of its space (``analysis.diagnosis.fit``):

- step along a bound as if it were not there: a mechanism coordinate at its bound whose step
  points out of it is held there, and the other coordinates' step is the one the bound
  leaves (checked against scipy's bounded least squares);
- start a trial where the loop is unstable while a stable start exists: every unstable start
  costs the same, so a fit from there has no slope, stops at once and calls itself converged.

The trials are the independent world's (benchmarks/otherworld.py, through the interchange
format)."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from steerlab.analysis.diagnosis import engine, simulate
from steerlab.analysis.diagnosis import steady_state as ss
from steerlab.analysis.diagnosis.candidates import CANDIDATES, candidate
from steerlab.analysis.diagnosis.data import prepare_study
from steerlab.analysis.diagnosis.fit import (
    ARM_BOUNDS,
    ModelSpec,
    _bounded_step,
    best_start_arms,
    evaluate_cost,
    is_unstable_cost,
    noise_model,
    steps_are_simulated,
)
from steerlab.benchmarks import _diagnose_otherworld as ow
from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.hardware.sim.physiology import ArmParams
from steerlab.protocols.datafile import load_study


def _quadratic(seed: int, n: int = 3):
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(20, n))
    J[:, 1] += 0.9 * J[:, 0]  # correlated coordinates: a clipped step is wrong in the other
    r = rng.normal(size=20)
    return J, r


@pytest.mark.parametrize("seed", range(6))
def test_a_step_out_of_a_bound_holds_that_coordinate_and_solves_for_the_others(seed):
    """Coordinate 0 sits at its lower bound 0 and the unconstrained Gauss-Newton step would
    take it below: the step must be scipy's bounded least-squares solution of the same
    quadratic model, and better than the unconstrained step clipped afterwards."""
    J, r = _quadratic(seed)
    free = np.linalg.lstsq(J, -r, rcond=None)[0]
    if free[0] > 0:  # make the bound bind: the same problem mirrored in coordinate 0
        J[:, 0] = -J[:, 0]
        free = np.linalg.lstsq(J, -r, rcond=None)[0]
    assert free[0] < 0
    x = np.zeros(3)
    specs = [SimpleNamespace(lower=0.0, upper=5.0)] + [
        SimpleNamespace(lower=-np.inf, upper=np.inf)
    ] * 2
    dx = _bounded_step(J.T @ J, J.T @ r, x, specs, n_m=3)
    ref = lsq_linear(J, -r, bounds=([0.0, -np.inf, -np.inf], [5.0, np.inf, np.inf]), tol=1e-12)
    assert ref.success
    assert dx[0] == 0.0
    np.testing.assert_allclose(dx, ref.x, atol=1e-9)

    def cost(d):
        return float(np.sum((J @ d + r) ** 2))

    clipped = np.concatenate([[0.0], free[1:]])
    assert cost(dx) < cost(clipped) - 1e-6


@pytest.mark.parametrize("seed", range(12))
def test_with_several_coordinates_at_bounds_the_step_is_the_bounded_minimum(seed):
    """Coordinates 0 and 1 (correlated) at their lower bounds, 2 at its upper: whichever of
    them the bounded minimum holds, the step is scipy's bounded least-squares solution.
    (Holding each one whose free step points out of its bound is not enough: with the
    coupling, a coordinate's free step can point out while the minimum leaves it inwards.)"""
    rng = np.random.default_rng(100 + seed)
    J = rng.normal(size=(20, 4))
    J[:, 1] += 0.95 * J[:, 0]
    r = rng.normal(size=20)
    x = np.array([0.0, 0.0, 1.0, 0.0])
    specs = [
        SimpleNamespace(lower=0.0, upper=5.0),
        SimpleNamespace(lower=0.0, upper=5.0),
        SimpleNamespace(lower=-5.0, upper=1.0),
        SimpleNamespace(lower=-np.inf, upper=np.inf),
    ]
    dx = _bounded_step(J.T @ J, J.T @ r, x, specs, n_m=4)
    lo = [s.lower - xi for s, xi in zip(specs, x, strict=True)]
    hi = [s.upper - xi for s, xi in zip(specs, x, strict=True)]
    ref = lsq_linear(J, -r, bounds=(lo, hi), tol=1e-12)
    assert ref.success
    # (scipy's minimum here never reaches the far bounds, which the step does not know of.)
    assert np.all((ref.x > np.array(lo) + 1e-6) | (np.array(lo) > -1e-12))
    np.testing.assert_allclose(dx, ref.x, atol=1e-8)


def test_a_step_that_leaves_a_bound_inwards_is_free():
    J, r = _quadratic(0)
    free = np.linalg.lstsq(J, -r, rcond=None)[0]
    x = np.zeros(3)
    # The bound on the side the step moves away from: nothing is held.
    lower = 0.0 if free[0] > 0 else -np.inf
    upper = np.inf if free[0] > 0 else 0.0
    specs = [SimpleNamespace(lower=lower, upper=upper)] + [
        SimpleNamespace(lower=-np.inf, upper=np.inf)
    ] * 2
    np.testing.assert_allclose(_bounded_step(J.T @ J, J.T @ r, x, specs, n_m=3), free)


# -- starts -----------------------------------------------------------------------------------
PLAUSIBLE = ArmParams(I_i=0.08, b_i=1.5, k_i=300.0, b_c=3.0, k_c=400.0)
# An arm in a corner (intrinsic damping at the top of its range, 10³ N·m·s/rad) whose loop
# stays stable with a reflex that makes the plausible arm's loop unstable.
CORNER = replace(PLAUSIBLE, b_i=1e3)


@pytest.fixture(scope="module")
def trials(tmp_path_factory):
    data = ow.make_study(tmp_path_factory.mktemp("st") / "s", None, None, seed=3, small=True)
    return prepare_study(load_study(data)).trials[:1]


def _reflex_spec(fs: float) -> ModelSpec:
    family = candidate("reflex_delay")
    form = next(f for f in family.forms if "40 ms" in f.name)
    return ModelSpec(Mechanisms(), (family.with_form(form),), fs)


def _unstable_for_plausible_only(trials, spec) -> np.ndarray:
    """Reflex coordinates (k_p, k_v) with the plausible arm's loop unstable and the corner
    arm's stable (bisection on the velocity gain k_v at the plausible arm's boundary)."""
    t = trials[0]

    def stable(arm, k_v):
        return ss.is_stable(ss.loop(t, arm, spec.mechanisms(np.array([0.0, k_v]))))

    lo, hi = 0.0, 30.0
    assert stable(PLAUSIBLE, lo) and not stable(PLAUSIBLE, hi)
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stable(PLAUSIBLE, mid) else (lo, mid)
    k_v = 1.05 * hi
    assert not stable(PLAUSIBLE, k_v) and stable(CORNER, k_v)
    return np.array([0.0, k_v])


def test_a_stable_arm_in_a_corner_is_started_from_rather_than_an_unstable_plausible_one(trials):
    t = trials[0]
    spec = _reflex_spec(t.fs_hz)
    x = _unstable_for_plausible_only(trials, spec)
    noise = noise_model(trials, {t.label: simulate.simulated_spectra(t, PLAUSIBLE, Mechanisms())})
    with np.errstate(all="ignore"):
        plausible, corner = {t.label: PLAUSIBLE}, {t.label: CORNER}
        assert is_unstable_cost(evaluate_cost(trials, spec, noise, plausible, x)[t.label])
        assert not is_unstable_cost(evaluate_cost(trials, spec, noise, corner, x)[t.label])
        assert best_start_arms(trials, spec, noise, [plausible], x=x)[t.label] is PLAUSIBLE
        chosen = best_start_arms(trials, spec, noise, [plausible], x=x, last_resort=corner)
        assert chosen[t.label] is CORNER
        # Where the plausible arm's loop is stable, the corner is not taken.
        calm = np.array([0.0, 0.5 * x[1]])
        chosen = best_start_arms(trials, spec, noise, [plausible], x=calm, last_resort=corner)
        assert chosen[t.label] is PLAUSIBLE


def test_a_corner_is_not_left_for_a_start_whose_loop_is_unstable(trials, monkeypatch):
    """``_out_of_corners`` re-fits from plausible arms; where that start's loop diverges, it
    keeps the fit it has without running a fit that could only stop at once."""
    t = trials[0]
    spec = _reflex_spec(t.fs_hz)
    x = _unstable_for_plausible_only(trials, spec)
    noise = noise_model(trials, {t.label: simulate.simulated_spectra(t, PLAUSIBLE, Mechanisms())})
    monkeypatch.setattr(engine, "plausible_arm", lambda t_, model_baseline=None: PLAUSIBLE)
    assert engine._degenerate(CORNER)

    def no_fit(*args, **kwargs):
        raise AssertionError("fitted from a start whose loop is unstable")

    monkeypatch.setattr(engine, "fit_model", no_fit)
    fit = SimpleNamespace(arms={t.label: CORNER}, x=x)
    with np.errstate(all="ignore"):
        assert engine._out_of_corners(trials, spec, noise, fit, {}) is fit


def test_a_corner_is_left_for_a_start_whose_loop_is_stable(trials, monkeypatch):
    """The other side: with the reflex off, the plausible start is stable, and the fit from
    there is run."""
    t = trials[0]
    spec = _reflex_spec(t.fs_hz)
    noise = noise_model(trials, {t.label: simulate.simulated_spectra(t, PLAUSIBLE, Mechanisms())})
    monkeypatch.setattr(engine, "plausible_arm", lambda t_, model_baseline=None: PLAUSIBLE)
    started: list = []

    def fit(trials_, spec_, noise_, arms0, x0=None, **kwargs):
        started.append(arms0[t.label])
        return SimpleNamespace(m2ll=np.inf)

    monkeypatch.setattr(engine, "fit_model", fit)
    corner = SimpleNamespace(arms={t.label: CORNER}, x=np.zeros(2), m2ll=1.0)
    assert engine._out_of_corners(trials, spec, noise, corner, {}) is corner
    assert started == [PLAUSIBLE]


def test_a_candidates_full_fit_that_ends_in_a_corner_is_taken_out_of_it(trials, monkeypatch):
    """A family's best form gets a full fit after its screening; where that fit ends with an
    arm at a bound, the fit from a plausible arm (``_out_of_corners``) must replace it. On the
    independent world's second-order lag study the full fit ended with three trials' arms at
    bounds, 1 000 units of −2 log L above the fit from plausible arms, and the next step's
    candidates all "improved" on it by that much. Here the real full fit is moved to a corner
    (its cost recomputed there), the one fault injected."""
    t = trials[0]
    noise = noise_model(trials, {t.label: simulate.simulated_spectra(t, PLAUSIBLE, Mechanisms())})
    spec0 = ModelSpec(Mechanisms(), (), t.fs_hz)
    base = engine.fit_model(trials, spec0, noise, {t.label: PLAUSIBLE})
    current = engine.Current(spec0, base, [], [])
    setup = SimpleNamespace(trials=trials, noise=noise)
    real_fit = engine.fit_model
    cornered: list = []

    def full_fit_in_a_corner(trials_, spec, noise_, arms0, **kwargs):
        fit = real_fit(trials_, spec, noise_, arms0, **kwargs)
        if "max_iter" in kwargs or cornered:  # screening fits, and the way out of the corner
            return fit
        arms = {t.label: CORNER}
        cornered.append(
            replace(fit, arms=arms, cost_trial=evaluate_cost(trials_, spec, noise_, arms, fit.x))
        )
        return cornered[0]

    monkeypatch.setattr(engine, "fit_model", full_fit_in_a_corner)
    r = engine.evaluate_candidate(setup, current, "actuator_lag", 1)
    assert cornered, "the family's full fit was not run"
    assert not engine._degenerate(r.fit.arms[t.label]), r.fit.arms
    assert r.fit.m2ll < cornered[0].m2ll


NONLINEAR_FAMILIES = {"coulomb_friction", "stiffness_nonlinearity", "grip_scheduled_stiffness"}


@pytest.mark.parametrize(
    ("name", "form"),
    [(c.name, f.name) for c in CANDIDATES for f in c.forms],
)
def test_a_fits_steps_are_simulated_exactly_for_the_nonlinear_families(name, form):
    """A fit on an approximate slope gets two tries per iteration where each try is a
    simulation, eight where tries take the bin route. The families start "off" (a friction of
    0 N·m), where every model is linear: judged there, the rule gave eight tries to every
    family (the first reading of this change ran its benchmark so)."""
    family = candidate(name)
    spec = ModelSpec(
        Mechanisms(), (family.with_form(next(f for f in family.forms if f.name == form)),), 250.0
    )
    x = spec.clip(spec.start())
    assert not steps_are_simulated(spec, x, 0)  # mechanisms held where they start: off
    assert steps_are_simulated(spec, x, spec.n_free) == (name in NONLINEAR_FAMILIES)
    # The same once the family is on (as where a later step re-fits it).
    on = spec.clip(x + np.array([p.step for p in spec.specs()]))
    assert steps_are_simulated(spec, on, spec.n_free) == (name in NONLINEAR_FAMILIES)


# -- a subject's whole fit in corners ---------------------------------------------------------
@pytest.fixture(scope="module")
def two_subjects(tmp_path_factory):
    """The independent world's null study, two subjects × PT, one period per trial."""
    from steerlab.benchmarks.otherworld import generate_study
    from steerlab.protocols.interchange import import_study

    root = tmp_path_factory.mktemp("two")
    generate_study(root / "csv", seed=5, mechanisms=[], **{**ow.SMALL_STUDY, "subjects": 2})
    import_study(root / "csv", root / "s")
    return prepare_study(load_study(root / "s")).trials


@pytest.mark.parametrize("inertia", ["a quarter", "at its upper bound"])
def test_a_subject_whose_whole_fit_collapsed_restarts_from_the_others_arms(
    two_subjects, monkeypatch, inertia
):
    """Where every trial of a subject ends in a corner and its inertia has gone with them, the
    way out starts from the arms the other subjects' trials of the condition fitted, with the
    data's inertia. On the independent world's sensor-delay study one subject collapsed this
    way (I_i a quarter of the data's), on its actuator-lag study one at I_i's upper bound; the
    first's FRF fits had run into bounds, so its plausible arms were far from the data, and
    from those no fit got out. Here the collapse is the fault injected into a good fit, and
    the plausible arm is a far one."""
    trials = two_subjects
    spec = ModelSpec(Mechanisms(), (), trials[0].fs_hz)
    ref = {t.label: simulate.simulated_spectra(t, PLAUSIBLE, Mechanisms()) for t in trials}
    noise = noise_model(trials, ref)
    good = engine.fit_model(trials, spec, noise, {t.label: t.arm_cell for t in trials})
    assert not any(engine._degenerate(a) for a in good.arms.values()), good.arms
    first = trials[0].subject
    top = ARM_BOUNDS["I_i"][1]
    arms = {
        t.label: replace(a, I_i=a.I_i / 4 if inertia == "a quarter" else top, b_i=1e3, k_i=1e5)
        if t.subject == first
        else a
        for t, a in ((t, good.arms[t.label]) for t in trials)
    }
    collapsed = replace(
        good, arms=arms, cost_trial=evaluate_cost(trials, spec, noise, arms, good.x)
    )
    assert collapsed.m2ll > good.m2ll
    far = ArmParams(I_i=0.1, b_i=1.0, k_i=13.0, b_c=2.6, k_c=100.0)  # a BT12-like arm
    monkeypatch.setattr(engine, "plausible_arm", lambda t, model_baseline=None: far)
    out = engine._out_of_corners(trials, spec, noise, collapsed, {})
    assert not any(engine._degenerate(a) for a in out.arms.values()), out.arms
    assert out.m2ll < good.m2ll + 1.0, (out.m2ll, good.m2ll)
    np.testing.assert_allclose(out.inertia[first], good.inertia[first], rtol=0.05)


def test_every_subject_collapsed_restarts_from_plausible_arms_with_the_datas_inertia(
    two_subjects,
):
    """Where every subject's fit collapsed there are no other arms to start from: the
    plausible ones are, with the data's inertia, not the collapsed one (on the independent
    world's pure-delay lag every trial of a subject ended at I_i = 10 kg·m², the bound)."""
    trials = two_subjects
    spec = ModelSpec(Mechanisms(), (), trials[0].fs_hz)
    ref = {t.label: simulate.simulated_spectra(t, PLAUSIBLE, Mechanisms()) for t in trials}
    noise = noise_model(trials, ref)
    good = engine.fit_model(trials, spec, noise, {t.label: t.arm_cell for t in trials})
    top = ARM_BOUNDS["I_i"][1]
    arms = {t.label: replace(good.arms[t.label], I_i=top, b_i=1e3, k_i=1e5) for t in trials}
    collapsed = replace(
        good, arms=arms, cost_trial=evaluate_cost(trials, spec, noise, arms, good.x)
    )
    out = engine._out_of_corners(trials, spec, noise, collapsed, {})
    assert not any(engine._degenerate(a) for a in out.arms.values()), out.arms
    assert out.m2ll < good.m2ll + 1.0, (out.m2ll, good.m2ll)
