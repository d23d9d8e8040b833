"""What the forward selection leaves out to save time, and that it leaves out nothing else.

Three rules (``analysis.diagnosis.engine``):

- the held-out folds of a step run in order of the candidates' in-sample gain, and a
  candidate whose in-sample gain times ``HELD_OUT_SKIP_RATIO`` is below a retainable
  candidate's held-out gain is not tried held out (``_held_out_stage``);
- at a later step, a family is screened first in its first step's best form, and in its
  other forms only if that form improves −2 log L by ``RETRY_MIN_DELTA_M2LL`` or more
  (``evaluate_candidate``);
- the linear families are fitted first, and a simulated family whose forms' screening gains
  less than ``1/FULL_FIT_RATIO`` of the best linear family's gain (far from the noise floor)
  is not fitted fully unless the held-out stage could still choose it (``select``,
  ``_held_out_stage``).

The fits are replaced by stand-ins with chosen −2 log L, so the rules are checked exactly; the
studies of ``test_diagnosis_otherworld.py`` and ``benchmarks/diagnose`` check them on real
fits.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import multiprocessing.connection as mp_connection
import signal
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from steerlab.analysis.diagnosis import engine
from steerlab.analysis.diagnosis.candidates import candidate
from steerlab.analysis.diagnosis.engine import (
    HELD_OUT_SKIP_RATIO,
    RETRY_MIN_DELTA_M2LL,
    CandidateResult,
    Current,
    judge,
)
from steerlab.analysis.diagnosis.fit import FitResult, ModelSpec
from steerlab.hardware.sim.mechanisms import Mechanisms


def _fit(name: str | None, m2ll: float, se: float = 1e-3) -> FitResult:
    free = () if name is None else (candidate(name),)
    spec = ModelSpec(Mechanisms(), free, 250.0)
    # Parameters 10 standard errors (se = 1e-3) from "off": they stand out (robust z > 3).
    return FitResult(spec=spec, x=spec.start() + 0.01, cov=np.eye(spec.n_free) * se**2, arms={},
                     cost_trial={"t": m2ll / 2.0}, simulated={}, n_obs=10_000, iterations=3,
                     converged=True, lack_of_fit=1.0)  # fmt: skip


def _result(name: str, gain: float, se: float = 1e-3) -> CandidateResult:
    # ΔBIC well below −MIN_DBIC for every gain used here.
    return CandidateResult(name, 1, _fit(name, 1e6 - gain, se), gain, -gain + 20.0, None)


def _stage(results, held_out: dict[str, float], executor=None, late=False) -> list[str]:
    """Run the held-out stage with each candidate's held-out gain given; return the order in
    which the candidates' folds were computed. ``late``: the time limit is already reached."""
    current = Current(_fit(None, 1e6).spec, _fit(None, 1e6), [np.zeros(0)] * 2, [0.0, 0.0])
    setup = SimpleNamespace(folds=[((), ()), ((), ())])
    asked: list[str] = []

    def fold(setup_, current_, r, i):
        if i == 0:  # a candidate's folds run as separate tasks: named once
            asked.append(r.name)
        g = held_out[r.name]
        return np.zeros(1), -g / 2, {f"{i}:t": -g / 2}

    def wait(futs):
        if late:  # as select's wait at the limit: nothing more done, the rest pending
            return set(), set(futs)
        return cf.wait(futs)

    undone: list[str] = []
    mp = pytest.MonkeyPatch()
    mp.setattr(engine, "held_out_fold", fold)
    try:
        engine._held_out_stage(
            setup, current, results, 1, executor, setup, False, lambda: late, wait, undone
        )
    finally:
        mp.undo()
    assert undone == [] if not late else len(undone) == 2
    judge(results, held_out=True)
    return asked


