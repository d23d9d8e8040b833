"""Drift: do the arm's stiffnesses change with the trial's position in the session?

The simulator's drift scales k_i and k_c by a factor f(trial_index) (:class:`Drift`). Each
trial has its own arm parameters in every model of the diagnosis, so drift never shows in a
trial's signals; it shows in how those parameters move from trial to trial. Per subject ×
condition (the condition sets the stiffness), the logarithms of each trial's fitted k_i and
k_c are modelled as

    log k = a_cell,param + log f(trial_index) + ε,   ε ~ N(0, σ²_param)

against the same without the drift term. Drift is a family (issue 18 item 2): *linear*,
f = 1 + r·(trial_index − 1), or *stepwise*, f = 1 before trial c and 1 + s from it on, for
every change point c that some cell has trials on both sides of (elsewhere a step is the
cells' own means); of k_i and k_c together (Steerlab's simulator) or of k_i alone (the term
is then left out of log k_c). The familiarization trial counts here (it is the first of its
condition, so it lengthens the lever from one trial to two); trials whose order is unknown
do not.

- Fit: each form's parameter (r, or s at each c) by bounded scalar minimisation of the
  restricted (REML) −2 log L = Σ_param ν log(RSS/ν), ν = n − n_cells; the form with the lowest
  is the family's. Forms within 3.84 of the best are reported as consistent with the data.
  Why ν and not n: every cell has its own mean, and with two or three trials per cell
  (Neyman & Scott, 1948) the likelihood with n, profiled over the cell means, takes the
  scatter as half (two trials per cell) or two thirds (three) of what it is, at any number of
  subjects, and so doubles the evidence for any trend. On simulated stiffnesses of the 12-trial
  design (the tests' ``_rows``, seeds 0–199; one scatter of 1 %, 0.5/1/3 % or 1/2/4 % by
  condition) the
  profiled form at ΔBIC < −10 passed 6, 9 and 12 drift-free sessions, the restricted form at
  −8 (:data:`MIN_DBIC`) 2, 6 and 2; drift of 4 % per trial is found in 200 (profiled: 200),
  2 % in 90 (174), 1 % in 13 (57), a 10 % step of k_i in 127 (197). On the independent
  world it removes all three drift false alarms of 40 null studies (seeds 5020, 5029, 5033:
  ΔBIC −12.0, −12.8, −13.5 became −3.0, −2.5, −2.9).
- ΔBIC = Δ(−2 log L) + p ln(2ν) + 2 ln K: p = 1 (linear) or 2 (stepwise: the
  change point is a parameter, chosen on the data), and the family's prior shared among its
  K forms.
- Held out: every trial's log k predicted from the other trials of its cell, with the form and
  its parameter chosen and fitted without that trial (leave-one-out); the gain is
  Σ_param n log(PRESS_no drift / PRESS_drift) in −2 log L units.
- The choice of form is paid for in BIC and again in every held-out fit: with the profiled
  likelihood, 18 drift-free sessions of 100 (1 % scatter) passed when the choice was paid for
  in neither, 2 with both (at ΔBIC < −10).
- Interval for the parameter: where the profile −2 log L is within 3.84 of its minimum.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq, minimize_scalar

from steerlab.hardware.sim.mechanisms import Drift

R_BOUND = 0.1  # |r| per trial: ±10 % per trial is far beyond any plausible drift
# A step of the stiffnesses: from halving to doubling.
STEP_BOUNDS = (-0.5, 1.0)
# Forms within this −2 log L of the best are consistent with the data (as the candidates').
FORM_CONSISTENT_M2LL = 3.84
PARAMS = ("k_i", "k_c")
# Calibrated on drift-free simulated stiffnesses (log-normal scatter, 200 sessions per design;
# docs/diagnosis.md, "Drift"), with the restricted likelihood: 2 subjects × 2 or 3 conditions ×
# 2 repetitions, 2 % scatter or 1/2/4 % by condition: at 8 at most 2 of 200 pass (at 6: 5,
# at 10: 1), and a step of k_i by 30 % inside a condition is found in 37–92 % (6: 55–98 %,
# 10: 21–80 %). (With the likelihood profiled over the cell means, which doubles the evidence,
# 10 had let 6–16 of 200 pass: python -m benchmarks drift_calibration --likelihood profiled.)
MIN_DBIC = 8.0
MIN_HELD_OUT = 0.0
# Within-condition differences (ν) below which drift is not judged: with 2 or 3 the scatter
# is estimated from as many numbers and the test's tails are far heavier than its χ² (one
# subject, two or three conditions of two trials: 2–3.5 % of drift-free sessions passed at
# ΔBIC < −8; two subjects, ν 4 and 6: at most 1 %; python -m benchmarks drift_calibration).
MIN_DOF = 4


@dataclass(frozen=True)
class TrialStiffness:
    label: str
    cell: tuple[str, str]
    trial_index: int
    repetition: int
    k_i: float
    k_c: float


@dataclass(frozen=True)
class DriftForm:
    """A form of the drift family: linear (``at_trial`` None) or a step at ``at_trial``, of
    k_i and k_c together or of k_i alone."""

    at_trial: int | None = None
    stiffnesses: tuple[str, ...] = PARAMS

    @property
    def name(self) -> str:
        law = "linear" if self.at_trial is None else f"stepwise from trial {self.at_trial}"
        return law + ("" if self.stiffnesses == PARAMS else " (k_i alone)")

    @property
    def mask(self) -> np.ndarray:
        """Which of :data:`PARAMS` drift."""
        return np.array([p in self.stiffnesses for p in PARAMS], dtype=float)

    @property
    def parameter(self) -> str:
        return "rate_per_trial" if self.at_trial is None else "step"

    def factor(self, idx: np.ndarray, v: float) -> np.ndarray:
        if self.at_trial is None:
            return 1.0 + v * (idx - 1.0)
        return 1.0 + v * (idx >= self.at_trial)

    def bounds(self, idx: np.ndarray) -> tuple[float, float]:
        if self.at_trial is not None:
            return STEP_BOUNDS
        # The factor must stay positive over the session.
        hi = min(R_BOUND, 0.99 / max(idx.max() - 1.0, 1.0)) if idx.max() > 1 else R_BOUND
        return -hi, R_BOUND

    @property
    def n_params(self) -> int:
        """Counted in BIC: the step's change point is a parameter (module docstring)."""
        return 1 if self.at_trial is None else 2

    def mechanism(self, v: float) -> Drift:
        scope = ",".join(self.stiffnesses)
        if self.at_trial is None:
            return Drift(rate_per_trial=v, stiffnesses=scope)
        return Drift(form="stepwise", step=v, at_trial=self.at_trial, stiffnesses=scope)


