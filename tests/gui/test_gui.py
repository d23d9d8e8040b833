"""The experimenter window and the subject dashboard, driven by their buttons (pytest-qt,
offscreen). Every test fails if it leaves a thread running."""

from __future__ import annotations

import json
import math
import re
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from PySide6.QtCore import Qt

from steerlab.app.gui.bridge import EngineBridge
from steerlab.app.gui.controller import WorkerFinished
from steerlab.app.gui.dashboard import SubjectDashboard
from steerlab.app.gui.live_admittance import NO_MODEL, LiveAdmittancePanel
from steerlab.app.gui.livedata import LiveData
from steerlab.app.gui.main import run_gui
from steerlab.app.gui.rig import RigError, make_rig_loop
from steerlab.app.gui.session_window import BREAK_MESSAGE, STOPPED_MESSAGE, ExperimenterWindow
from steerlab.protocols import events as ev
from steerlab.protocols.datafile import SessionFile, SessionWriter
from steerlab.protocols.engine import SessionEngine
from steerlab.protocols.protocol import load_protocol, parse_protocol
from steerlab.protocols.session import build_plan
from tests.helpers import ROOT, short_protocol_text

# -- threads -----------------------------------------------------------------------------------


def threads_left(before: set[threading.Thread], grace_s: float = 3.0) -> list[threading.Thread]:
    """Threads started since ``before`` still alive after ``grace_s`` (they may be ending)."""
    end = time.monotonic() + grace_s
    while True:
        left = [t for t in threading.enumerate() if t not in before and t.is_alive()]
        if not left or time.monotonic() > end:
            return left
        time.sleep(0.02)


@pytest.fixture(autouse=True)
def no_thread_left_running():
    before = set(threading.enumerate())
    yield
    left = threads_left(before)
    if left:
        pytest.fail(f"test left thread(s) running: {[t.name for t in left]}")


def test_thread_check_catches_a_leaked_thread():
    before = set(threading.enumerate())
    stop = threading.Event()
    t = threading.Thread(target=stop.wait, name="leaky", daemon=True)
    t.start()
    try:
        assert [x.name for x in threads_left(before, grace_s=0.05)] == ["leaky"]
    finally:
        stop.set()
        t.join()
    assert threads_left(before, grace_s=0.5) == []


# -- a short protocol and a paced loop -------------------------------------------------------


class PacedLoop:
    """A non-realtime device loop slowed to ``speed`` × wall clock, one block at a time.

    The realtime loop's stall watchdog (20 ms) trips on a loaded shared CI machine; pacing
    whole blocks keeps the trial long enough to click pause while testing the same engine, the
    same device loop and the same GUI path.
    """

    def __init__(self, loop, fs_hz: float, speed: float = 2.0) -> None:
        self.loop, self.fs, self.speed = loop, fs_hz, speed

    def run_trial(self, setup, control):
        for block in self.loop.run_trial(setup, control):
            time.sleep(len(block["time_s"]) / self.fs / self.speed)
            yield block

    def emergency_stop(self) -> None:
        self.loop.emergency_stop()

    def trial_stats(self) -> dict:
        return self.loop.trial_stats()


@pytest.fixture
def short_protocol():
    return parse_protocol(short_protocol_text(), "short.toml")


@pytest.fixture
def rigs():
    return []


@pytest.fixture
def window(qtbot, tmp_path, short_protocol, rigs):
    def factory(path, subject, protocol):
        h = make_rig_loop(None, subject, protocol, realtime=False)
        rigs.append(h)
        return replace(h, loop=PacedLoop(h.loop, protocol.loop_rate_hz))

    w = ExperimenterWindow(short_protocol, tmp_path / "data", rig_factory=factory)
    qtbot.addWidget(w)
    qtbot.addWidget(w.dashboard)
    w.show()
    return w


def click(qtbot, button) -> None:
    assert button.isEnabled(), f"{button.text()} is disabled"
    qtbot.mouseClick(button, Qt.MouseButton.LeftButton)


def ended(w) -> list[ev.TrialEnded]:
    return [e for e in w.events_seen if isinstance(e, ev.TrialEnded)]


def worker_finished(w) -> bool:
    """The worker's last event has reached the GUI thread (so have all before it)."""
    return any(isinstance(e, WorkerFinished) for e in w.events_seen)


