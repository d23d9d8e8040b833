"""Grip-force-scheduled LPV admittance model from local LTI models (docs/method.md, "LPV model").

One local arm model per operating point (condition), each with a scheduling value μ: the median
over subjects of the mean total grip force, in N. Two ways to make a global model of μ, with one
interface (:class:`LPVModel`):

- :class:`DeCaignyLPV`, the paper's (de Caigny, Camino & Swevers 2009): each local model is
  written as gain × first-order subsystem × second-order subsystem, each subsystem in observable
  canonical state-space form; every free state-space entry and the gain is fitted as a polynomial
  in μ, and the global model is the interpolated blocks in series.
- :class:`PhysicalLPV`, what the paper's discussion recommends: fit the physical parameters
  (I_i, b_i, k_i, b_c, k_c) as polynomials in μ and rebuild the arm model from them.

The local model (torque on the hands → wheel angle, rad/(N·m)) is

    H(s) = 1/(b_c s + k_c) + 1/(I_i s² + b_i s + k_i)
         = (I_i s² + (b_i+b_c) s + (k_i+k_c)) / ((b_c s + k_c)(I_i s² + b_i s + k_i)).

How the de Caigny decomposition pairs poles and zeros *(ours; the paper does not say)*:

- The poles are paired by physical origin, which the parameters tell us: the first-order block
  holds the contact pole −k_c/b_c, the second-order block the intrinsic pair of
  I_i s² + b_i s + k_i. The second-order block's entries are that quadratic's coefficients
  (a1 = b_i/I_i, a0 = k_i/I_i), which are smooth through the point where the pair turns from
  complex to real, so real intrinsic poles need no special case.
- ``zeros="split"`` is the paper's structure: one real zero in each block. The first-order block
  gets the zero nearer (on a log scale) to the contact pole — as the contact stiffens, that zero
  cancels the contact pole and the other runs off to −b_c/I_i — and the same ranked zero
  (slow or fast) must be chosen at every operating point, otherwise the entries would jump;
  :class:`StructureError` says so. If the numerator's zeros are complex at any operating point,
  no real first-order factor with one zero exists: :class:`StructureError` again.
- ``zeros="second_order"`` keeps the first-order block zero-free and puts both zeros in the
  second-order block (biproper, entries b1, b0 of its numerator). It exists for complex and
  real zeros alike.
- ``zeros="auto"`` (default) uses "split" when it exists at every operating point and
  "second_order" otherwise, and records which and why.

Gains are normalised so that every block's highest-power coefficients are 1 (monic), which
makes the state-space entries plain functions of pole and zero locations; the overall gain is
then 1/b_c.

RT is left out of the LPV by default (:data:`DEFAULT_EXCLUSIONS`) for the paper's reasons; the
exclusion is a plain argument, and its reason travels with every result.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike
from scipy import signal

PARAMETER_NAMES: tuple[str, ...] = ("I_i", "b_i", "k_i", "b_c", "k_c")
PARAMETER_UNITS: Mapping[str, str] = MappingProxyType(
    {
        "I_i": "kg·m²",
        "b_i": "N·m·s/rad",
        "k_i": "N·m/rad",
        "b_c": "N·m·s/rad",
        "k_c": "N·m/rad",
    }
)
SCHEDULING_VARIABLE = "median over subjects of the mean total grip force (both hands), N"

RT_EXCLUSION_REASON = (
    "RT (relax task) is left out of the LPV model: its pole/zero pattern differs from the other "
    "conditions and its grip force does not differ from BT18, so it would put a second, "
    "different local model at about the same scheduling value (Pronker et al. 2017)"
)
DEFAULT_EXCLUSIONS: Mapping[str, str] = MappingProxyType({"RT": RT_EXCLUSION_REASON})

OutOfRange = Literal["clip", "extrapolate", "raise"]
ZeroPlacement = Literal["auto", "split", "second_order"]
Structure = Literal["split", "second_order"]  # the de Caigny structure resolved from "auto"
ZeroRank = Literal["slow", "fast"]
METHODS: tuple[str, ...] = ("de_caigny", "physical")


class StructureError(ValueError):
    """A local model cannot be written in the requested gain × first × second-order structure."""


# --------------------------------------------------------------------------------------------
# Local (LTI) arm model


def _unpack(p: Mapping[str, float]) -> tuple[float, float, float, float, float]:
    missing = [k for k in PARAMETER_NAMES if k not in p]
    if missing:
        raise KeyError(f"arm parameters miss {missing}; need {list(PARAMETER_NAMES)}")
    vals = tuple(float(p[k]) for k in PARAMETER_NAMES)
    if not all(math.isfinite(v) for v in vals):
        given = {k: p[k] for k in PARAMETER_NAMES}
        raise ValueError(f"arm parameters must be finite, got {given}")
    if vals[0] <= 0 or vals[3] <= 0:
        # The model is third order only with I_i > 0 and b_c > 0; the structure relies on it.
        raise ValueError(f"need I_i > 0 and b_c > 0, got I_i={vals[0]}, b_c={vals[3]}")
    return vals  # type: ignore[return-value]


def admittance_tf(parameters: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """(num, den) of the local arm admittance, highest power first, rad/(N·m)."""
    I, bi, ki, bc, kc = _unpack(parameters)
    num = np.array([I, bi + bc, ki + kc])
    den = np.array([bc * I, bc * bi + kc * I, bc * ki + kc * bi, kc * ki])
    return num, den


def admittance_response(parameters: Mapping[str, float], f_hz: ArrayLike) -> np.ndarray:
    """Complex frequency response of the local arm admittance at ``f_hz``, rad/(N·m)."""
    I, bi, ki, bc, kc = _unpack(parameters)
    s = 2j * np.pi * np.asarray(f_hz, dtype=float)
    return 1.0 / (bc * s + kc) + 1.0 / ((I * s + bi) * s + ki)


def local_zeros(parameters: Mapping[str, float]) -> tuple[complex, complex]:
    """Zeros of the local model, slower (smaller magnitude) first."""
    I, bi, ki, bc, kc = _unpack(parameters)
    zeros = sorted(np.roots([I, bi + bc, ki + kc]), key=abs)
    return complex(zeros[0]), complex(zeros[1])


def _zeros_are_real(parameters: Mapping[str, float]) -> bool:
    I, bi, ki, bc, kc = _unpack(parameters)
    return (bi + bc) ** 2 - 4.0 * I * (ki + kc) >= 0.0


def _first_order_zero_rank(parameters: Mapping[str, float]) -> ZeroRank:
    """Which real zero belongs with the contact pole: 'slow' or 'fast' (nearer on a log scale)."""
    _, _, _, bc, kc = _unpack(parameters)
    pole = kc / bc
    slow, fast = (abs(z.real) for z in local_zeros(parameters))
    return "slow" if abs(math.log(slow / pole)) <= abs(math.log(fast / pole)) else "fast"


# --------------------------------------------------------------------------------------------
# Inputs


@dataclass(frozen=True)
class MeasuredFRF:
    """A measured frequency response Ĥ at one operating point."""

    frequencies_hz: np.ndarray
    response: np.ndarray  # complex, rad/(N·m)
    coherence: np.ndarray | None = None  # carried for reports; FIT% does not use it

    def __post_init__(self) -> None:
        f = np.asarray(self.frequencies_hz, dtype=float)
        h = np.asarray(self.response, dtype=complex)
        if f.ndim != 1 or f.shape != h.shape:
            raise ValueError(f"frequencies {f.shape} and response {h.shape} must be equal 1-D")
        if np.any(f <= 0):
            raise ValueError("FRF frequencies must be > 0 (FIT% weights by 1/f)")
        object.__setattr__(self, "frequencies_hz", f)
        object.__setattr__(self, "response", h)
        if self.coherence is not None:
            object.__setattr__(self, "coherence", np.asarray(self.coherence, dtype=float))


@dataclass(frozen=True)
class TimeData:
    """Measured signals at one operating point, for a time-domain VAF."""

    fs_hz: float
    torque_Nm: np.ndarray  # driver torque: the model's input
    angle_rad: np.ndarray  # measured wheel angle: compared with the model's output


@dataclass(frozen=True)
class OperatingPoint:
    condition: str
    mu_N: float  # scheduling value: median over subjects of the mean total grip force
    parameters: Mapping[str, float]  # local model, keys PARAMETER_NAMES
    frf: MeasuredFRF | None = None
    time: TimeData | None = None


PointLike = OperatingPoint | Sequence[Any]


def as_operating_points(points: Iterable[PointLike]) -> list[OperatingPoint]:
    """Accept OperatingPoint objects or tuples ``(condition, mu_N, parameters[, frf])`` where
    ``frf`` is a :class:`MeasuredFRF` or ``(frequencies_hz, H[, coherence])``."""
    out = []
    for p in points:
        if not isinstance(p, OperatingPoint):
            cond, mu, params, *rest = p
            frf = rest[0] if rest else None
            if frf is not None and not isinstance(frf, MeasuredFRF):
                frf = MeasuredFRF(*frf)
            p = OperatingPoint(str(cond), float(mu), dict(params), frf)
        _unpack(p.parameters)
        if not math.isfinite(p.mu_N):
            raise ValueError(f"{p.condition}: scheduling value must be finite, got {p.mu_N}")
        out.append(p)
    names = [p.condition for p in out]
    if len(set(names)) != len(names):
        raise ValueError(f"condition names must be unique, got {names}")
    return sorted(out, key=lambda p: p.mu_N)


def select_operating_points(
    points: Iterable[PointLike], exclude: Mapping[str, str] = DEFAULT_EXCLUSIONS
) -> tuple[list[OperatingPoint], dict[str, str]]:
    """Split into (included, {excluded condition: reason}); both sorted by μ."""
    pts = as_operating_points(points)
    included = [p for p in pts if p.condition not in exclude]
    excluded = {p.condition: exclude[p.condition] for p in pts if p.condition in exclude}
    return included, excluded


def default_frequencies_hz() -> np.ndarray:
    """Centres of the 31 double bands of the default perturbation (0.08–20 Hz)."""
    from steerlab.protocols.perturbation import PerturbationSpec, band_start_bins

    spec = PerturbationSpec()
    return (band_start_bins(spec) + 0.5) / spec.period_s


# --------------------------------------------------------------------------------------------
# Goodness of fit


def fit_percent(measured: ArrayLike, model: ArrayLike, f_hz: ArrayLike) -> float:
    """FIT% = 100·(1 − Σ(1/f)|Ĥ − H_model|² / Σ(1/f)|H_model|²) (docs/method.md step 6)."""
    h_meas = np.asarray(measured, dtype=complex)
    h_mod = np.asarray(model, dtype=complex)
    w = 1.0 / np.asarray(f_hz, dtype=float)
    return float(
        100.0 * (1.0 - np.sum(w * np.abs(h_meas - h_mod) ** 2) / np.sum(w * np.abs(h_mod) ** 2))
    )


def vaf(theta: ArrayLike, theta_hat: ArrayLike, *, clip_at_zero: bool = False) -> float:
    """VAF% = 100·(1 − Σ(θ − θ̂)² / Σθ²). Negative when the model is worse than predicting 0;
    ``clip_at_zero`` reports those as 0 %, which is how the paper quotes its worst case."""
    th = np.asarray(theta, dtype=float)
    err = th - np.asarray(theta_hat, dtype=float)
    v = float(100.0 * (1.0 - np.sum(err**2) / np.sum(th**2)))
    return max(v, 0.0) if clip_at_zero else v


def simulate(num: ArrayLike, den: ArrayLike, torque_Nm: ArrayLike, fs_hz: float) -> np.ndarray:
    """Wheel angle of an LTI admittance driven by ``torque_Nm``, from rest.

    Tustin discretisation: the arm's poles (≲ 10 Hz) sit far below a 1 kHz sampling rate, where
    it is accurate and, unlike zero-order hold, does not assume a staircase input.
    """
    b, a, _ = signal.cont2discrete((np.asarray(num), np.asarray(den)), 1.0 / fs_hz, "bilinear")
    return signal.lfilter(np.ravel(b), np.ravel(a), np.asarray(torque_Nm, dtype=float))


# --------------------------------------------------------------------------------------------
# Polynomials in μ


class _Schedule:
    """One least-squares polynomial in μ per named quantity, evaluated with plain floats.

    μ is mapped to x = (μ − centre)/half-width ∈ [−1, 1] over the operating points, so the
    Vandermonde system stays well conditioned at any order. Evaluation is Horner's rule on
    Python floats: at 3 coefficients × 5–6 quantities that beats numpy's per-call overhead.
    """

    def __init__(
        self,
        mus: np.ndarray,
        table: Mapping[str, np.ndarray],
        order: int,
        out_of_range: OutOfRange,
    ) -> None:
        if order < 0 or int(order) != order:
            raise ValueError(f"polynomial order must be a non-negative integer, got {order}")
        if out_of_range not in ("clip", "extrapolate", "raise"):
            raise ValueError(
                f"out_of_range must be clip, extrapolate or raise, got {out_of_range!r}"
            )
        distinct = np.unique(mus)
        if distinct.size < order + 1:
            raise ValueError(
                f"a polynomial of order {order} in μ needs at least {order + 1} operating points "
                f"with distinct μ, got {distinct.size}"
            )
        self.order = int(order)
        self.out_of_range = out_of_range
        self.lo, self.hi = float(mus.min()), float(mus.max())
        self.centre = 0.5 * (self.lo + self.hi)
        self.scale = 0.5 * (self.hi - self.lo) or 1.0
        vander = np.vander((mus - self.centre) / self.scale, self.order + 1)
        self.names = tuple(table)
        coeffs: list[tuple[float, ...]] = []
        for name in self.names:
            y = np.asarray(table[name], dtype=float)
            if np.all(y == y[0]):
                # A quantity held constant (I_i in the paper's fits) stays exactly constant.
                coeffs.append((float(y[0]),))
            else:
                c = np.linalg.lstsq(vander, y, rcond=None)[0]
                coeffs.append(tuple(float(v) for v in c))
        self.coeffs: tuple[tuple[float, ...], ...] = tuple(coeffs)

    def x(self, mu: float) -> float:
        mu = float(mu)
        if not self.lo <= mu <= self.hi:
            if mu != mu:
                raise ValueError("scheduling value is NaN")
            if self.out_of_range == "clip":
                mu = self.lo if mu < self.lo else self.hi
            elif self.out_of_range == "raise":
                raise ValueError(
                    f"μ = {mu} N is outside the operating points' range [{self.lo}, {self.hi}] N"
                )
        return (mu - self.centre) / self.scale

    def values(self, mu: float) -> list[float]:
        x = self.x(mu)
        out = []
        for c in self.coeffs:
            v = 0.0
            for a in c:
                v = v * x + a
            out.append(v)
        return out

    def to_dict(self, units: Mapping[str, str]) -> dict[str, Any]:
        return {
            "variable": "x = (mu_N - centre_N) / scale_N",
            "centre_N": self.centre,
            "scale_N": self.scale,
            "order": self.order,
            "coefficients_highest_power_first": {
                n: {"values": list(c), "unit": units.get(n, "")}
                for n, c in zip(self.names, self.coeffs, strict=True)
            },
        }


# --------------------------------------------------------------------------------------------
# The models


@runtime_checkable
class LPVModel(Protocol):
    """What the live loop and the reports use; both interpolation methods implement it."""

    method: str

    @property
    def mu_range(self) -> tuple[float, float]: ...

    def parameters(self, mu: float) -> dict[str, float]:
        """The interpolated quantities at μ (physical parameters, or state-space entries)."""
        ...

    def frequency_response(self, mu: float, f_hz: ArrayLike) -> np.ndarray:
        """Complex admittance at μ and ``f_hz``, rad/(N·m)."""
        ...

    def transfer_function(self, mu: float) -> tuple[np.ndarray, np.ndarray]:
        """(num, den) at μ, highest power first."""
        ...

    def to_dict(self) -> dict[str, Any]: ...


class _InterpolatedLPV:
    """Shared machinery: scheduling, evaluation, reporting. Subclasses fill ``_response``,
    ``_tf`` and the list of quantities they interpolate."""

    method = ""
    units: Mapping[str, str] = PARAMETER_UNITS

    def __init__(
        self,
        points: Sequence[OperatingPoint],
        table: Mapping[str, np.ndarray],
        order: int,
        out_of_range: OutOfRange,
    ) -> None:
        self.points = tuple(points)
        mus = np.array([p.mu_N for p in self.points])
        self._schedule = _Schedule(mus, table, order, out_of_range)
        self._names = self._schedule.names

    @property
    def order(self) -> int:
        return self._schedule.order

    @property
    def mu_range(self) -> tuple[float, float]:
        return self._schedule.lo, self._schedule.hi

    @property
    def conditions(self) -> list[str]:
        return [p.condition for p in self.points]

    def parameters(self, mu: float) -> dict[str, float]:
        return dict(zip(self._names, self._schedule.values(mu), strict=True))

    def frequency_response(self, mu: float, f_hz: ArrayLike) -> np.ndarray:
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        return self._response(self._schedule.values(mu), s)

    def transfer_function(self, mu: float) -> tuple[np.ndarray, np.ndarray]:
        return self._tf(self._schedule.values(mu))

    def _response(self, v: list[float], s: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _tf(self, v: list[float]) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "scheduling_variable": SCHEDULING_VARIABLE,
            "operating_points": [{"condition": p.condition, "mu_N": p.mu_N} for p in self.points],
            "mu_range_N": list(self.mu_range),
            "out_of_range": self._schedule.out_of_range,
            "polynomials": self._schedule.to_dict(self.units),
        }


class PhysicalLPV(_InterpolatedLPV):
    """Physical parameters as polynomials in μ; the arm model rebuilt from them."""

    method = "physical"

    @classmethod
    def fit(
        cls,
        points: Iterable[PointLike],
        *,
        order: int = 2,
        out_of_range: OutOfRange = "clip",
    ) -> PhysicalLPV:
        pts = as_operating_points(points)
        table = {k: np.array([float(p.parameters[k]) for p in pts]) for k in PARAMETER_NAMES}
        return cls(pts, table, order, out_of_range)

    def _response(self, v: list[float], s: np.ndarray) -> np.ndarray:
        I, bi, ki, bc, kc = v
        return 1.0 / (bc * s + kc) + 1.0 / ((I * s + bi) * s + ki)

    def _tf(self, v: list[float]) -> tuple[np.ndarray, np.ndarray]:
        return admittance_tf(dict(zip(PARAMETER_NAMES, v, strict=True)))


@dataclass(frozen=True)
class StateSpaceBlock:
    """x' = A x + B u, y = C x + D u."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray

    def frequency_response(self, f_hz: ArrayLike) -> np.ndarray:
        f = np.atleast_1d(np.asarray(f_hz, dtype=float))
        n = self.A.shape[0]
        out = np.empty(f.shape, dtype=complex)
        for i, fi in enumerate(f):
            x = np.linalg.solve(2j * np.pi * fi * np.eye(n) - self.A, self.B)
            out[i] = (self.C @ x + self.D).item()
        return out


