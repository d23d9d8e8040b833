"""Putting another device's recording onto a trial's samples: alignment and resampling.

Computation only (no files): ``protocols/tekscan_import.py`` and ``protocols/xdf_import.py`` do
the reading and writing.

**Alignment** of a recording that has no common clock with the trial (a TekScan movie) gives
``lag_s``: a moment at time τ of the other recording is at time ``τ + lag_s`` of the trial
(whose sample i is at ``time_s[i]``, 0 at its first sample).

* :func:`align_by_sync`: a sync event both sides recorded (a trigger frame of the movie and the
  trial's first sample, or one of its marks). The lag is exact up to where in its frame (and in
  its trial sample) the event fell: ``sem_s`` is that uniform error's SD,
  √(frame² + sample²)/√12.
* :func:`align_by_xcorr`: where there is no sync event, the lag that maximises the Pearson
  correlation between the recording and a signal of the trial that saw the same thing (the
  session's own grip force from its glove; else the driver torque's magnitude). The trial's
  signal is first averaged over one recording interval (a centred boxcar: it is sampled far
  faster than the recording, and its noise would otherwise make the correlation jagged from one
  trial sample to the next), then interpolated linearly at the recording's sample times shifted
  by each candidate lag; only lags where the two overlap by at least ``min_overlap`` of the
  shorter one are tried. Search: a grid of half the recording's sample interval over the whole
  admissible range; a fine grid (a tenth of that, no coarser than the trial's sample interval)
  around the :data:`N_CANDIDATES` best peaks, each two recording intervals from a better one (a
  periodic signal has side peaks a period away); a parabola through the best.
  **Uncertainty**: a moving-block bootstrap over the recording's samples (blocks of ``block``
  samples, default ∛K of K; ``n_boot`` replicates, seeded, so the result is reproducible): each
  replicate's correlation is recomputed around the candidates and its peak located as above;
  ``sem_s`` is half the central 68 % range of the replicates' peaks (robust to a few replicates
  jumping to a side peak; when many do, it grows to the distance between the peaks).
  ``other_peak_fraction`` is the share of replicates that peaked at another candidate,
  ``edge_fraction`` the share whose peak was on the edge of its fine window: more than a few
  per cent of either, and the peak is not well defined.

**Resampling** a recording onto the trial's sample times (:func:`resample`):

* ``"linear"``: linear interpolation between the two recorded samples around each trial
  sample; a trial sample before the first or after the last recorded sample, or between two
  recorded samples more than ``max_gap_s`` apart (a dropout), is NaN. No anti-alias filter:
  a recording faster than the trial is sampled, not averaged.
* ``"hold"``: zero-order hold, the latest recorded sample at or before each trial sample (what
  Steerlab's own loop does with the glove's frames); NaN before the first recorded sample and
  where the latest is older than ``max_gap_s``. Causal: it never uses a later sample, at the
  cost of a delay of half a recorded sample interval on average.

:func:`choose_method` picks linear for a regular recording at or above the trial's rate and
hold for a slower or irregular one (markers, events).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LINEAR = "linear"
HOLD = "hold"
METHODS = (LINEAR, HOLD)

#: Above this many multiples of the nominal sample interval, a gap between two recorded samples
#: is a dropout: not bridged by interpolation, not held across.
GAP_INTERVALS = 2.5


class AlignmentError(ValueError):
    """The two signals cannot be aligned as asked (too short, no overlap, flat)."""


def choose_method(nominal_srate_hz: float, trial_fs_hz: float) -> str:
    """Linear for a regular recording at or above the trial's rate, else zero-order hold."""
    if nominal_srate_hz > 0 and nominal_srate_hz >= trial_fs_hz:
        return LINEAR
    return HOLD


def max_gap_for(nominal_srate_hz: float) -> float:
    """The longest gap bridged (linear) or held across (hold): :data:`GAP_INTERVALS` nominal
    sample intervals; unlimited for an irregular recording (nominal rate 0)."""
    return GAP_INTERVALS / nominal_srate_hz if nominal_srate_hz > 0 else math.inf