LINEAR = DriftForm()


@dataclass
class DriftResult:
    rate: float  # the form's parameter: rate per trial (linear) or step (stepwise)
    ci95: tuple[float, float]
    se: float
    delta_m2ll: float  # no drift − drift (> 0: drift fits better)
    delta_bic: float  # drift − no drift (< 0: better)
    held_out_gain: float | None
    n_trials: int
    n_cells: int
    passed: bool
    reason: str
    rows: list[dict]
    form: DriftForm = LINEAR
    forms_m2ll: dict[str, float] = field(default_factory=dict)  # −2 log L of every form

    @property
    def forms_consistent(self) -> list[str]:
        best = min(self.forms_m2ll.values(), default=0.0)
        ranked = sorted(self.forms_m2ll.items(), key=lambda kv: kv[1])
        return [k for k, v in ranked if v - best <= FORM_CONSISTENT_M2LL]

    def factor(self, trial_index: int) -> float:
        return float(self.form.factor(np.array([float(trial_index)]), self.rate)[0])

    def mechanism(self) -> Drift:
        return self.form.mechanism(self.rate)

    def to_dict(self) -> dict:
        return {
            "name": "drift",
            "form": self.form.name,
            "forms_minus2loglik": self.forms_m2ll,
            "forms_consistent_with_data": self.forms_consistent,
            "parameters": [
                {
                    "mechanism": "drift",
                    "parameter": self.form.parameter,
                    "unit": "1",
                    "value": self.rate,
                    "se": self.se,
                    "ci95": list(self.ci95),
                }
            ],
            "delta_minus2loglik": self.delta_m2ll,
            "delta_bic": self.delta_bic,
            "held_out_gain_minus2loglik": self.held_out_gain,
            "held_out_method": "leave-one-trial-out prediction of log k_i and log k_c",
            "n_trials": self.n_trials,
            "n_cells": self.n_cells,
            "passed": self.passed,
            "reason": self.reason,
        }


