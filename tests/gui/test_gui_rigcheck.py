"""The GUI's rig check: the button opens a one-trial hands-off session, the subject dashboard
tells the experimenter to let go, and after the trial the wheel is identified off the GUI
thread (rig.json and index.html beside the recording)."""

from __future__ import annotations

import json

import h5py

from steerlab.analysis.rigcheck import PARAMS
from steerlab.app.gui.session_window import HANDS_OFF_MESSAGE, RigCheckDone
from tests.gui.test_gui import (  # noqa: F401 (fixtures)
    click,
    no_thread_left_running,
    rigs,
    short_protocol,
    window,
    worker_finished,
)


def test_rig_check_from_the_gui(qtbot, window):  # noqa: F811
    w = window
    w.rig_check_periods = 1
    click(qtbot, w.rig_check_button)
    assert w.controller.is_rig_check, w.alert_label.text()
    assert w.dashboard.label.text() == HANDS_OFF_MESSAGE
    assert not w.open_button.isEnabled() and not w.rig_check_button.isEnabled()
    assert w.trial_states() == {1: "pending"}
    assert "let go of the wheel" in w.instructions_label.text()
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.dashboard.active, timeout=5000)
    assert w.dashboard.label.text() == HANDS_OFF_MESSAGE
    qtbot.waitUntil(lambda: any(isinstance(e, RigCheckDone) for e in w.events_seen), timeout=60000)
    done = next(e for e in w.events_seen if isinstance(e, RigCheckDone))
    w.rig_check_thread.join(10)
    assert done.error is None, done.error
    assert w.trial_states() == {1: "done"}
    assert "rig check: PASS" in w.alert_label.text(), w.alert_label.text()
    assert w.dashboard.label.text().startswith("Rig check done")
    path = w.controller.path
    assert path.parent.parent.name == "rigcheck"
    with h5py.File(path, "r") as f:
        assert bool(f.attrs["hands_off_check"])
        (g,) = f["trials"].values()
        assert bool(g.attrs["hands_off"]) and g.attrs["status"] == "complete"
    d = json.loads((path.parent / "rig.json").read_text())
    # The GUI's simulated rig renders Table 1 on a 0.3 kg·m² wheel, at the protocol's 200 Hz.
    for p, true in (("inertia_kgm2", 0.3), ("damping_Nms_per_rad", 2.0),
                    ("stiffness_Nm_per_rad", 4.2)):  # fmt: skip
        assert abs(d[p]["value"] - true) <= 3 * d[p]["sem"], (p, d[p])
    assert set(PARAMS) <= set(d)
    assert (path.parent / "index.html").exists()
    qtbot.waitUntil(lambda: worker_finished(w), timeout=10000)
    # The same verdict as the command line and the page: a recording with hands on the wheel
    # is not valid, not a pass or a fail of the rig.
    done.fit.prep.warnings.append("hands on the wheel? (made up for this test)")
    w._show_rig_check(done)
    assert "rig check: NOT VALID" in w.alert_label.text(), w.alert_label.text()
