"""Drift: do the arm's stiffnesses change with the trial's position in the session?

The simulator's drift scales k_i and k_c by (1 + r·(trial_index − 1)). Each trial has its own
arm parameters in every model of the diagnosis, so drift never shows in a trial's signals; it
shows in how those parameters move from trial to trial. Per subject × condition (the
condition sets the stiffness), the logarithms of each trial's fitted k_i and k_c are modelled as

    log k = a_cell,param + log(1 + r·(trial_index − 1)) + ε,   ε ~ N(0, σ²_param)

against the same without the drift term. The familiarization trial counts here (it is the
first of its condition, so it lengthens the lever from one trial to two); trials whose order is
unknown do not.

- Fit: r by bounded scalar minimisation of the concentrated −2 log L = Σ_param n log(RSS/n).
- ΔBIC = Δ(−2 log L) + ln(n_observations).
- Held out: every trial's log k predicted from the other trials of its cell, with r fitted
  without that trial (leave-one-out); the gain is Σ_param n log(PRESS_no drift / PRESS_drift)
  in −2 log L units.
- Interval for r: where the profile −2 log L is within 3.84 of its minimum.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq, minimize_scalar

R_BOUND = 0.1  # |r| per trial: ±10 % per trial is far beyond any plausible drift
PARAMS = ("k_i", "k_c")
MIN_DBIC = 6.0  # "strong" evidence (Kass & Raftery), and the leave-one-out check as well
MIN_HELD_OUT = 0.0


@dataclass(frozen=True)
class TrialStiffness:
    label: str
    cell: tuple[str, str]
    trial_index: int
    repetition: int
    k_i: float
    k_c: float


@dataclass
class DriftResult:
    rate: float
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

    def to_dict(self) -> dict:
        return {
            "name": "drift",
            "parameters": [
                {
                    "mechanism": "drift",
                    "parameter": "rate_per_trial",
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


def _rss(cid: np.ndarray, idx: np.ndarray, y: np.ndarray, r: float) -> np.ndarray:
    f = 1.0 + r * (idx - 1.0)
    if np.any(f <= 0):
        return np.full(y.shape[1], np.inf)
    z = y - np.log(f)[:, None]
    out = np.zeros(y.shape[1])
    for c in np.unique(cid):
        m = cid == c
        out += np.sum((z[m] - z[m].mean(axis=0)) ** 2, axis=0)
    return out


def _m2ll(cid: np.ndarray, idx: np.ndarray, y: np.ndarray, r: float) -> float:
    n = len(y)
    rss = np.maximum(_rss(cid, idx, y, r), 1e-300)
    return float(np.sum(n * np.log(rss / n)))


def _fit_rate(cid: np.ndarray, idx: np.ndarray, y: np.ndarray) -> float:
    # The factor must stay positive over the session.
    hi = min(R_BOUND, 0.99 / max(idx.max() - 1.0, 1.0)) if idx.max() > 1 else R_BOUND
    res = minimize_scalar(
        lambda r: _m2ll(cid, idx, y, r), bounds=(-hi, R_BOUND), method="bounded",
        options={"xatol": 1e-6},
    )  # fmt: skip
    return float(res.x)


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
    r_hat = _fit_rate(cid, idx, y)
    m1 = _m2ll(cid, idx, y, r_hat)
    d_m2ll = m0 - m1
    d_bic = -d_m2ll + math.log(n * len(PARAMS))

    def excess(r: float) -> float:
        return _m2ll(cid, idx, y, r) - m1 - 3.84

    lo = hi = float("nan")
    span = 0.99 / max(idx.max() - 1.0, 1.0)
    try:
        a = -min(R_BOUND, span)
        lo = brentq(excess, a, r_hat) if excess(a) > 0 else a
        hi = brentq(excess, r_hat, R_BOUND) if excess(R_BOUND) > 0 else R_BOUND
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
        r_i = _fit_rate(cid[others], idx[others], y[others])
        f0 = np.log(1.0 + r0 * (idx[same] - 1.0))
        pred0 = (y[same] - f0[:, None]).mean(axis=0) + np.log(1.0 + r0 * (idx[i] - 1.0))
        press0 += (y[i] - pred0) ** 2
        f_same = np.log(1.0 + r_i * (idx[same] - 1.0))
        pred = (y[same] - f_same[:, None]).mean(axis=0) + np.log(1.0 + r_i * (idx[i] - 1.0))
        press1 += (y[i] - pred) ** 2
        counted += 1
    gain = float(np.sum(counted * np.log(np.maximum(press0, 1e-300) / np.maximum(press1, 1e-300))))

    ok_bic = d_bic < -MIN_DBIC
    ok_ho = gain > MIN_HELD_OUT
    passed = ok_bic and ok_ho
    if passed:
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
    )
