"""The experimenter's window: session, trial list, controls, live plots, quality, status.

Everything here runs on the GUI thread. Engine events arrive through the bridge's one signal
(:meth:`ExperimenterWindow.on_event`); samples are read from :class:`LiveData` by timers. The
emergency stop is wired to the button's ``pressed`` signal (it acts on press, not release)
and calls the controller directly, which calls ``engine.emergency_stop()``: no queue between
the button and the drive.
"""

from __future__ import annotations

import html
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import (
    QCloseEvent,
    QColor,
    QFont,
    QKeySequence,
    QResizeEvent,
    QScreen,
    QShortcut,
)
from PySide6.QtWidgets import (
    QAbstractItemView,
    QCheckBox,
    QComboBox,
    QFormLayout,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QMainWindow,
    QPushButton,
    QRadioButton,
    QSpinBox,
    QSplitter,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

import steerlab.app.gui.qt_compat  # noqa: F401 (PySide6 6.12 on Python 3.11: see that module)
from steerlab.app.gui import road_view
from steerlab.app.gui.bridge import BridgeFault, EngineBridge
from steerlab.app.gui.controller import (
    ABORTED,
    DONE,
    RUNNING,
    ControlError,
    RigFactory,
    SessionController,
    WorkerFinished,
    list_sessions,
    session_path,
)
from steerlab.app.gui.dashboard import DEFAULT_SPAN_DEG, SubjectDashboard
from steerlab.app.gui.live_admittance import LiveAdmittancePanel
from steerlab.app.gui.livedata import LiveData
from steerlab.app.gui.placement import GAP, MIN_DASHBOARD_WIDTH, side_by_side
from steerlab.app.gui.plots import CoherencePlot, LivePlots, RateMeter
from steerlab.app.gui.quality import QualityCheck, quality_check
from steerlab.app.gui.tracker_feed import TrackerFeed
from steerlab.protocols import events as ev
from steerlab.protocols.engine import State
from steerlab.protocols.latin_square import subject_row, williams_square
from steerlab.protocols.protocol import Protocol
from steerlab.protocols.session import TrialSpec, subject_id

if TYPE_CHECKING:  # the rig check's analysis is imported when a rig check is identified
    from steerlab.analysis.rigcheck import Check, RigFit

#: What the subject dashboard says during a rig check.
HANDS_OFF_MESSAGE = "RIG CHECK — let go of the wheel, do not touch it"
#: What it says between trials.
BREAK_MESSAGE = "break"
#: What it says from an emergency stop until the experimenter releases it.
STOPPED_MESSAGE = "Stopped — please let go of the wheel"


@dataclass(frozen=True)
class RigCheckDone:
    """Posted (through the bridge's signal) when a rig check's identification ends."""

    fit: RigFit | None  # None when the identification failed (error)
    checks: list[Check]
    error: BaseException | None


_STATE_COLOUR = {
    "pending": "#ffffff",
    RUNNING: "#fff3b0",
    DONE: "#c8f0c8",
    ABORTED: "#f6c6c6",
}


_ESTOP_STYLE = (
    "QPushButton { background: #d00000; color: white; border-radius: 6px; }"
    "QPushButton:pressed { background: #800000; }"
    # Latched: a different colour at a glance, so nobody takes the rig for ready.
    "QPushButton:checked { background: #ffd60a; color: black; border: 5px solid #d00000; }"
)
ESTOP_TEXT = "EMERGENCY STOP"
ESTOP_LATCHED_TEXT = "E-STOP LATCHED"


def _same_screen(a: QScreen | None, b: QScreen | None) -> bool:
    return a is not None and b is not None and a.geometry() == b.geometry()


def dashboard_span(protocol: Protocol) -> float:
    """Half-width of the subject display, degrees: room for the widest boundary."""
    finite = [c.boundary_deg for c in protocol.conditions if math.isfinite(c.boundary_deg)]
    return max([DEFAULT_SPAN_DEG] + [1.5 * b for b in finite])


def _boundary_text(b: float) -> str:
    if not math.isfinite(b):
        return "none"
    return "centre" if b == 0 else f"±{b:g}°"


def order_text(protocol: Protocol, row: int) -> str:
    """The subject's condition order as a person counts it: "order 2 of 6" for row 1."""
    n = len(williams_square(len(protocol.condition_names)))
    return f"condition order {row + 1} of {n}"


def trial_text(trial_index: int, condition: str, attempt: int | None = None) -> str:
    """How a trial is named on screen ("trial 2 (RT, attempt 1)"): the session file's group
    name ("02_RT_rep1_a1") is for programs."""
    again = f", attempt {attempt}" if attempt is not None else ""
    return f"trial {trial_index} ({condition}{again})"


def abort_text(name: str, status: str, reason: str | None) -> str:
    """The alert for a trial that did not complete, saying "aborted" once: a reason such as
    "aborted by the experimenter" already says it."""
    if not reason:
        return f"{name} {status}"
    if reason.startswith(status):
        return f"{name} {reason}"
    return f"{name} {status}: {reason}"


def session_state_text(c: SessionController, paused_in_trial: bool) -> str:
    """What the session is doing, in words (never the engine's state names): the same text
    between trials whether the last trial completed or was aborted."""
    e = c.engine
    if e is None:
        return "no session"
    if c.in_trial:
        if e.state is State.ABORTING:
            return "trial ending"
        return "trial paused" if paused_in_trial else "trial running"
    if e.state is State.BROKEN:
        return "engine failed: close the window and start again"
    if e.state is State.DONE or not e.pending():
        return "session finished"
    if c.estop_latched:
        return "stopped: release the emergency stop to go on"
    if c.between_trials or (e.state is State.IDLE and not c.worker_alive):
        return "ready for the next trial"
    return "starting the trial"


class ExperimenterWindow(QMainWindow):
    def __init__(
        self,
        protocol: Protocol,
        data_root: str | Path,
        *,
        rig_path: str | None = None,
        rig_factory: RigFactory | None = None,
        dashboard: SubjectDashboard | None = None,
        plot_fps: float = 40.0,
    ) -> None:
        super().__init__()
        self.protocol = protocol
        self.data_root = Path(data_root)
        self.rig_check_periods = 3  # of the hands-off trial's 10 s perturbation period
        self.setWindowTitle(f"Steerlab — experimenter ({protocol.name})")
        self.live = LiveData()
        self.bridge = EngineBridge(self.live, self)
        self.bridge.connect_to(self.on_event)
        self.tracker_feed = TrackerFeed()
        self.vehicle_feed = road_view.VehicleFeed()  # the car, for a loop in another process
        self.controller = SessionController(
            protocol, data_root, rig_path=rig_path, rig_factory=rig_factory,
            subscribers=(self.bridge, self.tracker_feed, self.vehicle_feed),
        )  # fmt: skip
        self.dashboard = dashboard or SubjectDashboard(span_deg=dashboard_span(protocol))
        self.dashboard.angle_source = self._display_angle
        # Esc stops from the subject's window too: it may have the keyboard focus.
        QShortcut(QKeySequence(Qt.Key.Key_Escape), self.dashboard, self.emergency_stop)
        self.road = road_view.install(self.dashboard, protocol, self._display_vehicle)
        self.last_quality: QualityCheck | None = None
        self.events_seen: list[object] = []  # for tests and the log; events are small
        self._trial_names: dict[str, str] = {}  # event key → what the screen calls the trial
        self._closing = False
        self._placing = False
        self._beside = False  # the dashboard was put beside this window, on its screen
        # A window that grows (its content's minimum width) is checked once the resize is
        # over: the dashboard beside it must not end up over it.
        self._clear_timer = QTimer(self)
        self._clear_timer.setSingleShot(True)
        self._clear_timer.setInterval(0)
        self._clear_timer.timeout.connect(self._keep_dashboard_clear)

        central = QWidget()
        outer = QVBoxLayout(central)
        outer.addLayout(self._build_safety_bar())
        split = QSplitter(Qt.Orientation.Horizontal)
        split.addWidget(self._build_left())
        split.addWidget(self._build_right(plot_fps))
        split.setStretchFactor(0, 0)
        split.setStretchFactor(1, 1)
        outer.addWidget(split, 1)
        self.setCentralWidget(central)
        self.resize(1400, 900)

        # The plots' frame rate, always in the status bar: if the machine cannot keep up, the
        # experimenter sees it (frames actually painted, not requested).
        self.fps_label = QLabel("plots: —")
        self.statusBar().addPermanentWidget(self.fps_label)
        self._fps_meter = RateMeter()
        self.status_timer = QTimer(self)
        self.status_timer.setInterval(500)
        self.status_timer.timeout.connect(self.refresh_status)
        self.status_timer.start()
        self._rate_at = (time.monotonic(), 0)
        self.plots.start()
        self._update_order_preview()
        self._refresh_sessions()
        self._update_controls()

    # -- layout -----------------------------------------------------------------------------------
    def _build_safety_bar(self) -> QHBoxLayout:
        bar = QHBoxLayout()
        self.estop_button = QPushButton(ESTOP_TEXT)
        self.estop_button.setMinimumHeight(56)
        self.estop_button.setMinimumWidth(260)
        f = QFont()
        f.setPointSize(16)
        f.setBold(True)
        self.estop_button.setFont(f)
        self.estop_button.setStyleSheet(_ESTOP_STYLE)
        # Checked while latched; only the controller's state sets it, never a click.
        self.estop_button.setCheckable(True)
        self.estop_button.setToolTip("Motor to zero torque and off, trial aborted (Esc)")
        # pressed, not clicked: act on the press; and straight to the engine, no queue.
        self.estop_button.pressed.connect(self.emergency_stop)
        self.estop_button.clicked.connect(self._show_estop_state)
        QShortcut(QKeySequence(Qt.Key.Key_Escape), self, self.emergency_stop)
        self.release_button = QPushButton("Release emergency stop")
        self.release_button.clicked.connect(self._release_estop)
        self.state_label = QLabel("no session")
        sf = QFont()
        sf.setPointSize(12)
        self.state_label.setFont(sf)
        self.alert_label = QLabel("")
        self.alert_label.setStyleSheet("color: #b00000;")
        self.alert_label.setWordWrap(True)
        bar.addWidget(self.estop_button)
        bar.addWidget(self.release_button)
        bar.addWidget(self.state_label)
        bar.addWidget(self.alert_label, 1)
        return bar

    def _build_left(self) -> QWidget:
        w = QWidget()
        w.setMinimumWidth(430)
        w.setMaximumWidth(560)
        lay = QVBoxLayout(w)
        lay.setContentsMargins(0, 0, 0, 0)

        box = QGroupBox("Session")
        g = QGridLayout(box)
        self.new_radio = QRadioButton("New, subject")
        self.resume_radio = QRadioButton("Resume")
        self.new_radio.setChecked(True)
        self.subject_spin = QSpinBox()
        self.subject_spin.setRange(1, 999)
        self.subject_spin.setValue(self._first_free_subject())
        self.subject_spin.valueChanged.connect(self._update_order_preview)
        self.order_label = QLabel("")
        self.order_label.setWordWrap(True)
        self.session_combo = QComboBox()
        self.session_combo.currentIndexChanged.connect(lambda _: self.resume_radio.setChecked(True))
        self.open_button = QPushButton("Open session")
        self.open_button.clicked.connect(self.open_session)
        self.rig_check_button = QPushButton("Rig check (hands off)")
        self.rig_check_button.setToolTip(
            "One trial with nobody touching the wheel: measures the wheel the rig renders "
            "(docs/rig-check.md)"
        )
        self.rig_check_button.clicked.connect(self.open_rig_check)
        g.addWidget(self.new_radio, 0, 0)
        g.addWidget(self.subject_spin, 0, 1)
        g.addWidget(self.order_label, 1, 0, 1, 2)
        g.addWidget(self.resume_radio, 2, 0)
        g.addWidget(self.session_combo, 2, 1)
        g.addWidget(self.open_button, 3, 0, 1, 2)
        g.addWidget(self.rig_check_button, 4, 0, 1, 2)
        lay.addWidget(box)

        self.table = QTableWidget(0, 6)
        self.table.setHorizontalHeaderLabels(
            ["#", "condition", "trial", "boundary", "state", "att."]
        )
        self.table.verticalHeader().setVisible(False)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.itemSelectionChanged.connect(self._update_controls)
        hdr = self.table.horizontalHeader()
        hdr.setStretchLastSection(True)
        for i, wdt in enumerate((32, 80, 50, 70, 70)):
            self.table.setColumnWidth(i, wdt)
        lay.addWidget(self.table, 1)

        ibox = QGroupBox("Instructions (read to the subject)")
        il = QVBoxLayout(ibox)
        self.instructions_label = QLabel("—")
        self.instructions_label.setWordWrap(True)
        f = QFont()
        f.setPointSize(12)
        self.instructions_label.setFont(f)
        il.addWidget(self.instructions_label)
        lay.addWidget(ibox)

        btns = QGridLayout()
        self.start_button = QPushButton("Start trial")
        self.pause_button = QPushButton("Pause")
        self.resume_button = QPushButton("Resume")
        self.abort_button = QPushButton("Abort trial")
        self.redo_button = QPushButton("Redo selected trial")
        self.start_button.clicked.connect(lambda: self._do(self.controller.start))
        self.pause_button.clicked.connect(lambda: self._do(self.controller.pause))
        self.resume_button.clicked.connect(lambda: self._do(self.controller.resume))
        self.abort_button.clicked.connect(lambda: self._do(self.controller.abort))
        self.redo_button.clicked.connect(self._redo_selected)
        btns.addWidget(self.start_button, 0, 0)
        btns.addWidget(self.pause_button, 0, 1)
        btns.addWidget(self.resume_button, 0, 2)
        btns.addWidget(self.abort_button, 1, 0)
        btns.addWidget(self.redo_button, 1, 1, 1, 2)
        lay.addLayout(btns)

        hw = QGroupBox("Hardware")
        hf = QFormLayout(hw)
        self.hw_labels: dict[str, QLabel] = {}
        for key, label in (
            ("rig", "rig"),
            ("drive", "drive"),
            ("glove", "glove stream"),
            ("rate", "samples"),
            ("faults", "faults"),
        ):
            lb = QLabel("—")
            lb.setWordWrap(True)
            self.hw_labels[key] = lb
            hf.addRow(label, lb)
        lay.addWidget(hw)

        dbox = QGroupBox("Subject display")
        dl = QHBoxLayout(dbox)
        self.screen_combo = QComboBox()
        for i, s in enumerate(SubjectDashboard.screens()):
            geo = s.geometry()
            name = s.name() or f"screen {i + 1}"
            self.screen_combo.addItem(f"{name} {geo.width()}×{geo.height()}", s)
        self.fullscreen_check = QCheckBox("full screen")
        self.show_dashboard_button = QPushButton("Show")
        self.show_dashboard_button.clicked.connect(self.show_dashboard)
        dl.addWidget(self.screen_combo, 1)
        dl.addWidget(self.fullscreen_check)
        dl.addWidget(self.show_dashboard_button)
        lay.addWidget(dbox)
        return w

    def _build_right(self, plot_fps: float) -> QWidget:
        right = QSplitter(Qt.Orientation.Vertical)
        self.plots = LivePlots(self.live, fps=plot_fps)
        right.addWidget(self.plots)
        bottom = QWidget()
        bl = QHBoxLayout(bottom)
        bl.setContentsMargins(0, 0, 0, 0)
        qbox = QGroupBox("Quality check (last trial)")
        ql = QVBoxLayout(qbox)
        self.quality_form = QFormLayout()
        self.quality_labels: dict[str, QLabel] = {}
        ql.addLayout(self.quality_form)
        self.quality_warnings = QLabel("")
        self.quality_warnings.setStyleSheet("color: #b00000;")
        self.quality_warnings.setWordWrap(True)
        ql.addWidget(self.quality_warnings)
        self.coherence_plot = CoherencePlot()
        ql.addWidget(self.coherence_plot, 1)
        bl.addWidget(qbox, 3)
        self.admittance = LiveAdmittancePanel(self.live, tracker=self.tracker_feed)
        bl.addWidget(self.admittance, 2)
        right.addWidget(bottom)
        right.setStretchFactor(0, 3)
        right.setStretchFactor(1, 2)
        return right

    # -- session ----------------------------------------------------------------------------------
    def _first_free_subject(self) -> int:
        n = 1
        while session_path(self.data_root, subject_id(n)).exists():
            n += 1
        return n

    def _update_order_preview(self) -> None:
        n = self.subject_spin.value()
        order = self.controller.preview_order(n)
        exists = session_path(self.data_root, subject_id(n)).exists()
        note = "  (file exists: resume it)" if exists else ""
        row = subject_row(n, len(self.protocol.condition_names))
        self.order_label.setText(
            f"{subject_id(n)}, {order_text(self.protocol, row)}: {' → '.join(order)}{note}"
        )

    def _refresh_sessions(self) -> None:
        self.session_combo.blockSignals(True)
        self.session_combo.clear()
        for info in list_sessions(self.data_root, self.protocol):
            text = f"{info.subject}: {info.done}/{info.n_trials} done ({info.path.name})"
            if not info.same_protocol:
                text += " — other protocol"
            self.session_combo.addItem(text, str(info.path))
        self.session_combo.blockSignals(False)

    def open_session(self) -> None:
        try:
            if self.resume_radio.isChecked():
                path = self.session_combo.currentData()
                if not path:
                    raise ControlError(f"no session file to resume in {self.data_root}")
                self.controller.open_resume(path)
            else:
                self.controller.open_new(self.subject_spin.value())
        except (ControlError, ValueError, OSError) as e:
            self._alert(str(e))
            return
        self._alert("")
        plan = self.controller.plan
        assert plan is not None
        self._lock_session_choice()
        self.order_label.setText(
            f"{plan.subject}, {order_text(self.protocol, plan.latin_square_row)}: "
            f"{' → '.join(plan.condition_order)}\nfile: {self.controller.path}"
        )
        self._refresh_table()
        self._show_next()
        self._update_controls()

    def _lock_session_choice(self) -> None:
        for w in (self.new_radio, self.resume_radio, self.subject_spin, self.session_combo,
                  self.open_button, self.rig_check_button):  # fmt: skip
            w.setEnabled(False)

    def open_rig_check(self) -> None:
        try:
            path = self.controller.open_rig_check(self.rig_check_periods)
        except (ControlError, ValueError, OSError) as e:
            self._alert(str(e))
            return
        self._alert("")
        self._lock_session_choice()
        self.order_label.setText(
            f"RIG CHECK: one hands-off trial; nobody may touch the wheel.\nfile: {path}"
        )
        self.dashboard.set_active(False, HANDS_OFF_MESSAGE)
        self._refresh_table()
        self._show_next()
        self._update_controls()

    def _identify_rig_check(self) -> None:
        """The fit off the GUI thread; its result comes back through the bridge's signal."""

        def work():
            try:
                fit, checks = self.controller.identify_rig_check()
                self.bridge.engine_event.emit(RigCheckDone(fit, checks, None))
            except Exception as e:  # shown to the experimenter, never lost
                self.bridge.engine_event.emit(RigCheckDone(None, [], e))

        self._alert("rig check: identifying the wheel ...")
        self.rig_check_thread = threading.Thread(target=work, name="steerlab-rigcheck")
        self.rig_check_thread.start()

    def _show_rig_check(self, done: RigCheckDone) -> None:
        if done.error is not None or done.fit is None:
            self._alert(f"rig check: {done.error}")
            return
        from steerlab.analysis.rigcheck import summary, verdict_line

        # The command line's and the page's verdict: hands on the wheel is NOT VALID, not FAIL.
        verdict = verdict_line(done.fit, done.checks)
        self.rig_check_result = summary(done.fit, done.checks)
        where = self.controller.path.parent if self.controller.path else "?"
        self._alert(f"rig check: {verdict}; rig.json and index.html in {where}")
        self.order_label.setText(f"RIG CHECK done: {verdict}\n{self.rig_check_result}")
        self.dashboard.set_active(False, "Rig check done: you may take the wheel again")

    # -- events from the engine (GUI thread) --------------------------------------------------
    def on_event(self, event: object) -> None:
        self.events_seen.append(event)
        c = self.controller
        if isinstance(event, ev.TrialStarted):
            c.note_event(event)
            self._trial_names[event.key] = trial_text(
                event.trial_index, event.condition, event.attempt
            )
            b = float(event.attributes.get("boundary_deg", math.inf))
            self.plots.set_boundary(b)
            self.dashboard.show_condition(event.condition, b)
            self.road.trial_started(event.attributes)  # a driving trial shows the road
            self.dashboard.set_active(True, HANDS_OFF_MESSAGE if c.is_rig_check else "")
            self._alert("")  # the previous trial's abort or warning is not about this one
            self._show_next()
        elif isinstance(event, ev.TrialEnded):
            self._show_waiting()
            self._quality(event)
            self._show_next()  # the box never shows a finished trial: the next one, at once
            if event.status != "complete":
                name = self._trial_names.get(event.key, f"trial {event.trial_index}")
                self._alert(abort_text(name, event.status, event.reason))
            elif c.is_rig_check:
                self._identify_rig_check()
        elif isinstance(event, RigCheckDone):
            self._show_rig_check(event)
        elif isinstance(event, ev.TrialMark):
            self.statusBar().showMessage(f"{event.kind} at sample {event.sample}", 5000)
        elif isinstance(event, WorkerFinished):
            if event.error is not None:
                self._alert(f"engine stopped with an error: {event.error!r}")
            self._show_next()
        elif isinstance(event, BridgeFault):
            self._alert(event.message.splitlines()[0])
        if isinstance(event, ev.TrialEnded | ev.TrialStarted | ev.TrialSuperseded | ev.StateChanged
                      | ev.SessionEnded | WorkerFinished):  # fmt: skip
            self._refresh_table()
            self._update_controls()

    def _quality(self, end: ev.TrialEnded) -> None:
        c = self.controller
        cap = self.live.take_trial(end.key)
        plan = c.plan
        if cap is None or plan is None:
            return
        a = cap.attributes
        try:
            q = quality_check(
                cap.channels(),
                key=end.key,
                condition=cap.condition,
                status=end.status,
                fs_hz=float(a["fs_hz"]),
                measured_start=int(a["measured_start"]),
                measured_stop=int(a["measured_stop"]),
                design=plan.design,
                boundary_deg=float(a.get("boundary_deg", math.inf)),
                n_planned=cap.n_planned,
                n_engine=end.n_samples,
                loop_stats=end.stats,
                steps_by_sample=c.rig is not None and c.rig.steps_by_sample,
            )
        except Exception as e:  # a figure that cannot be computed must not hide the others
            name = self._trial_names.get(end.key, f"trial {end.trial_index}")
            self._alert(f"quality check of {name} failed: {e!r}")
            return
        self.last_quality = q
        self._show_quality(q)

    def _show_quality(self, q: QualityCheck) -> None:
        name = self._trial_names.get(q.key, q.key)
        while self.quality_form.rowCount():
            self.quality_form.removeRow(0)
        self.quality_labels = {}
        for label, value in q.rows():
            if label == "trial":
                value = f"{name}: {q.status}"
            lb = QLabel(value)
            lb.setWordWrap(True)  # a long value wraps instead of widening the window
            self.quality_labels[label] = lb
            self.quality_form.addRow(label, lb)
        self.quality_warnings.setText("; ".join(q.warnings))
        self.coherence_plot.show_coherence(q.band_frequencies_hz, q.coherence)

    # -- controls ---------------------------------------------------------------------------------
    def _do(self, action) -> None:
        try:
            action()
        except ControlError as e:
            self._alert(str(e))
        self._update_controls()

    def emergency_stop(self) -> None:
        try:
            self.controller.emergency_stop()
        except Exception as e:  # the drive could not be reached: say so as loudly as possible
            self._alert(f"EMERGENCY STOP FAILED: {e!r} — switch the rig off at the mains")
        else:
            self._alert("emergency stop: motor off, trial aborted. Check the subject and the rig.")
        self._show_waiting()
        self._update_controls()

    def _show_waiting(self) -> None:
        """The subject's dashboard while no trial runs: stopped while the emergency stop is
        latched (the experimenter's window shows E-STOP LATCHED), else a break."""
        c = self.controller
        if c.estop_latched:
            message = STOPPED_MESSAGE
        elif c.is_rig_check and c.next_trial() is not None:
            message = HANDS_OFF_MESSAGE  # the hands-off trial has still to run
        else:
            message = BREAK_MESSAGE
        self.dashboard.set_active(False, message)

    def _show_estop_state(self) -> None:
        latched = self.controller.estop_latched
        self.estop_button.setChecked(latched)
        self.estop_button.setText(ESTOP_LATCHED_TEXT if latched else ESTOP_TEXT)
        self.estop_button.setToolTip(
            "Latched: motor off. Check the subject and the rig, then Release emergency stop "
            "(pressing it again stops again)"
            if latched
            else "Motor to zero torque and off, trial aborted (Esc)"
        )

    def _release_estop(self) -> None:
        self._do(self.controller.release_estop)
        if not self.controller.estop_latched:
            self._alert("")
            self._show_waiting()

    def _selected_trial(self) -> int | None:
        rows = self.table.selectionModel().selectedRows() if self.table.selectionModel() else []
        if not rows:
            return None
        item = self.table.item(rows[0].row(), 0)
        return int(item.text()) if item else None

    def select_trial(self, trial_index: int) -> None:
        self.table.selectRow(trial_index - 1)

    def _redo_selected(self) -> None:
        idx = self._selected_trial()
        if idx is None:
            self._alert("select the trial to redo in the list")
            return
        self._do(lambda: self.controller.redo(idx))

    def _update_controls(self) -> None:
        c = self.controller
        open_ = c.is_open
        in_trial = c.in_trial
        paused_in_trial = in_trial and c.engine is not None and c.engine.state.value == "paused"
        self.start_button.setEnabled(c.can_start())
        self.pause_button.setEnabled(open_ and in_trial and not paused_in_trial)
        self.resume_button.setEnabled(bool(paused_in_trial) and not c.estop_latched)
        self.abort_button.setEnabled(open_ and in_trial)  # not while waiting for start
        sel = self._selected_trial()
        self.redo_button.setEnabled(
            open_ and not in_trial and sel is not None and c.engine is not None
            and c.engine.status_of(sel) == "complete"
        )  # fmt: skip
        self.release_button.setVisible(c.estop_latched)
        self.estop_button.setEnabled(True)  # never disabled
        self._show_estop_state()
        self.state_label.setText(session_state_text(c, paused_in_trial))

    def _refresh_table(self) -> None:
        rows = self.controller.trial_rows()
        sel = self._selected_trial()
        self.table.setRowCount(len(rows))
        for i, r in enumerate(rows):
            s = r.spec
            vals = [str(s.trial_index), s.condition, s.label, _boundary_text(s.boundary_deg),
                    r.state, str(r.attempts)]  # fmt: skip
            colour = QColor(_STATE_COLOUR.get(r.state, "#ffffff"))
            for j, v in enumerate(vals):
                it = self.table.item(i, j)
                if it is None:
                    it = QTableWidgetItem()
                    self.table.setItem(i, j, it)
                it.setText(v)
                it.setBackground(colour)
        if sel is not None:
            self.table.selectRow(sel - 1)

    def trial_states(self) -> dict[int, str]:
        """Trial index → state as the list shows it."""
        return {int(self._cell(i, 0)): self._cell(i, 4) for i in range(self.table.rowCount())}

    def _cell(self, row: int, column: int) -> str:
        item = self.table.item(row, column)
        if item is None:  # every cell is filled when the list is built
            raise LookupError(f"trial list: no cell at row {row}, column {column}")
        return item.text()

    def _show_next(self) -> None:
        spec: TrialSpec | None = self.controller.next_trial()
        if spec is None:
            self.instructions_label.setText("—" if not self.controller.is_open else "session done")
            return
        words = html.escape(spec.instructions)
        self.instructions_label.setText(
            f"<b>{html.escape(spec.condition)}</b> — trial {spec.trial_index} ({spec.label}), "
            f"boundary {_boundary_text(spec.boundary_deg)}<br><br>“{words}”"
        )
        if not self.controller.in_trial:
            self.dashboard.show_condition(spec.condition, spec.boundary_deg)
            self.plots.set_boundary(spec.boundary_deg)

    # -- status -----------------------------------------------------------------------------------
    def _display_vehicle(self) -> dict[str, float] | None:
        rig = self.controller.rig
        shown = None if rig is None else getattr(rig.display, "vehicle", None)
        return shown or self.vehicle_feed.latest()

    def _display_angle(self) -> float | None:
        rig = self.controller.rig
        if rig is not None and rig.display.updates:
            return rig.display.angle_rad  # straight from the loop, every few cycles
        # A loop in another process shows nothing here: the newest sample received instead.
        return self.live.latest("wheel_angle_rad")

    def _show_frame_rate(self, now: float) -> None:
        fps = self._fps_meter.rate(self.plots.frames.frames, now)
        if fps is None:
            return
        if self.plots.idle:
            self.fps_label.setText("plots: no new data")
        else:
            self.fps_label.setText(f"plots: {fps:.0f} frames/s")

    def refresh_status(self) -> None:
        now, total = time.monotonic(), self.live.total_received
        self._show_frame_rate(now)
        t0, n0 = self._rate_at
        rate = (total - n0) / (now - t0) if now > t0 else 0.0
        self._rate_at = (now, total)
        rig = self.controller.rig
        if rig is None:
            return
        try:
            st = rig.status()
        except Exception as e:  # a status read must not take the window down
            self.hw_labels["faults"].setText(f"status unavailable: {e!r}")
            return
        self.hw_labels["rig"].setText(st.get("rig", rig.name))
        self.hw_labels["drive"].setText(st.get("drive_state", "?"))
        g = st.get("glove_rate_hz")
        self.hw_labels["glove"].setText(
            f"{g:.0f} frames/s" if g is not None else st.get("glove_note", "—")
        )
        self.hw_labels["rate"].setText(f"{rate:.0f} /s received")
        faults = st.get("faults") or []
        self.hw_labels["faults"].setText("; ".join(faults) if faults else "none")
        self.hw_labels["faults"].setStyleSheet("color: #b00000;" if faults else "")
        self._update_controls()

    def _alert(self, text: str) -> None:
        self.alert_label.setText(text)

    # -- subject display --------------------------------------------------------------------------
    def show_dashboard(self) -> None:
        screen = self.screen_combo.currentData()
        full = self.fullscreen_check.isChecked()
        if screen is not None and not full and _same_screen(screen, self.screen()):
            self._place_beside()  # never centred over this window and its stop button
            return
        self._beside = False
        self.dashboard.show_on(screen, full)

    def place_windows(self) -> None:
        """Put the subject's window where it cannot hide this one (call after show()).

        Without a window manager both windows open at the top-left corner and the dashboard
        would cover EMERGENCY STOP. With a second screen the dashboard goes there (it is the
        subject's monitor) and this window is fitted into its own screen; on one screen the
        windows are put side by side (:func:`steerlab.app.gui.placement.side_by_side`), and
        put side by side again if this window grows over the dashboard.
        """
        mine = self.screen()
        others = [s for s in SubjectDashboard.screens() if not _same_screen(s, mine)]
        if others:
            target = others[0]
            for i in range(self.screen_combo.count()):
                if _same_screen(self.screen_combo.itemData(i), target):
                    self.screen_combo.setCurrentIndex(i)
            self._fit_on_screen()
            self._beside = False
            self.dashboard.show_on(target, self.fullscreen_check.isChecked())
            return
        self._place_beside()

    def _frame_extra(self, w: QWidget) -> tuple[int, int]:
        """Title bar and borders around ``w`` (none without a window manager), px."""
        extra = w.frameGeometry().size() - w.geometry().size()
        return extra.width(), extra.height()

    def _fit_on_screen(self) -> None:
        """Shrink and move this window (not below its minimum) into its screen."""
        geo = self.screen().availableGeometry()
        fw, fh = self._frame_extra(self)
        hint = self.minimumSizeHint()
        w = max(hint.width(), min(self.width(), geo.width() - fw))
        h = max(hint.height(), min(self.height(), geo.height() - fh))
        f = self.frameGeometry()
        x = max(geo.x(), min(f.x(), geo.x() + geo.width() - (w + fw)))
        y = max(geo.y(), min(f.y(), geo.y() + geo.height() - (h + fh)))
        self._placing = True
        try:
            self.resize(w, h)
            self.move(x, y)  # move() places the frame, resize() sizes the inside
        finally:
            self._placing = False

    def _place_beside(self) -> None:
        geo = self.screen().availableGeometry()
        d = self.dashboard
        efw, efh = self._frame_extra(self)
        dfw, dfh = self._frame_extra(d)
        hint = self.minimumSizeHint()
        exp, dash = side_by_side(
            (geo.x(), geo.y(), geo.width(), geo.height()),
            (self.width() + efw, self.height() + efh),
            (hint.width() + efw, hint.height() + efh),
            (d.width() + dfw, d.height() + dfh),
        )
        self._placing = True
        try:
            self.move(exp[0], exp[1])  # move() places the frame, resize() sizes the inside
            self.resize(exp[2] - efw, exp[3] - efh)
            if d.isFullScreen():
                d.showNormal()
            d.move(dash[0], dash[1])
            d.resize(dash[2] - dfw, dash[3] - dfh)
            d.show()
            d.raise_()
        finally:
            self._placing = False
        self._beside = True

    def resizeEvent(self, event: QResizeEvent) -> None:  # noqa: N802 (Qt's name)
        super().resizeEvent(event)
        if not self._placing:
            self._clear_timer.start()

    def _keep_dashboard_clear(self) -> None:
        """Put the windows side by side again if this one has grown over the dashboard that
        was put beside it (a dashboard the experimenter sent elsewhere, or full screen, stays)."""
        d = self.dashboard
        if not self._beside or self._closing or not (self.isVisible() and d.isVisible()):
            return
        if d.isFullScreen():
            return
        if not _same_screen(d.screen(), self.screen()):
            return
        if not self.frameGeometry().intersects(d.frameGeometry()):
            return
        # Only where both fit: on a narrower screen no placement is free of overlap, and a
        # window manager that clamps the window would be fought for ever.
        fw, _ = self._frame_extra(self)
        room = self.screen().availableGeometry().width() - GAP - MIN_DASHBOARD_WIDTH
        if self.minimumSizeHint().width() + fw <= room:
            self._place_beside()

    # -- closing ----------------------------------------------------------------------------------
    def closeEvent(self, event: QCloseEvent) -> None:  # noqa: N802 (Qt's name)
        if not self._closing:
            self._closing = True
            self.plots.stop()
            self.status_timer.stop()
            try:
                # Abort a running trial ("window closed"); the writer keeps every sample.
                self.controller.shutdown("window closed")
            except ControlError as e:
                self._alert(str(e))
            t = getattr(self, "rig_check_thread", None)
            if t is not None:
                t.join(60.0)  # a rig check's fit: seconds; its files must be complete
            self.dashboard.close()
        event.accept()
