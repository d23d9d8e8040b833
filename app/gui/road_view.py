"""The subject's view of a driving trial: the road from above, the lane edges and the car.

Top-down, heading-up, centred on the car (ours). Why not the driver's seat: the subject's task
is the boundary task's, keep the car between two lines, and from above the lines and the car's
distance to them are drawn at one scale everywhere on the screen, as the boundary lines are; a
perspective view compresses exactly the near-lateral distance the subject must judge, and
needs a horizon, a camera height and a field of view that would all be ours to invent. The
view shows ``behind_m`` behind the car and ``ahead_s`` seconds of road ahead (the driver's far
point is 2 s ahead, ``hardware/sim/driver.py``).

Feedback, as in the boundary tasks: the lane edges are drawn in the boundary lines' red; when
the car's side crosses an edge (|lateral position| + car width / 2 > lane width / 2) that edge
is drawn thick and the car turns red until it is back inside.

Scene geometry comes from the same seeded road the loop drives (``protocols/driving.py``), rebuilt
from the trial's ``driving`` attribute and the protocol (the road is not sent sample by sample).
The car's state comes from a callable returning ``hardware.vehicle.DRIVING_CHANNELS`` (the
simulated rig's display in process, every 20 cycles; else the newest block the engine received,
:class:`VehicleFeed`, every 50 ms; None when unknown). Drawing is QPainter on a plain widget:
a few hundred points per frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt, QTimer
from PySide6.QtGui import QBrush, QColor, QPainter, QPen, QPolygonF
from PySide6.QtWidgets import QBoxLayout, QWidget

import steerlab.app.gui.qt_compat  # noqa: F401 (PySide6 6.12 on Python 3.11: see that module)
from steerlab.app.gui.dashboard import SubjectDashboard
from steerlab.hardware.vehicle import DRIVING_CHANNELS
from steerlab.protocols.driving import DrivingCondition, DrivingSetup, Road, VehicleSpec
from steerlab.protocols.protocol import Protocol

_BG = QColor("#101010")
_ROAD = QColor("#2b2b2b")
_EDGE = QColor("#ff3b30")  # the boundary lines' colour (app/gui/dashboard.py)
_CENTRE = QColor("#606060")
_CAR = QColor("#ffffff")
_CAR_OUT = QColor("#ff3b30")

VehicleSource = Callable[[], Mapping[str, float] | None]


def road_of_trial(attributes: Mapping[str, Any], protocol: Protocol) -> DrivingSetup | None:
    """The drive of a trial from its ``driving`` attribute (None for other trials)."""
    import json

    d = attributes.get("driving")
    if not d:
        return None
    d = json.loads(d) if isinstance(d, str) else dict(d)
    road = protocol.road.generate(float(d["road_length_m"]), seed=int(d["road_seed"]))
    vehicle = VehicleSpec(**d["vehicle"]) if "vehicle" in d else protocol.vehicle
    cond = DrivingCondition(
        float(d["speed_mps"]), float(d["friction"]), float(d["perturbation_level"])
    )
    return DrivingSetup(cond, vehicle, road)


class RoadView(QWidget):
    """Paints the road around the car; :meth:`set_drive` before, ``vehicle_source`` during."""

    def __init__(
        self,
        vehicle_source: VehicleSource | None = None,
        *,
        ahead_s: float = 2.5,
        behind_m: float = 8.0,
        lateral_gain: float = 3.0,
        fps: float = 60.0,
        parent: QWidget | None = None,
    ) -> None:
        super().__init__(parent)
        self.vehicle_source = vehicle_source
        self.ahead_s, self.behind_m, self.lateral_gain = ahead_s, behind_m, lateral_gain
        self.drive: DrivingSetup | None = None
        self.state: dict[str, float] = {}
        self.outside = 0  # −1: over the right edge, +1: over the left, 0: inside
        self.setMinimumSize(320, 240)
        self.setAttribute(Qt.WidgetAttribute.WA_OpaquePaintEvent, True)
        self.timer = QTimer(self)
        self.timer.setInterval(int(round(1000.0 / fps)))
        self.timer.timeout.connect(self.update)
        self.timer.start()

    def set_drive(self, drive: DrivingSetup | None) -> None:
        self.drive = drive
        self.state = {}
        # The road's distance at each of its points; set with (and only with) a drive.
        self._grid = None if drive is None else np.arange(len(drive.road.x_m)) * drive.road.grid_m
        self.update()

    def set_state(self, channels: Mapping[str, float]) -> None:
        self.state = dict(channels)

    # -- geometry (plain numbers, tested without painting) ---------------------------------------
    def lane_outline(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        """(left edge, right edge, centre) as (n, 2) points in car coordinates (x right,
        y ahead, metres), and the car's lateral position; None before the car is known."""
        drive, g = self.drive, self._grid
        if drive is None or g is None:
            return None
        st = self.state
        if self.vehicle_source is not None:
            got = self.vehicle_source()
            if got:
                st = self.state = dict(got)
        if "road_distance_m" not in st:
            st = {"road_distance_m": 0.0, "lateral_position_m": 0.0, "heading_error_rad": 0.0}
        road: Road = drive.road
        s, y, psi = st["road_distance_m"], st["lateral_position_m"], st["heading_error_rad"]
        ahead = self.ahead_s * drive.condition.speed_mps
        ss = np.linspace(s - self.behind_m, s + ahead, 160)
        h = np.interp(ss, g, road.heading_rad)
        cx, cy = np.interp(ss, g, road.x_m), np.interp(ss, g, road.y_m)
        w = np.interp(ss, g, road.lane_width_m)
        h0 = float(np.interp(s, g, road.heading_rad))
        # The car: on the normal of the centre line at s, y to the left; heading h0 + ψ_e.
        px = float(np.interp(s, g, road.x_m)) - y * math.sin(h0)
        py = float(np.interp(s, g, road.y_m)) + y * math.cos(h0)
        heading = h0 + psi
        nx, ny = -np.sin(h), np.cos(h)  # left normal of the centre line

        def to_car(x: np.ndarray, yy: np.ndarray) -> np.ndarray:
            dx, dy = x - px, yy - py
            c, sn = math.cos(heading), math.sin(heading)
            fwd = c * dx + sn * dy
            left = -sn * dx + c * dy
            return np.column_stack([-left, fwd])  # screen x to the right

        left = to_car(cx + nx * w / 2, cy + ny * w / 2)
        right = to_car(cx - nx * w / 2, cy - ny * w / 2)
        centre = to_car(cx, cy)
        width_here = float(np.interp(s, g, road.lane_width_m))
        over = abs(y) + drive.vehicle.width_m / 2 - width_here / 2
        self.outside = 0 if over <= 0 else (1 if y > 0 else -1)
        return left, right, centre, y

    def mapping(self) -> tuple[float, float, float, float]:
        """(x0, y0, px per m across, px per m along): the car's point and the two scales.

        Along the road the view holds behind_m + ahead_s of road, the car low down; across it,
        distances are drawn ``lateral_gain`` times larger (ours: at one scale a 3.6-m lane over
        45 m of road is a thin strip; the boundary task magnifies the angle in the same way)."""
        ahead = self.ahead_s * (self.drive.condition.speed_mps if self.drive else 15.0)
        sy = self.height() / (ahead + self.behind_m)
        return self.width() / 2.0, self.height() - self.behind_m * sy, sy * self.lateral_gain, sy

    # -- painting ----------------------------------------------------------------------------------
    def paintEvent(self, event) -> None:  # noqa: N802 (Qt's name)
        p = QPainter(self)
        p.fillRect(self.rect(), _BG)
        drive, geo = self.drive, self.lane_outline()
        if drive is None or geo is None:
            p.end()
            return
        left, right, centre, _ = geo
        ox, oy, sx, sy = self.mapping()

        def points(pts: np.ndarray) -> list[QPointF]:
            return [QPointF(ox + a * sx, oy - b * sy) for a, b in pts]

        def poly(pts: np.ndarray) -> QPolygonF:
            return QPolygonF(points(pts))

        p.setRenderHint(QPainter.RenderHint.Antialiasing, True)
        p.setPen(Qt.PenStyle.NoPen)
        p.setBrush(QBrush(_ROAD))
        p.drawPolygon(QPolygonF(points(left) + points(right[::-1])))
        dash = QPen(_CENTRE, 2, Qt.PenStyle.DashLine)
        p.setPen(dash)
        p.setBrush(Qt.BrushStyle.NoBrush)
        p.drawPolyline(poly(centre))
        for pts, side in ((left, 1), (right, -1)):
            hit = self.outside == side
            p.setPen(QPen(_EDGE, 9 if hit else 4))
            p.drawPolyline(poly(pts))
        veh: VehicleSpec = drive.vehicle
        # Width to the lane's scale (it is what the feedback judges); the length drawn 2× so
        # that the car reads as a car with the magnified width (its length plays no part).
        cw, cl = veh.width_m * sx, 2.0 * (veh.cg_to_front_m + veh.cg_to_rear_m + 1.6) * sy
        colour = _CAR_OUT if self.outside else _CAR
        p.setPen(QPen(colour, 2))
        p.setBrush(QBrush(colour if self.outside else QColor("#d0d0d0")))
        p.drawRoundedRect(QRectF(ox - cw / 2, oy - cl * 0.6, cw, cl), 6, 6)
        p.setBrush(QBrush(QColor("#404040")))  # the windscreen: which way is ahead
        p.drawRoundedRect(QRectF(ox - cw * 0.38, oy - cl * 0.38, cw * 0.76, cl * 0.18), 3, 3)
        p.end()


