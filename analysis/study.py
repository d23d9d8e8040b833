"""A whole study: every trial → per subject × condition → per condition.

1. Trials that cannot be analysed are skipped and listed with the reason (never fatal):
   familiarization, aborted, incomplete, superseded, duplicates of a measured repetition, and
   trials whose own analysis raised a ``ValueError`` (too short, wrong rate, …).
2. Per trial (:func:`analyze_trial`, a top-level function so it can run in worker processes):
   period selection, Fourier coefficients, grip-force moments over the analysed samples. It
   runs on the given ``concurrent.futures.Executor``, on a ``ProcessPoolExecutor(jobs)`` when
   ``jobs > 1``, or in this process.
3. Per subject × condition, over the measured repetitions: FRF, arm fit, VAF (pooled over the
   repetitions' analysed periods), FIT%, grip-force mean and SD (pooled over all analysed
   samples of the repetitions, so slow drifts between repetitions count as variability).
   The arm fits are one joint fit per subject (one task per subject on the same executor, or
   on a ``ProcessPoolExecutor(jobs)``); the comparison weighting starts from the default's
   solution.
4. Per condition: group FRF (complex mean over subjects, 95 % intervals) and the arm fit to it,
   with the subjects' estimator (their compensated Ĥ averaged, the same weighting and sampling)
   and I_i held at the median of the subjects' I_i (:func:`group_inertia`); grip force over
   subjects, including the median of the subjects' means (the LPV model's scheduling variable).

Keys in :meth:`StudyAnalysis.to_dict` carry their units; NaN and infinities become ``null``.
"""

from __future__ import annotations

import concurrent.futures as cf
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from steerlab.analysis.armfit import (
    ArmFit,
    FitOptions,
    JointArmFit,
    check_fittable,
    fit_arm_joint,
    vaf_percent,
)
from steerlab.analysis.frf import (
    DEFAULT_NOISE_BINS_PER_SIDE,
    FrequencyResponse,
    GroupFrequencyResponse,
    TrialSpectra,
    frequency_response,
    group_frequency_response,
    trial_spectra,
)
from steerlab.analysis.periods import (
    DEFAULT_DETECT_BELOW_MAX_DB,
    DEFAULT_DETECT_FLOOR_DB,
    DEFAULT_MIN_RUN_IN_S,
)
from steerlab.protocols.records import (
    STATUS_ABORTED,
    STATUS_COMPLETE,
    STATUS_DAMAGED,
    STATUS_INCOMPLETE,
    STATUS_SUPERSEDED,
    TrialRecord,
)

PAPER_CONDITION_ORDER = ("RT", "BT18", "BT12", "BT8", "BT5", "PT")

# progress(done, total, label): called in the calling process after each trial's analysis.
ProgressCallback = Callable[[int, int, str], None]


@dataclass(frozen=True)
class AnalysisOptions:
    period_s: float | None = None  # only for records without a design (default 45 s)
    min_run_in_s: float = DEFAULT_MIN_RUN_IN_S
    noise_bins_per_side: int = DEFAULT_NOISE_BINS_PER_SIDE
    detect_floor_db: float = DEFAULT_DETECT_FLOOR_DB
    detect_below_max_db: float = DEFAULT_DETECT_BELOW_MAX_DB
    fit: FitOptions = field(default_factory=FitOptions)
    confidence: float = 0.95
    # Fit every cell a second time with the other weighting (paper ↔ inverse variance), for
    # the report's side-by-side comparison.
    compare_weightings: bool = True
    # Remove each period's non-periodic jump from θ and Td before the DFT (analysis.frf: the
    # remnant's drift otherwise leaks into every band as a one-directional, correlated error).
    remove_drift: bool = True

    @property
    def comparison_fit(self) -> FitOptions:
        other = "paper" if self.fit.weighting == "inverse_variance" else "inverse_variance"
        return replace(self.fit, weighting=other)

    def to_dict(self) -> dict:
        return {
            "period_s": self.period_s,
            "min_run_in_s": self.min_run_in_s,
            "noise_bins_per_side": self.noise_bins_per_side,
            "detect_floor_dB": self.detect_floor_db,
            "detect_below_max_dB": self.detect_below_max_db,
            "fit": self.fit.to_dict(),
            "confidence": self.confidence,
            "compare_weightings": self.compare_weightings,
            "remove_drift": self.remove_drift,
        }