@pytest.mark.parametrize("threads", [False, True])
def test_a_candidate_far_below_anothers_held_out_gain_is_not_tried_held_out(threads):
    best = _result("sensor_delay", 4_000_000.0)
    close = _result("actuator_lag", 1_100_000.0)  # × 4 = 4.4 M: above 4.0 M, tried
    far = _result("reflex_delay", 96_000.0)  # × 4 far below: not tried
    held_out = {"sensor_delay": 4_000_000.0, "actuator_lag": 1_000_000.0, "reflex_delay": 1e9}
    results = [far, close, best]
    if threads:
        with cf.ThreadPoolExecutor(2) as ex:
            asked = _stage(results, held_out, ex)
    else:
        asked = _stage(results, held_out)
    # The largest in-sample gain first, then those that could still reach it.
    assert asked[0] == "sensor_delay" and sorted(asked) == ["actuator_lag", "sensor_delay"]
    assert best.passed and close.held_out_gain == 1_000_000.0
    assert far.held_out_gain is None and not far.passed
    assert far.held_out_skipped == 4_000_000.0
    assert "not tried on held-out data" in far.reason
    assert far.to_dict()["held_out_not_tried_below"] == 4_000_000.0
    assert HELD_OUT_SKIP_RATIO * far.delta_m2ll < best.held_out_gain


def test_a_held_out_gain_that_cannot_be_retained_leaves_the_others_tried():
    # The largest held-out gain belongs to a candidate whose parameter does not stand out
    # (robust z ≤ 3): it cannot be retained, so it does not spare anyone their folds.
    vague = _result("sensor_delay", 4_000_000.0, se=1.0)
    small = _result("reflex_delay", 96_000.0)
    asked = _stage([vague, small], {"sensor_delay": 4e6, "reflex_delay": 90_000.0})
    assert asked == ["sensor_delay", "reflex_delay"]
    assert not vague.passed and small.passed and small.held_out_gain == 90_000.0


def _evaluate(monkeypatch, first_form: str | None, first_gain: float) -> list[str]:
    """evaluate_candidate of the reflex family with every form's fit a stand-in: the form
    ``first_form`` (or the first) gains ``first_gain``, the others 100. Returns the forms
    fitted, in order."""
    fam = candidate("reflex_delay")
    first = first_form or fam.forms[0].name
    gains = {f.name: first_gain if f.name == first else 100.0 for f in fam.forms}
    log = _screened("reflex_delay", gains, monkeypatch)
    current = Current(_fit(None, 1e6).spec, _fit(None, 1e6), [], [])
    setup = SimpleNamespace(trials=[], noise={}, folds=[])
    r = engine.evaluate_candidate(setup, current, "reflex_delay", 2, first_form)
    tried = [f for f in log if f != "full"]
    assert r.only_first_form == (len(tried) == 1)
    return tried


def test_a_later_step_tries_the_other_forms_only_if_the_first_steps_form_helps(monkeypatch):
    forms = [f.name for f in candidate("reflex_delay").forms]
    first = forms[5]
    # It improves nothing: the family is judged in that form alone.
    assert _evaluate(monkeypatch, first, RETRY_MIN_DELTA_M2LL - 1.0) == [first]
    # It improves: every form is screened, the first step's first.
    tried = _evaluate(monkeypatch, first, RETRY_MIN_DELTA_M2LL + 1.0)
    assert tried[0] == first and sorted(tried) == sorted(forms)
    # At the first step (no earlier form) every form is screened, whatever the first gives.
    assert sorted(_evaluate(monkeypatch, None, 0.0)) == sorted(forms)


@pytest.mark.parametrize("threads", [False, True])
def test_candidates_the_time_limit_left_without_their_held_out_check_say_so(threads):
    results = [_result("sensor_delay", 4e6), _result("actuator_lag", 3e6)]
    held_out = {"sensor_delay": 4e6, "actuator_lag": 3e6}
    if threads:
        with cf.ThreadPoolExecutor(2) as ex:
            _stage(results, held_out, ex, late=True)
    else:
        _stage(results, held_out, late=True)
    for r in results:
        assert r.held_out_undone and r.held_out_gain is None and not r.passed
        assert "time limit" in r.reason


def _burn(seconds: float) -> float:
    t0 = time.process_time()
    while time.process_time() - t0 < seconds:
        pass
    return seconds


def _busy_pool(fn, *args) -> tuple[cf.ProcessPoolExecutor, list]:
    pool = cf.ProcessPoolExecutor(1)
    fut = pool.submit(fn, *args)
    t0 = time.monotonic()
    while not fut.running() and time.monotonic() - t0 < 30:
        time.sleep(0.05)
    procs = list(pool._processes.values())
    assert procs
    return pool, procs


