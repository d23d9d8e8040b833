"""Live scrolling plots, redrawn by a timer from the in-memory ring buffer.

The timer asks for a redraw at ``fps`` frames per second; each redraw copies the newest
``window_s`` seconds out of :class:`~app.gui.livedata.LiveData` and sets the curves. A QTimer
that falls behind coalesces its ticks, so a busy GUI shows fewer frames and the engine never
waits for it. Curves are decimated to one point per pixel column (min/max pairs, so a peak of
the perturbation is never hidden by the decimation). What a frame costs and why it is drawn
this way: docs/gui.md, "Live plots".
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QEvent, QObject, QRectF, QTimer
from PySide6.QtGui import QPainter, QPainterPath, QTransform
from PySide6.QtWidgets import QGraphicsItem, QWidget

import steerlab.app.gui.qt_compat  # noqa: F401 (PySide6 6.12 on Python 3.11: see that module)
from steerlab.app.gui.livedata import LiveData


def decimate_minmax(t: np.ndarray, y: np.ndarray, max_points: int) -> tuple[np.ndarray, ...]:
    """At most ``max_points`` points: pairs of (min, max) per bucket, in time order."""
    n = len(y)
    if n <= max_points:
        return t, y
    per = int(math.ceil(n / (max_points // 2)))
    m = n // per
    yy = y[: m * per].reshape(m, per)
    tt = t[: m * per].reshape(m, per)
    lo, hi = yy.argmin(axis=1), yy.argmax(axis=1)
    first = np.minimum(lo, hi)
    second = np.maximum(lo, hi)
    rows = np.arange(m)
    idx_t = np.empty(2 * m, dtype=float)
    idx_y = np.empty(2 * m, dtype=float)
    idx_t[0::2], idx_t[1::2] = tt[rows, first], tt[rows, second]
    idx_y[0::2], idx_y[1::2] = yy[rows, first], yy[rows, second]
    return idx_t, idx_y


def log_ticks(lo: float, hi: float) -> list[list[tuple[float, str]]]:
    """Ticks for a pyqtgraph log axis: 1, 2, 5 × 10^k between ``lo`` and ``hi`` (data units).

    pyqtgraph's own log ticks label every minor tick on a short range and run them together.
    """
    if not (lo > 0 and hi > lo):
        return [[], []]
    major = []
    for k in range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1):
        for m in (1, 2, 5):
            v = m * 10.0**k
            if lo <= v <= hi:
                major.append((math.log10(v), f"{v:g}"))
    return [major, []]


class FrameCounter(QObject):
    """Counts frames actually drawn, not merely requested: a frame is the first paint of the
    widget after :meth:`new_frame` (new curves were set). Qt paints again for other reasons (a
    relayout, an item whose size changed, a window uncovered); those repaints show nothing new,
    so they are counted in ``paints`` only, and ``frames`` never exceeds the refreshes."""

    def __init__(self, widget: QWidget) -> None:
        super().__init__(widget)
        self.frames = 0
        self.paints = 0
        self._pending = False
        widget.installEventFilter(self)

    def new_frame(self) -> None:
        self._pending = True

    def eventFilter(self, obj: QObject, event: QEvent) -> bool:  # noqa: N802 (Qt's name)
        if event.type() == QEvent.Type.Paint:
            self.paints += 1
            if self._pending:
                self.frames += 1
                self._pending = False
        return False


@dataclass(frozen=True)
class Trace:
    """One curve of a panel: a channel, its legend name (None: no legend) and its pen."""

    channel: str
    name: str | None
    colour: str
    width_px: int = 1


# The grip panel's left and right hands carry nearly the same force (each about half the
# total), so one thin line would hide the other: the left is drawn first as a wide, pale band
# and the right as a thin line on top, so both stay visible when they coincide.
@dataclass(frozen=True)
class Panel:
    """One plot: title, unit (the left axis label), curves, channel → plot scale, and the
    smallest y span shown (plot units), so an empty or constant trace (an aborted trial, the
    silence before a fade-in) keeps a readable scale instead of zooming into rounding noise."""

    title: str
    unit: str
    traces: tuple[Trace, ...]
    scale: float = 1.0
    min_span: float = 1.0


_PANELS: tuple[Panel, ...] = (
    Panel("Perturbation torque", "N·m", (Trace("perturbation_torque_Nm", None, "#d62728"),)),
    Panel("Driver torque", "N·m", (Trace("driver_torque_Nm", None, "#1f77b4"),)),
    Panel(
        "Wheel angle",
        "°",
        (Trace("wheel_angle_rad", None, "#2ca02c"),),
        scale=180.0 / math.pi,
        min_span=4.0,
    ),
    Panel(
        "Grip force",
        "N",
        (
            Trace("grip_force_left_N", "left", "#b9a3d6", 4),
            Trace("grip_force_right_N", "right", "#ff7f0e"),
            Trace("grip_force_N", "total", "#222222"),
        ),
        min_span=10.0,
    ),
)

#: Smallest distance between two labelled ticks of a y axis, px: pyqtgraph labels at least
#: three ticks on any axis, which on a plot 60 px high runs the labels together.
MIN_TICK_SPACING_PX = 26.0
#: Smallest height of the four plots together, px: each plot's data area is then about 56 px
#: high, room for two labelled ticks (the window must still fit a 1280×800 screen).
MIN_PLOTS_PX = 300
#: Height of each plot's title row, px (pyqtgraph's is 30: room for a 9-pt title and a margin
#: that four plots cannot spare).
TITLE_ROW_PX = 18
#: Width of each plot's left axis, px, the same for all: their data areas line up, and a tick
#: label that gets wider ("-10" after "-5") does not relayout the plots (a second paint).
LEFT_AXIS_PX = 52


def nice_step(at_least: float) -> float:
    """The smallest 1, 2 or 5 × 10^k that is ≥ ``at_least`` (> 0)."""
    k = math.floor(math.log10(at_least))
    for m in (1.0, 2.0, 5.0, 10.0):
        step = m * 10.0**k
        if step >= at_least * (1 - 1e-9):
            return step
    return 10.0 ** (k + 1)


class SparseAxis(pg.AxisItem):
    """A y axis whose labelled ticks are at least ``MIN_TICK_SPACING_PX`` apart, with one
    level of unlabelled minor ticks between them."""

    def tickSpacing(self, minVal: float, maxVal: float, size: float):  # noqa: N802, N803
        levels = super().tickSpacing(minVal, maxVal, size)
        span = abs(maxVal - minVal)
        if not levels or size <= 0 or span == 0:
            return levels
        major = levels[0][0]
        need = span * MIN_TICK_SPACING_PX / size
        if major < need:
            major = nice_step(need)
            # A single label gives no scale: one step finer, if the labels still keep apart.
            finer = major / 2  # 0.5, 1 or 2.5 × 10^k: two or three labels
            labels = math.floor(maxVal / major) - math.ceil(minVal / major) + 1
            if labels < 2 and finer * size / span >= 0.7 * MIN_TICK_SPACING_PX:
                major = finer
        mantissa = major / 10.0 ** math.floor(math.log10(major))
        return [(major, 0.0), (major / (4.0 if abs(mantissa - 2.0) < 1e-6 else 5.0), 0.0)]


#: What Qt caches as a pixmap: items that change a few times per trial (axes, titles, legends,
#: fixed lines). Without it every frame replays their drawing (text above all) wherever the
#: curves' repaint region touches them; with it they are blitted.
_CACHED = QGraphicsItem.CacheMode.DeviceCoordinateCache


class LiveCurve(QGraphicsItem):
    """One live curve: a path drawn with a one-pixel pen, and nothing else.

    pyqtgraph's ``PlotCurveItem`` does much more on every frame in Python (bounds from the
    data, signals to its view, export and fill options). Here ``set_curve`` builds the path
    (pyqtgraph's ``arrayToQPath``, vectorised) and ``paint`` draws it. The bounding rectangle
    is the plot's view, given by the owner: x is fixed and y is the held range, so Qt never
    has to ask the data.

    ``width_px`` > 1 draws a band that many pixels high as that many one-pixel strokes, each
    shifted by a pixel: Qt's raster engine strokes a one-pixel line about 15 times faster than
    a wide pen (measured: 0.15 ms for four strokes of 870 points, 2.4 ms for one 4-px pen).
    ``opts`` is what ``pg.LegendItem`` reads for its sample line.
    """

    def __init__(self, colour: str, width_px: int = 1) -> None:
        super().__init__()
        self.colour = colour
        self.width_px = int(width_px)
        self.pen = pg.mkPen(colour, width=1)  # cosmetic: one device pixel
        self.opts = {"pen": pg.mkPen(colour, width=self.width_px)}
        self._shifts = [
            QTransform.fromTranslate(0.0, k - (self.width_px - 1) / 2.0)
            for k in range(self.width_px)
        ]
        self._path = QPainterPath()
        self._rect = QRectF()
        self._x = self._y = np.zeros(0)

    def set_rect(self, rect: QRectF) -> None:
        if rect != self._rect:
            self.prepareGeometryChange()
            self._rect = QRectF(rect)

    # Not pyqtgraph's name setData: on a QGraphicsItem that is setData(key, value), which
    # Qt and pyqtgraph call to tag items.
    def set_curve(self, x: np.ndarray, y: np.ndarray) -> None:
        """Plot ``y`` against ``x`` (view units); NaN samples leave gaps."""
        finite = not (np.isnan(y).any() or np.isnan(x).any())
        if len(x) < 2:
            self._path = QPainterPath()
        elif finite:
            self._path = pg.arrayToQPath(x, y, connect="all", finiteCheck=False)
        else:
            self._path = pg.arrayToQPath(x, y, connect="finite", finiteCheck=True)
        self._x, self._y = x, y
        self.update()

    def getData(self) -> tuple[np.ndarray, np.ndarray]:  # noqa: N802 (pyqtgraph's name)
        return self._x, self._y

    def boundingRect(self) -> QRectF:  # noqa: N802 (Qt's name)
        return self._rect

    def paint(self, painter: QPainter, option, widget=None) -> None:
        painter.setPen(self.pen)
        if self.width_px == 1:
            painter.drawPath(self._path)
            return
        base = painter.transform()
        for shift in self._shifts:  # the shift is in device pixels: applied after the view's
            painter.setTransform(base * shift)
            painter.drawPath(self._path)
        painter.setTransform(base)


class HeldRange:
    """A y-range that grows at once to fit the data and shrinks only after ``hold_s``.

    A range that followed every frame would repaint the axis every frame (the costliest part
    of a pyqtgraph frame); this one changes a few times per trial.
    """

    def __init__(
        self, floor: float = 0.0, hold_s: float = 3.0, margin: float = 0.15, min_span: float = 1.0
    ) -> None:
        self.floor, self.hold_s, self.margin = floor, hold_s, margin
        self.min_span = min_span
        self.lo, self.hi = -0.5 * min_span, 0.5 * min_span
        self._since = 0.0

    def update(self, lo: float, hi: float, now: float) -> tuple[float, float] | None:
        """The new range, or None to keep the current one."""
        lo, hi = min(lo, -self.floor), max(hi, self.floor)
        if hi - lo < self.min_span:  # flat data: centred on it, never narrower than min_span
            mid = 0.5 * (lo + hi)
            lo, hi = mid - 0.5 * self.min_span, mid + 0.5 * self.min_span
        pad = self.margin * max(hi - lo, 1e-9)
        want_lo, want_hi = lo - pad, hi + pad
        grow = want_lo < self.lo or want_hi > self.hi
        # Shrink when the data use less than half of the range for a while.
        slack = (want_hi - want_lo) < 0.5 * (self.hi - self.lo)
        if not slack:
            self._since = now
        if grow or (slack and now - self._since > self.hold_s):
            self.lo, self.hi, self._since = want_lo, want_hi, now
            return self.lo, self.hi
        return None


class RateMeter:
    """Events per second between two readings of a running count (for the status bar)."""

    def __init__(self) -> None:
        self._at: tuple[float, int] | None = None

    def rate(self, count: int, now: float) -> float | None:
        """The rate since the previous call; None on the first call."""
        prev, self._at = self._at, (now, count)
        if prev is None or now <= prev[0]:
            return None
        return (count - prev[1]) / (now - prev[0])


class LivePlots(pg.GraphicsLayoutWidget):
    """Four stacked plots of the newest ``window_s`` seconds; x is time before now.

    The axes stay still (x from −window_s to 0, y held, no grid) and are cached as pixmaps, so
    a frame redraws only the curves. Each curve gets one point per pixel column of its plot
    (min and max of each two columns' samples): more could not be seen, and no peak is lost.
    """

    def __init__(
        self,
        live: LiveData,
        *,
        window_s: float = 10.0,
        fps: float = 40.0,
        max_points: int = 4000,
        parent: QWidget | None = None,
    ) -> None:
        super().__init__(parent)
        self.live = live
        self.window_s = window_s
        self.max_points = max_points  # a cap on 2 × the pixel width
        self.setBackground("w")
        self.setMinimumHeight(MIN_PLOTS_PX)
        self.curves: dict[str, LiveCurve] = {}
        self.plots: list[pg.PlotItem] = []
        self.ranges: list[HeldRange] = []
        self.legends: list[pg.LegendItem] = []
        self._scale: dict[str, float] = {}
        self._panel_of: dict[str, int] = {}
        for row, panel in enumerate(_PANELS):
            left = SparseAxis("left")
            p = self.addPlot(row=row, col=0, axisItems={"left": left})
            p.setTitle(panel.title, size="9pt")
            p.titleLabel.setMaximumHeight(TITLE_ROW_PX)
            p.layout.setRowFixedHeight(0, TITLE_ROW_PX)
            p.setLabel("left", panel.unit)
            # pyqtgraph would rescale a small range by an SI factor and append it to the label
            # ("N·m (x0.001)"): fixed units, and tick values in those units.
            left.enableAutoSIPrefix(False)
            left.setStyle(maxTextLevel=0)  # labels on the major ticks only
            left.setWidth(LEFT_AXIS_PX)
            p.setMenuEnabled(False)
            p.setMouseEnabled(x=False, y=False)
            p.hideButtons()
            p.disableAutoRange()
            p.setXRange(-window_s, 0.0, padding=0)
            p.setYRange(-0.5 * panel.min_span, 0.5 * panel.min_span, padding=0)
            p.addItem(pg.InfiniteLine(pos=0.0, angle=0, pen=pg.mkPen("#cccccc", width=1)))
            named = [t for t in panel.traces if t.name]
            if named:
                # In the title row's right end, out of the layout (a layout cell would narrow
                # this plot against the others): never over the data.
                legend = pg.LegendItem(colCount=len(named), labelTextSize="8pt")
                legend.layout.setContentsMargins(0, 0, 0, 0)
                legend.setParentItem(p)
                legend.anchor(itemPos=(1, 0), parentPos=(1, 0), offset=(-10, 0))
                self.legends.append(legend)
            for t in panel.traces:
                c = LiveCurve(t.colour, t.width_px)
                p.addItem(c, ignoreBounds=True)
                if t.name:
                    legend.addItem(c, t.name)
                self.curves[t.channel] = c
                self._scale[t.channel] = panel.scale
                self._panel_of[t.channel] = row
            if row < len(_PANELS) - 1:
                p.getAxis("bottom").setStyle(showValues=False)
            self.plots.append(p)
            self.ranges.append(HeldRange(min_span=panel.min_span))
        self.plots[-1].setLabel("bottom", "time before now", "s")
        self.boundary_lines = [
            pg.InfiniteLine(angle=0, pen=pg.mkPen("#d62728", width=1, style=pg.QtCore.Qt.DashLine))
            for _ in range(2)
        ]
        for ln in self.boundary_lines:
            ln.setVisible(False)
            self.plots[2].addItem(ln)
        for p in self.plots:
            for name in ("left", "bottom", "top", "right"):
                p.getAxis(name).setCacheMode(_CACHED)
            p.titleLabel.setCacheMode(_CACHED)
            for item in p.items:
                if isinstance(item, pg.InfiniteLine):
                    item.setCacheMode(_CACHED)
        for legend in self.legends:
            legend.setCacheMode(_CACHED)
        for i in range(len(self.plots)):
            self._set_curve_rects(i)
        self.frames = FrameCounter(self.viewport())
        self.refreshes = 0
        self.refresh_s = 0.0  # time spent in refresh(), for the benchmark
        self.trial_time_s = 0.0
        self.timer = QTimer(self)
        self.timer.setInterval(int(round(1000.0 / fps)))
        self.timer.timeout.connect(self.refresh)
        self._last_n = -1
        self._last_new = -math.inf  # time.perf_counter() of the last refresh with new data

    @property
    def idle(self) -> bool:
        """No new samples for a second (paused, between trials): no frames are drawn."""
        return time.perf_counter() - self._last_new > 1.0

    def start(self) -> None:
        self.timer.start()

    def stop(self) -> None:
        self.timer.stop()

    def set_boundary(self, boundary_deg: float) -> None:
        finite = math.isfinite(boundary_deg)
        for ln, sign in zip(self.boundary_lines, (1, -1), strict=True):
            ln.setVisible(finite)
            if finite:
                ln.setPos(sign * boundary_deg)
        # Keep the lines in view: the angle plot's range never shrinks inside them.
        self.ranges[2].floor = boundary_deg if finite else 0.0

    def _set_curve_rects(self, panel: int) -> None:
        r = self.ranges[panel]
        rect = QRectF(-self.window_s, r.lo, self.window_s, r.hi - r.lo)
        for ch, c in self.curves.items():
            if self._panel_of[ch] == panel:
                c.set_rect(rect)

    def points_per_curve(self) -> int:
        """One per pixel column of the data area (each pair of columns gets its samples' min
        and max: no peak is lost, and no column gets a point it cannot show), at most
        ``max_points``."""
        width = self.plots[0].getViewBox().width()
        return max(2, min(self.max_points, int(width)))

    def refresh(self) -> None:
        t0 = time.perf_counter()
        snap = self.live.snapshot(self.window_s)
        if snap.n_written == self._last_n:
            return  # nothing new: skip the redraw (paused, between trials)
        self._last_n = snap.n_written
        self._last_new = t0
        t = snap.channels["time_s"]
        if len(t):
            now = float(t[-1])
            rel = t - now
            n_points = self.points_per_curve()
            lo = [math.inf] * len(self.plots)
            hi = [-math.inf] * len(self.plots)
            for ch, curve in self.curves.items():
                s = self._scale[ch]
                y = snap.channels[ch] * s if s != 1.0 else snap.channels[ch]
                tt, yy = decimate_minmax(rel, y, n_points)
                curve.set_curve(tt, yy)
                if len(yy) and not np.isnan(yy).all():  # a channel the rig does not send: NaN
                    i = self._panel_of[ch]
                    lo[i] = min(lo[i], float(np.nanmin(yy)))
                    hi[i] = max(hi[i], float(np.nanmax(yy)))
            for i, (r, a, b) in enumerate(zip(self.ranges, lo, hi, strict=True)):
                if math.isfinite(a) and math.isfinite(b):
                    new = r.update(a, b, t0)
                    if new is not None:
                        self._set_y_range(i, new)
            self.trial_time_s = now
        else:
            for curve in self.curves.values():
                curve.set_curve(np.zeros(0), np.zeros(0))
        self.frames.new_frame()
        self.refreshes += 1
        self.refresh_s += time.perf_counter() - t0

    def _set_y_range(self, panel: int, lo_hi: tuple[float, float]) -> None:
        p = self.plots[panel]
        p.setYRange(*lo_hi, padding=0)
        self._set_curve_rects(panel)
        # pyqtgraph applies a new range when it paints; the horizontal lines then find their
        # new size during that paint and ask for a second one. Applied now, with the lines'
        # sizes, the one paint that follows draws the new range.
        p.getViewBox().updateMatrix()
        for item in p.items:
            if isinstance(item, pg.InfiniteLine):
                item.boundingRect()


class CoherencePlot(pg.PlotWidget):
    """Coherence per double band of the last trial (quality check)."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.setBackground("w")
        self.setLogMode(x=True, y=False)
        self.setYRange(0, 1.05, padding=0)
        self.setLabel("bottom", "frequency", "Hz")
        self.setLabel("left", "coherence")
        self.setMenuEnabled(False)
        self.setMouseEnabled(x=False, y=False)
        self.hideButtons()
        self.curve = self.plot(pen=None, symbol="o", symbolSize=5, symbolBrush="#1f77b4")
        self.getAxis("bottom").setTicks(log_ticks(0.01, 100.0))
        self.setMinimumHeight(120)

    def show_coherence(self, f_hz: np.ndarray, coherence: np.ndarray) -> None:
        self.curve.setData(f_hz, coherence)
