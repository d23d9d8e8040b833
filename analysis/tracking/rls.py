"""Recursive least squares with a forgetting factor on the arm's differential equation
(after Olivari et al. 2015, who track with RLS and forgetting).

The arm model θ/T_d = N(s)/D(s) with

    D(s) = b_c I s³ + (b_c b_i + k_c I) s² + (b_c k_i + k_c b_i) s + k_c k_i
    N(s) = I s² + (b_i + b_c) s + (k_i + k_c)

gives, with I = I_i known, one equation linear in six coefficients:

    I s²T_d = a3 s³θ + a2 s²θ + a1 sθ + a0 θ − c1 sT_d − c0 T_d

discretised through a state-variable filter (the same filter F(s) = (ω_f/(s + ω_f))⁴ on every
term, times a high-pass s/(s + ω_h) against slow remnant and offsets; Tustin at the loop rate).
RLS with forgetting factor λ = 1 − 1/(memory_s · f_s) tracks the six coefficients sample by
sample. The arm parameters follow from them every ``hop_s``: the six coefficients overdetermine
the four parameters, and solving for them directly (b_c = a3/I, b_i = c1 − b_c, k_i and k_c the
roots of z² − c0 z + a0) failed on half the samples of our trials (a difference of two noisy
numbers turning negative). So the rational model N/D they define is evaluated at log-spaced
frequencies and the arm model fitted to that response (:mod:`analysis.tracking.fitting`, as the
sliding window and the wavelets do), warm-started.

Equation error in a closed loop: the remnant enters the equation as (b_c s + k_c)·T_rem and is
correlated with θ and T_d (the driver is in the loop), and plain least squares on it is heavily
biased (on our simulated trials every coefficient but a3 came out 4–10× too small). So the
default is recursive *instrumental variables* (``instruments="perturbation"``, after Young's
refined IV): the same recursion with the regressor replaced, in the gain, by instruments built
from the perturbation alone, the filtered derivatives of the angle and torque that the rig (wheel
of the protocol, arm at the calibration's middle operating point) would show without any
remnant. They are uncorrelated with the remnant, so the estimate is consistent; the price is
variance. ``instruments=None`` gives plain RLS (biased, for comparison).
"""

from __future__ import annotations

import time

import numpy as np
from numba import njit
from scipy import signal

from steerlab.analysis.tracking.base import (
    TRACKED,
    TrackedAdmittance,
    TrackingTrial,
    closed_loop_response,
    finish,
)
from steerlab.analysis.tracking.calibration import CalibratedTracker
from steerlab.analysis.tracking.fitting import TrackFitter
from steerlab.protocols.protocol import VirtualWheel


def svf(x: np.ndarray, fs: float, k: int, f_filter_hz: float, f_highpass_hz: float) -> np.ndarray:
    """s^k · F(s) · s/(s + ω_h) applied to x (Tustin), the k-th filtered derivative."""
    wf, wh = 2 * np.pi * f_filter_hz, 2 * np.pi * f_highpass_hz
    den = np.polymul(np.poly1d([1.0, wf]) ** 4, [1.0, wh])
    num = np.zeros(k + 2)
    num[0] = wf**4  # wf⁴ s^(k+1)
    b, a = signal.bilinear(num, np.asarray(den), fs)
    return signal.lfilter(b, a, np.asarray(x, dtype=float))


@njit(cache=True)
def _rls(Phi, Z, y, lam, p0):
    """Recursive (IV-)least squares with forgetting; Z = Phi gives plain RLS."""
    n, m = Phi.shape
    theta = np.zeros(m)
    P = np.eye(m) * p0
    out = np.empty((n, m))
    Pz = np.empty(m)
    phiP = np.empty(m)
    for k in range(n):
        phi = Phi[k]
        z = Z[k]
        e = y[k]
        for i in range(m):
            e -= phi[i] * theta[i]
        den = lam
        for i in range(m):
            acc = 0.0
            acc2 = 0.0
            for j in range(m):
                acc += P[i, j] * z[j]
                acc2 += phi[j] * P[j, i]
            Pz[i] = acc
            phiP[i] = acc2
            den += phi[i] * acc
        for i in range(m):
            theta[i] += Pz[i] / den * e
        for i in range(m):
            for j in range(m):
                P[i, j] = (P[i, j] - Pz[i] * phiP[j] / den) / lam
        # Without excitation P grows without bound (wind-up): cap it at its start value.
        tr = 0.0
        for i in range(m):
            tr += P[i, i]
        if tr > m * p0:
            for i in range(m):
                for j in range(m):
                    P[i, j] *= m * p0 / tr
        out[k] = theta
    return out


