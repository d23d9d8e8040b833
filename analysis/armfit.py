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
    With the default (inverse-variance) weights, which are themselves estimates, a second-order
    term for their scatter is added (:func:`_estimated_weights_term`, docs/method-estimator.md
    §1; ``FitOptions.weight_uncertainty``), and the fit compares the model with the compensated
    estimate ``H_compensated`` where the response has one (analysis/frf.py).
    ``sem_method`` says which was used ("noise", or "residual" when no variance is available);
    both versions are kept (``sems_noise``, ``sems_residual``). Neither includes the model's
    lack of fit, which shows in FIT% instead.

FIT% (frequency domain), over the fitted bands:
    FIT = 100·(1 − Σ (1/f)|Ĥ − H_par|² / Σ (1/f)|H_par|²)

VAF (time domain): see :func:`simulate_angle` and :func:`vaf_percent`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
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

    # Read-only (properties): the estimates are frozen dataclasses.
    @property
    def frequencies_hz(self) -> np.ndarray: ...
    @property
    def H(self) -> np.ndarray: ...
    @property
    def coherence(self) -> np.ndarray: ...


WEIGHTINGS = ("inverse_variance", "paper")
SAMPLINGS = ("zoh", "ideal")
# The physical inertia of the wheel that the motor accelerates (Table 1), for the sampled-data
# model. It nearly cancels from that model (at the bands where aliasing matters the wheel's own
# inertia dominates both the direct and the aliased response), so the nominal value serves.
DEFAULT_WHEEL_INERTIA_KGM2 = 0.3
ALIAS_IMAGES = 30  # images ±m·fs summed on each side (truncation < 0.1 % at 20 Hz, 100 Hz)
INERTIA_MODES = ("subject", "free", "fixed")
# Inertia values of the coarse profile that gives the joint fit its start (kg·m²): from a
# slender forearm to both arms braced, beyond what a human arm about the column can have.
INERTIA_START_GRID = tuple(float(x) for x in np.geomspace(0.02, 0.6, 9))


@dataclass(frozen=True)
class FitOptions:
    """How :func:`fit_arm` / :func:`fit_arm_joint` fit the arm model.

    ``weighting``: "inverse_variance" (the default: maximum likelihood with a noise model
    measured at the unexcited bins and smoothed across frequency, see
    ``docs/method-estimator.md``) or "paper" (coherence × 1/f, Pronker et al. 2017).
    ``inertia``: "subject" (the default: one I_i per subject, shared by all of that subject's
    conditions, :func:`fit_arm_joint`), "free" (one I_i per fit) or "fixed" (held at ``I_i``).
    """

    I_i: float = DEFAULT_I_I_KGM2  # the held value when inertia="fixed"
    inertia: str = "subject"
    n_exclude_low: int = DEFAULT_N_EXCLUDE_LOW
    coherence_weighting: bool = True  # paper weighting only
    frequency_weighting: bool = True  # paper weighting only
    # Compare each band with the model mixed over the band's bins exactly as the estimator mixed
    # the data (FrequencyResponse.bin_weights) rather than with H at the band's mean frequency.
    # The double-band average is not H at the mean frequency: near the arm's resonance the two
    # differ by ~0.5 %, enough to bias b_c by about 1 % on noise-free data.
    band_mixing: bool = True
    weighting: str = "inverse_variance"
    # "zoh": the rig holds its torque command between samples and reads angle and torque at
    # the sample instants, so the held command's images above the Nyquist frequency fold back
    # onto the excited bands; the fit compares Ĥ with that sampled-data response (see
    # :func:`sampled_admittance`). "ideal": with H itself (continuous-time recording).
    sampling: str = "zoh"
    wheel_inertia: float = DEFAULT_WHEEL_INERTIA_KGM2
    # Standard errors that account for the maximum-likelihood weights being estimates (the
    # smoothed noise model's scatter, docs/method-estimator.md §1); False: the plug-in bound.
    weight_uncertainty: bool = True

    def __post_init__(self) -> None:
        if self.sampling not in SAMPLINGS:
            raise ValueError(f"sampling must be one of {SAMPLINGS}, got {self.sampling!r}")
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {self.weighting!r}")
        if self.inertia not in INERTIA_MODES:
            raise ValueError(f"inertia must be one of {INERTIA_MODES}, got {self.inertia!r}")
        if not (np.isfinite(self.I_i) and BOUNDS["I_i"][0] < self.I_i < BOUNDS["I_i"][1]):
            raise ValueError(
                f"I_i must be a finite inertia within {BOUNDS['I_i']} kg·m², got {self.I_i}"
            )

    @property
    def fit_inertia(self) -> bool:
        return self.inertia != "fixed"

    def to_dict(self) -> dict:
        return {
            "weighting": self.weighting,
            "inertia": self.inertia,
            "I_i_kgm2": self.I_i if self.inertia == "fixed" else None,
            "n_exclude_low": self.n_exclude_low,
            "coherence_weighting": self.coherence_weighting,
            "frequency_weighting": self.frequency_weighting,
            "band_mixing": self.band_mixing,
            "sampling": self.sampling,
            "wheel_inertia_kgm2": self.wheel_inertia,
            "weight_uncertainty": self.weight_uncertainty,
        }


