"""Fourier coefficients, admittance FRF, coherence and noise, per trial and per group.

Conventions
    Fourier coefficient of a period of P samples at bin k: X_k = (2/P) Σ_n x[n] e^{-2πi k n/P},
    so a sine of amplitude a on bin k has |X_k| = a (rad for θ, N·m for torques). Each period
    of each repetition is one spectrum ("segment"), as in Welch's method with non-overlapping,
    rectangular windows; whole periods make the rectangular window exact at the excited bins.

Estimator (closed loop, the perturbation as instrument)
    For each band, sums over its bins b, the periods p and the repetitions r:
        S_xy = mean_{r,p,b} conj(X) · Y
        Ĥ    = S_{Tp,θ} / S_{Tp,Td}                     rad/N·m, at the band's mean frequency
        Γ    = sqrt(|S_{Tp,θ}|² / (S_{Tp,Tp} S_{θ,θ}))  coherence, 0..1
    With one bin in one segment Γ is exactly 1 whatever the noise (a single complex product has
    the magnitude of the product of magnitudes); it is the averaging over bins, periods and
    repetitions that makes Γ informative. ``n_averaged`` says how many products were averaged.

Drift (the non-periodic part's jump)
    A period is a rectangular window on θ and Td, whose non-periodic part (the remnant, which
    wanders slowly: most of its power is below 0.1 Hz) does not end where it began. The jump
    Δ = x[start + P] − x[start] leaks into every bin as Δ/(jπk) (in the scaling above): a
    *real* random amplitude times a fixed complex direction, the same in every band. At the
    high bands of the stiff conditions, where θ's response is a few encoder counts, that leak
    was the largest error of Ĥ: twice the noise-bin variance, one-directional (along or across
    Ĥ: a standard error right for one contact parameter and wrong for the other) and correlated
    between bands (Monte-Carlo, docs/method-estimator.md). Subtracting the ramp Δ·n/P from each
    period of θ and Td removes it exactly, and nothing of the periodic part: x_per[start + P] =
    x_per[start] (first-order case of the local polynomial method, Pintelon & Schoukens,
    *System Identification*, 2nd ed., ch. 7). The sample after a period is the next period's
    first, or the recording's next sample (the engine records a fade-out after the last
    period); a period that ends the recording is left as it is (an extrapolated sample would
    add a ramp of the periodic part's curvature). Tp is periodic by design and left as it is.

Noise
    At the unexcited bins next to each band (``noise_bins_per_side`` on each side) only the
    driver's remnant and sensor noise remain. Reported per band: mean |Θ|² and |Td|² there (in
    the squared-amplitude units above, directly comparable with the excited bins' power), and
    the variance of Ĥ those bins imply: the estimator's error is
    Σ conj(Tp)·e / Σ conj(Tp)·Td with e = θ − H·Td the part of θ not driven through H, and e is
    measured at the noise bins as θ − Ĥ_band·Td, so
        var(Ĥ) ≈ mean|e|² · Σ|Tp|² / |Σ conj(Tp)·Td|²        (first order in the noise)

Remnant in Td (errors in variables)
    The remnant drives Td as well as θ, so S_TpTd carries noise (a share
    r = Σ|Tp|²·E|Td_noise|²/|S_TpTd|² of its power) correlated with Ĥ's error (ρ ≈ 1: one
    source behind both). A fit whose weights grow with |S_TpTd|² pulls that error in:
    E[|S_TpTd|²(Ĥ − H)] = Σ|Tp|²·E[e·conj(Td_noise)]. ``H_compensated`` removes it with the
    noise bins' cross-spectrum, Ĥ − Σ|Tp|²·mean(e·conj(Td))/q, and ``H_variance_smooth`` uses
    q = |S_TpTd|² − Σ|Tp|²·mean|Td|² (unbiased for the noise-free |E S_TpTd|²) in place of
    |S_TpTd|²; bands whose noise share exceeds one half are left as they are. ``H`` stays the
    paper's plain ratio (docs/method-estimator.md §1).

Smoothed noise model
    Each band's noise power rests on a few unexcited bins (``noise_bins_per_side`` × 2 per
    period and repetition), so it scatters by ±30 % or more from band to band; weights made of
    it would be about as noisy as the data. The remnant and sensor noise are smooth functions
    of frequency, so :func:`smooth_log_spectrum` fits log power as a local-linear function of
    log frequency (Gaussian kernel, :data:`DEFAULT_SMOOTHING_DECADES` wide) and corrects the
    log-χ² bias. ``H_variance_smooth`` is that smoothed noise power times the band's excitation
    factor Σ|Tp|²/q (above). It is what the default (inverse-variance, maximum-likelihood) fit
    weights with, and what every fit's standard errors use; ``H_variance_log_cov`` is how
    uncertain its log is (the smoother's χ² scatter, :func:`smoothed_log_covariance`, plus
    2r for q), which those standard errors account for (docs/method-estimator.md).

Group level
    See :func:`group_frequency_response`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import special, stats

from steerlab.analysis.periods import (
    DEFAULT_DETECT_BELOW_MAX_DB,
    DEFAULT_DETECT_FLOOR_DB,
    DEFAULT_MIN_RUN_IN_S,
    Excitation,
    PeriodSelection,
    find_excitation,
    select_periods,
)
from steerlab.protocols.records import TrialRecord

DEFAULT_NOISE_BINS_PER_SIDE = 2  # the paper's design leaves two free bins between low bands
# Kernel width (SD, in decades of frequency) of the noise smoothing: about ±5 bands of the
# paper's design around 1 Hz, narrow enough to follow a remnant corner anywhere in 0.05–1 Hz.
DEFAULT_SMOOTHING_DECADES = 0.10
# Local polynomial degree in log-log: quadratic follows the knee of the noise spectrum at the
# arm's resonance (2–5 Hz), which a local line over the same width flattens (docs/
# method-estimator.md: the linear smoother put the noise there 2–4 × too low in PT).
DEFAULT_SMOOTHING_DEGREE = 2
# Compensate Ĥ for the remnant's share of S_TpTd only where that share is under half of
# |S_TpTd|²: beyond, the band is noise-dominated and the first-order correction means nothing.
COMPENSATE_ABOVE = 0.5


def smooth_log_spectrum(
    f_hz: np.ndarray,
    power: np.ndarray,
    dof: np.ndarray | float,
    decades: float = DEFAULT_SMOOTHING_DECADES,
    degree: int = DEFAULT_SMOOTHING_DEGREE,
) -> np.ndarray:
    """A smooth estimate of a positive spectrum measured with scatter, on the same frequencies.

    ``power[j]`` is a mean of ``dof[j]/2`` squared magnitudes of complex Gaussian values (a
    scaled χ² with ``dof`` degrees of freedom). log power is regressed on log10 f by a local
    polynomial of ``degree`` (1: local-linear) with Gaussian kernel weights (SD ``decades``),
    each point weighted by its dof; the log of a χ² average is biased by ψ(ν/2) − ln(ν/2),
    which is removed first. Non-finite or non-positive inputs are left out of the regression
    (and get the smooth value). Where the kernel holds too few points for the polynomial, the
    degree is lowered.
    """
    return smooth_log_spectrum_with_covariance(f_hz, power, dof, decades, degree, cov=False)[0]


def _smoothable(f: np.ndarray, v: np.ndarray, nu: np.ndarray) -> np.ndarray:
    return np.isfinite(v) & (v > 0) & np.isfinite(f) & (f > 0) & (nu > 0)


def smoothing_matrix(
    f_hz: np.ndarray,
    dof: np.ndarray,
    ok: np.ndarray,
    decades: float = DEFAULT_SMOOTHING_DECADES,
    degree: int = DEFAULT_SMOOTHING_DEGREE,
) -> np.ndarray:
    """The linear map of :func:`smooth_log_spectrum`: smoothed log power = L @ (bias-corrected
    log power at the ``ok`` frequencies). ``(len(f_hz), ok.sum())``; rows of NaN where f is not
    a positive, finite frequency. Being linear, it also gives the smoothed values' covariance
    (:func:`smoothed_log_covariance`)."""
    f = np.asarray(f_hz, dtype=float)
    nu = np.broadcast_to(np.asarray(dof, dtype=float), f.shape)
    x = np.log10(np.where(f > 0, f, np.nan))
    xo, no = x[ok], nu[ok]
    L = np.full((len(f), len(xo)), np.nan)
    for j in range(len(f)):
        if not (np.isfinite(f[j]) and f[j] > 0):
            continue
        w = no * np.exp(-0.5 * ((xo - x[j]) / decades) ** 2)
        n_eff = int(np.count_nonzero(w > 1e-3 * w.max()))
        deg = min(degree, n_eff - 2)
        if deg < 1:
            L[j] = w / np.sum(w)
            continue
        sw = np.sqrt(w)
        A = np.vander(xo - x[j], deg + 1)  # the constant term, last, is the value at x[j]
        L[j] = np.linalg.pinv(A * sw[:, None])[-1] * sw
    return L


def smoothed_log_covariance(
    f_hz: np.ndarray,
    power: np.ndarray,
    dof: np.ndarray | float,
    decades: float = DEFAULT_SMOOTHING_DECADES,
    degree: int = DEFAULT_SMOOTHING_DEGREE,
) -> np.ndarray:
    """Covariance of log(:func:`smooth_log_spectrum`) between frequencies, from the raw
    values' χ² scatter: L diag(ψ'(ν/2)) Lᵀ (the log of a mean of ν/2 squared complex-normal
    magnitudes has variance ψ'(ν/2); different bands' values are independent). This is how
    uncertain a weight made from the smoothed spectrum is, which the arm fit's standard errors
    account for (docs/method-estimator.md)."""
    log_cov = smooth_log_spectrum_with_covariance(f_hz, power, dof, decades, degree)[1]
    assert log_cov is not None  # asked for (cov=True)
    return log_cov


def smooth_log_spectrum_with_covariance(
    f_hz: np.ndarray,
    power: np.ndarray,
    dof: np.ndarray | float,
    decades: float = DEFAULT_SMOOTHING_DECADES,
    degree: int = DEFAULT_SMOOTHING_DEGREE,
    *,
    cov: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`smooth_log_spectrum` and :func:`smoothed_log_covariance` from one smoothing
    matrix (the fit needs both, and the matrix is the costly part); ``cov=False``: no
    covariance (None)."""
    f = np.asarray(f_hz, dtype=float)
    v = np.asarray(power, dtype=float)
    nu = np.broadcast_to(np.asarray(dof, dtype=float), v.shape)
    ok = _smoothable(f, v, nu)
    if not np.any(ok):
        return np.full(v.shape, np.nan), (np.full((len(f), len(f)), np.nan) if cov else None)
    L = smoothing_matrix(f, nu, ok, decades, degree)
    y = np.log(v[ok]) - (special.digamma(nu[ok] / 2) - np.log(nu[ok] / 2))
    log_cov = (L * special.polygamma(1, nu[ok] / 2)) @ L.T if cov else None
    return np.exp(L @ y), log_cov