@dataclass(frozen=True)
class Subsystems:
    """H = gain · first · second, the blocks in observable canonical form."""

    gain: float
    first: StateSpaceBlock
    second: StateSpaceBlock


_ENTRY_UNITS_SPLIT = {
    "gain": "rad/(N·m·s)",
    "F_A": "1/s",  # contact pole
    "F_B": "1/s",  # contact pole − first-order zero
    "S_a1": "1/s",
    "S_a0": "1/s²",
    "S_b0": "1/s",  # minus the second-order zero
}
_ENTRY_UNITS_SECOND = {
    "gain": "rad/(N·m·s)",
    "F_A": "1/s",
    "S_a1": "1/s",
    "S_a0": "1/s²",
    "S_b1": "1/s",
    "S_b0": "1/s²",
}


def decompose(
    parameters: Mapping[str, float],
    zeros: Structure,
    first_order_zero: ZeroRank | None = None,
) -> dict[str, float]:
    """The free state-space entries and gain of one local model (see the module docstring).

    "split": H = g · (s − z_F)/(s − p) · (s − z_S)/(s² + a1 s + a0), with
    F = (A=p, B=p − z_F, C=1, D=1) and S = (A=[[−a1, 1], [−a0, 0]], B=[1, −z_S], C=[1, 0], D=0).
    "second_order": H = g · 1/(s − p) · (s² + c1 s + c0)/(s² + a1 s + a0), with F = (p, 1, 1, 0)
    and S = (A as above, B=[b1, b0] = [c1 − a1, c0 − a0], C=[1, 0], D=1).
    ``first_order_zero`` (split only) is which ranked zero goes with the contact pole; by
    default the one nearer to it.
    """
    I, bi, ki, bc, kc = _unpack(parameters)
    pole = -kc / bc
    entries = {"gain": 1.0 / bc, "F_A": pole}
    if zeros == "split":
        if not _zeros_are_real(parameters):
            z = local_zeros(parameters)
            raise StructureError(
                f"zeros {z[0]:.4g}, {z[1]:.4g} are complex: no real first-order subsystem with "
                "one zero exists; use zeros='second_order' or physical interpolation"
            )
        slow, fast = (z.real for z in local_zeros(parameters))
        rank = first_order_zero or _first_order_zero_rank(parameters)
        z_f, z_s = (slow, fast) if rank == "slow" else (fast, slow)
        entries.update(F_B=pole - z_f, S_a1=bi / I, S_a0=ki / I, S_b0=-z_s)
    elif zeros == "second_order":
        entries.update(S_a1=bi / I, S_a0=ki / I, S_b1=bc / I, S_b0=kc / I)
    else:
        raise ValueError(f"zeros must be 'split' or 'second_order', got {zeros!r}")
    return entries


