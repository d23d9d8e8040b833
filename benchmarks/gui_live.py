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
from collections.abc import Generator
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


def _qt_app(loop_in_process: bool = True):
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6.QtWidgets import QApplication

    from steerlab.app.gui.main import configure_process

    configure_process(loop_in_process)
    return QApplication.instance() or QApplication(sys.argv[:1])


def with_gui(
    protocol, out: Path, timeout_s: float, switch_interval_s: float | None, rig_path: str | None
) -> dict:
    from PySide6.QtCore import QEventLoop, QTimer

    from steerlab.app.gui.session_window import ExperimenterWindow
    from steerlab.protocols import events as ev

    app = _qt_app(loop_in_process=rig_path is None)
    if switch_interval_s is not None:
        sys.setswitchinterval(switch_interval_s)
    win = ExperimenterWindow(protocol, out / "gui", rig_path=rig_path)
    win.show()
    win.dashboard.show()
    win.open_session()
    plan = win.controller.plan
    assert plan is not None, win.alert_label.text()
    n_planned = plan.setup(plan.trials[0]).n_samples
    win.start_button.click()

    def ended() -> list:
        return [e for e in win.events_seen if isinstance(e, ev.TrialEnded)]

    def wait(cond, limit_s: float) -> None:
        # Qt's own event loop, as in `steerlab gui` (app.exec()), checked 20 times a second: a
        # polling loop would add its own cost to the Qt thread's CPU time.
        loop, check = QEventLoop(), QTimer()
        end = time.monotonic() + limit_s

        def poll() -> None:
            if cond() or time.monotonic() > end:
                loop.quit()

        check.timeout.connect(poll)
        check.start(50)
        if not cond():
            loop.exec()
        check.stop()

    wait(lambda: any(isinstance(e, ev.TrialStarted) for e in win.events_seen), 30)
    f0, r0, c0 = win.plots.frames.frames, win.plots.refreshes, win.plots.refresh_s
    t0, gui0, proc0 = time.perf_counter(), time.thread_time(), time.process_time()
    wait(lambda: bool(ended()), timeout_s)
    wall = time.perf_counter() - t0
    # CPU, not wall, time: what the GUI costs whatever else the machine runs. The Qt thread is
    # this one (it runs the event loop in wait()); the rest of the process is the engine's
    # thread (receiving blocks, the session writer) and the loop client's helpers.
    gui_cpu, proc_cpu = time.thread_time() - gui0, time.process_time() - proc0
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
        "gui_thread_cpu_percent": round(100 * gui_cpu / wall, 1),
        "gui_thread_cpu_ms_per_frame": round(1e3 * gui_cpu / max(frames, 1), 2),
        "other_threads_cpu_percent": round(100 * (proc_cpu - gui_cpu) / wall, 1),
        "fps_in_status_bar": getattr(win, "fps_label", None) and win.fps_label.text(),
        "switch_interval_s": sys.getswitchinterval(),
        **fig,
    }


