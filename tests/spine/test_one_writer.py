"""One writer per session file (issue 15, item 2), with a real second process.

A session (``steerlab run``) runs in another process; every other writer (``simulate --resume``,
``simulate --overwrite``, ``run --resume``, the GUI's session start) is refused with a message
naming it (pid, command, since when) and leaves the live file alone, while readers (``export``)
keep working. ``--overwrite`` removes session files of an earlier, bigger study, and refuses
to remove anything that is not a Steerlab session file.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time

import h5py
import pytest

from steerlab.app.gui.controller import ControlError, SessionController
from steerlab.protocols.datafile import DataFileError, SessionFile, SessionWriter
from steerlab.protocols.protocol import load_protocol
from steerlab.protocols.writelock import WriterLock, live_writer
from tests.helpers import ROOT, cli
from tests.spine.test_crash_recovery import _protocol, steerlab


def _first_trial_done(path) -> bool:
    with h5py.File(path, "r", libver="latest", swmr=True, locking=False) as f:
        return "complete" in [g.attrs["status"] for g in f["trials"].values()]


def test_a_second_writer_is_refused_naming_the_first(tmp_path, lenient_rig):
    # Refused in the break, when the file is closed and only the lock says it is in use.
    proto = _protocol(tmp_path, fam=1, brk=120.0)
    out = tmp_path / "sessions"
    path = out / "S01.h5"
    sim = ("simulate", "--subjects", 1, "--protocol", proto, "--out", out)
    run = ("run", "--subject", 1, "--protocol", proto, "--out", out, "--rig", lenient_rig)
    log = open(tmp_path / "first.log", "w")  # noqa: SIM115
    for _try in range(3):  # a loaded machine can stall the real-time loop, which aborts
        first = subprocess.Popen(
            [sys.executable, "-m", "steerlab", *map(str, run), *(("--resume",) if _try else ())],
            cwd=ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and first.poll() is None:
            try:
                if path.exists() and _first_trial_done(path):
                    break
            except (OSError, KeyError):
                pass
            time.sleep(0.25)
        if first.poll() is None:
            break
    try:
        before = path.read_bytes()
        holder = live_writer(path)
        assert holder["pid"] == first.pid and holder["command"].startswith("steerlab run")
        for args in (
            (*sim, "--resume"),
            (*sim, "--overwrite"),
            (*run, "--resume"),
        ):
            assert first.poll() is None, (tmp_path / "first.log").read_text()
            code, msg = cli(*args)  # this test's process: another one than the first's
            assert code == 2, (args, msg, (tmp_path / "first.log").read_text())
            assert str(path) in msg and f"process {first.pid}" in msg, msg
            assert "steerlab run" in msg and re.search(r"since \d{4}-\d\d-\d\dT", msg), msg
        # The GUI's session start says the same.
        ctl = SessionController(load_protocol(proto), out)
        with pytest.raises(ControlError, match=f"process {first.pid}"):
            ctl.open_resume(path)
        with pytest.raises(DataFileError, match=f"process {first.pid}"):
            SessionWriter(path)
        # Readers stay allowed, during the session.
        code, err = cli("export", out, "--out", tmp_path / "csv")
        assert code == 0, err
        assert len(list((tmp_path / "csv").glob("*.csv"))) == 1
        # The live file was not touched: the same bytes, no copies beside it.
        assert path.read_bytes() == before
        assert sorted(p.name for p in out.iterdir()) == [
            "S01.h5",
            "S01.h5.lock",
            "steerlab-run-S01.pid",
        ]
        assert first.poll() is None
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait(10)
        log.close()
    # The kernel drops the lock with the process: no stale lock after a kill.
    assert live_writer(path) is None
    with WriterLock(path) as lock:
        assert lock.held
    assert not (out / "S01.h5.lock").exists()


def test_overwrite_removes_the_earlier_study_and_only_that(tmp_path, fast_protocol_file):
    out = tmp_path / "s"
    sim = ("simulate", "--protocol", fast_protocol_file, "--out", out)
    r = steerlab(*sim, "--subjects", 3)
    assert r.returncode == 0, r.stderr
    old = SessionFile(out / "S01.h5").attrs["created_utc"]
    # A foreign .h5 in the folder: --overwrite does not know what it is and refuses, touching
    # nothing.
    with h5py.File(out / "notes.h5", "w") as f:
        f["x"] = [1]
    code, err = cli(*sim, "--subjects", 2, "--overwrite")
    assert code == 2 and "notes.h5" in err, err
    assert sorted(p.name for p in out.glob("*.h5")) == ["S01.h5", "S02.h5", "S03.h5", "notes.h5"]
    (out / "notes.h5").unlink()
    # A smaller study replacing a bigger one: S03 of the earlier study is removed, so a report
    # of the folder never mixes the two.
    time.sleep(1.1)
    code, err = cli(*sim, "--subjects", 2, "--overwrite")
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["S01.h5", "S02.h5"]
    assert SessionFile(out / "S01.h5").attrs["created_utc"] != old
