"""What the experimenter's buttons do, without Qt: sessions, the engine's worker thread, safety.

Threads: the engine runs in one worker thread (``steerlab-engine``), started by :meth:`start`.
Its subscribers (the LSL clock or publisher, the session writer, then the GUI's bridge) are
called on that thread.
Every method here is called from the GUI thread. They only post requests to the engine
(``pause``/``resume``/``abort``), except :meth:`emergency_stop`, which calls the engine's
``emergency_stop()`` directly: it goes straight to the loop's drive, whatever the engine thread
is doing.

One trial at a time: the engine is built with ``pause_between_trials=True``, so after each trial
it waits (state ``paused``, no trial current) until :meth:`start` resumes it.

On the lab's clock: the session is published on LSL (before the writer and the GUI's own
subscribers) unless ``lsl`` is False or ``STEERLAB_LSL=off``; the trials record the LSL clock
at their first sample either way (:mod:`protocols.lsl_publisher`, ``docs/lsl.md``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from steerlab.app.gui.rig import RigHandle, make_rig_loop
from steerlab.protocols import events as ev
from steerlab.protocols.datafile import DataFileError, SessionFile, SessionWriter, session_files
from steerlab.protocols.engine import IllegalTransition, SessionEngine, State
from steerlab.protocols.lsl_publisher import (
    LabClock,
    LslPublisher,
    close_lab_subscriber,
    lab_clock_for,
    lab_subscriber,
    publish_default,
)
from steerlab.protocols.names import UnsafeNameError, check_name, inside
from steerlab.protocols.protocol import Protocol
from steerlab.protocols.session import SessionPlan, TrialSpec, build_plan, subject_id
from steerlab.protocols.writelock import LockedError, WriterLock

#: Trial states in the trial list.
PENDING, RUNNING, DONE, ABORTED = "pending", "running", "done", "aborted"
_FROM_ENGINE = {"pending": PENDING, "running": RUNNING, "complete": DONE, "aborted": ABORTED}

RigFactory = Callable[[str | None, int, Protocol], RigHandle]


class ControlError(RuntimeError):
    """A request that cannot be honoured now; the message is for the experimenter."""


@dataclass(frozen=True)
class WorkerFinished:
    """Posted by the worker thread when ``engine.run()`` returned or raised."""

    state: str
    error: BaseException | None


@dataclass(frozen=True)
class SessionFileInfo:
    path: Path
    subject: str
    subject_number: int
    done: int
    n_trials: int
    same_protocol: bool


@dataclass(frozen=True)
class TrialRow:
    spec: TrialSpec
    state: str
    attempts: int


def session_path(root: str | Path, subject: str) -> Path:
    return Path(root) / f"{subject}.h5"


def list_sessions(root: str | Path, protocol: Protocol) -> list[SessionFileInfo]:
    """Session files in ``root`` that can be resumed (unreadable ones are skipped)."""
    out = []
    try:
        paths = session_files(root)
    except DataFileError:
        return []
    for p in paths:
        try:
            sf = SessionFile(p)
            number = int(sf.attrs["subject_number"])
        except (DataFileError, KeyError, TypeError, ValueError):
            continue
        att = sf.attempts()
        done = sum(1 for v in att.values() if any(s == "complete" for _, s in v))
        out.append(
            SessionFileInfo(
                path=p,
                subject=sf.subject,
                subject_number=number,
                done=done,
                n_trials=len(build_plan(protocol, number).trials),
                same_protocol=sf.attrs.get("protocol_toml") == protocol.source_text,
            )
        )
    return out


class SessionController:
    def __init__(
        self,
        protocol: Protocol,
        data_root: str | Path,
        *,
        rig_path: str | None = None,
        rig_factory: RigFactory | None = None,
        subscribers: tuple[Callable[[object], None], ...] = (),
        lsl: bool | None = None,
    ) -> None:
        """``subscribers`` get the engine's events (on the engine thread) and this
        controller's :class:`WorkerFinished` (on the worker thread). ``lsl``: publish the
        session on LSL (None: yes, unless ``STEERLAB_LSL=off``)."""
        self.protocol = protocol
        self.data_root = Path(data_root)
        self.rig_path = rig_path
        self.rig_factory: RigFactory = rig_factory or (
            lambda path, subject, protocol: make_rig_loop(path, subject, protocol)
        )
        self.subscribers = tuple(subscribers)
        self.lsl = publish_default(True, strict=False) if lsl is None else bool(lsl)
        self.lab: LabClock | LslPublisher | None = None  # the LSL clock, or its publisher
        self.plan: SessionPlan | None = None
        self.engine: SessionEngine | None = None
        self.rig: RigHandle | None = None
        self.writer: SessionWriter | None = None
        self.path: Path | None = None
        self.estop_latched = False
        self._worker: threading.Thread | None = None
        self._attempts: dict[int, int] = {}
        self._lock: WriterLock | None = None

    # -- opening a session ---------------------------------------------------------------------
    def preview_order(self, subject_number: int) -> tuple[str, ...]:
        return build_plan(self.protocol, subject_number).condition_order

    def open_new(self, subject_number: int) -> Path:
        if subject_number < 1:
            raise ControlError(f"subject number must be ≥ 1, got {subject_number}")
        path = session_path(self.data_root, subject_id(subject_number))
        if path.exists():
            raise ControlError(f"{path} exists already: resume it instead")
        self._open(build_plan(self.protocol, subject_number), path, None)
        return path

    def open_resume(self, path: str | Path) -> Path:
        path = Path(path)
        try:
            sf = SessionFile(path)
        except DataFileError as e:
            raise ControlError(str(e)) from None
        if sf.attrs.get("protocol_toml") != self.protocol.source_text:
            raise ControlError(
                f"{path} was recorded with a different protocol; start the GUI with the "
                "same --protocol as the session"
            )
        try:
            number = int(sf.attrs["subject_number"])
        except (KeyError, TypeError, ValueError):
            raise ControlError(
                f"{path}: no subject_number attribute; cannot rebuild its plan"
            ) from None
        self._open(build_plan(self.protocol, number, sf.subject), path, sf.attempts())
        return path

    def open_rig_check(self, periods: int = 3) -> Path:
        """A rig check instead of a session: one hands-off trial (docs/rig-check.md), recorded
        in ``DATA_ROOT/rigcheck/<UTC time>/rigcheck.h5``; :meth:`identify_rig_check` then
        writes rig.json and index.html beside it."""
        from datetime import UTC, datetime

        from steerlab.app.rigcheck import SESSION_FILE, hands_off_plan

        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
        path = self.data_root / "rigcheck" / stamp / SESSION_FILE
        if path.exists():
            raise ControlError(f"{path} exists already: wait a second and try again")
        self._open(hands_off_plan(self.protocol, periods), path, None, hands_off=True)
        return path

    @property
    def is_rig_check(self) -> bool:
        from steerlab.app.rigcheck import HandsOffPlan

        return isinstance(self.plan, HandsOffPlan)

    def identify_rig_check(self):
        """Fit the rig check's recording; (RigFit, checks). Runs for a few seconds: call it off
        the GUI thread."""
        from steerlab.analysis.rigcheck import identify

        if not self.is_rig_check or self.path is None:
            raise ControlError("no rig check is open")
        return identify(self.path, self.path.parent, rig_path=self.rig_path)

    def _open(
        self, plan: SessionPlan, path: Path, attempts: dict | None, *, hands_off: bool = False
    ) -> None:
        if self.engine is not None:
            raise ControlError("a session is open already; close the window to start another")
        try:
            check_name(plan.subject, f"{path}: subject")
            self.data_root.mkdir(parents=True, exist_ok=True)
            inside(self.data_root, path)
            path.parent.mkdir(parents=True, exist_ok=True)  # a rig check's own folder
            # The writer lock first: a session another process writes is refused, naming it.
            lock = WriterLock(path).acquire()
        except (UnsafeNameError, LockedError) as e:
            raise ControlError(str(e)) from None
        try:
            rig = self.rig_factory(self.rig_path, plan.subject_number, self.protocol)
        except BaseException:
            lock.release()
            raise
        engine = SessionEngine(plan, rig.loop, attempts=attempts, pause_between_trials=True)
        path.parent.mkdir(parents=True, exist_ok=True)
        extra = dict(rig.extra_attributes) | ({"hands_off_check": True} if hands_off else {})
        clock = lab_clock_for(rig.loop)
        writer = SessionWriter(
            path,
            extra_attributes=extra,
            lock=lock,
            first_sample_attributes=clock.first_sample_attributes,
        )
        self._lock = lock
        self.lab = lab_subscriber(
            clock,
            self.lsl,
            rig=rig.name,
            session_path=path,
            nominal_rate_hz=self.protocol.loop_rate_hz,
        )
        # First the LSL clock (it reads each block's arrival before anyone's work on it; it
        # takes microseconds and never raises), then the file, before anything is displayed.
        engine.subscribe(self.lab)
        if hands_off:
            from steerlab.app.rigcheck import mark_hands_off

            engine.subscribe(mark_hands_off(writer))
        else:
            engine.subscribe(writer)
        for s in self.subscribers:
            engine.subscribe(s)
        self.plan, self.rig, self.engine, self.writer, self.path = plan, rig, engine, writer, path
        self._attempts = {k: len(v) for k, v in (attempts or {}).items()}

    # -- state for the view ----------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self.engine is not None

    @property
    def worker_alive(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    @property
    def in_trial(self) -> bool:
        return self.engine is not None and self.engine.current is not None

    @property
    def between_trials(self) -> bool:
        """The engine waits for the experimenter to start the next trial."""
        e = self.engine
        return self.worker_alive and e is not None and e.state is State.PAUSED and not self.in_trial

    def can_start(self) -> bool:
        e = self.engine
        if e is None or self.estop_latched:
            return False
        if self.worker_alive:
            return self.between_trials
        return e.state is State.IDLE and bool(e.pending())

    def trial_rows(self) -> list[TrialRow]:
        e, plan = self.engine, self.plan
        if e is None or plan is None:
            return []
        return [
            TrialRow(t, _FROM_ENGINE.get(e.status_of(t.trial_index), ABORTED),
                     self._attempts.get(t.trial_index, 0))
            for t in plan.trials
        ]  # fmt: skip

    def next_trial(self) -> TrialSpec | None:
        """The running trial, or the one the next start will run."""
        e = self.engine
        if e is None:
            return None
        cur = e.current
        if cur is not None:
            return cur.spec
        todo = e.pending()
        return todo[0] if todo else None

    def note_event(self, event: object) -> None:
        """Keep the attempt counts shown in the list (call on the GUI thread)."""
        if isinstance(event, ev.TrialStarted):
            self._attempts[event.trial_index] = max(
                self._attempts.get(event.trial_index, 0), event.attempt
            )

    # -- requests --------------------------------------------------------------------------------
    def start(self) -> None:
        e = self._need_engine()
        if self.estop_latched:
            raise ControlError("release the emergency stop first")
        if self.worker_alive:
            if not self.between_trials:
                raise ControlError("a trial is running")
            e.resume()  # the engine waits between trials: this starts the next one
            return
        if e.state is State.DONE or not e.pending():
            raise ControlError("every trial of this session is done")
        if e.state is State.BROKEN:
            raise ControlError(f"the engine is broken ({e.last_error!r}); restart the GUI")
        self._worker = threading.Thread(target=self._run, name="steerlab-engine", daemon=False)
        self._worker.start()

    def _run(self) -> None:
        engine = self.engine
        assert engine is not None
        state, error = State.BROKEN.value, None
        try:
            state = engine.run().value
        except BaseException as e:  # reported to the GUI, which shows it; never dies silently
            error = e
        finally:
            done = WorkerFinished(state, error)
            for s in self.subscribers:
                try:
                    s(done)
                except Exception:
                    pass

    def pause(self) -> None:
        e = self._need_engine()
        if not self.in_trial:
            raise ControlError("no trial is running")
        try:
            e.pause()
        except IllegalTransition as x:
            raise ControlError(str(x)) from None

    def resume(self) -> None:
        e = self._need_engine()
        if not (self.in_trial and e.state is State.PAUSED):
            raise ControlError("no paused trial to resume")
        e.resume()

    def abort(self, reason: str = "aborted by the experimenter") -> None:
        self._need_engine().abort(reason)

    def redo(self, trial_index: int, timeout_s: float = 10.0) -> None:
        """Run ``trial_index`` again at the next start; its complete attempt is superseded."""
        e = self._need_engine()
        if self.in_trial:
            raise ControlError("abort the running trial first")
        if e.status_of(trial_index) != "complete":
            raise ControlError(f"trial {trial_index} has no complete attempt; it runs anyway")
        if self.worker_alive:
            # The engine waits between trials; a redo needs it idle (engine.redo's rule).
            e.abort(f"redo of trial {trial_index} requested")
            self.join(timeout_s)
        try:
            e.redo(trial_index)
        except IllegalTransition as x:
            raise ControlError(str(x)) from None

    def emergency_stop(self) -> None:
        """Motor to zero torque and off now; the trial ends as aborted. Works in any state."""
        self.estop_latched = True
        if self.engine is not None:
            self.engine.emergency_stop()
        elif self.rig is not None:
            self.rig.loop.emergency_stop()

    def release_estop(self) -> None:
        if self.in_trial:
            raise ControlError("the trial is still ending")
        self.estop_latched = False

    def join(self, timeout_s: float) -> bool:
        w = self._worker
        if w is None:
            return True
        w.join(timeout_s)
        return not w.is_alive()

    def shutdown(self, reason: str = "window closed", timeout_s: float = 10.0) -> None:
        """End the session safely: abort a running trial (the writer keeps every sample up to
        the end of the trial), wait for the worker, close the file and the rig."""
        if self.engine is not None and self.worker_alive:
            self.engine.abort(reason)
            if not self.join(timeout_s):
                # The loop did not come back: stop the motor directly, then wait again.
                self.engine.emergency_stop(f"{reason}; loop did not stop")
                self.join(timeout_s)
        if self.worker_alive:
            raise ControlError(
                f"the engine thread did not stop within {2 * timeout_s:.0f} s; "
                "the session file may be left incomplete"
            )
        if self.writer is not None:
            self.writer.close()
        close_lab_subscriber(self.lab)
        if self._lock is not None:
            self._lock.release()
            self._lock = None
        if self.rig is not None:
            self.rig.close()

    def _need_engine(self) -> SessionEngine:
        if self.engine is None:
            raise ControlError("open a session first")
        return self.engine
