"""The whole analysis of a study in one call: per trial → subjects → conditions → LPV → statistics.

:func:`analyse_directory` reads every session file of a directory and runs :func:`run_analysis`;
:func:`run_analysis` takes records and returns one :class:`StudyResults` whose
:meth:`~StudyResults.to_dict` is the content of a report's ``results.json`` (``docs/results.md``
documents every key). Nothing here draws or writes files; :mod:`analysis.report` does.

Stages
    1. :func:`analysis.study.analyze_study`: per-trial work on any executor, per subject ×
       condition fits, per condition group FRF and fit. Unusable trials are listed, never fatal.
    2. LPV (:func:`analysis.lpv.analyse_lpv`) on the conditions' group fits, scheduled on μ, the
       median over subjects of the mean total grip force; RT is left out as in the paper. Both
       interpolations (de Caigny, physical parameters), Table 2 and leave-one-out. The paper
       quotes leave-one-out as a time-domain VAF; here every subject's own measured driver
       torque drives the predicted model and is compared with that subject's measured angle
       (periodic steady state over the analysed periods, like the per-subject VAF), and the
       median over subjects is reported *(ours: the paper does not say whose data)*.
    3. Statistics over the conditions for every per-subject quantity (grip mean and SD, b_i,
       k_i, b_c, k_c, VAF): RM-ANOVA with sphericity and GG correction, Bonferroni pairwise
       tests, and Page's trend test for an ordered effect (conditions ordered from the widest
       boundary, RT, to the narrowest, PT). I_i (one per subject, shared by its conditions;
       the group fits hold the subjects' median) is not tested.
    4. The paper's qualitative findings, each restated as a test on these data (:class:`Check`).
"""

from __future__ import annotations

import concurrent.futures as cf
import math
import platform
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats as sps

from steerlab.analysis.armfit import ArmFit
from steerlab.analysis.lpv import (
    DEFAULT_EXCLUSIONS,
    METHODS,
    SCHEDULING_VARIABLE,
    LeaveOneOutReport,
    LPVAnalysis,
    LPVModel,
    OperatingPoint,
    analyse_lpv,
    as_operating_points,
    build_lpv,
)
from steerlab.analysis.rig_from_data import align_to_command
from steerlab.analysis.stats import (
    PairwiseResult,
    RMAnovaResult,
    pairwise_tests,
    prepare_wide,
    rm_anova,
)
from steerlab.analysis.strict_json import json_clean
from steerlab.analysis.study import (
    PAPER_CONDITION_ORDER,
    AnalysisOptions,
    ProgressCallback,
    StudyAnalysis,
    analyze_study,
)
from steerlab.protocols.datafile import DataFileError, SessionFile, session_files, software_version
from steerlab.protocols.records import TrialRecord

ALPHA = 0.05
LPV_ORDER = 2  # the paper's polynomial order; higher orders overfit five points

# Per-subject quantities tested over the conditions: key → (column of StudyAnalysis.table(),
# label, unit). I_i is not here: every fit holds it fixed (FitOptions.I_i).
STAT_QUANTITIES: Mapping[str, tuple[str, str, str]] = {
    "grip_mean": ("grip_mean_N", "mean total grip force", "N"),
    "grip_sd": ("grip_sd_N", "grip-force SD", "N"),
    "b_i": ("b_i_Nms_per_rad", "intrinsic damping b_i", "N·m·s/rad"),
    "k_i": ("k_i_Nm_per_rad", "intrinsic stiffness k_i", "N·m/rad"),
    "b_c": ("b_c_Nms_per_rad", "contact damping b_c", "N·m·s/rad"),
    "k_c": ("k_c_Nm_per_rad", "contact stiffness k_c", "N·m/rad"),
    "vaf": ("vaf_percent", "VAF", "%"),
}
PARAMETER_UNITS: Mapping[str, str] = {
    "I_i": "kg·m²",
    "b_i": "N·m·s/rad",
    "k_i": "N·m/rad",
    "b_c": "N·m·s/rad",
    "k_c": "N·m/rad",
}
# The paper's Table 2 (FIT%), for side-by-side display; None where the paper has no value.
PAPER_TABLE2: Mapping[str, Mapping[str, float | None]] = {
    "PT": {"lti": 94.1, "lpv": 91.5},
    "BT5": {"lti": 96.7, "lpv": 94.9},
    "BT8": {"lti": 99.0, "lpv": 97.7},
    "BT12": {"lti": 98.0, "lpv": 95.2},
    "BT18": {"lti": 96.6, "lpv": 95.1},
    "RT": {"lti": 91.5, "lpv": None},
}


# ------------------------------------------------------------------------------------------
# Reading a directory


@dataclass(frozen=True)
class InputFile:
    """One session file as the provenance lists it."""

    path: str
    subject: str
    size_bytes: int
    modified_utc: str
    created_utc: str | None
    written_by: str | None  # software_version attribute of the file
    protocol_name: str | None
    simulated: bool
    n_trials: int
    wheel: dict[str, float] | None = None  # [wheel] of the protocol the file was recorded with
    # Simulated files: condition → the simulated subject's arm parameters (its base behaviour
    # per condition; each trial varies around it by PopulationSpread.trial_cv).
    simulated_truth: dict[str, dict[str, float]] | None = None
    # Which wheel the data came from: a simulation's "wheel_used", or a rig session's last rig
    # check ("rig_check"); None when the file says neither (analysis.rigcheck.wheel_used_of).
    wheel_used: dict | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "subject": self.subject,
            "size_bytes": self.size_bytes,
            "modified_utc": self.modified_utc,
            "created_utc": self.created_utc,
            "written_by_software_version": self.written_by,
            "protocol_name": self.protocol_name,
            "simulated": self.simulated,
            "n_trials": self.n_trials,
            "wheel": self.wheel,
            "wheel_used": self.wheel_used,
        }


def load_directory(
    session_dir: str | Path, progress: ProgressCallback | None = None
) -> tuple[list[TrialRecord], list[InputFile]]:
    """Every trial of every ``*.h5`` in ``session_dir``, and what each file is.

    Raises :class:`DataFileError` naming the file for an unreadable one, and for a directory
    without session files. The channels the analysis never reads (``record.extra``: motor
    torques, per-hand grip, velocity) are dropped as each file is read: they are half of the
    samples (about 0.66 GB as float64 for an 18-subject study at 1 kHz).
    """
    files = session_files(session_dir)
    if not files:
        raise DataFileError(f"{session_dir}: no session files (*.h5)")
    records: list[TrialRecord] = []
    inputs: list[InputFile] = []
    for i, p in enumerate(files, 1):
        sf = SessionFile(p)
        recs = sf.records(extra_channels=())
        records.extend(recs)
        st = p.stat()
        a = sf.attrs
        inputs.append(
            InputFile(
                path=str(p.resolve()),
                subject=sf.subject,
                size_bytes=int(st.st_size),
                modified_utc=datetime.fromtimestamp(st.st_mtime, UTC).isoformat(timespec="seconds"),
                created_utc=_str_or_none(a.get("created_utc")),
                written_by=_str_or_none(a.get("software_version")),
                protocol_name=_str_or_none(a.get("protocol_name")),
                simulated=bool(a.get("simulated", False)),
                n_trials=len(recs),
                wheel=_wheel_of(a.get("protocol_toml")),
                simulated_truth=_truth_of(a.get("simulated_subject")),
                wheel_used=wheel_used_of(a),
            )
        )
        if progress is not None:
            progress(i, len(files), f"read {p.name}")
    return records, inputs


