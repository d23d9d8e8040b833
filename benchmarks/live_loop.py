"""One trial in real time on the simulated rig, through the CAN bus, the pty glove unit and the
HDF5 writer, with the control loop in its own process (as ``steerlab run`` does) and the
simulated devices in theirs (``hardware.sim.lab``).

Goals (issue 3, issue 14): zero lost samples; p99 period error < 0.25 ms; < 0.1 % late cycles
(> 0.5 ms).

``--stress N`` runs N CPU-bound processes (``while True: pass``, at this process's priority)
for the whole trial: how much load the loop tolerates. A trial that cannot keep time must end
aborted *safely*: ``aborted_safely`` is true when the trial ended aborted and the simulated
drive then applies zero torque (read at the drive, in the lab process).

``--no-realtime``: the loop (and the simulated devices) without SCHED_FIFO and mlockall, as for
a user without the rights: with ``--stress`` the loop then competes with the stress processes
on equal terms. ``--simulated-devices in_loop`` runs the simulated drive and glove unit inside
the loop's process (the layout before issue 14), for comparison. ``--trace`` records per cycle
when each phase ended and reports why cycles were late (``hardware.loop.trace_summary``).

Last line: one JSON object with, among others, ``p99_ms``, ``late_fraction``, ``lost_samples``,
``rt_priority``, ``mlocked``, ``cpu`` (the CPUs the loop process may run on).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from steerlab.benchmarks.machine import machine
from steerlab.hardware.realtime import REALTIME_ENV
from steerlab.hardware.rig import load_rig
from steerlab.hardware.trial_loops import rig_loop
from steerlab.protocols.datafile import SessionFile, SessionWriter
from steerlab.protocols.engine import SessionEngine
from steerlab.protocols.protocol import load_protocol
from steerlab.protocols.session import build_plan

HOG = "while True: pass"


def start_stress(n: int) -> list[subprocess.Popen]:
    """N CPU-bound processes; stop them with :func:`stop_stress`."""
    return [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(n)]


def stop_stress(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
    for p in procs:
        p.wait(10)


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks live_loop")
    ap.add_argument("--rig", help="rig file (default: the simulated rig)")
    ap.add_argument("--condition", default="BT12")
    ap.add_argument("--stress", type=int, default=0, metavar="N", help="N CPU-bound processes")
    ap.add_argument("--simulated-devices", choices=("process", "in_loop"), default="process")
    ap.add_argument("--trace", action="store_true", help="why cycles were late (per phase)")
    ap.add_argument("--profile", metavar="FILE", help="cProfile the loop thread into FILE")
    ap.add_argument(
        "--no-realtime",
        action="store_true",
        help="no SCHED_FIFO, no mlockall (as a user without the rights)",
    )
    a = ap.parse_args(argv)
    protocol = load_protocol()
    plan = build_plan(protocol, 1)
    spec = next(t for t in plan.trials if t.condition == a.condition and not t.familiarization)
    plan = replace(plan, trials=(spec,))
    if a.trace:
        os.environ["STEERLAB_LOOP_TRACE"] = "1"
    if a.profile:
        os.environ["STEERLAB_LOOP_PROFILE"] = str(Path(a.profile).resolve())
    if a.no_realtime:
        os.environ[REALTIME_ENV] = "off"
    load_before = os.getloadavg()
    drive_after: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "S01.h5"
        loop = rig_loop(a.rig, 1, simulated_devices=a.simulated_devices)
        hogs = start_stress(a.stress)
        try:
            engine = SessionEngine(plan, loop)
            engine.subscribe(SessionWriter(path))
            cpu0, t0 = os.times(), time.perf_counter()
            engine.run()
            wall = time.perf_counter() - t0
            cpu1 = os.times()
            status = dict(loop.status)
            if loop.lab is not None:  # what the drive does once the trial has ended
                drive_after = loop.lab.wait_zero_torque(timeout_s=2.0)
        finally:
            stop_stress(hogs)
            loop.close()
        (rec,) = SessionFile(path).records()
    stats = json.loads(rec.attrs["loop_stats"])
    planned = plan.setup(spec).n_samples
    lost = stats.get("samples", rec.n_samples) - rec.n_samples
    cycles = stats.get("cycles", 0)
    late_fraction = stats.get("late_cycles", 0) / cycles if cycles else None
    p99 = stats.get("period_error_p99_ms")
    tuning = loop.realtime
    zero_after = drive_after.get("applied_torque_nm") if drive_after else None
    return {
        "trial_s": planned / protocol.loop_rate_hz,
        "status": rec.status,
        "abort_reason": rec.abort_reason,
        "stress_processes": a.stress,
        "simulated_devices": a.simulated_devices,
        "cycles": cycles,
        "samples": rec.n_samples,
        "period_error_p50_ms": round(stats.get("period_error_p50_ms", float("nan")), 4),
        "period_error_max_ms": round(stats.get("period_error_max_ms", float("nan")), 3),
        "late_cycles": stats.get("late_cycles"),
        "drive_kind": load_rig(a.rig).drive.kind,
        # unanswered cycles: a CiA 402 drive's SYNCs, a SensoDrive's 0x201 requests
        "missed_tpdo": status.get("missed_tpdo"),
        "missed_replies": status.get("missed_replies"),
        "glove_dropped_frames": status.get("glove_dropped_frames"),
        "glove_rate_hz": status.get("glove_rate_hz"),
        "loop_process_cpu_s": round(stats.get("loop_process_cpu_s", float("nan")), 2),
        "lab_process_cpu_s": drive_after.get("cpu_s"),  # the simulated devices' (whole life)
        "engine_process_cpu_s": round((cpu1.user + cpu1.system) - (cpu0.user + cpu0.system), 2),
        "wall_s": round(wall, 2),
        "realtime_tuning": tuning,
        "trace": stats.get("trace_summary"),
        "drive_torque_after_nm": zero_after,
        "aborted_safely": rec.status == "aborted" and zero_after == 0.0,
        "goals": {"lost_samples": 0, "p99_ms": 0.25, "late_fraction": 0.001},
        "goals_met": (
            rec.status == "complete"
            and lost == 0
            and p99 is not None
            and p99 < 0.25
            and late_fraction is not None
            and late_fraction < 0.001
        ),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "machine": machine(),
        "p99_ms": None if p99 is None else round(p99, 4),
        "late_fraction": None if late_fraction is None else round(late_fraction, 6),
        "lost_samples": lost,
        "rt_priority": tuning.get("sched_fifo_priority"),
        "mlocked": tuning.get("mlockall"),
        "cpu": tuning.get("cpus"),
    }
