"""Simulate the full study through the engine, HDF5 included, and compare with real time.

Goal (issue 2): at least 500× faster than real time on a 2-core machine.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from steerlab.app.simulate import simulate_study
from steerlab.benchmarks.machine import machine, peak_rss_mb
from steerlab.protocols.datafile import SessionFile

GOAL_SPEEDUP = 500.0


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks simulate_study")
    ap.add_argument("--subjects", type=int, default=18)
    ap.add_argument("--jobs", type=int, default=None)
    ap.add_argument("--out", help="keep the study here (default: a temporary directory)")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(a.out) if a.out else Path(tmp) / "study"
        # Warm the compiled kernel (cached on disk) so the figure is the steady-state speed.
        simulate_study(1, Path(tmp) / "warm", jobs=1)
        t0 = time.perf_counter()
        simulate_study(a.subjects, out, jobs=a.jobs, overwrite=True)
        wall = time.perf_counter() - t0
        simulated = 0.0
        samples = 0
        size = 0
        for p in sorted(out.glob("*.h5")):
            size += p.stat().st_size
            sf = SessionFile(p)
            for attrs in sf.trial_attrs.values():
                samples += int(attrs["n_samples"])
                simulated += int(attrs["n_samples"]) / float(attrs["fs_hz"])
    speedup = simulated / wall
    return {
        "subjects": a.subjects,
        "simulated_s": round(simulated, 1),
        "recorded_minutes": round(simulated / 60, 1),
        "samples": samples,
        "wall_s": round(wall, 2),
        "simulated_s_per_wall_s": round(speedup, 1),
        "goal_speedup": GOAL_SPEEDUP,
        "goal_met": speedup >= GOAL_SPEEDUP,
        "hdf5_mb": round(size / 2**20, 1),
        **peak_rss_mb(),
        "machine": machine(),
    }