def _assert_ended(procs) -> None:
    # The sentinel, not join/is_alive: the pool's own thread reaps the worker too, and
    # is_alive reads a child reaped by another thread as alive.
    for p in procs:
        assert mp_connection.wait([p.sentinel], 10), f"worker {p.pid} still running"


def test_abandoning_our_own_pool_stops_its_busy_workers():
    # At the time limit with --jobs > 1 the fits still running are stopped, not waited for.
    pool, procs = _busy_pool(_burn, 60.0)
    engine._abandon(pool)
    _assert_ended(procs)


def _burn_deaf_to_sigterm(seconds: float, ready: str) -> float:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    open(ready, "w").close()
    return _burn(seconds)


def test_a_worker_that_outlives_its_grace_is_killed(tmp_path):
    ready = tmp_path / "deaf"
    pool, procs = _busy_pool(_burn_deaf_to_sigterm, 60.0, str(ready))
    t0 = time.monotonic()
    while not ready.exists() and time.monotonic() - t0 < 30:
        time.sleep(0.05)
    assert ready.exists()
    engine._abandon(pool, grace_s=0.5)
    _assert_ended(procs)


def test_a_later_step_tries_only_what_improved_the_step_before():
    """Improved the first step by much and the second by nothing: not tried at the third."""
    names = ["reflex_delay", "actuator_lag", "stiffness_nonlinearity", "sensor_delay"]
    step1 = [_result(n, 1000.0) for n in names]
    step2 = [
        _result("reflex_delay", 0.07),
        _result("actuator_lag", RETRY_MIN_DELTA_M2LL - 1.0),
        _result("stiffness_nonlinearity", 19.0),
    ]  # sensor_delay retained at step 1: not in step 2
    assert engine.retried(names, []) == names
    assert engine.retried(names[:3], [step1]) == names[:3]
    assert engine.retried(names[:3], [step1, step2]) == ["stiffness_nonlinearity"]
    # A name the step before did not try (dropped earlier) stays dropped.
    assert engine.retried(["coulomb_friction"], [step1, step2]) == []


# -- the full fit of a simulated family far below the best linear one ---------------------------
def _screened(name: str, gains: dict[str, float], monkeypatch) -> list[str]:
    """Stand-ins for the forms' screening (form → gain) and the full fit (the best form's
    gain × 2); returns a log of the fits: the forms screened, then "full"."""
    log: list[str] = []

    def fit_form(setup, current_, cand, max_iter=engine.MAX_ITER):
        log.append(cand.form.name)
        f = _fit(name, 1e6 - gains[cand.form.name])
        return FitResult(**{**f.__dict__, "spec": ModelSpec(Mechanisms(), (cand,), 250.0)})

    def full(trials, spec, noise, arms, x0, **opts):
        # A candidate's full fit, far from the floor, stops relative to its misfit.
        assert opts == {"relative_stop": True}
        log.append("full")
        f = _fit(name, 1e6 - 2.0 * gains[spec.free[0].form.name])
        return FitResult(**{**f.__dict__, "spec": spec})

    monkeypatch.setattr(engine, "_fit_form", fit_form)
    monkeypatch.setattr(engine, "fit_model", full)
    return log


def test_a_simulated_family_far_below_the_best_linear_one_is_not_fitted_fully(monkeypatch):
    forms = [f.name for f in candidate("coulomb_friction").forms]
    gains = dict(zip(forms, [30_000.0, 50_000.0, 40_000.0], strict=True))
    log = _screened("coulomb_friction", gains, monkeypatch)
    current = Current(_fit(None, 1e6).spec, _fit(None, 1e6), [], [])
    setup = SimpleNamespace(trials=[], noise={}, folds=[((), ())])

    # Its best screening (50 000) below the threshold: every form screened, no full fit.
    r = engine.evaluate_candidate(setup, current, "coulomb_friction", 1, None, 60_000.0)
    assert log == forms
    assert r.full_fit_skipped == 60_000.0 and r.delta_m2ll == 50_000.0
    assert r.form == forms[1] and r.to_dict()["full_fit_not_done_below"] == 60_000.0
    judge([r], held_out=True)
    assert "fitted only as far as its forms' screening" in r.reason

    # Completed later, it is what an evaluation without the threshold gives.
    full = engine.complete_full_fit(setup, current, r)
    log.clear()
    plain = engine.evaluate_candidate(setup, current, "coulomb_friction", 1, None, None)
    assert log == [*forms, "full"]
    assert full.full_fit_skipped is None and plain.full_fit_skipped is None
    assert full.delta_m2ll == plain.delta_m2ll == 100_000.0
    assert full.delta_bic == plain.delta_bic and full.form_m2ll == plain.form_m2ll

    # At or above the threshold: fitted fully.
    log.clear()
    r = engine.evaluate_candidate(setup, current, "coulomb_friction", 1, None, 50_000.0)
    assert log == [*forms, "full"] and r.full_fit_skipped is None


