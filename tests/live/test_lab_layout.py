"""The default simulated rig runs its simulated devices in a process of their own (issue 14, item
6): the loop's process holds only what it holds in the lab. And a trial that cannot keep time
(the machine does not give the loop its CPU) ends aborted *safely*: zero torque at the drive,
every sample kept. Behaviour, not timing: the loop is deprived of its CPU outright (SIGSTOP),
which a loaded machine does by degrees."""

from __future__ import annotations

import os
import re
import signal
import threading
import time

import numpy as np
import pytest

from steerlab.hardware.live import ProcessLoop
from steerlab.protocols import events as ev
from steerlab.protocols.datafile import SessionFile, SessionWriter
from steerlab.protocols.engine import SessionEngine, State
from steerlab.protocols.session import build_plan
from tests.live.conftest import SHORT_TRIAL_SAMPLES


def _engine(loop, protocol, path, trials=None):
    plan = build_plan(protocol, 2)
    if trials is not None:
        from dataclasses import replace

        plan = replace(plan, trials=plan.trials[:trials])
    eng = SessionEngine(plan, loop)
    eng.subscribe(SessionWriter(path))
    seen: list = []
    eng.subscribe(seen.append)
    return eng, seen


def _children_of(pid: int) -> set[int]:
    out = set()
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out |= {int(c) for c in f.read().split()}
        except OSError:
            pass
    return out


def test_default_simulated_rig_runs_its_devices_in_a_process_of_their_own(
    lenient_rig, short_protocol, tmp_path
):
    loop = ProcessLoop(str(lenient_rig), 2)
    try:
        lab = loop.lab
        assert lab is not None, "a simulated rig's devices belong in a lab process"
        loop_pid = loop._proc.pid
        assert lab.pid not in (os.getpid(), loop_pid)
        assert lab.pid not in _children_of(loop_pid)  # a killed loop does not take the drive
        # The subject is the rig population's subject 2, reported by the lab.
        assert loop.physiology is not None and loop.physiology["seed"] is not None
        before = lab.status()["enabled_syncs"]
        eng, seen = _engine(loop, short_protocol, tmp_path / "S02.h5", trials=1)
        assert eng.run() is State.DONE
        stats = loop.trial_stats()
        after = lab.status()
    finally:
        loop.close()
    (r,) = SessionFile(tmp_path / "S02.h5").records()
    assert r.status == "complete" and r.n_samples == SHORT_TRIAL_SAMPLES == stats["samples"]
    # Every control cycle reached the drive in the lab process: one SYNC per sample, plus the
    # 300 zeroing cycles, in OPERATION ENABLED.
    assert after["enabled_syncs"] - before >= SHORT_TRIAL_SAMPLES + 300
    assert after["applied_torque_nm"] == 0.0  # the trial's end left the motor at zero
    # The simulated subject holds the wheel there: the wheel moves under the perturbation and
    # the column torque is the subject's, its sensor offset (0.05 N·m) zeroed while the
    # subject had let go (the lab's "release" during the zeroing).
    assert 0.01 < np.std(r.wheel_angle_rad[1000:]) < 0.3
    assert np.std(r.driver_torque_Nm[1000:]) > 0.01
    assert abs(np.mean(r.driver_torque_Nm[:300])) < 0.04
    # The glove unit's frames came through the lab's pty (held values change at ~100 Hz).
    assert np.count_nonzero(np.diff(r.grip_force_N)) > 100


def test_in_loop_layout_stays_available(lenient_rig, short_protocol, tmp_path):
    loop = ProcessLoop(str(lenient_rig), 2, simulated_devices="in_loop")
    try:
        assert loop.lab is None
        eng, _ = _engine(loop, short_protocol, tmp_path / "S02.h5", trials=1)
        assert eng.run() is State.DONE
    finally:
        loop.close()
    with pytest.raises(ValueError, match="simulated_devices"):
        ProcessLoop(str(lenient_rig), 2, simulated_devices="elsewhere")


def test_a_loop_deprived_of_its_cpu_aborts_safely(lenient_rig, short_protocol, tmp_path):
    """The machine gives the loop no CPU for 1.5 s (longer than the stall limit, 0.5 s, and the
    drive's watch on the host, 100 ms): the drive cuts the torque by itself, the trial ends as
    aborted with the reason, and every sample the loop took is in the file."""
    loop = ProcessLoop(str(lenient_rig), 2)
    path = tmp_path / "S02.h5"
    try:
        lab = loop.lab
        eng, seen = _engine(loop, short_protocol, path, trials=1)
        fired = threading.Event()
        during: dict = {}

        def starve():
            pid = loop._proc.pid
            os.kill(pid, signal.SIGSTOP)
            try:
                time.sleep(1.5)
                during.update(lab.status())  # the drive on its own, the host frozen
            finally:
                os.kill(pid, signal.SIGCONT)

        def on(e):
            if isinstance(e, ev.SamplesAcquired) and e.start >= 2000 and not fired.is_set():
                fired.set()
                threading.Thread(target=starve, daemon=True).start()

        eng.subscribe(on)
        assert eng.run() is State.IDLE
        stats = loop.trial_stats()
        after = lab.wait_zero_torque(timeout_s=5.0)
    finally:
        loop.close()
    # While the host was frozen the drive had already cut the torque (its 0x1016 watch).
    assert during["applied_torque_nm"] == 0.0 and during["host_heartbeats_lost"] >= 1
    assert after["applied_torque_nm"] == 0.0
    (r,) = SessionFile(path).records()
    assert r.status == "aborted"
    assert re.search(r"control loop stalled|drive (fault|lost)", r.abort_reason), r.abort_reason
    emitted = sum(e.n for e in seen if isinstance(e, ev.SamplesAcquired))
    assert r.n_samples == emitted == stats["samples"] >= 2000
