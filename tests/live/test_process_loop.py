"""The engine's real-time loop in its own process, and the ``steerlab run``/``stop`` commands."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace

import h5py
import numpy as np
import pytest

from steerlab.hardware.live import ProcessLoop, RigError
from steerlab.protocols import events as ev
from steerlab.protocols.datafile import SessionFile, SessionWriter
from steerlab.protocols.engine import SessionEngine, State
from steerlab.protocols.session import build_plan
from tests.helpers import ROOT
from tests.live.conftest import SHORT_TRIAL_SAMPLES


@pytest.fixture
def process_loop(lenient_rig):
    loop = ProcessLoop(str(lenient_rig), 2)
    yield loop
    loop.close()


def _engine(loop, protocol, path):
    eng = SessionEngine(build_plan(protocol, 2), loop)
    eng.subscribe(SessionWriter(path))
    return eng


def _when(eng, start_samples, action):
    fired = threading.Event()

    def on(e):
        if isinstance(e, ev.SamplesAcquired) and e.start >= start_samples and not fired.is_set():
            fired.set()
            action()

    eng.subscribe(on)
    return fired


@pytest.mark.realtime
def test_session_in_the_loop_process_is_real_time(process_loop, short_protocol, tmp_path):
    # Behaviour, not timing (timing: benchmarks/live_loop.py): the loop process has the
    # real-time measures its tuning reports, and runs a whole session cycle by cycle.
    rt = process_loop.realtime
    assert rt["switch_interval_s"] == 2e-4
    pid = process_loop._proc.pid
    fifo = rt["sched_fifo_priority"]
    if isinstance(fifo, int):  # granted (root or CAP_SYS_NICE): the process really is FIFO
        assert os.sched_getscheduler(pid) == os.SCHED_FIFO
        assert os.sched_getparam(pid).sched_priority == fifo
    else:
        assert fifo.startswith("not permitted")
    if rt["mlockall"] is True:  # its memory is locked
        status = open(f"/proc/{pid}/status").read()
        locked_kb = int(status.split("VmLck:")[1].split()[0])
        assert locked_kb > 0
    assert rt["cpus"] == sorted(os.sched_getaffinity(pid))
    eng = _engine(process_loop, short_protocol, tmp_path / "S02.h5")
    assert eng.run() is State.DONE
    recs = SessionFile(tmp_path / "S02.h5").records()
    assert [r.status for r in recs] == ["complete", "complete"]
    stats = json.loads(recs[0].attrs["loop_stats"])
    assert stats["cycles"] == stats["samples"] == SHORT_TRIAL_SAMPLES
    # The samples are the cycles, one per period, in order.
    np.testing.assert_array_equal(recs[0].time_s, np.arange(SHORT_TRIAL_SAMPLES) / 1000.0)


def test_block_size_reaches_the_loop_process(lenient_rig, short_protocol, tmp_path):
    # The GUI asks for 20-ms blocks: its plots redraw only on new data, so 50-ms blocks (the
    # headless default) capped them at 20 frames/s (benchmarks/gui_live.py).
    loop = ProcessLoop(str(lenient_rig), 2, block_s=0.02)
    try:
        plan = build_plan(short_protocol, 2)
        eng = SessionEngine(replace(plan, trials=plan.trials[:1]), loop)
        sizes = []
        eng.subscribe(lambda e: sizes.append(e.n) if isinstance(e, ev.SamplesAcquired) else None)
        assert eng.run() is State.DONE
    finally:
        loop.close()
    assert sum(sizes) == SHORT_TRIAL_SAMPLES
    assert set(sizes[:-1]) == {20}


def test_pause_fades_out_and_ends_the_trial_without_losing_samples(
    process_loop, short_protocol, tmp_path
):
    eng = _engine(process_loop, short_protocol, tmp_path / "S02.h5")
    seen = []
    eng.subscribe(seen.append)
    _when(eng, 2000, eng.pause)
    t = threading.Thread(target=eng.run)
    t.start()
    deadline = time.monotonic() + 20
    while eng.state is not State.PAUSED and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(1.0)  # the loop keeps cycling in its process while the engine waits
    eng.resume()
    t.join(30)
    (r,) = SessionFile(tmp_path / "S02.h5").records()
    assert r.status == "aborted" and "paused mid-trial" in r.abort_reason
    assert r.n_samples == sum(e.n for e in seen if isinstance(e, ev.SamplesAcquired))
    tp = r.perturbation_torque_Nm
    # Faded to zero; no step larger than the perturbation's own largest step (no torque jump).
    own = np.max(np.abs(np.diff(r.perturbation_torque_Nm[:1500])))
    assert tp[-1] == 0.0 and np.max(np.abs(np.diff(tp[-600:]))) <= own + 1e-6


def test_emergency_stop_reaches_the_loop_process(process_loop, short_protocol, tmp_path):
    eng = _engine(process_loop, short_protocol, tmp_path / "S02.h5")
    _when(eng, 1500, lambda: threading.Thread(target=eng.emergency_stop).start())
    assert eng.run() is State.IDLE
    (r,) = SessionFile(tmp_path / "S02.h5").records()
    assert r.status == "aborted" and r.abort_reason == "emergency stop"
    assert process_loop.status["drive_enabled"] is False


def test_loop_process_dies_mid_trial(process_loop, short_protocol, tmp_path):
    eng = _engine(process_loop, short_protocol, tmp_path / "S02.h5")
    _when(eng, 1500, lambda: os.kill(process_loop._proc.pid, signal.SIGKILL))
    assert eng.run() is State.IDLE
    (r,) = SessionFile(tmp_path / "S02.h5").records()
    assert r.status == "aborted" and "live loop process died" in r.abort_reason
    assert r.n_samples >= 1500


def test_bad_rig_file_fails_to_come_up_with_its_reason(tmp_path):
    bad = tmp_path / "rig.toml"
    bad.write_text(
        (ROOT / "hardware" / "rigs" / "simulated.toml")
        .read_text()
        .replace("node_id = 1 ", "node_id = 300 ")
    )
    with pytest.raises(RigError, match=r"node_id"):
        ProcessLoop(str(bad), 1)


def wait_for_samples(path, n: int, deadline: float) -> bool:
    """Wait until a running session (another process) has flushed n samples of a trial."""
    while time.monotonic() < deadline:
        time.sleep(0.1)
        try:  # SWMR: read while the other process writes
            with h5py.File(path, "r", libver="latest", swmr=True) as f:
                for g in f["trials"].values():
                    if "time_s" in g:
                        g["time_s"].refresh()
                        if g["time_s"].shape[0] >= n:
                            return True
        except (OSError, KeyError):
            continue
    return False


def _steerlab(*args, **kw):
    return subprocess.Popen(
        [sys.executable, "-m", "steerlab", *map(str, args)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def test_steerlab_run_and_stop(tmp_path, short_protocol_file, lenient_rig):
    out = tmp_path / "sessions"
    p = _steerlab(
        "run", "--subject", 1, "--out", out, "--protocol", short_protocol_file, "--rig", lenient_rig
    )
    pidfile = out / "steerlab-run-S01.pid"
    deadline = time.monotonic() + 60
    # Stop it from "another terminal" once the first trial is under way.
    assert wait_for_samples(out / "S01.h5", 500, deadline) and pidfile.exists()
    s = _steerlab("stop", "--out", out)
    assert s.wait(30) == 0, s.stderr.read()
    _, err = p.communicate(timeout=60)
    assert p.returncode == 3
    # The trial under way (the first, or the second where the stop command was slow to start
    # on a loaded machine) was aborted. Where the stop landed between the second trial's
    # creation and its first sample, that trial holds none, and the first must be whole.
    recs = SessionFile(out / "S01.h5").records()
    r = recs[-1]
    assert r.status == "aborted" and "SIGUSR1" in r.abort_reason
    assert r.n_samples > 0 or (len(recs) == 2 and recs[0].status == "complete"), [
        (x.source, x.status, x.n_samples) for x in recs
    ]
    stopped = r.trial_index
    assert not pidfile.exists()
    # Resume finishes the session: the aborted trial again, then the rest.
    p = _steerlab(
        "run",
        "--subject",
        1,
        "--out",
        out,
        "--protocol",
        short_protocol_file,
        "--resume",
        "--rig",
        lenient_rig,
    )
    stdout, err = p.communicate(timeout=120)
    assert p.returncode == 0, err + stdout
    att = SessionFile(out / "S01.h5").attempts()
    assert sorted(att[stopped]) == [(1, "aborted"), (2, "complete")]
    assert all(a == [(1, "complete")] for k, a in att.items() if k != stopped) and len(att) == 2
    # Without --resume an existing session is refused.
    p = _steerlab(
        "run", "--subject", 1, "--out", out, "--protocol", short_protocol_file, "--rig", lenient_rig
    )
    _, err = p.communicate(timeout=60)
    assert p.returncode == 2 and "--resume" in err


@pytest.mark.parametrize("how", ["enter", "ctrl-c"])
def test_emergency_stop_from_the_keyboard(tmp_path, short_protocol_file, lenient_rig, how):
    """In the terminal running the session: Enter or Ctrl-C stops the motor and the trial."""
    import pty

    out = tmp_path / "s"
    master, slave = pty.openpty()
    p = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "steerlab",
            "run",
            "--subject",
            "1",
            "--out",
            str(out),
            "--protocol",
            str(short_protocol_file),
            "--rig",
            str(lenient_rig),
        ],
        cwd=ROOT,
        stdin=slave,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    os.close(slave)
    try:
        assert wait_for_samples(out / "S01.h5", 500, time.monotonic() + 60)
        if how == "enter":
            os.write(master, b"\n")
        else:
            p.send_signal(signal.SIGINT)
        stdout, err = p.communicate(timeout=60)
    finally:
        os.close(master)
    assert p.returncode == 3, err
    (r,) = SessionFile(out / "S01.h5").records()
    expected = "keyboard" if how == "enter" else "SIGINT"
    assert r.status == "aborted" and expected in r.abort_reason


def test_steerlab_run_warns_when_the_loop_is_not_real_time(
    tmp_path, short_protocol_file, lenient_rig
):
    """Without real-time priority and locked memory (here refused on purpose, as for a user
    without the rights) ``steerlab run`` says so at start-up, and the session file records
    what the loop got."""
    out = tmp_path / "s"
    args = ["--out", out, "--protocol", short_protocol_file, "--rig", lenient_rig]
    p = _steerlab("run", "--subject", 1, *args, env={**os.environ, "STEERLAB_REALTIME": "off"})
    try:
        assert wait_for_samples(out / "S01.h5", 500, time.monotonic() + 60)
        p.send_signal(signal.SIGINT)
        stdout, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    lines = [ln for ln in (stdout + err).splitlines() if "warning:" in ln]
    assert any("without real-time priority" in ln and "STEERLAB_REALTIME=off" in ln for ln in lines)
    assert any("memory is not locked" in ln for ln in lines), stdout + err
    assert "control loop: no SCHED_FIFO (not requested" in stdout + err
    with h5py.File(out / "S01.h5", "r") as f:
        tuning = json.loads(f.attrs["realtime_tuning"])
    assert tuning["mlockall"] == "not requested (STEERLAB_REALTIME=off)"