def _select_order(monkeypatch, gains: dict[str, float], folds: bool) -> list[tuple]:
    """select() with stand-in evaluations (name → gain), none retained; returns the
    evaluations in order as (name, full_fit_below)."""
    calls: list[tuple] = []

    def evaluate(setup, current, name, step, first_form=None, full_fit_below=None):
        calls.append((name, full_fit_below))
        return _result(name, gains[name])

    base = _fit(None, 1e6)
    monkeypatch.setattr(engine, "evaluate_candidate", evaluate)
    monkeypatch.setattr(engine, "make_current", lambda s, spec, fit, *a: Current(spec, fit, [], []))
    monkeypatch.setattr(engine, "_held_out_stage", lambda setup, cur, res, step, ex, *a: ex)
    monkeypatch.setattr(engine, "judge", lambda results, held_out: None)  # none passes
    setup = SimpleNamespace(folds=[((), ())] if folds else [], spec=lambda: base.spec, base=base)
    sel = engine.select(setup, list(gains), jobs=1)
    assert [r.name for r in sel.steps[0]] == list(gains)  # reported in the pool's order
    return calls


def test_the_linear_families_are_fitted_first_and_set_the_simulated_ones_threshold(monkeypatch):
    gains = {"reflex_delay": 98_000.0, "coulomb_friction": 2.6e6,
             "stiffness_nonlinearity": 1e5, "actuator_lag": 3.0e6, "sensor_delay": 4.4e6,
             "grip_scheduled_stiffness": 600.0}  # fmt: skip
    linear = {"reflex_delay", "actuator_lag", "sensor_delay"}
    assert {n for n in gains if engine.is_linear_family(n)} == linear
    calls = _select_order(monkeypatch, gains, folds=True)
    assert {n for n, _ in calls[:3]} == linear and all(b is None for _, b in calls[:3])
    assert [b for _, b in calls[3:]] == [4.4e6 / engine.FULL_FIT_RATIO] * 3

    # Near the noise floor (the leader's fraction below FULL_FIT_MIN_M2LL) every family is
    # fitted fully, and so it is without a held-out check.
    near = {**gains, "sensor_delay": engine.FULL_FIT_RATIO * engine.FULL_FIT_MIN_M2LL - 1.0,
            "actuator_lag": 10.0, "reflex_delay": 98.0}  # fmt: skip
    assert all(b is None for _, b in _select_order(monkeypatch, near, folds=True))
    calls = _select_order(monkeypatch, gains, folds=False)
    assert [n for n, _ in calls] == list(gains) and all(b is None for _, b in calls)


def _pooled_step(monkeypatch, gains: dict[str, float], executor) -> tuple[list, list[str]]:
    """select()'s first step with stand-in fits (a form's screening gains ``gains[form]``,
    or the family's gain where it has one form; a full fit twice its screening), none
    retained; returns the step's candidates and the fits in the order they ran."""
    ran: list[str] = []

    def fit_form(setup, current_, cand, max_iter=engine.MAX_ITER):
        ran.append(f"{cand.name}:{cand.form.name}")
        time.sleep(0.002)  # let the two workers' fits interleave
        f = _fit(cand.name, 1e6 - gains.get(cand.form.name, gains.get(cand.name, 0.0)))
        return FitResult(**{**f.__dict__, "spec": ModelSpec(Mechanisms(), (cand,), 250.0)})

    def full(setup, screened, relative_stop=True):
        ran.append(f"{screened.spec.free[0].name}:full")
        gain = 2.0 * (1e6 - screened.m2ll)
        return FitResult(**{**screened.__dict__, "cost_trial": {"t": (1e6 - gain) / 2.0}})

    base = _fit(None, 1e6)
    monkeypatch.setattr(engine, "_fit_form", fit_form)
    monkeypatch.setattr(engine, "_full_fit", full)
    monkeypatch.setattr(engine, "make_current", lambda s, spec, fit, *a: Current(spec, fit, [], []))
    monkeypatch.setattr(engine, "_held_out_stage", lambda setup, cur, res, step, ex, *a: ex)
    monkeypatch.setattr(engine, "judge", lambda results, held_out: None)  # none passes
    monkeypatch.setattr(engine, "share", lambda ex, value: value)  # threads share the set-up
    setup = SimpleNamespace(folds=[((), ())], spec=lambda: base.spec, base=base)
    families = ["reflex_delay", "coulomb_friction", "actuator_lag", "stiffness_nonlinearity",
                "sensor_delay", "grip_scheduled_stiffness"]  # fmt: skip
    sel = engine.select(setup, families, executor=executor)
    return sel.steps[0], ran


