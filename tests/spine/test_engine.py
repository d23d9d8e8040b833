"""The session engine: states, pause/resume/abort/redo, faults, and the file it leaves."""

from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np
import pytest

from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.rig import simulated_rig
from steerlab.protocols import events as ev
from steerlab.protocols.datafile import SessionFile, SessionWriter
from steerlab.protocols.engine import (
    TRANSITIONS,
    IllegalTransition,
    SessionEngine,
    State,
    TrialFault,
)
from steerlab.protocols.session import build_plan


def _rig(fs=200.0):
    from steerlab.hardware.sim.world import WorldConfig

    return simulated_rig(make_population(1, seed=3)[0], WorldConfig(fs_hz=fs))


class FaultAfter:
    """Wraps a real loop and injects a fault after some blocks (as a lost heartbeat would)."""

    def __init__(self, loop, blocks: int, exc: Exception) -> None:
        self.loop, self.blocks, self.exc = loop, blocks, exc

    def run_trial(self, setup, control):
        for i, b in enumerate(self.loop.run_trial(setup, control)):
            if i == self.blocks:
                raise self.exc
            yield b

    def emergency_stop(self):
        self.loop.emergency_stop()

    def trial_stats(self):
        return {}


def _events(engine):
    seen = []
    engine.subscribe(seen.append)
    return seen


def test_state_table_forbids_illegal_transitions(fast_protocol):
    eng = SessionEngine(build_plan(fast_protocol, 1), _rig().batch_loop())
    assert State.DONE in TRANSITIONS[State.RUNNING]
    with pytest.raises(IllegalTransition):
        eng._transition(State.PAUSED)  # idle → paused is not a transition
    with pytest.raises(IllegalTransition, match="cannot pause while idle"):
        eng.pause()


def test_full_session_events_and_done(fast_protocol, tmp_path):
    plan = build_plan(fast_protocol, 2)
    eng = SessionEngine(plan, _rig().batch_loop())
    seen = _events(eng)
    eng.subscribe(SessionWriter(tmp_path / "S02.h5"))
    assert eng.run() is State.DONE
    kinds = [type(e).__name__ for e in seen]
    assert kinds[1] == "SessionStarted" and kinds[-1] == "SessionEnded"
    assert kinds.count("TrialStarted") == kinds.count("TrialEnded") == 18
    states = [(e.old, e.new) for e in seen if isinstance(e, ev.StateChanged)]
    assert states == [("idle", "running"), ("running", "done")]
    sf = SessionFile(tmp_path / "S02.h5")
    assert all(s == "complete" for v in sf.attempts().values() for _, s in v)
    order = [r.condition for r in sf.records()][::3]
    assert order == list(plan.condition_order)


def test_fault_aborts_trial_keeps_samples_and_zeroes_motor(fast_protocol, tmp_path):
    plan = build_plan(fast_protocol, 1)
    rig = _rig()
    loop = FaultAfter(
        rig.device_loop(block_s=0.5), blocks=6, exc=TrialFault("drive heartbeat lost")
    )
    eng = SessionEngine(plan, loop)
    eng.subscribe(SessionWriter(tmp_path / "S01.h5"))
    assert eng.run() is State.IDLE
    assert not rig.drive.enabled and rig.drive.command == 0.0  # the finalizer ran
    recs = SessionFile(tmp_path / "S01.h5").records()
    assert len(recs) == 1
    r = recs[0]
    assert r.status == "aborted" and r.abort_reason == "drive heartbeat lost"
    assert r.n_samples == 6 * 100  # every block before the fault is in the file
    assert np.all(np.diff(r.time_s) > 0)
    assert r.attrs["marks"][-1]["kind"] == "abort"
    # Continue: the aborted trial is run again as attempt 2; attempt 1 stays as it was.
    eng.loop = rig.batch_loop()
    assert eng.run() is State.DONE  # the same writer reopens the file
    sf = SessionFile(tmp_path / "S01.h5")
    assert sorted(sf.attempts()[1]) == [(1, "aborted"), (2, "complete")]
    first = [x for x in sf.records() if x.trial_index == 1 and x.attrs["attempt"] == 1][0]
    np.testing.assert_array_equal(first.wheel_angle_rad, r.wheel_angle_rad)


def test_internal_error_aborts_with_reason(fast_protocol):
    plan = build_plan(fast_protocol, 1)
    eng = SessionEngine(plan, FaultAfter(_rig().batch_loop(), 1, ZeroDivisionError("boom")))
    seen = _events(eng)
    eng.run()
    end = [e for e in seen if isinstance(e, ev.TrialEnded)][0]
    assert end.status == "aborted" and "ZeroDivisionError" in end.reason