def sampled_admittance(
    p: Mapping[str, float | np.ndarray],
    s: np.ndarray,
    fs_hz: float,
    wheel_inertia: float = DEFAULT_WHEEL_INERTIA_KGM2,
    images: int = ALIAS_IMAGES,
) -> np.ndarray:
    """What Ŝ(Tp,θ)/Ŝ(Tp,Td) measures at s = j2πf when the rig holds its command.

    The wheel (inertia I_w, the motor's held command u and the hands' torque T_d acting on it)
    and the arm are continuous: θ = P·u with P = 1/(I_w s² + 1/H), T_d = θ/H. The command is
    held over each sample (zero-order hold Z(s) = (1 − e^{−sT})/(sT)) and θ, T_d are read at
    the sample instants, so each measured coefficient sums the images at f + m·fs:

        Ĥ_d(f) = Σ_m P Z (f + m fs) / Σ_m P Z / H (f + m fs)

    which is H(f) when fs → ∞. Whatever the discrete command is (rendered dynamics, the
    perturbation), it cancels from the ratio.
    """
    return _sampled(p, s, fs_hz, wheel_inertia, images, ())[0]


def _sampled(
    p: Mapping[str, float | np.ndarray],
    s: np.ndarray,
    fs_hz: float,
    wheel_inertia: float,
    images: int,
    names: Sequence[str],
) -> tuple[np.ndarray, list[np.ndarray]]:
    """:func:`sampled_admittance` and its partial derivatives with respect to ``names``.

    With N = Σ Z P and D = Σ Z P/H: ∂P = P² ∂H/H², ∂(P/H) = (P ∂H/H²)(P/H − 1), and
    ∂(N/D) = (∂N·D − N·∂D)/D².
    """
    T = 1.0 / fs_hz
    if all(np.ndim(v) == 0 for v in p.values()):
        # Scalar parameters (every fit): all images in one array operation, image axis last.
        m = np.arange(-images, images + 1)
        sm = np.asarray(s)[..., None] + 2j * np.pi * fs_hz * m
        h = _H(p, sm)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.where(sm == 0, 1.0, (1.0 - np.exp(-sm * T)) / (sm * T))
        P = 1.0 / (wheel_inertia * sm**2 + 1.0 / h)
        zP = z * P
        num_v = np.sum(zP, axis=-1)
        den_v = np.sum(zP / h, axis=-1)
        grads = []
        if names:
            d = _partials(p, sm)  # type: ignore[arg-type]
            a = zP / h**2
            b = P / h - 1.0
            for n in names:
                dn = np.sum(a * P * d[n], axis=-1)
                dd = np.sum(a * d[n] * b, axis=-1)
                grads.append((dn * den_v - num_v * dd) / den_v**2)
        return num_v / den_v, grads
    num: np.ndarray | float = 0.0
    den: np.ndarray | float = 0.0
    dnum: list = [0.0] * len(names)
    dden: list = [0.0] * len(names)
    for m_ in range(-images, images + 1):
        sm = s + 2j * np.pi * m_ * fs_hz
        h = _H(p, sm)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.where(sm == 0, 1.0, (1.0 - np.exp(-sm * T)) / (sm * T))
        P = 1.0 / (wheel_inertia * sm**2 + 1.0 / h)
        num = num + z * P
        den = den + z * P / h
        if names:
            d = _partials(p, sm)  # type: ignore[arg-type]
            a = z * P / h**2
            for i, n in enumerate(names):
                dnum[i] = dnum[i] + a * P * d[n]
                dden[i] = dden[i] + a * d[n] * (P / h - 1.0)
    hd = np.asarray(num / den)  # an array: there is at least one image (m = 0)
    return hd, [(dn * den - num * dd) / den**2 for dn, dd in zip(dnum, dden, strict=True)]