def open_new(qtbot, w, subject: int = 1) -> None:
    w.subject_spin.setValue(subject)
    click(qtbot, w.open_button)
    assert w.controller.is_open, w.alert_label.text()


# -- the experimenter window ---------------------------------------------------------------------


def test_full_trial_pause_resume_then_redo(qtbot, window, short_protocol, tmp_path):
    w = window
    plan = build_plan(short_protocol, 1)
    assert " → ".join(plan.condition_order) in w.order_label.text()
    open_new(qtbot, w)
    states = w.trial_states()
    assert len(states) == 18 and set(states.values()) == {"pending"}
    first = plan.trials[0]
    assert first.instructions in w.instructions_label.text()
    assert not w.pause_button.isEnabled() and w.start_button.isEnabled()

    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.live.total_received > 100, timeout=5000)
    assert w.trial_states()[1] == "running"
    assert w.dashboard.boundary_deg == first.boundary_deg
    click(qtbot, w.pause_button)
    qtbot.waitUntil(lambda: w.state_label.text() == "trial paused", timeout=3000)
    n = w.live.total_received
    qtbot.wait(300)
    assert w.live.total_received == n  # nothing advances while paused
    assert w.resume_button.isEnabled() and not w.start_button.isEnabled()
    click(qtbot, w.resume_button)
    qtbot.waitUntil(lambda: w.trial_states()[1] == "done", timeout=15000)

    # The engine waits for the experimenter before the next trial.
    qtbot.waitUntil(lambda: w.state_label.text() == "ready for the next trial", timeout=3000)
    assert w.start_button.isEnabled()
    assert w.trial_states()[2] == "pending"
    # The box shows the next trial as soon as one ends, never the finished one.
    assert plan.trials[1].instructions in w.instructions_label.text()
    assert f"— trial 2 ({plan.trials[1].label})" in w.instructions_label.text()
    assert "— trial 1 (" not in w.instructions_label.text()
    q = w.last_quality
    n_planned = plan.setup(first).n_samples
    assert q is not None and q.status == "complete"
    assert q.n_received == q.n_planned == n_planned and q.lost_samples == 0
    assert q.n_periods == 2 and q.coherence.size == 8
    assert "coherence (median / min)" in w.quality_labels
    marks = [e.kind for e in w.events_seen if isinstance(e, ev.TrialMark)]
    assert marks == ["pause", "resume"]
    assert w.plots.refreshes > 0

    # Redo trial 1: it runs again at the next start, as attempt 2.
    w.select_trial(1)
    click(qtbot, w.redo_button)
    qtbot.waitUntil(lambda: w.trial_states()[1] == "pending", timeout=5000)
    assert not w.controller.worker_alive
    click(qtbot, w.start_button)
    qtbot.waitUntil(
        lambda: any(isinstance(e, ev.TrialStarted) and e.attempt == 2 for e in w.events_seen),
        timeout=5000,
    )
    click(qtbot, w.abort_button)
    qtbot.waitUntil(lambda: len(ended(w)) == 2, timeout=5000)
    assert ended(w)[-1].status == "aborted"
    path = w.controller.path
    w.close()
    sf = SessionFile(path)
    assert sorted(sf.attempts()[1]) == [(1, "superseded"), (2, "aborted")]
    rec = [r for r in sf.records() if r.attrs["attempt"] == 1][0]
    assert rec.n_samples == n_planned
    assert [m["kind"] for m in rec.attrs["marks"]] == ["pause", "resume"]


def test_abort_then_start_runs_the_trial_again(qtbot, window):
    w = window
    open_new(qtbot, w, subject=2)
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.live.total_received > 50, timeout=5000)
    click(qtbot, w.abort_button)
    qtbot.waitUntil(lambda: worker_finished(w), timeout=5000)
    assert w.trial_states()[1] == "aborted"
    assert ended(w)[0].reason == "aborted by the experimenter"
    assert w.start_button.isEnabled()
    # Nothing was lost: the samples after the abort were never acquired, and it says so.
    q, end = w.last_quality, ended(w)[0]
    samples = w.quality_labels["samples"].text()
    assert q is not None and q.status == "aborted" and q.lost_samples == 0
    assert f"{q.n_planned - end.n_samples} not recorded (aborted)" in samples
    assert "lost" not in samples
    # The aborted trial runs again next, and the box says so at once.
    assert "— trial 1 (" in w.instructions_label.text()
    click(qtbot, w.start_button)
    qtbot.waitUntil(
        lambda: any(isinstance(e, ev.TrialStarted) and e.attempt == 2 for e in w.events_seen),
        timeout=5000,
    )
    assert w.trial_states()[1] == "running"
    w.close()


