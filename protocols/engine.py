"""The session engine: walks a subject's trials through a control loop, as a state machine.

States and legal transitions are in ``TRANSITIONS``; anything else raises
:class:`IllegalTransition`. The engine knows devices only through the :class:`TrialLoop` it is
given, and its subscribers only as callables that take plain events.

Thread model: ``run()`` blocks the thread that calls it (a worker thread in the GUI, the main
thread headless). ``pause``, ``resume``, ``abort``, ``redo`` and ``emergency_stop`` may be
called from any other thread; they take effect at the next block of samples, except the
emergency stop, which goes straight to the loop.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Generator, Iterator
from dataclasses import replace
from enum import StrEnum
from typing import Protocol

from steerlab.protocols import events as ev
from steerlab.protocols.records import STATUS_ABORTED, STATUS_COMPLETE, STATUS_SUPERSEDED
from steerlab.protocols.session import SessionPlan, TrialSetup, TrialSpec

STOP_GRACE_S = 2.0


class State(StrEnum):
    IDLE = "idle"
    RUNNING = "running"
    PAUSED = "paused"
    ABORTING = "aborting"
    DONE = "done"
    BROKEN = "broken"


TRANSITIONS: dict[State, set[State]] = {
    State.IDLE: {State.RUNNING, State.DONE},
    State.RUNNING: {State.PAUSED, State.ABORTING, State.IDLE, State.DONE, State.BROKEN},
    State.PAUSED: {State.RUNNING, State.ABORTING, State.IDLE, State.BROKEN},
    State.ABORTING: {State.IDLE, State.BROKEN},
    State.DONE: {State.IDLE},  # a redo after the end reopens the session
    State.BROKEN: {State.IDLE},  # only through reset(), after a person has looked
}


class IllegalTransition(RuntimeError):
    pass


class TrialFault(Exception):
    """A loop's reason to end the trial as aborted (lost heartbeat, glove stream stopped, ...)."""


class LoopControl:
    """What the engine tells a running loop; shared between threads."""

    def __init__(self) -> None:
        self.abort_reason: str | None = None
        self.paused = threading.Event()

    @property
    def stop_requested(self) -> bool:
        return self.abort_reason is not None


class TrialLoop(Protocol):
    """Runs one trial, yielding blocks of samples (channel name → array) as they come.

    It must leave the motor at zero torque when the generator ends, however it ends
    (exhausted, closed by the engine, or by an exception), and raise :class:`TrialFault`
    for a condition that should abort the trial.
    """

    def run_trial(self, setup: TrialSetup, control: LoopControl) -> Iterator[dict]: ...

    def emergency_stop(self) -> None: ...

    def trial_stats(self) -> dict: ...


Subscriber = Callable[[object], None]


