"""One real-time trial with the experimenter GUI open (offscreen), against the same trial headless.

Goal (issue "Experimenter GUI and subject dashboard"): live plots at ≥ 30 frames/s, and no
change in the loop's late cycles or lost samples compared with the same trial without a GUI.

Both runs use the default protocol (45 s period; the trial with run-in and fade-out is 51 s),
the same rig through ``app.gui.rig.make_rig_loop`` (same loop, same block size) and a session
writer. Frames are the plot widget's paint events during the trial.

The rig is by default ``hardware/rigs/simulated.toml``: the lab's path, with the loop in its own
process speaking CAN to a simulated drive and reading a simulated glove through a pty, because
that is the loop whose timing matters. ``--in-process`` measures instead the GUI's built-in
simulated rig, whose loop shares the GUI's process (its world steps by sample count, so a late
cycle there changes no recorded number).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from steerlab.benchmarks.machine import machine, peak_rss_mb

GOAL_FPS = 30.0
DEFAULT_RIG = str(Path(__file__).resolve().parents[1] / "hardware" / "rigs" / "simulated.toml")
TIMING_KEYS = ("period_error_p50_ms", "period_error_p99_ms", "period_error_max_ms",
               "late_cycles", "cycles")  # fmt: skip


def _figures(end, n_planned: int) -> dict:
    s = end.stats
    return {
        "status": end.status,
        "abort_reason": end.reason,
        "samples_planned": n_planned,
        "samples_recorded": end.n_samples,
        "lost_samples": n_planned - end.n_samples,
        **{k: (round(s[k], 4) if isinstance(s.get(k), float) else s.get(k)) for k in TIMING_KEYS},
    }


def headless(protocol, out: Path, rig_path: str | None) -> dict:
    from steerlab.app.gui.rig import make_rig_loop
    from steerlab.protocols import events as ev
    from steerlab.protocols.datafile import SessionWriter
    from steerlab.protocols.engine import SessionEngine
    from steerlab.protocols.session import build_plan

    plan = build_plan(protocol, 1)
    plan = replace(plan, trials=plan.trials[:1])
    rig = make_rig_loop(rig_path, 1, protocol)
    eng = SessionEngine(plan, rig.loop)
    writer = SessionWriter(out / "headless.h5")
    eng.subscribe(writer)
    ends = []
    eng.subscribe(lambda e: ends.append(e) if isinstance(e, ev.TrialEnded) else None)
    t0 = time.perf_counter()
    eng.run()
    wall = time.perf_counter() - t0
    writer.close()
    rig.close()
    return {"wall_s": round(wall, 2), **_figures(ends[0], plan.setup(plan.trials[0]).n_samples)}


def with_gui(
    protocol, out: Path, timeout_s: float, switch_interval_s: float | None, rig_path: str | None
) -> dict:
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6.QtWidgets import QApplication

    from steerlab.app.gui.main import configure_process
    from steerlab.app.gui.session_window import ExperimenterWindow
    from steerlab.protocols import events as ev

    configure_process()
    if switch_interval_s is not None:
        sys.setswitchinterval(switch_interval_s)
    app = QApplication.instance() or QApplication(sys.argv[:1])
    win = ExperimenterWindow(protocol, out / "gui", rig_path=rig_path)
    win.show()
    win.dashboard.show()
    win.open_session()
    plan = win.controller.plan
    assert plan is not None
    n_planned = plan.setup(plan.trials[0]).n_samples
    win.start_button.click()

    def ended() -> list:
        return [e for e in win.events_seen if isinstance(e, ev.TrialEnded)]

    def wait(cond, limit_s: float) -> None:
        end = time.monotonic() + limit_s
        while not cond() and time.monotonic() < end:
            app.processEvents()
            time.sleep(0.002)

    wait(lambda: any(isinstance(e, ev.TrialStarted) for e in win.events_seen), 30)
    f0, r0, c0 = win.plots.frames.frames, win.plots.refreshes, win.plots.refresh_s
    t0 = time.perf_counter()
    wait(lambda: bool(ended()), timeout_s)
    wall = time.perf_counter() - t0
    frames = win.plots.frames.frames - f0
    refreshes = win.plots.refreshes - r0
    cost = win.plots.refresh_s - c0
    if not ended():
        win.controller.abort("benchmark timeout")
        wait(lambda: bool(ended()), 10)
    fig = _figures(ended()[0], n_planned)
    win.close()
    app.processEvents()
    return {
        "wall_s": round(wall, 2),
        "plot_fps": round(frames / wall, 1),
        "plot_refreshes_per_s": round(refreshes / wall, 1),
        "plot_refresh_ms_mean": round(1e3 * cost / max(refreshes, 1), 2),
        "switch_interval_s": sys.getswitchinterval(),
        **fig,
    }


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks gui_live")
    ap.add_argument("--protocol", help="protocol TOML (default: the paper's)")
    ap.add_argument("--gui-only", action="store_true", help="skip the headless run")
    ap.add_argument(
        "--rig", default=DEFAULT_RIG, help="rig file (default: hardware/rigs/simulated.toml)"
    )
    ap.add_argument(
        "--in-process",
        action="store_true",
        help="the GUI's built-in simulated rig, its loop in the GUI's process (ignores --rig)",
    )
    ap.add_argument(
        "--switch-interval",
        type=float,
        default=None,
        help="GIL switch interval with the GUI, s (default: the GUI's own)",
    )
    a = ap.parse_args(argv)
    if a.in_process:
        a.rig = None
    from steerlab.protocols.protocol import load_protocol

    protocol = load_protocol(a.protocol)
    trial_s = protocol.trial_samples / protocol.loop_rate_hz
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        head = None if a.gui_only else headless(protocol, out, a.rig)
        gui = with_gui(protocol, out, trial_s * 2 + 30, a.switch_interval, a.rig)
    res: dict = {
        "rig": a.rig or "simulated, in process",
        "trial_s": trial_s,
        "loop_rate_hz": protocol.loop_rate_hz,
        "gui": gui,
        "headless": head,
        "goal_fps": GOAL_FPS,
        "fps_goal_met": gui["plot_fps"] >= GOAL_FPS,
    }
    if head is not None:
        res["late_cycles_change"] = (gui["late_cycles"] or 0) - (head["late_cycles"] or 0)
        res["lost_samples_change"] = gui["lost_samples"] - head["lost_samples"]
    return {**res, **peak_rss_mb(), "machine": machine(), "load_avg": os.getloadavg()}