def test_emergency_stop_disables_the_motor_and_latches(qtbot, window, rigs):
    w = window
    open_new(qtbot, w)
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.live.total_received > 50, timeout=5000)
    assert rigs[0].drive.enabled
    click(qtbot, w.estop_button)
    assert not rigs[0].drive.enabled  # at once, on the GUI thread, not via the engine
    qtbot.waitUntil(lambda: worker_finished(w), timeout=5000)
    assert not rigs[0].drive.enabled
    assert ended(w)[0].status == "aborted" and ended(w)[0].reason == "emergency stop"
    assert w.trial_states()[1] == "aborted"
    assert not w.start_button.isEnabled() and w.release_button.isVisible()
    # Works when no trial runs, too.
    click(qtbot, w.estop_button)
    assert not rigs[0].drive.enabled
    click(qtbot, w.release_button)
    assert w.start_button.isEnabled() and not w.release_button.isVisible()


def test_abort_is_disabled_while_waiting_for_start(qtbot, window):
    w = window
    open_new(qtbot, w)
    assert not w.abort_button.isEnabled()  # nothing runs yet
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.trial_states()[1] == "running", timeout=5000)
    assert w.abort_button.isEnabled()
    qtbot.waitUntil(lambda: w.state_label.text() == "ready for the next trial", timeout=15000)
    assert not w.abort_button.isEnabled() and w.start_button.isEnabled()
    w.close()


def test_the_abort_message_goes_when_the_next_trial_starts(qtbot, window):
    w = window
    open_new(qtbot, w)
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.live.total_received > 50, timeout=5000)
    click(qtbot, w.abort_button)
    qtbot.waitUntil(lambda: worker_finished(w), timeout=5000)
    # Named as the list names it, not by the file's group name ("01_RT_fam_a1").
    assert "trial 1 (RT, attempt 1) aborted" in w.alert_label.text(), w.alert_label.text()
    shown = [lb.text() for lb in w.quality_labels.values()]
    assert "trial 1 (RT, attempt 1): aborted" in shown
    assert not any(re.search(r"_a\d|\{|\}", t) for t in shown), shown
    click(qtbot, w.start_button)
    qtbot.waitUntil(
        lambda: any(isinstance(e, ev.TrialStarted) and e.attempt == 2 for e in w.events_seen),
        timeout=5000,
    )
    assert w.alert_label.text() == ""
    assert w.trial_states()[1] == "running"
    w.close()


def test_the_emergency_stop_shows_that_it_is_latched(qtbot, window):
    w = window
    open_new(qtbot, w)
    b = w.estop_button

    def colour() -> str:  # inside the border, left of the text
        return b.grab().toImage().pixelColor(12, b.height() // 2).name()

    ready = colour()
    assert b.text() == "EMERGENCY STOP" and not b.isChecked()
    click(qtbot, b)
    assert w.controller.estop_latched
    assert b.text() == "E-STOP LATCHED" and b.isChecked() and b.isEnabled()
    assert colour() != ready
    click(qtbot, b)  # pressed again: still latched, still shown so (a click does not untoggle)
    assert b.isChecked() and b.text() == "E-STOP LATCHED"
    click(qtbot, w.release_button)
    assert b.text() == "EMERGENCY STOP" and not b.isChecked() and colour() == ready
    w.close()


def test_the_state_reads_the_same_after_an_abort_as_after_a_complete_trial(qtbot, window):
    """In words, never the engine's state names; an abort's alert says "aborted" once."""
    w = window
    open_new(qtbot, w)
    assert w.state_label.text() == "ready for the next trial"
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.state_label.text() == "trial running", timeout=5000)
    qtbot.waitUntil(lambda: len(ended(w)) == 1, timeout=15000)
    qtbot.waitUntil(lambda: w.state_label.text() == "ready for the next trial", timeout=3000)
    # The built-in simulated rig steps its world once per cycle: late cycles are no warning.
    assert w.last_quality is not None and w.last_quality.steps_by_sample
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.live.total_received > 50 and w.controller.in_trial, timeout=5000)
    click(qtbot, w.abort_button)
    qtbot.waitUntil(lambda: worker_finished(w), timeout=5000)
    assert w.state_label.text() == "ready for the next trial"
    alert = w.alert_label.text()
    assert alert.startswith("trial 2 (") and alert.endswith(") aborted by the experimenter")
    assert alert.count("aborted") == 1, alert
    w.close()


