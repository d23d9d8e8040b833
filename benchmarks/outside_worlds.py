"""``python -m benchmarks outside_worlds [--root DIR] [--jobs N] [--conventions [SEEDS]]``: the
diagnosis on studies it did not generate, recorded with conventions it did not choose.

- The studies of another lab's system (``shared/data/outside-worlds``: a null study and hidden
  mechanisms, each with its ``truth.json``), imported through the interchange format as a
  user would (``steerlab import``), then ``steerlab diagnose`` with ``--jobs N`` (default: the
  command's own, a worker per core, at most 4). The truth is read only to score.
- ``--conventions``: null studies of the team's independent world (``benchmarks/otherworld``)
  under each recording convention of ``CONVENTIONS``, SEEDS of them each (default 3).
- ``--report``: ``steerlab report`` on each outside study and on a 2-subject × BT18, BT8, PT
  study of the independent world under each convention; the median relative error of every arm
  parameter against the truth (goals: k_i 5 %, k_c 10 %, b_i and b_c 15 %).

Per study: the expected and the named cause, the wall seconds of the diagnosis and the
convention taken from the data. Summary: correct names, false alarms, largest wall seconds.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from steerlab.analysis.diagnosis import run_diagnosis
from steerlab.benchmarks.otherworld import CONVENTIONS, generate_study, recovery
from steerlab.protocols.interchange import import_study

DEFAULT_ROOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "outside-worlds"
SMALL: dict[str, Any] = dict(
    subjects=1, conditions=("BT8", "PT"), fs_hz=250.0, n_periods=1, run_in_s=(3.0, 6.0)
)


def _diagnose(sessions: Path, jobs: int) -> dict:
    t0 = time.perf_counter()
    res = run_diagnosis(sessions, None, jobs=jobs)
    return {
        "cause": res.cause,
        "causes": res.causes,
        "wall_s": round(time.perf_counter() - t0, 1),
        "convention": res.rig_from_data.get("convention", {}).get("sentence"),
    }


def outside(root: Path, jobs: int, work: Path) -> list[dict]:
    rows = []
    for case in sorted(p for p in root.iterdir() if (p / "trials").is_dir()):
        truth = json.loads((case / "truth.json").read_text())
        kind = truth["case"]
        expected = "none" if kind == "null" else kind.split(":", 1)[1]
        sessions = work / case.name
        import_study(case / "trials", sessions)
        rows.append({"study": case.name, "expected": expected, **_diagnose(sessions, jobs)})
    return rows


def conventions(seeds: int, jobs: int, work: Path) -> list[dict]:
    rows = []
    for name, options in sorted(CONVENTIONS.items()):
        for seed in range(seeds):
            d = work / f"{name}_{seed}"
            generate_study(d / "csv", seed=1000 + seed, mechanisms=[], **(SMALL | options))
            import_study(d / "csv", d / "s")
            shutil.rmtree(d / "csv")
            row = {"study": f"{name} (null, seed {1000 + seed})", "expected": "none"}
            rows.append(row | _diagnose(d / "s", jobs))
    return rows


ARM = ("b_i", "k_i", "b_c", "k_c")


def _report(sessions: Path, out: Path) -> Path:
    from steerlab.app.cli import main as steerlab

    if steerlab(["report", str(sessions), "--out", str(out)]) != 0:
        raise RuntimeError(f"steerlab report {sessions} failed")
    return out / "per_subject.csv"


def _medians(cells: list[dict]) -> dict:
    out = {}
    for k in ARM:
        e = np.array([c[k] for c in cells], dtype=float)
        out[k] = round(float(np.nanmedian(np.abs(e))), 4) if np.isfinite(e).any() else None
    return out


def outside_recovery(root: Path, work: Path) -> list[dict]:
    """The report's arm parameters against each outside study's truth (per subject × condition:
    its trials share their parameters)."""
    rows = []
    for case in sorted(p for p in root.iterdir() if (p / "trials").is_dir()):
        truth = json.loads((case / "truth.json").read_text())
        sessions = work / case.name
        if not sessions.exists():
            import_study(case / "trials", sessions)
        est: dict[tuple[str, str], dict[str, float]] = {}
        with open(_report(sessions, work / f"{case.name}.report"), newline="") as fh:
            for row in csv.DictReader(fh):
                if row["quantity"] in ARM:
                    est.setdefault((row["subject"], row["condition"]), {})[row["quantity"]] = (
                        float(row["value"]) if row["value"] not in ("", "nan") else math.nan
                    )
        cells = {}
        for t in truth["trials"]:
            subj, _, cond, _ = t["name"].split("_")
            e = est.get((subj, cond), {})
            cells[(subj, cond)] = {k: e.get(k, math.nan) / t[k] - 1.0 for k in ARM}
        rows.append({"study": case.name, "median_abs_error": _medians(list(cells.values()))})
    return rows


def convention_recovery(work: Path, seed: int = 7) -> list[dict]:
    rows = []
    for name, options in sorted(CONVENTIONS.items()):
        d = work / f"report_{name}"
        truth = generate_study(d / "csv", seed=seed, mechanisms=[], **options)
        import_study(d / "csv", d / "s")
        rec = recovery(truth, _report(d / "s", d / "r"))
        rows.append({"study": name, "median_abs_error": _medians(rec["cells"])})
    return rows


def summary(rows: list[dict]) -> dict:
    nulls = [r for r in rows if r["expected"] == "none"]
    named = [r for r in rows if r["expected"] != "none"]
    return {
        "correct_names": f"{sum(r['cause'] == r['expected'] for r in named)}/{len(named)}",
        "false_alarms": f"{sum(r['cause'] != 'none' for r in nulls)}/{len(nulls)}",
        "largest_wall_s": max((r["wall_s"] for r in rows), default=None),
    }


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks outside_worlds")
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT, help="the outside studies' folder")
    ap.add_argument("--jobs", type=int, default=min(os.cpu_count() or 1, 4))
    ap.add_argument("--conventions", type=int, nargs="?", const=3, default=0, metavar="SEEDS")
    ap.add_argument("--report", action="store_true", help="the report's parameter recovery")
    ap.add_argument("--no-diagnose", action="store_true", help="skip the outside diagnoses")
    a = ap.parse_args(argv)
    recov = None
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        have = a.root.is_dir()
        rows = outside(a.root, a.jobs, work / "outside") if have and not a.no_diagnose else []
        conv = conventions(a.conventions, a.jobs, work / "conv") if a.conventions else []
        if a.report:
            (work / "outside").mkdir(parents=True, exist_ok=True)
            recov = (outside_recovery(a.root, work / "outside") if have else []) + (
                convention_recovery(work / "conv")
            )
    for r in rows + conv:
        line = f"{r['study']:36s} expected {r['expected']:24s} named {r['cause']:24s}"
        print(f"{line} {r['wall_s']} s")
    return {
        "outside": {"studies": rows, **summary(rows)},
        "conventions": {"studies": conv, **summary(conv)} if conv else None,
        "report_recovery": recov,
        "goals": {"correct_names_min": 0.9, "false_alarms_max": 0.05, "wall_s_max": 60.0},
    }
