"""``steerlab report``: analyse a directory of session files and write the report.

:func:`write_report` writes three files into the report directory:

- ``results.json``: every number (documented key by key in ``docs/results.md``);
- ``per_subject.csv``: per subject × condition values in long format, for R and spreadsheets;
- ``index.html``: one self-contained page for a lab meeting (figures embedded as ``data:``
  URIs, no external resources), including the paper's qualitative findings as checks.

All-or-nothing: the files are written into a hidden temporary directory beside the report
directory and moved into place only when everything succeeded, so a failure (a damaged
session file, an interrupted run) never leaves a half-written report, and an earlier report in
the same place survives until the new one is complete. Bad input raises
:class:`protocols.datafile.DataFileError` naming the file before anything is written.
"""

from __future__ import annotations

import concurrent.futures as cf
import csv
import html
import json
import os
import re
import shutil
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from steerlab.analysis.pipeline import (
    ALPHA,
    INERTIA_POORLY_DETERMINED,
    PAPER_TABLE2,
    PARAMETER_UNITS,
    STAT_QUANTITIES,
    WEIGHTING_DISAGREEMENT_SEMS,
    StudyResults,
    analyse_directory,
    json_clean,
    weightings_disagree,
    wheel_used_sentence,
)
from steerlab.analysis.study import AnalysisOptions, ProgressCallback
from steerlab.protocols.records import TrialRecord

RESULTS_JSON = "results.json"
PER_SUBJECT_CSV = "per_subject.csv"
INDEX_HTML = "index.html"
REPORT_FILES = (RESULTS_JSON, PER_SUBJECT_CSV, INDEX_HTML)
CSV_COLUMNS = ("subject", "condition", "quantity", "value", "sem", "unit")
# (quantity in the CSV, attribute of SubjectConditionResult, unit)
CSV_EXTRA_QUANTITIES = (
    ("vaf", "vaf_percent", "%"),
    ("fit", "fit_percent", "%"),
    ("grip_mean", "grip_mean_N", "N"),
    ("grip_sd", "grip_sd_N", "N"),
)
FIGURES = (
    "time_signals",
    "grip",
    "admittance",
    "subject_admittance",
    "parameters",
    "lpv_parameters",
    "lpv_responses",
    "leave_one_out",
)


class ReportError(ValueError):
    """The report cannot be written where asked (the message says why)."""


@dataclass(frozen=True)
class ReportResult:
    out_dir: Path
    results_json: Path
    per_subject_csv: Path
    index_html: Path
    results: StudyResults
    figures: tuple[str, ...]  # the figures embedded in index.html
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def checks_passed(self) -> int:
        return sum(c.passed is True for c in self.results.checks)

    @property
    def checks_total(self) -> int:
        return len(self.results.checks)


# ------------------------------------------------------------------------------------------
# The entry point


def _timing_line(t: dict) -> str:
    """How the angle and torque were aligned to the command (analysis.rig_from_data)."""
    if not t.get("applied"):
        return ""
    how = "as its data show" if t.get("source") == "data" else "as the recording states"

    def when(v: float) -> str:
        side = "after" if v > 0 else "before"
        return "at the command" if v == 0 else f"{abs(v):.3g} sample(s) {side} it"

    return (
        f'<p class="muted">Recording timing ({how}): the angle was read '
        f"{when(t['theta_offset_samples'])}, the torque {when(t['torque_offset_samples'])}; "
        "both were moved to the command's instant before the analysis."
        + "".join(f" {_prose(n)}." for n in t.get("notes", []))
        + "</p>"
    )