class NoAnalysableTrialError(ValueError):
    """Not one trial of the study can be analysed (e.g. a session stopped before its first
    measured trial ended); the message counts the skipped trials by reason and names the files."""

    def __init__(self, records: Sequence[TrialRecord], skipped: Sequence[SkippedTrial]):
        reasons: dict[str, int] = {}
        for s in skipped:
            reasons[s.reason.split(":")[0]] = reasons.get(s.reason.split(":")[0], 0) + 1
        files = sorted({r.source.split(":/")[0] for r in records if r.source})
        super().__init__(
            f"{', '.join(files) or 'the study'}: no analysable trial among {len(records)} "
            f"(skipped: {', '.join(f'{n} {k}' for k, n in sorted(reasons.items()))})"
        )


@dataclass(frozen=True)
class SkippedTrial:
    label: str
    source: str
    reason: str

    def to_dict(self) -> dict:
        return {"label": self.label, "source": self.source, "reason": self.reason}


@dataclass(frozen=True)
class GripMoments:
    """Count, mean and sum of squared deviations of the finite grip samples; pools exactly."""

    n: int
    mean: float
    m2: float

    @staticmethod
    def of(x: np.ndarray) -> GripMoments:
        x = np.asarray(x, dtype=float)
        x = x[np.isfinite(x)]
        if x.size == 0:
            return GripMoments(0, float("nan"), float("nan"))
        m = float(x.mean())
        return GripMoments(int(x.size), m, float(np.sum((x - m) ** 2)))

    @staticmethod
    def pool(parts: Sequence[GripMoments]) -> GripMoments:
        parts = [p for p in parts if p.n > 0]
        if not parts:
            return GripMoments(0, float("nan"), float("nan"))
        n = sum(p.n for p in parts)
        mean = sum(p.n * p.mean for p in parts) / n
        m2 = sum(p.m2 + p.n * (p.mean - mean) ** 2 for p in parts)
        return GripMoments(n, mean, m2)

    @property
    def sd(self) -> float:
        return math.sqrt(self.m2 / (self.n - 1)) if self.n > 1 else float("nan")


@dataclass(frozen=True)
class TrialAnalysis:
    """What :func:`analyze_trial` sends back: small, picklable, no time series."""

    index: int  # position in the records list given to analyze_study
    spectra: TrialSpectra
    grip: GripMoments


def analyze_trial(index: int, record: TrialRecord, options: AnalysisOptions) -> TrialAnalysis:
    """Per-trial work: periods, Fourier coefficients, grip moments. Raises ``ValueError``."""
    spectra = trial_spectra(
        record,
        period_s=options.period_s,
        min_run_in_s=options.min_run_in_s,
        noise_bins_per_side=options.noise_bins_per_side,
        detect_floor_db=options.detect_floor_db,
        detect_below_max_db=options.detect_below_max_db,
        remove_drift=options.remove_drift,
    )
    grip = GripMoments.of(spectra.selection.segment(record.grip_force_N))
    return TrialAnalysis(index, spectra, grip)


