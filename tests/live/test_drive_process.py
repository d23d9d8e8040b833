"""The simulated drive in a process of its own (hardware.sim.lab, over the udp_loopback CAN bus):
a SIGKILL of the host process is a real host kill, and the drive must cut the torque by itself
(its consumer heartbeat of the host, 0x1016, and abort connection option 0x6007)."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from steerlab.hardware.live import ProcessLoop
from steerlab.hardware.sim.lab import LabProcess, host_rig_text
from steerlab.protocols import events as ev
from steerlab.protocols.datafile import SessionFile, SessionWriter
from steerlab.protocols.engine import SessionEngine, State
from steerlab.protocols.session import build_plan
from tests.helpers import ROOT, lenient_rig_text

MARGIN_S = 0.5  # a loaded test machine; the timing goal is in benchmarks/faults.py


@pytest.fixture
def lab():
    lab = LabProcess()
    yield lab
    lab.close()


@pytest.fixture
def host_rig(lab, tmp_path):
    text = lenient_rig_text(
        host_rig_text(lab, (ROOT / "hardware" / "rigs" / "simulated.toml").read_text())
    )
    p = tmp_path / "host.toml"
    p.write_text(text)
    return p


def test_the_host_rig_sees_a_lab(host_rig, lab):
    from steerlab.hardware.rig import load_rig

    rig = load_rig(host_rig)
    assert not rig.simulated and rig.drive.interface == "udp_loopback"
    assert rig.glove.port == lab.pty and rig.drive.channel == lab.channel


def test_sigkill_of_the_host_leaves_zero_torque_at_the_drive(
    lab, host_rig, short_protocol, tmp_path
):
    loop = ProcessLoop(str(host_rig), 2)
    path = tmp_path / "S02.h5"
    syncs_before = lab.status()["enabled_syncs"]
    try:
        eng = SessionEngine(build_plan(short_protocol, 2), loop)
        eng.subscribe(SessionWriter(path))
        seen = []
        eng.subscribe(seen.append)
        killed: dict = {}

        def kill():
            # torque on the wheel, then the host dies at once
            deadline = time.monotonic() + 5
            while (st := lab.status())["applied_torque_nm"] == 0.0:
                assert time.monotonic() < deadline, st
            killed["before"] = st
            killed["t"] = time.monotonic()
            os.kill(loop._proc.pid, signal.SIGKILL)

        fired = threading.Event()

        def on(e):
            if isinstance(e, ev.SamplesAcquired) and e.start >= 1500 and not fired.is_set():
                fired.set()
                kill()

        eng.subscribe(on)
        assert eng.run() is State.IDLE
    finally:
        loop.close()
    before = killed["before"]
    assert before["state"] == "OPERATION ENABLED" and before["watching_host"]
    st = lab.wait_zero_torque(timeout_s=5.0)
    assert st["applied_torque_nm"] == 0.0, st
    assert st["state"] == "SWITCH ON DISABLED" and st["host_heartbeats_lost"] == 1
    zero_ms = (st["zero_torque_since"] - killed["t"]) * 1e3
    assert 0 < zero_ms < 100 + MARGIN_S * 1e3, zero_ms  # 100 ms: host_heartbeat_timeout_ms
    # The samples recorded before the kill are in the file.
    (r,) = SessionFile(path).records()
    assert r.status == "aborted" and "live loop process died" in r.abort_reason
    assert r.n_samples == sum(e.n for e in seen if isinstance(e, ev.SamplesAcquired)) >= 1500
    # … all of them: those the killed process took but had not handed over come from the shared
    # ring. The drive counts the control cycles it met (300 zeroing cycles before the trial).
    cycles = st["enabled_syncs"] - syncs_before - 300
    assert cycles - 1 <= r.n_samples <= cycles, (cycles, r.n_samples)
    assert np.allclose(np.diff(r.time_s), 1e-3) and r.time_s[0] == 0.0


def test_a_full_collection_in_the_lab_is_short_with_a_subjects_world():
    """The drive node answers each SYNC within the host's 0.8 ms, and 20 unanswered SYNCs end a
    trial. A full garbage collection holds the GIL while it walks the process's objects: over a
    subject's whole world that was 50-80 ms (every trial of ``steerlab run`` aborted with "20
    SYNCs in a row without TPDO1+TPDO2"). The lab freezes what it built, so a collection walks
    only what came later."""
    with LabProcess(subject=1) as lab:
        times = [lab.ask("collect", timeout_s=30.0)["collect_ms"] for _ in range(3)]
    assert min(times) < 5.0, times


@pytest.mark.parametrize("ending", ["closed", "killed"])
def test_a_lab_leaves_no_control_folder_behind(ending):
    lab = LabProcess(subject=1)
    folder = os.path.dirname(lab.control_address)
    assert os.path.isdir(folder)
    if ending == "killed":
        lab.proc.kill()
        lab.proc.wait(10)
    lab.close()
    assert not os.path.exists(folder)
    if ending == "closed":  # by itself, cleanly (its own removal of the folder once raised)
        assert lab.proc.returncode == 0


def test_the_fault_benchmark_measures_at_the_drive(tmp_path):
    """One row of ``python -m benchmarks faults`` (EMCY: the drive faults, torque off at once)."""
    from steerlab.benchmarks.faults import FAULTS, run_fault

    (fault,) = [f for f in FAULTS if f[0] == "EMCY"]
    row = run_fault(*fault, tmp_path, stall_s=0.5)
    assert row["status"] == "aborted" and "0x2310" in row["reason"]
    assert row["torque_before_nm"] != 0.0 and row["drive_state_after"] == "FAULT"
    assert 0 <= row["zero_torque_ms"] < 100 and row["lost_samples"] == 0
    assert row["timeout_ms"] is None and row["goal_met"]


def test_realtime_warnings_say_what_the_loop_did_not_get():
    from steerlab.hardware.realtime import realtime_warnings

    good = {"sched_fifo_priority": 20, "mlockall": True, "cpus": [0, 1]}
    assert realtime_warnings(good) == []
    bad = {"sched_fifo_priority": "not permitted (Operation not permitted)", "mlockall": "x",
           "cpus": [1]}  # fmt: skip
    w = realtime_warnings(bad)
    assert len(w) == 3 and "real-time priority" in w[0] and "not locked" in w[1]
    assert "CPU [1]" in w[2]


def test_realtime_summary_says_what_the_loop_got():
    from steerlab.hardware.realtime import realtime_summary

    good = {"sched_fifo_priority": 20, "mlockall": True, "cpus": [0, 1]}
    assert realtime_summary(good) == "control loop: SCHED_FIFO 20, memory locked, CPUs [0, 1]"
    bad = {"sched_fifo_priority": "not permitted (EPERM)", "mlockall": "not permitted (ENOMEM)"}
    s = realtime_summary(bad)
    assert "no SCHED_FIFO (not permitted (EPERM))" in s and "memory not locked" in s