def test_pause_resume_mid_trial_and_abort_from_another_thread(fast_protocol):
    plan = build_plan(fast_protocol, 1)
    plan = replace(plan, trials=plan.trials[:2])
    eng = SessionEngine(plan, _rig().device_loop(block_s=0.05))
    seen = _events(eng)
    paused = threading.Event()

    def on(e):
        if isinstance(e, ev.SamplesAcquired) and e.start == 200 and not paused.is_set():
            eng.pause()
        if isinstance(e, ev.StateChanged) and e.new == "paused":
            paused.set()

    eng.subscribe(on)
    t = threading.Thread(target=eng.run)
    t.start()
    assert paused.wait(10)
    n_at_pause = sum(e.n for e in seen if isinstance(e, ev.SamplesAcquired))
    assert eng.state is State.PAUSED
    threading.Event().wait(0.2)
    # Nothing advances while paused (the simulated world holds).
    assert sum(e.n for e in seen if isinstance(e, ev.SamplesAcquired)) == n_at_pause
    eng.resume()
    t.join(30)
    assert eng.state is State.DONE
    marks = [e.kind for e in seen if isinstance(e, ev.TrialMark)]
    assert marks == ["pause", "resume"]
    ends = [e for e in seen if isinstance(e, ev.TrialEnded)]
    assert [e.status for e in ends] == ["complete", "complete"]
    assert ends[0].n_samples == plan.setup(plan.trials[0]).n_samples


def test_abort_and_emergency_stop(fast_protocol):
    plan = build_plan(fast_protocol, 1)
    rig = _rig()
    eng = SessionEngine(plan, rig.device_loop(block_s=0.05))
    seen = _events(eng)

    def on(e):
        if isinstance(e, ev.SamplesAcquired) and e.start == 100:
            threading.Thread(target=eng.emergency_stop).start()

    eng.subscribe(on)
    eng.run()
    end = [e for e in seen if isinstance(e, ev.TrialEnded)][0]
    assert end.status == "aborted" and end.reason == "emergency stop"
    assert not rig.drive.enabled
    assert eng.state is State.IDLE
    assert eng.status_of(1) == "aborted"


def test_redo_supersedes_and_keeps_the_old_attempt(fast_protocol, tmp_path):
    plan = build_plan(fast_protocol, 1)
    plan = replace(plan, trials=plan.trials[:2])
    eng = SessionEngine(plan, _rig().batch_loop())
    eng.subscribe(SessionWriter(tmp_path / "S01.h5"))
    assert eng.run() is State.DONE
    with pytest.raises(KeyError):
        eng.redo(7)
    eng.redo(2)
    assert eng.state is State.IDLE and eng.status_of(2) == "pending"
    assert eng.run() is State.DONE
    sf = SessionFile(tmp_path / "S01.h5")
    assert sorted(sf.attempts()[2]) == [(1, "superseded"), (2, "complete")]


def test_resume_runs_only_missing_trials(fast_protocol, tmp_path):
    plan = build_plan(fast_protocol, 1)
    part = replace(plan, trials=plan.trials[:4])
    e1 = SessionEngine(part, _rig().batch_loop())
    e1.subscribe(SessionWriter(tmp_path / "S01.h5"))
    e1.run()
    before = {
        r.trial_index: r.wheel_angle_rad.copy() for r in SessionFile(tmp_path / "S01.h5").records()
    }
    attempts = SessionFile(tmp_path / "S01.h5").attempts()
    e2 = SessionEngine(plan, _rig().batch_loop(), attempts=attempts)
    seen = _events(e2)
    e2.subscribe(SessionWriter(tmp_path / "S01.h5"))
    assert e2.run() is State.DONE
    started = [e.trial_index for e in seen if isinstance(e, ev.TrialStarted)]
    assert started == list(range(5, 19))
    after = {r.trial_index: r for r in SessionFile(tmp_path / "S01.h5").records()}
    assert len(after) == 18
    for i, a in before.items():
        np.testing.assert_array_equal(after[i].wheel_angle_rad, a)


def test_resume_refuses_a_different_protocol(fast_protocol, default_protocol, tmp_path):
    from steerlab.protocols.datafile import DataFileError

    plan = build_plan(fast_protocol, 1)
    e1 = SessionEngine(replace(plan, trials=plan.trials[:1]), _rig().batch_loop())
    e1.subscribe(SessionWriter(tmp_path / "S01.h5"))
    e1.run()
    e2 = SessionEngine(build_plan(default_protocol, 1), _rig(1000.0).batch_loop())
    e2.subscribe(SessionWriter(tmp_path / "S01.h5"))
    with pytest.raises(DataFileError, match="different protocol"):
        e2.run()
    assert e2.state is State.BROKEN