def resolve_zero_placement(
    points: Sequence[OperatingPoint], zeros: ZeroPlacement = "auto"
) -> tuple[Structure, ZeroRank | None, str]:
    """(structure, first-order zero rank or None, reason) for a set of operating points.

    Raises :class:`StructureError` when "split" is asked for and does not exist.
    """
    if zeros == "second_order":
        return "second_order", None, "asked for: both zeros in the second-order block"
    if zeros not in ("auto", "split"):
        raise ValueError(f"zeros must be auto, split or second_order, got {zeros!r}")
    complex_at = [p.condition for p in points if not _zeros_are_real(p.parameters)]
    problem = None
    rank: ZeroRank | None = None
    if complex_at:
        problem = (
            f"the zeros are complex at {complex_at}, so no real first-order subsystem with one "
            "zero exists there"
        )
    else:
        ranks = {p.condition: _first_order_zero_rank(p.parameters) for p in points}
        if len(set(ranks.values())) > 1:
            problem = (
                "the zero nearest the contact pole is the slower one at some operating points and "
                f"the faster one at others ({ranks}); pairing it with the first-order block would "
                "make the state-space entries jump"
            )
        else:
            rank = next(iter(ranks.values()))
    if problem is None:
        return (
            "split",
            rank,
            (
                f"one real zero per block at every operating point; the {rank} zero pairs with the "
                "contact pole"
            ),
        )
    if zeros == "split":
        raise StructureError(
            f"cannot use the paper's split structure: {problem}. Use zeros='second_order' "
            "(both zeros in the second-order block) or PhysicalLPV"
        )
    return "second_order", None, f"{problem}; both zeros go in the second-order block"