def test_a_pool_runs_the_forms_of_a_family_as_tasks_with_the_sequential_results(monkeypatch):
    # Every family's forms (the linear families first, their best gain setting the threshold
    # of the simulated ones' full fits) run as separate tasks on a pool; what each candidate
    # gets is what the sequential evaluation gives it, the skipped full fit included.
    gains = {f.name: 40_000.0 + 1_000.0 * i for i, f in enumerate(candidate("reflex_delay").forms)}
    gains |= {"sensor_delay": 3.0e6, "actuator_lag": 2.0e6, "grip_scheduled_stiffness": 900.0}
    for name, g in (
        ("coulomb_friction", [2e6, 2.2e6, 2.1e6]),
        ("stiffness_nonlinearity", [5e4, 9e4, 7e4]),
    ):
        gains |= dict(zip([f.name for f in candidate(name).forms], g, strict=True))
    here, ran_here = _pooled_step(monkeypatch, gains, None)
    with cf.ThreadPoolExecutor(2) as ex:
        pooled, ran_pooled = _pooled_step(monkeypatch, gains, ex)
    assert sorted(ran_pooled) == sorted(ran_here)  # the same fits, in another order
    assert ran_pooled != ran_here
    fields = ("name", "form", "delta_m2ll", "delta_bic", "form_m2ll", "full_fit_skipped")
    assert [[getattr(r, f) for f in fields] for r in pooled] == [
        [getattr(r, f) for f in fields] for r in here
    ]
    # The threshold: 1/FULL_FIT_RATIO of the best linear gain, the lag's after its full fit
    # (4e6; its screening, 2e6, is below the sensor delay's 3e6): it waited for that fit.
    # Stiffening's best screening (9e4) and the grip map's are below it, friction's above.
    by = {r.name: r for r in pooled}
    for name in ("stiffness_nonlinearity", "grip_scheduled_stiffness"):
        assert by[name].full_fit_skipped == 4e6 / engine.FULL_FIT_RATIO
    assert by["coulomb_friction"].full_fit_skipped is None
    assert by["coulomb_friction"].delta_m2ll == 4.4e6