@dataclass(frozen=True)
class SubjectConditionResult:
    subject: str
    condition: str
    repetitions: tuple[int, ...]
    trials: tuple[TrialSpectra, ...]
    frf: FrequencyResponse
    fit: ArmFit | None
    grip: GripMoments
    fit_error: str | None = None
    fit_compare: ArmFit | None = None  # the same cell with the other weighting

    @property
    def vaf_percent(self) -> float | None:
        return None if self.fit is None else self.fit.vaf_percent

    @property
    def fit_percent(self) -> float | None:
        return None if self.fit is None else self.fit.fit_percent

    @property
    def vaf_compare_percent(self) -> float | None:
        return None if self.fit_compare is None else self.fit_compare.vaf_percent

    @property
    def grip_mean_N(self) -> float:
        return self.grip.mean

    @property
    def grip_sd_N(self) -> float:
        return self.grip.sd

    def row(self) -> dict:
        """One flat row for tables and statistics."""
        row: dict[str, str | float | int | None] = {
            "subject": self.subject,
            "condition": self.condition,
        }
        if self.fit is not None:
            d = self.fit.to_dict()
            row.update(self.fit.params.to_dict())
            row.update({f"sem_{k}": v for k, v in d["sem"].items()})
            row["unidentified"] = ",".join(d["unidentified"])
        row.update(
            {
                "vaf_percent": self.vaf_percent,
                "fit_percent": self.fit_percent,
                "grip_mean_N": self.grip_mean_N,
                "grip_sd_N": self.grip_sd_N,
                "n_repetitions": len(self.repetitions),
            }
        )
        return row

    def to_dict(self) -> dict:
        return {
            "subject": self.subject,
            "condition": self.condition,
            "repetitions": list(self.repetitions),
            "trials": [
                {
                    "label": t.label,
                    "source": t.source,
                    "periods": t.selection.to_dict(),
                    "excited_bins_origin": t.excitation.origin,
                }
                for t in self.trials
            ],
            "frf": self.frf.to_dict(),
            "fit": None if self.fit is None else self.fit.to_dict(),
            "fit_error": self.fit_error,
            "fit_other_weighting": None if self.fit_compare is None else self.fit_compare.to_dict(),
            "vaf_percent": self.vaf_percent,
            "fit_percent": self.fit_percent,
            "grip_mean_N": self.grip_mean_N,
            "grip_sd_N": self.grip_sd_N,
            "grip_n_samples": self.grip.n,
        }


@dataclass(frozen=True)
class ConditionResult:
    condition: str
    subjects: tuple[str, ...]
    group_frf: GroupFrequencyResponse
    fit: ArmFit | None
    grip_subject_means_N: np.ndarray
    grip_subject_sds_N: np.ndarray
    fit_error: str | None = None
    fit_compare: ArmFit | None = None

    @property
    def grip_median_of_means_N(self) -> float:
        """The LPV scheduling variable μ: median over subjects of their mean grip force."""
        return float(np.nanmedian(self.grip_subject_means_N))

    def to_dict(self) -> dict:
        return {
            "condition": self.condition,
            "subjects": list(self.subjects),
            "n_subjects": len(self.subjects),
            "group_frf": self.group_frf.to_dict(),
            "fit": None if self.fit is None else self.fit.to_dict(),
            "fit_error": self.fit_error,
            "fit_other_weighting": None if self.fit_compare is None else self.fit_compare.to_dict(),
            "fit_percent": None if self.fit is None else self.fit.fit_percent,
            "grip_mean_of_subject_means_N": float(np.nanmean(self.grip_subject_means_N)),
            "grip_median_of_subject_means_N": self.grip_median_of_means_N,
            "grip_sd_between_subjects_N": (
                float(np.nanstd(self.grip_subject_means_N, ddof=1))
                if len(self.subjects) > 1
                else None
            ),
            "grip_mean_of_subject_sds_N": float(np.nanmean(self.grip_subject_sds_N)),
        }