class SessionEngine:
    def __init__(
        self,
        plan: SessionPlan,
        loop: TrialLoop,
        *,
        attempts: dict[int, list[tuple[int, str]]] | None = None,
        pause_between_trials: bool = False,
        pace_breaks: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``attempts``: what a session file already holds, trial index → [(attempt, status)];
        a trial with a complete attempt is done, the rest are run (resume)."""
        self.plan = plan
        self.loop = loop
        self.pause_between_trials = pause_between_trials
        self.pace_breaks = pace_breaks
        self.clock = clock
        self._subs: list[Subscriber] = []
        self._state = State.IDLE
        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        self._pause_req = False
        self._stop_req: str | None = None
        self._control: LoopControl | None = None
        self._attempts = {k: list(v) for k, v in (attempts or {}).items()}
        self._deferred: list[int] = []  # trial indices to run after the others, in this order
        self.current: TrialSetup | None = None
        self.last_error: BaseException | None = None

    # -- subscribers ------------------------------------------------------------------------
    def subscribe(self, callback: Subscriber) -> Callable[[], None]:
        self._subs.append(callback)
        return lambda: self._subs.remove(callback)

    def _emit(self, event: object) -> None:
        for cb in list(self._subs):
            cb(event)

    # -- state ------------------------------------------------------------------------------
    @property
    def state(self) -> State:
        return self._state

    def _transition(self, new: State, reason: str = "") -> None:
        with self._lock:
            old = self._state
            if new == old:
                return
            if new not in TRANSITIONS[old]:
                raise IllegalTransition(f"engine cannot go from {old.value} to {new.value}")
            self._state = new
            self._wake.notify_all()
        self._emit(ev.StateChanged(old.value, new.value, reason))

    def status_of(self, trial_index: int) -> str:
        """pending | complete | aborted | running, for lists and the GUI."""
        if self.current is not None and self.current.spec.trial_index == trial_index:
            return "running"
        att = self._attempts.get(trial_index, [])
        if any(s == STATUS_COMPLETE for _, s in att):
            return "complete"
        if any(s != STATUS_SUPERSEDED for _, s in att):
            return "aborted"  # aborted, or left incomplete by a writer that died
        return "pending"

    def attempts_of(self, trial_index: int) -> list[tuple[int, str]]:
        """[(attempt, status)] recorded so far for a trial."""
        return list(self._attempts.get(trial_index, []))

    @property
    def waiting_for_start(self) -> bool:
        """Paused between trials: the next trial starts on resume()."""
        return self._state is State.PAUSED and self.current is None

    def pending(self) -> list[TrialSpec]:
        """The trials without a complete attempt, in the order they run: the plan's, except
        that deferred trials come after the others."""
        todo = [t for t in self.plan.trials if self.status_of(t.trial_index) != "complete"]
        later = [t for i in self._deferred for t in todo if t.trial_index == i]
        return [t for t in todo if t.trial_index not in self._deferred] + later

    # -- requests from other threads ----------------------------------------------------------
    def pause(self) -> None:
        with self._lock:
            if self._state is not State.RUNNING:
                raise IllegalTransition(f"cannot pause while {self._state.value}")
            self._pause_req = True
            if self._control:
                self._control.paused.set()

    def resume(self) -> None:
        with self._lock:
            self._pause_req = False
            if self._control:
                self._control.paused.clear()
            self._wake.notify_all()

    def abort(self, reason: str = "aborted by the experimenter") -> None:
        """End the current trial as aborted and stop before the next one."""
        with self._lock:
            self._stop_req = reason
            if self._control:
                self._control.abort_reason = reason
            self._pause_req = False
            self._wake.notify_all()

    def emergency_stop(self, reason: str = "emergency stop") -> None:
        # Straight to the loop, not via the engine thread: the motor must stop now.
        # The reason first (a flag, microseconds), so the trial records why; then the loop.
        self.abort(reason)
        self.loop.emergency_stop()

    def redo(self, trial_index: int, reason: str = "redo requested by the experimenter") -> None:
        """Run this trial again; the earlier attempt stays in the file, marked superseded."""
        with self._lock:
            busy = self._state in (State.RUNNING, State.PAUSED, State.ABORTING)
            if busy and not self.waiting_for_start:
                raise IllegalTransition(f"cannot redo a trial while {self._state.value}")
            spec = self.plan.trial(trial_index)
            att = self._attempts.get(trial_index, [])
            for a, s in att:
                if s == STATUS_COMPLETE:
                    self._emit(ev.TrialSuperseded(spec.key(a), trial_index, reason))
            self._attempts[trial_index] = [
                (a, STATUS_SUPERSEDED if s == STATUS_COMPLETE else s) for a, s in att
            ]
            if trial_index in self._deferred:  # a redo runs where the plan has it
                self._deferred.remove(trial_index)
            if self._state is State.DONE:
                self._transition(State.IDLE, "trial reopened for a redo")

    def defer(self, trial_index: int) -> None:
        """Run this trial after the other pending ones (going on from an aborted trial): the
        next run starts at the next trial, and this one comes last. Its attempts stay as they
        are recorded. Not while a trial runs."""
        with self._lock:
            busy = self._state in (State.RUNNING, State.PAUSED, State.ABORTING)
            if busy and not self.waiting_for_start:
                raise IllegalTransition(f"cannot defer a trial while {self._state.value}")
            self.plan.trial(trial_index)  # an unknown index raises here
            if trial_index in self._deferred:
                self._deferred.remove(trial_index)
            self._deferred.append(trial_index)

    def reset(self) -> None:
        """Leave BROKEN after a person has checked the rig."""
        self._transition(State.IDLE, "reset")

    # -- the walk -------------------------------------------------------------------------------
    def run(self) -> State:
        """Run pending trials until the session is done, a trial is aborted, or abort() is called.

        Returns the final state (DONE, IDLE or BROKEN). Call again to continue: the next run
        starts at the first trial without a complete attempt.
        """
        with self._lock:
            self._stop_req = None
            self._pause_req = False
        if not self.pending():
            if self._state is not State.DONE:
                self._transition(State.DONE, "nothing left to run")
            return self._state
        self._transition(State.RUNNING)
        previous: TrialSpec | None = None
        try:
            self._emit(
                ev.SessionStarted(
                    subject=self.plan.subject,
                    attributes=self.plan.attributes(),
                    protocol_text=self.plan.protocol.source_text,
                    design_json=self.plan.design.to_json(),
                    n_trials=len(self.plan.trials),
                )
            )
            while True:
                todo = self.pending()
                if not todo:
                    self._transition(State.DONE)
                    break
                if self._stop_req is not None:
                    self._transition(State.IDLE, self._stop_req)
                    break
                if previous is not None:
                    self._between_trials(previous, todo[0])
                    previous = None
                    continue  # a redo during the break changes what comes next
                spec = todo[0]
                status = self._run_trial(spec)
                previous = spec
                if status == STATUS_ABORTED:
                    self._transition(State.IDLE, "trial aborted")
                    break
        except BaseException as e:  # the state must say the engine is not usable
            self.last_error = e
            if self._state is not State.BROKEN:
                with self._lock:
                    self._state = State.BROKEN
                self._emit(ev.StateChanged("running", State.BROKEN.value, repr(e)))
            raise
        finally:
            remaining = len(self.pending())
            self._emit(
                ev.SessionEnded(
                    self.plan.subject,
                    self._state.value,
                    len(self.plan.trials) - remaining,
                    remaining,
                )
            )
        return self._state

    def _between_trials(self, previous: TrialSpec, nxt: TrialSpec) -> None:
        t = self.plan.protocol.trial
        if self.pause_between_trials:
            with self._lock:
                self._pause_req = True
        if self._pause_req:
            self._wait_while_paused()
        elif self.pace_breaks:
            pause = (
                t.break_between_conditions_s if nxt.first_of_condition else t.break_between_trials_s
            )
            end = self.clock() + pause
            with self._lock:
                while self._stop_req is None and self.clock() < end:
                    self._wake.wait(timeout=min(0.1, max(0.0, end - self.clock())))

    def _wait_while_paused(self, key: str | None = None, sample: int = 0) -> None:
        self._transition(State.PAUSED)
        if key:
            self._emit(ev.TrialMark(key, sample, "pause"))
        with self._lock:
            while self._pause_req and self._stop_req is None:
                self._wake.wait(timeout=0.1)
        if self._stop_req is None:
            self._transition(State.RUNNING)
            if key:
                self._emit(ev.TrialMark(key, sample, "resume"))

    def _run_trial(self, spec: TrialSpec) -> str:
        att = self._attempts.setdefault(spec.trial_index, [])
        attempt = max((a for a, _ in att), default=0) + 1
        setup = self.plan.setup(spec, attempt)
        control = LoopControl()
        with self._lock:
            self._control = control
            self.current = setup
        key = setup.key
        self._emit(
            ev.TrialStarted(
                key=key,
                trial_index=spec.trial_index,
                attempt=attempt,
                condition=spec.condition,
                attributes=self._trial_attributes(setup),
                n_planned=setup.n_samples,
            )
        )
        status, reason, n = STATUS_COMPLETE, None, 0
        gen = self.loop.run_trial(setup, control)
        try:
            stop_seen: float | None = None
            for block in gen:
                m = len(next(iter(block.values())))
                n += m  # acquired, whatever a subscriber makes of it (a failing writer keeps it)
                self._emit(ev.SamplesAcquired(key, n - m, block))
                if self._stop_req is not None:
                    # The loop has been told (control.abort_reason) and ends by itself; blocks
                    # it recorded meanwhile are still written. Only a loop that ignores the
                    # request is cut off.
                    stop_seen = stop_seen or self.clock()
                    if self.clock() - stop_seen > STOP_GRACE_S:
                        break
                    continue
                if self._pause_req:
                    self._wait_while_paused(key, n)
            if self._stop_req is not None:
                status, reason = STATUS_ABORTED, self._stop_req
                self._transition(State.ABORTING, reason)
            elif n < setup.n_samples:
                status, reason = (
                    STATUS_ABORTED,
                    f"loop ended after {n} of {setup.n_samples} samples",
                )
                self._transition(State.ABORTING, reason)
        except TrialFault as f:
            # A fault the experimenter's stop caused carries the stop's reason.
            status, reason = STATUS_ABORTED, self._stop_req or str(f)
            self._transition(State.ABORTING, reason)
        except Exception as e:
            status, reason = STATUS_ABORTED, f"internal error: {e!r}"
            self.last_error = e
            self._transition(State.ABORTING, reason)
        finally:
            if isinstance(gen, Generator):  # as every loop's run_trial is
                gen.close()  # runs the loop's finalizer: zero torque
            # Blocks a loop recorded after the engine let go of it (a loop in another process
            # stops at its next cycle): recorded samples, so they are handed on too.
            for block in getattr(self.loop, "take_unhanded", lambda: [])():
                m = len(next(iter(block.values())))
                n += m
                try:
                    self._emit(ev.SamplesAcquired(key, n - m, block))
                except TrialFault as f:
                    if status != STATUS_ABORTED:
                        status, reason = STATUS_ABORTED, str(f)
                    self._aborting(reason or str(f))
            stats = {}
            try:
                stats = dict(self.loop.trial_stats())
            except Exception as e:  # stats must never hide the trial's end
                stats = {"stats_error": repr(e)}
            att.append((attempt, status))
            with self._lock:
                self._control = None
                self.current = None
            end = ev.TrialEnded(key, spec.trial_index, status, reason, n, stats)
            try:
                self._emit(end)
            except TrialFault as f:
                # Recording the trial's end failed (the writer failed at the very end): the
                # trial is aborted with that reason, not the engine broken. Subscribers see
                # the trial's end again, with its real status (a failed writer ignores it).
                status, reason = STATUS_ABORTED, str(f)
                att[-1] = (attempt, status)
                self._aborting(reason)
                self._emit(replace(end, status=status, reason=reason))
        return status

    def _aborting(self, reason: str) -> None:
        if self._state is not State.ABORTING:
            self._transition(State.ABORTING, reason)

    def _trial_attributes(self, setup: TrialSetup) -> dict:
        s, p = setup.spec, self.plan.protocol
        attrs = {
            "subject": self.plan.subject,
            "condition": s.condition,
            "repetition": s.repetition,
            "familiarization": s.familiarization,
            "trial_index": s.trial_index,
            "attempt": setup.attempt,
            "latin_square_row": self.plan.latin_square_row,
            "boundary_deg": s.boundary_deg,
            "fs_hz": setup.fs_hz,
            "measured_start": setup.measured_start,
            "measured_stop": setup.measured_stop,
            "run_in_s": p.trial.run_in_s,
            "periods": p.trial.periods,
            "instructions": s.instructions,
        }
        if setup.schedule is not None:
            # A time-varying trial: when the task changed (docs/data-format.md).
            attrs["schedule"] = setup.schedule.to_dict()
        if setup.driving is not None:
            # A driving trial: speed, friction, perturbation level, road (docs/data-format.md).
            attrs["driving"] = setup.driving.to_dict()
        return attrs