def wheel_used_of(attrs) -> dict | None:
    """A session file's record of its wheel: "wheel_used" (simulate) or "rig_check" (run)."""
    import json

    for key in ("wheel_used", "rig_check"):
        v = attrs.get(key)
        if v is None:
            continue
        try:
            d = json.loads(v) if isinstance(v, str | bytes) else None
        except ValueError:
            d = None
        if isinstance(d, dict):
            if key == "rig_check":
                d = {"source": "rig check", "detail": d.get("path"), "passed": d.get("passed")}
            return d
    return None


def wheel_used_sentence(input_files: list[dict]) -> str:
    """One line for a report's header: which wheel the data were recorded or simulated with."""
    seen = []
    for f in input_files:
        w = f.get("wheel_used")
        if w is None:
            label = "not recorded (nominal assumed)"
        elif w.get("source") == "measured":
            label = f"measured by a rig check ({w.get('detail')})"
        elif w.get("source") == "rig check":
            ok = {True: "passed", False: "failed"}.get(w.get("passed"), "verdict unknown")
            label = f"the rig as checked ({w.get('detail')}, {ok})"
        else:
            label = f"nominal ({w.get('detail') or 'protocol'})"
        if label not in seen:
            seen.append(label)
    return "Wheel: " + "; ".join(seen) + "." if seen else ""


def _wheel_of(protocol_toml: Any) -> dict[str, float] | None:
    """The rendered wheel dynamics from a file's protocol, if it can be read (else None: the
    report then simply does not show them)."""
    import tomllib

    if not isinstance(protocol_toml, str) or not protocol_toml:
        return None
    try:
        wheel = tomllib.loads(protocol_toml).get("wheel")
    except tomllib.TOMLDecodeError:
        return None
    if not isinstance(wheel, dict):
        return None
    return {str(k): float(v) for k, v in wheel.items() if isinstance(v, int | float)}


def _truth_of(simulated_subject: Any) -> dict[str, dict[str, float]] | None:
    """The simulated subject's arm per condition, if the attribute can be read."""
    import json

    if isinstance(simulated_subject, bytes):
        simulated_subject = simulated_subject.decode("utf-8", "replace")
    if isinstance(simulated_subject, str):
        try:
            simulated_subject = json.loads(simulated_subject)
        except json.JSONDecodeError:
            return None
    if not isinstance(simulated_subject, dict):
        return None
    out = {}
    for cond, b in (simulated_subject.get("behaviour") or {}).items():
        arm = b.get("arm") if isinstance(b, dict) else None
        if isinstance(arm, dict):
            out[str(cond)] = {k: float(v) for k, v in arm.items() if isinstance(v, int | float)}
    return out or None


def _str_or_none(v: Any) -> str | None:
    return None if v is None else str(v)


def provenance(
    session_dir: str | Path | None, inputs: Sequence[InputFile], options: AnalysisOptions
) -> dict[str, Any]:
    """What produced a result: software versions, inputs, settings (``results.json``)."""
    import h5py
    import matplotlib
    import scipy

    return {
        "generated_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "software": {
            "steerlab": software_version(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "scipy": scipy.__version__,
            "pandas": pd.__version__,
            "h5py": h5py.__version__,
            "matplotlib": matplotlib.__version__,
        },
        "session_dir": None if session_dir is None else str(Path(session_dir).resolve()),
        "input_files": [f.to_dict() for f in inputs],
        "analysis_options": options.to_dict(),
        "lpv_options": {
            "order": LPV_ORDER,
            "methods": list(METHODS),
            "excluded": dict(DEFAULT_EXCLUSIONS),
            "scheduling_variable": SCHEDULING_VARIABLE,
        },
        "statistics_options": {"alpha": ALPHA, "pairwise_correction": "bonferroni"},
    }


# ------------------------------------------------------------------------------------------
# Statistics per quantity


@dataclass(frozen=True)
class TrendTest:
    """Page's L test for an ordered alternative in a repeated-measures design.

    ``direction`` "rising": predicted ranks 1..k along ``conditions``; "falling": reversed.
    ``mean_spearman_rho``: mean over subjects of the rank correlation between the condition's
    position and the value (descriptive; +1 = every subject strictly rising).
    """

    conditions: tuple[str, ...]
    direction: str
    n_subjects: int
    L: float
    p: float
    method: str
    mean_spearman_rho: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "test": "Page's L trend test (one-sided, ordered alternative)",
            "conditions_in_predicted_order": list(self.conditions),
            "direction": self.direction,
            "n_subjects": self.n_subjects,
            "L": self.L,
            "p": self.p,
            "method": self.method,
            "mean_spearman_rho": self.mean_spearman_rho,
        }


def trend_test(
    table: pd.DataFrame, column: str, conditions: Sequence[str], direction: str = "rising"
) -> TrendTest:
    """Page's test on complete subjects; raises ``ValueError`` with fewer than 3 conditions."""
    if len(conditions) < 3:
        raise ValueError(f"a trend test needs at least 3 conditions, got {len(conditions)}")
    wide = prepare_wide(
        table, dv=column, within="condition", subject="subject", conditions=list(conditions)
    )
    x = wide.values if direction == "rising" else wide.values[:, ::-1]
    res = sps.page_trend_test(x)
    pos = np.arange(x.shape[1])
    rhos = [sps.spearmanr(pos, row).statistic for row in x if np.ptp(row) > 0]
    sign = 1.0 if direction == "rising" else -1.0
    return TrendTest(
        conditions=tuple(conditions),
        direction=direction,
        n_subjects=wide.n_subjects,
        L=float(res.statistic),
        p=float(res.pvalue),
        method=str(res.method),
        mean_spearman_rho=sign * float(np.mean(rhos)) if rhos else float("nan"),
    )


@dataclass(frozen=True)
class QuantityStatistics:
    key: str
    column: str
    label: str
    unit: str
    anova: RMAnovaResult | None
    pairwise: PairwiseResult | None
    trend: TrendTest | None
    errors: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {
            "column": self.column,
            "label": self.label,
            "unit": self.unit,
            "rm_anova": None if self.anova is None else self.anova.to_dict(),
            "pairwise": None if self.pairwise is None else self.pairwise.to_dict(),
            "trend": None if self.trend is None else self.trend.to_dict(),
            "errors": list(self.errors),
        }


