"""Live admittance from grip force through an LPV model (docs/method.md, "LPV model").

μ is the mean total grip force over the last ``mu_window_s`` seconds of the running trial
(ours: the paper schedules on a per-condition mean; a one-second mean follows the changes the
method is about while smoothing the glove's noise). The panel shows μ, the intrinsic stiffness
k_i(μ) and |H(f; μ)| with the operating points' curves for reference. μ outside the operating
points' range is clipped to it, and the panel says so.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QTimer
from PySide6.QtGui import QFont
from PySide6.QtWidgets import (
    QFileDialog,
    QGridLayout,
    QGroupBox,
    QLabel,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

import steerlab.app.gui.qt_compat  # noqa: F401 (PySide6 6.12 on Python 3.11: see that module)
from steerlab.analysis.lpv_results import LoadedLPV, LPVLoadError, load_lpv_model
from steerlab.app.gui.livedata import LiveData
from steerlab.app.gui.plots import log_ticks
from steerlab.app.gui.tracker_feed import TrackerFeed

NO_MODEL = "no LPV model loaded"


class LiveAdmittancePanel(QGroupBox):
    def __init__(
        self,
        live: LiveData,
        *,
        mu_window_s: float = 1.0,
        rate_hz: float = 5.0,
        tracker: TrackerFeed | None = None,
        parent: QWidget | None = None,
    ) -> None:
        self.tracker = tracker
        super().__init__("Live admittance (LPV, grip-force scheduled)", parent)
        self.live = live
        self.mu_window_s = mu_window_s
        self.model: LoadedLPV | None = None
        self.f_hz = np.logspace(np.log10(0.05), np.log10(20.0), 80)
        self.mu: float | None = None
        self.k_i: float | None = None

        self.status = QLabel(NO_MODEL)
        self.status.setWordWrap(True)
        self.load_button = QPushButton("Load results.json…")
        self.load_button.clicked.connect(self._choose_file)
        big = QFont()
        big.setPointSize(16)
        big.setBold(True)
        self.k_label = QLabel("k_i —")
        self.k_label.setFont(big)
        self.mu_label = QLabel("μ —")
        self.plot = pg.PlotWidget()
        self.plot.setBackground("w")
        self.plot.setLogMode(x=True, y=True)
        self.plot.setLabel("bottom", "frequency (Hz)")
        self.plot.setLabel("left", "|H| (rad/N·m)")
        self.plot.getAxis("bottom").setTicks(log_ticks(0.01, 100.0))
        self.plot.getAxis("left").enableAutoSIPrefix(False)  # the ticks carry the values
        self.plot.setMenuEnabled(False)
        self.plot.setMouseEnabled(x=False, y=False)
        self.plot.hideButtons()
        self.plot.setMinimumHeight(140)
        self.curve = self.plot.plot(pen=pg.mkPen("#d62728", width=2))
        self._reference: list[pg.PlotDataItem] = []

        grid = QGridLayout()
        grid.addWidget(self.k_label, 0, 0)
        grid.addWidget(self.mu_label, 0, 1)
        lay = QVBoxLayout(self)
        lay.addWidget(self.status)
        lay.addWidget(self.load_button)
        lay.addLayout(grid)
        lay.addWidget(self.plot, 1)

        self.timer = QTimer(self)
        self.timer.setInterval(int(round(1000.0 / rate_hz)))
        self.timer.timeout.connect(self.refresh)
        self.timer.start()
        self._show_model_state()

    def _choose_file(self) -> None:
        path, _ = QFileDialog.getOpenFileName(
            self, "LPV model from a report", "", "report results (results.json *.json)"
        )
        if path:
            self.load(path)

    def load(self, path: str | Path) -> bool:
        """Load the model; on failure the panel keeps working without one and says why."""
        try:
            self.model = load_lpv_model(path)
        except LPVLoadError as e:
            self.model = None
            self._show_model_state(f"{NO_MODEL} ({e})")
            if self.tracker is not None:
                self.tracker.set_results(None)
            return False
        if self.tracker is not None:
            self.tracker.set_results(path)  # the grip-scheduled EKF starts with the next trial
        self._show_model_state()
        return True

    def _show_model_state(self, message: str | None = None) -> None:
        for c in self._reference:
            self.plot.removeItem(c)
        self._reference = []
        if self.model is None:
            self.status.setText(message or NO_MODEL)
            self.k_label.setText("k_i —")
            self.mu_label.setText("μ —")
            self.curve.setData([], [])
            self.plot.setEnabled(False)
            return
        self.plot.setEnabled(True)
        self.status.setText(self.model.describe())
        lo, hi = math.inf, 0.0
        for p in self.model.model.points:
            h = np.abs(self.model.model.frequency_response(p.mu_N, self.f_hz))
            c = self.plot.plot(self.f_hz, h, pen=pg.mkPen("#bbbbbb", width=1))
            self._reference.append(c)
            lo, hi = min(lo, float(h.min())), max(hi, float(h.max()))
        self.plot.getAxis("left").setTicks(log_ticks(lo / 2, hi * 2))

    def refresh(self) -> None:
        if self.model is None:
            return
        mu = self.live.mean_of_last("grip_force_N", self.mu_window_s)
        if mu is None or not math.isfinite(mu):
            self.mu_label.setText("μ — (no grip data)")
            return
        self.update_mu(mu)

    def update_mu(self, mu: float) -> None:
        assert self.model is not None
        m = self.model.model
        lo, hi = m.mu_range
        self.mu = mu
        self.k_i = float(m.parameters(mu)["k_i"])
        clipped = "" if lo <= mu <= hi else f"  (clipped to {lo:.0f}–{hi:.0f} N)"
        est = self.tracker.estimate if self.tracker is not None else None
        if est is not None:
            # The grip-scheduled EKF (analysis.tracking): grip force at once, corrected by the
            # perturbation response; the LPV alone is shown beside it.
            self.mu_label.setText(f"μ = {mu:.0f} N{clipped} · LPV alone: k_i = {self.k_i:.1f}")
            self.k_i = float(est.k_i)
            self.k_label.setText(f"k_i = {self.k_i:.1f} N·m/rad (EKF)")
            self.curve.setData(self.f_hz, np.abs(est.admittance(self.f_hz)))
            return
        note = f" — {self.tracker.error}" if self.tracker is not None and self.tracker.error else ""
        self.mu_label.setText(f"μ = {mu:.0f} N{clipped}{note}")
        self.k_label.setText(f"k_i = {self.k_i:.1f} N·m/rad")
        self.curve.setData(self.f_hz, np.abs(m.frequency_response(mu, self.f_hz)))
