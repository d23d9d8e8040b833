"""The live plots as the experimenter sees them: both hands' grip traces visible, the frame
rate in the status bar, NaN channels as gaps; and the check of Qt's X11 libraries."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from steerlab.app.gui.livedata import LiveData
from steerlab.app.gui.main import choose_platform
from steerlab.app.gui.plots import MIN_TICK_SPACING_PX, LivePlots, RateMeter, decimate_minmax
from steerlab.app.gui.session_window import ExperimenterWindow
from steerlab.app.gui.system_libs import (
    ALL_PACKAGES,
    XcbCheck,
    check_xcb,
    missing_libraries_message,
    unresolved_libraries,
    uses_xcb,
)
from steerlab.protocols import events as ev
from steerlab.protocols.protocol import load_protocol
from tests.helpers import ROOT


def feed(live: LiveData, seconds: float, fs: float = 1000.0, left_share: float = 0.5) -> None:
    live(ev.TrialStarted("S01/t1", 1, 1, "BT12", {"fs_hz": fs}, int(seconds * fs)))
    t = np.arange(int(seconds * fs)) / fs
    grip = 40.0 + 5.0 * np.sin(2 * np.pi * 0.2 * t)
    block = {
        "time_s": t,
        "perturbation_torque_Nm": np.sin(2 * np.pi * 1.0 * t),
        "driver_torque_Nm": -np.sin(2 * np.pi * 1.0 * t),
        "wheel_angle_rad": 0.1 * np.sin(2 * np.pi * 0.3 * t),
        "grip_force_N": grip,
        "grip_force_left_N": left_share * grip,
        "grip_force_right_N": (1 - left_share) * grip,
    }
    live(ev.SamplesAcquired("S01/t1", 0, block))


def test_left_and_right_grip_are_both_visible_when_equal(qtbot):
    live = LiveData()
    p = LivePlots(live)
    qtbot.addWidget(p)
    p.resize(900, 600)
    p.show()
    feed(live, 12.0)  # equal hands: the right trace lies exactly on the left one
    p.refresh()
    left, right, total = (p.curves[c] for c in
                          ("grip_force_left_N", "grip_force_right_N", "grip_force_N"))  # fmt: skip
    grip_plot = p.plots[3]
    assert {left, right, total} <= set(grip_plot.items)
    np.testing.assert_array_equal(left.getData()[1], right.getData()[1])
    # Distinct pens: the left a wide pale band drawn first, the right a thin line on top.
    assert left.width_px >= 3 and right.width_px == 1 and total.width_px == 1
    assert len({left.pen.color().name(), right.pen.color().name(), total.pen.color().name()}) == 3
    assert left.zValue() <= right.zValue()
    order = [i for i in grip_plot.items if i in (left, right)]
    assert order == [left, right]  # same z: the later one is drawn on top
    # A legend names the three, with the pens they are drawn with.
    legend = p.legends[0]
    names = [label.text for _, label in legend.items]
    assert names == ["left", "right", "total"]
    assert legend.items[0][0].item.opts["pen"].widthF() == left.width_px
    # Pixels: the band shows above and below the right trace at the same x.
    img = p.grab().toImage()
    vb = grip_plot.getViewBox()
    x_view, y_view = -5.0, float(right.getData()[1][len(right.getData()[1]) // 2])
    pt = vb.mapViewToDevice(pg_point(x_view, y_view))
    colours = {img.pixelColor(int(pt.x()), int(pt.y()) + dy).name() for dy in (-1, 0, 1)}
    assert left.pen.color().name() in colours


def pg_point(x: float, y: float):
    from PySide6.QtCore import QPointF

    return QPointF(x, y)


def test_curves_get_one_point_per_pixel_column_and_keep_peaks(qtbot):
    live = LiveData()
    p = LivePlots(live)
    qtbot.addWidget(p)
    p.resize(900, 600)
    p.show()
    feed(live, 12.0)
    p.refresh()
    width = int(p.plots[0].getViewBox().width())
    x, y = p.curves["perturbation_torque_Nm"].getData()
    assert 2 <= len(x) <= width
    assert np.all(np.diff(x) >= 0)
    # min/max decimation keeps the extremes of the raw data
    t = np.arange(10_000) / 1000.0
    raw = np.sin(2 * np.pi * 3 * t)
    raw[4321] = 7.0
    _, d = decimate_minmax(t, raw, width)
    assert d.max() == 7.0 and d.min() == pytest.approx(raw.min())


def test_a_channel_the_rig_does_not_send_is_a_gap_not_a_crash(qtbot):
    live = LiveData()
    p = LivePlots(live)
    qtbot.addWidget(p)
    p.show()
    live(ev.TrialStarted("k", 1, 1, "RT", {"fs_hz": 100.0}, 1000))
    t = np.arange(500) / 100.0
    live(ev.SamplesAcquired("k", 0, {"time_s": t, "grip_force_N": np.ones(500)}))
    p.refresh()
    x, y = p.curves["grip_force_left_N"].getData()
    assert np.isnan(y).all()
    assert p.ranges[3].hi > 1.0  # the range follows the channel that is there


def test_flat_traces_keep_a_readable_scale_and_the_unit_labels_apart(qtbot):
    # After an abort, or before the perturbation fades in, every trace is flat: the y ranges
    # must not close in on rounding noise, and no SI factor ("N·m (x1e-12)") may join a unit
    # label and run into the next plot's.
    live = LiveData()
    p = LivePlots(live)
    qtbot.addWidget(p)
    p.resize(900, 520)
    p.show()
    p.set_boundary(0.0)  # PT: the lines on the centre hold nothing open
    for r in p.ranges:
        r.hold_s = 0.0  # shrink at once, as 3 s of flat data would
    live(ev.TrialStarted("k", 1, 1, "PT", {"fs_hz": 100.0}, 1000))
    channels = ("perturbation_torque_Nm", "driver_torque_Nm", "wheel_angle_rad",
                "grip_force_left_N", "grip_force_right_N")  # fmt: skip
    for start in (0, 300):
        t = (start + np.arange(300)) / 100.0
        block = {"time_s": t, "grip_force_N": np.full(300, 40.0)}
        block |= {c: np.zeros(300) for c in channels}
        live(ev.SamplesAcquired("k", start, block))
        p.refresh()
    qtbot.wait(50)
    labels = []
    for plot in p.plots:
        lo, hi = plot.getViewBox().viewRange()[1]
        assert hi - lo >= 1.0, (plot.titleLabel.text, lo, hi)
        axis = plot.getAxis("left")
        text = axis.label.toPlainText()
        assert "(x" not in text and "e-" not in text, text
        labels.append(axis.label.sceneBoundingRect())
    for i, a in enumerate(labels):
        for b in labels[i + 1 :]:
            assert not a.intersects(b), (a, b)


def _grow(live: LiveData, start: int, amplitude: float, fs: float = 1000.0) -> None:
    t = (start + np.arange(20)) / fs
    wave = amplitude * np.sin(2 * np.pi * 3.0 * t)
    block = {"time_s": t, "perturbation_torque_Nm": wave, "driver_torque_Nm": wave,
             "wheel_angle_rad": 0.01 * wave, "grip_force_N": 40 + 10 * wave,
             "grip_force_left_N": 20 + 5 * wave, "grip_force_right_N": 20 + 5 * wave}  # fmt: skip
    live(ev.SamplesAcquired("S01/t1", start, block))


def test_one_frame_per_refresh_painted_once_even_when_the_ranges_change(qtbot):
    """The status bar's frames are refreshes that reached the screen: never more than the
    timer's rate. A new y range (every refresh here) and a wider tick label repaint nothing
    a second time."""
    live = LiveData()
    p = LivePlots(live)
    qtbot.addWidget(p)
    p.resize(1000, 500)
    p.show()
    p.stop()  # refreshed by hand below
    qtbot.waitExposed(p)
    live(ev.TrialStarted("S01/t1", 1, 1, "BT12", {"fs_hz": 1000.0}, 100_000))
    qtbot.wait(50)
    frames0, paints0 = p.frames.frames, p.frames.paints
    n = 30
    for i in range(n):
        _grow(live, 20 * i, 1.0 + 0.5 * i)  # the data leave the y range every time
        p.refresh()
        qtbot.wait(15)
    assert p.frames.frames - frames0 == n
    assert p.frames.paints - paints0 <= n + 2, p.frames.paints - paints0


@pytest.mark.parametrize("height", [433, 330])
def test_y_axis_labels_keep_apart_on_short_plots(qtbot, height):
    """433 px: the plots in a 1232×904 window (a 1600×1000 screen); 330 px: nearly their
    smallest. Labels at least MIN_TICK_SPACING_PX apart, or 70 % of it rather than one alone."""
    live = LiveData()
    p = LivePlots(live)
    qtbot.addWidget(p)
    p.resize(900, height)
    p.show()
    qtbot.waitExposed(p)
    feed(live, 12.0)
    p.refresh()
    qtbot.wait(20)
    for plot in p.plots:
        vb, axis = plot.getViewBox(), plot.getAxis("left")
        lo, hi = vb.viewRange()[1]
        labelled = axis.tickValues(lo, hi, vb.height())[0][1]
        px = (labelled[1] - labelled[0]) / (hi - lo) * vb.height() if len(labelled) > 1 else 1e9
        name = plot.titleLabel.text
        assert 1 <= len(labelled) <= 4, (name, labelled)
        assert px >= MIN_TICK_SPACING_PX or (
            len(labelled) >= 2 and px >= 0.7 * MIN_TICK_SPACING_PX
        ), (name, labelled, px)
        assert axis.style["maxTextLevel"] == 0  # the minor ticks stay unlabelled


def test_frame_rate_in_the_status_bar(qtbot, tmp_path):
    w = ExperimenterWindow(load_protocol(), tmp_path)
    qtbot.addWidget(w)
    qtbot.addWidget(w.dashboard)
    w.show()
    assert w.fps_label.text() == "plots: —"
    assert w.fps_label in w.statusBar().findChildren(type(w.fps_label))
    feed(w.live, 2.0)
    w.refresh_status()  # first reading
    frames0 = w.plots.frames.frames

    def more_data_and_frames() -> bool:
        n = w.live.n_written
        w.live(ev.SamplesAcquired("S01/t1", n, {"time_s": np.arange(n, n + 20) / 1000.0}))
        return w.plots.frames.frames > frames0 + 5

    qtbot.waitUntil(more_data_and_frames, timeout=10_000)
    w.refresh_status()
    text = w.fps_label.text()
    assert text.startswith("plots: ") and text.endswith(" frames/s"), text
    assert int(text.split()[1]) > 0
    w.close()


def test_rate_meter():
    m = RateMeter()
    assert m.rate(10, 1.0) is None
    assert m.rate(50, 2.0) == pytest.approx(40.0)
    assert m.rate(50, 2.0) is None  # no time passed: no rate


# -- Qt's X11 libraries ----------------------------------------------------------------------

LDD_MISSING = """\
\tlinux-vdso.so.1 (0x00007ffd)
\tlibxcb-icccm.so.4 => not found
\tlibxcb-keysyms.so.1 => not found
\tlibxcb.so.1 => /lib/x86_64-linux-gnu/libxcb.so.1 (0x00007f)
\tlibxcb-icccm.so.4 => not found
\tlibweird.so.9 => not found
"""


def test_ldd_output_names_the_missing_libraries_and_their_packages():
    missing = unresolved_libraries(LDD_MISSING)
    assert missing == ("libxcb-icccm.so.4", "libxcb-keysyms.so.1", "libweird.so.9")
    c = XcbCheck(None, missing)
    assert not c.ok and c.packages == ("libxcb-icccm4", "libxcb-keysyms1")
    assert c.unknown == ("libweird.so.9",)
    msg = missing_libraries_message(c)
    assert "sudo apt-get install libxcb-icccm4 libxcb-keysyms1\n" in msg
    assert "libweird.so.9" in msg and " ".join(ALL_PACKAGES) in msg


def _loader_finds(soname: str) -> bool:
    """The dynamic loader asked directly (dlopen), not through ldd."""
    import ctypes

    try:
        ctypes.CDLL(soname)
    except OSError:
        return False
    return True


def test_the_real_plugin_is_checked_with_ldd():
    # Whatever this machine has installed, the check must agree with the dynamic loader itself:
    # every library it calls missing fails to dlopen, and the two that a plain Debian lacks
    # (docs/gui.md) are called missing exactly when dlopen cannot find them.
    c = check_xcb()
    assert c.plugin is not None and c.plugin.name == "libqxcb.so"
    for soname in c.missing:
        assert not _loader_finds(soname), soname
    for soname in ("libxcb-icccm.so.4", "libxcb-keysyms.so.1"):
        assert (soname in c.missing) == (not _loader_finds(soname)), (soname, c.missing)
    if not c.ok:
        assert "sudo apt-get install" in missing_libraries_message(c)


def test_platform_choice(monkeypatch):
    assert uses_xcb({}, "linux") and uses_xcb({"QT_QPA_PLATFORM": "xcb"}, "linux")
    assert not uses_xcb({"QT_QPA_PLATFORM": "offscreen"}, "linux")
    assert not uses_xcb({"QT_QPA_PLATFORM": "wayland;xcb"}, "linux")
    assert not uses_xcb({}, "darwin")
    assert choose_platform({"QT_QPA_PLATFORM": "offscreen"}) is None
    import steerlab.app.gui.main as main

    monkeypatch.setattr(main, "check_xcb", lambda platform="xcb": XcbCheck(
        None, ("libxcb-icccm.so.4",) if platform == "xcb" else ()))  # fmt: skip
    env: dict[str, str] = {}
    msg = choose_platform(env)
    assert msg is not None and "libxcb-icccm4" in msg
    env = {"WAYLAND_DISPLAY": "wayland-0"}
    assert choose_platform(env) is None and env["QT_QPA_PLATFORM"] == "wayland"


def test_the_check_runs_before_any_qt_gui_module_is_loaded():
    # A missing X11 library aborts the interpreter when Qt's GUI starts: the check must come
    # first, so importing `steerlab gui`'s entry point and checking load no Qt GUI module.
    import json
    import subprocess
    import sys

    code = (
        "import json, sys\n"
        "from steerlab.app.gui.main import choose_platform\n"
        "from steerlab.app.gui.system_libs import check_xcb\n"
        "choose_platform({}); check_xcb()\n"
        "qt = [m for m in sys.modules if m.startswith(('PySide6.', 'pyqtgraph'))]\n"
        "print(json.dumps(sorted(qt)))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1]) == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Qt's X11 default: Linux")
def test_no_display_is_one_line_and_exit_code_2_before_qt_starts(tmp_path):
    # Without the check Qt aborts the interpreter (status 134) with a hint about
    # libxcb-cursor0, which is installed.
    unset = ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM")
    env = {k: v for k, v in os.environ.items() if k not in unset}
    r = subprocess.run([sys.executable, "-m", "steerlab", "gui", "--out", str(tmp_path / "d")],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip() == (
        "steerlab gui: no display (DISPLAY and WAYLAND_DISPLAY are unset); run it on a desktop "
        "session, or set QT_QPA_PLATFORM=offscreen for a headless check"
    )
    from steerlab.app.gui.system_libs import no_display

    assert no_display({}, "linux") is not None
    assert no_display({"QT_QPA_PLATFORM": "xcb"}, "linux") is not None
    assert no_display({"DISPLAY": ":0"}, "linux") is None
    assert no_display({"WAYLAND_DISPLAY": "wayland-0"}, "linux") is None
    assert no_display({"QT_QPA_PLATFORM": "offscreen"}, "linux") is None
    assert no_display({}, "darwin") is None
