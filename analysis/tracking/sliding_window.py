"""Sliding-window LTI identification (after Katzourakis et al. 2014): the arm is assumed
time-invariant inside each window of ``window_s`` seconds, identified there as in the paper's
stationary analysis, and the window slides by ``hop_s``.

Inside a window: Welch cross-spectra with the perturbation as instrument (the driver is in the
loop), Ĥ = S(Tp,θ)/S(Tp,Td) over Hann segments of ``segment_s`` (default half the window;
segments every ``hop_s``, so they overlap), summed over log-spaced frequency bands from two
bins above DC to ``f_max_hz``; then the arm model fitted to Ĥ (:mod:`analysis.tracking.fitting`).

Causal: the estimate at time t uses the window ending at t and is held until the next window;
nothing exists before the first window is full (``valid`` False). A step in the arm shows fully
only once the window has slid past it: the settling time is about the window length.
"""

from __future__ import annotations

import time

import numpy as np

from steerlab.analysis.tracking.base import TRACKED, TrackedAdmittance, TrackingTrial, finish
from steerlab.analysis.tracking.calibration import CalibratedTracker
from steerlab.analysis.tracking.fitting import TrackFitter


def band_edges(f_lo: float, f_hi: float, n_bands: int) -> np.ndarray:
    return np.geomspace(f_lo, f_hi, n_bands + 1)


def segment_spectra(
    trial: TrackingTrial, seg_n: int, hop_n: int, edges: np.ndarray
) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Band-summed (cross-)spectra of Hann segments: (segment end samples, spectra (S, B),
    band centre frequencies, bins per band)."""
    fs = trial.fs_hz
    x = {
        "p": trial.perturbation_Nm,
        "t": trial.driver_torque_Nm,
        "y": trial.angle_rad,
    }
    starts = np.arange(0, trial.n - seg_n + 1, hop_n)
    f = np.fft.rfftfreq(seg_n, 1.0 / fs)
    band = np.searchsorted(edges, f, side="right") - 1
    use = (band >= 0) & (band < len(edges) - 1)
    nb = len(edges) - 1
    win = np.hanning(seg_n)
    idx = starts[:, None] + np.arange(seg_n)[None, :]
    F = {}
    for k, sig in x.items():
        seg = np.asarray(sig, dtype=float)[idx]
        seg = seg - seg.mean(axis=1, keepdims=True)
        F[k] = np.fft.rfft(seg * win, axis=1)[:, use]
    b = band[use]

    def bsum(v: np.ndarray) -> np.ndarray:
        out = np.zeros((v.shape[0], nb), dtype=v.dtype)
        for j in range(nb):
            out[:, j] = v[:, b == j].sum(axis=1)
        return out

    P = F["p"]
    spec = {
        "py": bsum(np.conj(P) * F["y"]),
        "pt": bsum(np.conj(P) * F["t"]),
        "pp": bsum(np.abs(P) ** 2),
        "yy": bsum(np.abs(F["y"]) ** 2),
        "tt": bsum(np.abs(F["t"]) ** 2),
    }
    counts = np.bincount(b, minlength=nb)
    centres = np.array(
        [
            f[use][b == j].mean() if counts[j] else np.sqrt(edges[j] * edges[j + 1])
            for j in range(nb)
        ]
    )
    return starts + seg_n, spec, centres, counts


def ratio_and_weights(spec: dict[str, np.ndarray], counts: np.ndarray):
    """Ĥ and the relative-error weights from (summed) cross-spectra."""
    with np.errstate(divide="ignore", invalid="ignore"):
        H = spec["py"] / spec["pt"]
        g_y = np.abs(spec["py"]) ** 2 / (spec["pp"] * spec["yy"])
        g_t = np.abs(spec["pt"]) ** 2 / (spec["pp"] * spec["tt"])
        g = np.clip(np.minimum(g_y, g_t), 0.0, 0.999)
        w = counts * g / (1.0 - g)
    return H, np.nan_to_num(w, nan=0.0)


class SlidingWindowFRF(CalibratedTracker):
    """Windowed FRF with the perturbation as instrument, then the arm fit; see module doc.
    Of the calibration it uses the fixed inertia, start values and the fit's weak prior."""

    causal = True

    def __init__(
        self,
        window_s: float = 10.0,
        hop_s: float = 0.25,
        segment_s: float | None = None,
        f_max_hz: float = 15.0,
        n_bands: int = 14,
    ) -> None:
        if window_s <= 0 or hop_s <= 0:
            raise ValueError("window_s and hop_s must be > 0")
        self.window_s, self.hop_s = window_s, hop_s
        self.segment_s = segment_s or window_s / 2.0
        if self.segment_s > window_s:
            raise ValueError("segment_s must not exceed window_s")
        self.f_max_hz, self.n_bands = f_max_hz, n_bands
        self.name = f"sliding_window_{window_s:g}s"

    def track(self, trial: TrackingTrial) -> TrackedAdmittance:
        cal = self.calibrated()
        t0 = time.perf_counter()
        fs = trial.fs_hz
        seg_n = int(round(self.segment_s * fs))
        hop_n = max(1, int(round(self.hop_s * fs)))
        win_n = int(round(self.window_s * fs))
        edges = band_edges(2.0 / self.segment_s, self.f_max_hz, self.n_bands)
        ends, spec, centres, counts = segment_spectra(trial, seg_n, hop_n, edges)
        # Window sums by cumulative sums over segments: those with start ≥ end − window.
        cum = {
            k: np.vstack([np.zeros((1, v.shape[1]), v.dtype), np.cumsum(v, 0)])
            for k, v in spec.items()
        }
        fitter = TrackFitter(
            centres, cal.I_i, [{n: p.parameters[n] for n in TRACKED} for p in cal.points],
            cal.middle_point(),
        )  # fmt: skip
        P = np.full((trial.n, 4), np.nan)
        valid = np.zeros(trial.n, dtype=bool)
        starts = ends - seg_n
        t_est = []
        for j, e in enumerate(ends):
            if e < win_n:
                continue
            lo = int(np.searchsorted(starts, e - win_n))
            win = {k: c[j + 1] - c[lo] for k, c in cum.items()}
            H, w = ratio_and_weights(win, counts * (j + 1 - lo))
            p, _ = fitter.fit(H, w)
            nxt = ends[j + 1] if j + 1 < len(ends) else trial.n
            P[e - 1 : nxt] = p  # known at sample e−1 (the window's last), held till the next
            valid[e - 1 : nxt] = True
            t_est.append(e / fs)
        return finish(
            self.name, trial, P, valid, cal.I_i, self.causal, t0,
            {"window_s": self.window_s, "hop_s": self.hop_s, "segment_s": self.segment_s,
             "bands_Hz": centres.tolist()},
        )  # fmt: skip