class VehicleFeed:
    """Engine subscriber: the newest sample's car state, for a loop in another process (a lab
    rig's loop process shows the car to no display here). Called on the engine's thread; the
    Qt thread reads :meth:`latest` (one reference swap, no lock)."""

    def __init__(self) -> None:
        self._latest: dict[str, float] | None = None

    def __call__(self, event: object) -> None:
        from steerlab.protocols import events as ev

        if isinstance(event, ev.SamplesAcquired):
            ch = event.channels
            if "road_distance_m" in ch and event.n:
                self._latest = {c: float(ch[c][-1]) for c in DRIVING_CHANNELS if c in ch}
        elif isinstance(event, ev.TrialStarted):
            self._latest = None

    def latest(self) -> dict[str, float] | None:
        return self._latest


class DrivingDisplay:
    """The road view inside the subject dashboard: shown for driving trials, hidden otherwise.

    The dashboard keeps its own indicator view for the boundary tasks; this only swaps which of
    the two is visible (``install`` adds the road view to the dashboard's layout)."""

    def __init__(
        self, dashboard: SubjectDashboard, protocol: Protocol, source: VehicleSource
    ) -> None:
        self.dashboard, self.protocol = dashboard, protocol
        self.view = RoadView(source, parent=dashboard)
        self.view.setVisible(False)
        box = dashboard.layout()
        if not isinstance(box, QBoxLayout):
            raise TypeError(f"the subject dashboard's layout is a {type(box).__name__}, not a box")
        box.insertWidget(0, self.view, 1)

    def trial_started(self, attributes: Mapping[str, Any]) -> None:
        drive = road_of_trial(attributes, self.protocol)
        self.view.set_drive(drive)
        self.view.setVisible(drive is not None)
        self.dashboard.view.setVisible(drive is None)


def install(
    dashboard: SubjectDashboard, protocol: Protocol, source: VehicleSource
) -> DrivingDisplay:
    return DrivingDisplay(dashboard, protocol, source)