def drift_removed(x: np.ndarray, selection: PeriodSelection) -> np.ndarray:
    """``selection.periods(x)`` with each period's non-periodic jump removed (module
    docstring): period p minus (x[end_p] − x[start_p])·n/P, where end_p is the sample after it
    (a period that ends the recording is left as it is)."""
    x = np.asarray(x, dtype=float)
    out = selection.periods(x).copy()
    P = selection.period_samples
    ramp = np.arange(P) / P
    for p in range(selection.n_periods):
        after = selection.start + (p + 1) * P
        if after < len(x):
            out[p] -= (x[after] - out[p, 0]) * ramp
    return out


def fourier_coefficients(periods: np.ndarray, bins: np.ndarray) -> np.ndarray:
    """Amplitude-scaled DFT coefficients at ``bins`` of each row of ``(n_periods, P)``."""
    x = np.atleast_2d(np.asarray(periods, dtype=float))
    return np.fft.rfft(x, axis=1)[:, np.asarray(bins, dtype=int)] * (2.0 / x.shape[1])


@dataclass(frozen=True)
class TrialSpectra:
    """Fourier coefficients of one trial at the excited and at the noise bins.

    ``tp``, ``td``, ``theta``: complex ``(n_periods, n_excited_bins)``, in the order of
    ``excitation.bins``. ``noise_td``, ``noise_theta``: complex ``(n_periods, len(noise_bins))``;
    ``noise_index_of_band[j]`` indexes the columns that belong to band j.
    """

    label: str
    source: str
    selection: PeriodSelection
    excitation: Excitation
    tp: np.ndarray
    td: np.ndarray
    theta: np.ndarray
    noise_bins: np.ndarray
    noise_td: np.ndarray
    noise_theta: np.ndarray
    noise_index_of_band: tuple[np.ndarray, ...]

    @property
    def n_periods(self) -> int:
        return self.selection.n_periods