@dataclass(frozen=True)
class ArmFit:
    """A fitted arm model. ``sems``/``covariance`` cover the free parameters only, in
    ``free`` order; ``vaf_percent`` is None until time data were simulated. In a joint fit
    (``inertia`` "subject") I_i is free and shared: its SEM and its covariance with this
    fit's own parameters are those of the joint fit."""

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
    # Normalised χ² of the fit under the noise model: 2Σ|e|²/var / (2K − n), ≈ 1 when the model
    # explains Ĥ to within its noise (None without a noise model).
    chi2_per_dof: float | None = None
    # d(parameter)/d(I_i) at the fit, from the joint covariance: how much each parameter moves
    # if I_i were held at another value (empty unless I_i is free).
    inertia_sensitivity: dict[str, float] = field(default_factory=dict)

    def admittance(self, f_hz: np.ndarray | float) -> np.ndarray:
        return arm_admittance(self.params, f_hz)

    def with_vaf(self, vaf: float) -> ArmFit:
        return replace(self, vaf_percent=float(vaf))

    def at_bound(self) -> list[str]:
        """Free parameters whose estimate ended on the search box (within 1 %)."""
        out = []
        for n in self.free:
            lo, hi = BOUNDS[n]
            v = getattr(self.params, n)
            if v <= lo * 1.01 or v >= hi / 1.01:
                out.append(n)
        return out

    def unidentified(self) -> list[str]:
        """Free parameters the data do not determine: at a search bound, or SEM ≥ value (or no
        finite SEM). Such values are flagged wherever they appear and kept out of the
        statistics (``docs/method-estimator.md``)."""
        bad = set(self.at_bound())
        for n in self.free:
            sem = self.sems.get(n, float("nan"))
            if not (np.isfinite(sem) and sem < getattr(self.params, n)):
                bad.add(n)
        return [n for n in self.free if n in bad]

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
            "chi2_per_dof": self.chi2_per_dof,
            "cost": self.cost,
            "success": self.success,
            "message": self.message,
            "at_bound": [_key(n) for n in self.at_bound()],
            "unidentified": [_key(n) for n in self.unidentified()],
            "inertia_sensitivity": {_key(n): v for n, v in self.inertia_sensitivity.items()},
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
    # Two springs in series are each stiffer than the pair (1/|Ĥ| at the lowest band): a
    # contact start below that (a noisy top band) would put the whole start grid in the basin
    # where the two springs swap roles.
    k_c = max(k_c, 3.0 / abs(H[0]))
    # Low band: both springs in series, |Ĥ| ≈ 1/k_c + 1/k_i.
    inv_ki = abs(H[0]) - 1.0 / k_c
    k_i = 1.0 / inv_ki if inv_ki > 0.2 * abs(H[0]) else 2.0 / abs(H[0])
    b_i = 2 * 0.7 * np.sqrt(k_i * I_i)
    return {"I_i": I_i, "b_i": b_i, "k_i": k_i, "b_c": b_c, "k_c": k_c}


def _clip_log(name: str, value: float) -> float:
    lo, hi = BOUNDS[name]
    return float(np.log(np.clip(value, lo * 1.0001, hi / 1.0001)))


OWN = PARAM_NAMES[1:]  # the parameters every fit has of its own; I_i is fixed or shared
_LO = np.array([np.log(BOUNDS[n][0]) for n in OWN])
_HI = np.array([np.log(BOUNDS[n][1]) for n in OWN])
_I_LO, _I_HI = np.log(BOUNDS["I_i"][0]), np.log(BOUNDS["I_i"][1])


