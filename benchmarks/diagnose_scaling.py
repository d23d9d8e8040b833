"""The diagnosis of the demo study on 1, 2, 4 … Dask workers: wall time per worker count.

``python -m benchmarks diagnose_scaling [--workers 1,2,4] [--subjects 18] [--data DIR]``

The demo is ``steerlab simulate --subjects 18 --out DIR`` (seed 0, the paper's protocol at
1 kHz); ``--subjects N`` takes its first N subjects (the same sessions: subject i's seed does
not depend on N). ``--data`` diagnoses session files already simulated instead. For each worker
count a Dask ``LocalCluster`` (``--scheduler local:N``, one thread per worker) is started, the
diagnosis runs once with its candidates' fits on it (``steerlab diagnose DIR --scheduler
local:N``), and the cluster is closed; the start of the cluster is timed apart.

Only the candidate stage is parallel (one task per candidate and step, about six at a time);
loading, the baseline, drift and the comparison run in the diagnosing process, so the speed-up
is bounded by that stage's share (``stages_s``). The candidate stage's time limit is lifted
(``--time-limit``, default none) so that every worker count does the same work, and the
results must be the same at every count (``same_result``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from pathlib import Path

from steerlab.benchmarks.machine import machine


def _worker_counts(text: str) -> list[int]:
    try:
        counts = [int(w) for w in text.split(",") if w.strip()]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise SystemExit(f"--workers {text!r}: give worker counts ≥ 1, e.g. 1,2,4")
    return counts


def _result_key(result) -> str:
    """What the diagnosis found, without its timing: equal strings mean identical results."""
    d = result.to_dict()
    d.pop("timing_s", None)
    return json.dumps(d, sort_keys=True)


def diagnose_on(data: Path, workers: int) -> tuple[dict, str]:
    from steerlab.analysis.diagnosis import run_diagnosis
    from steerlab.analysis.executors import executor_for

    load = os.getloadavg()
    t0 = time.perf_counter()
    with executor_for(f"local:{workers}") as ex:
        started = time.perf_counter()
        cpu0 = time.process_time()
        result = run_diagnosis(data, None, jobs=workers, executor=ex)
        wall = time.perf_counter() - started
        cpu = time.process_time() - cpu0
    row = {
        "workers": workers,
        "wall_s": round(wall, 1),
        "cluster_start_s": round(started - t0, 1),
        "diagnosing_process_cpu_s": round(cpu, 1),
        "stages_s": {k: round(v, 1) for k, v in result.timing_s.items()},
        "cause": result.cause,
        "causes": result.causes,
        "limits": result.limits,
        "loadavg_1_5_15_before": [round(x, 2) for x in load],
        "loadavg_1_5_15_after": [round(x, 2) for x in os.getloadavg()],
    }
    return row, _result_key(result)


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks diagnose_scaling")
    ap.add_argument("--workers", default="1,2,4", help="Dask worker counts (default 1,2,4)")
    ap.add_argument("--subjects", type=int, default=18, help="the demo's first N subjects")
    ap.add_argument("--seed", type=int, default=0, help="the demo's seed (default 0)")
    ap.add_argument("--data", help="diagnose these session files instead of simulating")
    ap.add_argument(
        "--time-limit",
        type=float,
        default=math.inf,
        help="the candidate stage's limit in s (default: none, so every count does the same work)",
    )
    a = ap.parse_args(argv)
    counts = _worker_counts(a.workers)
    from steerlab.analysis.diagnosis import engine

    engine.CANDIDATE_TIME_LIMIT_S = a.time_limit
    with tempfile.TemporaryDirectory(prefix="steerlab-diagnose-scaling-") as tmp:
        simulate_s = None
        if a.data:
            data = Path(a.data)
        else:
            from steerlab.app.simulate import simulate_study

            data = Path(tmp) / "demo"
            t0 = time.perf_counter()
            simulate_study(a.subjects, data, seed=a.seed)
            simulate_s = round(time.perf_counter() - t0, 1)
        rows, keys = [], []
        for w in counts:
            row, key = diagnose_on(data, w)
            rows.append(row)
            keys.append(key)
            print(f"{w} worker(s): {row['wall_s']} s (cause {row['cause']})", flush=True)
    return {
        "data": a.data or f"steerlab simulate --subjects {a.subjects} --seed {a.seed}",
        "subjects": a.subjects if not a.data else None,
        "simulate_s": simulate_s,
        "time_limit_s": a.time_limit if math.isfinite(a.time_limit) else None,
        "runs": rows,
        "same_result": len(set(keys)) == 1,
        "machine": machine(),
    }