class DeCaignyLPV(_InterpolatedLPV):
    """Gain and observable-canonical state-space entries as polynomials in μ (de Caigny et al.)."""

    method = "de_caigny"

    def __init__(
        self,
        points: Sequence[OperatingPoint],
        table: Mapping[str, np.ndarray],
        order: int,
        out_of_range: OutOfRange,
        structure: Structure,
        first_order_zero: ZeroRank | None,
        structure_reason: str,
    ) -> None:
        super().__init__(points, table, order, out_of_range)
        self.structure = structure
        self.first_order_zero = first_order_zero
        self.structure_reason = structure_reason
        self.units = _ENTRY_UNITS_SPLIT if structure == "split" else _ENTRY_UNITS_SECOND

    @classmethod
    def fit(
        cls,
        points: Iterable[PointLike],
        *,
        order: int = 2,
        zeros: ZeroPlacement = "auto",
        out_of_range: OutOfRange = "clip",
    ) -> DeCaignyLPV:
        pts = as_operating_points(points)
        structure, rank, reason = resolve_zero_placement(pts, zeros)
        local = [decompose(p.parameters, structure, rank) for p in pts]
        table = {k: np.array([e[k] for e in local]) for k in local[0]}
        return cls(pts, table, order, out_of_range, structure, rank, reason)

    def _response(self, v: list[float], s: np.ndarray) -> np.ndarray:
        if self.structure == "split":
            g, fa, fb, a1, a0, b0 = v
            return g * (1.0 + fb / (s - fa)) * ((s + b0) / ((s + a1) * s + a0))
        g, fa, a1, a0, b1, b0 = v
        return g / (s - fa) * (1.0 + (b1 * s + b0) / ((s + a1) * s + a0))

    def _tf(self, v: list[float]) -> tuple[np.ndarray, np.ndarray]:
        if self.structure == "split":
            g, fa, fb, a1, a0, b0 = v
            num = g * np.polymul([1.0, fb - fa], [1.0, b0])
        else:
            g, fa, a1, a0, b1, b0 = v
            num = g * np.array([1.0, a1 + b1, a0 + b0])
        return num, np.polymul([1.0, -fa], [1.0, a1, a0])

    def subsystems(self, mu: float) -> Subsystems:
        """Gain and the two blocks at μ, in observable canonical form."""
        e = self.parameters(mu)
        a_s = np.array([[-e["S_a1"], 1.0], [-e["S_a0"], 0.0]])
        c_s = np.array([[1.0, 0.0]])
        if self.structure == "split":
            first = _block([[e["F_A"]]], [[e["F_B"]]], [[1.0]], [[1.0]])
            second = _block(a_s, [[1.0], [e["S_b0"]]], c_s, [[0.0]])
        else:
            first = _block([[e["F_A"]]], [[1.0]], [[1.0]], [[0.0]])
            second = _block(a_s, [[e["S_b1"]], [e["S_b0"]]], c_s, [[1.0]])
        return Subsystems(gain=e["gain"], first=first, second=second)

    def state_space(self, mu: float) -> StateSpaceBlock:
        """The series connection gain → first → second as one 3-state model at μ."""
        sub = self.subsystems(mu)
        f, s, g = sub.first, sub.second, sub.gain
        a = np.block([[f.A, np.zeros((1, 2))], [s.B @ f.C, s.A]])
        b = np.vstack([f.B * g, s.B @ f.D * g])
        c = np.hstack([s.D @ f.C, s.C])
        d = s.D @ f.D * g
        return StateSpaceBlock(a, b, c, d)

    def to_dict(self) -> dict[str, Any]:
        d = super().to_dict()
        d["structure"] = self.structure
        d["structure_reason"] = self.structure_reason
        d["first_order_zero"] = self.first_order_zero
        d["fixed_entries"] = (
            {"F_C": 1.0, "F_D": 1.0, "S_b1": 1.0, "S_C": [1.0, 0.0], "S_D": 0.0}
            if self.structure == "split"
            else {"F_B": 1.0, "F_C": 1.0, "F_D": 0.0, "S_C": [1.0, 0.0], "S_D": 1.0}
        )
        d["local_pole_zero"] = [_pole_zero_summary(p) for p in self.points]
        return d


