"""What the forward selection leaves out to save time, and that it leaves out nothing else.

Two rules (``analysis.diagnosis.engine``):

- the held-out folds of a step run in order of the candidates' in-sample gain, and a
  candidate whose in-sample gain times ``HELD_OUT_SKIP_RATIO`` is below a retainable
  candidate's held-out gain is not tried held out (``_held_out_stage``);
- at a later step, a family is screened first in its first step's best form, and in its
  other forms only if that form improves −2 log L by ``RETRY_MIN_DELTA_M2LL`` or more
  (``evaluate_candidate``).

The fits are replaced by stand-ins with chosen −2 log L, so the rules are checked exactly; the
studies of ``test_diagnosis_otherworld.py`` and ``benchmarks/diagnose`` check them on real
fits.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing.connection as mp_connection
import signal
import time
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

    def folds(setup_, current_, r):
        asked.append(r.name)
        g = held_out[r.name]
        return [np.zeros(1), np.zeros(1)], [-g / 2, -g / 2], {"0:t": -g / 2, "1:t": -g / 2}

    def wait(futs):
        if late:  # as select's wait at the limit: nothing more done, the rest pending
            return set(), set(futs)
        return cf.wait(futs)

    undone: list[str] = []
    mp = pytest.MonkeyPatch()
    mp.setattr(engine, "held_out_folds", folds)
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
    current = Current(_fit(None, 1e6).spec, _fit(None, 1e6), [], [])
    tried: list[str] = []

    def fit_form(setup, current_, cand, max_iter=engine.MAX_ITER):
        tried.append(cand.form.name)
        gain = first_gain if cand.form.name == (first_form or fam.forms[0].name) else 100.0
        f = _fit("reflex_delay", 1e6 - gain)
        return FitResult(**{**f.__dict__, "spec": ModelSpec(Mechanisms(), (cand,), 250.0)})

    monkeypatch.setattr(engine, "_fit_form", fit_form)
    monkeypatch.setattr(engine, "fit_model", lambda trials, spec, noise, arms, x0: _fit(
        "reflex_delay", 1e6 - (first_gain if spec.free[0].form.name == (first_form or
        fam.forms[0].name) else 100.0)))  # fmt: skip
    setup = SimpleNamespace(trials=[], noise={}, folds=[])
    r = engine.evaluate_candidate(setup, current, "reflex_delay", 2, first_form)
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