@dataclass(frozen=True)
class _Problem:
    """One frequency response prepared for fitting: bands used, weights, noise variance."""

    f: np.ndarray
    H: np.ndarray
    s_bins: np.ndarray
    mix: np.ndarray
    w: np.ndarray  # weights, before the joint normalisation
    var: np.ndarray | None  # variance of Ĥ per band (smoothed where available), for the SEMs
    fs_hz: float | None = None  # set: compare with the sampled-data response (zoh)
    wheel_inertia: float = DEFAULT_WHEEL_INERTIA_KGM2
    # Covariance of log(var) between the bands used, when var is an estimate with a known
    # scatter (the smoothed noise model): see _estimated_weights_term.
    var_log_cov: np.ndarray | None = None

    def model(self, p: Mapping[str, float | np.ndarray]) -> np.ndarray:
        if self.fs_hz is None:
            return np.sum(self.mix * _H(p, self.s_bins), axis=-1)
        h = sampled_admittance(p, self.s_bins, self.fs_hz, self.wheel_inertia)
        return np.sum(self.mix * h, axis=-1)

    def partials(self, p: Mapping[str, float], names: Sequence[str]) -> np.ndarray:
        if self.fs_hz is None:
            d = _partials(p, self.s_bins)
            return np.array([np.sum(self.mix * d[n], axis=-1) for n in names]).T  # (K, n)
        _, dl = _sampled(p, self.s_bins, self.fs_hz, self.wheel_inertia, ALIAS_IMAGES, names)
        return np.array([np.sum(self.mix * x, axis=-1) for x in dl]).T