def _block(a: ArrayLike, b: ArrayLike, c: ArrayLike, d: ArrayLike) -> StateSpaceBlock:
    return StateSpaceBlock(*(np.asarray(m, dtype=float) for m in (a, b, c, d)))


def _pole_zero_summary(p: OperatingPoint) -> dict[str, Any]:
    I, bi, ki, bc, kc = _unpack(p.parameters)
    zs = local_zeros(p.parameters)
    return {
        "condition": p.condition,
        "contact_pole_rad_s": -kc / bc,
        "intrinsic_poles_real": bi**2 - 4.0 * I * ki >= 0.0,
        "zeros_rad_s": [[z.real, z.imag] for z in zs],
        "zeros_real": _zeros_are_real(p.parameters),
    }


def build_lpv(
    points: Iterable[PointLike],
    method: str = "physical",
    *,
    order: int = 2,
    zeros: ZeroPlacement = "auto",
    out_of_range: OutOfRange = "clip",
) -> LPVModel:
    """Fit an LPV model with ``method`` "physical" or "de_caigny" on exactly these points."""
    if method == "physical":
        return PhysicalLPV.fit(points, order=order, out_of_range=out_of_range)
    if method == "de_caigny":
        return DeCaignyLPV.fit(points, order=order, zeros=zeros, out_of_range=out_of_range)
    raise ValueError(f"unknown LPV method {method!r}; choose from {METHODS}")


