"""Which samples of a trial to analyse, and which frequency bins the perturbation excited.

Only whole perturbation periods are analysed: over a whole period every excited sine completes
an integer number of cycles, so the DFT of the period puts each sine exactly on its bin, with no
leakage into the bins between bands where the noise is measured.

Choosing the periods
    - The recorder knew where the run-in ended (``record.measured_start``/``measured_stop``):
      the whole periods from ``measured_start`` that fit before ``measured_stop``.
    - Unknown (imported data): the largest number of whole periods that *end at the end of the
      record* (or at ``measured_stop`` if only that is known) and leave at least
      ``min_run_in_s`` before them. Default run-in: :data:`DEFAULT_MIN_RUN_IN_S` = 2 s, several
      time constants of the closed loop wheel + arm (its slowest mode decays in a few tenths of a
      second for the paper's wheel), so the start-up transient is gone; the end of a record is
      kept because that is the part furthest from the start-up.

Excited bins
    From ``record.design`` when the record carries it; otherwise detected in the perturbation
    signal over the chosen periods (:func:`detect_excitation`). Adjacent excited bins are paired
    into double bands; a lone excited bin is a band of its own.

Bin k of a period of P samples is the frequency k / period_s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from steerlab.protocols.perturbation import PerturbationDesign, period_samples
from steerlab.protocols.records import TrialRecord

DEFAULT_PERIOD_S = 45.0  # the paper's period; used only when a record carries no design
DEFAULT_MIN_RUN_IN_S = 2.0
MIN_SAMPLE_RATE_HZ = 100.0  # ≥ 5× the highest band (20 Hz): the bands sit well below Nyquist
# Detection thresholds (see detect_excitation): an excited bin must stand this far above the
# median bin power (the noise floor: excited bins are ~1 % of all bins) …
DEFAULT_DETECT_FLOOR_DB = 20.0
# … and be no further than this below the strongest bin. Reduced-power bands are −10 dB in the
# paper's design; −40 dB keeps any sensible power ratio but rejects harmonics of a distorting
# actuator and rounding noise of a clean, computed perturbation signal.
DEFAULT_DETECT_BELOW_MAX_DB = -40.0
# A design attached to a record must hold at least this share of the recorded perturbation's
# power at its bins. Guards against a default design attached to data that were perturbed with
# another one (the shared example's band layout differs from today's default design: 81 %).
# One reduced-power bin of the paper's design carries ~0.8 % of the power, so two wrong bins
# fail; measurement noise or distortion of a real perturbation stays far below 1 %.
MIN_DESIGN_POWER_SHARE = 0.99


@dataclass(frozen=True)
class PeriodSelection:
    """Whole periods ``[start, start + n_periods * period_samples)`` of one record."""

    fs_hz: float
    period_samples: int
    start: int
    n_periods: int
    origin: str  # "recorded": from measured_start/stop; "end-aligned": found from the end

    @property
    def stop(self) -> int:
        return self.start + self.n_periods * self.period_samples

    @property
    def period_s(self) -> float:
        return self.period_samples / self.fs_hz

    @property
    def n_samples(self) -> int:
        return self.n_periods * self.period_samples

    def segment(self, x: np.ndarray) -> np.ndarray:
        """The analysed samples of ``x`` (a record channel), as one array."""
        return np.asarray(x)[self.start : self.stop]

    def periods(self, x: np.ndarray) -> np.ndarray:
        """The analysed samples of ``x`` as an ``(n_periods, period_samples)`` array."""
        return self.segment(x).reshape(self.n_periods, self.period_samples)

    def to_dict(self) -> dict:
        return {
            "fs_Hz": self.fs_hz,
            "period_samples": self.period_samples,
            "period_s": self.period_s,
            "start_sample": self.start,
            "stop_sample": self.stop,
            "start_s": self.start / self.fs_hz,
            "n_periods": self.n_periods,
            "origin": self.origin,
        }


@dataclass(frozen=True)
class Excitation:
    """The excited DFT bins of one period, grouped into (double) bands."""

    period_s: float
    bins: np.ndarray  # int, sorted ascending
    band_of_bin: np.ndarray  # int, 0..n_bands-1, non-decreasing along ``bins``
    origin: str  # "design" or "detected"

    @property
    def n_bands(self) -> int:
        return int(self.band_of_bin.max()) + 1 if len(self.bins) else 0

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self.bins / self.period_s

    def bins_of_band(self, band: int) -> np.ndarray:
        return self.bins[self.band_of_bin == band]

    @property
    def band_frequencies_hz(self) -> np.ndarray:
        """Mean frequency of each band's bins."""
        return np.array([self.bins_of_band(j).mean() / self.period_s for j in range(self.n_bands)])

    def noise_bins(self, per_side: int, nyquist_bin: int) -> list[np.ndarray]:
        """Per band: up to ``per_side`` nearest unexcited bins below and above it.

        Bins 0 (the mean, dominated by offsets) and ``nyquist_bin`` and above are never used.
        Neighbouring bands may share noise bins (with two gap bins they do).
        """
        # A mask, not np.setdiff1d: same bins, but setdiff1d's hashing cost ~5 ms per trial at
        # 1 kHz (22 500 bins), a quarter of a whole study's analysis time.
        taken = np.zeros(max(int(nyquist_bin), 1), dtype=bool)
        taken[0] = True
        inside = self.bins[(self.bins >= 0) & (self.bins < nyquist_bin)]
        taken[inside] = True
        free = np.flatnonzero(~taken)
        out = []
        for j in range(self.n_bands):
            b = self.bins_of_band(j)
            lo = np.searchsorted(free, b.min())
            hi = np.searchsorted(free, b.max(), side="right")
            out.append(np.concatenate([free[max(0, lo - per_side) : lo], free[hi : hi + per_side]]))
        return out

    def same_bins(self, other: Excitation) -> bool:
        return (
            abs(self.period_s - other.period_s) < 1e-9
            and np.array_equal(self.bins, other.bins)
            and np.array_equal(self.band_of_bin, other.band_of_bin)
        )

    def to_dict(self) -> dict:
        return {
            "period_s": self.period_s,
            "bins": self.bins.tolist(),
            "band_of_bin": self.band_of_bin.tolist(),
            "origin": self.origin,
        }