def trial_spectra(
    record: TrialRecord,
    *,
    selection: PeriodSelection | None = None,
    excitation: Excitation | None = None,
    period_s: float | None = None,
    min_run_in_s: float = DEFAULT_MIN_RUN_IN_S,
    noise_bins_per_side: int = DEFAULT_NOISE_BINS_PER_SIDE,
    detect_floor_db: float = DEFAULT_DETECT_FLOOR_DB,
    detect_below_max_db: float = DEFAULT_DETECT_BELOW_MAX_DB,
    remove_drift: bool = True,
) -> TrialSpectra:
    """Choose the periods and bins of ``record`` (unless given) and take the coefficients
    (θ and Td with each period's drift removed unless ``remove_drift`` is False)."""
    where = record.source or record.label()
    if selection is None:
        selection = select_periods(record, period_s=period_s, min_run_in_s=min_run_in_s)
    if excitation is None:
        excitation = find_excitation(
            record, selection, floor_db=detect_floor_db, below_max_db=detect_below_max_db
        )
    channels = {}
    for name in ("perturbation_torque_Nm", "driver_torque_Nm", "wheel_angle_rad"):
        x = selection.periods(getattr(record, name))
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{where}: {name} has non-finite samples in the analysed periods")
        if remove_drift and name != "perturbation_torque_Nm":
            x = drift_removed(getattr(record, name), selection)
            if not np.all(np.isfinite(x)):  # a non-finite sample just after the periods
                x = selection.periods(getattr(record, name))
        channels[name] = x
    per_band = excitation.noise_bins(noise_bins_per_side, selection.period_samples // 2)
    noise_bins, inverse = np.unique(np.concatenate(per_band), return_inverse=True)
    # np.unique's inverse maps the concatenation back; split it per band again.
    bounds = np.cumsum([len(b) for b in per_band])[:-1]
    index_of_band = tuple(np.split(inverse.astype(int), bounds))
    bins = excitation.bins
    td, th = channels["driver_torque_Nm"], channels["wheel_angle_rad"]
    return TrialSpectra(
        label=record.label(),
        source=record.source,
        selection=selection,
        excitation=excitation,
        tp=fourier_coefficients(channels["perturbation_torque_Nm"], bins),
        td=fourier_coefficients(td, bins),
        theta=fourier_coefficients(th, bins),
        noise_bins=noise_bins,
        noise_td=fourier_coefficients(td, noise_bins),
        noise_theta=fourier_coefficients(th, noise_bins),
        noise_index_of_band=index_of_band,
    )


def _phase_deg(h: np.ndarray) -> np.ndarray:
    # Unwrapped along frequency, so a phase passing −180° stays continuous on a Bode plot.
    return np.degrees(np.unwrap(np.angle(h)))


@dataclass(frozen=True)
class FrequencyResponse:
    """Admittance estimate θ/Td of one subject × condition, one value per band.

    Units: H in rad/N·m; powers in squared amplitude per bin (rad², N·m²).
    """

    frequencies_hz: np.ndarray
    H: np.ndarray  # complex
    coherence: np.ndarray
    n_averaged: np.ndarray  # int: products averaged per band (bins × periods × repetitions)
    power_theta_rad2: np.ndarray  # mean |Θ|² at the band's bins
    power_td_Nm2: np.ndarray
    noise_theta_rad2: np.ndarray  # mean |Θ|² at the neighbouring unexcited bins
    noise_td_Nm2: np.ndarray
    H_variance: np.ndarray  # first-order variance of Ĥ implied by the noise bins, (rad/N·m)²
    bins_of_band: tuple[tuple[int, ...], ...]
    period_s: float
    # How each band's estimate mixes its bins: Ĥ_band = Σ_i bin_weights[j, i] · H(bin_frequencies
    # [j, i]) for a noise-free linear system (the weights are each bin's share of S_{Tp,Td}; they
    # sum to 1). Lone-bin bands are padded with weight 0. Lets a fit compare like with like.
    bin_frequencies_hz: np.ndarray  # (n_bands, max bins per band)
    bin_weights: np.ndarray  # complex, same shape
    trials: tuple[str, ...] = ()
    # The same variance from the noise power smoothed across frequency (module docstring);
    # None only for hand-built responses.
    H_variance_smooth: np.ndarray | None = None
    noise_dof: np.ndarray | None = None  # real degrees of freedom of each band's noise power
    fs_hz: float | None = None  # the recording's sample rate (None if the trials differ)
    # Covariance of log H_variance_smooth between bands (smoothed_log_covariance): the weights
    # made from it are estimates, which the fit's standard errors account for.
    H_variance_log_cov: np.ndarray | None = None
    # Ĥ with the remnant's share of S_TpTd removed (module docstring), what the
    # maximum-likelihood fit compares the model with; None only for hand-built responses.
    H_compensated: np.ndarray | None = None

    @property
    def magnitude(self) -> np.ndarray:
        return np.abs(self.H)

    @property
    def phase_deg(self) -> np.ndarray:
        return _phase_deg(self.H)

    def to_dict(self) -> dict:
        return {
            "frequencies_Hz": self.frequencies_hz.tolist(),
            "H_real_rad_per_Nm": self.H.real.tolist(),
            "H_imag_rad_per_Nm": self.H.imag.tolist(),
            "magnitude_rad_per_Nm": self.magnitude.tolist(),
            "phase_deg": self.phase_deg.tolist(),
            "coherence": self.coherence.tolist(),
            "n_averaged": self.n_averaged.tolist(),
            "power_theta_rad2": self.power_theta_rad2.tolist(),
            "power_td_Nm2": self.power_td_Nm2.tolist(),
            "noise_theta_rad2": self.noise_theta_rad2.tolist(),
            "noise_td_Nm2": self.noise_td_Nm2.tolist(),
            "H_sd_rad_per_Nm": np.sqrt(self.H_variance).tolist(),
            "H_sd_smoothed_rad_per_Nm": (
                None if self.H_variance_smooth is None else np.sqrt(self.H_variance_smooth).tolist()
            ),
            "bins_of_band": [list(b) for b in self.bins_of_band],
            "period_s": self.period_s,
            "trials": list(self.trials),
        }


def frequency_response(spectra: TrialSpectra | Sequence[TrialSpectra]) -> FrequencyResponse:
    """Ĥ, Γ and noise per band, averaged over bins, periods and the given repetitions."""
    items = [spectra] if isinstance(spectra, TrialSpectra) else list(spectra)
    if not items:
        raise ValueError("frequency_response needs at least one trial")
    exc = items[0].excitation
    for s in items[1:]:
        if not s.excitation.same_bins(exc):
            raise ValueError(
                f"{s.source or s.label} was perturbed at other bins than "
                f"{items[0].source or items[0].label}; their spectra cannot be averaged"
            )
    nb = exc.n_bands
    band = exc.band_of_bin
    # Stack every (repetition, period) as a row; columns are the excited bins.
    tp = np.concatenate([s.tp for s in items])
    td = np.concatenate([s.td for s in items])
    th = np.concatenate([s.theta for s in items])

    def band_sum(x: np.ndarray) -> np.ndarray:
        return np.array([x[:, band == j].sum() for j in range(nb)])

    n_avg = np.array([tp.shape[0] * np.count_nonzero(band == j) for j in range(nb)])
    s_tp_th = band_sum(np.conj(tp) * th)
    s_tp_td = band_sum(np.conj(tp) * td)
    s_tp_tp = band_sum(np.abs(tp) ** 2).real
    s_th_th = band_sum(np.abs(th) ** 2).real
    s_td_td = band_sum(np.abs(td) ** 2).real
    with np.errstate(divide="ignore", invalid="ignore"):
        H = s_tp_th / s_tp_td
        coh = np.sqrt(np.abs(s_tp_th) ** 2 / (s_tp_tp * s_th_th))

    noise_th = np.empty(nb)
    noise_td = np.empty(nb)
    resid = np.empty(nb)
    cross = np.full(nb, np.nan, dtype=complex)  # mean e·conj(Td) at the noise bins
    dof = np.zeros(nb)
    for j in range(nb):
        nth = np.concatenate([s.noise_theta[:, s.noise_index_of_band[j]] for s in items])
        ntd = np.concatenate([s.noise_td[:, s.noise_index_of_band[j]] for s in items])
        noise_th[j] = np.mean(np.abs(nth) ** 2) if nth.size else np.nan
        noise_td[j] = np.mean(np.abs(ntd) ** 2) if ntd.size else np.nan
        e = nth - H[j] * ntd
        resid[j] = np.mean(np.abs(e) ** 2) if nth.size else np.nan
        if nth.size:
            cross[j] = np.mean(e * np.conj(ntd))
        dof[j] = 2 * nth.size
    with np.errstate(divide="ignore", invalid="ignore"):
        excitation_factor = s_tp_tp / np.abs(s_tp_td) ** 2
        H_var = resid * excitation_factor
        # The remnant drives both θ and Td, so S_TpTd's noise is correlated with Ĥ's error, and
        # |S_TpTd|² over-states the excitation by the noise's share (module docstring).
        q = np.abs(s_tp_td) ** 2 - s_tp_tp * noise_td
        usable = np.isfinite(q) & (q > COMPENSATE_ABOVE * np.abs(s_tp_td) ** 2)
        q = np.where(usable, q, np.abs(s_tp_td) ** 2)
        H_comp = np.where(usable & np.isfinite(cross), H - s_tp_tp * cross / q, H)
        r = s_tp_tp * noise_td / q  # relative noise variance of S_TpTd
        smooth_resid, log_cov = smooth_log_spectrum_with_covariance(
            exc.band_frequencies_hz, resid, dof
        )
        H_var_smooth = smooth_resid * s_tp_tp / q
    # log q scatters by 2r (|1 + x|² with x complex normal of variance r), independently of
    # the noise bins: the other half of the weights' own uncertainty.
    log_cov = log_cov + np.diag(np.where(np.isfinite(r), 2.0 * r, 0.0))
    # θ_b = H(f_b)·Td_b at each bin, so Ĥ = Σ_b H(f_b)·c_b / Σ_b c_b with c_b = Σ conj(Tp)·Td.
    width = max(np.count_nonzero(band == j) for j in range(nb))
    bin_f = np.repeat(exc.band_frequencies_hz[:, None], width, axis=1)
    bin_w = np.zeros((nb, width), dtype=complex)
    c = (np.conj(tp) * td).sum(axis=0)
    for j in range(nb):
        cols = np.nonzero(band == j)[0]
        bin_f[j, : len(cols)] = exc.bins[cols] / exc.period_s
        bin_w[j, : len(cols)] = c[cols] / s_tp_td[j]

    return FrequencyResponse(
        frequencies_hz=exc.band_frequencies_hz,
        H=H,
        coherence=coh,
        n_averaged=n_avg,
        power_theta_rad2=s_th_th / n_avg,
        power_td_Nm2=s_td_td / n_avg,
        noise_theta_rad2=noise_th,
        noise_td_Nm2=noise_td,
        H_variance=H_var,
        bins_of_band=tuple(tuple(int(b) for b in exc.bins_of_band(j)) for j in range(nb)),
        period_s=exc.period_s,
        bin_frequencies_hz=bin_f,
        bin_weights=bin_w,
        trials=tuple(s.label for s in items),
        H_variance_smooth=H_var_smooth,
        noise_dof=dof,
        fs_hz=_common_rate([s.selection.fs_hz for s in items]),
        H_variance_log_cov=log_cov,
        H_compensated=H_comp,
    )


def _common_rate(rates: Sequence[float | None]) -> float | None:
    """The one sample rate of several recordings, or None when they differ or one is unknown."""
    if not rates or any(r is None for r in rates):
        return None
    r0 = float(rates[0])  # type: ignore[arg-type]
    return r0 if all(abs(float(r) - r0) <= 1e-9 * r0 for r in rates) else None  # type: ignore[arg-type]


@dataclass(frozen=True)
class GroupFrequencyResponse:
    """Mean over subjects of their complex Ĥ, with confidence intervals per band.

    ``H`` is the plain complex mean (the average of the per-subject Fourier-coefficient
    estimates, the paper's group estimate, what the paper weighting fits); ``H_compensated`` the
    mean of the subjects' compensated Ĥ (:class:`FrequencyResponse`), what the default
    (inverse-variance) group fit compares the model with, as every subject's fit does.
    Intervals, all Student-t with n−1 degrees of freedom:

    - ``real_ci``/``imag_ci``: on the real and imaginary parts: the interval of the complex
      mean itself, per coefficient.
    - ``magnitude_ci``: on log|Ĥ|, mapped back: admittance differs between subjects by
      factors, not by amounts, so log-magnitude is closer to normal and the interval can never
      reach zero; it is what a Bode magnitude plot shows.
    - ``phase_ci_deg``: on each subject's phase relative to the mean's phase
      (angle(Ĥ_s / H)), so the ±180° wrap never splits the subjects.

    Intervals are NaN with fewer than two subjects.
    """

    frequencies_hz: np.ndarray
    H: np.ndarray
    coherence: np.ndarray  # mean of the subjects' coherence
    n_subjects: int
    subjects: tuple[str, ...]
    confidence: float
    real_ci: tuple[np.ndarray, np.ndarray]
    imag_ci: tuple[np.ndarray, np.ndarray]
    magnitude_ci: tuple[np.ndarray, np.ndarray]
    phase_ci_deg: tuple[np.ndarray, np.ndarray]
    subject_H: np.ndarray  # complex (n_subjects, n_bands)
    # Variance of the complex mean from the spread between subjects, Σ|Ĥ_s − H|² / (n(n−1)):
    # the uncertainty of the group estimate, used for the group fit's standard errors.
    H_variance: np.ndarray
    # Mean over subjects of their bin weights (see FrequencyResponse): how the group mean mixes
    # the bins of each band, to first order.
    bin_frequencies_hz: np.ndarray
    bin_weights: np.ndarray
    # The spread between subjects of the estimate the default fit compares with (the
    # compensated Ĥ where every subject has one), smoothed across frequency
    # (smooth_log_spectrum, 2(n−1) degrees of freedom); with one subject, that subject's own
    # smoothed noise variance.
    H_variance_smooth: np.ndarray | None = None
    fs_hz: float | None = None  # the subjects' common sample rate (None if they differ)
    H_variance_log_cov: np.ndarray | None = None  # as in FrequencyResponse
    # Mean of the subjects' compensated Ĥ (theirs where they have none); None only when no
    # subject has one (hand-built responses).
    H_compensated: np.ndarray | None = None

    @property
    def magnitude(self) -> np.ndarray:
        return np.abs(self.H)

    @property
    def phase_deg(self) -> np.ndarray:
        return _phase_deg(self.H)

    def to_dict(self) -> dict:
        pct = round(100 * self.confidence)
        return {
            "frequencies_Hz": self.frequencies_hz.tolist(),
            "H_real_rad_per_Nm": self.H.real.tolist(),
            "H_imag_rad_per_Nm": self.H.imag.tolist(),
            "magnitude_rad_per_Nm": self.magnitude.tolist(),
            "phase_deg": self.phase_deg.tolist(),
            "coherence_mean": self.coherence.tolist(),
            "n_subjects": self.n_subjects,
            "subjects": list(self.subjects),
            "confidence": self.confidence,
            f"H_real_ci{pct}_rad_per_Nm": [a.tolist() for a in self.real_ci],
            f"H_imag_ci{pct}_rad_per_Nm": [a.tolist() for a in self.imag_ci],
            f"magnitude_ci{pct}_rad_per_Nm": [a.tolist() for a in self.magnitude_ci],
            f"phase_ci{pct}_deg": [a.tolist() for a in self.phase_ci_deg],
            "H_sd_of_mean_rad_per_Nm": np.sqrt(self.H_variance).tolist(),
        }


def group_frequency_response(
    responses: Sequence[FrequencyResponse],
    *,
    subjects: Sequence[str] | None = None,
    confidence: float = 0.95,
) -> GroupFrequencyResponse:
    """Average per-subject responses (one per subject, same bands) with intervals."""
    if not responses:
        raise ValueError("group_frequency_response needs at least one subject")
    f0 = responses[0]
    for r in responses[1:]:
        if r.bins_of_band != f0.bins_of_band or abs(r.period_s - f0.period_s) > 1e-9:
            raise ValueError("subjects' frequency responses are on different bands")
    Hs = np.array([r.H for r in responses])
    n = len(responses)
    H = Hs.mean(axis=0)
    if n > 1:
        t = stats.t.ppf(0.5 + confidence / 2, n - 1)

        def interval(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            m, half = x.mean(axis=0), t * x.std(axis=0, ddof=1) / np.sqrt(n)
            return m, m - half, m + half

        _, re_lo, re_hi = interval(Hs.real)
        _, im_lo, im_hi = interval(Hs.imag)
        _, lm_lo, lm_hi = interval(np.log(np.abs(Hs)))
        _, ph_lo, ph_hi = interval(np.angle(Hs / H))
        ph = _phase_deg(H)
        mag_ci = (np.exp(lm_lo), np.exp(lm_hi))
        ph_ci = (ph + np.degrees(ph_lo), ph + np.degrees(ph_hi))
    else:
        nan = np.full(H.shape, np.nan)
        re_lo = re_hi = im_lo = im_hi = nan
        mag_ci = ph_ci = (nan, nan)
    names = tuple(subjects) if subjects is not None else tuple(str(i) for i in range(n))
    H_var = (
        np.sum(np.abs(Hs - H) ** 2, axis=0) / (n * (n - 1)) if n > 1 else np.full(H.shape, np.nan)
    )
    # The subjects' compensated Ĥ: the default group fit then compares the model with the same
    # estimate as the subjects' own fits, whose parameters it is read against.
    comp = [r.H_compensated for r in responses]
    have_comp = any(c is not None for c in comp)
    Hcs = np.array([r.H if c is None else c for r, c in zip(responses, comp, strict=True)])
    H_comp = Hcs.mean(axis=0) if have_comp else None
    # One subject: no spread between subjects, but that subject's own noise still says how well
    # each band is known (what the fit's weights and SEMs need).
    var_smooth: np.ndarray | None
    var_log_cov: np.ndarray | None
    if n > 1:
        # The fit's noise model: the spread of what it fits (the compensated Ĥ by default).
        H_var_fit = np.sum(np.abs(Hcs - Hcs.mean(axis=0)) ** 2, axis=0) / (n * (n - 1))
        var_smooth, var_log_cov = smooth_log_spectrum_with_covariance(
            f0.frequencies_hz, H_var_fit, 2.0 * (n - 1)
        )
    else:
        var_smooth, var_log_cov = f0.H_variance_smooth, f0.H_variance_log_cov
    return GroupFrequencyResponse(
        frequencies_hz=f0.frequencies_hz,
        H=H,
        coherence=np.array([r.coherence for r in responses]).mean(axis=0),
        n_subjects=n,
        subjects=names,
        confidence=confidence,
        real_ci=(re_lo, re_hi),
        imag_ci=(im_lo, im_hi),
        magnitude_ci=mag_ci,
        phase_ci_deg=ph_ci,
        subject_H=Hs,
        H_variance=H_var,
        bin_frequencies_hz=f0.bin_frequencies_hz,
        bin_weights=np.mean([r.bin_weights for r in responses], axis=0),
        H_variance_smooth=var_smooth,
        fs_hz=_common_rate([r.fs_hz for r in responses]),
        H_variance_log_cov=var_log_cov,
        H_compensated=H_comp,
    )