def _two_steps(monkeypatch, jobs: int, log: Path) -> list[list]:
    """select() with stand-in fits over two steps (the sensor delay retained at the first),
    ``jobs`` processes; each fit's start and end appended to ``log``; returns the steps'
    candidates as (name, form, Δ−2 log L, forms' −2 log L, full fit skipped below)."""
    step1 = {"sensor_delay": 3e6, "coulomb_friction": 1e5, "stiffness_nonlinearity": 5e4}
    # At the second step the friction's first form improves nothing (its others are not
    # asked for), stiffening's improves (all its forms are).
    step2 = {"coulomb_friction": 1.0, "stiffness_nonlinearity": 40.0}

    def fit_form(setup, current_, cand, max_iter=engine.MAX_ITER):
        step = 1 + current_.spec.n_free
        i = [f.name for f in cand.forms].index(cand.form.name)
        gain = (step1 if step == 1 else step2)[cand.name] * (1.0 + 0.1 * i)
        with log.open("a") as f:
            f.write(f"start {step} {cand.name} {i}\n")
        time.sleep(0.3 if (step, cand.name) == (2, "stiffness_nonlinearity") else 0.01)
        with log.open("a") as f:
            f.write(f"end {step} {cand.name} {i}\n")
        spec = ModelSpec(Mechanisms(), current_.spec.free + (cand,), 250.0)
        f = _fit(cand.name, current_.fit.m2ll - gain)
        return FitResult(**{**f.__dict__, "spec": spec, "x": spec.start() + 0.01})

    def full(setup, screened, relative_stop=True):
        return FitResult(**{**screened.__dict__, "cost_trial": {"t": screened.m2ll / 2 - 1.0}})

    def judge(results, held_out):
        for r in results:
            r.passed = r.step == 1 and r.name == "sensor_delay"
            r.held_out_gain = r.delta_m2ll

    base = _fit(None, 1e6)
    monkeypatch.setattr(engine, "_fit_form", fit_form)
    monkeypatch.setattr(engine, "_full_fit", full)
    monkeypatch.setattr(engine, "make_current", lambda s, spec, fit, *a: Current(spec, fit, [], []))
    monkeypatch.setattr(engine, "_held_out_stage", lambda setup, cur, res, step, ex, *a: ex)
    monkeypatch.setattr(engine, "judge", judge)
    monkeypatch.setattr(
        engine, "current_after", lambda s, best, *a: Current(best.fit.spec, best.fit, [], [])
    )
    monkeypatch.setattr(engine, "_final_fit", lambda setup, spec, fit, *a: fit)
    monkeypatch.setattr(engine, "_confirm_refits", lambda *a: None)
    setup = SimpleNamespace(folds=[((), ())], spec=lambda: base.spec, base=base)
    sel = engine.select(setup, list(step1), jobs=jobs)
    return [
        [(r.name, r.form, r.delta_m2ll, r.form_m2ll, r.full_fit_skipped) for r in step]
        for step in sel.steps
    ]


@pytest.mark.skipif(
    mp.get_start_method() != "fork", reason="the stand-in fits reach the workers by fork"
)
def test_an_idle_worker_starts_the_forms_a_plan_may_ask_for_next(monkeypatch, tmp_path):
    # At a later step a family is screened in its first step's best form first, and in its
    # others only if that form improves −2 log L: on a pool, a worker with nothing else to do
    # (the friction's first form, which improves nothing, ended early) starts those others
    # meanwhile. The results are the sequential ones.
    here = _two_steps(monkeypatch, 1, tmp_path / "here.log")
    pooled = _two_steps(monkeypatch, 2, tmp_path / "pooled.log")
    assert pooled == here and len(here) == 2
    events = (tmp_path / "pooled.log").read_text().split("\n")
    last = len(candidate("stiffness_nonlinearity").forms) - 1  # its first step's best form
    first = events.index(f"end 2 stiffness_nonlinearity {last}")
    assert "start 2 stiffness_nonlinearity 0" in events[:first]  # started early …
    assert events.count("start 2 stiffness_nonlinearity 0") == 1  # … and not fitted again
    asked = sorted(e for e in (tmp_path / "here.log").read_text().split("\n") if e)
    assert set(asked) <= {e for e in events if e}