def excitation_from_design(design: PerturbationDesign) -> Excitation:
    order = np.argsort(design.bins, kind="stable")
    bins = np.asarray(design.bins, dtype=int)[order]
    band = np.asarray(design.band_of_bin, dtype=int)[order]
    # Renumber bands in frequency order so band j is always the j-th lowest.
    _, first = np.unique(band, return_index=True)
    rank = {b: r for r, b in enumerate(band[np.sort(first)])}
    band = np.array([rank[b] for b in band], dtype=int)
    return Excitation(float(design.period_s), bins, band, "design")


def pair_bins(bins: np.ndarray) -> np.ndarray:
    """Band index per bin: adjacent bins pair up (left to right), a lone bin is its own band.

    A run of three adjacent bins k, k+1, k+2 gives the band (k, k+1) and the band (k+2).
    """
    bins = np.asarray(bins, dtype=int)
    band = np.empty(len(bins), dtype=int)
    j, i = 0, 0
    while i < len(bins):
        band[i] = j
        if i + 1 < len(bins) and bins[i + 1] == bins[i] + 1:
            band[i + 1] = j
            i += 2
        else:
            i += 1
        j += 1
    return band


def detect_excitation(
    perturbation_periods: np.ndarray,
    period_s: float,
    *,
    floor_db: float = DEFAULT_DETECT_FLOOR_DB,
    below_max_db: float = DEFAULT_DETECT_BELOW_MAX_DB,
) -> Excitation:
    """Find the excited bins in a perturbation signal of ``(n_periods, period_samples)``.

    The periods' spectra are averaged coherently (the perturbation repeats exactly, noise does
    not), then a bin counts as excited when its power is ``floor_db`` above the median bin power
    *and* no more than ``-below_max_db`` below the strongest bin.
    """
    x = np.atleast_2d(np.asarray(perturbation_periods, dtype=float))
    n = x.shape[1]
    spec = np.fft.rfft(x, axis=1).mean(axis=0) * (2.0 / n)
    power = np.abs(spec[1 : (n - 1) // 2 + 1]) ** 2  # bins 1 .. below Nyquist
    if power.size == 0 or not np.any(power > 0):
        raise ValueError("perturbation signal is zero over the chosen periods: nothing excited")
    floor = np.median(power)
    excited = (power > floor * 10 ** (floor_db / 10)) & (
        power >= power.max() * 10 ** (below_max_db / 10)
    )
    bins = np.nonzero(excited)[0] + 1
    return Excitation(float(period_s), bins, pair_bins(bins), "detected")


def _power_share(perturbation_periods: np.ndarray, bins: np.ndarray) -> float:
    """Share of the perturbation's power (mean removed) at ``bins``, periods averaged."""
    x = np.atleast_2d(np.asarray(perturbation_periods, dtype=float))
    n = x.shape[1]
    power = np.abs(np.fft.rfft(x, axis=1).mean(axis=0)[1 : (n - 1) // 2 + 1]) ** 2
    total = power.sum()
    inside = power[bins[bins <= len(power)] - 1].sum()
    return float(inside / total) if total > 0 else float("nan")


def record_period_s(record: TrialRecord, period_s: float | None = None) -> float:
    """The perturbation period: the design's, else ``period_s``, else the paper's 45 s."""
    if record.design is not None:
        return float(record.design.period_s)
    return float(period_s) if period_s is not None else DEFAULT_PERIOD_S


def select_periods(
    record: TrialRecord,
    *,
    period_s: float | None = None,
    min_run_in_s: float = DEFAULT_MIN_RUN_IN_S,
) -> PeriodSelection:
    """The whole perturbation periods of ``record`` to analyse (see the module docstring).

    ``period_s`` is used only when the record carries no design. Raises ``ValueError`` naming
    ``record.source`` when the sample rate, the period or the length do not allow one period.
    """
    where = record.source or record.label()
    fs = float(record.fs_hz)
    if not fs >= MIN_SAMPLE_RATE_HZ:
        raise ValueError(f"{where}: sample rate {fs} Hz is below {MIN_SAMPLE_RATE_HZ:g} Hz")
    n = record.n_samples
    for name in ("perturbation_torque_Nm", "driver_torque_Nm", "wheel_angle_rad"):
        if len(getattr(record, name)) != n:
            raise ValueError(
                f"{where}: {name} has {len(getattr(record, name))} samples, time_s has {n}"
            )
    T = record_period_s(record, period_s)
    try:
        P = period_samples(T, fs)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None

    stop = n if record.measured_stop is None else int(record.measured_stop)
    if not 0 < stop <= n:
        raise ValueError(f"{where}: measured_stop={record.measured_stop} outside 0..{n}")
    if record.measured_start is not None:
        start = int(record.measured_start)
        if not 0 <= start < stop:
            raise ValueError(f"{where}: measured_start={start} not before the stop ({stop})")
        k = (stop - start) // P
        if k < 1:
            raise ValueError(
                f"{where}: the measured part ({(stop - start) / fs:.2f} s from sample {start}) is "
                f"shorter than one perturbation period ({T:g} s)"
            )
        sel = PeriodSelection(fs, P, start, k, "recorded")
    else:
        run_in = int(np.ceil(min_run_in_s * fs - 1e-9))
        k = (stop - run_in) // P
        if k < 1:
            raise ValueError(
                f"{where}: {stop / fs:.2f} s of data hold no whole perturbation period ({T:g} s) "
                f"after a run-in of at least {min_run_in_s:g} s"
            )
        sel = PeriodSelection(fs, P, stop - k * P, k, "end-aligned")
    _check_uniform(record, sel, where)
    return sel


def _check_uniform(record: TrialRecord, sel: PeriodSelection, where: str) -> None:
    # Bins are counted in samples: a gap or a wrong fs_hz in imported data would silently move
    # every frequency, so the time stamps of the analysed samples must match fs_hz.
    t = sel.segment(record.time_s)
    if len(t) < 2:
        return
    dt = np.diff(t)
    bad = np.nonzero(np.abs(dt * sel.fs_hz - 1.0) > 0.5)[0]
    if bad.size:
        i = sel.start + int(bad[0])
        raise ValueError(
            f"{where}: time_s is not sampled at {sel.fs_hz:g} Hz in the analysed periods "
            f"(step of {dt[bad[0]]:g} s after sample {i})"
        )


def find_excitation(
    record: TrialRecord,
    selection: PeriodSelection,
    *,
    floor_db: float = DEFAULT_DETECT_FLOOR_DB,
    below_max_db: float = DEFAULT_DETECT_BELOW_MAX_DB,
) -> Excitation:
    """The record's excited bins: from its design, else detected over ``selection``.

    Raises ``ValueError`` when a band lies at or above the Nyquist frequency.
    """
    where = record.source or record.label()
    if record.design is not None:
        exc = excitation_from_design(record.design)
        share = _power_share(selection.periods(record.perturbation_torque_Nm), exc.bins)
        if not share >= MIN_DESIGN_POWER_SHARE:
            raise ValueError(
                f"{where}: the record's perturbation design does not match its perturbation "
                f"signal (its bins hold {100 * share:.0f} % of the signal's power); "
                "drop the design to detect the excited bins from the signal"
            )
    else:
        exc = detect_excitation(
            selection.periods(record.perturbation_torque_Nm),
            selection.period_s,
            floor_db=floor_db,
            below_max_db=below_max_db,
        )
    if exc.n_bands == 0:
        raise ValueError(f"{where}: no excited frequency bins")
    if exc.bins.max() >= selection.period_samples // 2:
        raise ValueError(
            f"{where}: excited bin {exc.bins.max()} ({exc.bins.max() / exc.period_s:g} Hz) is "
            f"not below the Nyquist frequency of {selection.fs_hz / 2:g} Hz"
        )
    return exc
