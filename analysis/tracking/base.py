"""What every tracking estimator takes and gives, and the one simulation that scores them all.

A time-varying trial (:class:`TrackingTrial`) holds the loop's signals; an estimator returns a
:class:`TrackedAdmittance`: the arm parameters (k_i, b_i, k_c, b_c; I_i held) at every sample.
Its ``theta_hat`` is **not** the estimator's own prediction: it is the wheel angle that the arm
model with those parameter trajectories gives when driven by the measured driver torque alone
(:func:`simulate_time_varying`), the same output-error simulation for every estimator. A
one-step-ahead predictor that re-reads the measured angle would score a VAF near 100 % for any
parameters; this one scores the parameters.

The arm model (docs/method.md), torque on the hands T_d → wheel angle θ:

    I_i θ_h'' + b_i θ_h' + k_i θ_h = T_d (+ remnant)        intrinsic
    b_c q' + k_c q = T_d,   θ = θ_h + q                     contact in series

discretised per sample with the trapezoidal rule (Tustin) at the parameters of that sample.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from numba import njit
from scipy import signal

from steerlab.protocols.protocol import VirtualWheel
from steerlab.protocols.records import TrialRecord
from steerlab.protocols.session import ConditionSchedule

if TYPE_CHECKING:
    from steerlab.analysis.tracking.calibration import Calibration

TRACKED = ("b_i", "k_i", "b_c", "k_c")  # the order used in every array here
TRUTH_KEYS = {
    "b_i": "true_b_i_Nms_per_rad",
    "k_i": "true_k_i_Nm_per_rad",
    "b_c": "true_b_c_Nms_per_rad",
    "k_c": "true_k_c_Nm_per_rad",
}


@dataclass(frozen=True)
class TrackingTrial:
    """One trial's loop signals, as the trackers need them (SI units, one value per sample)."""

    fs_hz: float
    perturbation_Nm: np.ndarray
    driver_torque_Nm: np.ndarray
    angle_rad: np.ndarray
    grip_N: np.ndarray
    label: str = ""
    schedule: ConditionSchedule | None = None
    truth: Mapping[str, np.ndarray] | None = None  # TRACKED name → true value (simulated only)
    start: int = 0  # first sample worth scoring (after the perturbation's fade-in)
    truth_grip: np.ndarray | None = None  # the driver's true grip mean (simulated only)

    @property
    def n(self) -> int:
        return len(self.angle_rad)

    @property
    def time_s(self) -> np.ndarray:
        return np.arange(self.n) / self.fs_hz

    @classmethod
    def from_record(cls, rec: TrialRecord) -> TrackingTrial:
        sch = rec.attrs.get("schedule")
        schedule = None
        if sch:
            schedule = ConditionSchedule.from_dict(json.loads(sch) if isinstance(sch, str) else sch)
        truth = None
        if all(k in rec.extra for k in TRUTH_KEYS.values()):
            truth = {n: np.asarray(rec.extra[k], dtype=float) for n, k in TRUTH_KEYS.items()}
        grip_mean = rec.extra.get("true_grip_mean_N")
        run_in = rec.attrs.get("run_in_s")
        start = rec.measured_start or (int(round(float(run_in) * rec.fs_hz)) if run_in else 0)
        return cls(
            fs_hz=float(rec.fs_hz),
            perturbation_Nm=np.asarray(rec.perturbation_torque_Nm, dtype=float),
            driver_torque_Nm=np.asarray(rec.driver_torque_Nm, dtype=float),
            angle_rad=np.asarray(rec.wheel_angle_rad, dtype=float),
            grip_N=np.asarray(rec.grip_force_N, dtype=float),
            label=rec.label() if not rec.source else rec.source,
            schedule=schedule,
            truth=truth,
            start=int(start),
            truth_grip=None if grip_mean is None else np.asarray(grip_mean, dtype=float),
        )


def is_time_varying(rec: TrialRecord) -> bool:
    """Whether a recorded trial changed its task within the trial (has a ``schedule``)."""
    return rec.time_varying


@dataclass
class TrackedAdmittance:
    """Arm parameters over a trial from one estimator.

    ``params[name][k]``: estimate at sample k (N·m/rad, N·m·s/rad), using data up to k for a
    causal estimator, around k otherwise; ``valid[k]`` is False where the estimator has none
    yet (a sliding window still filling); those samples hold the first valid estimate so the
    simulation can run, and metrics leave them out.
    """

    name: str
    fs_hz: float
    params: dict[str, np.ndarray]
    I_i: float
    valid: np.ndarray
    theta_hat: np.ndarray
    causal: bool
    compute_s: float = 0.0
    info: dict = field(default_factory=dict)

    @property
    def time_s(self) -> np.ndarray:
        return np.arange(len(self.valid)) / self.fs_hz

    def matrix(self) -> np.ndarray:
        """(n, 4) in TRACKED order."""
        return np.column_stack([self.params[p] for p in TRACKED])


@runtime_checkable
class TrackingEstimator(Protocol):
    """Every tracker: calibrate once on the stationary conditions, then track any trial."""

    name: str
    causal: bool

    def calibrate(self, calibration: Calibration) -> None: ...

    def track(self, trial: TrackingTrial) -> TrackedAdmittance: ...


# --------------------------------------------------------------------------------------------
# The arm model, one trapezoidal step at a time


