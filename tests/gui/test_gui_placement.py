"""Where the subject's window opens: never over the experimenter's window and its EMERGENCY
STOP. Real windows on Qt's offscreen platform; screen layouts other than its default single
800×800 screen are given by its configuration file, in a process of their own (the platform
is chosen once per process)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from PySide6.QtCore import QPoint, QRect

from steerlab.app.gui.placement import MIN_DASHBOARD_WIDTH, overlaps, side_by_side
from steerlab.app.gui.session_window import ExperimenterWindow
from steerlab.protocols.protocol import load_protocol

SCRIPT = r"""
import json, tempfile
from PySide6.QtCore import QPoint
from PySide6.QtWidgets import QApplication
app = QApplication([])
from steerlab.app.gui.session_window import ExperimenterWindow
from steerlab.protocols.protocol import load_protocol

def rect(g):
    return [g.x(), g.y(), g.width(), g.height()]

w = ExperimenterWindow(load_protocol(), tempfile.mkdtemp())
w.show(); w.dashboard.show()
for _ in range(5): app.processEvents()
out = {"before": [rect(w.frameGeometry()), rect(w.dashboard.frameGeometry())]}
w.place_windows()
for _ in range(5): app.processEvents()
s = w.estop_button
tl = s.mapToGlobal(QPoint(0, 0))
out.update(exp=rect(w.frameGeometry()), dash=rect(w.dashboard.frameGeometry()),
           stop=[tl.x(), tl.y(), s.width(), s.height()],
           exp_screen=w.screen().name(), dash_screen=w.dashboard.screen().name(),
           screens={x.name(): rect(x.availableGeometry()) for x in app.screens()},
           combo=w.screen_combo.currentText())
w.close(); app.processEvents()
print(json.dumps(out))
"""


# What a trial does to the experimenter window on a screen 1600 px wide: the quality check
# fills in long values (an aborted trial, a loop with no timing figures), the alert line a
# long message, and the window itself is widened (by its content, or by a window manager).
GROW = r"""
import math
import numpy as np
from steerlab.app.gui.quality import QualityCheck
q = QualityCheck(key="02_RT_rep1_a1", condition="RT", status="aborted", n_planned=50751,
                 n_received=37480, n_engine=37480, n_measured=30000, n_periods=2,
                 band_frequencies_hz=np.geomspace(0.1, 20.0, 10), coherence=np.full(10, 0.9),
                 angle_rms_deg=8.04, boundary_deg=math.inf, outside_boundary_percent=None,
                 loop={"samples": 37480, "late_cycles_over_half_a_millisecond": 12345},
                 warnings=("trial not complete", "median coherence 0.31 < 0.5"))
w._show_quality(q)
w._alert("trial 2 (RT, attempt 1) aborted: control loop stalled (no cycle for 1.2 s); "
         "the samples up to the end are in the file")
