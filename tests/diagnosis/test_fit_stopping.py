"""When a fit stops (``analysis.diagnosis.fit.stop_tolerance``): at 0.01 units of cost per
trial, and, for a candidate's fits far from the noise floor (a lack of fit above 3), once an
iteration gains less than 10⁻³ of the cost's excess over the floor.

The trials are the independent world's (benchmarks/otherworld.py, through the interchange
format)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from steerlab.analysis.diagnosis import engine, simulate
from steerlab.analysis.diagnosis.data import prepare_study
from steerlab.analysis.diagnosis.fit import (
    REL_TOL_EXCESS,
    RELATIVE_STOP_MIN_LACK,
    TOL_PER_TRIAL,
    UNSTABLE_RESIDUAL,
    ModelSpec,
    fit_model,
    noise_model,
    stop_tolerance,
)
from steerlab.benchmarks import _diagnose_otherworld as ow
from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.protocols.datafile import load_study


def _trials(n: int, bins: int = 100) -> list[SimpleNamespace]:
    return [SimpleNamespace(label=f"t{i}", bins=np.arange(bins)) for i in range(n)]


def test_the_absolute_tolerance_unless_asked_and_far_from_the_floor():
    trials = _trials(4)  # 800 residual values
    absolute = TOL_PER_TRIAL * 4
    far = {t.label: 10 * 200.0 for t in trials}  # lack of fit 10
    assert stop_tolerance(trials, far, relative=False) == absolute
    assert stop_tolerance(trials, far, relative=True) == pytest.approx(REL_TOL_EXCESS * 9 * 800)
    at_edge = {t.label: RELATIVE_STOP_MIN_LACK * 200.0 for t in trials}
    assert stop_tolerance(trials, at_edge, relative=True) == absolute
    # Beyond a lack of 3 with an excess whose thousandth is less than 0.01 per trial: never
    # below the absolute tolerance.
    tiny = [SimpleNamespace(label="t", bins=np.arange(2))]  # 4 residual values
    assert REL_TOL_EXCESS * (13.0 - 4) < TOL_PER_TRIAL
    assert stop_tolerance(tiny, {"t": 13.0}, relative=True) == TOL_PER_TRIAL


def test_an_unstable_trial_does_not_loosen_the_others():
    trials = _trials(4)
    costs = {t.label: 200.0 for t in trials}  # at the floor
    costs["t0"] = UNSTABLE_RESIDUAL**2 * 200  # a diverged simulation's cost
    assert stop_tolerance(trials, costs, relative=True) == TOL_PER_TRIAL * 4
    costs["t1"] = 50 * 200.0  # the stable three at a lack of fit of 17.3
    excess = (50 + 2 - 3) * 200.0
    assert stop_tolerance(trials, costs, relative=True) == pytest.approx(REL_TOL_EXCESS * excess)


def _baseline_fits(root: Path, kind, form):
    data = ow.make_study(root, kind, form, seed=4, small=True)
    trials = prepare_study(load_study(data)).trials[:2]
    arms0 = {t.label: engine.plausible_arm(t) for t in trials}
    ref = {t.label: simulate.simulated_spectra(t, arms0[t.label], Mechanisms()) for t in trials}
    noise = noise_model(trials, ref)
    spec = ModelSpec(Mechanisms(), (), trials[0].fs_hz)
    return [fit_model(trials, spec, noise, arms0, relative_stop=r) for r in (False, True)]


def test_far_from_the_floor_a_fit_stops_sooner_and_near_where_the_absolute_one_does(tmp_path):
    # The plain arm on a 12 ms actuator lag: 400 × the floor, and the absolute tolerance
    # spends its whole budget.
    absolute, relative = _baseline_fits(tmp_path / "s", "actuator_lag", "first_order")
    assert absolute.lack_of_fit > 100
    assert relative.iterations < absolute.iterations
    # What the early stop leaves is small beside the contest it serves (10⁵–10⁶ units).
    assert 0 <= relative.m2ll - absolute.m2ll < 0.01 * absolute.m2ll


def test_near_the_floor_nothing_changes(tmp_path):
    absolute, relative = _baseline_fits(tmp_path / "s", None, None)
    assert absolute.lack_of_fit < RELATIVE_STOP_MIN_LACK
    assert relative.iterations == absolute.iterations
    assert relative.m2ll == absolute.m2ll