# --------------------------------------------------------------------------------------------
# Table 2: FIT% at the operating points


@dataclass(frozen=True)
class FitRow:
    condition: str
    mu_N: float
    included: bool
    exclusion_reason: str | None
    lti_fit_percent: float | None  # local model vs measured FRF; None without an FRF
    lpv_fit_percent: dict[str, float | None]  # per method; None when excluded or no FRF

    def to_dict(self) -> dict[str, Any]:
        return {
            "condition": self.condition,
            "mu_N": self.mu_N,
            "included_in_lpv": self.included,
            "exclusion_reason": self.exclusion_reason,
            "lti_fit_percent": self.lti_fit_percent,
            "lpv_fit_percent": dict(self.lpv_fit_percent),
        }


@dataclass(frozen=True)
class FitTable:
    rows: list[FitRow]
    methods: tuple[str, ...]
    order: int
    excluded: dict[str, str]
    structure: Structure | None = None  # de Caigny structure, when that method ran
    structure_reason: str | None = None

    def row(self, condition: str) -> FitRow:
        for r in self.rows:
            if r.condition == condition:
                return r
        raise KeyError(condition)

    def to_dict(self) -> dict[str, Any]:
        return {
            "quantity": "FIT% = 100·(1 − Σ(1/f)|Ĥ − H|² / Σ(1/f)|H|²)",
            "methods": list(self.methods),
            "order": self.order,
            "excluded": dict(self.excluded),
            "de_caigny_structure": self.structure,
            "de_caigny_structure_reason": self.structure_reason,
            "rows": [r.to_dict() for r in self.rows],
        }


