"""The diagnosis's candidates fitted on Dask (``steerlab diagnose --scheduler``) give the
in-process diagnosis, number for number."""

from __future__ import annotations

import json
import math

import pytest

from steerlab.analysis.diagnosis import engine, run_diagnosis
from steerlab.benchmarks.diagnose import make_study

CANDIDATES = ("actuator_lag", "sensor_delay", "coulomb_friction")


def _found(result) -> str:
    d = result.to_dict()
    d.pop("timing_s")
    return json.dumps(d, sort_keys=True)


@pytest.mark.slow
def test_a_dask_local_cluster_gives_the_in_process_diagnosis(tmp_path, monkeypatch):
    pytest.importorskip("distributed", reason="Dask is the optional extra steerlab[dask]")
    from steerlab.analysis.executors import executor_for

    # Without a time limit the work done cannot depend on the machine's load.
    monkeypatch.setattr(engine, "CANDIDATE_TIME_LIMIT_S", math.inf)
    # A hidden mechanism, so that a candidate is retained and the final re-fit runs too; three
    # candidates (one nonlinear, simulated on remnant realisations) keep it short.
    data = make_study(tmp_path / "s", "actuator_lag", 0.005, seed=14)
    here = run_diagnosis(data, None, candidates=CANDIDATES)
    assert here.cause == "actuator_lag", here.summary()
    with executor_for("local:2") as ex:
        assert ex is not None and type(ex).__module__.startswith("distributed")
        on_dask = run_diagnosis(data, None, candidates=CANDIDATES, executor=ex)
    assert _found(on_dask) == _found(here)


@pytest.mark.slow
def test_our_own_pool_of_two_jobs_gives_the_in_process_diagnosis(tmp_path):
    # steerlab diagnose's default: as many jobs as cores. With the default time limit (CPU
    # seconds, the workers' included), the in-process run of the same study: number for
    # number, the held-out stage's choices included (a lag study: several candidates pass on
    # BIC at the first step).
    data = make_study(tmp_path / "s", "actuator_lag", 0.005, seed=14)
    here = run_diagnosis(data, None, candidates=CANDIDATES)
    assert here.cause == "actuator_lag", here.summary()
    pooled = run_diagnosis(data, None, candidates=CANDIDATES, jobs=2)
    assert _found(pooled) == _found(here)


@pytest.mark.slow
def test_a_retained_frictions_final_fit_on_two_jobs_is_the_in_process_one(tmp_path):
    # A nonlinear mechanism retained: its final fit simulates eight remnant realisations per
    # trial, which the main process makes after the workers got their set-up; each worker
    # rebuilds them for its share of the simulations (engine.TrialState).
    data = make_study(tmp_path / "s", "coulomb_friction", 0.15, seed=14)
    only = ("coulomb_friction",)
    here = run_diagnosis(data, None, candidates=only)
    assert here.cause == "coulomb_friction", here.summary()
    pooled = run_diagnosis(data, None, candidates=only, jobs=2)
    assert _found(pooled) == _found(here)