def quantity_statistics(
    table: pd.DataFrame, conditions: Sequence[str], alpha: float = ALPHA
) -> dict[str, QuantityStatistics]:
    """RM-ANOVA, Bonferroni pairwise tests and Page's trend test for every quantity.

    A quantity that cannot be tested (too few subjects with every condition, no fits) gets
    ``None`` results and the reason in ``errors``: a report must still be written.
    """
    out = {}
    for key, (col, label, unit) in STAT_QUANTITIES.items():
        errors = []
        anova = pw = trend = None
        if col not in table.columns:
            errors.append(f"no values of {col} (no successful fits?)")
        else:
            conds = list(conditions)
            try:
                anova = rm_anova(
                    table, dv=col, within="condition", subject="subject", conditions=conds,
                    alpha=alpha,
                )  # fmt: skip
                pw = pairwise_tests(
                    table, dv=col, within="condition", subject="subject", conditions=conds,
                    alpha=alpha,
                )  # fmt: skip
            except ValueError as e:
                errors.append(f"RM-ANOVA/pairwise: {e}")
            try:
                trend = trend_test(table, col, conditions)
            except ValueError as e:
                errors.append(f"trend test: {e}")
        out[key] = QuantityStatistics(key, col, label, unit, anova, pw, trend, tuple(errors))
    return out


# ------------------------------------------------------------------------------------------
# Leave-one-out in the time domain, per subject


@dataclass(frozen=True)
class LeaveOneOutVAF:
    """Time-domain VAF of one left-out operating point for every subject (see module doc)."""

    method: str
    condition: str
    vaf_percent: dict[str, float | None]  # subject → VAF of the model rebuilt without the point
    in_sample_vaf_percent: dict[str, float | None]  # same, with the point in the model

    @staticmethod
    def _median(d: Mapping[str, float | None]) -> float | None:
        v = [x for x in d.values() if x is not None and math.isfinite(x)]
        return float(np.median(v)) if v else None

    @property
    def median_vaf_percent(self) -> float | None:
        return self._median(self.vaf_percent)

    @property
    def median_in_sample_vaf_percent(self) -> float | None:
        return self._median(self.in_sample_vaf_percent)

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "left_out": self.condition,
            "median_vaf_percent": self.median_vaf_percent,
            "median_in_sample_vaf_percent": self.median_in_sample_vaf_percent,
            "vaf_percent_per_subject": dict(self.vaf_percent),
            "in_sample_vaf_percent_per_subject": dict(self.in_sample_vaf_percent),
        }


@dataclass(frozen=True)
class _SegmentSpectrum:
    """One analysed segment's spectra (DC left out) with its Parseval weights."""

    f_hz: np.ndarray
    td: np.ndarray
    theta: np.ndarray
    weight: np.ndarray  # 2 for the one-sided bins, 1 for Nyquist: Σ w|X|² ∝ Σ x²


def _cell_spectra(
    study: StudyAnalysis, records: Sequence[TrialRecord]
) -> dict[tuple[str, str], list[_SegmentSpectrum]]:
    by_source = {r.source: r for r in records if r.source}
    out: dict[tuple[str, str], list[_SegmentSpectrum]] = {}
    for cell in study.subject_conditions:
        segs = []
        for t in cell.trials:
            rec = by_source.get(t.source)
            if rec is None:
                continue
            td = t.selection.segment(rec.driver_torque_Nm)
            th = t.selection.segment(rec.wheel_angle_rad)
            n = len(td)
            f = np.fft.rfftfreq(n, 1.0 / rec.fs_hz)[1:]
            w = np.full(f.shape, 2.0)
            if n % 2 == 0:
                w[-1] = 1.0
            segs.append(_SegmentSpectrum(f, np.fft.rfft(td)[1:], np.fft.rfft(th)[1:], w))
        if segs:
            out[(cell.subject, cell.condition)] = segs
    return out


def _vaf(segs: Sequence[_SegmentSpectrum], response: Callable[[np.ndarray], np.ndarray]) -> float:
    """VAF of the model's periodic steady state, as :func:`analysis.armfit.vaf_percent`, by
    Parseval: the analysed segments are whole perturbation periods, so no start-up transient
    and no initial state enter (the same VAF as the per-subject fits report)."""
    err = tot = 0.0
    for s in segs:
        err += float(np.sum(s.weight * np.abs(s.theta - response(s.f_hz) * s.td) ** 2))
        tot += float(np.sum(s.weight * np.abs(s.theta) ** 2))
    return 100.0 * (1.0 - err / tot) if tot > 0 else float("nan")


def leave_one_out_models(
    lpv: LPVAnalysis, points: Sequence[OperatingPoint], *, order: int = LPV_ORDER
) -> list[tuple[OperatingPoint, str, LPVModel]]:
    """``(left-out point, method, model rebuilt without it)`` for every intermediate point,
    rebuilt exactly as :func:`analysis.lpv.leave_one_out` rebuilds them (same points, order and
    de Caigny structure), for plots and the time-domain verification."""
    loo = lpv.leave_one_out
    if loo is None:
        return []
    included = sorted((p for p in points if p.condition not in loo.excluded), key=lambda p: p.mu_N)
    zeros = loo.structure or "auto"
    out = []
    for k, p in enumerate(included):
        if p.condition in loo.not_left_out:
            continue
        train = included[:k] + included[k + 1 :]
        for m in loo.methods:
            out.append((p, m, build_lpv(train, m, order=order, zeros=zeros, out_of_range="raise")))
    return out


def leave_one_out_vaf(
    lpv: LPVAnalysis,
    points: Sequence[OperatingPoint],
    study: StudyAnalysis,
    records: Sequence[TrialRecord],
    *,
    order: int = LPV_ORDER,
) -> list[LeaveOneOutVAF]:
    """Time-domain verification of the leave-one-out models, per subject.

    The group LPV model rebuilt without an intermediate operating point is evaluated at that
    point's μ and driven by each subject's measured driver torque in the left-out condition;
    its angle is compared with the subject's measured angle. ``in_sample`` uses the model built
    on all included points instead.
    """
    spectra = _cell_spectra(study, records)
    subjects = sorted({s for s, _ in spectra})
    out = []
    for p, m, fold in leave_one_out_models(lpv, points, order=order):
        full = lpv.models[m]
        v: dict[str, float | None] = {}
        v_in: dict[str, float | None] = {}
        for s in subjects:
            segs = spectra.get((s, p.condition))
            if segs is None:
                continue
            v[s] = _vaf(segs, partial(fold.frequency_response, p.mu_N))
            v_in[s] = _vaf(segs, partial(full.frequency_response, p.mu_N))
        out.append(LeaveOneOutVAF(m, p.condition, v, v_in))
    return out


# ------------------------------------------------------------------------------------------
# The paper's findings as checks


@dataclass(frozen=True)
class Check:
    """One of the paper's qualitative findings, tested on these data.

    ``passed``: True when the data agree, False when they differ, None when it could not be
    computed (``note`` says why).
    """

    id: str
    paper: str  # the finding, as the paper states it
    test: str  # how it is decided here
    passed: bool | None
    values: dict[str, Any] = field(default_factory=dict)
    note: str = ""

    @property
    def status(self) -> str:
        return {True: "pass", False: "differs", None: "not computed"}[self.passed]

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "paper": self.paper,
            "test": self.test,
            "status": self.status,
            "passed": self.passed,
            "values": self.values,
            "note": self.note,
        }


