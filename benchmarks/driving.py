"""The driving task (issue 19): admittance from grip alone against the truth and against the
perturbation-based trackers on the same simulated drives; the simulator's speed; the live
loop's timing with the vehicle model in it; the road view's frame rate.

``python -m benchmarks driving [--subjects N] [--seed S] [--no-loop] [--no-view]``

Goals: the simulated driving study ≥ 100× real time (headless, batch); the live-loop goals of
``python -m benchmarks live_loop`` (no lost sample, p99 period error < 0.25 ms, < 0.1 % late
cycles) with the vehicle in the loop; the road view ≥ 60 frames/s offscreen.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from steerlab.benchmarks.machine import machine
from steerlab.protocols.protocol import load_protocol
from steerlab.protocols.session import build_plan

PROTOCOL = "driving.toml"


def _simulate(out: Path, subjects: int, seed: int) -> dict:
    """The study through ``steerlab simulate``'s own function; the drives' speed apart."""
    from steerlab.app.simulate import SimulationJob, run_subject
    from steerlab.hardware.sim.world import WorldConfig

    protocol = load_protocol(PROTOCOL)
    drive_s = 0.0
    stamps: list[tuple[float, str]] = []
    c0, t0 = time.process_time(), time.perf_counter()
    for n in range(1, subjects + 1):
        job = SimulationJob(n, str(out), seed, PROTOCOL, False, WorldConfig(), False)
        last = [time.perf_counter()]

        def on_trial(e, last=last) -> None:
            now = time.perf_counter()
            stamps.append((now - last[0], e.key))
            last[0] = now

        run_subject(job, on_trial=on_trial)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    trial_s = protocol.trial_samples / protocol.loop_rate_hz
    drives = [dt for dt, key in stamps if "_D" in key]
    drive_s = sum(drives)
    return {
        "subjects": subjects,
        "wall_s": round(wall, 1),
        "simulated_s": round(len(stamps) * trial_s, 1),
        "cpu_s": round(cpu, 1),
        "realtime_factor_all_wall": round(len(stamps) * trial_s / wall, 1),
        "realtime_factor_all_cpu": round(len(stamps) * trial_s / cpu, 1),
        "drives": len(drives),
        "realtime_factor_drives_wall": round(len(drives) * trial_s / drive_s, 1)
        if drives
        else None,
    }


def _kernel_speed() -> dict:
    """One drive in the batch loop, compiled beforehand: the vehicle kernel's own speed."""
    from steerlab.hardware.sim.physiology import make_population
    from steerlab.hardware.sim.rig import simulated_rig
    from steerlab.protocols.engine import LoopControl

    protocol = load_protocol(PROTOCOL)
    plan = build_plan(protocol, 1)
    spec = next(t for t in plan.trials if t.condition == "D20_FREE")
    rig = simulated_rig(make_population(1, seed=1)[0])
    list(rig.batch_loop().run_trial(plan.setup(spec), LoopControl()))  # compile
    setup = plan.setup(spec)
    c0, t0 = time.process_time(), time.perf_counter()
    list(rig.batch_loop().run_trial(setup, LoopControl()))
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    trial_s = setup.n_samples / setup.fs_hz
    # CPU time as well as wall time: on a shared, loaded machine the wall clock measures the
    # other processes too.
    return {"samples": setup.n_samples, "wall_s": round(dt, 3), "cpu_s": round(cpu, 3),
            "realtime_factor_wall": round(trial_s / dt, 1),
            "realtime_factor_cpu": round(trial_s / cpu, 1)}  # fmt: skip


def _accuracy(out: Path) -> dict:
    from steerlab.analysis.driving_report import analyse_driving
    from steerlab.protocols.datafile import SessionFile, session_files

    records = [r for p in session_files(out) for r in SessionFile(p).records()]
    t0 = time.perf_counter()
    rep = analyse_driving(records)
    took = time.perf_counter() - t0
    if rep is None:
        return {"error": "no drives"}
    stats = {
        f"{factor}/{dv}": {
            "means": {c: round(m, 5) for c, m in r["condition_means"].items()},
            "F": round(r["F"], 2),
            "p": r["p"],
        }
        for factor, by in rep.stats.items()
        for dv, r in by.items()
    }
    departures = [d.lane_departure_percent for d in rep.drives]
    return {
        "analysis_s": round(took, 1),
        "summary": rep.summary(),
        "lane_departure_percent_max": round(max(departures), 2),
        "statistics": stats,
        "problems": rep.problems,
    }