def _design(rows: Sequence[TrialStiffness]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    cells = sorted({r.cell for r in rows})
    cid = np.array([cells.index(r.cell) for r in rows])
    idx = np.array([r.trial_index for r in rows], dtype=float)
    y = np.log(np.array([[r.k_i, r.k_c] for r in rows]))
    return cid, idx, y


def _rss(
    cid: np.ndarray, idx: np.ndarray, y: np.ndarray, r: float, form: DriftForm = LINEAR
) -> np.ndarray:
    f = form.factor(idx, r)
    if np.any(f <= 0):
        return np.full(y.shape[1], np.inf)
    z = y - np.log(f)[:, None] * form.mask[None, :]
    # Within-cell sums of squares about each cell's mean, per column.
    n_cell = np.maximum(np.bincount(cid), 1)
    out = np.empty(y.shape[1])
    for j in range(y.shape[1]):
        mean = np.bincount(cid, weights=z[:, j]) / n_cell
        out[j] = np.sum((z[:, j] - mean[cid]) ** 2)
    return out


def _m2ll(
    cid: np.ndarray, idx: np.ndarray, y: np.ndarray, r: float, form: DriftForm = LINEAR
) -> float:
    nu = _dof(cid)
    rss = np.maximum(_rss(cid, idx, y, r, form), 1e-300)
    return float(np.sum(nu * np.log(rss / nu)))


def _dof(cid: np.ndarray) -> int:
    """Residual degrees of freedom: trials less one mean per cell (module docstring)."""
    return len(cid) - len(np.unique(cid))


def _fit_rate(cid: np.ndarray, idx: np.ndarray, y: np.ndarray, form: DriftForm = LINEAR) -> float:
    res = minimize_scalar(
        lambda r: _m2ll(cid, idx, y, r, form), bounds=form.bounds(idx), method="bounded",
        options={"xatol": 1e-6},
    )  # fmt: skip
    return float(res.x)


def _fit_forms(
    cid: np.ndarray, idx: np.ndarray, y: np.ndarray
) -> list[tuple[float, DriftForm, float]]:
    """(−2 log L, form, parameter) of every form, best first."""
    fits = []
    for f in drift_forms(cid, idx):
        v = _fit_rate(cid, idx, y, f)
        fits.append((_m2ll(cid, idx, y, v, f), f, v))
    return sorted(fits, key=lambda t: t[0])


def drift_forms(cid: np.ndarray, idx: np.ndarray) -> list[DriftForm]:
    """Linear, and a step at every trial index that some cell has trials on both sides of;
    each of k_i and k_c together, and of k_i alone."""
    steps = [
        c
        for c in sorted({int(i) for i in idx})
        if any(idx[cid == k].min() < c <= idx[cid == k].max() for k in np.unique(cid))
    ]
    return [
        DriftForm(at_trial=c, stiffnesses=scope)
        for scope in (PARAMS, ("k_i",))
        for c in [None, *steps]
    ]


def analyse_drift(rows: Sequence[TrialStiffness], r0: float = 0.0) -> DriftResult | None:
    """The drift test on per-trial stiffnesses; None when no cell has two ordered trials.

    ``r0``: the rate of the model the diagnosis starts from (a model file's drift); the test
    is then whether the data need another rate than that.
    """
    by_cell: dict[tuple[str, str], list[TrialStiffness]] = {}
    for r in rows:
        by_cell.setdefault(r.cell, []).append(r)
    keep = [r for rs in by_cell.values() if len({x.trial_index for x in rs}) >= 2 for r in rs]
    n_cells = sum(1 for rs in by_cell.values() if len({x.trial_index for x in rs}) >= 2)
    if len(keep) < 3 or n_cells == 0:
        return None
    cid, idx, y = _design(keep)
    n = len(keep)
    m0 = _m2ll(cid, idx, y, r0)
    fits = _fit_forms(cid, idx, y)
    m1, form, r_hat = fits[0]
    forms_m2ll = {f.name: m for m, f, _ in fits}
    d_m2ll = m0 - m1
    nu = _dof(cid)
    # The family's prior is shared among its forms (1/K each): 2 ln K on the −2 log L scale.
    d_bic = -d_m2ll + form.n_params * math.log(nu * len(PARAMS)) + 2 * math.log(len(fits))

    def excess(r: float) -> float:
        return _m2ll(cid, idx, y, r, form) - m1 - 3.84

    lo = hi = float("nan")
    a, b = form.bounds(idx)
    try:
        lo = brentq(excess, a, r_hat) if excess(a) > 0 else a
        hi = brentq(excess, r_hat, b) if excess(b) > 0 else b
    except ValueError:
        pass
    se = (hi - lo) / 3.92 if np.isfinite(lo) and np.isfinite(hi) else float("nan")

    # Leave one trial out: its log k from the rest of its cell, r from everything else.
    press0 = np.zeros(y.shape[1])
    press1 = np.zeros(y.shape[1])
    counted = 0
    for i in range(n):
        others = np.arange(n) != i
        same = others & (cid == cid[i])
        if not same.any():
            continue
        # The form is chosen again without the trial: a change point chosen on all trials
        # would carry the left-out trial's own scatter into its prediction.
        _, form_i, r_i = _fit_forms(cid[others], idx[others], y[others])[0]
        f0 = np.log(1.0 + r0 * (idx[same] - 1.0))
        pred0 = (y[same] - f0[:, None]).mean(axis=0) + np.log(1.0 + r0 * (idx[i] - 1.0))
        press0 += (y[i] - pred0) ** 2
        mask = form_i.mask
        f_same = np.log(form_i.factor(idx[same], r_i))[:, None] * mask
        f_i = np.log(form_i.factor(idx[i : i + 1], r_i))[0] * mask
        pred = (y[same] - f_same).mean(axis=0) + f_i
        press1 += (y[i] - pred) ** 2
        counted += 1
    gain = float(np.sum(counted * np.log(np.maximum(press0, 1e-300) / np.maximum(press1, 1e-300))))

    ok_bic = d_bic < -MIN_DBIC
    ok_ho = gain > MIN_HELD_OUT
    passed = ok_bic and ok_ho and nu >= MIN_DOF
    if nu < MIN_DOF:
        reason = (
            f"not judged: {nu} differences between trials of the same subject and condition; "
            f"at least {MIN_DOF} are needed to tell a trend from their scatter (more subjects, "
            "repetitions or the familiarization trials)"
        )
    elif passed:
        reason = "stiffness changes with trial order, on BIC and in leave-one-out prediction"
    elif ok_bic:
        reason = "better on BIC, but does not predict left-out trials"
    else:
        reason = "no trend of the stiffnesses with trial order beyond their scatter"
    table = [
        {
            "trial": r.label,
            "trial_index": r.trial_index,
            "repetition": r.repetition,
            "k_i_Nm_per_rad": r.k_i,
            "k_c_Nm_per_rad": r.k_c,
        }
        for r in keep
    ]
    return DriftResult(
        rate=r_hat,
        ci95=(float(lo), float(hi)),
        se=float(se),
        delta_m2ll=float(d_m2ll),
        delta_bic=float(d_bic),
        held_out_gain=gain,
        n_trials=n,
        n_cells=n_cells,
        passed=passed,
        reason=reason,
        rows=table,
        form=form,
        forms_m2ll=forms_m2ll,
    )
