"""Reduced Power Method multisine perturbation (Mugge et al. 2007; Pronker et al. 2017).

The perturbation torque is a sum of sines on the DFT grid of one period (resolution 1/T Hz).
Frequencies come in *double bands*: two adjacent bins per band, so an analysis can average them.
Between bands at least ``gap_bins`` bins are left unexcited, so that noise and nonlinear
distortion can be measured there. Bins up to ``full_power_max_hz`` get full power; bins above
get ``reduced_power_ratio`` times that power.

Default reduced-power ratio: 0.1 (amplitude ratio 0.316). The high band then carries about a
tenth of the torque variance, so subjects are not driven into a high-bandwidth behaviour, yet
the arm's response at 20 Hz stays well above encoder and torque-sensor noise (see
``docs/perturbation.md``). It is also the ratio used in the shared example data.

Units: torque in N·m, frequency in Hz, phase in rad; signal(t) = Σ a_k sin(2π f_k t + φ_k).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

import numpy as np


@dataclass(frozen=True)
class PerturbationSpec:
    """What a protocol asks for; :func:`design_multisine` makes the :class:`PerturbationDesign`."""

    period_s: float = 45.0
    n_bands: int = 31
    first_bin: int = 3
    f_max_hz: float = 20.0
    full_power_max_hz: float = 0.7
    reduced_power_ratio: float = 0.1
    sd_nm: float = 2.26
    gap_bins: int = 2
    seed: int = 2017
    crest_iterations: int = 200

    def validate(self, where: str = "perturbation") -> None:
        def bad(name: str, msg: str) -> ValueError:
            return ValueError(f"{where}.{name}: {msg}")

        if not self.period_s > 0:
            raise bad("period_s", f"must be > 0, got {self.period_s}")
        if self.n_bands < 1:
            raise bad("n_bands", f"must be ≥ 1, got {self.n_bands}")
        if self.first_bin < 1:
            raise bad("first_bin", f"must be ≥ 1, got {self.first_bin}")
        if self.gap_bins < 1:
            raise bad(
                "gap_bins", f"must be ≥ 1 (unexcited bins between bands), got {self.gap_bins}"
            )
        if not 0 < self.reduced_power_ratio <= 1:
            raise bad("reduced_power_ratio", f"must be in (0, 1], got {self.reduced_power_ratio}")
        if not self.sd_nm > 0:
            raise bad("sd_nm", f"must be > 0, got {self.sd_nm}")
        top = round(self.f_max_hz * self.period_s)
        need = self.first_bin + (self.n_bands - 1) * (2 + self.gap_bins) + 1
        if top < need:
            raise bad(
                "f_max_hz",
                f"{self.f_max_hz} Hz leaves room for bins up to {top}, but {self.n_bands} bands "
                f"with {self.gap_bins} gap bins from bin {self.first_bin} need bin {need}",
            )


@dataclass(frozen=True)
class PerturbationDesign:
    """A realised multisine: everything needed to regenerate the signal exactly."""

    period_s: float
    bins: np.ndarray  # int, DFT bin index k (frequency k / period_s)
    amplitudes_nm: np.ndarray  # sine amplitude per bin, N·m
    phases_rad: np.ndarray
    band_of_bin: np.ndarray  # int, band index 0..n_bands-1 for each bin
    spec: PerturbationSpec = field(default_factory=PerturbationSpec)
    crest_factor: float = float("nan")

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self.bins / self.period_s

    @property
    def sd_nm(self) -> float:
        return float(np.sqrt(np.sum(self.amplitudes_nm**2) / 2.0))

    def signal(self, t_s: np.ndarray) -> np.ndarray:
        """Perturbation torque at times ``t_s`` (s, any phase of the period), N·m."""
        t = np.asarray(t_s, dtype=float)
        # Reduce time modulo the period first: keeps the sine arguments small and exact.
        tm = np.mod(t, self.period_s)
        w = 2 * np.pi * self.frequencies_hz
        out = np.zeros_like(tm)
        for a, wk, ph in zip(self.amplitudes_nm, w, self.phases_rad, strict=True):
            out += a * np.sin(wk * tm + ph)
        return out

    def one_period(self, fs_hz: float) -> np.ndarray:
        """One period sampled at ``fs_hz`` (must give an integer number of samples)."""
        n = period_samples(self.period_s, fs_hz)
        spec = np.zeros(n // 2 + 1, dtype=complex)
        # sin(wt + φ) = Im(e^{i(wt+φ)}) -> rfft coefficient  -i/2 · a e^{iφ} · n
        spec[self.bins] = -0.5j * self.amplitudes_nm * np.exp(1j * self.phases_rad) * n
        return np.fft.irfft(spec, n)

    def to_dict(self) -> dict:
        return {
            "period_s": self.period_s,
            "bins": self.bins.tolist(),
            "frequencies_hz": self.frequencies_hz.tolist(),
            "amplitudes_Nm": self.amplitudes_nm.tolist(),
            "phases_rad": self.phases_rad.tolist(),
            "band_of_bin": self.band_of_bin.tolist(),
            "crest_factor": self.crest_factor,
            "spec": asdict(self.spec),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, d: dict) -> PerturbationDesign:
        return cls(
            period_s=float(d["period_s"]),
            bins=np.asarray(d["bins"], dtype=int),
            amplitudes_nm=np.asarray(d["amplitudes_Nm"], dtype=float),
            phases_rad=np.asarray(d["phases_rad"], dtype=float),
            band_of_bin=np.asarray(d["band_of_bin"], dtype=int),
            spec=PerturbationSpec(**d.get("spec", {})),
            crest_factor=float(d.get("crest_factor", float("nan"))),
        )

    @classmethod
    def from_json(cls, s: str) -> PerturbationDesign:
        return cls.from_dict(json.loads(s))


def period_samples(period_s: float, fs_hz: float) -> int:
    n = period_s * fs_hz
    if abs(n - round(n)) > 1e-6 * max(1.0, n):
        raise ValueError(
            f"a period of {period_s} s at {fs_hz} Hz is {n} samples; need a whole number"
        )
    return int(round(n))


def band_start_bins(spec: PerturbationSpec) -> np.ndarray:
    """First bin of each double band: log-spread from ``first_bin`` to the top bin.

    Bands are spaced by at least ``2 + gap_bins`` bins; where log spacing would crowd them
    (the low end) they sit at that minimum spacing, which is what makes the low end linear.
    """
    spacing = 2 + spec.gap_bins
    top = round(spec.f_max_hz * spec.period_s) - 1  # last band is (top, top + 1)
    n = spec.n_bands
    starts = np.empty(n, dtype=int)
    starts[0] = spec.first_bin
    for j in range(1, n):
        # Log-spread the remaining bands between the previous one and the top.
        remaining = n - j
        ratio = (top / starts[j - 1]) ** (1.0 / remaining)
        starts[j] = max(starts[j - 1] + spacing, int(round(starts[j - 1] * ratio)))
    # Whatever rounding did, the last band ends exactly at the top bin + 1 ≤ f_max.
    starts[-1] = max(starts[-2] + spacing, top)
    return starts


def design_multisine(spec: PerturbationSpec | None = None) -> PerturbationDesign:
    """Build the multisine for ``spec``; same spec (seed included) → same design."""
    spec = spec or PerturbationSpec()
    spec.validate()
    starts = band_start_bins(spec)
    bins = np.repeat(starts, 2) + np.tile([0, 1], len(starts))
    band = np.repeat(np.arange(len(starts)), 2)
    f = bins / spec.period_s
    rel = np.where(f <= spec.full_power_max_hz + 1e-12, 1.0, np.sqrt(spec.reduced_power_ratio))
    amps = rel * spec.sd_nm / np.sqrt(np.sum(rel**2) / 2.0)
    rng = np.random.default_rng(spec.seed)
    phases = rng.uniform(-np.pi, np.pi, size=len(bins))
    phases, crest = _lower_crest_factor(bins, amps, phases, spec.crest_iterations)
    return PerturbationDesign(
        period_s=spec.period_s,
        bins=bins,
        amplitudes_nm=amps,
        phases_rad=phases,
        band_of_bin=band,
        spec=spec,
        crest_factor=crest,
    )


def _lower_crest_factor(
    bins: np.ndarray, amps: np.ndarray, phases: np.ndarray, iterations: int
) -> tuple[np.ndarray, float]:
    """Iterative clipping (van der Ouderaa, Schoukens & Renneboog 1988).

    Clip the time signal, keep only the phases of its spectrum at the excited bins, restore the
    amplitudes; keep the best phases seen. Deterministic given the starting phases.
    """
    n = int(2 ** np.ceil(np.log2(8 * (bins.max() + 1))))  # oversampled grid for the peak
    coef = np.zeros(n // 2 + 1, dtype=complex)

    def synth(ph: np.ndarray) -> np.ndarray:
        coef[:] = 0
        coef[bins] = -0.5j * amps * np.exp(1j * ph) * n
        return np.fft.irfft(coef, n)

    def crest(x: np.ndarray) -> float:
        return float(np.max(np.abs(x)) / np.sqrt(np.mean(x**2)))

    x = synth(phases)
    best_ph, best_cf = phases.copy(), crest(x)
    ph = phases.copy()
    for i in range(iterations):
        level = (0.9 - 0.3 * i / max(iterations, 1)) * np.max(np.abs(x))
        c = np.fft.rfft(np.clip(x, -level, level))
        # angle(c) = angle(-0.5j a e^{iφ}) = φ - π/2  →  φ = angle + π/2
        ph = np.angle(c[bins]) + np.pi / 2
        x = synth(ph)
        cf = crest(x)
        if cf < best_cf:
            best_ph, best_cf = ph.copy(), cf
    best_ph = np.mod(best_ph + np.pi, 2 * np.pi) - np.pi
    return best_ph, best_cf