@njit(cache=True, inline="always")
def arm_step(th_h, om_h, q, u0, u1, extra, I, bi, ki, bc, kc, h):
    """Advance (θ_h, ω_h, q) one sample: torque u0 → u1 on the hands, ``extra`` the mean
    additional intrinsic torque over the step (remnant). Trapezoidal rule, exact for the
    linear model up to O((ωh)²)."""
    a = 0.5 * h / I
    det = 1.0 + a * bi + 0.25 * h * h * ki / I
    r0 = th_h + 0.5 * h * om_h
    r1 = om_h - a * (ki * th_h + bi * om_h) + a * (u0 + u1 + 2.0 * extra)
    th_n = ((1.0 + a * bi) * r0 + 0.5 * h * r1) / det
    om_n = (-a * ki * r0 + r1) / det
    c = 0.5 * h * kc / bc
    q_n = ((1.0 - c) * q + 0.5 * h * (u0 + u1) / bc) / (1.0 + c)
    return th_n, om_n, q_n


@njit(cache=True)
def _simulate(P, I, td, h):
    n = len(td)
    out = np.empty(n)
    th = om = 0.0
    q = td[0] / P[0, 3] if n else 0.0  # the contact is in equilibrium with the first torque
    for k in range(n):
        out[k] = th + q
        if k + 1 < n:
            th, om, q = arm_step(
                th, om, q, td[k], td[k + 1], 0.0, I, P[k, 0], P[k, 1], P[k, 2], P[k, 3], h
            )
    return out


def simulate_time_varying(params: np.ndarray, I_i: float, torque_Nm: np.ndarray, fs_hz: float):
    """Wheel angle of the arm model with per-sample parameters ``params`` (n, 4 in TRACKED
    order) driven by ``torque_Nm`` from rest (output error: no measured angle enters)."""
    P = np.ascontiguousarray(params, dtype=float)
    td = np.ascontiguousarray(torque_Nm, dtype=float)
    if P.shape != (len(td), 4):
        raise ValueError(f"params {P.shape} must be (n, 4) for {len(td)} samples")
    return _simulate(P, float(I_i), td, 1.0 / fs_hz)


def finish(
    name: str,
    trial: TrackingTrial,
    params: np.ndarray,
    valid: np.ndarray,
    I_i: float,
    causal: bool,
    t0: float,
    info: dict | None = None,
) -> TrackedAdmittance:
    """Fill the samples without an estimate, run the common simulation, wrap the result."""
    P = np.array(params, dtype=float)
    valid = np.asarray(valid, dtype=bool) & np.all(np.isfinite(P) & (P > 0), axis=1)
    if not valid.any():
        raise ValueError(f"{name}: no estimate anywhere in {trial.label or 'the trial'}")
    # Without an estimate (not yet, or a failed local one) a sample holds the last valid one;
    # before the first, the first.
    idx = np.where(valid, np.arange(len(P)), int(np.argmax(valid)))
    P = P[np.maximum.accumulate(idx)]
    compute = time.perf_counter() - t0
    theta_hat = simulate_time_varying(P, I_i, trial.driver_torque_Nm, trial.fs_hz)
    return TrackedAdmittance(
        name=name,
        fs_hz=trial.fs_hz,
        params={p: P[:, i] for i, p in enumerate(TRACKED)},
        I_i=float(I_i),
        valid=valid,
        theta_hat=theta_hat,
        causal=causal,
        compute_s=compute,
        info=dict(info or {}),
    )


def admittance(p: Mapping[str, float], I_i: float, f_hz: np.ndarray) -> np.ndarray:
    """H(f) = θ/T_d of the arm model, rad/(N·m)."""
    s = 2j * np.pi * np.asarray(f_hz, dtype=float)
    return 1.0 / (p["b_c"] * s + p["k_c"]) + 1.0 / ((I_i * s + p["b_i"]) * s + p["k_i"])


def closed_loop_response(
    tp: np.ndarray, fs: float, arm: dict[str, float], I_i: float, wheel: VirtualWheel
) -> tuple[np.ndarray, np.ndarray]:
    """(θ, T_d) of the rig driven by the perturbation alone: wheel with the rendered damping and
    stiffness, the arm model in contact (no remnant, no sensor noise)."""
    Iw, bw, kw = wheel.inertia_kgm2, wheel.damping_nms_per_rad, wheel.stiffness_nm_per_rad
    bi, ki, bc, kc = arm["b_i"], arm["k_i"], arm["b_c"], arm["k_c"]
    A = np.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [-(kw + kc) / Iw, -(bw + bc) / Iw, kc / Iw, bc / Iw],
            [0.0, 0.0, 0.0, 1.0],
            [kc / I_i, bc / I_i, -(kc + ki) / I_i, -(bc + bi) / I_i],
        ]
    )
    B = np.array([[0.0], [1.0 / Iw], [0.0], [0.0]])
    C = np.array([[1.0, 0.0, 0.0, 0.0], [kc, bc, -kc, -bc]])
    out = []
    for row in C:
        num, den = signal.ss2tf(A, B, row[None, :], np.zeros((1, 1)))
        b, a = signal.bilinear(num[0], den, fs)
        out.append(signal.lfilter(b, a, np.asarray(tp, dtype=float)))
    return out[0], out[1]