def _not_computed(id: str, paper: str, test: str, why: str) -> Check:
    return Check(id, paper, test, None, {}, why)


def _significant(a: RMAnovaResult, alpha: float) -> bool:
    return a.p_gg < alpha


def compute_checks(
    stats: Mapping[str, QuantityStatistics],
    study: StudyAnalysis,
    lpv: LPVAnalysis | None,
    loo_vaf: Sequence[LeaveOneOutVAF],
    conditions: Sequence[str],
    alpha: float = ALPHA,
) -> list[Check]:
    checks: list[Check] = []

    def rises(key: str, id: str, paper: str) -> None:
        q = stats.get(key)
        test = (
            f"Page's trend test over {' < '.join(conditions)} (widest to narrowest boundary), "
            f"one-sided p < {alpha}"
        )
        if q is None or q.trend is None:
            checks.append(_not_computed(id, paper, test, "; ".join(q.errors if q else [])))
            return
        t = q.trend
        checks.append(
            Check(
                id,
                paper,
                test,
                t.p < alpha,
                {
                    "L": t.L,
                    "p": t.p,
                    "mean_spearman_rho": t.mean_spearman_rho,
                    "n_subjects": t.n_subjects,
                    "condition_means": _means(q),
                },
            )
        )

    def changes(key: str, id: str, paper: str) -> None:
        q = stats.get(key)
        test = f"RM-ANOVA over the conditions, Greenhouse–Geisser corrected p < {alpha}"
        if q is None or q.anova is None:
            checks.append(_not_computed(id, paper, test, "; ".join(q.errors if q else [])))
            return
        a = q.anova
        checks.append(
            Check(
                id,
                paper,
                test,
                _significant(a, alpha),
                {
                    "F": a.F,
                    "df1": a.df1,
                    "df2": a.df2,
                    "p_gg": a.p_gg,
                    "eps_gg": a.eps_gg,
                    "partial_eta_squared": a.partial_eta_squared,
                },
            )
        )

    both = ("RT", "BT18")
    have_both = all(c in conditions for c in both)

    rises("grip_mean", "grip_rises", "Grip force rises as the boundary narrows.")
    q = stats.get("grip_mean")
    paper = (
        "Grip-force differences are significant (p < 0.01) between all conditions except RT vs "
        "BT18."
    )
    test = "every Bonferroni-corrected pairwise p < 0.01, except RT–BT18"
    if q is None or q.pairwise is None:
        checks.append(_not_computed("grip_pairs_differ", paper, test, "no pairwise tests"))
    else:
        others = [c for c in q.pairwise.comparisons if {c.a, c.b} != set(both)]
        not_sig = [f"{c.a}–{c.b}" for c in others if not c.p_corrected < 0.01]
        checks.append(
            Check(
                "grip_pairs_differ",
                paper,
                test,
                not not_sig,
                {"pairs_not_significant": not_sig, "n_pairs_tested": len(others)},
            )
        )
    paper = "Grip force does not differ between RT and BT18."
    test = f"Bonferroni-corrected paired t-test RT vs BT18: p ≥ {alpha}"
    if q is None or q.pairwise is None or not have_both:
        checks.append(_not_computed("grip_rt_bt18_same", paper, test, "RT or BT18 missing"))
    else:
        c = q.pairwise.get(*both)
        checks.append(
            Check(
                "grip_rt_bt18_same",
                paper,
                test,
                c.p_corrected >= alpha,
                {
                    "mean_difference_N": c.mean_difference,
                    "t": c.t,
                    "df": c.df,
                    "p_bonferroni": c.p_corrected,
                },
                "no significant difference is not proof of equality: see the mean difference",
            )
        )
    rises("grip_sd", "grip_sd_rises", "Grip-force SD rises as the boundary narrows.")
    checks.append(_admittance_falls(study, conditions, alpha))
    for key in ("k_i", "b_c", "k_c"):
        changes(key, f"{key}_changes", f"{key} changes significantly with the condition.")
    q = stats.get("k_i")
    paper = "Intrinsic stiffness k_i differs between every pair of conditions."
    test = f"every Bonferroni-corrected pairwise p < {alpha}"
    if q is None or q.pairwise is None:
        checks.append(_not_computed("k_i_all_pairs", paper, test, "no pairwise tests"))
    else:
        not_sig = [f"{c.a}–{c.b}" for c in q.pairwise.comparisons if not c.p_corrected < alpha]
        checks.append(
            Check(
                "k_i_all_pairs",
                paper,
                test,
                not not_sig,
                {"pairs_not_significant": not_sig, "n_pairs_tested": q.pairwise.n_comparisons},
            )
        )
    rises("b_c", "b_c_rises", "Contact damping b_c rises for narrower boundaries.")
    rises("k_c", "k_c_rises", "Contact stiffness k_c rises for narrower boundaries.")
    q = stats.get("b_i")
    paper = "Intrinsic damping b_i shows no significant relation with the condition."
    test = f"RM-ANOVA, Greenhouse–Geisser corrected p ≥ {alpha}"
    if q is None or q.anova is None:
        checks.append(_not_computed("b_i_no_effect", paper, test, "no RM-ANOVA"))
    else:
        a = q.anova
        checks.append(
            Check(
                "b_i_no_effect", paper, test, not _significant(a, alpha), {"F": a.F, "p_gg": a.p_gg}
            )
        )
    checks.append(_damping_sems_larger(study))
    checks.append(_vaf_lowest_in_rt(stats.get("vaf"), conditions, alpha))
    checks.extend(_lpv_checks(lpv, loo_vaf))
    return _explain_pairs(checks)


def _explain_pairs(checks: list[Check]) -> list[Check]:
    """A "changes" check that differs next to a "rises" check that passes (or the reverse)
    for the same quantity looks contradictory; say why both can hold."""
    by_id = {c.id: c for c in checks}
    out = []
    for c in checks:
        for q in ("k_i", "b_c", "k_c"):
            ch, ri = by_id.get(f"{q}_changes"), by_id.get(f"{q}_rises")
            if ch is None or ri is None or ch.passed is None or ri.passed is None:
                continue
            if ch.passed == ri.passed or c.id not in (ch.id, ri.id):
                continue
            if ri.passed:
                why = (
                    f"Not a contradiction: Page's trend test (the {q}_rises row) asks only "
                    "whether each subject's values rise in the predicted order, using ranks "
                    "within subjects, and is far more powerful for an ordered effect than the "
                    "omnibus RM-ANOVA, which weighs the size of the differences against the "
                    "scatter between subjects. A consistent but small rise passes the first "
                    "and not the second."
                )
            else:
                why = (
                    f"Not a contradiction: the RM-ANOVA (the {q}_changes row) detects any "
                    "difference between the conditions; Page's trend test (the "
                    f"{q}_rises row) asks for a rise in the predicted order, which these data "
                    "do not show although the conditions differ."
                )
            note = f"{c.note} {why}".strip()
            c = Check(c.id, c.paper, c.test, c.passed, c.values, note)
        out.append(c)
    return out


