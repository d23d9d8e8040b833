"""Shared fixtures. Qt runs offscreen in every test (no display on CI)."""

from __future__ import annotations

import fcntl
import gc
import os
import sys
import tempfile
from contextlib import ExitStack
from pathlib import Path

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# Before anything imports pylsl: every LSL packet of the tests (and of the processes they
# start, which inherit it) stays on this machine's loopback (docs/lsl.md;
# tests/lsl/test_lsl_loopback.py checks it is in force).
from steerlab.benchmarks._lsl_loopback import keep_lsl_on_loopback  # noqa: E402

keep_lsl_on_loopback()

from steerlab.hardware.realtime import REALTIME_ENV  # noqa: E402
from steerlab.protocols.protocol import load_protocol, parse_protocol  # noqa: E402
from tests.helpers import fast_protocol_text, lenient_rig_text  # noqa: E402

#: Shared by every pytest process of this user on the machine (both xdist workers, and a second
#: run beside them): a ``realtime`` test holds it exclusively, every other test shared.
_CPU_LOCK = Path(tempfile.gettempdir()) / f"steerlab-tests-cpu-{os.getuid()}.lock"
#: Taken exclusively for a moment before the main lock, so that a waiting ``realtime`` test is
#: not passed over by the other worker's next test, and the next, for as long as the run lasts.
_CPU_TURNSTILE = _CPU_LOCK.with_suffix(".turn")
# Set here rather than in a fixture: module- and session-scoped fixtures start sessions too.
# The mark tells the xdist workers (which inherit the environment) that the tests set it.
_DEFAULTED = "STEERLAB_TESTS_REALTIME_DEFAULTED"
if REALTIME_ENV not in os.environ:
    os.environ[REALTIME_ENV] = "off"
    os.environ[_DEFAULTED] = "1"
#: What the person running the tests asked for, if anything (``off`` keeps even the
#: ``realtime`` tests off real-time priority).
_ASKED_REALTIME = None if os.environ.get(_DEFAULTED) else os.environ[REALTIME_ENV]


def pytest_collection_finish(session):
    """Freeze what collection built (every test module, numpy, scipy, Qt, canopen's parsed EDS
    files...) so that the collector stops walking it.

    Many tests run a simulated drive node and its host in this one process, with heartbeat and
    SDO deadlines of 100-300 ms. A full collection of a test process walks some hundred
    thousand objects holding the GIL (80-117 ms measured), which in the lab would stall nobody:
    there the drive is its own device and the loop process pauses the collector during a trial
    (DeviceLoop.run_trial). Frozen, a collection walks only what the tests create later."""
    gc.collect()
    gc.freeze()


@pytest.fixture(autouse=True)
def _real_time_only_alone(request, monkeypatch):
    """Sessions started by a test run without real-time priority (``STEERLAB_REALTIME=off``,
    inherited by the loop and simulated lab processes), unless the test is marked
    ``realtime``; such a test then runs alone.

    Why: a session under SCHED_FIFO takes the CPU from every ordinary process (its loop and its
    simulated lab each at real-time priority: two such sessions left an ordinary command minutes
    to start on this 2-core machine). A test on the other xdist worker that runs a simulated drive
    node and its host in-process, with heartbeat and SDO deadlines of 100-300 ms, may then miss
    them. (A CI run failed so: "no heartbeat with NMT state OPERATIONAL within 150 ms after NMT
    start"; the cause measured there is the collector, below.)"""
    realtime = request.node.get_closest_marker("realtime") is not None
    if realtime and _ASKED_REALTIME == "off":
        pytest.skip(f"{REALTIME_ENV}=off asked: no real-time priority to check")
    if realtime and _ASKED_REALTIME is None:
        monkeypatch.delenv(REALTIME_ENV, raising=False)
    with ExitStack() as held:
        turnstile = held.enter_context(open(_CPU_TURNSTILE, "a"))
        lock = held.enter_context(open(_CPU_LOCK, "a"))
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        fcntl.flock(lock, fcntl.LOCK_EX if realtime else fcntl.LOCK_SH)
        fcntl.flock(turnstile, fcntl.LOCK_UN)
        try:
            yield
        finally:
            # Unlocked, not only closed: a child forked during the test shares the open file
            # and would otherwise hold the lock for as long as it lives.
            fcntl.flock(lock, fcntl.LOCK_UN)


#: Test folders whose tests run a simulated drive node and its host (or the live loop) in the
#: test process, with deadlines of 100-300 ms.
_DEADLINE_FOLDERS = ("canopen", "gui", "hardware", "live")


@pytest.fixture(autouse=True)
def _no_collection_during_deadlines(request):
    """In a test with in-process deadlines, the collector is paused (as the loop process pauses
    it during a trial), after a full collection of what earlier tests left.

    The freeze after collection (above) does not cover what a worker's earlier tests left: a
    late full collection in a worker was measured at 75-230 ms (a report's or a fuzz test's
    garbage), longer than the drive's heartbeat timeout, and it holds the GIL, stopping the
    simulated drive's and the host's heartbeat threads alike (as a CI run showed: both sides
    lost heartbeats for 0.21 s)."""
    if Path(request.node.path).relative_to(ROOT / "tests").parts[0] not in _DEADLINE_FOLDERS:
        yield
        return
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        gc.enable()


@pytest.fixture
def default_protocol():
    return load_protocol()


@pytest.fixture
def fast_protocol():
    return parse_protocol(fast_protocol_text(), "fast.toml")


@pytest.fixture
def fast_protocol_file(tmp_path):
    p = tmp_path / "fast.toml"
    p.write_text(fast_protocol_text())
    return p


@pytest.fixture
def lenient_rig(tmp_path):
    """The simulated rig with the limits a behaviour test relaxes (tests/helpers.py)."""
    p = tmp_path / "lenient-rig.toml"
    p.write_text(lenient_rig_text())
    return p