@pytest.mark.parametrize("threads", [False, True])
def test_a_screened_only_candidate_still_to_be_tried_is_fitted_fully_first(monkeypatch, threads):
    completed: list[str] = []

    def complete(setup, current, r):
        completed.append(r.name)
        return _result(r.name, 10 * r.delta_m2ll)  # its full fit: ten times its screening

    monkeypatch.setattr(engine, "complete_full_fit", complete)

    def short(name: str, gain: float) -> CandidateResult:
        r = _result(name, gain)
        r.full_fit_skipped = gain + 1.0
        return r

    def stage(results, held_out):
        if not threads:
            return _stage(results, held_out)
        with cf.ThreadPoolExecutor(2) as ex:
            return _stage(results, held_out, ex)

    # A retainable leader far above it: neither completed nor tried.
    far = short("stiffness_nonlinearity", 50_000.0)
    asked = stage([_result("sensor_delay", 4e6), far], {"sensor_delay": 4e6})
    assert asked == ["sensor_delay"] and completed == []
    assert far.held_out_skipped == 4e6 and far.full_fit_skipped is not None and not far.passed

    # A leader that cannot be retained: completed, then tried on its full fit.
    vague = _result("sensor_delay", 4e6, se=1.0)
    near = short("coulomb_friction", 50_000.0)
    asked = stage([vague, near], {"sensor_delay": 4e6, "coulomb_friction": 400_000.0})
    assert completed == ["coulomb_friction"] and asked == ["sensor_delay", "coulomb_friction"]
    assert near.full_fit_skipped is None and near.delta_m2ll == 500_000.0 and near.passed

    # One whose screening fails on BIC, beside a leader that cannot be retained: its full fit
    # might pass, so it is completed, and tried on it.
    completed.clear()
    vague = _result("sensor_delay", 4e6, se=1.0)
    weak = short("grip_scheduled_stiffness", 15.0)  # ΔBIC +5 at its screening, −130 in full
    asked = stage([vague, weak], {"sensor_delay": 4e6, "grip_scheduled_stiffness": 120.0})
    assert completed == ["grip_scheduled_stiffness"] and asked[-1] == "grip_scheduled_stiffness"
    assert weak.delta_m2ll == 150.0 and weak.held_out_gain == 120.0

    # Beside a leader that can be retained it stays as screened, and says why.
    weak = short("grip_scheduled_stiffness", 15.0)
    asked = stage([_result("sensor_delay", 4e6), weak], {"sensor_delay": 4e6})
    assert asked == ["sensor_delay"] and weak.full_fit_skipped is not None
    assert weak.reason.startswith("not better on BIC at its screening")


def test_a_screening_that_gains_too_little_to_be_retried_is_fitted_fully(monkeypatch):
    # Whether a later step retries a family depends on its full gain: below the retry
    # threshold the screening alone cannot say, so the full fit is done.
    forms = [f.name for f in candidate("grip_scheduled_stiffness").forms]
    gains = dict(zip(forms, [RETRY_MIN_DELTA_M2LL - 2.0, 1.0], strict=True))
    log = _screened("grip_scheduled_stiffness", gains, monkeypatch)
    current = Current(_fit(None, 1e6).spec, _fit(None, 1e6), [], [])
    setup = SimpleNamespace(trials=[], noise={}, folds=[((), ())])
    r = engine.evaluate_candidate(setup, current, "grip_scheduled_stiffness", 1, None, 5e4)
    assert log == [*forms, "full"] and r.full_fit_skipped is None
    assert r.delta_m2ll == 2 * (RETRY_MIN_DELTA_M2LL - 2.0) > RETRY_MIN_DELTA_M2LL
    assert engine.retried(["grip_scheduled_stiffness"], [[r]]) == ["grip_scheduled_stiffness"]


def test_a_model_retained_far_from_the_floor_is_fitted_on_to_the_absolute_tolerance(monkeypatch):
    """Its fits may have stopped relative to its misfit (``fit.stop_tolerance``): the next
    step's candidates, started from its arms, would collect what it left. Near the floor the
    candidate's fit and folds are taken as judged."""
    from dataclasses import replace

    calls: list[tuple] = []
    polished = _fit("coulomb_friction", 1e6 - 150.0)

    def fit_model(trials, spec, noise, arms, x0=None, **opts):
        calls.append(("fit", opts))
        return polished

    def fold_eval(setup, spec, arms, x_starts=None, relative_stop=None):
        calls.append(("folds", relative_stop))
        return [np.ones(1)], [7.0], {}

    monkeypatch.setattr(engine, "fit_model", fit_model)
    monkeypatch.setattr(engine, "_fold_eval", fold_eval)
    monkeypatch.setattr(engine, "_out_of_corners", lambda trials, spec, noise, fit, opts: fit)
    setup = SimpleNamespace(trials=[], noise={})
    near = replace(_result("coulomb_friction", 100.0), fold_x=[np.zeros(1)], fold_cost=[9.0])
    current = engine.current_after(setup, near)
    assert current.fit is near.fit and current.fold_test_cost == [9.0] and calls == []
    far = replace(near, fit=replace(near.fit, lack_of_fit=engine.RELATIVE_STOP_MIN_LACK + 0.5))
    current = engine.current_after(setup, far)
    assert calls == [("fit", {"relative_stop": False}), ("folds", False)]
    assert current.fit is polished and current.fold_test_cost == [7.0]