def write_report(
    session_dir: str | Path,
    out_dir: str | Path,
    *,
    jobs: int = 1,
    executor: cf.Executor | None = None,
    progress: ProgressCallback | None = None,
    figures: bool = True,
    options: AnalysisOptions | None = None,
) -> ReportResult:
    """Analyse every session file in ``session_dir`` and write the report into ``out_dir``.

    ``executor``/``jobs``: where the per-trial work runs (see
    :func:`analysis.study.analyze_study`). ``progress(done, total, label)`` is called per file
    read, per trial analysed, then once per later stage. ``figures=False`` writes the page
    without figures (faster; the numbers are the same).

    Raises :class:`DataFileError` for unreadable input (naming the file) and
    :class:`ReportError` when ``out_dir`` exists and is not an earlier report.
    """
    out = Path(out_dir)
    _check_out_dir(out)  # before the analysis: a wrong --out should not cost a minute
    t_all = time.perf_counter()
    n_fig = len(FIGURES) if figures else 0
    stages = ["LPV model", "statistics", RESULTS_JSON, PER_SUBJECT_CSV]
    stages += [f"figure {name}" for name in FIGURES[:n_fig]] + [INDEX_HTML]
    step = _Stages(stages, progress)

    res, records = analyse_directory(
        session_dir, executor=executor, jobs=jobs, progress=progress, options=options, stage=step
    )
    timings = res.timings_s  # read_files, then the analysis's; the report adds its own
    tracking = None
    if any(r.time_varying for r in records):
        # Only studies with time-varying trials get the tracking section (analysis.tracking).
        from steerlab.analysis.tracking.report_section import analyse_tracking

        t0 = time.perf_counter()
        tracking = analyse_tracking(records)
        timings["tracking"] = time.perf_counter() - t0
    driving = None
    if any(r.driving for r in records):
        # Only studies with driving trials get the driving section (analysis.driving_report).
        from steerlab.analysis.driving_report import report_section

        t0 = time.perf_counter()
        driving = report_section(records, figures=figures)
        timings["driving"] = time.perf_counter() - t0

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        step(RESULTS_JSON)
        t0 = time.perf_counter()
        doc = res.to_dict()
        if tracking is not None:
            doc["tracking"] = json_clean(tracking.to_dict())
        if driving is not None:
            doc["driving"] = json_clean(driving[0])
        text = json.dumps(doc, allow_nan=False, ensure_ascii=False, indent=1)
        (tmp / RESULTS_JSON).write_text(text + "\n", encoding="utf-8")
        step(PER_SUBJECT_CSV)
        write_per_subject_csv(res, tmp / PER_SUBJECT_CSV)
        timings["write_data"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        images = render_figures(res, records, on_figure=step) if figures else {}
        timings["figures"] = time.perf_counter() - t0

        extra = []
        if tracking is not None:
            from steerlab.analysis import figures as F
            from steerlab.analysis.tracking.report_section import figure, html_section

            fig = figure(tracking) if figures else None
            uri = None
            if fig is not None:
                import matplotlib.pyplot as plt

                uri = F.png_data_uri(fig)
                plt.close(fig)
            extra.append(html_section(tracking, uri))
        if driving is not None:
            extra.append(driving[1])
        step(INDEX_HTML)
        t0 = time.perf_counter()
        page = html_page(res, images, records, extra_sections=extra)
        (tmp / INDEX_HTML).write_text(page, encoding="utf-8")
        timings["write_html"] = time.perf_counter() - t0
        _install(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    timings["total"] = time.perf_counter() - t_all
    step.finish()
    return ReportResult(
        out_dir=out,
        results_json=out / RESULTS_JSON,
        per_subject_csv=out / PER_SUBJECT_CSV,
        index_html=out / INDEX_HTML,
        results=res,
        figures=tuple(k for k, v in images.items() if v is not None),
        timings_s=timings,
    )


class _Stages:
    """Reports each later stage as ``progress(k, n_stages, name)`` when it starts."""

    def __init__(self, names: Sequence[str], progress: ProgressCallback | None) -> None:
        self.names, self.progress, self.done = list(names), progress, 0

    def __call__(self, name: str) -> None:
        if self.progress is not None:
            self.progress(min(self.done, len(self.names) - 1), len(self.names), name)
        self.done += 1

    def finish(self) -> None:
        if self.progress is not None:
            self.progress(len(self.names), len(self.names), "done")


def _check_out_dir(out: Path) -> None:
    if not out.exists():
        return
    if not out.is_dir():
        raise ReportError(f"{out}: exists and is not a directory")
    others = sorted(p.name for p in out.iterdir() if p.name not in REPORT_FILES)
    if others:
        # Replacing the directory would delete them: refuse rather than guess.
        shown = ", ".join(others[:5]) + (" …" if len(others) > 5 else "")
        raise ReportError(
            f"{out}: exists and holds files that are not part of a report ({shown}); "
            "choose an empty or new directory"
        )


def _install(tmp: Path, out: Path) -> None:
    """Move the finished report into place; an earlier report is replaced only now."""
    mode = 0o777 & ~_umask()
    os.chmod(tmp, mode)  # mkdtemp makes it private; a report directory is an ordinary one
    if not out.exists():
        os.replace(tmp, out)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    old.rmdir()
    os.replace(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        os.replace(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# ------------------------------------------------------------------------------------------
# per_subject.csv


def per_subject_rows(res: StudyResults) -> list[dict[str, Any]]:
    """Long format: one row per subject × condition × quantity (sem None where none)."""
    rows = []
    for r in res.study.subject_conditions:
        if r.fit is not None:
            for name, value in r.fit.params.as_dict().items():
                rows.append(
                    {
                        "subject": r.subject,
                        "condition": r.condition,
                        "quantity": name,
                        "value": value,
                        "sem": r.fit.sems.get(name),
                        "unit": PARAMETER_UNITS[name],
                    }
                )
        for q, attr, unit in CSV_EXTRA_QUANTITIES:
            rows.append(
                {
                    "subject": r.subject,
                    "condition": r.condition,
                    "quantity": q,
                    "value": getattr(r, attr),
                    "sem": None,
                    "unit": unit,
                }
            )
    return rows


def _csv_number(v: float | None) -> str:
    # repr round-trips a float exactly, so the CSV and results.json carry identical numbers.
    if v is None or not np.isfinite(v):
        return ""
    return repr(float(v))


def write_per_subject_csv(res: StudyResults, path: Path) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for row in per_subject_rows(res):
            w.writerow(
                [
                    row["subject"],
                    row["condition"],
                    row["quantity"],
                    _csv_number(row["value"]),
                    _csv_number(row["sem"]),
                    row["unit"],
                ]
            )


# ------------------------------------------------------------------------------------------
# Figures


def example_trial(res: StudyResults, records: Sequence[TrialRecord]):
    """The trial whose time signals the report shows: the first subject's first analysed
    repetition of BT12 (a mid-range condition), else of the middle condition."""
    conds = list(res.conditions)
    if not conds:
        return None, None
    want = "BT12" if "BT12" in conds else conds[len(conds) // 2]
    by_source = {r.source: r for r in records if r.source}
    for cell in res.study.subject_conditions:
        if cell.condition == want and cell.trials:
            t = cell.trials[0]
            rec = by_source.get(t.source)
            if rec is not None:
                return rec, t.selection
    return None, None


def render_figures(
    res: StudyResults,
    records: Sequence[TrialRecord],
    on_figure: Callable[[str], None] | None = None,
) -> dict[str, str | None]:
    """name → PNG data URI (None when the figure has nothing to show, e.g. no LPV model)."""
    from steerlab.analysis import figures as F

    makers: dict[str, Callable[[], Any]] = {
        "time_signals": lambda: (
            F.time_signals(*example_trial(res, records))
            if example_trial(res, records)[0] is not None
            else None
        ),
        "grip": lambda: F.grip_boxplots(res),
        "admittance": lambda: F.admittance(res),
        "subject_admittance": lambda: F.subject_admittance(res),
        "parameters": lambda: F.parameter_boxplots(res),
        "lpv_parameters": lambda: F.lpv_parameters(res),
        "lpv_responses": lambda: F.lpv_responses(res),
        "leave_one_out": lambda: F.leave_one_out(res),
    }
    out: dict[str, str | None] = {}
    for name in FIGURES:
        if on_figure is not None:
            on_figure(f"figure {name}")
        fig = makers[name]()
        out[name] = None if fig is None else F.png_data_uri(fig)
    return out


# ------------------------------------------------------------------------------------------
# index.html

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;max-width:1200px;
margin:.8em auto;padding:0 1em;color:#222;line-height:1.4}
h1{font-size:1.4em;margin:.2em 0}h2{border-bottom:2px solid #ddd;padding-bottom:.15em;
margin:1.4em 0 .4em;font-size:1.25em}h3{margin-bottom:.3em}
#conditions,#checks{margin-top:.6em}
table{border-collapse:collapse;margin:.4em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.2em .45em;text-align:right;vertical-align:top}
th{background:#f3f3f3}td.l,th.l{text-align:left}
table.compact td{padding:.1em .45em}
.pass{background:#dff3df;color:#135e13;font-weight:600}
.differs{background:#fbe3d6;color:#8a3300;font-weight:600}
.na{background:#eee;color:#555}
.sig{font-weight:700}.muted{color:#777}.spread{color:#555;font-size:.85em}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #eee}
figcaption{font-size:.9em;color:#444}
.small{font-size:.85em}code{background:#f5f5f5;padding:0 .2em}
.warn{background:#fff4d6;border:1px solid #e0b040;padding:.2em .8em;margin:.5em 0;
font-size:.92em}.warn ul{margin:.2em 0;padding-left:1.2em}
.bad{color:#b00020;font-weight:600}
p{margin:.35em 0}
"""

# How the page names what the results name for programs.
METHOD_NAMES = {"de_caigny": "de Caigny", "physical": "physical parameters"}
WEIGHTING_NAMES = {
    "inverse_variance": "inverse variance (maximum likelihood)",
    "paper": "the paper's coherence × 1/f",
}
STRUCTURE_NAMES = {
    "split": "one real zero in each block",
    "second_order": "both zeros in the second-order block",
}
TIMING_NAMES = {
    "read_files": "reading the files",
    "trials_subjects_conditions": "trials, subjects and conditions",
    "lpv": "LPV model",
    "statistics": "statistics",
    "tracking": "tracking",
    "driving": "driving",
    "write_data": "writing the data",
    "figures": "figures",
    "write_html": "writing the page",
    "total": "total",
}
# Labels of the numbers a check rests on (Check.values keys).
VALUE_LABELS = {
    "L": "Page's L",
    "p": "p",
    "mean_spearman_rho": "mean Spearman ρ",
    "n_subjects": "subjects",
    "condition_means": "condition means",
    "pairs_not_significant": "pairs not significant",
    "n_pairs_tested": "pairs tested",
    "mean_difference_N": "mean difference (N)",
    "t": "t",
    "df": "df",
    "p_bonferroni": "Bonferroni p",
    "group_low_f_admittance_rad_per_Nm": "group mean |Ĥ| up to 0.7 Hz (rad/N·m)",
    "F": "F",
    "df1": "df1",
    "df2": "df2",
    "p_gg": "p (Greenhouse–Geisser)",
    "eps_gg": "ε (Greenhouse–Geisser)",
    "partial_eta_squared": "partial η²",
    "median_relative_sem": "median SEM / estimate",
    "condition_means_percent": "mean VAF (%)",
    "not_significantly_lower_than": "RT not significantly lower than",
    "lti_fit_percent": "LTI FIT%",
    "lpv_fit_percent": "LPV FIT%",
}
# Long words for the identifiers that other modules put into their sentences.
_IDENTIFIERS = {
    **METHOD_NAMES,
    "inverse_variance": WEIGHTING_NAMES["inverse_variance"],
    "second_order": "second-order",
    "trial_cv": "trial spread",
}
_LIST_REPR = re.compile(r"\[((?:'[^'\[\]]*'(?:, )?)+)\]")
_QUOTED = re.compile(r"(?<![\w'])'([^'\n]+?)'(?![\w])")
_ROW_REF = re.compile(r"\b([kb]_[ic])_(rises|changes)\b")
_SYMBOL = re.compile(r"\b([A-Za-z])_(i|c|gg|GG)\b")
_SUPERSCRIPT = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")


def _e(x: Any) -> str:
    return html.escape(str(x))


def _prose(text: Any) -> str:
    """Plain text from the analysis as HTML a reader can read: Python list reprs become
    comma-separated words, identifiers their names, quotes typographic, and parameter
    names get their subscripts (k_i → k<sub>i</sub>)."""
    s = str(text)
    s = _LIST_REPR.sub(lambda m: ", ".join(re.findall(r"'([^']*)'", m.group(1))), s)
    s = _ROW_REF.sub(lambda m: f"“{m.group(1)} {m.group(2)}”", s)
    for ident, name in _IDENTIFIERS.items():
        s = re.sub(rf"\b{ident}\b", name, s)
    s = _QUOTED.sub(r"‘\1’", s)
    s = html.escape(s, quote=False)
    return _SYMBOL.sub(r"\1<sub>\2</sub>", s)


def _sym(name: str) -> str:
    """A parameter name with its subscript: "k_i" → k<sub>i</sub>."""
    return _prose(name)


def method_name(method: str) -> str:
    return METHOD_NAMES.get(method, method.replace("_", " "))


def _sci(x: float, sig: int) -> str:
    mantissa, exp = f"{x:.{sig - 1}e}".split("e")
    if int(exp) == 0:  # "1.2 × 10⁰" is 1.2
        return mantissa
    return f"{mantissa} × 10{str(int(exp)).translate(_SUPERSCRIPT)}"


def _num(v: Any, sig: int = 3) -> str:
    """``sig`` significant digits, fixed-point between 1e-4 and 1e6 (powers of ten written
    as such outside), trailing zeros kept."""
    if v is None:
        return "–"
    if isinstance(v, int | np.integer) and not isinstance(v, bool):
        return str(v)  # counts and degrees of freedom are exact
    try:
        x = float(v)
    except (TypeError, ValueError):
        return _e(v)
    if not np.isfinite(x):
        return "–"
    if x == 0:
        return "0"
    if abs(x) >= 1e6 or abs(x) < 1e-4:
        return _sci(x, sig)
    decimals = max(sig - 1 - int(np.floor(np.log10(abs(x)))), 0)
    return f"{x:.{decimals}f}"


def _pm(v: Any, sem: Any) -> str:
    """Value ± SEM, both to the decimals the SEM supports (one significant digit of the
    SEM, two when it starts with 1 or 2): 0.0999 ± 0.0007, 54.2 ± 1.4, 232 ± 7."""
    if v is None or not np.isfinite(float(v)):
        return "–"
    x = float(v)
    s = None if sem is None else float(sem)
    if s is None or not np.isfinite(s) or s <= 0:
        return f"{_num(x)} ± –"
    e = int(np.floor(np.log10(s)))
    digits = 2 if s / 10.0**e < 3 else 1
    d = max(digits - 1 - e, 0)
    if abs(x) >= 1e6 or d > 8:
        return f"{_num(x)} ± {_num(s, digits)}"
    return f"{x:.{d}f} ± {s:.{d}f}"


def _fixed(v: Any, decimals: int) -> str:
    """A fixed number of decimals (percentages, forces): columns line up."""
    if v is None:
        return "–"
    x = float(v)
    return f"{x:.{decimals}f}" if np.isfinite(x) else "–"


def _p(p: float | None) -> str:
    if p is None or not np.isfinite(p):
        return "–"
    if p <= 0:
        return "0"
    return _sci(p, 2) if p < 0.001 else f"{p:.3f}"


def _seconds(s: float) -> str:
    return f"{s:.0f} s" if s >= 10 else (f"{s:.1f} s" if s >= 0.1 else "< 0.1 s")


def _table(
    header: Sequence[str], rows: Sequence[Sequence[str]], left: int = 1, cls: str = ""
) -> str:
    """Cells are HTML already; the first ``left`` columns are left-aligned."""
    th = "".join(f'<th class="{"l" if i < left else ""}">{h}</th>' for i, h in enumerate(header))
    body = "".join(
        "<tr>"
        + "".join(f'<td class="{"l" if i < left else ""}">{c}</td>' for i, c in enumerate(r))
        + "</tr>"
        for r in rows
    )
    c = f' class="{cls}"' if cls else ""
    return f"<table{c}><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>"


# What each figure shows, for a reader who cannot see it (the img's alt text).
FIGURE_DESCRIPTIONS = {
    "time_signals": "One recorded trial: perturbation torque, driver torque, wheel angle and "
    "grip force against time, the analysed periods shaded",
    "grip": "Grip force per condition: box plots of the subjects' mean grip and grip SD",
    "admittance": "Admittance magnitude, phase and coherence against frequency per "
    "condition: subjects' mean estimate, 95 % band and the group fit",
    "subject_admittance": "Admittance magnitude against frequency for each subject, one "
    "panel per subject: the estimate and the subject's own fit per condition",
    "parameters": "Arm-model parameters per condition: the subjects' estimates with their "
    "SEMs as box plots, the group fit, and the inertia of each subject",
    "lpv_parameters": "Group-fit arm parameters against grip force at each operating point, "
    "with the LPV model's interpolation",
    "lpv_responses": "Admittance of both LPV models at each operating point against the "
    "measured group frequency response",
    "leave_one_out": "Each intermediate operating point's measured admittance and its "
    "prediction by the LPV models rebuilt without it",
}


def _figure(images: dict[str, str | None], name: str, caption: str) -> str:
    uri = images.get(name)
    if uri is None:
        return ""
    alt = FIGURE_DESCRIPTIONS.get(name, name.replace("_", " "))
    return (
        f'<figure id="fig-{name}"><img alt="{_e(alt)}" src="{uri}">'
        f"<figcaption>{caption}</figcaption></figure>"
    )


T = TypeVar("T")


def in_condition_order(
    items: Iterable[T], conditions: Sequence[str], condition: Callable[[T], str] = str
) -> list[T]:
    """``items`` in the protocol's condition order (``condition`` names an item's), anything
    else after them."""
    rank = {c: i for i, c in enumerate(conditions)}
    # Stable: items of one condition, and those of none, keep their order.
    return sorted(items, key=lambda x: rank.get(condition(x), len(rank)))


# ------------------------------------------------------------------------------------------
# The numbers the first screen shows


@dataclass(frozen=True)
class Spread:
    """Median and interquartile range of the subjects' values (None without values)."""

    median: float | None
    q1: float | None
    q3: float | None
    n: int

    @classmethod
    def of(cls, values: Sequence[float | None]) -> Spread:
        v = np.array([x for x in values if x is not None and np.isfinite(x)], dtype=float)
        if v.size == 0:
            return cls(None, None, None, 0)
        q1, med, q3 = np.percentile(v, [25, 50, 75])
        return cls(float(med), float(q1), float(q3), int(v.size))


@dataclass(frozen=True)
class ConditionSummary:
    """One condition's answer: the group fit (± SEM) and the spread of the subjects' own
    estimates (those the data determine), grip force and model quality."""

    condition: str
    n_subjects: int
    grip: Spread  # subjects' mean grip; its median is μ
    grip_sd: Spread
    group: dict[str, tuple[float, float | None]]  # parameter → (value, SEM)
    subjects: dict[str, Spread]
    group_fit_percent: float | None
    vaf: Spread


def condition_summaries(res: StudyResults) -> list[ConditionSummary]:
    out = []
    for c in res.study.conditions:
        cells = [r for r in res.study.subject_conditions if r.condition == c.condition]
        group = {}
        if c.fit is not None:
            group = {n: (getattr(c.fit.params, n), c.fit.sems.get(n)) for n in FREE_PARAMETERS}
        subjects = {}
        for n in FREE_PARAMETERS:
            subjects[n] = Spread.of(
                [
                    getattr(r.fit.params, n)
                    for r in cells
                    if r.fit is not None and n not in r.fit.unidentified()
                ]
            )
        out.append(
            ConditionSummary(
                condition=c.condition,
                n_subjects=len(c.subjects),
                grip=Spread.of(list(c.grip_subject_means_N)),
                grip_sd=Spread.of(list(c.grip_subject_sds_N)),
                group=group,
                subjects=subjects,
                group_fit_percent=None if c.fit is None else c.fit.fit_percent,
                vaf=Spread.of([r.vaf_percent for r in cells]),
            )
        )
    return out


FREE_PARAMETERS = ("b_i", "k_i", "b_c", "k_c")


# ------------------------------------------------------------------------------------------
# index.html


def html_page(
    res: StudyResults,
    images: dict[str, str | None],
    records: Sequence[TrialRecord],
    extra_sections: Sequence[str] = (),
) -> str:
    """The report page; ``images`` from :func:`render_figures` (empty: no figures);
    ``extra_sections``: HTML sections placed before the skipped trials (the tracking section
    of a study with time-varying trials).

    The answer comes first: the per-condition parameters, then the paper's findings checked,
    then the method, the figures and the detail; full matrices are collapsed at the end."""
    prov = res.provenance
    n_trials = sum(len(r.trials) for r in res.study.subject_conditions)
    n_fam = sum(_reason_kind(s.reason) == "familiarization" for s in res.study.skipped)
    n_skip = len(res.study.skipped) - n_fam
    title = f"Steerlab report: {Path(prov.get('session_dir') or 'study').name}"
    generated = str(prov.get("generated_utc", ""))[:16].replace("T", " ")
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{_e(title)}</h1>",
        f'<p class="muted small">{_count(len(res.subjects), "subject")} × '
        f"{_count(len(res.conditions), 'condition')}, {_count(n_trials, 'trial')} analysed"
        + (f", {n_skip} skipped" if n_skip else "")
        + (f" ({n_fam} familiarization trials not analysed, by design)" if n_fam else "")
        + f". Generated {_e(generated)} UTC by Steerlab "
        f"{_e(prov.get('software', {}).get('steerlab', ''))}.</p>",
        _warnings(res),
        _condition_table(res),
        _checks_summary(res),
        _contents(images),
        _method_section(res, records),
        "<h2 id='figures'>Figures</h2>" if any(images.values()) else "",
        *_figures(images),
        '<h2 id="detail">Detail</h2><p>Everything behind the numbers above.</p>',
        _checks_detail(res),
        _table2(res),
        _loo_table(res),
        _anova_table(res),
        _pairwise_summary(res),
        _truth_section(res),
        _inertia_section(res),
        _weighting_section(res),
        *extra_sections,
        _skipped_section(res),
        _familiarization_section(res),
        _notes_section(res),
        _provenance_section(res),
        _pairwise_matrices(res),
        "</body></html>",
    ]
    return _DOCS_PATH.sub("Steerlab's docs/", "\n".join(p for p in parts if p))


# The page stands alone, away from the repository: a bare "docs/x.md" (in this module's text or
# in a sentence from another) is named as Steerlab's. No base64 figure can match: it has no ".".
_DOCS_PATH = re.compile(r"(?<!Steerlab's )(?<![\w/.-])docs/(?=[\w-]+\.md)")


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def _figures(images: dict[str, str | None]) -> list[str]:
    return [
        _figure(
            images,
            "time_signals",
            "One trial as recorded. Only whole perturbation periods after the run-in "
            "(shaded) are analysed; grip force is the sum of both hands.",
        ),
        _figure(
            images, "grip", "Grip force per condition. Diamonds: μ, the LPV scheduling variable."
        ),
        _figure(
            images,
            "admittance",
            "Admittance (wheel angle per torque on the hands) per condition: mean over "
            "subjects of their complex FRFs (dots), 95 % intervals across subjects (bands) "
            "and the group fit (lines); hollow dots: the lowest bands, left out of the "
            "fits. Bottom: coherence, mean over subjects.",
        ),
        _figure(
            images,
            "subject_admittance",
            "Every subject's admittance magnitude per condition: the estimate Ĥ (dots) and "
            "the subject's own arm-model fit (lines).",
        ),
        _figure(
            images,
            "parameters",
            "Arm-model parameters per condition (log scale). Boxes: the subjects' "
            "estimates; grey bars: each estimate ± its SEM (Cramér–Rao bound of the fit, "
            "from the measured noise of Ĥ, see Steerlab's docs/method-estimator.md); black: "
            "the group fit ± SEM; red ×: estimates the data do not determine (at a search bound or "
            "SEM ≥ value), counted and left out of boxes and statistics. Last panel: "
            "I<sub>i</sub>, one per subject (joint fit over its conditions).",
        ),
        _figure(
            images,
            "lpv_parameters",
            "Operating points of the LPV model. The physical-parameter interpolation is "
            "the curve; hollow points are not in the LPV model.",
        ),
        _figure(images, "lpv_responses", "Both LPV models evaluated at each operating point's μ."),
        _figure(
            images,
            "leave_one_out",
            "Each intermediate operating point predicted by both LPV models rebuilt without "
            "it (FIT% against the measured group FRF; VAF: median over subjects, time "
            "domain). Thick grey: the point's own local LTI model.",
        ),
    ]


def _contents(images: dict[str, str | None]) -> str:
    items = [("method", "Method")]
    if any(v is not None for v in images.values()):
        items.append(("figures", "Figures"))
    items += [
        ("checks-detail", "Checks in detail"),
        ("table2", "Table 2"),
        ("loo", "Leave-one-out"),
        ("anova", "RM-ANOVA"),
        ("pairwise", "Pairwise tests"),
        ("inertia", "Inertia"),
        ("weighting", "Two weightings"),
        ("skipped", "Skipped trials"),
        ("familiarization", "Familiarization trials"),
        ("provenance", "Provenance"),
    ]
    links = " · ".join(f'<a href="#{a}">{_e(t)}</a>' for a, t in items)
    return f'<p class="small">Further down: {links}</p>'


# The "Read this first" items point at the section holding their detail.
_SECTION_LINKS = {
    "table2": ("table2", "Table 2"),
    "loo": ("loo", "leave-one-out"),
    "anova": ("anova", "statistics"),
    "checks": ("checks", "the checks"),
    "notes": ("notes", "notes"),
    "conditions": ("conditions", "per condition"),
    "inertia": ("inertia", "inertia"),
    "weighting": ("weighting", "two weightings"),
}


def _warnings(res: StudyResults) -> str:
    items = res.reader_warnings()
    if not items:
        return ""
    lis = []
    for w in items:
        link = _SECTION_LINKS.get(w.section)
        more = f' <a href="#{link[0]}">See {_e(link[1])}.</a>' if link else ""
        lis.append(f"<li>{_prose(w.text)}{more}</li>")
    return f'<div class="warn" id="read-first"><b>Read this first</b><ul>{"".join(lis)}</ul></div>'


def _spread_text(s: Spread, sig: int = 3) -> str:
    if s.median is None:
        return "–"
    if s.n < 2:
        return _num(s.median, sig)
    return f"{_num(s.median, sig)} ({_num(s.q1, sig)}–{_num(s.q3, sig)})"


def _condition_table(res: StudyResults) -> str:
    rows = []
    for s in condition_summaries(res):
        row = [
            f"<b>{_e(s.condition)}</b>",
            str(s.n_subjects),
            _spread_text(s.grip),
            _spread_text(s.grip_sd),
        ]
        for n in FREE_PARAMETERS:
            if n in s.group:
                v, sem = s.group[n]
                row.append(
                    f"{_pm(v, sem)}<br><span class='spread'>{_spread_text(s.subjects[n])}</span>"
                )
            else:
                row.append(f"–<br><span class='spread'>{_spread_text(s.subjects[n])}</span>")
        row += [_fixed(s.group_fit_percent, 1), _spread_text(s.vaf)]
        rows.append(row)
    header = [
        "condition",
        "n",
        "grip (N)",
        "grip SD (N)",
        "b<sub>i</sub> (N·m·s/rad)",
        "k<sub>i</sub> (N·m/rad)",
        "b<sub>c</sub> (N·m·s/rad)",
        "k<sub>c</sub> (N·m/rad)",
        "group FIT%",
        "VAF%",
    ]
    return (
        '<h2 id="conditions">Per condition</h2>'
        '<p class="small">Parameters: the group fit ± SEM (the arm model fitted to the '
        "subjects' mean FRF); below, smaller: median (interquartile range) of the subjects' "
        "own fits. Grip force, grip SD and VAF: median (interquartile range) over subjects; "
        "the median grip is μ, the LPV scheduling variable.</p>"
        + _table(header, rows, cls="compact")
    )


def _check_evidence(c: Any, conds: Sequence[str]) -> str:
    """One line: the number that decides the check."""
    v = c.values
    if c.passed is None:
        return f'<span class="muted">{_prose(c.note)}</span>'
    if "p_bonferroni" in v:
        return (
            f"mean difference {_num(v.get('mean_difference_N'))} N, "
            f"Bonferroni p = {_p(v['p_bonferroni'])}"
        )
    if "pairs_not_significant" in v:
        ns, n = v["pairs_not_significant"], v.get("n_pairs_tested")
        if not ns:
            return f"all {n} pairs significant"
        return f"{n - len(ns)} of {n} pairs significant; not: {_e(', '.join(ns))}"
    if "p_gg" in v:
        return f"RM-ANOVA F = {_num(v.get('F'))}, p = {_p(v['p_gg'])}"
    if "L" in v:
        return (
            f"Page's trend test p = {_p(v.get('p'))}, mean Spearman ρ = "
            f"{_fixed(v.get('mean_spearman_rho'), 2)}"
        )
    if "median_relative_sem" in v:
        d = v["median_relative_sem"]
        return "median SEM / estimate: " + ", ".join(
            f"{_sym(n)} {100 * x:.1f} %" for n, x in d.items() if x is not None
        )
    if "condition_means_percent" in v:
        d = v["condition_means_percent"]
        means = (f"{k} {d[k]:.0f} %" for k in in_condition_order(d, conds))
        txt = "mean VAF: " + ", ".join(means)
        ns = v.get("not_significantly_lower_than") or []
        return _e(txt) + (f"; RT not lower than {_e(', '.join(ns))}" if ns else "")
    if "lti_fit_percent" in v:
        d = {k: x for k, x in v["lti_fit_percent"].items() if x is not None}
        if d:
            k = min(d, key=d.__getitem__)
            return f"lowest {d[k]:.1f} % ({_e(k)})"
    if "lpv_fit_percent" in v:
        flat = [
            (x, k, m)
            for k, dm in v["lpv_fit_percent"].items()
            for m, x in dm.items()
            if x is not None
        ]
        if flat:
            x, k, m = min(flat)
            return f"lowest {x:.1f} % ({_e(k)}, {_e(method_name(m))})"
    if v and all("/" in k for k in v):
        by: dict[str, list[str]] = {}
        for k, x in v.items():
            m, cond = k.split("/", 1)
            by.setdefault(method_name(m), []).append(f"{cond} {_fixed(x, 0)} %")
        return "median VAF, " + "; ".join(f"{m}: {', '.join(xs)}" for m, xs in by.items())
    return _values_prose(v, conds)


def _checks_summary(res: StudyResults) -> str:
    cls = {"pass": "pass", "differs": "differs", "not computed": "na"}
    conds = list(res.conditions)
    n_ok = sum(c.passed is True for c in res.checks)
    n_diff = sum(c.passed is False for c in res.checks)
    n_na = len(res.checks) - n_ok - n_diff
    rows = [
        [
            f'<span class="{cls[c.status]}">{_e(c.status)}</span>',
            _prose(c.paper),
            f'<span class="small">{_check_evidence(c, conds)}</span>',
        ]
        for c in res.checks
    ]
    counts = f"{n_ok} agree, {n_diff} differ" + (f", {n_na} not computed" if n_na else "")
    return (
        f'<h2 id="checks">The paper\'s findings, checked on these data: {counts}</h2>'
        '<p class="small">Each finding of Pronker et al. (2017) decided from this study\'s '
        'numbers; the test and all values are in <a href="#checks-detail">the checks in '
        "detail</a>. A “differs” is a finding about these data, not necessarily an "
        "error.</p>" + _table(["result", "finding", "evidence"], rows, left=3, cls="compact")
    )


def _value_text(k: str, x: Any) -> str:
    if (k == "p" or k.startswith("p_")) and isinstance(x, float):
        return _p(x)
    return _num(x)


def _values_prose(values: dict[str, Any], conds: Sequence[str]) -> str:
    """A check's numbers in words: dicts over conditions (or parameters) as "RT 43.7, BT18
    44.8, …" in the protocol's order, lists as comma-separated words."""
    parts = []
    for k, v in values.items():
        if "/" in k:
            m, cond = k.split("/", 1)
            label = f"{_e(method_name(m))}, {_e(cond)} left out"
        else:
            label = _prose(VALUE_LABELS.get(k, k.replace("_", " ")))
        if isinstance(v, dict):
            inner = []
            for a in in_condition_order(list(v), conds):
                b = v[a]
                if isinstance(b, dict):
                    sub = ", ".join(f"{_e(method_name(m))} {_num(x)}" for m, x in b.items())
                    inner.append(f"{_e(a)}: {sub}")
                else:
                    inner.append(f"{_sym(a)} {_num(b)}")
            nested = any(isinstance(b, dict) for b in v.values())
            parts.append(f"{label}: " + ("; " if nested else ", ").join(inner))
        elif isinstance(v, list):
            parts.append(f"{label}: {_e(', '.join(map(str, v))) or 'none'}")
        elif v is None:
            parts.append(f"{label}: –")
        else:
            parts.append(f"{label} = {_value_text(k, v)}")
    return "; ".join(parts)


def _checks_detail(res: StudyResults) -> str:
    cls = {"pass": "pass", "differs": "differs", "not computed": "na"}
    conds = list(res.conditions)
    rows = [
        [
            f'<span class="{cls[c.status]}">{_e(c.status)}</span>',
            _prose(c.paper),
            _prose(c.test),
            f'<span class="small">{_values_prose(c.values, conds)}</span>'
            + (f'<br><span class="muted small">{_prose(c.note)}</span>' if c.note else ""),
        ]
        for c in res.checks
    ]
    return (
        '<h2 id="checks-detail">The paper\'s findings in detail</h2>'
        "<p>Each row restates one finding of Pronker et al. (2017) and decides it from this "
        "study's numbers with the test shown; nothing here is copied from the paper.</p>"
        + _table(["result", "paper", "test", "values"], rows, left=4)
    )


def _method_section(res: StudyResults, records: Sequence[TrialRecord]) -> str:
    prov = res.provenance
    return (
        '<h2 id="method">Method</h2>'
        f"<p class='muted'>{_prose(wheel_used_sentence(prov.get('input_files', [])))}</p>"
        + _timing_line(prov.get("recording_timing") or {})
        + _how_to_read(res)
        + _key_numbers(res, records)
    )


def _how_to_read(res: StudyResults) -> str:
    pct = round(100 * res.study.options.confidence)
    return f"""<h3 id="how">How to read this</h3>
<ul>
<li><b>Admittance</b> H = θ/T<sub>d</sub> (rad/N·m): how far the wheel turns per N·m of torque
on the hands. High = relaxed arms, low = stiff arms. It is estimated from the closed loop with the
perturbation torque as instrument, per double frequency band.</li>
<li><b>Arm model</b>: contact (b<sub>c</sub>, k<sub>c</sub>) in series with the intrinsic arm
(I<sub>i</sub>, b<sub>i</sub>, k<sub>i</sub>). {_prose(_inertia_sentence(res))}
<b>SEM</b> = standard error of an estimate (Cramér–Rao bound of the fit actually used);
{pct} % intervals on FRFs are across subjects.</li>
<li><b>Fit</b>: {_prose(_weighting_sentence(res))}</li>
<li><b>VAF</b> (time domain) and <b>FIT%</b> (frequency domain, 1/f-weighted): 100 % is a perfect
model. VAF uses the measured driver torque as the model's input.</li>
<li><b>μ</b>: the median over subjects of their mean total grip force in a condition; the LPV
model's scheduling variable. RT is left out of the LPV model, as in the paper.</li>
<li><b>Statistics</b>: repeated-measures ANOVA over the conditions (Greenhouse–Geisser corrected
p when Mauchly's test rejects sphericity, and reported always), Bonferroni-corrected paired
t-tests, and Page's trend test where the paper claims a rising or falling trend. α = {ALPHA}.</li>
<li><b>Checks</b>: each of the paper's qualitative findings is recomputed from these data:
<span class="pass">pass</span> = the data agree, <span class="differs">differs</span> = they do
not.</li>
</ul>"""


def _key_numbers(res: StudyResults, records: Sequence[TrialRecord]) -> str:
    used = {t.source for r in res.study.subject_conditions for t in r.trials}
    rec = next((r for r in records if r.source in used), None)
    design = rec.design if rec is not None else None
    rates = sorted({r.fs_hz for r in records if r.source in used})
    periods = sorted({t.n_periods for r in res.study.subject_conditions for t in r.trials})
    reps = sorted({len(r.repetitions) for r in res.study.subject_conditions})
    wheels = [f["wheel"] for f in res.provenance.get("input_files", []) if f.get("wheel")]
    wheel = wheels[0] if wheels else None
    fit = res.study.options.fit
    rows = [
        ("subjects", "18", str(len(res.subjects))),
        (
            "conditions",
            "6 (RT, BT18, BT12, BT8, BT5, PT)",
            f"{len(res.conditions)} ({', '.join(res.conditions)})",
        ),
        ("measured repetitions per condition", "2", ", ".join(map(str, reps)) or "–"),
    ]
    if design is not None:
        n_bands = len(set(np.asarray(design.band_of_bin).tolist()))
        f = design.frequencies_hz
        rows += [
            ("perturbation period", "45 s", f"{_num(design.period_s)} s"),
            ("double frequency bands", "31", str(n_bands)),
            (
                "excited frequencies",
                "up to 20 Hz, full power ≤ 0.7 Hz",
                f"{_num(f.min())}–{_num(f.max())} Hz, full power ≤ "
                f"{_num(design.spec.full_power_max_hz)} Hz",
            ),
            ("perturbation SD", "2.26 N·m", f"{_num(design.sd_nm)} N·m"),
        ]
    rows += [
        ("analysed periods per trial", "–", ", ".join(map(str, periods)) or "–"),
        ("sample rate", "–", ", ".join(f"{_num(r)} Hz" for r in rates) or "–"),
    ]
    if wheel:
        rows.append(
            (
                "wheel I, b, k (Table 1)",
                "0.3 kg·m², 2 N·m·s/rad, 4.2 N·m/rad",
                f"{_num(wheel.get('inertia_kgm2'))} kg·m², "
                f"{_num(wheel.get('damping_Nms_per_rad'))} N·m·s/rad, "
                f"{_num(wheel.get('stiffness_Nm_per_rad'))} N·m/rad",
            )
        )
    inert = res.inertia_dict()
    if res.lpv is not None:
        excluded = ", ".join(res.lpv.excluded) or "none"
        lpv = f"order-{res.lpv.table.order} polynomials in μ; left out: {excluded}"
    else:
        lpv = f"not built: {res.lpv_error or 'no operating points'}"
    rows += [
        (
            "I_i",
            "held constant (value not given)",
            f"held at {_num(fit.I_i)} kg·m²"
            if fit.inertia == "fixed"
            else (
                "one per subject, shared by its conditions; median "
                f"{_num(inert['median_over_subjects_kgm2'])} kg·m²"
                if fit.inertia == "subject"
                else "fitted per subject × condition"
            ),
        ),
        ("bands left out of the fits", "the two lowest", f"the {fit.n_exclude_low} lowest"),
        (
            "fit weights",
            "coherence × 1/f",
            "1/var(Ĥ): maximum likelihood, noise from the unexcited bins smoothed across frequency"
            if fit.weighting == "inverse_variance"
            else ("coherence" if fit.coherence_weighting else "1")
            + (" × 1/f" if fit.frequency_weighting else ""),
        ),
        ("LPV", "order-2 polynomials in μ; left out: RT", lpv),
    ]
    body = _table(
        ["", "paper", "this study"], [[_prose(a), _prose(b), _prose(c)] for a, b, c in rows]
    )
    return f'<h3 id="numbers">Key numbers: the paper and this study</h3>{body}'


def _inertia_sentence(res: StudyResults) -> str:
    fit = res.study.options.fit
    if fit.inertia == "fixed":
        return f"I_i is held fixed at {_num(fit.I_i)} kg·m², so it has no SEM and is not tested."
    if fit.inertia == "subject":
        return (
            "I_i is estimated from the data: one value per subject, shared by all of that "
            "subject's conditions (a joint fit); it has an SEM but is not tested across "
            "conditions (see Inertia)."
        )
    return "I_i is fitted separately for every subject × condition."


def _weighting_sentence(res: StudyResults) -> str:
    fit = res.study.options.fit
    if fit.weighting == "inverse_variance":
        main = (
            "maximum likelihood in the frequency domain: each band weighted by 1/var(Ĥ), the "
            "noise measured at the unexcited bins and smoothed across frequency (the default)"
        )
    else:
        main = "the paper's weighting, coherence × 1/f"
    other = (
        " The same fits with the other weighting are shown beside them (Two weightings)."
        if res.study.options.compare_weightings
        else ""
    )
    return f"{main}; the {fit.n_exclude_low} lowest bands are left out.{other}"


def _truth_section(res: StudyResults) -> str:
    if not res.simulated_truth:
        return ""
    rows = []
    for cond in res.conditions:
        cells = [
            (r.subject, r.fit)
            for r in res.study.subject_conditions
            if r.condition == cond and r.fit is not None
        ]
        row = [_e(cond)]
        for n in ("I_i", "b_i", "k_i", "b_c", "k_c"):
            est, tru = [], []
            for subject, fit in cells:
                t = res.truth(subject, cond)
                if t and n in t:
                    est.append(getattr(fit.params, n))
                    tru.append(t[n])
            if not est:
                row.append("–")
                continue
            err = 100 * (np.asarray(est) / np.asarray(tru) - 1)
            row.append(
                f"{_num(float(np.median(est)))} / {_num(float(np.median(tru)))} "
                f"({float(np.median(np.abs(err))):.1f} %)"
            )
        rows.append(row)
    header = ["condition", *(_sym(n) for n in ("I_i", "b_i", "k_i", "b_c", "k_c"))]
    return (
        '<h2 id="truth">Recovered parameters and the simulated truth</h2>'
        "<p>This study is simulated: each cell shows the median over subjects of the "
        "estimate / of the simulated subject's true value (median |error| over subjects). "
        "Each trial varies around the subject's value by a few per cent (the simulator's "
        "trial-to-trial spread).</p>" + _table(header, rows)
    )


def _inertia_section(res: StudyResults) -> str:
    d = res.inertia_dict()
    fit = res.study.options.fit
    if fit.inertia == "fixed":
        return (
            '<h2 id="inertia">Inertia</h2>'
            f"<p>I<sub>i</sub> was held at {_num(fit.I_i)} kg·m² (inertia option “fixed”), "
            "not estimated. The default estimates it from the data, one value per subject.</p>"
        )
    if not d["fits"]:
        return (
            '<h2 id="inertia">Inertia</h2><p>I<sub>i</sub> was fitted per subject × condition.</p>'
        )
    rows = []
    for v in d["fits"]:
        name, sens = v["fit"], v["sensitivity"]
        med = {}
        for q in FREE_PARAMETERS:
            vals = [c.get(f"{q}_percent_per_10_percent_I_i") for c in sens]
            vals = [x for x in vals if x is not None and np.isfinite(x)]
            med[q] = f"{float(np.median(vals)):+.1f} %" if vals else "–"
        rel = v["relative_sem"]
        if rel is None:
            rel_txt = "–"
        elif v["poorly_determined"]:
            rel_txt = f'<span class="bad">{100 * rel:.0f} %</span>'
        else:
            rel_txt = f"{100 * rel:.1f} %"
        rows.append(
            [
                _e(name),
                _pm(v["I_i_kgm2"], v["I_i_sem_kgm2"]),
                rel_txt,
                med["k_i"],
                med["b_i"],
                med["k_c"],
                med["b_c"],
            ]
        )
    header = [
        "fit",
        "I<sub>i</sub> ± SEM (kg·m²)",
        "relative SEM",
        "k<sub>i</sub> per +10 % I<sub>i</sub>",
        "b<sub>i</sub>",
        "k<sub>c</sub>",
        "b<sub>c</sub>",
    ]
    return (
        '<h2 id="inertia">Inertia: what the data say about I<sub>i</sub></h2>'
        "<p>The paper holds I<sub>i</sub> constant without giving its value. Here it is "
        "estimated: one value per subject, shared by all of that subject's conditions; the "
        "group fits hold the median of the subjects' values. The sensitivity columns say how "
        "much each parameter would move (median over the conditions) if I<sub>i</sub> were "
        "10 % higher, from the joint fit's covariance: what a wrong fixed inertia would do "
        "to the other estimates. A "
        f"relative SEM above {100 * INERTIA_POORLY_DETERMINED:.0f} % is marked: the data say "
        "little about I<sub>i</sub> there.</p>" + _table(header, rows)
    )


def _weighting_section(res: StudyResults) -> str:
    if not res.study.options.compare_weightings:
        return ""
    wc = res.weighting_comparison()
    main, other = wc["default"], wc["other"]
    rows = []
    free: tuple[str, ...] = ()
    for c in res.study.conditions:
        if c.fit is None or c.fit_compare is None:
            continue
        free = tuple(c.fit.free)
        cells = [r for r in res.study.subject_conditions if r.condition == c.condition]
        vaf_a = [r.vaf_percent for r in cells if r.vaf_percent is not None]
        vaf_b = [r.vaf_compare_percent for r in cells if r.vaf_compare_percent is not None]
        row = [_e(c.condition)]
        for n in c.fit.free:
            a, b = getattr(c.fit.params, n), getattr(c.fit_compare.params, n)
            sa, sb = c.fit.sems.get(n), c.fit_compare.sems.get(n)
            mark = ' class="bad"' if weightings_disagree(a, b, sa, sb) else ""
            row.append(f"<span{mark}>{_pm(a, sa)}<br>{_pm(b, sb)}</span>")
        row += [
            f"{_fixed(c.fit.fit_percent, 1)}<br>{_fixed(c.fit_compare.fit_percent, 1)}",
            f"{_fixed(float(np.median(vaf_a)) if vaf_a else None, 1)}<br>"
            f"{_fixed(float(np.median(vaf_b)) if vaf_b else None, 1)}",
        ]
        rows.append(row)
    header = ["condition", *(_sym(n) for n in free), "group FIT%", "median VAF%"]
    subj = [r for r in wc["cells"] if r["subject"] != "group"]
    dis = [r for r in subj if r["disagree"]]
    listing = ""
    if dis:
        names = "; ".join(
            f"{r['subject']} {r['condition']}: {', '.join(r['disagree'])}" for r in dis
        )
        listing = (
            f"<details><summary>The {len(dis)} subject fits that change</summary>"
            f"<p class='small'>{_prose(names)}</p></details>"
        )
    return (
        '<h2 id="weighting">Two weightings side by side</h2>'
        f"<p>Top line of each cell: the default, {_e(WEIGHTING_NAMES.get(main, main))}; "
        f"bottom: {_e(WEIGHTING_NAMES.get(other, other))}. Group fits per condition, with the "
        "median over subjects of their own VAF. Red: the two differ by more than "
        f"{WEIGHTING_DISAGREEMENT_SEMS:g}× the larger SEM.</p>"
        f"<p>{_weighting_meaning(wc)}</p>" + _table(header, rows) + listing
    )


def _weighting_meaning(wc: dict[str, Any]) -> str:
    """What the subject fits that change with the weighting say: which fit to trust, and why
    a difference beyond the SEMs is expected rather than a sign of unreliable fits."""
    n, k = wc["n_subject_fits"], wc["n_subject_fits_that_change"]
    ml = "the default" if wc["default"] == "inverse_variance" else "the other weighting"
    trust = (
        f"Trust maximum likelihood ({ml}); the paper's weighting is shown to compare with the "
        "paper's method. Why: Steerlab's docs/method-estimator.md, section 1."
    )
    if not k:
        none = "The subject fit does not" if n == 1 else f"None of the {n} subject fits"
        return f"{none} change{'s' if n > 1 else ''} by more than that. {trust}"
    most = ", ".join(f"{_sym(p)} {c}×" for p, c in wc["changed_parameters"].items())
    return (
        f"Of the {n} subject fits, {k} change by more than that on some parameter ({most}; "
        "each of them in results.json, <code>weighting_comparison</code>). This is expected "
        "and does not make the fits unreliable: the two weightings are different estimators "
        "of the same parameters. Maximum likelihood weights each band by its measured noise. "
        "The paper's coherence × 1/f does not: it favours the low bands, where the remnant "
        "dominates, while the contact parameters (b<sub>c</sub>, k<sub>c</sub>) show only at "
        "high frequency, so its estimates scatter more and are biased, most of all the "
        "contact parameters (on Steerlab's simulator: the paper columns of the "
        "estimator-efficiency benchmark, Steerlab's docs/benchmarks.md). " + trust
    )


def _table2(res: StudyResults) -> str:
    if res.lpv is None:
        return (
            '<h2 id="table2">Table 2</h2><p class="bad">No LPV model could be built: '
            f"{_prose(res.lpv_error or 'no operating points')}.</p>"
        )
    order = in_condition_order([r.condition for r in res.lpv.table.rows], res.conditions)
    rows_by = {r.condition: r for r in res.lpv.table.rows}
    header = ["FIT%"] + [_e(c) for c in order]
    rows = [["operating point μ (N)"] + [_fixed(rows_by[c].mu_N, 1) for c in order]]
    rows.append(["LTI"] + [_fixed(rows_by[c].lti_fit_percent, 2) for c in order])
    for m in res.lpv.table.methods:
        rows.append(
            [f"LPV, {_e(method_name(m))}"]
            + [_fixed(rows_by[c].lpv_fit_percent.get(m), 2) for c in order]
        )
    rows.append(
        ['<span class="muted">paper LTI</span>']
        + [
            f'<span class="muted">{_fixed(PAPER_TABLE2.get(c, {}).get("lti"), 1)}</span>'
            for c in order
        ]
    )
    rows.append(
        ['<span class="muted">paper LPV (de Caigny)</span>']
        + [
            f'<span class="muted">{_fixed(PAPER_TABLE2.get(c, {}).get("lpv"), 1)}</span>'
            for c in order
        ]
    )
    t = res.lpv.table
    excluded = "; ".join(f"{k}: {v}" for k, v in t.excluded.items()) or "none"
    return (
        '<h2 id="table2">Table 2: FIT% at the operating points</h2>'
        "<p>FIT% of the local LTI model (the group fit) and of each LPV model at μ, against "
        "the measured group FRF over all bands. "
        f"De Caigny structure: {_e(STRUCTURE_NAMES.get(t.structure or '', t.structure or 'none'))} "
        f"({_prose(t.structure_reason)}). Left out of the LPV model: {_prose(excluded)}.</p>"
        + _table(header, rows)
    )


def _loo_table(res: StudyResults) -> str:
    loo = res.leave_one_out
    if loo is None:
        why = res.lpv.leave_one_out_skipped if res.lpv else res.lpv_error
        return f'<h2 id="loo">Leave-one-out</h2><p>Not computed: {_prose(why)}.</p>'
    vaf = {(v.method, v.condition): v for v in res.loo_vaf}
    by_method = sorted(loo.results, key=lambda r: r.method)
    rows = []
    for r in in_condition_order(by_method, res.conditions, lambda r: r.condition):
        v = vaf.get((r.method, r.condition))
        rows.append(
            [
                _e(r.condition),
                _e(method_name(r.method)),
                _fixed(r.mu_N, 1),
                _fixed(r.fit_vs_measured_percent, 2),
                _fixed(r.in_sample_fit_vs_measured_percent, 2),
                _fixed(r.fit_vs_local_percent, 2),
                _fixed(None if v is None else v.median_vaf_percent, 1),
                _fixed(None if v is None else v.median_in_sample_vaf_percent, 1),
                _e(", ".join(in_condition_order(list(r.trained_on), res.conditions))),
            ]
        )
    ends = "; ".join(f"{k}: {v}" for k, v in loo.not_left_out.items())
    return (
        '<h2 id="loo">Leave-one-out verification</h2>'
        "<p>Each intermediate operating point is left out, the LPV model rebuilt from the "
        "others and evaluated at the left-out μ. FIT% against the measured group FRF (and "
        "against the point's own local model); VAF: the subjects' measured driver torque "
        "drives the predicted model, compared with their measured angle, median over "
        f"subjects. Not left out: {_prose(ends)}.</p>"
        + _table(
            [
                "left out",
                "method",
                "μ (N)",
                "FIT% predicted",
                "FIT% in-sample",
                "FIT% vs local",
                "VAF% predicted",
                "VAF% in-sample",
                "trained on",
            ],
            rows,
            left=2,
        )
    )


def _anova_table(res: StudyResults) -> str:
    rows = []
    # Quantities without an ANOVA are named once per reason above the table, not as rows of
    # dashes that each repeat the same long sentence (on a one-condition study, all of them).
    not_run: dict[str, list[str]] = {}
    for q in res.statistics.values():
        a = q.anova
        if a is None:
            why = "; ".join(q.errors) or "no reason recorded"
            not_run.setdefault(why, []).append(_prose(q.label))
            continue
        sph = a.sphericity
        sig = a.p_gg < ALPHA
        means = ", ".join(
            f"{c} {_num(m)}" for c, m in zip(a.conditions, a.condition_means, strict=True)
        )
        rows.append(
            [
                _prose(q.label),
                _e(q.unit),
                str(a.n_subjects),
                _num(a.F),
                str(a.df1),
                str(a.df2),
                _p(a.p),
                f"{_num(sph.W)} (p {_p(sph.p)})",
                _fixed(a.eps_gg, 3),
                f'<span class="{"sig" if sig else ""}">{_p(a.p_gg)}</span>',
                _fixed(a.partial_eta_squared, 3),
                _p(q.trend.p) if q.trend else "–",
                f'<span class="small">{_e(means)}</span>',
            ]
        )
    head = '<h2 id="anova">Repeated-measures ANOVA over the conditions</h2>'
    missing = "".join(
        (
            f'<p class="bad">Not computed for {", ".join(labels)}: {_prose(why)}.</p>'
            if rows
            else f'<p class="bad">No statistics could be computed: {_prose(why)}.</p>'
        )
        for why, labels in not_run.items()
    )
    if not rows:
        return head + missing
    return (
        head + missing + "<p>One value per subject and condition (repetitions pooled). "
        "p<sub>GG</sub>: Greenhouse–Geisser corrected; bold when &lt; α. Page: one-sided trend "
        f"test for a rise from RT to PT. {_prose(_inertia_sentence(res))}</p>"
        + _table(
            [
                "quantity",
                "unit",
                "n",
                "F",
                "df1",
                "df2",
                "p",
                "Mauchly W (p)",
                "ε<sub>GG</sub>",
                "p<sub>GG</sub>",
                "η²<sub>p</sub>",
                "Page p (rise)",
                "condition means",
            ],
            rows,
            left=2,
        )
    )


def _pairwise_summary(res: StudyResults) -> str:
    """One row per quantity: how many pairs differ, and the pairs that do not (usually the
    shorter list), with their mean difference."""
    rows = []
    for q in res.statistics.values():
        pw = q.pairwise
        if pw is None:
            continue
        comps = list(pw.comparisons)
        sig = [c for c in comps if c.p_corrected < pw.alpha]
        ns = [c for c in comps if not c.p_corrected < pw.alpha]
        if not ns:
            ns_txt = "none"
        elif not sig:
            ns_txt = f"all {len(comps)}"
        else:
            ns_txt = "; ".join(
                f"{_e(c.a)}–{_e(c.b)} ({_num(c.mean_difference)} {_e(q.unit)}, "
                f"p = {_p(c.p_corrected)})"
                for c in ns
            )
        rows.append(
            [
                _prose(q.label),
                str(pw.n_subjects),
                f"{len(sig)} of {len(comps)}",
                ns_txt,
            ]
        )
    if not rows:
        return (
            '<h2 id="pairwise">Pairwise comparisons</h2><p>Not computed (why: under the '
            'RM-ANOVA, <a href="#anova">above</a>).</p>'
        )
    return (
        '<h2 id="pairwise">Pairwise comparisons (paired t-tests, Bonferroni)</h2>'
        f"<p>Pairs of conditions whose difference is significant (Bonferroni-corrected "
        f"p &lt; {ALPHA}), and the pairs that are not, with their mean difference (first "
        'minus second). Every p and difference: <a href="#pairwise-matrices">the full '
        "matrices</a> at the end.</p>"
        + _table(["quantity", "n", "pairs that differ", "pairs that do not differ"], rows, left=1)
    )


def _pairwise_matrices(res: StudyResults) -> str:
    out = []
    for q in res.statistics.values():
        pw = q.pairwise
        if pw is None:
            continue
        conds = [str(c) for c in pw.conditions]
        rows = []
        for a in conds:
            row = [f"<b>{_e(a)}</b>"]
            for b in conds:
                if a == b:
                    row.append("")
                    continue
                c = pw.get(a, b)
                if conds.index(a) < conds.index(b):
                    sig = c.p_corrected < pw.alpha
                    row.append(f'<span class="{"sig" if sig else ""}">{_p(c.p_corrected)}</span>')
                else:
                    row.append(f'<span class="muted">{_num(c.mean_difference)}</span>')
            rows.append(row)
        out.append(f"<h3>{_prose(q.label)} ({_e(q.unit)}), n = {pw.n_subjects}</h3>")
        out.append(_table([""] + [_e(c) for c in conds], rows))
    if not out:
        return ""
    return (
        f'<details id="pairwise-matrices"><summary>Full pairwise matrices ({len(out) // 2} '
        "quantities)</summary><p>Above the diagonal: Bonferroni-corrected p (bold when &lt; "
        "α). Below: mean difference row − column, in the quantity's unit.</p>"
        + "\n".join(out)
        + "</details>"
    )


def _reason_kind(reason: str) -> str:
    for kind in (
        "familiarization",
        "aborted",
        "incomplete",
        "superseded",
        "duplicate",
        "not analysable",
    ):
        if reason.startswith(kind):
            return kind
    return reason.split(":")[0]


def _trial_rows(items: Sequence[Any]) -> list[list[str]]:
    return [
        [
            f"<code>{_e(s.label)}</code>",
            _prose(s.reason),
            f'<code class="small">{_e(s.source)}</code>',
        ]
        for s in items
    ]


def _skipped_section(res: StudyResults) -> str:
    """Trials left out for a reason; familiarization trials are not among them."""
    skipped = [s for s in res.study.skipped if _reason_kind(s.reason) != "familiarization"]
    if not skipped:
        return '<h2 id="skipped">Skipped trials</h2><p>None: every measured trial was analysed.</p>'
    counts = Counter(_reason_kind(s.reason) for s in skipped)
    summary = ", ".join(f"{k}: {n}" for k, n in counts.most_common())
    return f'<h2 id="skipped">Skipped trials ({len(skipped)})</h2><p>{_e(summary)}.</p>' + _table(
        ["trial", "reason", "source"], _trial_rows(skipped), left=3
    )


def _familiarization_section(res: StudyResults) -> str:
    fam = [s for s in res.study.skipped if _reason_kind(s.reason) == "familiarization"]
    if not fam:
        return ""
    return (
        f'<h2 id="familiarization">Familiarization trials ({len(fam)}), not analysed by '
        "design</h2><p>Each condition starts with a familiarization trial (the paper's "
        "protocol); only the measured repetitions after it are analysed.</p>"
        f"<details><summary>The {len(fam)} familiarization trials</summary>"
        + _table(["trial", "reason", "source"], _trial_rows(fam), left=3)
        + "</details>"
    )


def _notes_section(res: StudyResults) -> str:
    notes = list(res.study.notes)
    at_bound = res.estimates_at_bound()
    if at_bound:
        notes.append(
            "estimates at the edge of the fit's search box (not determined by the data, "
            f"whatever their SEM): {'; '.join(at_bound)}"
        )
    if res.left_out_of_statistics:
        notes.append(
            "estimates left out of the statistics (at a search bound, or SEM ≥ value): "
            + "; ".join(res.left_out_of_statistics)
        )
    if res.lpv_error:
        notes.append(f"LPV model not built: {res.lpv_error}")
    for q in res.statistics.values():
        notes += [f"{q.label}: {e}" for e in q.errors]
    if not notes:
        return ""
    items = "".join(f"<li>{_prose(n)}</li>" for n in notes)
    return f'<h2 id="notes">Notes</h2><ul>{items}</ul>'


def _provenance_section(res: StudyResults) -> str:
    prov = res.provenance
    sw = ", ".join(f"{k} {v}" for k, v in prov.get("software", {}).items())
    files = [
        [
            _e(Path(f["path"]).name),
            _e(f["subject"]),
            str(f["n_trials"]),
            _fixed(f["size_bytes"] / 1e6, 1),
            _e(f.get("created_utc") or "–"),
            _e(f.get("modified_utc") or "–"),
            _e(f.get("written_by_software_version") or "–"),
            "yes" if f.get("simulated") else "no",
        ]
        for f in prov.get("input_files", [])
    ]
    timings = ", ".join(
        f"{TIMING_NAMES.get(k, k.replace('_', ' '))}: {_seconds(v)}"
        for k, v in res.timings_s.items()
    )
    return (
        '<h2 id="provenance">Provenance</h2>'
        f"<p>Generated {_e(prov.get('generated_utc'))} from "
        f"<code>{_e(prov.get('session_dir'))}</code>. Software: {_e(sw)}. "
        f"Analysis time: {_e(timings)}. Every number is in <code>{RESULTS_JSON}</code> "
        f"(keys documented in Steerlab's docs/results.md); per-subject values also in "
        f"<code>{PER_SUBJECT_CSV}</code>.</p>"
        + _table(
            [
                "file",
                "subject",
                "trials",
                "MB",
                "created (UTC)",
                "modified (UTC)",
                "written by",
                "simulated",
            ],
            files,
            left=2,
        )
        + "<p class='small muted'>Method: Pronker, Abbink, van Paassen &amp; Mulder (2017), "
        "Estimating driver time-varying neuromuscular admittance through LPV model and grip "
        "force, IFAC-PapersOnLine 50(1), 14916–14921, doi 10.1016/j.ifacol.2017.08.2539.</p>"
    )


__all__ = [
    "CSV_COLUMNS",
    "FIGURES",
    "REPORT_FILES",
    "STAT_QUANTITIES",
    "ReportError",
    "ReportResult",
    "html_page",
    "per_subject_rows",
    "render_figures",
    "write_per_subject_csv",
    "write_report",
]
