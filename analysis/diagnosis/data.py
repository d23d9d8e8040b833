"""Measured trials prepared for the diagnosis: spectra on a fixed bin grid, checks of the input.

Every trial is compared with the simulator on the same footing:

- The analysed samples are whole perturbation periods (``analysis.periods.select_periods``),
  taken as one DFT segment; with several periods per trial the excited bins are multiples of
  the period count.
- Each channel is made periodic before the DFT by removing the ramp between its first sample
  and the sample after the segment. A trial's angle wanders slowly (the remnant), so the
  periodic extension of a raw segment jumps at its ends and the jump leaks into every bin
  with a 1/k spectrum. At 6–25 Hz that leakage, not noise, dominated the unexcited bins of the
  angle (by 100× in simulated data), and it looks coherent from repetition to repetition.
  The same correction is applied to the simulated channels, so it cannot favour a model.
- Bins from the first to ``F_MAX_HZ`` (25 Hz: the top band is 20 Hz, and harmonics of the
  strongly excited low bands stay below it) are kept, excited and unexcited alike; the bins
  are grouped into bands of at least ``MIN_BAND_BINS`` where the noise is taken as white.
- Only the five core interchange channels are used (time, perturbation torque, driver torque,
  wheel angle, grip force), so data from any rig that can export them can be diagnosed.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.signal import butter, sosfiltfilt

from steerlab.analysis.armfit import FitOptions, fit_arm, fit_arm_joint
from steerlab.analysis.frf import TrialSpectra, frequency_response, trial_spectra
from steerlab.analysis.periods import (
    Excitation,
    PeriodSelection,
    find_excitation,
    record_period_s,
    select_periods,
)
from steerlab.hardware.safety import SafetyLimits
from steerlab.hardware.sim.physiology import ArmParams
from steerlab.protocols.datafile import DataFileError, SessionFile, session_files
from steerlab.protocols.protocol import VirtualWheel
from steerlab.protocols.records import STATUS_COMPLETE, TrialRecord

if TYPE_CHECKING:  # wheel.py imports this module
    from steerlab.analysis.diagnosis.wheel import DiagnosisWheel

# The baseline's starting arms come from the report's default estimator (docs/method-estimator.md):
# maximum likelihood with the measured, smoothed noise model, the rig's sampled-data response,
# and one arm inertia per subject from the data. The paper's weighting with I_i held at 0.1
# (the diagnosis' fit until issue 18) misfitted every trial of a world whose arm is 0.07 kg·m²,
# and the misfit was then reported as "unexplained" on null data.
DIAGNOSIS_FIT = FitOptions()
F_MAX_HZ = 25.0
MIN_BAND_BINS = 16
BAND_MIN_RATIO = 1.26  # a band spans at least a third of an octave
TRANSIENT_ORDER = 2  # smooth terms (constant, slope) projected out of each band
GRIP_LOWPASS_HZ = 2.0  # the slow grip fluctuation is below ~1 Hz; glove noise is white
# A rig whose wheel relation Tp − Td = Z_w θ is off by more than this (relative error at the
# excited bins) is not the rig the simulator models.
RIG_MISMATCH_LIMIT = 0.5
# ... below this frequency, where the wheel's own dynamics dominate Tp − Td and the candidate
# mechanisms at plausible strength change it by a few per cent (a 10 ms actuator lag: 6 % at
# 1 Hz, but 70 % at 20 Hz).
RIG_CHECK_MAX_HZ = 2.0


FALLBACK_ARM = ArmParams(0.1, 1.0, 13.0, 2.6, 100.0)  # a mid-range arm (BT12-like)


class DiagnosisError(DataFileError):
    """Input the diagnosis cannot work with. A ``DataFileError`` so that the command line
    reports it as bad input (one message, exit status 2)."""


@dataclass
class TrialData:
    """One trial, measured, on the diagnosis' bin grid."""

    label: str
    subject: str
    condition: str
    repetition: int
    familiarization: bool
    trial_index: int | None
    fs_hz: float
    tp: np.ndarray  # perturbation torque from the trial's first sample to the end of the sim
    grip: np.ndarray  # measured total grip force, low-passed, same length
    grip_raw: np.ndarray
    start: int
    stop: int
    n_sim: int  # samples simulated: up to and including the sample after the segment
    selection: PeriodSelection
    excitation: Excitation
    bins: np.ndarray  # DFT bins of the segment used (1 … K)
    excited: np.ndarray  # bool per bin
    band: np.ndarray  # noise band index per bin
    Y: np.ndarray  # complex (4, n_bins): θ (rad), Td (N·m), ramp removed; θ, Td raw
    Tp: np.ndarray  # complex (n_bins,)
    Zw: np.ndarray  # complex (n_bins,), wheel impedance I s² + b s + k
    theta: np.ndarray  # measured segment (mean-free)
    td: np.ndarray
    arm0: ArmParams  # the FRF fit of this trial alone (subject's I_i held): a start
    arm_cell: ArmParams  # the FRF fit of the subject × condition (all repetitions): another
    spectra: TrialSpectra  # the paper's per-trial Fourier coefficients (analysis.frf)
    source: str = ""
    notes: list[str] = field(default_factory=list)
    # The wheel the simulated world has (inertia, rendered b and k): nominal, or a rig check's
    # (analysis.diagnosis.wheel); its wheel-side mechanisms are in the baseline's mechanisms.
    wheel: VirtualWheel = field(default_factory=VirtualWheel)
    # How its damping and spring act (hardware.sim.world.WorldConfig.wheel_rendering): as
    # Steerlab's rig renders them, or physically; from the data (analysis.rig_from_data).
    wheel_rendering: str = "sampled"
    # The torque and slew limits the simulated loop applies to its command: Steerlab's rig's,
    # unless the baseline finds the recording's rig had none (engine.choose_rig_limits).
    safety: SafetyLimits = field(default_factory=SafetyLimits)
    # Remnant realisations (N·m, n_sim samples each) for nonlinear models; set by the fit.
    remnant: list[np.ndarray] = field(default_factory=list)
    # Undo the model's torque-reading delay in the wheel-equation channel (final fit only).
    undo_reading_delay: bool = False
    # The subject's arm inertia from the data (:func:`_cell_fits`), NaN until fitted: the start
    # of the inertia every model fits per subject (analysis.diagnosis.fit), or, when
    # ``inertia_fixed`` (run_diagnosis(inertia_kgm2=...)), the value every model holds.
    I_i: float = float("nan")
    I_i_sem: float | None = None
    inertia_fixed: bool = False
    _projector: Callable[[np.ndarray], np.ndarray] | None = field(default=None, repr=False)
    _grip_stats: tuple[float, float] | None = field(default=None, repr=False)
    # analysis.diagnosis.steady_state.perturbation's result (False: the steady state does not
    # apply to this trial), computed once.
    _perturbation: object = field(default=None, repr=False, init=False)

    @property
    def grip_stats(self) -> tuple[float, float]:
        """Mean and standard deviation (N) of the grip force in the analysed segment."""
        if self._grip_stats is None:
            g = self.grip[self.start : self.stop]
            self._grip_stats = (float(np.mean(g)), float(np.std(g)))
        return self._grip_stats

    def __getstate__(self) -> dict:
        # The cached projector is a closure: rebuilt on demand in worker processes.
        state = dict(self.__dict__)
        state["_projector"] = None
        return state

    @property
    def n_bands(self) -> int:
        return int(self.band.max()) + 1

    @property
    def freqs_hz(self) -> np.ndarray:
        return self.bins * self.fs_hz / (self.stop - self.start)

    @property
    def cell(self) -> tuple[str, str]:
        return (self.subject, self.condition)