def test_the_dashboard_says_stopped_after_an_emergency_stop_until_released(qtbot, window):
    w = window
    open_new(qtbot, w)
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.live.total_received > 50, timeout=5000)
    click(qtbot, w.estop_button)
    qtbot.waitUntil(lambda: worker_finished(w), timeout=5000)
    # The trial's end comes after the stop: it must not turn the stop into a break.
    assert ended(w) and w.dashboard.label.text() == STOPPED_MESSAGE
    assert not w.dashboard.active
    assert w.state_label.text() == "stopped: release the emergency stop to go on"
    click(qtbot, w.release_button)
    assert w.dashboard.label.text() == BREAK_MESSAGE
    assert w.state_label.text() == "ready for the next trial"
    w.close()


def test_the_condition_order_is_counted_from_one(qtbot, window, short_protocol):
    w = window
    w.subject_spin.setValue(1)
    assert "S01, condition order 1 of 6:" in w.order_label.text(), w.order_label.text()
    w.subject_spin.setValue(8)  # row 1 of the Williams square: subjects 2, 8, 14, ...
    assert "S08, condition order 2 of 6:" in w.order_label.text()
    open_new(qtbot, w, subject=6)
    text = w.order_label.text()
    assert "S06, condition order 6 of 6:" in text and "row 5" not in text, text
    assert " → ".join(build_plan(short_protocol, 6).condition_order) in text
    w.close()


def test_closing_the_window_mid_trial_aborts_and_keeps_the_data(qtbot, window):
    w = window
    open_new(qtbot, w)
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.live.total_received > 200, timeout=5000)
    path = w.controller.path
    w.close()
    assert not w.controller.worker_alive
    (rec,) = SessionFile(path).records()
    assert rec.status == "aborted" and rec.abort_reason == "window closed"
    assert rec.n_samples >= 200
    assert np.all(np.diff(rec.time_s) > 0)


def test_resume_shows_done_trials_and_runs_the_rest(qtbot, tmp_path, short_protocol, rigs):
    root = tmp_path / "data"
    root.mkdir()
    plan = build_plan(short_protocol, 3)
    h = make_rig_loop(None, 3, short_protocol, realtime=False)
    eng = SessionEngine(replace(plan, trials=plan.trials[:2]), h.loop)
    eng.subscribe(SessionWriter(root / "S03.h5"))
    eng.run()

    def factory(path, subject, protocol):
        rig = make_rig_loop(None, subject, protocol, realtime=False)
        rigs.append(rig)
        return rig

    w = ExperimenterWindow(short_protocol, root, rig_factory=factory)
    qtbot.addWidget(w)
    qtbot.addWidget(w.dashboard)
    assert w.subject_spin.value() == 1  # the first free subject number
    w.subject_spin.setValue(3)
    click(qtbot, w.open_button)  # a new session must not overwrite S03
    assert not w.controller.is_open and "exists already" in w.alert_label.text()
    assert w.session_combo.count() == 1 and "S03: 2/18 done" in w.session_combo.itemText(0)
    w.resume_radio.setChecked(True)
    click(qtbot, w.open_button)
    states = w.trial_states()
    assert states[1] == states[2] == "done" and states[3] == "pending"
    assert plan.trials[2].instructions in w.instructions_label.text()
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.trial_states()[3] == "done", timeout=10000)
    w.close()
    assert sorted(SessionFile(root / "S03.h5").attempts()) == [1, 2, 3]


