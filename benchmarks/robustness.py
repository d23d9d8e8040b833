"""Does the default analysis hold on worlds unlike Steerlab's? Recovery on another lab's data.

Each *world* is a study made by :mod:`benchmarks.otherworld` (a closed-loop simulator that shares
no code with ``hardware/sim``: its own integrator, remnant, multisine, sampling and parameter
values), written in the trial interchange format, brought in with ``steerlab import``
(:func:`protocols.interchange.import_study`) and analysed with Steerlab's **default** options
(:class:`analysis.study.AnalysisOptions()`; nothing is tuned per world). The worlds vary what a
lab varies and Steerlab cannot know: arm inertia 0.05–0.15 kg·m²; remnant level ×0.5–×3 and
corner 0.05–1 Hz (first and second order); sensor noise; sample rate 100 Hz–2 kHz; a rig that
renders faster than it records (with an averaging recorder); a heavier wheel; trials starting at
any phase (every world); the two lowest bands with low coherence, as in the paper.

Per world and parameter: median and 90th-percentile |relative error| over every subject ×
condition, and the number of estimates the analysis itself flagged as not determined by the
data (``ArmFit.unidentified``: at a search bound or SEM ≥ value). Goal on every world, with no
option changed: median error k_i ≤ 5 %, k_c ≤ 10 %, b_i and b_c ≤ 15 %.

``python -m benchmarks robustness [--subjects 3] [--seed 0] [--worlds a,b] [--jobs 1]``
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import tempfile
import time
from pathlib import Path

import numpy as np

from steerlab.benchmarks.machine import machine, peak_rss_mb

BASE_REMNANT = 0.25  # otherworld's default remnant SD relative to the perturbation's
PARAMS = ("I_i", "b_i", "k_i", "b_c", "k_c")
GOALS = {"k_i": 0.05, "k_c": 0.10, "b_i": 0.15, "b_c": 0.15}
CONDITIONS = ("RT", "BT18", "BT12", "BT8", "BT5", "PT")

#: name → otherworld StudyOptions overrides. Every world draws a random start phase per trial.
WORLDS: dict[str, dict] = {
    "reference: I 0.07 at 250 Hz": {},
    "inertia 0.05": {"arm_inertia": 0.05},
    "inertia 0.15": {"arm_inertia": 0.15},
    "inertia varies by subject (SD 30 %)": {"arm_inertia": 0.09, "inertia_rel_sd": 0.3},
    "remnant x0.5": {"remnant_rel": 0.5 * BASE_REMNANT},
    "remnant x3": {"remnant_rel": 3 * BASE_REMNANT},
    "remnant corner 0.05 Hz": {"remnant_corner_hz": 0.05},
    "remnant corner 1 Hz 2nd order": {"remnant_corner_hz": 1.0, "remnant_order": 2},
    "low coherence in the lowest bands": {
        "remnant_rel": 3 * BASE_REMNANT,
        "remnant_corner_hz": 0.05,
        "remnant_order": 2,
    },
    "sensor noise x5 quantised": {
        "angle_noise_rad": 1e-4,
        "torque_noise_Nm": 0.1,
        "angle_lsb_rad": 2 * np.pi / 4096,
        "torque_lsb_Nm": 0.01,
    },
    "100 Hz": {"fs_hz": 100.0},
    # The rig renders at 1 kHz and a recorder keeps 250 Hz means: not the hold the default's
    # sampled-data term assumes; and a heavier wheel than Table 1's (the term's I_w).
    "1 kHz rig recorded as 250 Hz means": {"control_per_sample": 4, "record_filter": "mean"},
    "heavier wheel 0.36": {"wheel_inertia": 0.36},
    "2 kHz velocity by difference": {"fs_hz": 2000.0, "velocity_source": "difference"},
}


def run_world(name: str, overrides: dict, subjects: int, seed: int) -> dict:
    """Generate, import and analyse one world; errors per parameter against its truth."""
    from steerlab.analysis.pipeline import load_directory
    from steerlab.analysis.study import AnalysisOptions, analyze_study
    from steerlab.benchmarks.otherworld import generate_study
    from steerlab.protocols.interchange import import_study

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="steerlab-robust-") as tmp:
        csv_dir, h5_dir = Path(tmp) / "csv", Path(tmp) / "h5"
        truth = generate_study(
            csv_dir, subjects=subjects, conditions=CONDITIONS, seed=seed, **overrides
        )
        t_gen = time.perf_counter() - t0
        import_study(csv_dir, h5_dir)
        records, _ = load_directory(h5_dir)
        study = analyze_study(records, options=AnalysisOptions(compare_weightings=False))
    errors: dict[str, list[float]] = {n: [] for n in PARAMS}
    flagged: dict[str, int] = {n: 0 for n in PARAMS}
    missing = 0
    for subj, s in truth["subjects"].items():
        for cond, arm in s["conditions"].items():
            try:
                r = study.result(subj, cond)
            except KeyError:
                missing += 1
                continue
            if r.fit is None:
                missing += 1
                continue
            bad = set(r.fit.unidentified())
            for n in PARAMS:
                errors[n].append(getattr(r.fit.params, n) / arm[n] - 1.0)
                flagged[n] += n in bad
    out: dict = {"world": name, "overrides": overrides, "cells_missing": missing}
    ok = True
    for n in PARAMS:
        e = np.abs(np.array(errors[n]))
        med = float(np.median(e)) if e.size else float("nan")
        out[n] = {
            "median_abs_error_percent": round(100 * med, 2),
            "p90_abs_error_percent": round(100 * float(np.percentile(e, 90)), 2)
            if e.size
            else None,
            "median_signed_error_percent": (
                round(100 * float(np.median(errors[n])), 2) if e.size else None
            ),
            "n": int(e.size),
            "flagged_unidentified": flagged[n],
        }
        if n in GOALS:
            out[n]["goal_percent"] = 100 * GOALS[n]
            ok &= bool(med <= GOALS[n])
    out["meets_goals"] = ok and missing == 0
    out["generate_s"] = round(t_gen, 1)
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    return out


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks robustness")
    ap.add_argument("--subjects", type=int, default=3, help="subjects per world (6 conditions)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--worlds", default="", help="comma-separated names (default: all)")
    ap.add_argument("--jobs", type=int, default=1, help="worlds in parallel processes")
    ap.add_argument("--scheduler", help="Dask scheduler address, or local[:N] (worlds on Dask)")
    a = ap.parse_args(argv)
    names = [w.strip() for w in a.worlds.split(",") if w.strip()] or list(WORLDS)
    unknown = [w for w in names if w not in WORLDS]
    if unknown:
        raise SystemExit(f"unknown world(s) {unknown}; known: {list(WORLDS)}")
    t0 = time.perf_counter()
    if a.scheduler:
        from steerlab.analysis.executors import executor_for

        with executor_for(a.scheduler, a.jobs) as ex:
            assert ex is not None
            futs = [ex.submit(run_world, w, WORLDS[w], a.subjects, a.seed) for w in names]
            rows = [f.result() for f in futs]
    elif a.jobs > 1:
        with cf.ProcessPoolExecutor(a.jobs) as ex:
            futs = [ex.submit(run_world, w, WORLDS[w], a.subjects, a.seed) for w in names]
            rows = [f.result() for f in futs]
    else:
        rows = [run_world(w, WORLDS[w], a.subjects, a.seed) for w in names]
    for r in rows:
        cells = "  ".join(
            f"{n} {r[n]['median_abs_error_percent']:5.1f}/{r[n]['p90_abs_error_percent']:5.1f}%"
            for n in PARAMS
        )
        print(f"{r['world'][:38]:<38} {cells}  {'ok' if r['meets_goals'] else 'MISSED'}")
    return {
        "subjects_per_world": a.subjects,
        "seed": a.seed,
        "options": "AnalysisOptions() defaults (inverse-variance ML weights, I_i per subject)",
        "worlds": rows,
        "all_meet_goals": all(r["meets_goals"] for r in rows),
        "wall_s": round(time.perf_counter() - t0, 1),
        **peak_rss_mb(),
        "machine": machine(),
    }