def channel_spectra(
    x: np.ndarray, start: int, stop: int, bins: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Amplitude-scaled spectra (|X| = sine amplitude) of x[start:stop] at ``bins``: with the
    ramp x[stop] − x[start] removed, and raw (see the module docstring for which is used
    where). Without a sample after the segment the last step is extrapolated."""
    x = np.asarray(x, dtype=float)
    seg = x[start:stop]
    n = len(seg)
    nxt = x[stop] if stop < len(x) else 2 * seg[-1] - seg[-2]
    raw = np.fft.rfft(seg)[bins] * (2.0 / n)
    # DFT of the ramp Δ·m/n at bin k: −Δ / (1 − e^{−j2πk/n}).
    ramp = -(nxt - seg[0]) * _ramp_dft(n, np.asarray(bins, dtype=np.int64).tobytes())
    return raw - ramp * (2.0 / n), raw


@lru_cache(maxsize=256)
def _ramp_dft(n: int, bins: bytes) -> np.ndarray:
    """1 / (1 − e^{−j2πk/n}) at the bins (``bins``: the int array's bytes, as a cache key):
    the same for every simulation of a trial."""
    k = np.frombuffer(bins, dtype=np.int64)
    out = 1.0 / (1.0 - np.exp(-2j * np.pi * k / n))
    out.flags.writeable = False
    return out


def measurement_spectra(
    theta: np.ndarray, td: np.ndarray, start: int, stop: int, bins: np.ndarray
) -> np.ndarray:
    """(4, n_bins): θ and Td with the ramp removed, then θ and Td raw."""
    th_r, th = channel_spectra(theta, start, stop, bins)
    td_r, td_ = channel_spectra(td, start, stop, bins)
    return np.array([th_r, td_r, th, td_])


def transient_projector(trial: TrialData) -> Callable[[np.ndarray], np.ndarray]:
    """x ↦ x with, in every band, its least-squares fit by a polynomial in frequency of
    TRANSIENT_ORDER terms removed (last axis = bins).

    What is not periodic in a segment (the start-up transient, the remnant's slow wander)
    leaks into the DFT as a term that varies smoothly with frequency (the local polynomial
    method of Pintelon & Schoukens). Left in, it is structure that the arm parameters can
    shape through the simulated transient; on null data that made the fit beat the true
    parameters by hundreds of units of −2 log L. Excited lines and distortion are not smooth
    from bin to bin and lose only their small projection on the polynomial.
    """
    if trial._projector is not None:
        return trial._projector
    # Every band's orthonormal polynomial basis, per bin (q[j, k]: basis function j of bin
    # k's band at bin k; the bands are contiguous): the projection's coefficients are sums
    # over each band (np.add.reduceat), a few operations on whole rows. It runs once per
    # simulation in the fits; as two (n_bins × bands·order) matrix products it took a
    # tenth of a diagnosis's time.
    n = len(trial.bins)
    q = np.zeros((TRANSIENT_ORDER, n))
    for b in range(trial.n_bands):
        idx = np.flatnonzero(trial.band == b)
        x = (trial.bins[idx] - trial.bins[idx].mean()) / max(1.0, np.ptp(trial.bins[idx]) / 2)
        P = np.stack([x**j for j in range(TRANSIENT_ORDER)], axis=1)
        Q, _ = np.linalg.qr(P)  # (len(idx), min(len(idx), TRANSIENT_ORDER))
        q[: Q.shape[1], idx] = Q.T
    if np.any(np.diff(trial.band) < 0) or np.any(np.diff(trial.band) > 1):
        raise ValueError("transient_projector: the bands must be contiguous and in order")
    starts = np.flatnonzero(np.diff(trial.band, prepend=-1))
    counts = np.diff(np.append(starts, n))

    def project(v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=complex)
        out = v.copy()
        for qj in q:
            coef = np.add.reduceat(v * qj, starts, axis=-1)
            out -= np.repeat(coef, counts, axis=-1) * qj
        return out

    trial._projector = project
    return project


def make_bands(n_bins: int) -> np.ndarray:
    """Band index for bins 1..n_bins: contiguous, ≥ MIN_BAND_BINS bins, ≥ 1/3 octave wide."""
    band = np.empty(n_bins, dtype=int)
    j, lo = 0, 1
    k = 1
    while k <= n_bins:
        band[k - 1] = j
        if (k - lo + 1) >= MIN_BAND_BINS and k >= BAND_MIN_RATIO * lo:
            j += 1
            lo = k + 1
        k += 1
    # A short last band joins the one before.
    last = band == band[-1]
    if band[-1] > 0 and np.count_nonzero(last) < MIN_BAND_BINS:
        band[last] = band[-1] - 1
    return band


def wheel_impedance(
    f_hz: np.ndarray, wheel: VirtualWheel | None = None, gravity_nm: float = 0.0
) -> np.ndarray:
    """I s² + b s + k (+ m·g·r, an unbalanced wheel's gravity torque at small angles)."""
    w = wheel or VirtualWheel()
    s = 2j * np.pi * np.asarray(f_hz, dtype=float)
    return w.inertia_kgm2 * s**2 + w.damping_nms_per_rad * s + w.stiffness_nm_per_rad + gravity_nm


def _lowpass(x: np.ndarray, fs: float, fc: float) -> np.ndarray:
    if len(x) < 30 or fc >= 0.45 * fs:
        return np.asarray(x, dtype=float).copy()
    sos = butter(2, fc / (fs / 2), output="sos")
    return sosfiltfilt(sos, np.asarray(x, dtype=float))


def analysis_bins(
    fs: float, sel: PeriodSelection, exc: Excitation
) -> tuple[np.ndarray, np.ndarray, float]:
    """The DFT bins of the analysed segment from the first to the top frequency (F_MAX_HZ, or
    1.25 × the highest excited one, below 0.4 fs), which of them are excited, and that top."""
    f_max = min(max(F_MAX_HZ, 1.25 * float(exc.frequencies_hz.max())), 0.4 * fs)
    bins = np.arange(1, int(math.floor(f_max * sel.n_samples / fs)) + 1)
    return bins, np.isin(bins, exc.bins * sel.n_periods), f_max


def prepare_trial(rec: TrialRecord, wheel: VirtualWheel | None = None) -> TrialData:
    """Spectra and signals of one trial; ``ValueError`` (naming the trial) if unusable."""
    wheel = wheel or VirtualWheel()
    where = rec.source or rec.label()
    fs = float(rec.fs_hz)
    T = record_period_s(rec)
    if fs > 0 and rec.n_samples < T * fs:
        raise ValueError(
            f"{where}: {rec.n_samples / fs:.1f} s of data, shorter than one perturbation "
            f"period ({T:g} s)"
        )
    sel = select_periods(rec)
    exc = find_excitation(rec, sel)
    P = sel.n_samples
    bins, excited, f_max = analysis_bins(fs, sel, exc)
    K = len(bins)
    if not excited.any():
        raise ValueError(f"{where}: no excited bin below {f_max:g} Hz")
    start, stop = sel.start, sel.stop
    n_sim = min(stop + 1, rec.n_samples)
    for name in ("perturbation_torque_Nm", "driver_torque_Nm", "wheel_angle_rad", "grip_force_N"):
        x = getattr(rec, name)[:n_sim]
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{where}: {name} has non-finite samples")
    th = np.asarray(rec.wheel_angle_rad, dtype=float)
    td = np.asarray(rec.driver_torque_Nm, dtype=float)
    tp = np.asarray(rec.perturbation_torque_Nm, dtype=float)
    grip_raw = np.asarray(rec.grip_force_N, dtype=float)[:n_sim]
    Y = measurement_spectra(th, td, start, stop, bins)
    seg_th, seg_td = th[start:stop], td[start:stop]
    spectra = trial_spectra(rec, selection=sel, excitation=exc)
    # The FRF fits need the subject's inertia, which needs all of the subject's trials:
    # :func:`_cell_fits` replaces this placeholder.
    arm0 = FALLBACK_ARM
    f = bins * fs / P
    return TrialData(
        label=rec.label(),
        subject=rec.subject,
        condition=rec.condition,
        repetition=int(rec.repetition),
        familiarization=bool(rec.familiarization),
        trial_index=rec.trial_index,
        fs_hz=fs,
        tp=tp[:n_sim].copy(),
        grip=_lowpass(grip_raw, fs, GRIP_LOWPASS_HZ),
        grip_raw=grip_raw,
        start=start,
        stop=stop,
        n_sim=n_sim,
        selection=sel,
        excitation=exc,
        bins=bins,
        excited=excited,
        band=make_bands(K),
        Y=Y,
        Tp=channel_spectra(tp, start, stop, bins)[1],
        Zw=wheel_impedance(f, wheel),
        theta=seg_th - seg_th.mean(),
        td=seg_td - seg_td.mean(),
        arm0=arm0,
        arm_cell=arm0,
        spectra=spectra,
        source=rec.source,
        wheel=wheel,
    )


@dataclass
class PreparedStudy:
    """What the diagnosis works on, and what it had to leave out."""

    trials: list[TrialData]  # measured repetitions
    familiarization: list[TrialData]  # used only for the trial-order (drift) axis
    skipped: list[tuple[str, str]]  # (label, reason)
    notes: list[str]
    limits: list[str]  # what the data do not allow (shown prominently)
    wheel_check: dict = field(default_factory=dict)  # the wheel fitted from the data (_check_rig)

    @property
    def subjects(self) -> list[str]:
        return sorted({t.subject for t in self.trials})

    @property
    def conditions(self) -> list[str]:
        from steerlab.analysis.study import _condition_key

        return sorted({t.condition for t in self.trials}, key=_condition_key)

    @property
    def has_held_out(self) -> bool:
        """At least one subject × condition with two measured repetitions."""
        reps: dict[tuple[str, str], set[int]] = {}
        for t in self.trials:
            reps.setdefault(t.cell, set()).add(t.repetition)
        return any(len(r) >= 2 for r in reps.values())


def _perturbation_present(rec: TrialRecord) -> bool:
    tp = np.asarray(rec.perturbation_torque_Nm, dtype=float)
    tp = tp[np.isfinite(tp)]
    return tp.size > 0 and float(np.std(tp)) > 1e-3


def recorded_rig_limits(directory: str | Path) -> tuple[dict[str, SafetyLimits], list[str]]:
    """Session file (resolved path) → the command limits its rig recorded
    (``attrs["rig"]["safety"]``, written by ``steerlab run`` and ``rig-check``), and a note per
    file whose record is unusable.

    A rig that clipped at 6 N·m, or slewed at 200 N·m/s, applied another torque than Steerlab's
    defaults would in simulation; imported and simulated studies record none and are simulated
    with the defaults (:func:`analysis.diagnosis.engine.choose_rig_limits` then asks the data
    whether the recording's rig clipped at all)."""
    known = {f.name for f in fields(SafetyLimits)}
    out: dict[str, SafetyLimits] = {}
    notes: list[str] = []

    def unusable(path: Path, why: str) -> None:
        notes.append(
            f"{path.name}: the rig's recorded limits are unusable ({why}); simulated with "
            "Steerlab's defaults"
        )

    for path in session_files(directory):
        try:
            rig = SessionFile(path).attrs.get("rig")
        except (OSError, DataFileError):
            continue  # load_study reports the file
        if rig is None:
            continue  # not recorded: an imported or simulated study
        if isinstance(rig, str):
            try:
                rig = json.loads(rig)
            except json.JSONDecodeError as e:
                unusable(path, f"attribute rig is not JSON: {e}")
                continue
        raw = rig.get("safety") if isinstance(rig, dict) else None
        if raw is None and isinstance(rig, dict):
            continue  # a rig record without limits
        if not isinstance(raw, dict):
            unusable(path, "rig.safety is not a table of limits")
            continue
        try:
            lim = SafetyLimits(**{k: v for k, v in raw.items() if k in known})
            bad = lim.problems()
        except TypeError as e:
            bad = [("", str(e))]
        if bad:
            field_, why = bad[0]
            unusable(path, f"rig.safety.{field_} {why}" if field_ else f"rig.safety: {why}")
            continue
        out[str(path.resolve())] = lim
    return out, notes


def prepare_study(
    records: Sequence[TrialRecord],
    wheel: DiagnosisWheel | None = None,
    inertia_kgm2: float | None = None,
    rig_limits: Mapping[str, SafetyLimits] | None = None,
    wheel_rendering: str = "sampled",
    rig_wheel: DiagnosisWheel | None = None,
) -> PreparedStudy:
    """Select and prepare the trials; raise :class:`DiagnosisError` when nothing is usable.
    ``wheel``: the wheel the data are checked against and simulated with (nominal by default;
    see :mod:`analysis.diagnosis.wheel`). ``inertia_kgm2``: hold every subject's arm inertia at
    this value instead of fitting it from the data (see :func:`_cell_fits`). ``rig_limits``:
    session file → its rig's command limits (:func:`recorded_rig_limits`); trials of other
    files are simulated with Steerlab's defaults. ``wheel_rendering``: how the simulated wheel's
    damping and spring act (``analysis.rig_from_data``); ``rig_wheel``: the wheel the data are
    checked against, where ``wheel`` took its inertia from the data."""
    rendered = wheel.rendered if wheel is not None else None
    if not records:
        raise DiagnosisError("no trials in the data")
    skipped: list[tuple[str, str]] = []
    notes: list[str] = []
    limits: list[str] = []
    if not any(_perturbation_present(r) for r in records):
        raise DiagnosisError(
            "no perturbation in the data (the perturbation torque is zero or constant in every "
            "trial): a simulation driven by the measured perturbation has nothing to reproduce. "
            "What can still be said without a perturbation: grip-force levels per condition, "
            "and the wheel angle's spread, neither of which tests the arm model."
        )
    chosen: dict[tuple[str, str, int, bool], TrialRecord] = {}
    for r in records:
        if r.status != STATUS_COMPLETE:
            skipped.append((r.label(), f"status {r.status}"))
            continue
        if not _perturbation_present(r):
            skipped.append((r.label(), "no perturbation in this trial"))
            continue
        key = (r.subject, r.condition, r.repetition, r.familiarization)
        old = chosen.get(key)
        if old is not None:
            later = (r.trial_index or 0) >= (old.trial_index or 0)
            drop = old if later else r
            skipped.append((drop.label(), "duplicate; the later attempt is used"))
            if not later:
                continue
        chosen[key] = r
    trials: list[TrialData] = []
    fam: list[TrialData] = []
    short: list[str] = []
    for r in chosen.values():
        try:
            t = prepare_trial(r, rendered)
            t.wheel_rendering = wheel_rendering
            if rig_limits:
                t.safety = rig_limits.get(str(Path(r.source_file).resolve()), t.safety)
        except ValueError as e:
            msg = str(e)
            skipped.append((r.label(), msg))
            if "shorter than one perturbation period" in msg or "no whole perturbation" in msg:
                short.append(r.label())
            continue
        (fam if t.familiarization else trials).append(t)
    if not trials:
        why = "; ".join(f"{lab}: {reason}" for lab, reason in skipped[:6])
        hint = ""
        if short:
            hint = (
                " Every trial is shorter than one perturbation period: the diagnosis compares "
                "whole periods (the design's excited frequencies are only exact over a whole "
                "period), so it needs at least one."
            )
        raise DiagnosisError(f"no measured trial can be diagnosed ({why}).{hint}")
    # The limits the simulated command sees (the loop's timeouts do not shape it).
    shaping = ("max_torque_nm", "max_slew_nm_per_s", "soft_angle_limit_deg", "fade_zone_deg",
               "brake_damping_nms_per_rad")  # fmt: skip
    own = sorted({tuple(getattr(t.safety, k) for k in shaping) for t in trials + fam})
    if own != [tuple(getattr(SafetyLimits(), k) for k in shaping)]:
        said = "; ".join(
            f"{v[0]:g} N·m, {v[1]:g} N·m/s, soft angle limit {v[2]:g}° (fade {v[3]:g}°)"
            for v in own
        )
        notes.append(f"simulated with the command limits the session files record ({said})")
    fs = {t.fs_hz for t in trials}
    if len(fs) > 1:
        notes.append(
            f"trials recorded at several rates ({sorted(fs)} Hz); each is simulated at its own"
        )
    trials.sort(key=lambda t: (t.subject, t.trial_index or 0, t.condition, t.repetition))
    _cell_fits(trials, fam, inertia_kgm2)
    if inertia_kgm2 is not None:
        notes.append(f"arm inertia held at {inertia_kgm2:g} kg·m² (not fitted from the data)")
    fam.sort(key=lambda t: (t.subject, t.trial_index or 0))
    # The data are checked against the rig's wheel as it was chosen, before the data's
    # inertia joined it: a wheel of another rig is refused, not fitted.
    check = _check_rig(trials, rig_wheel or wheel)
    prep = PreparedStudy(trials, fam, skipped, notes, limits, check)
    if not prep.has_held_out:
        limits.append(
            "only one measured repetition per subject × condition: no held-out check is "
            "possible, so causes rest on in-sample evidence (BIC) alone, with a stricter "
            "threshold; record two repetitions to validate them"
        )
    if len(prep.conditions) == 1:
        limits.append(
            f"a single condition ({prep.conditions[0]}): the diagnosis cannot compare operating "
            "points, so an amplitude-dependent stiffness is told from a stiffer arm only by "
            "its distortion, not by how the stiffness changes between conditions"
        )
    if any(t.trial_index is None for t in trials):
        limits.append("trial order unknown for some trials: the drift check leaves them out")
    return prep


def with_inertia(arm: ArmParams, trial: TrialData) -> ArmParams:
    """``arm`` with the trial's subject's inertia (from the data), where it has been fitted."""
    if math.isfinite(trial.I_i):
        return replace(arm, I_i=trial.I_i)
    return arm


def _cell_fits(
    trials: Sequence[TrialData],
    fam: Sequence[TrialData] = (),
    inertia_kgm2: float | None = None,
) -> None:
    """The FRF fits that start the baseline, with the report's default estimator.

    Per subject, one joint fit of all its subject × condition responses (all repetitions of a
    condition pooled) with one I_i shared by the conditions; then each trial alone (measured and
    familiarization) with that I_i held. A subject whose joint fit fails keeps each cell's own
    fit (I_i free), and failing that the fallback arm; the trial's I_i is then the cell's.
    With ``inertia_kgm2`` every subject's I_i is held at that value instead.
    """
    options = DIAGNOSIS_FIT
    if inertia_kgm2 is not None:
        options = replace(DIAGNOSIS_FIT, inertia="fixed", I_i=float(inertia_kgm2))
    by_subject: dict[str, dict[str, list[TrialData]]] = {}
    for t in trials:
        by_subject.setdefault(t.subject, {}).setdefault(t.condition, []).append(t)
    for subject, cells in by_subject.items():
        conds = list(cells)
        ests = [frequency_response([t.spectra for t in cells[c]]) for c in conds]
        try:
            joint = fit_arm_joint(ests, options, labels=conds)
            I_i, I_sem = float(joint.I_i), joint.I_i_sem
            cell_arm = {c: ArmParams(**f.params.as_dict()) for c, f in joint.by_label().items()}
        except (ValueError, np.linalg.LinAlgError):
            I_i, I_sem, cell_arm = float("nan"), None, {}
            for c, est in zip(conds, ests, strict=True):
                try:
                    cell_arm[c] = ArmParams(**fit_arm(est, options).params.as_dict())
                except (ValueError, np.linalg.LinAlgError):
                    continue
        if not (math.isfinite(I_i) and I_i > 0):
            vals = [a.I_i for a in cell_arm.values()]
            I_i = float(np.exp(np.mean(np.log(vals)))) if vals else FALLBACK_ARM.I_i
        held = replace(options, inertia="fixed", I_i=I_i)
        subject_trials = [t for c in conds for t in cells[c]]
        subject_trials += [t for t in fam if t.subject == subject]
        for t in subject_trials:
            t.I_i, t.I_i_sem = I_i, I_sem
            t.inertia_fixed = inertia_kgm2 is not None
            t.arm_cell = cell_arm.get(t.condition, replace(FALLBACK_ARM, I_i=I_i))
            try:
                fit = fit_arm(frequency_response(t.spectra), held)
                t.arm0 = ArmParams(**fit.params.as_dict())
            except (ValueError, np.linalg.LinAlgError):
                t.arm0 = t.arm_cell
    # A familiarization trial of a subject without measured trials: its own fit.
    for t in fam:
        if math.isfinite(t.I_i):
            continue
        try:
            t.arm0 = ArmParams(**fit_arm(frequency_response(t.spectra), options).params.as_dict())
            t.I_i = t.arm0.I_i
        except (ValueError, np.linalg.LinAlgError):
            t.I_i = FALLBACK_ARM.I_i
        t.arm_cell = t.arm0


def wheel_fit(
    trials: Sequence[TrialData],
    f_max_hz: float = RIG_CHECK_MAX_HZ,
    impedance: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[dict[str, float], float]:
    """The wheel's I, b, k fitted from Tp − Td = (I s² + b s + k) θ at the excited bins below
    ``f_max_hz``, and the relative misfit there of ``impedance`` (frequencies in Hz → Z; by
    default each trial's ``Zw``)."""
    rows, rhs, err, tot = [], [], 0.0, 0.0
    for t in trials:
        m = t.excited & (t.freqs_hz < f_max_hz)
        s = 2j * np.pi * t.freqs_hz[m]
        th = t.Y[0, m]
        lhs = t.Tp[m] - t.Y[1, m]
        w = 1.0 / np.maximum(np.abs(t.Tp[m]), 1e-9)  # each bin relative to its excitation
        A = np.stack([s**2 * th, s * th, th], axis=1) * w[:, None]
        rows.append(np.concatenate([A.real, A.imag]))
        b = lhs * w
        rhs.append(np.concatenate([b.real, b.imag]))
        zw = t.Zw[m] if impedance is None else impedance(t.freqs_hz[m])
        err += float(np.sum(np.abs((lhs - zw * th) * w) ** 2))
        tot += float(np.sum(np.abs(lhs * w) ** 2))
    A = np.concatenate(rows)
    b = np.concatenate(rhs)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    return {
        "I_kgm2": float(sol[0]),
        "b_Nms_per_rad": float(sol[1]),
        "k_Nm_per_rad": float(sol[2]),
    }, math.sqrt(err / tot) if tot > 0 else float("nan")


def _check_rig(trials: Sequence[TrialData], wheel: DiagnosisWheel | None = None) -> dict:
    """Refuse data whose wheel is not the rig's rendered wheel (``wheel``'s, nominal by
    default), or with another sign convention. Returns the check's numbers, for the report."""
    # Low-frequency admittance must be positive with Steerlab's sign convention.
    re = []
    for t in trials:
        m = t.excited & (t.freqs_hz < 0.5)
        if m.any():
            re.append(
                np.real(np.sum(np.conj(t.Tp[m]) * t.Y[0, m]) / np.sum(np.conj(t.Tp[m]) * t.Y[1, m]))
            )
    if re and np.median(re) < 0:
        raise DiagnosisError(
            "the admittance θ/Td is negative at low frequency: the driver-torque sign is "
            "opposite to Steerlab's convention (driver_torque_Nm is the torque the wheel exerts "
            "on the hands; docs/data-format.md). Flip it on import; nothing else is wrong."
        )
    rendered = wheel.rendered if wheel is not None else VirtualWheel()
    gravity = wheel.mechanisms.wheel_imbalance.torque_nm if wheel is not None else 0.0
    fitted, misfit = wheel_fit(trials, impedance=lambda f: wheel_impedance(f, rendered, gravity))
    _, misfit_nominal = wheel_fit(trials, impedance=wheel_impedance)
    if not misfit <= RIG_MISMATCH_LIMIT:
        w = rendered
        name = wheel.sentence() if wheel is not None else "nominal (Table 1)"
        hint = (
            ""
            if wheel is not None and wheel.measured
            else " If the rig was measured (steerlab rig-check), pass its rig.json with "
            "--rig-model."
        )
        raise DiagnosisError(
            "the data do not come from the rig the simulator models: at the excited "
            "frequencies Tp − Td differs from the wheel's rendered dynamics "
            f"({w.inertia_kgm2:.4g} kg·m², {w.damping_nms_per_rad:.4g} N·m·s/rad, "
            f"{w.stiffness_nm_per_rad + gravity:.4g} N·m/rad; wheel: {name}) times the angle by "
            f"{100 * misfit:.0f} % "
            f"(fitted from the data: I = {fitted['I_kgm2']:.3g} kg·m², "
            f"b = {fitted['b_Nms_per_rad']:.3g} N·m·s/rad, k = {fitted['k_Nm_per_rad']:.3g} "
            "N·m/rad); check the sign conventions of driver_torque_Nm and wheel_angle_rad "
            "(docs/data-format.md). What can still be said: the admittance θ/Td does not "
            "depend on the wheel, so `steerlab report` still estimates it and fits the arm "
            f"model.{hint}"
        )
    return {
        "method": (
            f"Tp − Td = (I s² + b s + k) θ at the excited bins below {RIG_CHECK_MAX_HZ:g} Hz "
            "(equation error, each bin relative to its perturbation); misfit: relative error "
            "of a wheel's linear impedance there (an imbalance counts as stiffness)"
        ),
        "fitted_from_data": fitted,
        "misfit_percent": 100 * misfit,
        "misfit_nominal_percent": 100 * misfit_nominal,
    }
