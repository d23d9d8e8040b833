"""``steerlab report`` on the full 18-subject default study: how long does it take?

Goals (issue "Analysis … the report"): the analysis without figures under 5 s, the whole report
(figures and page included) under 30 s, on the 2-core development machine.

"Analysis" is ``write_report(..., figures=False)`` from the session files to the three written
files: reading the HDF5 files, per-trial spectra, 108 subject fits and 6 group fits, VAF, LPV
with leave-one-out, statistics, results.json, per_subject.csv and the figure-less page. Its
stages are reported too, so a miss can be traced (``stages_s``); ``analysis_without_read_s``
leaves out the reading of the files, which depends on the disk and the page cache more than on
Steerlab.

Usage: ``python -m benchmarks report [--study DIR] [--jobs N] [--repeat N]``. Without
``--study`` the default study (18 subjects, seed 0, the paper's protocol at 1 kHz) is simulated
into a temporary directory first (about 30 s, 800 MB; not timed).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from steerlab.benchmarks.machine import machine, peak_rss_mb

GOAL_ANALYSIS_S = 5.0
GOAL_REPORT_S = 30.0


def _timed_report(study: Path, out: Path, *, jobs: int, figures: bool) -> tuple[float, dict]:
    from steerlab.analysis.report import write_report

    t0 = time.perf_counter()
    res = write_report(study, out, jobs=jobs, figures=figures)
    return time.perf_counter() - t0, res.timings_s


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks report")
    ap.add_argument("--study", help="directory of session files (default: simulate 18 subjects)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes for the trials")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each; the fastest counts")
    ap.add_argument("--keep", help="leave the last whole report here")
    a = ap.parse_args(argv)

    # Imports and matplotlib's font cache are start-up costs, not the report's: pay them first.
    import steerlab.analysis.figures  # noqa: F401
    import steerlab.analysis.report  # noqa: F401

    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        tmpd = Path(tmp)
        if a.study:
            study = Path(a.study)
            simulated_here = False
        else:
            from steerlab.app.simulate import simulate_study

            study = tmpd / "study"
            simulate_study(18, study, seed=0, jobs=2)
            simulated_here = True
        n_files = len(list(study.glob("*.h5")))
        size_mb = sum(p.stat().st_size for p in study.glob("*.h5")) / 2**20

        runs_analysis, runs_report = [], []
        for i in range(a.repeat):
            runs_analysis.append(_timed_report(study, tmpd / f"a{i}", jobs=a.jobs, figures=False))
            out = Path(a.keep) if (a.keep and i == a.repeat - 1) else tmpd / f"r{i}"
            runs_report.append(_timed_report(study, out, jobs=a.jobs, figures=True))
    analysis_s, stages = min(runs_analysis, key=lambda r: r[0])
    report_s, report_stages = min(runs_report, key=lambda r: r[0])
    without_read = analysis_s - stages.get("read_files", 0.0)
    return {
        "study": str(study) if not simulated_here else "simulated: 18 subjects, seed 0, 1 kHz",
        "session_files": n_files,
        "study_mb": round(size_mb, 1),
        "jobs": a.jobs,
        "repeat": a.repeat,
        "analysis_s": round(analysis_s, 2),
        "analysis_without_read_s": round(without_read, 2),
        "stages_s": {k: round(v, 2) for k, v in stages.items()},
        "report_s": round(report_s, 2),
        "report_stages_s": {k: round(v, 2) for k, v in report_stages.items()},
        "goal_analysis_s": GOAL_ANALYSIS_S,
        "goal_analysis_met": analysis_s < GOAL_ANALYSIS_S,
        "goal_analysis_without_read_met": without_read < GOAL_ANALYSIS_S,
        "goal_report_s": GOAL_REPORT_S,
        "goal_report_met": report_s < GOAL_REPORT_S,
        "load_average_before": [round(x, 2) for x in load_before],
        **peak_rss_mb(),
        "machine": machine(),
    }