def fit_table(
    points: Iterable[PointLike],
    *,
    methods: Sequence[str] = METHODS,
    order: int = 2,
    exclude: Mapping[str, str] = DEFAULT_EXCLUSIONS,
    zeros: ZeroPlacement = "auto",
) -> FitTable:
    """The paper's Table 2: FIT% of the local LTI model and of each LPV model at every point."""
    pts = as_operating_points(points)
    included, excluded = select_operating_points(pts, exclude)
    if not included:
        raise ValueError(
            "no operating point to build an LPV model from (no condition with an analysable "
            f"trial{', after excluding ' + ', '.join(sorted(excluded)) if excluded else ''})"
        )
    models = {m: build_lpv(included, m, order=order, zeros=zeros) for m in methods}
    rows = []
    for p in pts:
        lti = None
        lpv: dict[str, float | None] = {m: None for m in methods}
        if p.frf is not None:
            f, h = p.frf.frequencies_hz, p.frf.response
            lti = fit_percent(h, admittance_response(p.parameters, f), f)
            if p.condition not in excluded:
                for m, model in models.items():
                    lpv[m] = fit_percent(h, model.frequency_response(p.mu_N, f), f)
        rows.append(
            FitRow(
                p.condition,
                p.mu_N,
                p.condition not in excluded,
                excluded.get(p.condition),
                lti,
                lpv,
            )
        )
    dc = models.get("de_caigny")
    return FitTable(
        rows=rows,
        methods=tuple(methods),
        order=order,
        excluded=excluded,
        structure=getattr(dc, "structure", None),
        structure_reason=getattr(dc, "structure_reason", None),
    )


# --------------------------------------------------------------------------------------------
# Leave-one-out verification


@dataclass(frozen=True)
class LeaveOneOutResult:
    method: str
    condition: str  # the operating point left out and predicted
    mu_N: float
    trained_on: list[str]
    predicted_parameters: dict[str, float]
    fit_vs_local_percent: float  # prediction vs the point's own local model
    in_sample_fit_vs_local_percent: float  # same, with the point in the fit
    fit_vs_measured_percent: float | None  # prediction vs the measured FRF
    in_sample_fit_vs_measured_percent: float | None
    vaf_percent: float | None  # prediction driven by the measured torque vs measured angle
    in_sample_vaf_percent: float | None

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "left_out": self.condition,
            "mu_N": self.mu_N,
            "trained_on": list(self.trained_on),
            "predicted_parameters": dict(self.predicted_parameters),
            "fit_vs_local_percent": self.fit_vs_local_percent,
            "in_sample_fit_vs_local_percent": self.in_sample_fit_vs_local_percent,
            "fit_vs_measured_percent": self.fit_vs_measured_percent,
            "in_sample_fit_vs_measured_percent": self.in_sample_fit_vs_measured_percent,
            "vaf_percent": self.vaf_percent,
            "in_sample_vaf_percent": self.in_sample_vaf_percent,
        }


@dataclass(frozen=True)
class LeaveOneOutReport:
    results: list[LeaveOneOutResult]
    methods: tuple[str, ...]
    order: int
    excluded: dict[str, str]
    not_left_out: dict[str, str]  # the end points, and why they are not predicted
    structure: Structure | None = None

    def get(self, method: str, condition: str) -> LeaveOneOutResult:
        for r in self.results:
            if (r.method, r.condition) == (method, condition):
                return r
        raise KeyError((method, condition))

    def to_dict(self) -> dict[str, Any]:
        return {
            "methods": list(self.methods),
            "order": self.order,
            "excluded": dict(self.excluded),
            "not_left_out": dict(self.not_left_out),
            "de_caigny_structure": self.structure,
            "results": [r.to_dict() for r in self.results],
        }