class RecursiveLeastSquares(CalibratedTracker):
    """RLS with forgetting on the filtered arm equation; see the module docstring. Of the
    calibration it uses only the fixed inertia I_i: RLS starts from nothing."""

    causal = True

    def __init__(
        self,
        memory_s: float = 1.5,
        f_filter_hz: float = 20.0,
        f_highpass_hz: float = 0.3,
        instruments: str | None = "perturbation",
        wheel: VirtualWheel | None = None,
        hop_s: float = 0.1,
    ) -> None:
        if memory_s <= 0:
            raise ValueError("memory_s must be > 0")
        if instruments not in ("perturbation", None):
            raise ValueError(f"instruments must be 'perturbation' or None, got {instruments!r}")
        self.memory_s, self.f_filter_hz, self.f_highpass_hz = memory_s, f_filter_hz, f_highpass_hz
        self.instruments = instruments
        self.wheel = wheel
        self.hop_s = hop_s
        self.freqs = np.geomspace(0.3, 15.0, 14)
        self.name = f"rls_{memory_s:g}s" if instruments else f"rls_plain_{memory_s:g}s"

    def track(self, trial: TrackingTrial) -> TrackedAdmittance:
        cal = self.calibrated()
        t0 = time.perf_counter()
        fs, I_i = trial.fs_hz, cal.I_i
        th, td = trial.angle_rad, trial.driver_torque_Nm
        ff, fh = self.f_filter_hz, self.f_highpass_hz
        th_k = [svf(th, fs, k, ff, fh) for k in range(4)]
        td_k = [svf(td, fs, k, ff, fh) for k in range(3)]
        Phi = np.column_stack([th_k[3], th_k[2], th_k[1], th_k[0], -td_k[1], -td_k[0]])
        y = I_i * td_k[2]
        # Scale each regressor to unit RMS: the same P0 then means the same for all six.
        scale = np.sqrt(np.mean(Phi[trial.start :] ** 2, axis=0)) + 1e-300
        Phi = np.ascontiguousarray(Phi / scale)
        Z = Phi
        if self.instruments == "perturbation":
            x, v = closed_loop_response(
                trial.perturbation_Nm,
                fs,
                cal.middle_point(),
                I_i,
                self.wheel or cal.wheel,
            )
            x_k = [svf(x, fs, k, ff, fh) for k in range(4)]
            v_k = [svf(v, fs, k, ff, fh) for k in range(2)]
            Z = np.column_stack([x_k[3], x_k[2], x_k[1], x_k[0], -v_k[1], -v_k[0]])
            Z = np.ascontiguousarray(Z / (np.sqrt(np.mean(Z[trial.start :] ** 2, axis=0)) + 1e-300))
        lam = 1.0 - 1.0 / (self.memory_s * fs)
        coef = _rls(Phi, Z, y, lam, 1e4) / scale
        fitter = TrackFitter(
            self.freqs, I_i, [{n: p.parameters[n] for n in TRACKED} for p in cal.points],
            cal.middle_point(),
        )  # fmt: skip
        s = 2j * np.pi * self.freqs
        P = np.full((trial.n, 4), np.nan)
        # The first memory: the estimate is still filling.
        first = trial.start + int(self.memory_s * fs)
        hop = max(1, int(round(self.hop_s * fs)))
        w = np.ones(len(s))
        for k in range(first, trial.n, hop):
            a3, a2, a1, a0, c1, c0 = coef[k]
            H = (I_i * s**2 + c1 * s + c0) / (((a3 * s + a2) * s + a1) * s + a0)
            P[k : k + hop] = fitter.fit(H, w)[0]
        valid = np.arange(trial.n) >= first
        return finish(
            self.name, trial, P, valid, I_i, self.causal, t0,
            {"memory_s": self.memory_s, "lambda": lam, "f_filter_Hz": self.f_filter_hz,
             "f_highpass_Hz": self.f_highpass_hz, "instruments": self.instruments},
        )  # fmt: skip