def test_bridge_delivers_on_the_gui_thread_and_keeps_samples_off_the_queue(qtbot):
    live = LiveData()
    bridge = EngineBridge(live)
    got: list[tuple[object, int]] = []
    bridge.connect_to(lambda e: got.append((e, threading.get_ident())))
    attrs = {"fs_hz": 100.0}
    blk = {c: np.arange(10.0) for c in ("time_s", "wheel_angle_rad", "grip_force_N")}

    def engine_thread():
        bridge(ev.TrialStarted("k", 1, 1, "RT", attrs, 10))
        bridge(ev.SamplesAcquired("k", 0, blk))
        bridge(ev.TrialEnded("k", 1, "complete", None, 10))
        bridge(WorkerFinished("done", None))

    t = threading.Thread(target=engine_thread)
    t.start()
    t.join()
    qtbot.waitUntil(lambda: len(got) == 3, timeout=2000)
    assert [type(e).__name__ for e, _ in got] == ["TrialStarted", "TrialEnded", "WorkerFinished"]
    assert {tid for _, tid in got} == {threading.get_ident()}
    assert live.latest("wheel_angle_rad") == 9.0
    cap = live.take_trial("k")
    assert cap is not None and cap.n_received == 10


# -- the subject dashboard -------------------------------------------------------------------------

EXPECTED_LINES = {
    "RT": [],
    "BT18": [-18.0, 18.0],
    "BT12": [-12.0, 12.0],
    "BT8": [-8.0, 8.0],
    "BT5": [-5.0, 5.0],
    "PT": [0.0, 0.0],
}


def test_dashboard_boundary_lines_for_every_condition(qtbot):
    proto = load_protocol()
    d = SubjectDashboard(span_deg=30.0)
    qtbot.addWidget(d)
    d.resize(1200, 400)
    d.show()
    assert {c.name for c in proto.conditions} == set(EXPECTED_LINES)
    for c in proto.conditions:
        d.show_condition(c.name, c.boundary_deg)
        assert d.boundary_positions() == EXPECTED_LINES[c.name], c.name
        # Fixed scale: the same degrees land on the same pixels whatever the condition.
        for x in d.boundary_positions():
            px = d.view.mapFromScene(x, 0.5).x()
            assert px == pytest.approx(d.view.viewport().width() * (x + 30.0) / 60.0, abs=2)
    for ln in d.lines:
        assert ln.pen().isCosmetic() and ln.pen().widthF() >= 6  # thick at any window size
    d.set_angle(math.radians(10.0))  # counter-clockwise: the indicator moves left
    assert d.indicator_position() == pytest.approx(-10.0)
    d.set_angle(math.radians(-90.0))  # clamped at the edge, never off the screen
    assert d.indicator_position() == pytest.approx(30.0)


def test_dashboard_follows_the_angle_source_and_chooses_a_screen(qtbot):
    angle = [math.radians(-4.0)]
    d = SubjectDashboard(lambda: angle[0])
    qtbot.addWidget(d)
    qtbot.waitUntil(lambda: d.indicator_position() == pytest.approx(4.0), timeout=1000)
    screens = SubjectDashboard.screens()
    assert screens
    d.show_on(screens[-1], full_screen=True)
    assert d.isFullScreen() and d.screen().name() == screens[-1].name()
    d.show_on(screens[0], full_screen=False)
    assert not d.isFullScreen()


# -- the live admittance panel -------------------------------------------------------------------

POINTS = [
    ("PT", 210.0, {"I_i": 0.02, "b_i": 2.0, "k_i": 60.0, "b_c": 6.0, "k_c": 900.0}),
    ("BT5", 150.0, {"I_i": 0.02, "b_i": 1.8, "k_i": 40.0, "b_c": 5.0, "k_c": 700.0}),
    ("BT12", 100.0, {"I_i": 0.02, "b_i": 1.5, "k_i": 25.0, "b_c": 4.0, "k_c": 500.0}),
    ("BT18", 80.0, {"I_i": 0.02, "b_i": 1.4, "k_i": 18.0, "b_c": 3.5, "k_c": 400.0}),
    ("RT", 78.0, {"I_i": 0.02, "b_i": 1.0, "k_i": 9.0, "b_c": 3.0, "k_c": 300.0}),
]