def _loop_timing(condition: str) -> dict:
    """One driving trial in real time through the loop process (as ``steerlab run``)."""
    import json

    from steerlab.hardware.trial_loops import rig_loop
    from steerlab.protocols.datafile import SessionFile, SessionWriter
    from steerlab.protocols.engine import SessionEngine

    protocol = load_protocol(PROTOCOL)
    plan = build_plan(protocol, 1)
    spec = next(t for t in plan.trials if t.condition == condition)
    plan = replace(plan, trials=(spec,))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "S01.h5"
        loop = rig_loop(None, 1)
        try:
            engine = SessionEngine(plan, loop)
            engine.subscribe(SessionWriter(path))
            engine.run()
        finally:
            loop.close()
        (rec,) = SessionFile(path).records()
    st = json.loads(rec.attrs["loop_stats"])
    planned = plan.setup(spec).n_samples
    out = {
        "condition": spec.condition,
        "status": rec.status,
        "abort_reason": rec.abort_reason,
        "lost_samples": int(planned - rec.n_samples),
    }
    if "cycles" in st:
        out |= {
            "period_error_p99_ms": round(st["period_error_p99_ms"], 4),
            "period_error_max_ms": round(st["period_error_max_ms"], 3),
            "late_fraction": st["late_cycles"] / st["cycles"],
        }
    if "lateral_position_m" not in rec.extra:
        return out
    y, w = rec.extra["lateral_position_m"], rec.extra["lane_width_m"]
    return {
        "condition": spec.condition,
        "status": rec.status,
        "abort_reason": rec.abort_reason,
        "lost_samples": int(planned - rec.n_samples),
        "period_error_p99_ms": round(st["period_error_p99_ms"], 4),
        "period_error_max_ms": round(st["period_error_max_ms"], 3),
        "late_fraction": st["late_cycles"] / st["cycles"],
        "lane_departure_percent": round(float(100 * np.mean(np.abs(y) > (w - 1.8) / 2)), 2),
    }


def _view_fps(frames: int = 300) -> dict:
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6.QtWidgets import QApplication

    from steerlab.app.gui.road_view import RoadView
    from steerlab.protocols.driving import DrivingCondition, DrivingSetup

    app = QApplication.instance() or QApplication([])
    p = load_protocol(PROTOCOL)
    drive = DrivingSetup(DrivingCondition(20.0), p.vehicle, p.road.generate(3000.0))
    v = RoadView(fps=1000.0)
    v.resize(1280, 720)
    v.set_drive(drive)
    v.show()
    app.processEvents()
    c0, t0 = time.process_time(), time.perf_counter()
    for i in range(frames):
        y = 0.3 * np.sin(i / 20)
        v.set_state({"road_distance_m": 100.0 + 0.33 * i, "lateral_position_m": y,
                     "heading_error_rad": 0.01})  # fmt: skip
        v.repaint()
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    v.close()
    return {"frames": frames, "size": "1280x720", "fps_wall": round(frames / dt, 1),
            "fps_cpu": round(frames / cpu, 1)}  # fmt: skip


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks driving")
    ap.add_argument("--subjects", type=int, default=4)
    ap.add_argument("--seed", type=int, default=19)
    ap.add_argument("--no-loop", action="store_true", help="skip the real-time loop trial")
    ap.add_argument("--no-view", action="store_true", help="skip the road view's frame rate")
    ap.add_argument("--loop-condition", default="D20_FREE")
    ap.add_argument(
        "--loop-only",
        action="store_true",
        help="only the real-time loop: the drive and, for comparison, BT12 of the same protocol",
    )
    a = ap.parse_args(argv)
    load0 = os.getloadavg()
    out: dict = {"machine": machine()}
    if a.loop_only:
        out["live_loop"] = _loop_timing(a.loop_condition)
        out["live_loop_boundary_task"] = _loop_timing("BT12")
        out["load_avg_before"] = [round(x, 2) for x in load0]
        out["load_avg_after"] = [round(x, 2) for x in os.getloadavg()]
        return out
    out["kernel"] = _kernel_speed()
    with tempfile.TemporaryDirectory() as tmp:
        out["simulate"] = _simulate(Path(tmp), a.subjects, a.seed)
        out["accuracy"] = _accuracy(Path(tmp))
    if not a.no_view:
        out["road_view"] = _view_fps()
    if not a.no_loop:
        out["live_loop"] = _loop_timing(a.loop_condition)
    out["load_avg_before"] = [round(x, 2) for x in load0]
    out["load_avg_after"] = [round(x, 2) for x in os.getloadavg()]
    return out
