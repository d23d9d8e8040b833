"""The paper's tracker: admittance from grip force alone, through the LPV model.

No perturbation is needed at run time: the grip force, smoothed by a first-order low-pass
(``grip_tau_s``, against the glove's frame noise), schedules the physical-parameter LPV model
calibrated on the stationary conditions. It reacts as fast as the grip does, and it is exactly
as right as the grip → admittance relation is: a calibration error, or a task that changes
stiffness without changing grip (RT vs BT18 in the paper), stays in its estimate.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.signal import lfilter

from steerlab.analysis.tracking.base import TrackedAdmittance, TrackingTrial, finish
from steerlab.analysis.tracking.calibration import CalibratedTracker

DEFAULT_GRIP_TAU_S = 0.1


def smooth_grip(grip: np.ndarray, fs_hz: float, tau_s: float) -> np.ndarray:
    """Causal first-order low-pass, started at the first sample (no start-up transient)."""
    g = np.asarray(grip, dtype=float)
    if tau_s <= 0 or len(g) == 0:
        return g.copy()
    a = 1.0 - np.exp(-1.0 / (tau_s * fs_hz))
    y, _ = lfilter([a], [1.0, a - 1.0], g, zi=[(1.0 - a) * g[0]])
    return y


class GripScheduledLPV(CalibratedTracker):
    """LPV model scheduled on the (smoothed) total grip force; calibrate before tracking."""

    name = "lpv"
    causal = True

    def __init__(self, grip_tau_s: float = DEFAULT_GRIP_TAU_S) -> None:
        self.grip_tau_s = grip_tau_s

    def track(self, trial: TrackingTrial) -> TrackedAdmittance:
        cal = self.calibrated()
        t0 = time.perf_counter()
        mu = smooth_grip(trial.grip_N, trial.fs_hz, self.grip_tau_s)
        P = cal.prior(mu)
        return finish(
            self.name,
            trial,
            P,
            np.ones(trial.n, dtype=bool),
            cal.I_i,
            self.causal,
            t0,
            {"grip_tau_s": self.grip_tau_s},
        )