def _json_clean(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _json_clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_clean(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


@dataclass(frozen=True)
class StudyAnalysis:
    subject_conditions: tuple[SubjectConditionResult, ...]
    conditions: tuple[ConditionResult, ...]
    skipped: tuple[SkippedTrial, ...]
    options: AnalysisOptions
    notes: tuple[str, ...] = ()
    # The inertia of each subject's joint fit; empty when I_i is held fixed or fitted per cell.
    # "group" only when no subject's I_i was determined and the group fits estimated their own.
    inertia: dict[str, JointArmFit] = field(default_factory=dict)
    inertia_compare: dict[str, JointArmFit] = field(default_factory=dict)

    def result(self, subject: str, condition: str) -> SubjectConditionResult:
        for r in self.subject_conditions:
            if r.subject == subject and r.condition == condition:
                return r
        raise KeyError(f"no result for subject {subject!r}, condition {condition!r}")

    def condition(self, condition: str) -> ConditionResult:
        for c in self.conditions:
            if c.condition == condition:
                return c
        raise KeyError(f"no result for condition {condition!r}")

    def operating_points(self) -> list[tuple[str, float, dict[str, float], tuple]]:
        """Per condition with a group fit: ``(condition, μ_N, parameters, (f_Hz, H, coherence))``
        with μ the median over subjects of the mean grip force: the tuples
        ``analysis.lpv.as_operating_points`` accepts."""
        return [
            (
                c.condition,
                c.grip_median_of_means_N,
                c.fit.params.as_dict(),
                (c.group_frf.frequencies_hz, c.group_frf.H, c.group_frf.coherence),
            )
            for c in self.conditions
            if c.fit is not None
        ]

    def table(self) -> list[dict]:
        """One flat row per subject × condition (parameters, SEMs, VAF, FIT%, grip)."""
        return [r.row() for r in self.subject_conditions]

    def to_dict(self) -> dict:
        return _json_clean(
            {
                "options": self.options.to_dict(),
                "skipped_trials": [s.to_dict() for s in self.skipped],
                "notes": list(self.notes),
                "subject_condition_table": self.table(),
                "subject_conditions": [r.to_dict() for r in self.subject_conditions],
                "conditions": [c.to_dict() for c in self.conditions],
                "inertia": {k: v.to_dict() for k, v in self.inertia.items()},
                "inertia_other_weighting": {
                    k: v.to_dict() for k, v in self.inertia_compare.items()
                },
            }
        )


def _skip_reason(rec: TrialRecord) -> str | None:
    if rec.familiarization:
        return "familiarization trial"
    if rec.status == STATUS_ABORTED:
        return "aborted" + (f": {rec.abort_reason}" if rec.abort_reason else "")
    if rec.status == STATUS_INCOMPLETE:
        return "incomplete (still running, or the recording stopped mid-trial)"
    if rec.status == STATUS_SUPERSEDED:
        return "superseded by a later attempt of the same trial"
    if rec.status == STATUS_DAMAGED:
        return rec.abort_reason or "damaged"
    if rec.status != STATUS_COMPLETE:
        return f"unknown status {rec.status!r}"
    if rec.driving:
        return "driving trial: see the driving section"
    if rec.time_varying:
        # Its task changed within the trial: no single operating point (analysis.tracking).
        return "time-varying trial (the task changed within it): see the tracking section"
    return None


def _condition_key(c: str) -> tuple[int, str]:
    order = PAPER_CONDITION_ORDER
    return (order.index(c), "") if c in order else (len(order), c)


def _run_trials(
    jobs_list: list[tuple[int, TrialRecord]],
    options: AnalysisOptions,
    executor: cf.Executor | None,
    jobs: int,
    progress: ProgressCallback | None,
) -> tuple[list[TrialAnalysis], list[tuple[int, str]]]:
    done: list[TrialAnalysis] = []
    failed: list[tuple[int, str]] = []
    total = len(jobs_list)

    def report(i: int, label: str) -> None:
        if progress is not None:
            progress(i, total, label)

    if executor is None and jobs <= 1:
        for k, (i, rec) in enumerate(jobs_list, 1):
            try:
                done.append(analyze_trial(i, rec, options))
            except ValueError as e:
                failed.append((i, str(e)))
            report(k, rec.label())
        return done, failed

    own = executor is None
    ex = executor if executor is not None else cf.ProcessPoolExecutor(max_workers=jobs)
    try:
        futures = {ex.submit(analyze_trial, i, rec, options): (i, rec) for i, rec in jobs_list}
        for k, fut in enumerate(cf.as_completed(futures), 1):
            i, rec = futures[fut]
            try:
                done.append(fut.result())
            except ValueError as e:
                failed.append((i, str(e)))
            report(k, rec.label())
    finally:
        if own:
            ex.shutdown(cancel_futures=True)
    done.sort(key=lambda t: t.index)  # completion order must not change the results
    failed.sort()
    return done, failed


def analyze_study(
    records: Sequence[TrialRecord],
    *,
    executor: cf.Executor | None = None,
    jobs: int = 1,
    progress: ProgressCallback | None = None,
    options: AnalysisOptions | None = None,
) -> StudyAnalysis:
    """Analyse every usable trial of a study (see the module docstring)."""
    opt = options or AnalysisOptions()
    skipped: list[SkippedTrial] = []
    notes: list[str] = []

    # Keep one record per (subject, condition, repetition): the latest attempt.
    chosen: dict[tuple[str, str, int], int] = {}
    for i, rec in enumerate(records):
        reason = _skip_reason(rec)
        if reason is not None:
            skipped.append(SkippedTrial(rec.label(), rec.source, reason))
            continue
        key = (rec.subject, rec.condition, rec.repetition)
        if key in chosen:
            j = chosen[key]
            old = records[j]
            # The later attempt wins: by trial_index when known, else by position in the list.
            later = (rec.trial_index is None or old.trial_index is None) or (
                rec.trial_index >= old.trial_index
            )
            keep, drop = (i, j) if later else (j, i)
            chosen[key] = keep
            skipped.append(
                SkippedTrial(
                    records[drop].label(),
                    records[drop].source,
                    f"duplicate of {records[keep].source or records[keep].label()} "
                    "(the later attempt is used)",
                )
            )
        else:
            chosen[key] = i
    todo = [(i, records[i]) for i in sorted(chosen.values())]

    done, failed = _run_trials(todo, opt, executor, jobs, progress)
    for i, msg in failed:
        skipped.append(
            SkippedTrial(records[i].label(), records[i].source, f"not analysable: {msg}")
        )
    if not done and not any(r.time_varying for r in records):
        raise NoAnalysableTrialError(records, skipped)

    cells: dict[tuple[str, str], list[TrialAnalysis]] = {}
    for t in done:
        rec = records[t.index]
        cells.setdefault((rec.subject, rec.condition), []).append(t)

    cell_frfs: list[tuple[str, str, list[TrialAnalysis], FrequencyResponse]] = []
    for (subj, cond), items in sorted(
        cells.items(), key=lambda kv: (kv[0][0], _condition_key(kv[0][1]))
    ):
        items.sort(key=lambda t: records[t.index].repetition)
        try:
            frf = frequency_response([t.spectra for t in items])
        except ValueError as e:
            notes.append(f"{subj} {cond}: repetitions not combined, left out: {e}")
            continue
        cell_frfs.append((subj, cond, items, frf))

    # Arm fits: one joint fit per subject over its conditions (one shared I_i), or per cell.
    by_subject: dict[str, list[tuple[str, FrequencyResponse]]] = {}
    for subj, cond, _, frf in cell_frfs:
        by_subject.setdefault(subj, []).append((cond, frf))
    own_pool = executor is None and jobs > 1 and len(by_subject) > 1
    fit_ex = cf.ProcessPoolExecutor(max_workers=jobs) if own_pool else executor
    try:
        fits, inertia = _fit_sets(by_subject, opt.fit, notes, executor=fit_ex)
        fits_cmp: dict[tuple[str, str], ArmFit | str] = {}
        inertia_cmp: dict[str, JointArmFit] = {}
        if opt.compare_weightings:
            fits_cmp, inertia_cmp = _fit_sets(
                by_subject, opt.comparison_fit, [], starts=inertia, executor=fit_ex
            )
    finally:
        if own_pool and fit_ex is not None:
            fit_ex.shutdown(cancel_futures=True)

    per_cell: list[SubjectConditionResult] = []
    for subj, cond, items, frf in cell_frfs:
        label = f"{subj} {cond}"
        fit, fit_error = None, None
        got = fits[(subj, cond)]
        cmp = fits_cmp.get((subj, cond))
        segments = [
            (
                t.spectra.selection.segment(records[t.index].driver_torque_Nm),
                t.spectra.selection.segment(records[t.index].wheel_angle_rad),
            )
            for t in items
        ]
        rates = [records[t.index].fs_hz for t in items]
        if isinstance(got, str):
            fit_error = got
        else:
            fit = got.with_vaf(vaf_percent(got.params, segments, rates))
        if isinstance(cmp, ArmFit):
            cmp = cmp.with_vaf(vaf_percent(cmp.params, segments, rates))
        per_cell.append(
            SubjectConditionResult(
                subject=subj,
                condition=cond,
                repetitions=tuple(records[t.index].repetition for t in items),
                trials=tuple(t.spectra for t in items),
                frf=frf,
                fit=fit,
                grip=GripMoments.pool([t.grip for t in items]),
                fit_error=fit_error,
                fit_compare=cmp if isinstance(cmp, ArmFit) else None,
            )
        )
        if fit_error is not None:
            notes.append(f"{label}: no arm fit: {fit_error}")

    groups: dict[str, GroupFrequencyResponse] = {}
    for cond in sorted({r.condition for r in per_cell}, key=_condition_key):
        rs = [r for r in per_cell if r.condition == cond]
        try:
            groups[cond] = group_frequency_response(
                [r.frf for r in rs], subjects=[r.subject for r in rs], confidence=opt.confidence
            )
        except ValueError as e:
            notes.append(f"{cond}: no group result: {e}")
    gfits: dict[tuple[str, str], ArmFit | str] = {}
    gfits_cmp: dict[tuple[str, str], ArmFit | str] = {}
    held = {c: group_inertia(per_cell, c, opt.fit) for c in groups}
    own = [(c, g) for c, g in groups.items() if held[c] is None]
    if own:
        if opt.fit.inertia != "fixed":
            notes.append(
                f"{', '.join(c for c, _ in own)}: no subject's I_i is determined; the group "
                "fit estimates its own from the mean FRF"
            )
        got_sets, ginertia = _fit_sets({"group": own}, opt.fit, notes)
        gfits.update(got_sets)
        inertia.update(ginertia)
        if opt.compare_weightings:
            got_sets, ginertia_cmp = _fit_sets(
                {"group": own}, opt.comparison_fit, [], starts=ginertia
            )
            gfits_cmp.update(got_sets)
            inertia_cmp.update(ginertia_cmp)
    for c, g in groups.items():
        I_c = held[c]
        if I_c is None:
            continue
        fopt = replace(opt.fit, inertia="fixed", I_i=I_c)
        gfits.update(_fit_sets({"group": [(c, g)]}, fopt, notes)[0])
        if opt.compare_weightings:
            cmp_opt = replace(opt.comparison_fit, inertia="fixed", I_i=I_c)
            gfits_cmp.update(_fit_sets({"group": [(c, g)]}, cmp_opt, [])[0])
    per_condition: list[ConditionResult] = []
    for cond, group in groups.items():
        rs = [r for r in per_cell if r.condition == cond]
        got = gfits[("group", cond)]
        cmp = gfits_cmp.get(("group", cond))
        if isinstance(got, str):
            notes.append(f"{cond}: no group arm fit: {got}")
        per_condition.append(
            ConditionResult(
                condition=cond,
                subjects=tuple(r.subject for r in rs),
                group_frf=group,
                fit=None if isinstance(got, str) else got,
                grip_subject_means_N=np.array([r.grip_mean_N for r in rs]),
                grip_subject_sds_N=np.array([r.grip_sd_N for r in rs]),
                fit_error=got if isinstance(got, str) else None,
                fit_compare=cmp if isinstance(cmp, ArmFit) else None,
            )
        )

    return StudyAnalysis(
        subject_conditions=tuple(per_cell),
        conditions=tuple(per_condition),
        skipped=tuple(skipped),
        options=opt,
        notes=tuple(notes),
        inertia=inertia,
        inertia_compare=inertia_cmp,
    )


def group_inertia(
    cells: Sequence[SubjectConditionResult], condition: str, fopt: FitOptions
) -> float | None:
    """The I_i a condition's group fit holds: the median of the subjects' I_i in that condition
    (their joint fits' shared value by default), leaving out those the data do not determine.
    None with ``inertia="fixed"`` (every fit holds ``fopt.I_i`` already) or when no subject's
    I_i is determined.

    The mean of the subjects' responses is not an arm's response (averaging 1/(b_c s + k_c)
    over subjects is not one spring-damper), and a group fit that estimates I_i from it puts
    part of that mismatch into I_i: on a simulated study whose subjects all have I_i = 0.1
    kg·m², fitted to the mean of their noise-free responses, 0.097 (docs/method-estimator.md).
    The arm's inertia is a property of the person, which every subject's joint fit determines
    to about 1 %; their median is the group's.
    """
    if fopt.inertia == "fixed":
        return None
    vals = [
        r.fit.params.I_i
        for r in cells
        if r.condition == condition and r.fit is not None and "I_i" not in r.fit.unidentified()
    ]
    return float(np.median(vals)) if vals else None


def _fit_set(
    name: str, items: list[tuple[str, Any]], fopt: FitOptions, start: JointArmFit | None
) -> tuple[dict[tuple[str, str], ArmFit | str], JointArmFit | None, list[str]]:
    """One set's fits (see :func:`_fit_sets`); a module-level function so that it runs on any
    executor (process pools and Dask pickle it)."""
    out: dict[tuple[str, str], ArmFit | str] = {}
    notes: list[str] = []
    good: list[tuple[str, Any]] = []
    for cond, est in items:
        try:  # a response the fit cannot use at all (too few bands, no noise variance)
            check_fittable(est, fopt)
        except ValueError as e:
            out[(name, cond)] = str(e)
            continue
        good.append((cond, est))
    if not good:
        return out, None, notes
    if start is not None and start.labels != tuple(c for c, _ in good):
        start = None
    try:
        joint = fit_arm_joint([e for _, e in good], fopt, labels=[c for c, _ in good], start=start)
    except (ValueError, np.linalg.LinAlgError) as e:
        for cond, _ in good:
            out[(name, cond)] = f"joint fit of {name} failed: {e}"
        notes.append(f"{name}: joint arm fit failed: {e}")
        return out, None, notes
    for cond, fit in joint.by_label().items():
        out[(name, cond)] = fit
    keep = joint.mode == "subject" or (fopt.inertia == "subject" and len(good) == 1)
    return out, joint if keep else None, notes


def _fit_sets(
    sets: dict[str, list[tuple[str, Any]]],
    fopt: FitOptions,
    notes: list[str],
    starts: dict[str, JointArmFit] | None = None,
    executor: cf.Executor | None = None,
) -> tuple[dict[tuple[str, str], ArmFit | str], dict[str, JointArmFit]]:
    """Fit each set of responses (a subject's conditions, or the group's) with one I_i per
    set (``fopt.inertia`` "subject"), or each response alone. Returns ``{(set, condition):
    ArmFit or the error message}`` and the joint fits by set. A response that cannot be fitted
    is left out of its set's joint fit, with a note, so it cannot take the others with it.
    ``starts``: joint fits of the same sets (the default's, for the comparison weighting) to
    start from, by set name (see :func:`fit_arm_joint`). ``executor``: where the sets are
    fitted (one task per set); the results do not depend on it."""
    starts = starts or {}
    args = [(name, items, fopt, starts.get(name)) for name, items in sets.items()]
    if executor is None or len(args) < 2:
        results = [_fit_set(*a) for a in args]
    else:
        futures = [executor.submit(_fit_set, *a) for a in args]
        results = [f.result() for f in futures]
    out: dict[tuple[str, str], ArmFit | str] = {}
    joints: dict[str, JointArmFit] = {}
    for (name, *_), (o, joint, n) in zip(args, results, strict=True):
        out.update(o)
        notes.extend(n)
        if joint is not None:
            joints[name] = joint
    return out, joints
