"""The subject's road view (offscreen Qt) and one driving trial through the GUI's live loop."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("PySide6")

from PySide6.QtGui import QColor  # noqa: E402

from steerlab.app.gui.rig import make_rig_loop  # noqa: E402
from steerlab.app.gui.road_view import RoadView, VehicleFeed, road_of_trial  # noqa: E402
from steerlab.app.gui.session_window import ExperimenterWindow  # noqa: E402
from steerlab.protocols import events as ev  # noqa: E402
from steerlab.protocols.driving import (  # noqa: E402
    DrivingCondition,
    DrivingSetup,
    RoadSpec,
    VehicleSpec,
)
from steerlab.protocols.protocol import parse_protocol  # noqa: E402
from tests.gui.test_gui import PacedLoop, click, open_new, short_protocol_text  # noqa: E402

STRAIGHT = RoadSpec(min_radius_m=1e9, max_radius_m=1e9)


def _drive(road_spec=STRAIGHT, speed=15.0):
    return DrivingSetup(DrivingCondition(speed), VehicleSpec(), road_spec.generate(600.0))


def _red_pixels(img, x0, x1, y0, y1) -> int:
    n = 0
    for x in range(x0, x1, 2):
        for y in range(y0, y1, 2):
            c = QColor(img.pixel(x, y))
            n += c.red() > 200 and c.green() < 100 and c.blue() < 100
    return n


def test_the_lane_is_drawn_around_the_car(qtbot):
    v = RoadView()
    qtbot.addWidget(v)
    v.resize(600, 400)
    drive = _drive()
    v.set_drive(drive)
    v.set_state({"road_distance_m": 50.0, "lateral_position_m": 0.0, "heading_error_rad": 0.0})
    left, right, centre, _ = v.lane_outline()
    w = 3.6  # the lead-in is wide
    near = np.abs(left[:, 1]) < 5
    # Car coordinates: x to the right, y ahead; the left edge at −w/2, the right at +w/2.
    np.testing.assert_allclose(left[near, 0], -w / 2, atol=1e-6)
    np.testing.assert_allclose(right[near, 0], w / 2, atol=1e-6)
    np.testing.assert_allclose(centre[:, 0], 0.0, atol=1e-6)
    assert centre[0, 1] == pytest.approx(-v.behind_m)
    assert centre[-1, 1] == pytest.approx(v.ahead_s * 15.0)
    assert v.outside == 0
    # The car 0.5 m left of the centre: the lane appears 0.5 m to its right.
    v.set_state({"road_distance_m": 50.0, "lateral_position_m": 0.5, "heading_error_rad": 0.0})
    left, right, _, _ = v.lane_outline()
    assert left[near, 0] == pytest.approx(-w / 2 + 0.5)
    # A heading error to the left: the road ahead turns to the right on the screen.
    v.set_state({"road_distance_m": 50.0, "lateral_position_m": 0.0, "heading_error_rad": 0.1})
    _, _, centre, _ = v.lane_outline()
    assert centre[-1, 0] > 1.0


def test_leaving_the_lane_turns_the_car_and_the_edge_red(qtbot):
    v = RoadView()
    qtbot.addWidget(v)
    v.resize(600, 400)
    v.set_drive(_drive())
    v.set_state({"road_distance_m": 50.0, "lateral_position_m": 0.0, "heading_error_rad": 0.0})
    v.lane_outline()
    img = v.grab().toImage()
    ox, oy, sx, sy = v.mapping()
    car = (int(ox - 0.6 * sx), int(ox + 0.6 * sx), int(oy - 1.5 * sy), int(oy + 1.0 * sy))
    assert _red_pixels(img, *car) == 0
    v.set_state({"road_distance_m": 50.0, "lateral_position_m": 1.2, "heading_error_rad": 0.0})
    v.lane_outline()
    assert v.outside == 1  # over the left edge: 1.2 + 0.9 > 1.8
    img = v.grab().toImage()
    assert _red_pixels(img, *car) > 20
    v.set_state({"road_distance_m": 50.0, "lateral_position_m": -1.2, "heading_error_rad": 0.0})
    v.lane_outline()
    assert v.outside == -1


DRIVE_ONLY = """
[[conditions]]
name = "DRIVE"
task = "driving"
speed_mps = 15.0
friction = 1.0
perturbation_level = 1.0
"""


def test_a_driving_trial_runs_through_the_live_loop_with_the_road_on_the_dashboard(qtbot, tmp_path):
    text = short_protocol_text()
    head = text.split("[[conditions]]", 1)[0]
    protocol = parse_protocol(head + DRIVE_ONLY, "drive.toml")
    rigs = []

    def factory(path, subject, protocol):
        h = make_rig_loop(None, subject, protocol, realtime=False)
        rigs.append(h)
        return replace(h, loop=PacedLoop(h.loop, protocol.loop_rate_hz))

    w = ExperimenterWindow(protocol, tmp_path / "data", rig_factory=factory)
    qtbot.addWidget(w)
    qtbot.addWidget(w.dashboard)
    w.show()
    w.dashboard.show()
    open_new(qtbot, w)
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.road.view.isVisible(), timeout=10000)
    assert not w.dashboard.view.isVisible()  # the boundary indicator gives way to the road
    qtbot.waitUntil(lambda: w.road.view.state.get("road_distance_m", 0.0) > 5.0, timeout=15000)
    qtbot.waitUntil(lambda: w.trial_states()[1] == "done", timeout=30000)
    started = next(e for e in w.events_seen if isinstance(e, ev.TrialStarted))
    d = started.attributes["driving"]
    d = json.loads(d) if isinstance(d, str) else d
    assert d["speed_mps"] == 15.0
    # The dashboard's road is the loop's road (rebuilt from the trial's attribute).
    drive = road_of_trial(started.attributes, protocol)
    assert drive.road.seed == protocol.road.seed + 0  # the familiarization trial
    rig = rigs[0]
    assert set(rig.display.vehicle) >= {"road_distance_m", "lateral_position_m"}
    w.close()


def test_the_vehicle_feed_keeps_the_newest_car_state_from_the_engine():
    feed = VehicleFeed()
    assert feed.latest() is None
    block = {"time_s": np.arange(3) / 1000, "road_distance_m": np.array([1.0, 1.1, 1.2]),
             "lateral_position_m": np.array([0.0, 0.1, 0.2]),
             "heading_error_rad": np.zeros(3)}  # fmt: skip
    feed(ev.SamplesAcquired("k", 0, block))
    got = feed.latest()
    assert got["road_distance_m"] == pytest.approx(1.2)
    assert got["lateral_position_m"] == pytest.approx(0.2)
    feed(ev.SamplesAcquired("k", 3, {"time_s": np.arange(3) / 1000}))  # a boundary task's block
    assert feed.latest()["road_distance_m"] == pytest.approx(1.2)
