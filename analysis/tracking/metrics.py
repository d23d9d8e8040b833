"""How well a tracker did on a trial whose truth is known (simulated), and on any trial (VAF).

- **VAF** of the wheel angle: 100·(1 − Σ(θ − θ̂)²/Σθ²) over the scored span, θ and θ̂ taken
  mean-free there; θ̂ is the output-error simulation of the tracked parameters driven by the
  measured driver torque (:mod:`analysis.tracking.base`). Needs no truth.
- **RMS error of log k_i** against the true k_i, over the scored span where the tracker has an
  estimate; **bias**: the mean of that error, as a percentage (exp(mean) − 1).
- **Settling time** after each step of the task (trials with ``transition = "step"``) where the
  true k_i changes by more than ``min_step`` (a factor): from the step to the first sample from
  which the estimate stays within ±``tol`` (a fraction) of the true k_i for ``dwell_s`` seconds
  (or to the next step, if sooner). A tracker that never does "did not settle" (``None``); the
  summary gives the median over steps, counting those as the whole segment, and the fraction
  that settled. ``strict_settling_s`` is the classic, harsher version: within the band until
  the next step, so any later excursion (noise) counts; RMS error covers those too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from steerlab.analysis.tracking.base import TRACKED, TrackedAdmittance, TrackingTrial

DEFAULT_TOL = 0.15
DEFAULT_MIN_STEP = 1.3
DEFAULT_DWELL_S = 2.0


def vaf_percent(theta: np.ndarray, theta_hat: np.ndarray) -> float:
    th = theta - theta.mean()
    e = th - (theta_hat - theta_hat.mean())
    return float(100.0 * (1.0 - np.sum(e**2) / np.sum(th**2)))


@dataclass
class StepSettling:
    time_s: float  # when the task changed
    k_i_from: float
    k_i_to: float
    settling_s: float | None  # None: did not settle before the next change
    segment_s: float
    strict_settling_s: float | None = None  # within the band until the next change

    @property
    def settling_or_segment_s(self) -> float:
        """Settling time, a step that never settled counting as its whole segment."""
        return self.settling_s if self.settling_s is not None else self.segment_s


@dataclass
class TrackingScore:
    name: str
    label: str
    vaf_percent: float
    rms_log: dict[str, float | None]  # per parameter, log units
    bias_percent: dict[str, float | None]
    steps: list[StepSettling] = field(default_factory=list)
    compute_s: float = 0.0
    causal: bool = True

    @property
    def rms_log_k_i(self) -> float | None:
        return self.rms_log.get("k_i")

    @property
    def bias_k_i_percent(self) -> float | None:
        return self.bias_percent.get("k_i")

    def settling_summary(self) -> tuple[float | None, float | None]:
        """(median settling s, counting unsettled steps as their segment; settled fraction)."""
        if not self.steps:
            return None, None
        vals = [s.settling_or_segment_s for s in self.steps]
        frac = sum(s.settling_s is not None for s in self.steps) / len(self.steps)
        return float(np.median(vals)), float(frac)

    def to_dict(self) -> dict[str, Any]:
        med, frac = self.settling_summary()
        return {
            "estimator": self.name,
            "trial": self.label,
            "causal": self.causal,
            "vaf_percent": self.vaf_percent,
            "rms_log": self.rms_log,
            "bias_percent": self.bias_percent,
            "settling_median_s": med,
            "settled_fraction": frac,
            "steps": [s.__dict__ for s in self.steps],
            "compute_s": self.compute_s,
        }


def _dwell_settling(err: np.ndarray, dwell: int, fs: float) -> float | None:
    """First sample from which ``err`` stays False for ``dwell`` samples (or to the end)."""
    ok = ~err
    n = len(ok)
    # run[i]: how many consecutive good samples start at i.
    run = np.zeros(n + 1, dtype=int)
    for i in range(n - 1, -1, -1):
        run[i] = run[i + 1] + 1 if ok[i] else 0
    hit = np.flatnonzero((run[:n] >= dwell) | ((run[:n] > 0) & (np.arange(n) + run[:n] == n)))
    return float(hit[0] / fs) if len(hit) else None


def score(
    trial: TrackingTrial,
    tracked: TrackedAdmittance,
    *,
    from_s: float | None = None,
    tol: float = DEFAULT_TOL,
    min_step: float = DEFAULT_MIN_STEP,
    dwell_s: float = DEFAULT_DWELL_S,
) -> TrackingScore:
    """Score ``tracked`` on ``trial`` from ``from_s`` (default: the trial's first scored
    sample) to the end."""
    fs = trial.fs_hz
    k0 = trial.start if from_s is None else int(round(from_s * fs))
    span = slice(k0, trial.n)
    vaf = vaf_percent(trial.angle_rad[span], tracked.theta_hat[span])
    rms: dict[str, float | None] = {}
    bias: dict[str, float | None] = {}
    ok = tracked.valid[span]
    for p in TRACKED:
        if trial.truth is None or not ok.any():
            rms[p] = bias[p] = None
            continue
        e = np.log(tracked.params[p][span][ok]) - np.log(trial.truth[p][span][ok])
        rms[p] = float(np.sqrt(np.mean(e**2)))
        bias[p] = float(100.0 * (math.exp(np.mean(e)) - 1.0))
    steps = []
    sch = trial.schedule
    if trial.truth is not None and sch is not None and sch.transition == "step":
        k_true, k_hat = trial.truth["k_i"], tracked.params["k_i"]
        band = math.log(1.0 + tol)
        starts = list(sch.starts) + [trial.n]
        for i in range(1, len(starts) - 1):
            a, b = starts[i], min(starts[i + 1], trial.n)
            if a < k0 or b - a < 2:
                continue
            before, after = k_true[a - 1], k_true[b - 1]
            if max(after / before, before / after) < min_step:
                continue
            err = np.abs(np.log(k_hat[a:b]) - np.log(k_true[a:b])) > band
            err |= ~tracked.valid[a:b]
            bad = np.flatnonzero(err)
            strict: float | None
            if len(bad) == 0:
                strict = 0.0
            elif bad[-1] == b - a - 1:
                strict = None
            else:
                strict = float((bad[-1] + 1) / fs)
            steps.append(
                StepSettling(
                    a / fs,
                    float(before),
                    float(after),
                    _dwell_settling(err, int(round(dwell_s * fs)), fs),
                    (b - a) / fs,
                    strict,
                )
            )
    return TrackingScore(
        tracked.name, trial.label, vaf, rms, bias, steps, tracked.compute_s, tracked.causal
    )
