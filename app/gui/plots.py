"""Live scrolling plots, redrawn by a timer from the in-memory ring buffer.

The timer asks for a redraw at ``fps`` frames per second; each redraw copies the newest
``window_s`` seconds out of :class:`~app.gui.livedata.LiveData` and sets the curves. A QTimer
that falls behind coalesces its ticks, so a busy GUI shows fewer frames and the engine never
waits for it. Curves are decimated to at most ``max_points`` per curve (min/max pairs, so a
peak of the perturbation is never hidden by the decimation).
"""

from __future__ import annotations

import math
import time

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QEvent, QObject, QTimer
from PySide6.QtWidgets import QWidget

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
    """Counts paint events of a widget: frames actually drawn, not merely requested."""

    def __init__(self, widget: QWidget) -> None:
        super().__init__(widget)
        self.frames = 0
        widget.installEventFilter(self)

    def eventFilter(self, obj: QObject, event: QEvent) -> bool:  # noqa: N802 (Qt's name)
        if event.type() == QEvent.Type.Paint:
            self.frames += 1
        return False


# (title, unit, [(channel, legend, colour)], scale)
_PANELS = (
    ("Perturbation torque", "N·m", [("perturbation_torque_Nm", None, "#d62728")], 1.0),
    ("Driver torque", "N·m", [("driver_torque_Nm", None, "#1f77b4")], 1.0),
    ("Wheel angle", "°", [("wheel_angle_rad", None, "#2ca02c")], 180.0 / math.pi),
    (
        "Grip force",
        "N",
        [
            ("grip_force_left_N", "left", "#9467bd"),
            ("grip_force_right_N", "right", "#ff7f0e"),
            ("grip_force_N", "total", "#222222"),
        ],
        1.0,
    ),
)


class HeldRange:
    """A y-range that grows at once to fit the data and shrinks only after ``hold_s``.

    A range that followed every frame would repaint the axis every frame (the costliest part
    of a pyqtgraph frame); this one changes a few times per trial.
    """

    def __init__(self, floor: float = 0.0, hold_s: float = 3.0, margin: float = 0.15) -> None:
        self.floor, self.hold_s, self.margin = floor, hold_s, margin
        self.lo, self.hi = -1.0, 1.0
        self._since = 0.0

    def update(self, lo: float, hi: float, now: float) -> tuple[float, float] | None:
        """The new range, or None to keep the current one."""
        lo, hi = min(lo, -self.floor), max(hi, self.floor)
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


class LivePlots(pg.GraphicsLayoutWidget):
    """Four stacked plots of the newest ``window_s`` seconds; x is time before now.

    The axes stay still (x from −window_s to 0, y held, no grid, legend in the title) so a
    frame repaints only the curves: on this 2-core machine that halves the cost of a frame.
    """

    def __init__(
        self,
        live: LiveData,
        *,
        window_s: float = 10.0,
        fps: float = 40.0,
        max_points: int = 1000,
        parent: QWidget | None = None,
    ) -> None:
        super().__init__(parent)
        self.live = live
        self.window_s = window_s
        self.max_points = max_points
        self.setBackground("w")
        self.curves: dict[str, pg.PlotDataItem] = {}
        self.plots: list[pg.PlotItem] = []
        self.ranges: list[HeldRange] = []
        self._scale: dict[str, float] = {}
        self._panel_of: dict[str, int] = {}
        for row, (title, unit, chans, scale) in enumerate(_PANELS):
            p = self.addPlot(row=row, col=0)
            legend = "  ".join(
                f"<span style='color:{colour}'>■ {name}</span>" for _, name, colour in chans if name
            )
            p.setTitle(f"{title}  {legend}" if legend else title, size="9pt")
            p.setLabel("left", unit)
            p.setMenuEnabled(False)
            p.setMouseEnabled(x=False, y=False)
            p.hideButtons()
            p.disableAutoRange()
            p.setXRange(-window_s, 0.0, padding=0)
            p.setYRange(-1.0, 1.0, padding=0)
            p.addItem(pg.InfiniteLine(pos=0.0, angle=0, pen=pg.mkPen("#cccccc", width=1)))
            for ch, _name, colour in chans:
                c = p.plot(pen=pg.mkPen(colour, width=1))
                c.setSkipFiniteCheck(True)
                self.curves[ch] = c
                self._scale[ch] = scale
                self._panel_of[ch] = row
            if row < len(_PANELS) - 1:
                p.getAxis("bottom").setStyle(showValues=False)
            self.plots.append(p)
            self.ranges.append(HeldRange())
        self.plots[-1].setLabel("bottom", "time before now", "s")
        self.boundary_lines = [
            pg.InfiniteLine(angle=0, pen=pg.mkPen("#d62728", width=1, style=pg.QtCore.Qt.DashLine))
            for _ in range(2)
        ]
        for ln in self.boundary_lines:
            ln.setVisible(False)
            self.plots[2].addItem(ln)
        self.frames = FrameCounter(self.viewport())
        self.refreshes = 0
        self.refresh_s = 0.0  # time spent in refresh(), for the benchmark
        self.trial_time_s = 0.0
        self.timer = QTimer(self)
        self.timer.setInterval(int(round(1000.0 / fps)))
        self.timer.timeout.connect(self.refresh)
        self._last_n = -1

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

    def refresh(self) -> None:
        t0 = time.perf_counter()
        snap = self.live.snapshot(self.window_s)
        if snap.n_written == self._last_n:
            return  # nothing new: skip the redraw (paused, between trials)
        self._last_n = snap.n_written
        t = snap.channels["time_s"]
        if len(t):
            now = float(t[-1])
            rel = t - now
            lo = [math.inf] * len(self.plots)
            hi = [-math.inf] * len(self.plots)
            for ch, curve in self.curves.items():
                s = self._scale[ch]
                y = snap.channels[ch] * s if s != 1.0 else snap.channels[ch]
                tt, yy = decimate_minmax(rel, y, self.max_points)
                curve.setData(tt, yy)
                if len(yy):
                    i = self._panel_of[ch]
                    lo[i] = min(lo[i], float(np.nanmin(yy)))
                    hi[i] = max(hi[i], float(np.nanmax(yy)))
            for p, r, a, b in zip(self.plots, self.ranges, lo, hi, strict=True):
                if math.isfinite(a) and math.isfinite(b):
                    new = r.update(a, b, t0)
                    if new is not None:
                        p.setYRange(*new, padding=0)
            self.trial_time_s = now
        else:
            for curve in self.curves.values():
                curve.setData([], [])
        self.refreshes += 1
        self.refresh_s += time.perf_counter() - t0


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
