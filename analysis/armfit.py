"""The paper's arm model fitted to an admittance estimate: parameters, SEMs, FIT% and VAF.

Model (torque on the hands → wheel angle, rad/N·m):

    H(s) = 1/(b_c s + k_c) + 1/(I_i s² + b_i s + k_i)

Fit
    Weighted least squares on the complex error, J(p) = Σ_k w_k |H(f_k; p) − Ĥ_k|² with
    w_k = Γ_k / f_k (coherence, and 1/f to even out the logarithmic spread of the bands), as in
    the paper. The lowest ``n_exclude_low`` bands are left out (default 2, as the paper: the
    remnant dominates there and they inflate the SEMs). The parameters are fitted as logarithms,
    which keeps them positive and puts stiffness (tens) and damping (units) on one scale. Start
    values: rough physical estimates from the data (contact terms from Ĥ at the highest band,
    intrinsic stiffness from the lowest) refined by a coarse grid (×0.1 … ×10 per parameter,
    evaluated at once), then least squares from the best grid points; the best result wins.

Inertia
    I_i is held at :data:`DEFAULT_I_I_KGM2` = 0.1 kg·m² unless ``fit_inertia``: the arms'
    inertia about the column (Pick & Cole 2006, 2008, about 0.1 kg·m²; the same value as
    Steerlab's simulated driver). The paper holds I_i constant without giving its value; a
    lab that wants its own can fit it once (``fit_inertia=True``) and fix it from then on.

Standard errors
    The paper takes them from the Cramér–Rao lower bound, the inverse Fisher information. For a
    weighted least-squares fit that bound is σ² (Jᵀ W J)⁻¹ (J: Jacobian of [Re H; Im H] with
    respect to the free parameters in their own units, W = diag(w), σ² = Σ w|e|² / (2K − n)
    from the weighted residuals), and it holds only if the weights are proportional to the
    inverse variances of Ĥ. Coherence × 1/f weights are not: in our Monte-Carlo checks that
    formula missed the actual spread by factors of about 0.5 to 1.6, depending on the
    parameter. So Steerlab uses, whenever the variance v_k of each Ĥ_k is measured, the
    covariance that holds for any weights,

        cov = A⁻¹ (Jᵀ W Σ W J) A⁻¹,   A = Jᵀ W J,   Σ = diag(v_k/2 for Re and Im)

    which *is* the inverse Fisher information (the Cramér–Rao bound) when W ∝ Σ⁻¹, and agrees
    with the Monte-Carlo spread (tests/analysis). v_k comes from the unexcited bins for one
    subject (:attr:`analysis.frf.FrequencyResponse.H_variance`) and from the spread between
    subjects for a group mean (:attr:`analysis.frf.GroupFrequencyResponse.H_variance`).
    ``sem_method`` says which was used ("noise", or "residual" when no variance is available);
    both versions are kept (``sems_noise``, ``sems_residual``). Neither includes the model's
    lack of fit, which shows in FIT% instead.

FIT% (frequency domain), over the fitted bands:
    FIT = 100·(1 − Σ (1/f)|Ĥ − H_par|² / Σ (1/f)|H_par|²)

VAF (time domain): see :func:`simulate_angle` and :func:`vaf_percent`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
from scipy.optimize import least_squares

PARAM_NAMES = ("I_i", "b_i", "k_i", "b_c", "k_c")
PARAM_UNITS = {
    "I_i": "kgm2",
    "b_i": "Nms_per_rad",
    "k_i": "Nm_per_rad",
    "b_c": "Nms_per_rad",
    "k_c": "Nm_per_rad",
}
DEFAULT_I_I_KGM2 = 0.1
DEFAULT_N_EXCLUDE_LOW = 2
# Search box for the log-parameters: wide enough for any human arm, narrow enough that a poor
# start cannot run off to a degenerate model (a term vanishing at 0 or ∞).
BOUNDS = {
    "I_i": (1e-3, 10.0),
    "b_i": (1e-3, 1e3),
    "k_i": (1e-2, 1e5),
    "b_c": (1e-3, 1e3),
    "k_c": (1e-2, 1e5),
}
N_STARTS = 3  # least-squares runs, from the best points of the start grid


def _key(name: str) -> str:
    return f"{name}_{PARAM_UNITS[name]}"


@dataclass(frozen=True)
class ArmParams:
    """Arm model parameters. Units: kg·m², N·m·s/rad, N·m/rad."""

    I_i: float
    b_i: float
    k_i: float
    b_c: float
    k_c: float

    def as_dict(self) -> dict[str, float]:
        return {n: float(getattr(self, n)) for n in PARAM_NAMES}

    def to_dict(self) -> dict[str, float]:
        """With units in the keys, e.g. ``k_i_Nm_per_rad``."""
        return {_key(n): v for n, v in self.as_dict().items()}

    def admittance(self, f_hz: np.ndarray | float) -> np.ndarray:
        return arm_admittance(self, f_hz)


def arm_admittance(params: ArmParams | Mapping[str, float], f_hz: np.ndarray | float) -> np.ndarray:
    """H(j2πf) of the arm model, rad/N·m; ``params`` an :class:`ArmParams` or a name → value map."""
    p = params.as_dict() if isinstance(params, ArmParams) else params
    return _H(p, 2j * np.pi * np.asarray(f_hz, dtype=float))


def _H(p: Mapping[str, float | np.ndarray], s: np.ndarray) -> np.ndarray:
    return 1.0 / (p["b_c"] * s + p["k_c"]) + 1.0 / (p["I_i"] * s**2 + p["b_i"] * s + p["k_i"])


def _partials(p: Mapping[str, float], s: np.ndarray) -> dict[str, np.ndarray]:
    dc = p["b_c"] * s + p["k_c"]
    di = p["I_i"] * s**2 + p["b_i"] * s + p["k_i"]
    return {
        "I_i": -(s**2) / di**2,
        "b_i": -s / di**2,
        "k_i": -1.0 / di**2,
        "b_c": -s / dc**2,
        "k_c": -1.0 / dc**2,
    }


class AdmittanceEstimate(Protocol):
    """What :func:`fit_arm` needs: a FrequencyResponse or a GroupFrequencyResponse.

    Optional attributes used when present: ``bin_frequencies_hz``/``bin_weights`` (how each
    band mixes its bins) and ``H_variance`` (the variance of Ĥ, for the standard errors).
    """

    frequencies_hz: np.ndarray
    H: np.ndarray
    coherence: np.ndarray


WEIGHTINGS = ("paper", "inverse_variance")


@dataclass(frozen=True)
class FitOptions:
    I_i: float = DEFAULT_I_I_KGM2  # fixed value, or the start value when fit_inertia
    fit_inertia: bool = False
    n_exclude_low: int = DEFAULT_N_EXCLUDE_LOW
    coherence_weighting: bool = True
    frequency_weighting: bool = True
    # Compare each band with the model mixed over the band's bins exactly as the estimator mixed
    # the data (FrequencyResponse.bin_weights) rather than with H at the band's mean frequency.
    # The double-band average is not H at the mean frequency: near the arm's resonance the two
    # differ by ~0.5 %, enough to bias b_c by about 1 % on noise-free data.
    band_mixing: bool = True
    # "paper": coherence × 1/f (Pronker et al. 2017). "inverse_variance": 1/var(Ĥ) per band,
    # from the noise at the unexcited bins: far better contact parameters (b_c, k_c) on
    # simulated data (docs/benchmarks.md, estimator_efficiency), but not the paper's numbers.
    weighting: str = "paper"

    def __post_init__(self) -> None:
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {self.weighting!r}")

    def to_dict(self) -> dict:
        return {
            "weighting": self.weighting,
            "I_i_kgm2": self.I_i,
            "fit_inertia": self.fit_inertia,
            "n_exclude_low": self.n_exclude_low,
            "coherence_weighting": self.coherence_weighting,
            "frequency_weighting": self.frequency_weighting,
            "band_mixing": self.band_mixing,
        }


@dataclass(frozen=True)
class ArmFit:
    """A fitted arm model. ``sems``/``covariance`` cover the free parameters only, in
    ``free`` order; ``vaf_percent`` is None until time data were simulated."""

    params: ArmParams
    free: tuple[str, ...]
    sems: dict[str, float]
    covariance: np.ndarray
    sem_method: str  # "noise" (measured variance of Ĥ, sandwich form) or "residual"
    frequencies_hz: np.ndarray  # the bands used
    H_measured: np.ndarray
    H_model: np.ndarray  # the model as compared with H_measured (mixed over each band's bins)
    weights: np.ndarray
    fit_percent: float
    sigma2: float  # weighted residual variance
    cost: float  # Σ w |e|²
    success: bool
    message: str
    options: FitOptions = field(default_factory=FitOptions)
    sems_residual: dict[str, float] = field(default_factory=dict)
    sems_noise: dict[str, float] | None = None
    vaf_percent: float | None = None

    def admittance(self, f_hz: np.ndarray | float) -> np.ndarray:
        return arm_admittance(self.params, f_hz)

    def with_vaf(self, vaf: float) -> ArmFit:
        return replace(self, vaf_percent=float(vaf))

    def to_dict(self) -> dict:
        names = [_key(n) for n in self.free]
        return {
            "params": self.params.to_dict(),
            "sem": {_key(n): v for n, v in self.sems.items()},
            "sem_method": self.sem_method,
            "sem_residual": {_key(n): v for n, v in self.sems_residual.items()},
            "sem_noise": (
                None
                if self.sems_noise is None
                else {_key(n): v for n, v in self.sems_noise.items()}
            ),
            "fixed": [_key(n) for n in PARAM_NAMES if n not in self.free],
            "covariance": {"parameters": names, "matrix": self.covariance.tolist()},
            "fit_percent": self.fit_percent,
            "vaf_percent": self.vaf_percent,
            "frequencies_Hz": self.frequencies_hz.tolist(),
            "weighted_residual_variance": self.sigma2,
            "cost": self.cost,
            "success": self.success,
            "message": self.message,
            "options": self.options.to_dict(),
        }


def fit_percent(f_hz: np.ndarray, H_measured: np.ndarray, H_model: np.ndarray) -> float:
    """FIT% = 100·(1 − Σ(1/f)|Ĥ − H_par|² / Σ(1/f)|H_par|²).

    :func:`fit_arm` passes H_par mixed over each band's bins like Ĥ (see ``band_mixing``).
    """
    w = 1.0 / np.asarray(f_hz, dtype=float)
    return float(
        100.0
        * (1.0 - np.sum(w * np.abs(H_measured - H_model) ** 2) / np.sum(w * np.abs(H_model) ** 2))
    )


def _start_values(f: np.ndarray, H: np.ndarray, I_i: float) -> dict[str, float]:
    # High band: the contact spring-damper dominates, 1/Ĥ ≈ k_c + j·2πf·b_c.
    z = 1.0 / H[-1]
    w_top = 2 * np.pi * f[-1]
    b_c = z.imag / w_top if z.imag > 0 else 1.0
    k_c = z.real if z.real > 0 else 10.0 / abs(H[0])
    # Low band: both springs in series, |Ĥ| ≈ 1/k_c + 1/k_i.
    inv_ki = abs(H[0]) - 1.0 / k_c
    k_i = 1.0 / inv_ki if inv_ki > 0.2 * abs(H[0]) else 2.0 / abs(H[0])
    b_i = 2 * 0.7 * np.sqrt(k_i * I_i)
    return {"I_i": I_i, "b_i": b_i, "k_i": k_i, "b_c": b_c, "k_c": k_c}


def _clip_log(name: str, value: float) -> float:
    lo, hi = BOUNDS[name]
    return float(np.log(np.clip(value, lo * 1.0001, hi / 1.0001)))


def fit_arm(estimate: AdmittanceEstimate, options: FitOptions | None = None) -> ArmFit:
    """Fit the arm model to a frequency response (see the module docstring)."""
    opt = options or FitOptions()
    f_all = np.asarray(estimate.frequencies_hz, dtype=float)
    H_all = np.asarray(estimate.H, dtype=complex)
    coh_all = np.asarray(estimate.coherence, dtype=float)
    ok = np.isfinite(H_all) & np.isfinite(coh_all) & (f_all > 0)
    use = np.nonzero(ok)[0][np.argsort(f_all[ok], kind="stable")][opt.n_exclude_low :]
    f, H, coh = f_all[use], H_all[use], coh_all[use]
    free = PARAM_NAMES if opt.fit_inertia else PARAM_NAMES[1:]
    if len(f) < len(free):
        raise ValueError(
            f"{len(f)} usable bands after leaving out the {opt.n_exclude_low} lowest; "
            f"fitting {len(free)} parameters needs at least {len(free)}"
        )
    bin_f = getattr(estimate, "bin_frequencies_hz", None)
    bin_w = getattr(estimate, "bin_weights", None)
    if opt.band_mixing and bin_f is not None and bin_w is not None:
        s_bins = 2j * np.pi * np.asarray(bin_f, dtype=float)[use]
        mix = np.asarray(bin_w, dtype=complex)[use]
    else:
        s_bins = 2j * np.pi * f[:, None]
        mix = np.ones((len(f), 1), dtype=complex)

    def model(p: Mapping[str, float | np.ndarray]) -> np.ndarray:
        return np.sum(mix * _H(p, s_bins), axis=-1)

    w = np.ones_like(f)
    if opt.weighting == "inverse_variance":
        var = np.asarray(getattr(estimate, "H_variance", np.full(len(f_all), np.nan)), float)[use]
        if not np.all(np.isfinite(var) & (var > 0)):
            raise ValueError("inverse-variance weighting needs the FRF's variance (H_variance)")
        w = np.nanmedian(var) / var
    else:
        if opt.coherence_weighting:
            w = w * coh
        if opt.frequency_weighting:
            w = w / f
    sw = np.sqrt(w)
    fixed = {"I_i": opt.I_i}

    def params_of(x: np.ndarray) -> dict[str, float]:
        p = dict(fixed)
        p.update({n: float(np.exp(v)) for n, v in zip(free, x, strict=True)})
        return p

    def partials(p: dict[str, float]) -> np.ndarray:
        d = _partials(p, s_bins)
        return np.array([np.sum(mix * d[n], axis=-1) for n in free]).T  # (K, n_free)

    def residual(x: np.ndarray) -> np.ndarray:
        e = sw * (model(params_of(x)) - H)
        return np.concatenate([e.real, e.imag])

    def jacobian(x: np.ndarray) -> np.ndarray:
        p = params_of(x)
        J = sw[:, None] * partials(p) * np.array([p[n] for n in free])  # d/dlog p = p·d/dp
        return np.concatenate([J.real, J.imag])

    # Coarse grid around the physical start: costs for all points at once, keep the best few.
    start = _start_values(f, H, opt.I_i)
    x0 = np.array([_clip_log(n, start[n]) for n in free])
    steps = np.log([0.1, 0.3, 1.0, 3.0, 10.0])
    grid = x0 + np.stack(np.meshgrid(*[steps] * len(free), indexing="ij"), -1).reshape(
        -1, len(free)
    )
    lo = np.array([np.log(BOUNDS[n][0]) for n in free])
    hi = np.array([np.log(BOUNDS[n][1]) for n in free])
    grid = np.clip(grid, lo + 1e-4, hi - 1e-4)
    pg: dict[str, float | np.ndarray] = {
        n: np.exp(grid[:, i])[:, None, None] for i, n in enumerate(free)
    }
    pg.update(fixed)
    costs = np.sum(w * np.abs(model(pg) - H) ** 2, axis=1)
    candidates = [grid[i] for i in np.argsort(costs)[:N_STARTS]]

    best = None
    for xs in candidates:
        r = least_squares(
            residual, xs, jac=jacobian, bounds=(lo, hi), method="trf",
            x_scale=1.0, ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=500,
        )  # fmt: skip
        if best is None or r.cost < best.cost:
            best = r
    assert best is not None
    p_hat = params_of(best.x)
    H_par = model(p_hat)

    # Cramér–Rao bound in the parameters' own units (not their logarithms).
    Jc = partials(p_hat)
    J = np.concatenate([Jc.real, Jc.imag])
    W = np.concatenate([w, w])
    cost = float(np.sum(w * np.abs(H_par - H) ** 2))
    dof = 2 * len(f) - len(free)
    sigma2 = cost / dof if dof > 0 else float("nan")
    A = J.T @ (W[:, None] * J)
    try:
        A_inv = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        A_inv = np.full(A.shape, np.nan)
    cov_res = sigma2 * A_inv
    cov = cov_res
    method = "residual"
    cov_noise = None
    var_all = getattr(estimate, "H_variance", None)
    if var_all is not None and np.all(np.isfinite(np.asarray(var_all)[use])):
        v = np.asarray(var_all, dtype=float)[use]
        S = np.concatenate([v, v]) / 2.0  # complex error: half the variance in each part
        cov = cov_noise = A_inv @ (J.T @ ((W**2 * S)[:, None] * J)) @ A_inv
        method = "noise"

    def sd(c: np.ndarray) -> dict[str, float]:
        return {
            n: float(np.sqrt(c[i, i])) if c[i, i] >= 0 else float("nan") for i, n in enumerate(free)
        }

    return ArmFit(
        params=ArmParams(**p_hat),
        free=tuple(free),
        sems=sd(cov),
        covariance=cov,
        sem_method=method,
        frequencies_hz=f,
        H_measured=H,
        H_model=H_par,
        weights=w,
        fit_percent=fit_percent(f, H, H_par),
        sigma2=sigma2,
        cost=cost,
        success=bool(best.success),
        message=str(best.message),
        options=opt,
        sems_residual=sd(cov_res),
        sems_noise=None if cov_noise is None else sd(cov_noise),
    )


def simulate_angle(
    params: ArmParams | Mapping[str, float], torque_Nm: np.ndarray, fs_hz: float
) -> np.ndarray:
    """The model's wheel angle for a driver-torque segment of whole perturbation periods.

    Computed as the periodic steady state: θ̂ = IDFT(H(f_k) · DFT(Td − mean Td)). Over whole
    periods the perturbation-driven part of Td is exactly periodic, so this is the response
    the continuous-time model gives after its transients have died out, with no initial state
    to guess and no discretisation error at the excited frequencies. The non-periodic
    (remnant) part wraps around the segment's ends, an error confined to the arm's settling
    time (tenths of a second) out of each 45 s period. The mean is removed because sensor
    offsets make the DC level meaningless; compare with a mean-free measured angle.
    """
    x = np.asarray(torque_Nm, dtype=float)
    n = len(x)
    spec = np.fft.rfft(x - x.mean())
    f = np.fft.rfftfreq(n, 1.0 / fs_hz)
    spec[1:] *= arm_admittance(params, f[1:])
    spec[0] = 0.0
    return np.fft.irfft(spec, n)


def vaf_percent(
    params: ArmParams | Mapping[str, float],
    segments: Iterable[tuple[np.ndarray, np.ndarray]],
    fs_hz: float | Iterable[float],
) -> float:
    """VAF = 100·(1 − Σ(θ − θ̂)² / Σθ²), pooled over ``(driver_torque, angle)`` segments.

    Each segment must hold whole perturbation periods; θ is taken mean-free (see
    :func:`simulate_angle`). ``fs_hz``: one rate for all segments, or one per segment.
    """
    segs = list(segments)
    if isinstance(fs_hz, int | float):
        rates = [float(fs_hz)] * len(segs)
    else:
        rates = [float(r) for r in fs_hz]
    err = total = 0.0
    for (td, th), fs in zip(segs, rates, strict=True):
        th = np.asarray(th, dtype=float)
        th = th - th.mean()
        err += float(np.sum((th - simulate_angle(params, td, fs)) ** 2))
        total += float(np.sum(th**2))
    return 100.0 * (1.0 - err / total) if total > 0 else float("nan")
