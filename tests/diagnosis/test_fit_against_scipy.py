"""``fit_model`` on a model that must be simulated (dry friction) ends where scipy's
``least_squares`` ends on the same residual: the approximate arm slope it starts with (the
linear part's, ``analysis.diagnosis.fit``) must not move the end point, only the path.

The trials are the independent world's Coulomb friction (benchmarks/otherworld.py, through the
interchange format); scipy fits the same whitened residual, arms in logarithms, mechanism
parameters within their bounds, with its own trust-region method and tight tolerances."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from steerlab.analysis.diagnosis import engine, simulate
from steerlab.analysis.diagnosis import fit as fitmod
from steerlab.analysis.diagnosis.candidates import candidate
from steerlab.analysis.diagnosis.data import prepare_study
from steerlab.analysis.diagnosis.fit import ModelSpec, fit_model, noise_model, whitener
from steerlab.benchmarks import _diagnose_otherworld as ow
from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.protocols.datafile import load_study

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("fr") / "s"
    data = ow.make_study(root, "friction", "coulomb", seed=4, small=True)
    trials = prepare_study(load_study(data)).trials[:2]
    arms0 = {t.label: engine.plausible_arm(t) for t in trials}
    ref = {t.label: simulate.simulated_spectra(t, arms0[t.label], Mechanisms()) for t in trials}
    noise = noise_model(trials, ref)
    engine.set_remnants(trials, arms0, 1)
    return trials, arms0, noise


@pytest.mark.parametrize("form", [0, 2], ids=["Coulomb", "viscous plus Coulomb"])
def test_a_simulated_models_fit_ends_where_scipy_least_squares_does(study, form):
    trials, arms0, noise = study
    fam = candidate("coulomb_friction")
    spec = ModelSpec(Mechanisms(), (fam.with_form(fam.forms[form]),), trials[0].fs_hz)
    x0 = np.full(spec.n_free, 0.05)
    ours = fit_model(trials, spec, noise, arms0, x0=x0, fit_inertia=False)
    assert ours.converged

    W = {t.label: whitener(t, noise[t.label]) for t in trials}
    n_arm = len(fitmod.ARM_FREE)

    def residual(p):
        arms = {
            t.label: fitmod._arm_from_log(arms0[t.label], p[n_arm * i : n_arm * (i + 1)])
            for i, t in enumerate(trials)
        }
        st = fitmod._evaluate(trials, spec, W, arms, p[len(trials) * n_arm :])
        return np.concatenate([st.r[t.label] for t in trials])

    p0 = np.concatenate([fitmod._arm_log(arms0[t.label]) for t in trials] + [x0])
    lo = [-np.inf] * (len(p0) - spec.n_free) + [p.lower for p in spec.specs()]
    hi = [np.inf] * (len(p0) - spec.n_free) + [p.upper for p in spec.specs()]
    scale = [1.0] * (len(p0) - spec.n_free) + [0.02] * spec.n_free
    ref = least_squares(
        residual, p0, bounds=(lo, hi), x_scale=scale, diff_step=1e-4,
        xtol=1e-10, ftol=1e-12, gtol=1e-10,
    )  # fmt: skip
    assert ref.status > 0
    ref_m2ll = 4.0 * ref.cost  # −2 log L = 2 Σ|r|², scipy's cost ½ Σ|r|²
    # Within the fit's own tolerance (0.01 per trial and iteration) and a unit of −2 log L:
    # neither ends measurably better than the other.
    assert abs(ours.m2ll - ref_m2ll) < 1.0
    # The friction torque (the world's 0.15 N·m) agrees to a per cent.
    assert ours.x[0] == pytest.approx(ref.x[len(trials) * n_arm], rel=0.01)