def resample(
    t_src: np.ndarray,
    v_src: np.ndarray,
    t_dst: np.ndarray,
    *,
    method: str,
    max_gap_s: float = math.inf,
) -> np.ndarray:
    """``v_src`` (n,) or (n, channels) at ``t_src`` (increasing) → values at ``t_dst``, float64,
    NaN where the recording says nothing (see the module docstring)."""
    if method not in METHODS:
        raise ValueError(f"resampling method {method!r}: expected one of {METHODS}")
    t_src = np.asarray(t_src, dtype=float)
    t_dst = np.asarray(t_dst, dtype=float)
    v = np.asarray(v_src, dtype=float)
    one = v.ndim == 1
    if one:
        v = v[:, None]
    out = np.full((len(t_dst), v.shape[1]), np.nan)
    if len(t_src) == 0 or len(t_dst) == 0:
        return out[:, 0] if one else out
    if np.any(np.diff(t_src) < 0):
        order = np.argsort(t_src, kind="stable")
        t_src, v = t_src[order], v[order]
    # The latest recorded sample at or before each trial sample (-1: none).
    i = np.searchsorted(t_src, t_dst, side="right") - 1
    if method == HOLD:
        ok = (i >= 0) & (t_dst - t_src[np.maximum(i, 0)] <= max_gap_s)
        out[ok] = v[i[ok]]
    else:
        eps = 1e-9
        inside = (t_dst >= t_src[0] - eps) & (t_dst <= t_src[-1] + eps)
        lo = np.clip(i, 0, len(t_src) - 1)
        hi = np.clip(i + 1, 0, len(t_src) - 1)
        gap = t_src[hi] - t_src[lo]
        ok = inside & (gap <= max_gap_s)
        for c in range(v.shape[1]):
            out[ok, c] = np.interp(t_dst[ok], t_src, v[:, c])
    return out[:, 0] if one else out


@dataclass(frozen=True)
class Alignment:
    """Where another recording sits on a trial: trial time = recording time + ``lag_s``."""

    lag_s: float
    sem_s: float
    method: str  # "sync" or "cross_correlation"
    detail: str  # how lag and uncertainty were found, for the file and the user
    peak_correlation: float | None = None
    n_samples: int = 0  # recording samples in the overlap at the lag
    overlap_s: float = 0.0
    edge_fraction: float = 0.0  # bootstrap replicates whose peak hit the search window's edge
    other_peak_fraction: float = 0.0  # bootstrap replicates that peaked at another candidate

    def to_trial_time(self, t: np.ndarray) -> np.ndarray:
        return np.asarray(t, dtype=float) + self.lag_s

    def attributes(self) -> dict:
        """The alignment as attributes for the file."""
        out: dict = {
            "alignment_method": self.method,
            "lag_s": self.lag_s,
            "lag_sem_s": self.sem_s,
            "alignment_detail": self.detail,
        }
        if self.peak_correlation is not None:
            out["peak_correlation"] = self.peak_correlation
            out["alignment_samples"] = self.n_samples
            out["alignment_overlap_s"] = self.overlap_s
            out["bootstrap_edge_fraction"] = self.edge_fraction
            out["bootstrap_other_peak_fraction"] = self.other_peak_fraction
        return out


def align_by_sync(
    frame_time_s: float,
    trial_time_s: float,
    *,
    frame_interval_s: float,
    trial_interval_s: float = 0.0,
    what: str = "",
) -> Alignment:
    """A sync event at ``frame_time_s`` of the recording and ``trial_time_s`` of the trial."""
    lag = float(trial_time_s) - float(frame_time_s)
    sem = math.sqrt(frame_interval_s**2 + trial_interval_s**2) / math.sqrt(12.0)
    detail = (
        f"sync event{(' (' + what + ')') if what else ''}: lag = trial time {trial_time_s:.6g} s"
        f" - recording time {frame_time_s:.6g} s; uncertainty: where in its frame"
        f" ({frame_interval_s:.4g} s) and trial sample ({trial_interval_s:.4g} s) the event fell,"
        " uniform: SD = sqrt(frame^2 + sample^2)/sqrt(12)"
    )
    return Alignment(lag_s=lag, sem_s=sem, method="sync", detail=detail)


def _valid(t: np.ndarray, x: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, dtype=float).reshape(-1)
    x = np.asarray(x, dtype=float).reshape(-1)
    if t.shape != x.shape:
        raise AlignmentError(f"{what}: {len(t)} times but {len(x)} values")
    ok = np.isfinite(t) & np.isfinite(x)
    t, x = t[ok], x[ok]
    order = np.argsort(t, kind="stable")
    return t[order], x[order]