def frame_cost(protocol, out: Path, frames: int = 300) -> dict:
    """CPU time of one live-plot frame on the Qt thread: a refresh and the paint it causes.

    The samples are a real trial of the built-in simulated rig (run ahead, not in real time),
    fed to the window's live data 20 ms at a time, one block per frame, with the other
    widgets' timers stopped. CPU time of the Qt thread, not wall time, so the figure changes
    little with the machine's load; median and 10th percentile over ``frames`` frames.
    """
    import numpy as np
    from PySide6.QtWidgets import QApplication

    from steerlab.app.gui.rig import make_rig_loop
    from steerlab.app.gui.session_window import ExperimenterWindow
    from steerlab.protocols import events as ev
    from steerlab.protocols.engine import LoopControl
    from steerlab.protocols.session import build_plan

    app = QApplication.instance()
    if app is None:
        raise RuntimeError("frame_cost: make the QApplication first (_qt_app)")
    plan = build_plan(protocol, 1)
    spec = plan.trials[0]
    setup = plan.setup(spec)
    fs = protocol.loop_rate_hz
    rig = make_rig_loop(None, 1, protocol, realtime=False)
    need = int(round((frames * 0.02 + 11.0) * fs))  # the plots' 10 s window, then the frames
    blocks, n = [], 0
    gen = rig.loop.run_trial(setup, LoopControl())
    for b in gen:
        blocks.append(b)
        n += len(b["time_s"])
        if n >= need:
            break
    if isinstance(gen, Generator):  # as every loop's run_trial is (protocols/engine.py)
        gen.close()  # the loop's finalizer: zero torque
    rig.close()
    win = ExperimenterWindow(protocol, out / "frame_cost")
    win.show()
    for _ in range(20):
        app.processEvents()
    for t in (win.plots.timer, win.dashboard.timer, win.admittance.timer, win.status_timer):
        t.stop()
    key = "frame/cost"
    win.live(ev.TrialStarted(key, 1, 1, spec.condition, {"fs_hz": fs}, setup.n_samples))
    win.plots.set_boundary(spec.boundary_deg)
    feed, i = iter(blocks), 0

    def push_until(t_s: float) -> None:
        nonlocal i
        while i < t_s * fs:
            b = next(feed)
            win.live(ev.SamplesAcquired(key, i, b))
            i += len(b["time_s"])

    push_until(10.0)
    win.plots.refresh()
    app.processEvents()
    refresh, paint = [], []
    for k in range(frames):
        push_until(10.0 + 0.02 * (k + 1))
        t0 = time.thread_time()
        win.plots.refresh()
        t1 = time.thread_time()
        app.processEvents()  # the scene's dirty region, then the paint event it posts
        app.processEvents()
        t2 = time.thread_time()
        refresh.append(t1 - t0)
        paint.append(t2 - t1)
    frame = np.add(refresh, paint)
    vb = win.plots.plots[0].getViewBox()
    res = {
        "frames": frames,
        "frame_ms_median": round(1e3 * float(np.median(frame)), 2),
        "frame_ms_p10": round(1e3 * float(np.percentile(frame, 10)), 2),
        "refresh_ms_median": round(1e3 * float(np.median(refresh)), 2),
        "paint_ms_median": round(1e3 * float(np.median(paint)), 2),
        "plot_area_px": [int(vb.width()), int(vb.height())],
        "points_per_curve": {ch: len(c.getData()[0]) for ch, c in win.plots.curves.items()},
    }
    win.close()
    app.processEvents()
    return res


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks gui_live")
    ap.add_argument("--protocol", help="protocol TOML (default: the paper's)")
    ap.add_argument("--gui-only", action="store_true", help="skip the headless run")
    ap.add_argument(
        "--frame-cost-only",
        action="store_true",
        help="only the CPU cost of a plot frame (a few seconds; no real-time trial)",
    )
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
        if a.frame_cost_only:
            _qt_app()
            cost = frame_cost(protocol, out)
            return {"frame_cost": cost, "machine": machine(), "load_avg": os.getloadavg()}
        head = None if a.gui_only else headless(protocol, out, a.rig)
        gui = with_gui(protocol, out, trial_s * 2 + 30, a.switch_interval, a.rig)
        cost = frame_cost(protocol, out)
    res: dict = {
        "rig": a.rig or "simulated, in process",
        "trial_s": trial_s,
        "loop_rate_hz": protocol.loop_rate_hz,
        "gui": gui,
        "headless": head,
        "goal_fps": GOAL_FPS,
        "fps_goal_met": gui["plot_fps"] >= GOAL_FPS,
        "frame_cost": cost,
    }
    if head is not None:
        res["late_cycles_change"] = (gui["late_cycles"] or 0) - (head["late_cycles"] or 0)
        res["lost_samples_change"] = gui["lost_samples"] - head["lost_samples"]
    return {**res, **peak_rss_mb(), "machine": machine(), "load_avg": os.getloadavg()}