def _means(q: QuantityStatistics) -> dict[str, float] | None:
    if q.anova is None:
        return None
    return {
        str(c): float(m) for c, m in zip(q.anova.conditions, q.anova.condition_means, strict=True)
    }


def low_frequency_magnitude(frf_f: np.ndarray, H: np.ndarray, n_exclude_low: int) -> float:
    """Mean |Ĥ| over the full-power bands (≤ 0.7 Hz) that the fits use: the "admittance level"."""
    f = np.asarray(frf_f)
    order = np.argsort(f)[n_exclude_low:]
    sel = order[f[order] <= 0.7]
    return float(np.mean(np.abs(np.asarray(H)[sel]))) if sel.size else float("nan")


def _admittance_falls(study: StudyAnalysis, conditions: Sequence[str], alpha: float) -> Check:
    paper = "Narrower boundaries give lower admittance."
    test = (
        "Page's trend test (falling) on each subject's mean |Ĥ| over the fitted bands ≤ 0.7 Hz, "
        f"one-sided p < {alpha}"
    )
    n_low = study.options.fit.n_exclude_low
    rows = [
        {
            "subject": r.subject,
            "condition": r.condition,
            "low_f_admittance": low_frequency_magnitude(r.frf.frequencies_hz, r.frf.H, n_low),
        }
        for r in study.subject_conditions
    ]
    try:
        t = trend_test(pd.DataFrame(rows), "low_f_admittance", conditions, "falling")
    except (ValueError, KeyError) as e:
        return _not_computed("admittance_falls", paper, test, str(e))
    group = {
        c.condition: low_frequency_magnitude(c.group_frf.frequencies_hz, c.group_frf.H, n_low)
        for c in study.conditions
    }
    return Check(
        "admittance_falls",
        paper,
        test,
        t.p < alpha,
        {
            "L": t.L,
            "p": t.p,
            "mean_spearman_rho": t.mean_spearman_rho,
            "group_low_f_admittance_rad_per_Nm": group,
        },
    )


def _damping_sems_larger(study: StudyAnalysis) -> Check:
    paper = "Damping has larger SEMs than stiffness."
    test = (
        "median over subjects × conditions of SEM/estimate: b_i > k_i and b_c > k_c "
        "(relative, since damping and stiffness have different units)"
    )
    rel: dict[str, list[float]] = {n: [] for n in ("b_i", "k_i", "b_c", "k_c")}
    for r in study.subject_conditions:
        if r.fit is None:
            continue
        for n in rel:
            v, s = getattr(r.fit.params, n), r.fit.sems.get(n, float("nan"))
            if v > 0 and math.isfinite(s):
                rel[n].append(s / v)
    if not all(rel.values()):
        return _not_computed("damping_sems_larger", paper, test, "no fitted SEMs")
    med = {n: float(np.median(v)) for n, v in rel.items()}
    return Check(
        "damping_sems_larger",
        paper,
        test,
        med["b_i"] > med["k_i"] and med["b_c"] > med["k_c"],
        {"median_relative_sem": med},
    )


def _vaf_lowest_in_rt(
    q: QuantityStatistics | None, conditions: Sequence[str], alpha: float
) -> Check:
    paper = "VAF is lower in RT."
    test = (
        "RT has the lowest mean VAF and is lower than every other condition "
        f"(Bonferroni p < {alpha})"
    )
    if q is None or q.anova is None or q.pairwise is None or "RT" not in conditions:
        return _not_computed("vaf_lowest_in_rt", paper, test, "no VAF statistics or no RT")
    means = _means(q) or {}
    lowest = min(means, key=means.__getitem__) if means else None
    others = [q.pairwise.get("RT", c) for c in conditions if c != "RT"]
    not_sig = [c.b for c in others if not (c.p_corrected < alpha and c.mean_difference < 0)]
    return Check(
        "vaf_lowest_in_rt",
        paper,
        test,
        lowest == "RT" and not not_sig,
        {"condition_means_percent": means, "not_significantly_lower_than": not_sig},
    )


def _lpv_checks(lpv: LPVAnalysis | None, loo_vaf: Sequence[LeaveOneOutVAF]) -> list[Check]:
    out = []
    paper = "The local LTI models fit well: FIT% 91.5–99.0 at the operating points."
    test = "LTI FIT% > 90 at every operating point (Table 2)"
    if lpv is None:
        out.append(_not_computed("lti_fit_above_90", paper, test, "no LPV analysis"))
    else:
        lti = {r.condition: r.lti_fit_percent for r in lpv.table.rows}
        ok = all(v is not None and v > 90.0 for v in lti.values())
        out.append(Check("lti_fit_above_90", paper, test, ok, {"lti_fit_percent": lti}))
    paper = "The LPV model fits nearly as well: FIT% 91.5–97.7 at the included operating points."
    test = "LPV FIT% > 90 at every included operating point, both interpolation methods"
    if lpv is None:
        out.append(_not_computed("lpv_fit_above_90", paper, test, "no LPV analysis"))
    else:
        vals = {r.condition: dict(r.lpv_fit_percent) for r in lpv.table.rows if r.included}
        ok = all(v is not None and v > 90.0 for d in vals.values() for v in d.values())
        out.append(Check("lpv_fit_above_90", paper, test, ok, {"lpv_fit_percent": vals}))
    med = {(v.method, v.condition): v.median_vaf_percent for v in loo_vaf}
    paper = "Leave-one-out: VAF > 80 % when BT12 or BT8 is left out."
    test = (
        "median over subjects of the time-domain VAF > 80 % with BT12, BT8 left out, both methods"
    )
    wanted = [(m, c) for m in METHODS for c in ("BT12", "BT8")]
    got = {k: v for k in wanted if (v := med.get(k)) is not None}
    if len(got) < len(wanted):
        out.append(_not_computed("loo_bt12_bt8", paper, test, "BT12 or BT8 not left out"))
    else:
        out.append(
            Check(
                "loo_bt12_bt8",
                paper,
                test,
                all(v > 80.0 for v in got.values()),
                {f"{m}/{c}": v for (m, c), v in got.items()},
            )
        )
    paper = (
        "Leave-one-out: the prediction fails (VAF 0 %) when BT5, the highest intermediate grip "
        "force, is left out."
    )
    test = "median VAF with BT5 left out (de Caigny, the paper's method) < 80 %"
    bt5 = med.get(("de_caigny", "BT5"))
    if bt5 is None:
        out.append(_not_computed("loo_bt5_fails", paper, test, "BT5 not left out"))
    else:
        out.append(
            Check(
                "loo_bt5_fails",
                paper,
                test,
                bt5 < 80.0,
                {f"{m}/BT5": med.get((m, "BT5")) for m in METHODS},
                "where the arm parameters vary smoothly with grip force (as in Steerlab's "
                "simulated drivers) an interpolation is expected to predict BT5; 'differs' "
                "is then no error",
            )
        )
    return out