def _pearson(X: np.ndarray, R: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column-wise Pearson correlation of X (K, 1) with R (K, M) over the rows W marks."""
    n = W.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = (X * W).sum(axis=0) / n
        mr = (R * W).sum(axis=0) / n
        dx = (X - mx) * W
        dr = (R - mr) * W
        r = (dx * dr).sum(axis=0) / np.sqrt((dx * dx).sum(axis=0) * (dr * dr).sum(axis=0))
    return r, n


def _curve(tau, x, ref_t, ref_x, lags, min_n) -> tuple[np.ndarray, np.ndarray]:
    """Correlation at each lag (NaN where fewer than ``min_n`` samples overlap)."""
    r = np.full(len(lags), np.nan)
    n = np.zeros(len(lags))
    block = max(1, int(2_000_000 // max(len(tau), 1)))
    X = x[:, None]
    for s in range(0, len(lags), block):
        L = lags[s : s + block]
        T = tau[:, None] + L[None, :]
        W = ((T >= ref_t[0]) & (T <= ref_t[-1])).astype(float)
        R = np.interp(T, ref_t, ref_x)
        rb, nb = _pearson(X, R, W)
        rb[nb < min_n] = np.nan
        r[s : s + block], n[s : s + block] = rb, nb
    return r, n


def _peak(lags: np.ndarray, r: np.ndarray) -> tuple[float, float, int]:
    """(lag, value, index) of the curve's maximum, refined by a parabola through it."""
    if not np.any(np.isfinite(r)):
        return math.nan, math.nan, -1
    k = int(np.nanargmax(r))
    lag, val = float(lags[k]), float(r[k])
    if 0 < k < len(r) - 1 and np.isfinite(r[k - 1]) and np.isfinite(r[k + 1]):
        a, b, c = r[k - 1], r[k], r[k + 1]
        den = a - 2 * b + c
        if den < 0:
            d = 0.5 * (a - c) / den
            lag += d * float(lags[1] - lags[0])
            val = float(b - 0.25 * (a - c) * d)
    return lag, val, k


N_CANDIDATES = 5


def _candidates(lags: np.ndarray, r: np.ndarray, separation: float) -> list[int]:
    """Indices of the curve's highest local maxima, each ``separation`` from a higher one."""
    ok = np.isfinite(r)
    rr = np.where(ok, r, -np.inf)
    left = np.concatenate([[-np.inf], rr[:-1]])
    right = np.concatenate([rr[1:], [-np.inf]])
    maxima = np.flatnonzero(ok & (rr >= left) & (rr >= right))
    out: list[int] = []
    for k in maxima[np.argsort(-rr[maxima], kind="stable")]:
        if all(abs(lags[k] - lags[j]) >= separation for j in out):
            out.append(int(k))
        if len(out) == N_CANDIDATES:
            break
    return out


def align_by_xcorr(
    rec_t: np.ndarray,
    rec_x: np.ndarray,
    ref_t: np.ndarray,
    ref_x: np.ndarray,
    *,
    max_lag_s: float | None = None,
    min_overlap: float = 0.5,
    n_boot: int = 200,
    block: int | None = None,
    seed: int = 0,
    reference: str = "reference",
) -> Alignment:
    """The lag that best lines up ``rec_x`` (at ``rec_t``, the other recording's time) with
    ``ref_x`` (at ``ref_t``, trial time), and its bootstrap uncertainty (module docstring)."""
    tau, x = _valid(rec_t, rec_x, "recording")
    ref_t, ref_x = _valid(ref_t, ref_x, reference)
    if len(tau) < 10:
        raise AlignmentError(f"the recording has {len(tau)} usable samples; 10 are needed")
    if len(ref_t) < 2:
        raise AlignmentError(f"{reference}: fewer than 2 usable samples")
    if np.ptp(x) == 0:
        raise AlignmentError("the recording is constant: nothing to correlate")
    if np.ptp(ref_x) == 0:
        raise AlignmentError(f"{reference} is constant: nothing to correlate")
    if not 0 < min_overlap <= 1:
        raise AlignmentError(f"min_overlap must be in (0, 1], got {min_overlap}")
    dt_rec = float(np.median(np.diff(tau)))
    dt_ref = float(np.median(np.diff(ref_t)))
    if not dt_rec > 0:
        raise AlignmentError("the recording's sample times do not increase")
    # The reference is sampled far faster than the recording: averaged over one recording
    # interval (a boxcar), it holds what the recording can see, and its noise no longer makes
    # the correlation curve jagged from one reference sample to the next.
    width = int(round(dt_rec / dt_ref)) // 2 * 2 + 1 if dt_ref > 0 else 1  # odd: centred
    if width > 1:
        ref_x = np.convolve(ref_x, np.ones(width) / width, mode="same")
        edge = width // 2
        ref_t, ref_x = ref_t[edge : len(ref_t) - edge], ref_x[edge : len(ref_x) - edge]
    rec_dur = tau[-1] - tau[0] + dt_rec
    ref_dur = ref_t[-1] - ref_t[0] + dt_ref
    overlap_s = min_overlap * min(rec_dur, ref_dur)
    min_n = max(10, int(math.floor(overlap_s / dt_rec)))
    lo = ref_t[0] - tau[-1] + overlap_s - dt_rec
    hi = ref_t[-1] - tau[0] - overlap_s + dt_rec
    if max_lag_s is not None:
        lo, hi = max(lo, -max_lag_s), min(hi, max_lag_s)
    if not lo <= hi:
        raise AlignmentError(
            f"no lag within ±{max_lag_s} s lets the recording ({rec_dur:.3g} s) and"
            f" {reference} ({ref_dur:.3g} s) overlap by {overlap_s:.3g} s"
        )
    # Coarse: half a recording interval over the whole range.
    h_c = dt_rec / 2
    coarse = np.arange(lo, hi + h_c / 2, h_c)
    r_c, _ = _curve(tau, x, ref_t, ref_x, coarse, min_n)
    best, _, k = _peak(coarse, r_c)
    if k < 0:
        raise AlignmentError(
            f"the recording and {reference} never overlap by {min_n} samples at any lag"
        )
    # Fine: around the best coarse peaks (the global one and up to N_CANDIDATES - 1 others,
    # each at least two recording intervals from a better one: a periodic signal, gait or a
    # steady grip rhythm, has side peaks one period away).
    cand = _candidates(coarse, r_c, 2 * dt_rec)
    h_f = min(h_c / 10, dt_ref)
    half = 4 * h_c
    offsets = np.arange(-half, half + h_f / 2, h_f)
    windows = np.array([coarse[c] + offsets for c in cand])  # (C, F)
    T = tau[:, None] + windows.reshape(-1)[None, :]
    W = ((T >= ref_t[0]) & (T <= ref_t[-1])).astype(float)
    R = np.interp(T, ref_t, ref_x)

    def best_of(rows) -> tuple[float, float, int, bool, int]:
        r, n = _pearson(x[rows, None], R[rows], W[rows])
        r[n < min_n] = np.nan
        found = []
        for w in range(len(cand)):
            cols = slice(w * len(offsets), (w + 1) * len(offsets))
            pl, pv, pk = _peak(windows[w], r[cols])
            if pk >= 0:
                found.append((pv, pl, w, pk in (0, len(offsets) - 1), int(n[cols][pk])))
        if not found:
            return math.nan, math.nan, -1, False, 0
        pv, pl, w, at_edge, n_at = max(found)
        return pl, pv, w, at_edge, n_at

    K = len(tau)
    lag, peak_r, main, _, n_at = best_of(np.arange(K))
    if main < 0:
        raise AlignmentError(f"no correlation around the lag {best:.4g} s")
    # Moving-block bootstrap over the recording's samples, on those windows.
    b = min(block or max(1, round(K ** (1 / 3))), K)
    rng = np.random.default_rng(seed)
    n_blocks = -(-K // b)
    peaks, edge, elsewhere = [], 0, 0
    for _ in range(n_boot):
        starts = rng.integers(0, K - b + 1, size=n_blocks)
        idx = (starts[:, None] + np.arange(b)[None, :]).reshape(-1)[:K]
        pl, _, w, at_edge, _ = best_of(idx)
        if w < 0:
            continue
        peaks.append(pl)
        edge += at_edge
        elsewhere += w != main
    if len(peaks) < 2:
        raise AlignmentError("the bootstrap found no correlation peak")
    lo16, hi84 = np.percentile(peaks, [15.865, 84.135])
    sem = float(hi84 - lo16) / 2
    detail = (
        f"cross-correlation with {reference}: Pearson r over the overlap, lags searched"
        f" {lo:.4g}…{hi:.4g} s (overlap ≥ {overlap_s:.3g} s), grid {h_c:.4g} s, then"
        f" {h_f:.4g} s around the {len(cand)} best peaks and a parabola through the best;"
        f" uncertainty: half the central 68 % range of the peak over {len(peaks)} moving-block"
        f" bootstrap replicates (blocks of {b} of {K} samples, seed {seed}); {elsewhere}"
        " replicate(s) peaked at another candidate"
    )
    return Alignment(
        lag_s=float(lag),
        sem_s=sem,
        method="cross_correlation",
        detail=detail,
        peak_correlation=float(peak_r),
        n_samples=n_at,
        overlap_s=n_at * dt_rec,
        edge_fraction=edge / len(peaks),
        other_peak_fraction=elsewhere / len(peaks),
    )
