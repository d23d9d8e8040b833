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
import shutil
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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
        + "".join(f" {_e(n)}." for n in t.get("notes", []))
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
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;max-width:1100px;
margin:1.5em auto;padding:0 1em;color:#222;line-height:1.45}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:2px solid #ddd;padding-bottom:.2em;
margin-top:1.8em}h3{margin-bottom:.3em}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .5em;text-align:right;vertical-align:top}
th{background:#f3f3f3}td.l,th.l{text-align:left}
.pass{background:#dff3df;color:#135e13;font-weight:600}
.differs{background:#fbe3d6;color:#8a3300;font-weight:600}
.na{background:#eee;color:#555}
.sig{font-weight:700}.muted{color:#777}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #eee}
figcaption{font-size:.9em;color:#444}
.small{font-size:.85em}code{background:#f5f5f5;padding:0 .2em}
.warn{background:#fff4d6;border:1px solid #e0b040;padding:.4em 1em;margin:1em 0}
.bad{color:#b00020;font-weight:600}
"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _num(v: Any, sig: int = 3) -> str:
    """``sig`` significant digits, fixed-point between 1e-3 and 1e5, trailing zeros kept."""
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
    if abs(x) >= 1e5 or abs(x) < 1e-3:
        return f"{x:.{sig - 1}e}"
    decimals = max(sig - 1 - int(np.floor(np.log10(abs(x)))), 0)
    return f"{x:.{decimals}f}"


def _fixed(v: Any, decimals: int) -> str:
    """A fixed number of decimals (percentages, forces): columns line up."""
    if v is None:
        return "–"
    x = float(v)
    return f"{x:.{decimals}f}" if np.isfinite(x) else "–"


def _p(p: float | None) -> str:
    if p is None or not np.isfinite(p):
        return "–"
    return f"{p:.1e}" if p < 0.001 else f"{p:.3f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], left: int = 1) -> str:
    """Cells are HTML already; the first ``left`` columns are left-aligned."""
    th = "".join(f'<th class="{"l" if i < left else ""}">{h}</th>' for i, h in enumerate(header))
    body = "".join(
        "<tr>"
        + "".join(f'<td class="{"l" if i < left else ""}">{c}</td>' for i, c in enumerate(r))
        + "</tr>"
        for r in rows
    )
    return f"<table><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>"


def _figure(images: dict[str, str | None], name: str, caption: str) -> str:
    uri = images.get(name)
    if uri is None:
        return ""
    return (
        f'<figure id="fig-{name}"><img alt="{_e(name)}" src="{uri}">'
        f"<figcaption>{caption}</figcaption></figure>"
    )


def html_page(
    res: StudyResults,
    images: dict[str, str | None],
    records: Sequence[TrialRecord],
    extra_sections: Sequence[str] = (),
) -> str:
    """The report page; ``images`` from :func:`render_figures` (empty: no figures);
    ``extra_sections``: HTML sections placed before the skipped trials (the tracking section
    of a study with time-varying trials)."""
    prov = res.provenance
    n_ok = sum(c.passed is True for c in res.checks)
    n_diff = sum(c.passed is False for c in res.checks)
    n_trials = sum(len(r.trials) for r in res.study.subject_conditions)
    title = f"Steerlab report: {Path(prov.get('session_dir') or 'study').name}"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{_e(title)}</h1>",
        f'<p class="muted">Generated {_e(prov.get("generated_utc", ""))} by Steerlab '
        f"{_e(prov.get('software', {}).get('steerlab', ''))}. {len(res.subjects)} subjects, "
        f"{len(res.conditions)} conditions, {n_trials} trials analysed, "
        f"{len(res.study.skipped)} trials skipped. "
        f"The paper's findings: {n_ok} agree, {n_diff} differ, "
        f"{len(res.checks) - n_ok - n_diff} not computed.</p>",
        f'<p class="muted">{_e(wheel_used_sentence(prov.get("input_files", [])))}</p>',
        _timing_line(prov.get("recording_timing") or {}),
        _warnings(res),
        _contents(images),
        _how_to_read(res),
        _key_numbers(res, records),
        _checks_section(res),
        "<h2 id='figures'>Figures</h2>",
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
            "from the measured noise of Ĥ, see docs/method-estimator.md); black: the group "
            "fit ± SEM; red ×: estimates the data do not determine (at a search bound or "
            "SEM ≥ value), counted and left out of boxes and statistics. Last panel: I_i, one "
            "per subject (joint fit over its conditions).",
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
        _condition_table(res),
        _truth_section(res),
        _inertia_section(res),
        _weighting_section(res),
        _table2(res),
        _loo_table(res),
        _anova_table(res),
        _pairwise_tables(res),
        *extra_sections,
        _skipped_section(res),
        _notes_section(res),
        _provenance_section(res),
        "</body></html>",
    ]
    return "\n".join(p for p in parts if p)


def _contents(images: dict[str, str | None]) -> str:
    items = [
        ("checks", "The paper's findings, checked"),
        ("how", "How to read this"),
        ("numbers", "Key numbers"),
    ]
    if any(v is not None for v in images.values()):
        items.append(("figures", "Figures"))
    items += [
        ("conditions", "Per condition"),
        ("inertia", "Inertia"),
        ("weighting", "Two weightings"),
        ("table2", "Table 2"),
        ("loo", "Leave-one-out"),
        ("anova", "RM-ANOVA"),
        ("pairwise", "Pairwise tests"),
        ("skipped", "Skipped trials"),
        ("provenance", "Provenance"),
    ]
    links = " · ".join(f'<a href="#{a}">{_e(t)}</a>' for a, t in items)
    return f'<p class="small">{links}</p>'


def _how_to_read(res: StudyResults) -> str:
    pct = round(100 * res.study.options.confidence)
    return f"""<h2 id="how">How to read this</h2>
<ul>
<li><b>Admittance</b> H = θ/T<sub>d</sub> (rad/N·m): how far the wheel turns per N·m of torque
on the hands. High = relaxed arms, low = stiff arms. It is estimated from the closed loop with the
perturbation torque as instrument, per double frequency band.</li>
<li><b>Arm model</b>: contact (b<sub>c</sub>, k<sub>c</sub>) in series with the intrinsic arm
(I<sub>i</sub>, b<sub>i</sub>, k<sub>i</sub>). {_e(_inertia_sentence(res))}
<b>SEM</b> = standard error of an estimate (Cramér–Rao bound of the fit actually used);
{pct} % intervals on FRFs are across subjects.</li>
<li><b>Fit</b>: {_e(_weighting_sentence(res))}</li>
<li><b>VAF</b> (time domain) and <b>FIT%</b> (frequency domain, 1/f-weighted): 100 % is a perfect
model. VAF uses the measured driver torque as the model's input.</li>
<li><b>μ</b>: the median over subjects of their mean total grip force in a condition; the LPV
model's scheduling variable. RT is left out of the LPV model, as in the paper.</li>
<li><b>Statistics</b>: repeated-measures ANOVA over the conditions (Greenhouse–Geisser corrected
p when Mauchly's test rejects sphericity, and reported always), Bonferroni-corrected paired
t-tests, and Page's trend test where the paper claims a rising or falling trend. α = {ALPHA}.</li>
<li><b>Checks</b>: each of the paper's qualitative findings is recomputed from these data:
<span class="pass">pass</span> = the data agree, <span class="differs">differs</span> = they do
not. A "differs" is a finding about these data, not necessarily an error.</li>
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
        (
            "LPV",
            "order-2 polynomials in μ; RT left out",
            f"order {res.lpv.table.order if res.lpv else '–'}; "
            f"{', '.join(res.lpv.excluded) if res.lpv else '–'} left out",
        ),
    ]
    body = _table(["", "paper", "this study"], [[_e(a), _e(b), _e(c)] for a, b, c in rows])
    return f'<h2 id="numbers">Key numbers of the method</h2>{body}'


def _check_values(values: dict[str, Any]) -> str:
    parts = []
    for k, v in values.items():
        if isinstance(v, dict):
            inner = ", ".join(
                f"{_e(a)}: {_num(b) if not isinstance(b, dict) else _e(_short(b))}"
                for a, b in v.items()
            )
            parts.append(f"{_e(k)}: {{{inner}}}")
        elif isinstance(v, list):
            parts.append(f"{_e(k)}: {_e(', '.join(map(str, v))) or 'none'}")
        elif (k == "p" or k.startswith("p_")) and isinstance(v, float):
            parts.append(f"{_e(k)} = {_p(v)}")
        else:
            parts.append(f"{_e(k)} = {_num(v)}")
    return "; ".join(parts)


def _short(d: dict) -> str:
    return ", ".join(f"{a} {_num(b)}" for a, b in d.items())


def _checks_section(res: StudyResults) -> str:
    cls = {"pass": "pass", "differs": "differs", "not computed": "na"}
    rows = [
        [
            f'<span class="{cls[c.status]}">{_e(c.status)}</span>',
            _e(c.paper),
            _e(c.test),
            f'<span class="small">{_check_values(c.values)}</span>'
            + (f'<br><span class="muted small">{_e(c.note)}</span>' if c.note else ""),
        ]
        for c in res.checks
    ]
    return (
        '<h2 id="checks">The paper\'s findings, checked on these data</h2>'
        "<p>Each row restates one finding of Pronker et al. (2017) and decides it from this "
        "study's numbers with the test shown; nothing here is copied from the paper.</p>"
        + _table(["result", "paper", "test", "values"], rows, left=4)
    )


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


def _warnings(res: StudyResults) -> str:
    items = res.warnings()
    if not items:
        return ""
    lis = "".join(f"<li>{_e(w)}</li>" for w in items)
    return f'<div class="warn"><b>Read this first</b><ul>{lis}</ul></div>'


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
    header = ["condition", "I_i", "b_i", "k_i", "b_c", "k_c"]
    return (
        '<h2 id="truth">Recovered parameters and the simulated truth</h2>'
        "<p>This study is simulated: each cell shows the median over subjects of the "
        "estimate / of the simulated subject's true value (median |error| over subjects). "
        "Each trial varies around the subject's value by a few per cent "
        "(PopulationSpread.trial_cv).</p>" + _table(header, rows)
    )


def _inertia_section(res: StudyResults) -> str:
    d = res.inertia_dict()
    fit = res.study.options.fit
    if fit.inertia == "fixed":
        return (
            '<h2 id="inertia">Inertia</h2>'
            f"<p>I_i was held at {_num(fit.I_i)} kg·m² (--inertia fixed), not estimated. The "
            "default estimates it from the data, one value per subject.</p>"
        )
    if not d["fits"]:
        return '<h2 id="inertia">Inertia</h2><p>I_i was fitted per subject × condition.</p>'
    rows = []
    for v in d["fits"]:
        name, sens = v["fit"], v["sensitivity"]
        med = {}
        for q in ("k_i", "b_i", "k_c", "b_c"):
            vals = [c.get(f"{q}_percent_per_10_percent_I_i") for c in sens]
            vals = [x for x in vals if x is not None and np.isfinite(x)]
            med[q] = f"{float(np.median(vals)):+.1f} %" if vals else "–"
        rel = v["relative_sem"]
        rows.append(
            [
                _e(name),
                f"{_num(v['I_i_kgm2'])} ± {_num(v['I_i_sem_kgm2'])}",
                (
                    f'<span class="bad">{100 * rel:.0f} %</span>'
                    if v["poorly_determined"]
                    else f"{100 * rel:.1f} %"
                )
                if rel is not None
                else "–",  # fmt: skip
                med["k_i"],
                med["b_i"],
                med["k_c"],
                med["b_c"],
            ]
        )
    header = [
        "fit",
        "I_i ± SEM (kg·m²)",
        "relative SEM",
        "k_i per +10 % I_i",
        "b_i",
        "k_c",
        "b_c",
    ]
    return (
        '<h2 id="inertia">Inertia: what the data say about I_i</h2>'
        "<p>The paper holds I_i constant without giving its value. Here it is estimated: "
        "one value per subject, shared by all of that subject's conditions (and one for the "
        "group fits). The sensitivity columns say how much each parameter would move (median "
        "over the conditions) if I_i were 10 % higher, from the joint fit's covariance: "
        "what a wrong fixed inertia would do to the other estimates. A relative SEM above "
        f"{100 * INERTIA_POORLY_DETERMINED:.0f} % is marked: the data say little about I_i "
        "there.</p>" + _table(header, rows)
    )


def _weighting_section(res: StudyResults) -> str:
    if not res.study.options.compare_weightings:
        return ""
    wc = res.weighting_comparison()
    main, other = wc["default"], wc["other"]
    rows = []
    for c in res.study.conditions:
        if c.fit is None or c.fit_compare is None:
            continue
        cells = [r for r in res.study.subject_conditions if r.condition == c.condition]
        vaf_a = [r.vaf_percent for r in cells if r.vaf_percent is not None]
        vaf_b = [r.vaf_compare_percent for r in cells if r.vaf_compare_percent is not None]
        row = [_e(c.condition)]
        for n in c.fit.free:
            a, b = getattr(c.fit.params, n), getattr(c.fit_compare.params, n)
            sa, sb = c.fit.sems.get(n), c.fit_compare.sems.get(n)
            mark = ' class="bad"' if weightings_disagree(a, b, sa, sb) else ""
            row.append(f"<span{mark}>{_num(a)} ± {_num(sa)}<br>{_num(b)} ± {_num(sb)}</span>")
        row += [
            f"{_fixed(c.fit.fit_percent, 1)}<br>{_fixed(c.fit_compare.fit_percent, 1)}",
            f"{_fixed(float(np.median(vaf_a)) if vaf_a else None, 1)}<br>"
            f"{_fixed(float(np.median(vaf_b)) if vaf_b else None, 1)}",
        ]
        rows.append(row)
    free = res.study.conditions[0].fit.free if res.study.conditions and res.study.conditions[
        0].fit else ()  # fmt: skip
    header = ["condition", *free, "group FIT%", "median VAF%"]
    n_dis = sum(bool(r["disagree"]) for r in wc["cells"])
    return (
        '<h2 id="weighting">Two weightings side by side</h2>'
        f"<p>Top line of each cell: the default ({_e(main)}); bottom: {_e(other)}. Group fits "
        "per condition, with the median over subjects of their own VAF. Red: the two differ by "
        f"more than {WEIGHTING_DISAGREEMENT_SEMS:g}× the larger SEM. Over the subject fits, "
        f"{n_dis} of {len(wc['cells'])} cells disagree somewhere (results.json, "
        "<code>weighting_comparison</code>). Why the default is maximum likelihood: "
        "docs/method-estimator.md.</p>" + _table(header, rows)
    )


def _condition_table(res: StudyResults) -> str:
    rows = []
    for c in res.study.conditions:
        cells = [r for r in res.study.subject_conditions if r.condition == c.condition]
        vaf = [r.vaf_percent for r in cells if r.vaf_percent is not None]
        fitp = [r.fit_percent for r in cells if r.fit_percent is not None]
        row = [
            _e(c.condition),
            str(len(c.subjects)),
            _fixed(c.grip_median_of_means_N, 1),
            _fixed(float(np.nanmean(c.grip_subject_means_N)), 1),
            _fixed(float(np.nanmean(c.grip_subject_sds_N)), 2),
        ]
        for n in ("b_i", "k_i", "b_c", "k_c"):
            if c.fit is None:
                row.append("–")
            else:
                row.append(f"{_num(getattr(c.fit.params, n))} ± {_num(c.fit.sems.get(n))}")
        row += [
            _fixed(None if c.fit is None else c.fit.fit_percent, 2),
            _fixed(float(np.median(vaf)) if vaf else None, 1),
            _fixed(float(np.median(fitp)) if fitp else None, 1),
        ]
        rows.append(row)
    header = [
        "condition",
        "n",
        "μ (N)",
        "mean grip (N)",
        "mean grip SD (N)",
        "b_i ± SEM",
        "k_i ± SEM",
        "b_c ± SEM",
        "k_c ± SEM",
        "group FIT%",
        "median VAF%",
        "median FIT%",
    ]
    return (
        '<h2 id="conditions">Per condition</h2>'
        "<p>Group fit: the arm model fitted to the mean over subjects of their FRFs (SEM from "
        "the spread between subjects). Medians: over the subjects' own fits. Units: b in "
        "N·m·s/rad, k in N·m/rad.</p>" + _table(header, rows)
    )


def _table2(res: StudyResults) -> str:
    if res.lpv is None:
        return f'<h2 id="table2">Table 2</h2><p>No LPV model: {_e(res.lpv_error)}</p>'
    paper_order = ("PT", "BT5", "BT8", "BT12", "BT18", "RT")
    order: list[str] = [c for c in paper_order if c in res.conditions]
    order += [c for c in res.conditions if c not in order]
    rows_by = {r.condition: r for r in res.lpv.table.rows}
    header = ["FIT%"] + [_e(c) for c in order]
    rows = [["operating point μ (N)"] + [_fixed(rows_by[c].mu_N, 1) for c in order]]
    rows.append(["LTI"] + [_fixed(rows_by[c].lti_fit_percent, 2) for c in order])
    for m in res.lpv.table.methods:
        rows.append(
            [f"LPV, {_e(m)}"] + [_fixed(rows_by[c].lpv_fit_percent.get(m), 2) for c in order]
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
    return (
        '<h2 id="table2">Table 2: FIT% at the operating points</h2>'
        "<p>FIT% of the local LTI model (the group fit) and of each LPV model at μ, against "
        "the measured group FRF over all bands. "
        f"De Caigny structure: {_e(t.structure)} ({_e(t.structure_reason)}). "
        f"Excluded: {_e('; '.join(f'{k}: {v}' for k, v in t.excluded.items()) or 'none')}.</p>"
        + _table(header, rows)
    )


def _loo_table(res: StudyResults) -> str:
    loo = res.leave_one_out
    if loo is None:
        why = res.lpv.leave_one_out_skipped if res.lpv else res.lpv_error
        return f'<h2 id="loo">Leave-one-out</h2><p>Not computed: {_e(why)}</p>'
    vaf = {(v.method, v.condition): v for v in res.loo_vaf}
    rows = []
    for r in loo.results:
        v = vaf.get((r.method, r.condition))
        rows.append(
            [
                _e(r.condition),
                _e(r.method),
                _fixed(r.mu_N, 1),
                _fixed(r.fit_vs_measured_percent, 2),
                _fixed(r.in_sample_fit_vs_measured_percent, 2),
                _fixed(r.fit_vs_local_percent, 2),
                _fixed(None if v is None else v.median_vaf_percent, 1),
                _fixed(None if v is None else v.median_in_sample_vaf_percent, 1),
                _e(", ".join(r.trained_on)),
            ]
        )
    ends = "; ".join(f"{k}: {v}" for k, v in loo.not_left_out.items())
    return (
        '<h2 id="loo">Leave-one-out verification</h2>'
        "<p>Each intermediate operating point is left out, the LPV model rebuilt from the "
        "others and evaluated at the left-out μ. FIT% against the measured group FRF (and "
        "against the point's own local model); VAF: the subjects' measured driver torque "
        "drives the predicted model, compared with their measured angle, median over "
        f"subjects. Not left out: {_e(ends)}.</p>"
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
    for q in res.statistics.values():
        a = q.anova
        if a is None:
            rows.append([_e(q.label), _e(q.unit)] + ["–"] * 10 + [_e("; ".join(q.errors))])
            continue
        sph = a.sphericity
        sig = a.p_gg < ALPHA
        means = ", ".join(
            f"{c} {_num(m)}" for c, m in zip(a.conditions, a.condition_means, strict=True)
        )
        rows.append(
            [
                _e(q.label),
                _e(q.unit),
                str(a.n_subjects),
                _fixed(a.F, 2),
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
    return (
        '<h2 id="anova">Repeated-measures ANOVA over the conditions</h2>'
        "<p>One value per subject and condition (repetitions pooled). p<sub>GG</sub>: "
        "Greenhouse–Geisser corrected; bold when &lt; α. Page: one-sided trend test for a "
        "rise from RT to PT. I<sub>i</sub> is fixed in every fit and not tested.</p>"
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
                "ε_GG",
                "p_GG",
                "η²p",
                "Page p (rise)",
                "condition means",
            ],
            rows,
            left=2,
        )
    )


def _pairwise_tables(res: StudyResults) -> str:
    out = [
        '<h2 id="pairwise">Pairwise comparisons (paired t-tests, Bonferroni)</h2>'
        "<p>Above the diagonal: Bonferroni-corrected p (bold when &lt; α). Below: mean "
        "difference row − column, in the quantity's unit.</p>"
    ]
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
        out.append(f"<h3>{_e(q.label)} ({_e(q.unit)}), n = {pw.n_subjects}</h3>")
        out.append(_table([""] + [_e(c) for c in conds], rows))
    return "\n".join(out)


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


def _skipped_section(res: StudyResults) -> str:
    skipped = res.study.skipped
    if not skipped:
        return '<h2 id="skipped">Skipped trials</h2><p>None.</p>'
    counts = Counter(_reason_kind(s.reason) for s in skipped)
    summary = ", ".join(f"{k}: {n}" for k, n in counts.most_common())
    routine = [s for s in skipped if _reason_kind(s.reason) == "familiarization"]
    other = [s for s in skipped if _reason_kind(s.reason) != "familiarization"]

    def rows(items):
        return [
            [_e(s.label), _e(s.reason), f'<span class="small">{_e(s.source)}</span>'] for s in items
        ]

    parts = [f'<h2 id="skipped">Skipped trials ({len(skipped)})</h2><p>{_e(summary)}.</p>']
    if other:
        parts.append(_table(["trial", "reason", "source"], rows(other), left=3))
    if routine:
        parts.append(
            f"<details><summary>{len(routine)} familiarization trials (never analysed, by "
            "design)</summary>"
            + _table(["trial", "reason", "source"], rows(routine), left=3)
            + "</details>"
        )
    return "\n".join(parts)


def _notes_section(res: StudyResults) -> str:
    notes = list(res.study.notes)
    at_bound = res.estimates_at_bound()
    if at_bound:
        notes.append(
            "estimates at the edge of the fit's search box (not determined by the data, "
            f"whatever their SEM): {'; '.join(at_bound)}"
        )
    if res.lpv_error:
        notes.append(f"LPV: {res.lpv_error}")
    for q in res.statistics.values():
        notes += [f"{q.label}: {e}" for e in q.errors]
    if not notes:
        return ""
    items = "".join(f"<li>{_e(n)}</li>" for n in notes)
    return f"<h2>Notes</h2><ul>{items}</ul>"


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
    timings = ", ".join(f"{k} {v:.2f} s" for k, v in res.timings_s.items())
    return (
        '<h2 id="provenance">Provenance</h2>'
        f"<p>Generated {_e(prov.get('generated_utc'))} from "
        f"<code>{_e(prov.get('session_dir'))}</code>. Software: {_e(sw)}. "
        f"Analysis timings: {_e(timings)}. Every number is in <code>{RESULTS_JSON}</code> "
        f"(keys documented in docs/results.md); per-subject values also in "
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