# ------------------------------------------------------------------------------------------
# Everything


def parameters_at_bound(fit: ArmFit) -> list[str]:
    """Free parameters that ended within 1 % of the fit's search box (analysis.armfit.BOUNDS):
    the data did not determine them, whatever their SEM says."""
    return fit.at_bound()


def _parameter_dict(fit: ArmFit, truth: Mapping[str, float] | None = None) -> dict[str, Any]:
    bound = fit.at_bound()
    unid = fit.unidentified()
    out = {}
    for n, v in fit.params.as_dict().items():
        d = {
            "value": v,
            "sem": fit.sems.get(n),
            "unit": PARAMETER_UNITS[n],
            "fixed": n not in fit.free,
            "at_bound": n in bound,
            "unidentified": n in unid,
        }
        if truth is not None and n in truth:
            d["simulated_truth"] = float(truth[n])
        out[n] = d
    return out


# The rule for estimates the data do not determine (ArmFit.unidentified: at a search bound, or
# SEM ≥ value): they are flagged where they appear and left out of the statistics, so one
# wild value cannot carry a condition's mean (RM-ANOVA needs complete subjects, so that
# subject drops out of that parameter's tests).
UNIDENTIFIED_RULE = (
    "estimates at a search bound or with SEM ≥ value are flagged and left out of the "
    "statistics (the subject drops out of that parameter's repeated-measures tests)"
)
WEIGHTING_DISAGREEMENT_SEMS = 2.0  # |default − other| > this × the larger SEM: "disagree"


def weightings_disagree(a: float, b: float, sem_a: float | None, sem_b: float | None) -> bool:
    """Whether two estimates of one parameter (default and other weighting) differ by more than
    :data:`WEIGHTING_DISAGREEMENT_SEMS` × the larger of their SEMs (no finite SEM: no verdict)."""
    sems = [float("nan") if x is None else float(x) for x in (sem_a, sem_b)]
    if not any(math.isfinite(x) for x in sems):
        return False
    return abs(a - b) > WEIGHTING_DISAGREEMENT_SEMS * float(np.nanmax(sems))


INERTIA_POORLY_DETERMINED = 0.3  # relative SEM of a subject's I_i above which we say so


def statistics_table(study: StudyAnalysis) -> tuple[pd.DataFrame, list[str]]:
    """The subject × condition table the statistics use, unidentified estimates blanked out
    (``UNIDENTIFIED_RULE``), and what was left out, as "S03 BT5: k_c"."""
    rows = study.table()
    left_out = []
    for r, cell in zip(rows, study.subject_conditions, strict=True):
        if cell.fit is None:
            continue
        bad = cell.fit.unidentified()
        for n in bad:
            col = STAT_QUANTITIES.get(n, (None,))[0]
            if col is not None and col in r:
                r[col] = float("nan")
        if bad:
            left_out.append(f"{cell.subject} {cell.condition}: {', '.join(bad)}")
    return pd.DataFrame(rows), left_out


@dataclass(frozen=True)
class ReaderWarning:
    """One item of the report's "Read this first" box: ``text`` in words; ``section`` the
    report section that holds the detail ("" for none)."""

    text: str
    section: str = ""


