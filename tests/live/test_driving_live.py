"""A drive on the lab's path: the host's vehicle in the real-time device loop, real CAN frames to
the simulated drive node, real glove frames through a pty (issue 19)."""

from __future__ import annotations

import numpy as np

from steerlab.hardware.vehicle import DRIVING_CHANNELS
from steerlab.protocols.datafile import SessionFile, SessionWriter
from steerlab.protocols.engine import SessionEngine, State
from steerlab.protocols.protocol import parse_protocol
from steerlab.protocols.session import build_plan
from tests.live.conftest import SHORT_PROTOCOL, on_fresh_rigs

DRIVE = (
    SHORT_PROTOCOL.split("[[conditions]]")[0]
    + """
[[conditions]]
name = "DRIVE"
task = "driving"
speed_mps = 15.0
"""
)


def _drive(devices, where):
    plan = build_plan(parse_protocol(DRIVE, "drive.toml"), 2)
    eng = SessionEngine(plan, devices.device_loop())
    eng.subscribe(SessionWriter(where / "S02.h5"))
    state = eng.run()
    return state, SessionFile(where / "S02.h5").records()


def test_a_drive_through_can_and_serial_frames(devices, rig_config, tmp_path):
    with on_fresh_rigs(devices, rig_config, tmp_path, _drive) as ((state, recs), rig):
        _check_the_drive(rig, state, recs)


def _check_the_drive(devices, state, recs) -> None:
    assert state is State.DONE, [(r.status, r.abort_reason) for r in recs]
    (rec,) = recs
    assert rec.status == "complete" and rec.driving
    n = rec.n_samples
    for c in DRIVING_CHANNELS:
        assert len(rec.extra[c]) == n and np.all(np.isfinite(rec.extra[c])), c
    s = rec.extra["road_distance_m"]
    assert s[-1] == np.float32(s[-1]) and abs(s[-1] - 15.0 * n / 1000) < 1.0
    ta = rec.extra["aligning_torque_Nm"]
    assert np.std(ta) > 0.01  # the wheel moved, the tyres answered
    # The aligning torque centres the wheel: it opposes the angle when the angle is large.
    th = rec.wheel_angle_rad
    big = np.abs(th) > np.radians(5)
    if big.sum() > 100:
        assert np.mean(np.sign(ta[big]) == -np.sign(th[big])) > 0.7
    y, w = rec.extra["lateral_position_m"], rec.extra["lane_width_m"]
    assert np.all(np.abs(y) < (w - 1.8) / 2)  # the simulated driver kept the lane
    assert not devices.drive.enabled
