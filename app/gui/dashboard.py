"""The subject's dashboard: a large wheel-angle indicator and the condition's boundary lines.

Scene coordinates: x is in degrees of wheel angle as the subject sees it, y runs 0..1 over the
bar's height. The view maps the scene's fixed span (±``span_deg``) to the window whatever its
size, so a line at x = 12 is 12° from the centre on every screen and in every condition: the
subject compares widths between conditions, so the scale must not change with them.

Positive angle is counter-clockwise seen by the driver (hardware/interfaces.py): the top of the
wheel moves left, so the indicator is drawn at x = −angle.

Lines: none for an infinite boundary (RT), both on the centre for a zero boundary (PT), at
±boundary otherwise. The indicator keeps one colour inside and outside the lines (ours: the
paper's display shows the angle and the lines, no extra feedback).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from PySide6.QtCore import QLineF, QRectF, Qt, QTimer
from PySide6.QtGui import QBrush, QColor, QFont, QGuiApplication, QPainter, QPen, QScreen
from PySide6.QtWidgets import (
    QGraphicsLineItem,
    QGraphicsRectItem,
    QGraphicsScene,
    QGraphicsView,
    QLabel,
    QVBoxLayout,
    QWidget,
)

import steerlab.app.gui.qt_compat  # noqa: F401 (PySide6 6.12 on Python 3.11: see that module)

DEFAULT_SPAN_DEG = 30.0
_BG = QColor("#101010")
_LINE = QColor("#ff3b30")
_INDICATOR = QColor("#ffffff")
_CENTRE = QColor("#606060")


def _pen(colour: QColor, width_px: float, style: Qt.PenStyle = Qt.PenStyle.SolidLine) -> QPen:
    pen = QPen(colour, width_px, style)
    pen.setCosmetic(True)  # width in pixels: the scene's x scale must not fatten the lines
    pen.setCapStyle(Qt.PenCapStyle.FlatCap)
    return pen


class _FitView(QGraphicsView):
    """Shows the whole scene rectangle, stretched to the widget (degrees stay degrees)."""

    def __init__(self, scene: QGraphicsScene) -> None:
        super().__init__(scene)
        self.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.setVerticalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.setFrameShape(QGraphicsView.Shape.NoFrame)
        self.setRenderHint(QPainter.RenderHint.Antialiasing, True)
        self.setBackgroundBrush(QBrush(_BG))

    def resizeEvent(self, event) -> None:  # noqa: N802 (Qt's name)
        super().resizeEvent(event)
        self.fitInView(self.sceneRect(), Qt.AspectRatioMode.IgnoreAspectRatio)

    def showEvent(self, event) -> None:  # noqa: N802
        super().showEvent(event)
        self.fitInView(self.sceneRect(), Qt.AspectRatioMode.IgnoreAspectRatio)


class SubjectDashboard(QWidget):
    def __init__(
        self,
        angle_source: Callable[[], float | None] | None = None,
        *,
        span_deg: float = DEFAULT_SPAN_DEG,
        fps: float = 60.0,
        parent: QWidget | None = None,
    ) -> None:
        super().__init__(parent)
        self.setWindowTitle("Steerlab — subject display")
        self.angle_source = angle_source
        self.span_deg = span_deg
        self.boundary_deg = math.inf
        self.condition: str | None = None
        self.active = False

        self.scene = QGraphicsScene(self)
        self.scene.setSceneRect(QRectF(-span_deg, 0.0, 2 * span_deg, 1.0))
        self.view = _FitView(self.scene)
        self.centre = QGraphicsLineItem(QLineF(0, 0.25, 0, 0.75))
        self.centre.setPen(_pen(_CENTRE, 2, Qt.PenStyle.DashLine))
        self.scene.addItem(self.centre)
        track = QGraphicsRectItem(QRectF(-span_deg, 0.47, 2 * span_deg, 0.06))
        track.setPen(QPen(Qt.PenStyle.NoPen))
        track.setBrush(QBrush(QColor("#262626")))
        self.scene.addItem(track)
        self.lines: list[QGraphicsLineItem] = []
        for _ in range(2):
            ln = QGraphicsLineItem(QLineF(0, 0.1, 0, 0.9))
            ln.setPen(_pen(_LINE, 8))
            ln.setZValue(2)
            ln.setVisible(False)
            self.scene.addItem(ln)
            self.lines.append(ln)
        self.indicator = QGraphicsLineItem(QLineF(0, 0.2, 0, 0.8))
        self.indicator.setPen(_pen(_INDICATOR, 14))
        self.indicator.setZValue(3)
        self.scene.addItem(self.indicator)

        self.label = QLabel("")
        self.label.setAlignment(Qt.AlignmentFlag.AlignCenter)
        f = QFont()
        f.setPointSize(20)
        self.label.setFont(f)
        self.label.setStyleSheet("color: #a0a0a0; background: #101010;")
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.setSpacing(0)
        lay.addWidget(self.view, 1)
        lay.addWidget(self.label)
        self.setStyleSheet("background: #101010;")
        self.resize(1000, 400)

        self.timer = QTimer(self)
        self.timer.setInterval(int(round(1000.0 / fps)))
        self.timer.timeout.connect(self.refresh)
        self.timer.start()
        self.set_active(False)

    # -- what the experimenter window tells it --------------------------------------------------
    def show_condition(self, condition: str | None, boundary_deg: float) -> None:
        self.condition, self.boundary_deg = condition, float(boundary_deg)
        finite = math.isfinite(self.boundary_deg)
        for ln, sign in zip(self.lines, (-1.0, 1.0), strict=True):
            ln.setVisible(finite)
            if finite:
                ln.setPos(sign * min(self.boundary_deg, self.span_deg), 0.0)

    def set_active(self, active: bool, message: str = "") -> None:
        """Active: a trial runs (bright indicator). Otherwise the indicator dims."""
        self.active = active
        pen = self.indicator.pen()
        pen.setColor(_INDICATOR if active else QColor("#555555"))
        self.indicator.setPen(pen)
        self.label.setText(message)

    def set_angle(self, angle_rad: float) -> None:
        x = -math.degrees(angle_rad)
        self.indicator.setPos(max(-self.span_deg, min(self.span_deg, x)), 0.0)

    def refresh(self) -> None:
        if self.angle_source is None:
            return
        a = self.angle_source()
        if a is not None and math.isfinite(a):
            self.set_angle(a)

    # -- for tests and the experimenter's preview ---------------------------------------------
    def boundary_positions(self) -> list[float]:
        """Scene x of the visible boundary lines, left to right."""
        return sorted(ln.scenePos().x() for ln in self.lines if ln.isVisible())

    def indicator_position(self) -> float:
        return self.indicator.scenePos().x()

    # -- where it shows --------------------------------------------------------------------------
    @staticmethod
    def screens() -> list[QScreen]:
        return list(QGuiApplication.screens())

    def show_on(self, screen: QScreen | None, full_screen: bool) -> None:
        if screen is not None:
            self.setScreen(screen)
            geo = screen.availableGeometry()
            if not full_screen:
                self.showNormal()
                w, h = min(self.width(), geo.width()), min(self.height(), geo.height())
                self.setGeometry(geo.x() + (geo.width() - w) // 2,
                                 geo.y() + (geo.height() - h) // 2, w, h)  # fmt: skip
            else:
                self.setGeometry(geo)
        if full_screen:
            self.showFullScreen()
        else:
            self.showNormal()
        self.raise_()