@dataclass
class StudyResults:
    """Everything a report shows; :meth:`to_dict` is ``results.json`` (docs/results.md)."""

    study: StudyAnalysis
    conditions: tuple[str, ...]
    subjects: tuple[str, ...]
    points: list[OperatingPoint]
    lpv: LPVAnalysis | None
    lpv_error: str | None
    loo_vaf: list[LeaveOneOutVAF]
    statistics: dict[str, QuantityStatistics]
    checks: list[Check]
    provenance: dict[str, Any]
    timings_s: dict[str, float] = field(default_factory=dict)
    left_out_of_statistics: list[str] = field(default_factory=list)
    # Simulated studies: subject → condition → true arm parameters (from the session files).
    simulated_truth: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)

    @property
    def simulated(self) -> bool:
        files = self.provenance.get("input_files") or []
        return bool(files) and all(f.get("simulated") for f in files)

    def truth(self, subject: str, condition: str) -> dict[str, float] | None:
        return self.simulated_truth.get(subject, {}).get(condition)

    def inertia_dict(self) -> dict[str, Any]:
        """What the data say about I_i: per subject (joint fit) and for the group fits."""
        opt = self.study.options.fit
        d: dict[str, Any] = {"mode": opt.inertia, "held_value_kgm2": None}
        if opt.inertia == "fixed":
            d["held_value_kgm2"] = opt.I_i
        per: dict[str, dict[str, Any]] = {}
        for name, j in self.study.inertia.items():
            sens = []
            for lab, fit in j.by_label().items():
                row: dict[str, Any] = {"condition": lab}
                row.update(
                    {
                        f"{n}_percent_per_10_percent_I_i": (
                            100.0 * (0.1 * j.I_i * v) / getattr(fit.params, n)
                        )
                        for n, v in fit.inertia_sensitivity.items()
                    }
                )
                sens.append(row)
            rel = None if j.I_i_sem is None or j.I_i <= 0 else j.I_i_sem / j.I_i
            per[name] = {
                "fit": name,
                "I_i_kgm2": j.I_i,
                "I_i_sem_kgm2": j.I_i_sem,
                "relative_sem": rel,
                "poorly_determined": rel is None
                or not math.isfinite(rel)
                or rel > INERTIA_POORLY_DETERMINED,
                "conditions": list(j.labels),
                "sensitivity": sens,
                "profile_I_kgm2": list(j.profile_I),
                "profile_cost": list(j.profile_cost),
            }
        d["fits"] = list(per.values())
        subj = [v["I_i_kgm2"] for k, v in per.items() if k != "group"]
        d["median_over_subjects_kgm2"] = float(np.median(subj)) if subj else None
        return d

    def weighting_comparison(self) -> dict[str, Any]:
        """Default and other weighting side by side, per subject × condition and group."""
        main = self.study.options.fit.weighting
        other = self.study.options.comparison_fit.weighting
        rows = []
        items = [
            (r.subject, r.condition, r.fit, r.fit_compare) for r in self.study.subject_conditions
        ]
        items += [("group", c.condition, c.fit, c.fit_compare) for c in self.study.conditions]
        for subj, cond, a, b in items:
            if a is None or b is None:
                continue
            row: dict[str, Any] = {
                "subject": subj,
                "condition": cond,
                f"fit_percent_{main}": a.fit_percent,
                f"fit_percent_{other}": b.fit_percent,
                "parameters": {},
                "disagree": [],
            }
            for n in a.free:
                va, vb = getattr(a.params, n), getattr(b.params, n)
                sa, sb = a.sems.get(n, float("nan")), b.sems.get(n, float("nan"))
                row["parameters"][n] = {main: va, f"{main}_sem": sa, other: vb, f"{other}_sem": sb}
                if weightings_disagree(va, vb, sa, sb):
                    row["disagree"].append(n)
            rows.append(row)
        per_subject = [r for r in rows if r["subject"] != "group"]
        changed = Counter(n for r in per_subject for n in r["disagree"])
        return {
            "default": main,
            "other": other,
            "rule": f"disagree: |difference| > {WEIGHTING_DISAGREEMENT_SEMS:g} × the larger SEM",
            "cells": rows,
            "n_subject_fits": len(per_subject),
            "n_subject_fits_that_change": sum(1 for r in per_subject if r["disagree"]),
            "changed_parameters": dict(changed.most_common()),
        }

    def reader_warnings(self) -> list[ReaderWarning]:
        """What a reader must know before trusting the numbers, each in a sentence or two.

        Only what changes how the numbers may be read: simulated data, a part not built,
        checks not computed, data left out, estimates the data do not determine. Subject fits
        that change with the other weighting are not here: the two weightings are different
        estimators, the paper's one less efficient, so on most studies some fits differ by
        more than their SEMs and that says nothing against the default fit
        (``weighting_comparison`` and the report's two-weightings section say so).

        Long lists (which subject fits, which estimates) stay in the sections named by
        ``section``: a reader acts on a count and a place to look, not on forty names.
        """
        out: list[ReaderWarning] = []
        if self.simulated:
            out.append(
                ReaderWarning(
                    "This study is SIMULATED (Steerlab's simulated rig), not measured data."
                )
            )
        if self.lpv is None:
            pts = ", ".join(p.condition for p in self.points) or "none"
            out.append(
                ReaderWarning(
                    "The LPV model could not be built, so there is no Table 2, no "
                    "leave-one-out verification and no LPV check. Why: "
                    f"{self.lpv_error or 'no operating points'}. Operating points in this "
                    f"study (one per analysed condition): {pts}.",
                    "table2",
                )
            )
        elif self.lpv.leave_one_out is None:
            out.append(
                ReaderWarning(
                    "The leave-one-out verification of the LPV model was not computed: "
                    f"{self.lpv.leave_one_out_skipped}.",
                    "loo",
                )
            )
        errors = {e for q in self.statistics.values() if q.anova is None for e in q.errors}
        if errors and all(q.anova is None for q in self.statistics.values()):
            out.append(
                ReaderWarning(
                    "No statistics across the conditions could be run: "
                    f"{'; '.join(sorted(errors))}.",
                    "anova",
                )
            )
        n_na = sum(c.passed is None for c in self.checks)
        if n_na:
            out.append(
                ReaderWarning(
                    f"{n_na} of the paper's {len(self.checks)} findings could not be checked on "
                    "these data (each row says why).",
                    "checks",
                )
            )
        if self.study.notes:
            out.append(
                ReaderWarning(
                    f"{len(self.study.notes)} subject × condition cell(s) or condition(s) were "
                    "left out of the analysis.",
                    "notes",
                )
            )
        groups_bad = [
            f"{c.condition}: {', '.join(c.fit.unidentified())}"
            for c in self.study.conditions
            if c.fit is not None and c.fit.unidentified()
        ]
        if groups_bad:
            out.append(
                ReaderWarning(
                    "Group fits the data do not determine: " + "; ".join(groups_bad) + ".",
                    "conditions",
                )
            )
        if self.left_out_of_statistics:
            out.append(
                ReaderWarning(
                    f"{len(self.left_out_of_statistics)} subject estimate(s) the data do not "
                    "determine (at a search bound, or SEM ≥ value) are left out of the "
                    "statistics and the boxes.",
                    "notes",
                )
            )
        inert = self.inertia_dict()
        poor = [v["fit"] for v in inert["fits"] if v["poorly_determined"]]
        if poor:
            n_subj = sum(1 for v in inert["fits"] if v["fit"] != "group")
            n_poor = sum(1 for f in poor if f != "group")
            who = f"{n_poor} of {n_subj} subjects" + (
                " and the group fits" if "group" in poor else ""
            )
            out.append(
                ReaderWarning(
                    f"I_i is poorly determined (SEM > {INERTIA_POORLY_DETERMINED:.0%} of the "
                    f"value) for {who}; the inertia section shows how much the other "
                    "parameters depend on it.",
                    "inertia",
                )
            )
        return out

    def warnings(self) -> list[str]:
        """What a reader must know before trusting the numbers (shown at the top)."""
        return [w.text for w in self.reader_warnings()]

    @property
    def leave_one_out(self) -> LeaveOneOutReport | None:
        return None if self.lpv is None else self.lpv.leave_one_out

    def estimates_at_bound(self) -> list[str]:
        """Every subject-level estimate stuck at the search box, as "S03 BT5: k_c"."""
        out = []
        for r in self.study.subject_conditions:
            if r.fit is not None and (b := parameters_at_bound(r.fit)):
                out.append(f"{r.subject} {r.condition}: {', '.join(b)}")
        return out

    def subject_condition_dicts(self) -> list[dict[str, Any]]:
        out = []
        for r in self.study.subject_conditions:
            truth = self.truth(r.subject, r.condition)
            params = {} if r.fit is None else _parameter_dict(r.fit, truth)
            out.append(
                {
                    "subject": r.subject,
                    "condition": r.condition,
                    "repetitions": list(r.repetitions),
                    "trials": [t.source or t.label for t in r.trials],
                    "parameters": params,
                    "sem_method": None if r.fit is None else r.fit.sem_method,
                    "fit_success": None if r.fit is None else r.fit.success,
                    "fit_error": r.fit_error,
                    "vaf_percent": r.vaf_percent,
                    "fit_percent": r.fit_percent,
                    "grip_mean_N": r.grip_mean_N,
                    "grip_sd_N": r.grip_sd_N,
                    "grip_n_samples": r.grip.n,
                    "frf": r.frf.to_dict(),
                }
            )
        return out

    def condition_dicts(self) -> list[dict[str, Any]]:
        out = []
        for c in self.study.conditions:
            d = c.to_dict()
            fit = d.pop("fit")
            params = None if c.fit is None else _parameter_dict(c.fit)
            d["group_fit"] = None if fit is None else {"parameters": params, **fit}
            d["grip_subject_means_N"] = dict(
                zip(c.subjects, c.grip_subject_means_N.tolist(), strict=True)
            )
            d["grip_subject_sds_N"] = dict(
                zip(c.subjects, c.grip_subject_sds_N.tolist(), strict=True)
            )
            out.append(d)
        return out

    def lpv_dict(self) -> dict[str, Any]:
        pts = []
        excluded = dict(DEFAULT_EXCLUSIONS)
        for p in self.points:
            pts.append(
                {
                    "condition": p.condition,
                    "mu_N": p.mu_N,
                    "included": p.condition not in excluded,
                    "exclusion_reason": excluded.get(p.condition),
                    "parameters": dict(p.parameters),
                }
            )
        d: dict[str, Any] = {
            "scheduling_variable": SCHEDULING_VARIABLE,
            "order": LPV_ORDER,
            "operating_points": pts,
            "error": self.lpv_error,
        }
        if self.lpv is None:
            d.update(models=None, table2=None, leave_one_out=None)
            return d
        table = self.lpv.table.to_dict()
        for row in table["rows"]:
            row["paper"] = dict(PAPER_TABLE2.get(row["condition"], {"lti": None, "lpv": None}))
        d["models"] = {m: model.to_dict() for m, model in self.lpv.models.items()}
        d["table2"] = table
        loo = None if self.lpv.leave_one_out is None else self.lpv.leave_one_out.to_dict()
        if loo is not None:
            loo["time_domain_vaf"] = [v.to_dict() for v in self.loo_vaf]
        d["leave_one_out"] = loo
        d["leave_one_out_skipped"] = self.lpv.leave_one_out_skipped
        return d

    def _inertia_not_tested(self) -> str:
        opt = self.study.options.fit
        if opt.inertia == "fixed":
            return f"held fixed at {opt.I_i} kg·m² in every fit; not estimated, so not tested"
        if opt.inertia == "subject":
            return (
                "one value per subject, shared by all of that subject's conditions (joint fit), "
                "so it cannot differ between conditions and is not tested"
            )
        return "fitted per cell; not tested (the paper holds it constant)"

    def to_dict(self) -> dict[str, Any]:
        return json_clean(
            {
                "format": "steerlab-report-results",
                "format_version": 1,
                "provenance": self.provenance,
                "conditions": list(self.conditions),
                "subjects": list(self.subjects),
                "n_trials_analysed": sum(len(r.trials) for r in self.study.subject_conditions),
                "subject_conditions": self.subject_condition_dicts(),
                "conditions_group": self.condition_dicts(),
                "lpv": self.lpv_dict(),
                "warnings": self.warnings(),
                "simulated": self.simulated,
                "inertia": self.inertia_dict(),
                "weighting_comparison": (
                    self.weighting_comparison() if self.study.options.compare_weightings else None
                ),
                "statistics": {
                    "alpha": ALPHA,
                    "conditions": list(self.conditions),
                    "not_tested": {"I_i": self._inertia_not_tested()},
                    "unidentified_rule": UNIDENTIFIED_RULE,
                    "left_out": list(self.left_out_of_statistics),
                    "quantities": {k: q.to_dict() for k, q in self.statistics.items()},
                },
                "checks": [c.to_dict() for c in self.checks],
                "skipped_trials": [s.to_dict() for s in self.study.skipped],
                "notes": list(self.study.notes),
                "timings_s": self.timings_s,
            }
        )


