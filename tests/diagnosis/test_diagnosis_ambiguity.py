"""Two mechanisms that explain the data equally well are both named (issue 18 item 4).

``engine.confusable`` compares the criterion that chose the retained candidate (the held-out
−2 log L, summed over test trials) with each other passing candidate's, trial by trial; the
trials are independent, so the sum's standard error is √n × the per-trial differences' SD. The
figures here are small enough to check by hand.
"""

from __future__ import annotations

import math

import numpy as np

from steerlab.analysis.diagnosis.candidates import candidate
from steerlab.analysis.diagnosis.engine import AMBIGUITY_Z, CandidateResult, confusable
from steerlab.analysis.diagnosis.fit import FitResult, ModelSpec
from steerlab.hardware.sim.mechanisms import Mechanisms


def _result(name: str, held_out: list[float], passed: bool = True) -> CandidateResult:
    spec = ModelSpec(Mechanisms(), (candidate(name),), 250.0)
    fit = FitResult(spec=spec, x=spec.start(), cov=np.eye(spec.n_free) * 1e-6, arms={},
                    cost_trial={}, simulated={}, n_obs=1000, iterations=3, converged=True,
                    lack_of_fit=1.0)  # fmt: skip
    r = CandidateResult(name, 1, fit, 100.0, -80.0, 90.0, [45.0, 45.0])
    r.held_out_trial_cost = {f"{i % 2}:t{i}": c for i, c in enumerate(held_out)}
    r.passed = passed
    return r


def test_an_alternative_within_the_noise_is_named_with_its_evidence():
    best = _result("actuator_lag", [10.0, 12.0, 11.0, 9.0])
    # Per trial 0.5, −0.5, 0.8, 0.1 worse: 0.9 in all, SE √4 × SD = 2 × 0.5909 = 1.18.
    same = _result("sensor_delay", [10.5, 11.5, 11.8, 9.1])
    out = confusable(best, [best, same], held_out=True)
    assert [a["name"] for a in out] == ["sensor_delay"]
    a = out[0]
    assert a["worse_by"] == 0.9 or math.isclose(a["worse_by"], 0.9)
    sd = math.sqrt(((0.5 - 0.225) ** 2 + (-0.5 - 0.225) ** 2 + (0.8 - 0.225) ** 2
                    + (0.1 - 0.225) ** 2) / 3)  # fmt: skip
    assert math.isclose(a["se"], 2 * sd)
    assert a["criterion"] == "held-out −2 log L" and a["held_out_gain_minus2loglik"] == 90.0
    assert [p["parameter"] for p in a["parameters"]] == ["delay_s"]


def test_a_clearly_worse_or_failed_alternative_is_not_named():
    best = _result("actuator_lag", [10.0, 12.0, 11.0, 9.0])
    worse = _result("sensor_delay", [30.0, 33.0, 29.0, 31.0])  # 81 worse, SE 3.3
    failed = _result("reflex_delay", [10.0, 12.0, 11.0, 9.0], passed=False)
    assert confusable(best, [best, worse, failed], held_out=True) == []
    # The threshold is the criterion's noise: just inside two SEs is named, just outside not.
    d = np.array([1.0, -1.0, 1.0, -1.0])
    se = 2 * d.std(ddof=1)
    for shift, named in ((AMBIGUITY_Z * se / 4 - 0.01, True), (AMBIGUITY_Z * se / 4 + 0.01, False)):
        alt = _result("sensor_delay", list(np.array([10.0, 12.0, 11.0, 9.0]) + d + shift))
        assert bool(confusable(best, [alt], held_out=True)) is named
