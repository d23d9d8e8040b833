"""Time-varying admittance: trackers behind one interface, scored on the same trials.

- :class:`GripScheduledLPV` (``lpv``): the paper's LPV model scheduled on grip force;
- :class:`SlidingWindowFRF`: LTI identification in a sliding window (perturbation as instrument);
- :class:`RecursiveLeastSquares`: RLS with forgetting on the arm's differential equation;
- :class:`WaveletTracker`: Morlet-wavelet time-frequency identification;
- :class:`GripInformedEKF` (``grip_ekf``, ours): the LPV prediction as the prior of a Kalman
  filter on the arm model, corrected by the measured perturbation response;
- :class:`analysis.tracking.online.OnlineTracker`: the LPV and ours, one loop sample at a time.

Calibration on the stationary conditions: :class:`Calibration`. Scores: :mod:`.metrics`.
"""

from steerlab.analysis.tracking.base import (
    TRACKED,
    TrackedAdmittance,
    TrackingEstimator,
    TrackingTrial,
    is_time_varying,
    simulate_time_varying,
)
from steerlab.analysis.tracking.calibration import Calibration, CalibrationError
from steerlab.analysis.tracking.kalman import EKFConfig, GripInformedEKF
from steerlab.analysis.tracking.metrics import TrackingScore, score
from steerlab.analysis.tracking.rls import RecursiveLeastSquares
from steerlab.analysis.tracking.scheduled import GripScheduledLPV
from steerlab.analysis.tracking.sliding_window import SlidingWindowFRF
from steerlab.analysis.tracking.timefreq import WaveletTracker


def default_estimators() -> list[TrackingEstimator]:
    """The trackers the benchmark compares, ours last. Where a rival has a free setting, both the
    canonical one and the one that gave it the best angle VAF on the tuning subjects are here
    (sliding window 10 s and 5 s; wavelets of 5 and 3 cycles; RLS memory 1.5 s was best)."""
    return [
        GripScheduledLPV(),
        SlidingWindowFRF(window_s=10.0),
        SlidingWindowFRF(window_s=5.0),
        RecursiveLeastSquares(memory_s=1.5),
        WaveletTracker(n_cycles=5.0),
        WaveletTracker(n_cycles=3.0),
        GripInformedEKF(),
    ]


__all__ = [
    "TRACKED",
    "Calibration",
    "CalibrationError",
    "EKFConfig",
    "GripInformedEKF",
    "GripScheduledLPV",
    "RecursiveLeastSquares",
    "SlidingWindowFRF",
    "TrackedAdmittance",
    "TrackingEstimator",
    "TrackingScore",
    "TrackingTrial",
    "WaveletTracker",
    "default_estimators",
    "is_time_varying",
    "score",
    "simulate_time_varying",
]
