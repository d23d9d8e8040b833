"""``steerlab stop`` stops the right session: by subject (and rig), after checking in /proc that
the pid is still that session; stale pid files are removed with a message; two sessions in one
data folder are told apart. Real processes throughout."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from steerlab.app.run import RunError, SessionProcess, pidfile_path, running_sessions, stop_running
from steerlab.protocols.datafile import SessionFile
from tests.helpers import ROOT
from tests.live.test_process_loop import wait_for_samples

CHILD = """
import signal, sys, time
def on(signum, frame):
    open(sys.argv[1], "a").write("SIGUSR1\\n")
    sys.exit(0)
signal.signal(signal.SIGUSR1, on)
print("ready", flush=True)
time.sleep(60)
"""


@pytest.fixture
def children(tmp_path):
    """Start processes that note a SIGUSR1 in their own file, and stop them afterwards."""
    procs = []

    def start(name: str) -> tuple[subprocess.Popen, Path]:
        mark = tmp_path / f"{name}.signals"
        p = subprocess.Popen([sys.executable, "-c", CHILD, str(mark)], stdout=subprocess.PIPE)
        assert p.stdout.readline().strip() == b"ready"
        procs.append(p)
        return p, mark

    yield start
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.wait(5)


def _pidfile_for(proc: subprocess.Popen, out: Path, subject: str, rig: str = "/r/sim.toml"):
    from steerlab.app.run import _proc_cmdline, _proc_start_ticks

    sp = SessionProcess(
        proc.pid,
        _proc_start_ticks(proc.pid),
        _proc_cmdline(proc.pid),
        subject,
        rig,
        str(out),
        pidfile_path(out, subject),
    )
    sp.write_exclusive()
    return sp


def test_two_sessions_in_one_folder_are_told_apart(tmp_path, children):
    (a, a_mark), (b, b_mark) = children("a"), children("b")
    _pidfile_for(a, tmp_path, "S01")
    _pidfile_for(b, tmp_path, "S02", rig="/r/lab2.toml")
    with pytest.raises(RunError, match=r"2 sessions are running.*S01.*S02.*--subject"):
        stop_running(tmp_path)
    assert a.poll() is None and b.poll() is None  # nobody signalled
    target = stop_running(tmp_path, subject=2)
    assert target.pid == b.pid and b.wait(10) == 0 and b_mark.read_text() == "SIGUSR1\n"
    assert a.poll() is None and not a_mark.exists()  # the other session goes on
    # by rig as well; a rig that runs nothing here is refused
    with pytest.raises(RunError, match="no running session for subject S01 on rig /r/lab2"):
        stop_running(tmp_path, subject=1, rig="/r/lab2.toml")
    assert stop_running(tmp_path, rig="/r/sim.toml").pid == a.pid and a.wait(10) == 0


def test_a_stale_pid_file_is_removed_with_a_message(tmp_path, children):
    p, _ = children("gone")
    sp = _pidfile_for(p, tmp_path, "S01")
    p.kill()
    p.wait(5)
    said = []
    with pytest.raises(RunError, match="no running session"):
        stop_running(tmp_path, say=said.append)
    assert not sp.path.exists()
    assert said == [f"removed a stale pid file {sp.path}: process {p.pid} is not running"]


def test_a_reused_pid_is_not_signalled(tmp_path, children):
    """The pid file's process is gone and its pid now belongs to an unrelated program: the
    start time (and command line) tell, and that program is left alone."""
    other, mark = children("unrelated")
    sp = SessionProcess(
        other.pid, 12345, ["python", "-m", "steerlab", "run"], "S01", "/r", str(tmp_path),
        pidfile_path(tmp_path, "S01"),
    )  # fmt: skip
    sp.write_exclusive()
    said = []
    assert running_sessions(tmp_path, say=said.append) == []
    assert "is another process now" in said[0] and not sp.path.exists()
    time.sleep(0.2)
    assert other.poll() is None and not mark.exists()
    # the same start time but another command line: also not ours
    from steerlab.app.run import _proc_start_ticks

    sp2 = SessionProcess(
        other.pid, _proc_start_ticks(other.pid), ["steerlab", "run"], "S01", "/r",
        str(tmp_path), sp.path,
    )  # fmt: skip
    sp2.write_exclusive()
    with pytest.raises(RunError):
        stop_running(tmp_path, subject=1, say=said.append)
    assert "is another program now" in said[-1] and other.poll() is None


def test_garbage_pid_file_is_stale(tmp_path):
    p = pidfile_path(tmp_path, "S03")
    p.write_text("4242")  # the old format: a bare pid, which nothing can verify
    said = []
    assert running_sessions(tmp_path, say=said.append) == [] and not p.exists()
    assert "not a readable Steerlab pid file" in said[0]


def _steerlab(*args, urgent: bool = False):
    return subprocess.Popen(
        [sys.executable, "-m", "steerlab", *map(str, args)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_urgent if urgent else None,
    )


def _urgent() -> None:
    # A command typed next to two sessions (each a loop and a simulated lab process; at
    # SCHED_FIFO where permitted, when run outside the tests) on a loaded 2-core machine: what
    # CPU they leave goes mostly to it.
    try:
        os.nice(-10)
    except OSError:
        pass


def test_steerlab_stop_by_subject_with_two_real_sessions(
    tmp_path, short_protocol_file, lenient_rig
):
    # trials of 16.5 s for S02 (6 periods of 2.5 s); S01's of 101.5 s, so that S02 is still
    # running when the stop comes and S01 when S02 has been stopped, however slowly the
    # commands in between start on a loaded machine (the test ends both once it has seen that)
    long = tmp_path / "long.toml"
    long.write_text(short_protocol_file.read_text().replace("periods = 1", "periods = 6"))
    longer = tmp_path / "longer.toml"
    longer.write_text(short_protocol_file.read_text().replace("periods = 1", "periods = 40"))
    protocols = {1: longer, 2: long}
    short_protocol_file = long
    rig = lenient_rig
    out = tmp_path / "sessions"
    runs = {
        n: _steerlab(
            "run",
            "--subject",
            n,
            "--out",
            out,
            "--protocol",
            protocols[n],
            "--rig",
            rig,
            "--no-breaks",
        )  # fmt: skip
        for n in (1, 2)
    }
    try:
        deadline = time.monotonic() + 90
        assert wait_for_samples(out / "S02.h5", 1500, deadline)
        # the second session is already running: a third for S02 is refused
        third = _steerlab("run", "--subject", 2, "--out", out, "--protocol",
                          short_protocol_file, "--rig", rig, "--resume", urgent=True)  # fmt: skip
        # Generous: two sessions (loop and simulated lab processes; under SCHED_FIFO, they left
        # an ordinary process minutes to start Python in) on a 2-core machine.
        _, err = third.communicate(timeout=300)
        # Refused, naming the running session: by its writer lock (which names the process
        # and its command line) or, without one, by its pid file.
        assert third.returncode == 2, err
        assert "already running" in err or f"being written by process {runs[2].pid}" in err, err
        s = _steerlab("stop", "--out", out, "--subject", 2, urgent=True)
        stdout, err = s.communicate(timeout=300)
        assert s.returncode == 0, err
        assert f"S02 (process {runs[2].pid}" in stdout
        assert runs[2].wait(60) == 3
        assert runs[1].poll() is None, runs[1].communicate()  # S01 goes on
        r = SessionFile(out / "S02.h5").records()[-1]  # the trial under way
        assert r.status == "aborted" and "SIGUSR1" in r.abort_reason
        assert not pidfile_path(out, "S02").exists() and pidfile_path(out, "S01").exists()
    finally:
        for p in runs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in runs.values():
            p.communicate(timeout=60)