def results_json(path) -> None:
    pts = [
        {"condition": c, "mu_N": mu, "included": c != "RT",
         "parameters": {k: {"value": v, "unit": ""} if k == "k_i" else v for k, v in p.items()}}
        for c, mu, p in POINTS
    ]  # fmt: skip
    path.write_text(json.dumps({"format": "steerlab-report-results",
                                "lpv": {"order": 2, "operating_points": pts}}))  # fmt: skip


def test_live_admittance_panel(qtbot, tmp_path):
    from steerlab.analysis.lpv import PhysicalLPV

    live = LiveData()
    p = LiveAdmittancePanel(live)
    qtbot.addWidget(p)
    assert p.status.text() == NO_MODEL
    (tmp_path / "bad.json").write_text("{}")
    assert not p.load(tmp_path / "bad.json")
    assert p.status.text().startswith(NO_MODEL) and p.model is None
    results_json(tmp_path / "results.json")
    assert p.load(tmp_path / "results.json")
    assert "RT" in p.status.text() and p.model.conditions == ("BT18", "BT12", "BT5", "PT")
    ref = PhysicalLPV.fit([x for x in POINTS if x[0] != "RT"], order=2)
    # Live grip force → μ → k_i(μ).
    live(ev.TrialStarted("k", 1, 1, "BT12", {"fs_hz": 100.0}, 300))
    grip = np.full(300, 120.0)
    live(ev.SamplesAcquired("k", 0, {"time_s": np.arange(300) / 100, "grip_force_N": grip}))
    p.refresh()
    assert p.mu == pytest.approx(120.0)
    assert p.k_i == pytest.approx(ref.parameters(120.0)["k_i"])
    np.testing.assert_allclose(p.curve.yData, np.abs(ref.frequency_response(120.0, p.f_hz)))
    p.update_mu(500.0)  # above the operating points: clipped, and said so
    assert "clipped" in p.mu_label.text()
    assert p.k_i == pytest.approx(ref.parameters(210.0)["k_i"])


@pytest.mark.parametrize("rig_file", ["simulated.toml", "sensodrive-sim.toml"])
def test_rig_file_runs_its_loop_in_a_process_and_the_stop_reaches_it(qtbot, tmp_path, rig_file):
    # A simulated rig file (a CiA 402 drive, a SENSO-Wheel): the drive and glove unit
    # simulated, the loop in its own process (hardware.live). Lenient stall limit: behaviour,
    # not timing, on a shared machine.
    rig = tmp_path / "rig.toml"
    text = (ROOT / "hardware" / "rigs" / rig_file).read_text()
    rig.write_text(re.sub(r"(?m)^loop_stall_s = \S+", "loop_stall_s = 0.5", text))
    proto = parse_protocol(short_protocol_text(loop_rate_hz=1000.0), "short1k.toml")
    w = ExperimenterWindow(proto, tmp_path / "data", rig_path=str(rig))
    qtbot.addWidget(w)
    qtbot.addWidget(w.dashboard)
    open_new(qtbot, w)
    assert not w.controller.rig.simulated
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.live.total_received > 500, timeout=20000)
    assert w.controller.rig.status()["drive_enabled"]
    click(qtbot, w.estop_button)
    qtbot.waitUntil(lambda: worker_finished(w), timeout=10000)
    assert ended(w)[0].status == "aborted" and "emergency stop" in ended(w)[0].reason
    assert w.controller.rig.status()["drive_enabled"] is False
    w.refresh_status()
    assert w.hw_labels["rig"].text() == "rig.toml"
    w.close()


# -- the command ---------------------------------------------------------------------------------


def test_unknown_rig_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(RigError, match="no such rig file"):
        make_rig_loop(str(tmp_path / "nope.toml"), 1, load_protocol())
    assert run_gui(str(tmp_path / "nope.toml"), str(tmp_path), None) == 2
    assert "no such rig file" in capsys.readouterr().err


def test_pyside_refcount_workaround_is_in_place():
    import sys

    from steerlab.app.gui import qt_compat

    if sys.version_info < (3, 12) and qt_compat.has_refcount_bug():
        # PySide6 6.12 on 3.11 loses a reference to None per void call: the singletons must
        # have been given headroom, or a long session aborts the interpreter.
        assert qt_compat.protect() and sys.getrefcount(None) > 1 << 39