for _ in range(10): app.processEvents()
out["filled"] = [rect(w.frameGeometry()), rect(w.dashboard.frameGeometry())]
w.resize(1373, w.height())
for _ in range(10): app.processEvents()
out["widened"] = [rect(w.frameGeometry()), rect(w.dashboard.frameGeometry())]
out["dash_screen_after"] = w.dashboard.screen().name()
"""


def screen(name: str, x: int, w: int, h: int) -> dict:
    return {"name": name, "x": x, "y": 0, "width": w, "height": h,
            "logicalDpi": 96, "logicalBaseDpi": 96, "dpr": 1}  # fmt: skip


def placed(tmp_path, screens: list[dict], then: str = "") -> dict:
    """The windows' rectangles after ``place_windows`` (and after the code ``then``, run
    before the window closes with ``w``, ``app``, ``rect`` and ``out`` in scope)."""
    cfg = tmp_path / "screens.json"
    cfg.write_text(json.dumps({"screens": screens}))
    env = dict(os.environ, QT_QPA_PLATFORM=f"offscreen:configfile={cfg}")
    end = "w.close(); app.processEvents()"
    script = SCRIPT.replace(end, f"{then}\n{end}")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                       timeout=300, check=False)  # fmt: skip
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def inside(r: list[int], s: list[int]) -> bool:
    x, y, w, h = r
    return s[0] <= x and s[1] <= y and x + w <= s[0] + s[2] and y + h <= s[1] + s[3]


def test_one_screen_puts_the_dashboard_beside_the_experimenter_window(tmp_path):
    out = placed(tmp_path, [screen("lab", 0, 1920, 1080)])
    # Without placement both open at the corner: the dashboard hides the stop button.
    assert overlaps(*map(tuple, out["before"]))
    exp, dash, stop = out["exp"], out["dash"], out["stop"]
    assert not overlaps(tuple(exp), tuple(dash))
    assert not overlaps(tuple(stop), tuple(dash))
    s = out["screens"]["lab"]
    assert inside(exp, s) and inside(dash, s)
    assert dash[0] >= exp[0] + exp[2] and dash[2] >= MIN_DASHBOARD_WIDTH


def test_second_screen_gets_the_dashboard(tmp_path):
    out = placed(tmp_path, [screen("experimenter", 0, 1920, 1080),
                            screen("subject", 1920, 1280, 1024)])  # fmt: skip
    assert out["exp_screen"] == "experimenter" and out["dash_screen"] == "subject"
    assert inside(out["dash"], out["screens"]["subject"])
    assert out["combo"].startswith("subject")  # the choice is shown under "Subject display"
    assert not overlaps(tuple(out["exp"]), tuple(out["dash"]))


def test_one_1600_px_screen_the_dashboard_stays_clear_while_the_window_grows(tmp_path):
    out = placed(tmp_path, [screen("lab", 0, 1600, 1000)], then=GROW)
    s = out["screens"]["lab"]
    exp, dash = out["exp"], out["dash"]
    assert not overlaps(tuple(exp), tuple(dash)) and inside(dash, s)
    assert exp[2] == 1600 - 8 - MIN_DASHBOARD_WIDTH
    # Long quality values and alerts wrap: the window keeps its width.
    filled_exp, filled_dash = out["filled"]
    assert filled_exp == exp and filled_dash == dash
    # Widened anyway: the two are put side by side again, the dashboard on the screen.
    wide_exp, wide_dash = out["widened"]
    assert not overlaps(tuple(wide_exp), tuple(wide_dash)), out["widened"]
    assert inside(wide_exp, s) and inside(wide_dash, s)
    assert wide_dash[2] >= MIN_DASHBOARD_WIDTH


PLOT_HEIGHTS = r"""
out["plot_heights"] = [p.getViewBox().height() for p in w.plots.plots]
"""


def test_one_1600_px_screen_leaves_the_plots_readable(tmp_path):
    out = placed(tmp_path, [screen("lab", 0, 1600, 1000)], then=GROW + PLOT_HEIGHTS)
    assert inside(out["filled"][0], out["screens"]["lab"])
    # Each plot's data area: room for three labelled ticks (it was 55-59 px).
    assert min(out["plot_heights"]) >= 62, out["plot_heights"]


def test_two_screens_the_dashboard_stays_on_the_second_and_each_window_fits(tmp_path):
    # The experimenter's screen narrower than the window's default size (1400 px).
    out = placed(tmp_path, [screen("experimenter", 0, 1280, 800),
                            screen("subject", 1280, 1600, 1000)], then=GROW)  # fmt: skip
    assert out["exp_screen"] == "experimenter" and out["dash_screen"] == "subject"
    assert inside(out["exp"], out["screens"]["experimenter"]), out["exp"]
    assert inside(out["dash"], out["screens"]["subject"])
    for exp, dash in (out["filled"], out["widened"]):
        assert not overlaps(tuple(exp), tuple(dash))
        assert inside(dash, out["screens"]["subject"])
    assert out["dash_screen_after"] == "subject"


def test_small_screen_never_covers_the_stop_button(qtbot, tmp_path):
    # The default offscreen screen (800×800) is narrower than the experimenter window's
    # minimum: the windows must overlap, but the dashboard keeps off the top-left.
    w = ExperimenterWindow(load_protocol(), tmp_path)
    qtbot.addWidget(w)
    qtbot.addWidget(w.dashboard)
    w.show()
    w.dashboard.show()
    w.place_windows()
    tl = w.estop_button.mapToGlobal(QPoint(0, 0))
    stop = QRect(tl.x(), tl.y(), w.estop_button.width(), w.estop_button.height())
    assert not w.dashboard.frameGeometry().intersects(stop)
    geo = w.screen().availableGeometry()
    assert geo.contains(w.dashboard.frameGeometry())
    # "Show" under Subject display, same screen, not full screen: beside again, not centred.
    w.dashboard.move(0, 0)
    w.show_dashboard_button.click()
    assert not w.dashboard.frameGeometry().intersects(stop)
    w.close()


@pytest.mark.parametrize(
    ("screen_w", "exp_w", "expect_exp_w"),
    [(1920, 1404, 1404), (1600, 1404, 1600 - 8 - MIN_DASHBOARD_WIDTH), (1000, 1404, 925)],
)
def test_side_by_side_arithmetic(screen_w, exp_w, expect_exp_w):
    exp, dash = side_by_side((0, 0, screen_w, 1000), (exp_w, 904), (925, 678), (1004, 404))
    assert exp[2] == expect_exp_w
    assert dash[0] + dash[2] <= screen_w  # always on the screen
    if screen_w - expect_exp_w - 8 >= MIN_DASHBOARD_WIDTH:
        assert not overlaps(exp, dash) and dash[0] == expect_exp_w + 8
    else:  # too small for both: against the right edge, away from the stop button
        assert dash[0] == screen_w - dash[2]