def _variance(
    estimate: AdmittanceEstimate, use: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The variance of Ĥ at the bands ``use`` (smoothed where available) and, for the smoothed
    one, the covariance of its log between those bands (None when unknown)."""
    for name in ("H_variance_smooth", "H_variance"):
        v = getattr(estimate, name, None)
        if v is not None:
            v = np.asarray(v, dtype=float)[use]
            if np.all(np.isfinite(v) & (v > 0)):
                c = getattr(estimate, "H_variance_log_cov", None)
                c = c if name == "H_variance_smooth" else None
                if c is not None:
                    c = np.asarray(c, dtype=float)[np.ix_(use, use)]
                    c = c if np.all(np.isfinite(c)) else None
                return v, c
    return None, None


def _prepare(estimate: AdmittanceEstimate, opt: FitOptions, n_own: int) -> _Problem:
    f_all = np.asarray(estimate.frequencies_hz, dtype=float)
    H_all = np.asarray(estimate.H, dtype=complex)
    H_comp = getattr(estimate, "H_compensated", None)
    if opt.weighting == "inverse_variance" and H_comp is not None:
        # Weights that grow with |S_TpTd|² would pull Ĥ's remnant-correlated error into the
        # estimate; the compensated Ĥ has none (analysis/frf.py, docs/method-estimator.md §1).
        H_all = np.asarray(H_comp, dtype=complex)
    coh_all = np.asarray(estimate.coherence, dtype=float)
    ok = np.isfinite(H_all) & np.isfinite(coh_all) & (f_all > 0)
    use = np.nonzero(ok)[0][np.argsort(f_all[ok], kind="stable")][opt.n_exclude_low :]
    f, H, coh = f_all[use], H_all[use], coh_all[use]
    if len(f) < n_own:
        raise ValueError(
            f"{len(f)} usable bands after leaving out the {opt.n_exclude_low} lowest; "
            f"fitting {n_own} parameters needs at least {n_own}"
        )
    bin_f = getattr(estimate, "bin_frequencies_hz", None)
    bin_w = getattr(estimate, "bin_weights", None)
    if opt.band_mixing and bin_f is not None and bin_w is not None:
        s_bins = 2j * np.pi * np.asarray(bin_f, dtype=float)[use]
        mix = np.asarray(bin_w, dtype=complex)[use]
    else:
        s_bins = 2j * np.pi * f[:, None]
        mix = np.ones((len(f), 1), dtype=complex)
    var, var_log_cov = _variance(estimate, use)
    if opt.weighting == "inverse_variance":
        if var is None:
            raise ValueError(
                "inverse-variance weighting needs the FRF's noise variance (H_variance): "
                "use --weighting paper for a response without noise bins"
            )
        w = 1.0 / var
    else:
        w = np.ones_like(f)
        if opt.coherence_weighting:
            w = w * coh
        if opt.frequency_weighting:
            w = w / f
        # Each response counts alike in a joint fit: weights relative to its own size.
        w = w / np.sum(w * np.abs(H) ** 2)
    fs = getattr(estimate, "fs_hz", None) if opt.sampling == "zoh" else None
    return _Problem(f, H, s_bins, mix, w, var, fs, opt.wheel_inertia, var_log_cov)


# The inertia profile only chooses the joint refinement's start (which then converges to
# 1e-12), so its fits stop at a looser tolerance: the same optimum, a third fewer iterations.
PROFILE_TOL = 1e-6


def _fit_own(
    prob: _Problem, I_i: float, x_starts: Sequence[np.ndarray], tol: float = 1e-12
) -> tuple[np.ndarray, float]:
    """Least squares of one response's own four parameters at a fixed I_i, from each start;
    the best (log-parameters, cost)."""
    sw = np.sqrt(prob.w)

    def params_of(x: np.ndarray) -> dict[str, float]:
        p = {n: float(np.exp(v)) for n, v in zip(OWN, x, strict=True)}
        p["I_i"] = I_i
        return p

    def residual(x: np.ndarray) -> np.ndarray:
        e = sw * (prob.model(params_of(x)) - prob.H)
        return np.concatenate([e.real, e.imag])

    def jacobian(x: np.ndarray) -> np.ndarray:
        p = params_of(x)
        J = sw[:, None] * prob.partials(p, OWN) * np.exp(x)
        return np.concatenate([J.real, J.imag])

    best_x, best_cost = None, np.inf
    for xs in x_starts:
        r = least_squares(
            residual, np.clip(xs, _LO + 1e-4, _HI - 1e-4), jac=jacobian, bounds=(_LO, _HI),
            method="trf", x_scale=1.0, ftol=tol, xtol=tol, gtol=tol, max_nfev=500,
        )  # fmt: skip
        if r.cost < best_cost:
            best_x, best_cost = r.x, float(r.cost)
    assert best_x is not None
    return best_x, best_cost


def _grid_starts(prob: _Problem, I_i: float) -> list[np.ndarray]:
    """The best points of a coarse grid (×0.1 … ×10 per parameter) around a physical start."""
    start = _start_values(prob.f, prob.H, I_i)
    x0 = np.array([_clip_log(n, start[n]) for n in OWN])
    steps = np.log([0.1, 0.3, 1.0, 3.0, 10.0])
    grid = x0 + np.stack(np.meshgrid(*[steps] * len(OWN), indexing="ij"), -1).reshape(-1, len(OWN))
    grid = np.clip(grid, _LO + 1e-4, _HI - 1e-4)
    pg: dict[str, float | np.ndarray] = {
        n: np.exp(grid[:, i])[:, None, None] for i, n in enumerate(OWN)
    }
    pg["I_i"] = I_i
    costs = np.sum(prob.w * np.abs(prob.model(pg) - prob.H) ** 2, axis=1)
    return [grid[i] for i in np.argsort(costs)[:N_STARTS]]


@dataclass(frozen=True)
class JointArmFit:
    """Fits of several responses of one subject (or of the group) sharing one I_i.

    ``I_i``/``I_i_sem``: the shared inertia and its standard error (None when held fixed);
    ``profile_I``/``profile_cost``: the summed weighted cost with every response refitted at
    each I_i of :data:`INERTIA_START_GRID`, which shows how sharply the data determine it.
    """

    fits: tuple[ArmFit, ...]
    labels: tuple[str, ...]
    I_i: float
    I_i_sem: float | None
    mode: str
    profile_I: tuple[float, ...] = ()
    profile_cost: tuple[float, ...] = ()

    def by_label(self) -> dict[str, ArmFit]:
        return dict(zip(self.labels, self.fits, strict=True))

    def to_dict(self) -> dict:
        return {
            "mode": self.mode,
            "I_i_kgm2": self.I_i,
            "I_i_sem_kgm2": self.I_i_sem,
            "labels": list(self.labels),
            "profile_I_kgm2": list(self.profile_I),
            "profile_cost": list(self.profile_cost),
        }


def check_fittable(estimate: AdmittanceEstimate, options: FitOptions | None = None) -> None:
    """Raise the ``ValueError`` :func:`fit_arm` would raise before fitting (too few usable
    bands, no noise variance for the default weighting), without fitting."""
    opt = options or FitOptions()
    _prepare(estimate, opt, len(OWN) + (1 if opt.fit_inertia else 0))


def fit_arm(estimate: AdmittanceEstimate, options: FitOptions | None = None) -> ArmFit:
    """Fit the arm model to one frequency response (see the module docstring).

    With ``inertia`` "subject" or "free" I_i is fitted from this response alone; to share it
    between a subject's conditions use :func:`fit_arm_joint`.
    """
    return fit_arm_joint([estimate], options).fits[0]


def fit_arm_joint(
    estimates: Sequence[AdmittanceEstimate],
    options: FitOptions | None = None,
    labels: Sequence[str] | None = None,
    start: JointArmFit | None = None,
) -> JointArmFit:
    """Fit the arm model to several responses at once with one I_i for all of them.

    Each response keeps its own b_i, k_i, b_c, k_c. With ``inertia`` "fixed" the responses are
    independent fits at the held I_i; with "free" each gets its own I_i (separate fits);
    otherwise ("subject") I_i is one parameter of a joint maximum-likelihood fit: a profile
    over :data:`INERTIA_START_GRID` (every response refitted at each value) gives the start,
    then all parameters are refined together and the covariance is that of the joint fit.

    ``start``: a joint fit of the same responses (say with the other weighting) whose solution
    starts the refinement instead of the profile (which is then not computed): the same model
    on the same data has its optimum nearby, and the profile is most of the cost.
    """
    opt = options or FitOptions()
    ests = list(estimates)
    if not ests:
        raise ValueError("fit_arm_joint needs at least one frequency response")
    labs = tuple(labels) if labels is not None else tuple(str(i) for i in range(len(ests)))
    if opt.inertia == "free" and len(ests) > 1:
        fits = [fit_arm_joint([e], opt).fits[0] for e in ests]
        return JointArmFit(tuple(fits), labs, float("nan"), None, "free")
    shared = opt.inertia != "fixed"
    n_own = len(OWN) + (1 if shared else 0)
    probs = [_prepare(e, opt, n_own) for e in ests]
    if opt.weighting == "inverse_variance":
        # One scale for all: relative weights between responses are part of the likelihood.
        scale = float(np.median(np.concatenate([1.0 / p.w for p in probs])))
        probs = [replace(p, w=p.w * scale) for p in probs]

    profile_I: list[float] = []
    profile_cost: list[float] = []
    # Starts and the inertia profile on the continuous model (cheap, analytic); the sampled-data
    # term is a small correction that the joint refinement below adds.
    coarse = [replace(p, fs_hz=None) for p in probs]
    if start is not None and len(start.fits) == len(probs):
        I0 = opt.I_i if not shared else float(start.I_i)
        if not np.isfinite(I0):
            I0 = opt.I_i
        xs = [
            np.clip([np.log(getattr(f.params, n)) for n in OWN], _LO + 1e-4, _HI - 1e-4)
            for f in start.fits
        ]
    elif not shared:
        I0 = opt.I_i
        xs = [_fit_own(p, I0, _grid_starts(p, I0))[0] for p in coarse]
    else:
        prev: list[np.ndarray | None] = [None] * len(probs)
        best: tuple[float, float, list[np.ndarray]] = (np.inf, 0.0, [])
        for I in INERTIA_START_GRID:
            total, xi = 0.0, []
            for k, prob in enumerate(coarse):
                near = prev[k]
                n_grid = 2 if near is None else 1  # the neighbour's optimum is the likeliest
                starts = _grid_starts(prob, I)[:n_grid] + ([near] if near is not None else [])
                x, c = _fit_own(prob, I, starts, PROFILE_TOL)
                xi.append(x)
                total += c
            prev = list(xi)
            profile_I.append(I)
            profile_cost.append(2.0 * total)
            if total < best[0]:
                best = (total, I, xi)
        I0, xs = best[1], best[2]

    # Joint refinement: x = [log I_i]? + each response's four log-parameters.
    n_p = len(OWN)
    nI = 1 if shared else 0
    sws = [np.sqrt(p.w) for p in probs]

    def unpack(x: np.ndarray) -> list[dict[str, float]]:
        I = float(np.exp(x[0])) if shared else I0
        out = []
        for k in range(len(probs)):
            seg = x[nI + k * n_p : nI + (k + 1) * n_p]
            d = {n: float(np.exp(v)) for n, v in zip(OWN, seg, strict=True)}
            d["I_i"] = I
            out.append(d)
        return out

    names_all = (("I_i",) if shared else ()) + OWN

    def jac_rows(ps: list[dict[str, float]], log: bool) -> list[np.ndarray]:
        """Per response: ∂(weighted model)/∂(all parameters), complex (K_k, n_total)."""
        rows = []
        n_tot = nI + n_p * len(probs)
        for k, (p, pr) in enumerate(zip(ps, probs, strict=True)):
            Jk = np.zeros((len(pr.f), n_tot), dtype=complex)
            d = pr.partials(p, names_all)
            scale = np.array([p[n] for n in names_all]) if log else 1.0
            d = d * scale
            if shared:
                Jk[:, 0] = d[:, 0]
            Jk[:, nI + k * n_p : nI + (k + 1) * n_p] = d[:, nI:]
            rows.append(Jk)
        return rows

    def residual(x: np.ndarray) -> np.ndarray:
        es = [sw * (pr.model(p) - pr.H) for sw, pr, p in zip(sws, probs, unpack(x), strict=True)]
        e = np.concatenate(es)
        return np.concatenate([e.real, e.imag])

    def jacobian(x: np.ndarray) -> np.ndarray:
        J = np.concatenate(
            [sw[:, None] * Jk for sw, Jk in zip(sws, jac_rows(unpack(x), True), strict=True)]
        )
        return np.concatenate([J.real, J.imag])

    head = [np.array([np.log(I0)])] if shared else []
    x0 = np.concatenate(head + list(xs))
    lo = np.concatenate(([np.array([_I_LO])] if shared else []) + [_LO] * len(probs))
    hi = np.concatenate(([np.array([_I_HI])] if shared else []) + [_HI] * len(probs))
    r = least_squares(
        residual, np.clip(x0, lo + 1e-4, hi - 1e-4), jac=jacobian, bounds=(lo, hi),
        method="trf", x_scale=1.0, ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=1000,
    )  # fmt: skip
    ps = unpack(r.x)

    # Covariance in the parameters' own units: the sandwich A⁻¹ (Jᵀ W Σ W J) A⁻¹, the inverse
    # Fisher information (Cramér–Rao bound) when W ∝ Σ⁻¹ (the default weighting).
    Jc = np.concatenate(jac_rows(ps, False))
    J = np.concatenate([Jc.real, Jc.imag])
    w_all = np.concatenate([p.w for p in probs])
    W = np.concatenate([w_all, w_all])
    H_pars = [pr.model(p) for pr, p in zip(probs, ps, strict=True)]
    costs = [
        float(np.sum(pr.w * np.abs(h - pr.H) ** 2)) for pr, h in zip(probs, H_pars, strict=True)
    ]
    dof_total = 2 * sum(len(pr.f) for pr in probs) - len(r.x)
    sigma2_all = sum(costs) / dof_total if dof_total > 0 else float("nan")
    A = J.T @ (W[:, None] * J)
    try:
        A_inv = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        A_inv = np.full(A.shape, np.nan)
    cov_res = sigma2_all * A_inv
    have_var = all(pr.var is not None for pr in probs)
    if have_var:
        v_all = np.concatenate([pr.var for pr in probs if pr.var is not None])  # have_var: all
        S = np.concatenate([v_all, v_all]) / 2.0  # complex error: half the variance in each part
        cov = cov_noise = A_inv @ (J.T @ ((W**2 * S)[:, None] * J)) @ A_inv
        method = "noise"
        logcovs = [pr.var_log_cov for pr in probs]
        if (
            opt.weighting == "inverse_variance"
            and opt.weight_uncertainty
            and all(c is not None for c in logcovs)
        ):
            cov = cov_noise = cov + _estimated_weights_term(Jc, v_all, _block_diag(logcovs))
    else:
        cov, cov_noise, method = cov_res, None, "residual"

    fits = []
    free = names_all
    for k, (pr, p, h, c) in enumerate(zip(probs, ps, H_pars, costs, strict=True)):
        idx = ([0] if shared else []) + list(range(nI + k * n_p, nI + (k + 1) * n_p))
        ix = np.ix_(idx, idx)

        def sd(cm: np.ndarray, ix=ix) -> dict[str, float]:
            sub = cm[ix]
            return {
                n: float(np.sqrt(sub[i, i])) if sub[i, i] >= 0 else float("nan")
                for i, n in enumerate(free)
            }

        dof = 2 * len(pr.f) - n_p - (nI / len(probs))
        chi2 = None
        if pr.var is not None:
            # Each of the 2K real residuals has half the complex variance: χ² = Σ|e|²/(var/2).
            chi2 = float(2.0 * np.sum(np.abs(h - pr.H) ** 2 / pr.var) / dof) if dof > 0 else None
        sens: dict[str, float] = {}
        if shared and np.isfinite(cov[0, 0]) and cov[0, 0] > 0:
            sens = {n: float(cov[idx[i], 0] / cov[0, 0]) for i, n in enumerate(free) if i > 0}
        fits.append(
            ArmFit(
                params=ArmParams(**p),
                free=tuple(free),
                sems=sd(cov),
                covariance=cov[ix],
                sem_method=method,
                frequencies_hz=pr.f,
                H_measured=pr.H,
                H_model=h,
                weights=pr.w,
                fit_percent=fit_percent(pr.f, pr.H, h),
                sigma2=c / dof if dof > 0 else float("nan"),
                cost=c,
                success=bool(r.success),
                message=str(r.message),
                options=opt,
                sems_residual=sd(cov_res),
                sems_noise=None if cov_noise is None else sd(cov_noise),
                chi2_per_dof=chi2,
                inertia_sensitivity=sens,
            )
        )
    I_hat = ps[0]["I_i"]
    I_sem = float(np.sqrt(cov[0, 0])) if shared and cov[0, 0] >= 0 else None
    return JointArmFit(
        tuple(fits),
        labs,
        float(I_hat),
        I_sem,
        "subject" if shared and len(probs) > 1 else ("free" if shared else "fixed"),
        tuple(profile_I),
        tuple(profile_cost),
    )


def _block_diag(blocks: Sequence[np.ndarray | None]) -> np.ndarray:
    n = sum(len(b) for b in blocks if b is not None)
    out = np.zeros((n, n))
    i = 0
    for b in blocks:
        assert b is not None
        out[i : i + len(b), i : i + len(b)] = b
        i += len(b)
    return out


def _estimated_weights_term(Jc: np.ndarray, var: np.ndarray, log_cov: np.ndarray) -> np.ndarray:
    """What the maximum-likelihood fit's covariance gains because its weights 1/v̂_k are
    estimates, to second order in their error (docs/method-estimator.md §1).

    With v̂_k = v_k e^{η_k}, η normal with mean 0 and covariance ``log_cov`` (the smoothed
    noise model's own scatter), the weights are W(1 + δ), δ_k = e^{−η_k} − 1. Expanding the
    weighted least-squares estimate in δ, with F_k the Fisher information of band k and F their
    sum, the estimator's covariance is F⁻¹ + F⁻¹[Σ E(δ_k²) F_k − Σ E(δ_k δ_l) F_k F⁻¹ F_l] F⁻¹
    (random weights cost efficiency; nothing when δ is the same for every band), while the
    plug-in bound (Σ F_k (1 + δ_k))⁻¹ that the fit reports has the mean
    F⁻¹ − F⁻¹[Σ E(δ_k) F_k − Σ E(δ_k δ_l) F_k F⁻¹ F_l] F⁻¹ (1/v̂ is larger than 1/v on
    average). Their difference, with the plug-in F_k, is returned. For independent variance
    estimates of M − 1 complex degrees of freedom it is the (M − 1)/(M − 3) of Pintelon &
    Schoukens' sample maximum-likelihood estimator to first order in 1/M.
    """
    # Each band's complex error has var/2 in its real and in its imaginary part.
    Fk = 2.0 * np.real(np.einsum("ki,kj->kij", Jc.conj(), Jc)) / var[:, None, None]
    F = Fk.sum(axis=0)
    try:
        G = np.linalg.inv(F)
    except np.linalg.LinAlgError:
        return np.zeros(F.shape)
    c = np.diag(log_cov)
    e_half = np.exp(c / 2)
    mean_d = e_half - 1.0
    # Lognormal moments: E[δ_k δ_l] = e^{(c_k + c_l)/2 + C_kl} − e^{c_k/2} − e^{c_l/2} + 1.
    second = np.outer(e_half, e_half) * np.exp(log_cov) - e_half[:, None] - e_half[None, :] + 1
    pair = np.einsum("kij,kjm->im", Fk @ G, np.tensordot(second, Fk, axes=1))
    middle = np.tensordot(np.diag(second) + mean_d, Fk, axes=1) - 2.0 * pair
    return G @ middle @ G


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
