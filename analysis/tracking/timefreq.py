"""Time-frequency identification with Morlet wavelets (after Mulder et al. 2011).

The three signals (perturbation Tp, driver torque Td, angle θ) are decimated to about
``rate_hz`` and transformed with complex Morlet wavelets of ``n_cycles`` cycles at log-spaced
frequencies; the local cross-spectra with the perturbation as instrument, smoothed in time by a
Gaussian ``smooth`` times the wavelet's own width, give Ĥ(t, f) = ⟨W̄_Tp W_θ⟩ / ⟨W̄_Tp W_Td⟩
and a coherence. Every ``hop_s`` the arm model is fitted to Ĥ(t, ·) (:mod:`fitting`).

The time resolution is the wavelet's: n_cycles/(2πf) at frequency f, so the low frequencies,
where k_i shows, resolve seconds, the high ones tenths. Not causal: the wavelets are centred,
each estimate uses data on both sides of its time (offline only).
"""

from __future__ import annotations

import time

import numpy as np
from scipy import signal

from steerlab.analysis.tracking.base import TRACKED, TrackedAdmittance, TrackingTrial, finish
from steerlab.analysis.tracking.calibration import CalibratedTracker
from steerlab.analysis.tracking.fitting import TrackFitter


def morlet_transform(x: np.ndarray, fs: float, freqs: np.ndarray, n_cycles: float) -> np.ndarray:
    """(len(freqs), len(x)) complex wavelet coefficients, unit gain at each centre frequency."""
    out = np.empty((len(freqs), len(x)), dtype=complex)
    for i, f in enumerate(freqs):
        sd = n_cycles / (2 * np.pi * f)
        t = np.arange(-4 * sd, 4 * sd + 1 / fs, 1 / fs)
        w = np.exp(2j * np.pi * f * t) * np.exp(-0.5 * (t / sd) ** 2)
        w /= np.sum(np.abs(w))
        out[i] = signal.fftconvolve(x, w, mode="same")
    return out


def _gauss_smooth(X: np.ndarray, fs: float, sds: np.ndarray) -> np.ndarray:
    out = np.empty_like(X)
    for i, sd in enumerate(sds):
        t = np.arange(-4 * sd, 4 * sd + 1 / fs, 1 / fs)
        g = np.exp(-0.5 * (t / sd) ** 2)
        out[i] = signal.fftconvolve(X[i], g / g.sum(), mode="same")
    return out


class WaveletTracker(CalibratedTracker):
    """Morlet-wavelet Ĥ(t, f) with the perturbation as instrument, then the arm fit. Of the
    calibration it uses the fixed inertia, start values and the fit's weak prior."""

    causal = False

    def __init__(
        self,
        f_lo_hz: float = 0.3,
        f_hi_hz: float = 12.0,
        n_freqs: int = 16,
        n_cycles: float = 5.0,
        smooth: float = 1.5,
        hop_s: float = 0.25,
        rate_hz: float = 100.0,
    ) -> None:
        self.freqs = np.geomspace(f_lo_hz, f_hi_hz, n_freqs)
        self.name = f"wavelet_{n_cycles:g}cyc"
        self.n_cycles, self.smooth, self.hop_s, self.rate_hz = n_cycles, smooth, hop_s, rate_hz

    def track(self, trial: TrackingTrial) -> TrackedAdmittance:
        cal = self.calibrated()
        t0 = time.perf_counter()
        q = max(1, int(round(trial.fs_hz / self.rate_hz)))
        fs = trial.fs_hz / q

        def dec(x):
            x = np.asarray(x, dtype=float) - np.mean(x)
            return signal.decimate(x, q, ftype="fir") if q > 1 else x

        W = {
            k: morlet_transform(dec(x), fs, self.freqs, self.n_cycles)
            for k, x in (
                ("p", trial.perturbation_Nm),
                ("t", trial.driver_torque_Nm),
                ("y", trial.angle_rad),
            )
        }
        sds = self.smooth * self.n_cycles / (2 * np.pi * self.freqs)
        Cp = np.conj(W["p"])
        s_py = _gauss_smooth(Cp * W["y"], fs, sds)
        s_pt = _gauss_smooth(Cp * W["t"], fs, sds)
        s_pp = _gauss_smooth(np.abs(W["p"]) ** 2, fs, sds)
        s_yy = _gauss_smooth(np.abs(W["y"]) ** 2, fs, sds)
        s_tt = _gauss_smooth(np.abs(W["t"]) ** 2, fs, sds)
        with np.errstate(divide="ignore", invalid="ignore"):
            H = s_py / s_pt
            g = np.minimum(np.abs(s_py) ** 2 / (s_pp * s_yy), np.abs(s_pt) ** 2 / (s_pp * s_tt))
            g = np.clip(g, 0.0, 0.999)
            # Independent samples per smoothing window grow with frequency: more weight there.
            w = np.nan_to_num(g / (1 - g) * self.freqs[:, None] / self.freqs[0], nan=0.0)
        fitter = TrackFitter(
            self.freqs, cal.I_i, [{n: p.parameters[n] for n in TRACKED} for p in cal.points],
            cal.middle_point(),
        )  # fmt: skip
        hop = max(1, int(round(self.hop_s * fs)))
        n_dec = H.shape[1]
        idx = np.arange(0, n_dec, hop)
        est = np.array([fitter.fit(H[:, i], w[:, i])[0] for i in idx])
        # Centre times in the original samples; parameters interpolated linearly between them.
        t_orig = idx * q
        P = np.column_stack(
            [np.exp(np.interp(np.arange(trial.n), t_orig, np.log(est[:, j]))) for j in range(4)]
        )
        return finish(
            self.name, trial, P, np.ones(trial.n, dtype=bool), cal.I_i, self.causal, t0,
            {"freqs_Hz": self.freqs.tolist(), "n_cycles": self.n_cycles, "smooth": self.smooth},
        )  # fmt: skip
