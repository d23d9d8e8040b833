"""Arm parameters from a frequency response that changes over time (sliding window, wavelets).

At each analysis time the arm model is fitted to the local estimate Ĥ(f) by weighted least
squares on the *relative* error, (H(f; p) − Ĥ)/|Ĥ|, so low and high frequencies count
alike whatever |H| is; weights w = γ²/(1 − γ²) × (bins averaged), the inverse variance of
that relative error for coherence γ. Parameters are fitted as logarithms (positive, one scale),
I_i held. Each fit starts from the previous time's estimate and, when that fits badly, also
from the best calibration operating point, so a step in the task cannot trap it.

A weak prior (``prior_sd`` in log units, default 2: a factor e² ≈ 7) around the neutral
operating point keeps short windows with little information from running off to a degenerate
model (a term at 0 or ∞). It is the same for every time and does not know the task.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import least_squares

from steerlab.analysis.tracking.base import TRACKED

PRIOR_SD_LOG = 2.0


def _model(x: np.ndarray, I_i: float, s: np.ndarray):
    bi, ki, bc, kc = np.exp(x)
    dc = bc * s + kc
    di = (I_i * s + bi) * s + ki
    H = 1.0 / dc + 1.0 / di
    # d H / d log p = p · dH/dp
    J = np.stack([-bi * s / di**2, -ki / di**2, -bc * s / dc**2, -kc / dc**2], axis=1)
    return H, J


class TrackFitter:
    """Fits one Ĥ(f) after another, warm-started; see the module docstring."""

    def __init__(
        self,
        f_hz: np.ndarray,
        I_i: float,
        starts: Sequence[dict[str, float]],
        prior: dict[str, float],
        prior_sd: float = PRIOR_SD_LOG,
    ) -> None:
        self.s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        self.I_i = float(I_i)
        self.starts = [np.log([p[n] for n in TRACKED]) for p in starts]
        self.x_prior = np.log([prior[n] for n in TRACKED])
        self.prior_sd = prior_sd
        self.x = self.x_prior.copy()

    def _residual(self, x, H, sw):
        Hm, _ = _model(x, self.I_i, self.s)
        e = sw * (Hm - H) / np.abs(H)
        return np.concatenate([e.real, e.imag, (x - self.x_prior) / self.prior_sd])

    def _jacobian(self, x, H, sw):
        _, J = _model(x, self.I_i, self.s)
        Jr = (sw / np.abs(H))[:, None] * J
        return np.vstack([Jr.real, Jr.imag, np.eye(4) / self.prior_sd])

    def fit(self, H: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
        """(parameters in TRACKED order, weighted cost) for one Ĥ(f) with weights w(f)."""
        ok = np.isfinite(H) & (np.abs(H) > 0) & np.isfinite(w) & (w > 0)
        if ok.sum() < 3:
            return np.exp(self.x), float("nan")
        Hs, sw, s_all = H[ok], np.sqrt(w[ok]), self.s
        self.s = s_all[ok]
        try:
            cands = [self.x]
            cost0 = 0.5 * np.sum(self._residual(self.x, Hs, sw) ** 2)
            costs = [0.5 * np.sum(self._residual(x, Hs, sw) ** 2) for x in self.starts]
            if costs and min(costs) < cost0:
                cands.append(self.starts[int(np.argmin(costs))])
            best = None
            for x0 in cands:
                r = least_squares(
                    self._residual, x0, jac=self._jacobian, args=(Hs, sw), method="lm",
                    xtol=1e-8, ftol=1e-8, max_nfev=100,
                )  # fmt: skip
                if best is None or r.cost < best.cost:
                    best = r
            assert best is not None
            self.x = best.x
            return np.exp(best.x), float(best.cost)
        finally:
            self.s = s_all