def run_analysis(
    records: Sequence[TrialRecord],
    *,
    executor: cf.Executor | None = None,
    jobs: int = 1,
    progress: ProgressCallback | None = None,
    options: AnalysisOptions | None = None,
    provenance_info: dict[str, Any] | None = None,
    stage: Callable[[str], None] | None = None,
    simulated_truth: dict[str, dict[str, dict[str, float]]] | None = None,
) -> StudyResults:
    """Study → LPV → statistics → checks. ``progress`` gets one call per trial (from
    :func:`analyze_study`); ``stage(name)`` is called as each later stage starts."""
    opt = options or AnalysisOptions()
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    study = analyze_study(records, executor=executor, jobs=jobs, progress=progress, options=opt)
    timings["trials_subjects_conditions"] = time.perf_counter() - t0

    conditions = tuple(c.condition for c in study.conditions)
    subjects = tuple(sorted({r.subject for r in study.subject_conditions}))

    if stage is not None:
        stage("LPV model")
    t0 = time.perf_counter()
    lpv = None
    lpv_error = None
    loo_vaf: list[LeaveOneOutVAF] = []
    points: list[OperatingPoint] = []
    try:
        points = as_operating_points(study.operating_points())
        lpv = analyse_lpv(points, order=LPV_ORDER, exclude=DEFAULT_EXCLUSIONS)
        if lpv.leave_one_out is not None:
            loo_vaf = leave_one_out_vaf(lpv, points, study, records, order=LPV_ORDER)
    except ValueError as e:  # too few operating points, a structure that cannot be built …
        lpv_error = str(e)
    timings["lpv"] = time.perf_counter() - t0

    if stage is not None:
        stage("statistics")
    t0 = time.perf_counter()
    table, left_out = statistics_table(study)
    if table.empty:
        stats_ = {
            k: QuantityStatistics(k, col, label, unit, None, None, None, ("no analysed data",))
            for k, (col, label, unit) in STAT_QUANTITIES.items()
        }
    else:
        stats_ = quantity_statistics(table, conditions)
    checks = compute_checks(stats_, study, lpv, loo_vaf, conditions)
    timings["statistics"] = time.perf_counter() - t0

    return StudyResults(
        study=study,
        conditions=conditions,
        subjects=subjects,
        points=points,
        lpv=lpv,
        lpv_error=lpv_error,
        loo_vaf=loo_vaf,
        statistics=stats_,
        checks=checks,
        provenance=provenance_info or provenance(None, [], opt),
        timings_s=timings,
        left_out_of_statistics=left_out,
        simulated_truth=simulated_truth or {},
    )


def analyse_directory(
    session_dir: str | Path,
    *,
    executor: cf.Executor | None = None,
    jobs: int = 1,
    progress: ProgressCallback | None = None,
    options: AnalysisOptions | None = None,
    stage: Callable[[str], None] | None = None,
) -> tuple[StudyResults, list[TrialRecord]]:
    """Read ``session_dir`` and analyse it (:func:`run_analysis`, ``stage`` as there); the
    records come back for plotting time signals. ``timings_s`` starts with ``read_files``."""
    opt = options or AnalysisOptions()
    t0 = time.perf_counter()
    records, inputs = load_directory(session_dir, progress)
    t_read = time.perf_counter() - t0
    # Another lab's recording may read the angle and torque at another instant than the
    # command, or skew them against each other (analysis.rig_from_data): a skew turns the
    # admittance's phase (half a sample: 7° at 20 Hz, b_c 36 % off on the independent world).
    records, timing = align_to_command(records)
    truth = {f.subject: f.simulated_truth for f in inputs if f.simulated_truth}
    res = run_analysis(
        records,
        executor=executor,
        jobs=jobs,
        progress=progress,
        options=opt,
        provenance_info=provenance(session_dir, inputs, opt),
        stage=stage,
        simulated_truth=truth,
    )
    res.timings_s = {"read_files": t_read, **res.timings_s}
    res.provenance["recording_timing"] = timing
    return res, records


__all__ = [
    "ALPHA",
    "PAPER_CONDITION_ORDER",
    "PAPER_TABLE2",
    "STAT_QUANTITIES",
    "Check",
    "InputFile",
    "LeaveOneOutVAF",
    "QuantityStatistics",
    "ReaderWarning",
    "StudyResults",
    "TrendTest",
    "analyse_directory",
    "compute_checks",
    "json_clean",
    "leave_one_out_models",
    "leave_one_out_vaf",
    "load_directory",
    "quantity_statistics",
    "run_analysis",
    "trend_test",
]
