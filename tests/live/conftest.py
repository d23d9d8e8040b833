"""Fixtures for the live path: the simulated rig over the virtual CAN bus and a pty glove."""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import replace

import pytest

from steerlab.hardware.live import RigDevices
from steerlab.hardware.rig import load_rig
from steerlab.protocols.protocol import parse_protocol
from tests.session_helpers import short_protocol

SHORT_PROTOCOL = short_protocol("short-test")
# Samples of one SHORT_PROTOCOL trial at 1 kHz: run-in 1 s + one 2.5 s period + fade-out 0.5 s.
SHORT_TRIAL_SAMPLES = 4000


@pytest.fixture
def short_protocol():
    return parse_protocol(SHORT_PROTOCOL, "short.toml")


@pytest.fixture
def short_protocol_file(tmp_path):
    p = tmp_path / "short.toml"
    p.write_text(SHORT_PROTOCOL)
    return p


HOST_TIMEOUT_MS = 100


@pytest.fixture
def rig_config():
    # The test process is not real-time tuned and shares the CPU with other tests: allow late
    # cycles here, so that each fault test sees its own fault (the stall test sets its own).
    # The drive's watch on the host gets the longest timeout a rig file may ask for (100 ms),
    # the drive's heartbeat and missed TPDOs lenient timeouts: host and simulated drive share
    # this (not real-time) process, starved together under load.
    rig = load_rig()
    return replace(
        rig,
        safety=replace(rig.safety, loop_stall_s=0.5, glove_timeout_s=1.0),
        drive=replace(
            rig.drive,
            host_heartbeat_timeout_ms=HOST_TIMEOUT_MS,
            heartbeat_timeout_ms=1000,
            max_missed_tpdo=500,
        ),
    )


@pytest.fixture
def devices(rig_config):
    d = RigDevices(rig_config, subject_number=2)
    yield d
    d.close()


# Aborts that say the test process was starved of the CPU, not that the path under test failed:
# the loop stalled past its (lenient) limit, or the drive's watch on its host (at most 100 ms,
# the rig file's rule) fired. Host, loop and simulated drive are threads of one test process
# that is neither real-time nor alone on the CPU (the other test workers, and whatever else
# runs). The safety rule working is tested where it is the subject (test_drive_guard.py,
# the fault tests below, benchmarks/faults.py).
STARVED = ("control loop stalled", "0x8130")


def starved(recs) -> bool:
    """Whether any of ``recs`` (trial records, or the engine's TrialEnded events) was aborted
    for one of the STARVED reasons."""
    return any(
        r.status == "aborted"
        and any(s in (getattr(r, "abort_reason", None) or getattr(r, "reason", None) or "")
                for s in STARVED)
        for r in recs
    )  # fmt: skip


@contextmanager
def on_fresh_rigs(devices, rig_config, tmp_path, session, attempts: int = 3, is_starved=None):
    """``session(devices, directory) -> (state, recs, ...)``, run again on a fresh rig (one drive
    node on the bus at a time) while its trials were aborted only because the process was
    starved (``is_starved(result)``, default: :func:`starved` of its records). Yields the last
    result and its rig; a fresh rig is closed on leaving (``devices`` stays the fixture's to
    close)."""
    is_starved = is_starved or (lambda result: starved(result[1]))
    from steerlab.hardware.live import RigDevices

    rig = devices
    try:
        for attempt in range(attempts):
            directory = tmp_path / f"attempt{attempt}"
            directory.mkdir()
            result = session(rig, directory)
            if not is_starved(result) or attempt == attempts - 1:
                break
            rig.close()
            rig = RigDevices(rig_config, subject_number=2)
        yield result, rig
    finally:
        if rig is not devices:
            rig.close()
