"""The experimenter window's status shows what the loop process did not get (real-time priority,
locked memory, a core of its own): app/gui/rig.py's lab status carries the warnings."""

from __future__ import annotations

from types import SimpleNamespace

from steerlab.app.gui.rig import _lab_status
from steerlab.hardware.realtime import realtime_warnings


def test_lab_status_carries_the_real_time_warnings():
    refused = {
        "switch_interval_s": 2e-4,
        "sched_fifo_priority": "not permitted (Operation not permitted)",
        "mlockall": "not permitted (Cannot allocate memory)",
        "cpus": [0],
    }
    loop = SimpleNamespace(realtime=refused, status={"drive_state": "x", "faults": ["f1"]})
    faults = _lab_status(loop, "rig.toml")()["faults"]
    expected = realtime_warnings(refused)
    assert len(expected) == 3
    assert faults == ["f1"] + [f"warning: {w}" for w in expected]
    assert "real-time priority" in faults[1] and "not locked" in faults[2]


def test_no_warning_when_the_loop_got_everything():
    granted = {"sched_fifo_priority": 20, "mlockall": True, "cpus": [0, 1]}
    loop = SimpleNamespace(realtime=granted, status={})
    assert _lab_status(loop, "rig.toml")()["faults"] == []