def leave_one_out(
    points: Iterable[PointLike],
    *,
    methods: Sequence[str] = METHODS,
    order: int = 2,
    exclude: Mapping[str, str] = DEFAULT_EXCLUSIONS,
    zeros: ZeroPlacement = "auto",
    frequencies_hz: ArrayLike | None = None,
) -> LeaveOneOutReport:
    """Leave each intermediate operating point out, rebuild, and predict it.

    FIT% against the local model is computed on the point's measured frequencies when it has an
    FRF, else on ``frequencies_hz`` (default: the perturbation's band centres). The de Caigny
    structure is chosen once on all included points so that every fold uses the same one.
    """
    included, excluded = select_operating_points(points, exclude)
    if len(included) < 3:
        raise ValueError(f"leave-one-out needs ≥ 3 operating points, got {len(included)}")
    grid = default_frequencies_hz() if frequencies_hz is None else np.asarray(frequencies_hz, float)
    structure: Structure | None = None
    if "de_caigny" in methods:
        structure = resolve_zero_placement(included, zeros)[0]
    zeros_used: ZeroPlacement = structure or zeros
    full = {m: build_lpv(included, m, order=order, zeros=zeros_used) for m in methods}
    ends = {
        included[0].condition: "lowest μ: predicting it would be extrapolation",
        included[-1].condition: "highest μ: predicting it would be extrapolation",
    }
    results = []
    for k, p in enumerate(included):
        if p.condition in ends:
            continue
        train = included[:k] + included[k + 1 :]
        f = p.frf.frequencies_hz if p.frf is not None else grid
        h_local = admittance_response(p.parameters, f)
        for m in methods:
            model = build_lpv(train, m, order=order, zeros=zeros_used, out_of_range="raise")
            h_pred = model.frequency_response(p.mu_N, f)
            h_in = full[m].frequency_response(p.mu_N, f)
            meas = in_meas = v = v_in = None
            if p.frf is not None:
                meas = fit_percent(p.frf.response, h_pred, f)
                in_meas = fit_percent(p.frf.response, h_in, f)
            if p.time is not None:
                v = _time_vaf(model.transfer_function(p.mu_N), p.time)
                v_in = _time_vaf(full[m].transfer_function(p.mu_N), p.time)
            results.append(
                LeaveOneOutResult(
                    method=m,
                    condition=p.condition,
                    mu_N=p.mu_N,
                    trained_on=[q.condition for q in train],
                    predicted_parameters=model.parameters(p.mu_N),
                    # The local model is the reference here, the prediction the "model".
                    fit_vs_local_percent=fit_percent(h_local, h_pred, f),
                    in_sample_fit_vs_local_percent=fit_percent(h_local, h_in, f),
                    fit_vs_measured_percent=meas,
                    in_sample_fit_vs_measured_percent=in_meas,
                    vaf_percent=v,
                    in_sample_vaf_percent=v_in,
                )
            )
    return LeaveOneOutReport(
        results=results,
        methods=tuple(methods),
        order=order,
        excluded=excluded,
        not_left_out=ends,
        structure=structure,
    )


def _time_vaf(tf: tuple[np.ndarray, np.ndarray], t: TimeData) -> float:
    return vaf(t.angle_rad, simulate(tf[0], tf[1], t.torque_Nm, t.fs_hz))


# --------------------------------------------------------------------------------------------
# Everything at once


@dataclass
class LPVAnalysis:
    models: dict[str, LPVModel]
    table: FitTable
    leave_one_out: LeaveOneOutReport | None
    excluded: dict[str, str] = field(default_factory=dict)
    leave_one_out_skipped: str | None = None  # why there is no leave-one-out, if there is none

    def to_dict(self) -> dict[str, Any]:
        return {
            "excluded": dict(self.excluded),
            "models": {m: model.to_dict() for m, model in self.models.items()},
            "fit_table": self.table.to_dict(),
            "leave_one_out": None if self.leave_one_out is None else self.leave_one_out.to_dict(),
            "leave_one_out_skipped": self.leave_one_out_skipped,
        }


def analyse_lpv(
    points: Iterable[PointLike],
    *,
    methods: Sequence[str] = METHODS,
    order: int = 2,
    exclude: Mapping[str, str] = DEFAULT_EXCLUSIONS,
    zeros: ZeroPlacement = "auto",
    frequencies_hz: ArrayLike | None = None,
) -> LPVAnalysis:
    """Models, Table 2 and leave-one-out in one call (leave-one-out only with ≥ 3 points)."""
    pts = as_operating_points(points)
    included, excluded = select_operating_points(pts, exclude)
    if not included:
        raise ValueError(
            "no operating point to build an LPV model from (no condition with an analysable "
            f"trial{', after excluding ' + ', '.join(sorted(excluded)) if excluded else ''})"
        )
    models = {m: build_lpv(included, m, order=order, zeros=zeros) for m in methods}
    table = fit_table(pts, methods=methods, order=order, exclude=exclude, zeros=zeros)
    loo = None
    skipped = None
    if len(included) < 3 or len(included) - 1 < order + 1:
        skipped = (
            f"{len(included)} operating points: leaving one out leaves too few for a polynomial "
            f"of order {order} (needs {order + 1}) or no intermediate point"
        )
    else:
        loo = leave_one_out(
            pts,
            methods=methods,
            order=order,
            exclude=exclude,
            zeros=zeros,
            frequencies_hz=frequencies_hz,
        )
    return LPVAnalysis(
        models=models,
        table=table,
        leave_one_out=loo,
        excluded=excluded,
        leave_one_out_skipped=skipped,
    )
