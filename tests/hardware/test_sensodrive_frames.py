"""The SensoDrive frames: byte layouts and units as the public clients use them
(``sensodrive-protocol.md``), and, from outside, a real SENSO-Wheel recording's angles."""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from steerlab.hardware.can.frames import FrameError
from steerlab.hardware.can.sensodrive_frames import (
    NM_PER_RAD_PER_STIFFNESS_LSB,
    NMS_PER_RAD_PER_DAMPING_LSB,
    RAD_PER_ANGLE_INCREMENT,
    STATE_REPLY_ID,
    WHEEL_REPLY_ID,
    Command,
    State,
    StateCommand,
    WheelCommand,
    WheelReply,
    decode_hand_sensor_reply,
    decode_state_command,
    decode_state_reply,
    decode_wheel_command,
    decode_wheel_reply,
    encode_hand_sensor_reply,
    encode_state_command,
    encode_state_reply,
    encode_wheel_command,
    encode_wheel_reply,
    reply_id,
)

REAL = Path(
    os.environ.get(
        "STEERLAB_REAL_SENSODRIVE",
        Path(__file__).resolve().parents[3] / "shared" / "data" / "real-sensodrive",
    )
)


def test_replies_come_on_the_request_id_plus_0x10():
    assert reply_id(0x200) == STATE_REPLY_ID == 0x210
    assert reply_id(0x201) == WHEEL_REPLY_ID == 0x211
    assert reply_id(0x20A) == 0x21A


def test_the_pronker_wheel_is_encoded_as_the_protocol_notes_work_it_out():
    # 4.2 N·m/rad → 73 mN·m/deg (renders 4.18), 2 N·m·s/rad → 209 mN·m/rpm (renders 1.996).
    data = encode_wheel_command(WheelCommand(1.5, 0.0, 2.0, 4.2))
    assert data == bytes([0xDC, 0x05, 0, 0, 209, 0, 73, 0])
    back = decode_wheel_command(data)
    assert back.stiffness_nm_per_rad == pytest.approx(4.18, abs=0.005)
    assert back.damping_nms_per_rad == pytest.approx(1.996, abs=0.001)
    assert 1 / NM_PER_RAD_PER_STIFFNESS_LSB == pytest.approx(1000 * math.pi / 180)
    assert 1 / NMS_PER_RAD_PER_DAMPING_LSB == pytest.approx(1000 * 2 * math.pi / 60)


def test_fields_are_little_endian_and_signed():
    assert encode_wheel_command(WheelCommand(torque_nm=-1.5))[:2] == bytes([0x24, 0xFA])
    r = decode_wheel_reply(bytes([0x60, 0x79, 0xFE, 0xFF, 0xF6, 0xFF, 0x18, 0xFC]))
    assert r.angle_rad == pytest.approx(math.radians(-100000 * 0.009))  # -2.5 turns
    assert r.rate_rad_s == pytest.approx(-10 * 2 * math.pi / 60)
    assert r.torque_nm == pytest.approx(-1.0)


def test_state_command_carries_end_stop_and_limits():
    data = encode_state_command(StateCommand(Command.ON, 360, 200, 200))
    assert data == bytes([0x14, 0, 0x68, 0x01, 0, 0, 200, 200])
    assert decode_state_command(data) == StateCommand(Command.ON, 360, 200, 200)
    assert decode_state_reply(encode_state_reply(State.ERROR, 0x0102)) == (State.ERROR, 0x0102)
    assert decode_state_reply(bytes([0x33, 0, 0, 0, 0, 0, 0, 0]))[0] == 0x33


def test_hand_sensor_voltages_b_then_a():
    data = encode_hand_sensor_reply(2.5, -1.25)
    assert len(data) == 8 and data[2:4] == (-256).to_bytes(2, "little", signed=True)
    assert decode_hand_sensor_reply(data) == pytest.approx((2.5, -1.25))


@pytest.mark.parametrize(
    "command, field",
    [
        (WheelCommand(torque_nm=40.0), "torque"),
        (WheelCommand(torque_nm=float("nan")), "torque"),
        (WheelCommand(damping_nms_per_rad=-400.0), "damping"),
        (WheelCommand(stiffness_nm_per_rad=2000.0), "stiffness"),
    ],
)
def test_a_value_the_field_cannot_hold_is_refused_never_wrapped(command, field):
    with pytest.raises(FrameError, match=field):
        encode_wheel_command(command)


def test_short_or_unknown_frames_are_frame_errors():
    with pytest.raises(FrameError, match="0x211"):
        decode_wheel_reply(bytes(4))
    with pytest.raises(FrameError, match="unknown state command"):
        decode_state_command(bytes([0x02, 0, 0, 0, 0, 0, 0, 0]))


@given(
    t=st.floats(-32.7, 32.7),
    b=st.floats(-300.0, 300.0),
    k=st.floats(-1800.0, 1800.0),
)
def test_wheel_command_round_trip_within_half_a_step(t, b, k):
    back = decode_wheel_command(encode_wheel_command(WheelCommand(t, -t, b, k)))
    assert abs(back.torque_nm - t) <= 0.5e-3 + 1e-12
    assert abs(back.friction_nm + t) <= 0.5e-3 + 1e-12
    assert abs(back.damping_nms_per_rad - b) <= NMS_PER_RAD_PER_DAMPING_LSB / 2 + 1e-12
    assert abs(back.stiffness_nm_per_rad - k) <= NM_PER_RAD_PER_STIFFNESS_LSB / 2 + 1e-12


@pytest.mark.skipif(
    not (REAL / "sensodrive_handsoff.csv").is_file(),
    reason=f"the real SensoDrive recording is not at {REAL} (set STEERLAB_REAL_SENSODRIVE)",
)
def test_a_real_senso_wheel_reports_angles_on_the_grid_the_codec_decodes():
    # The recording keeps the angle the drive reported, in rad with 7 significant digits: every
    # sample must be a whole number of 0.009° increments, and re-encoding it must give it back.
    with open(REAL / "sensodrive_handsoff.csv", newline="") as f:
        angle = np.array([float(r["wheel_angle_rad"]) for r in csv.DictReader(f)])
    n = angle / RAD_PER_ANGLE_INCREMENT
    assert angle.size > 10_000 and np.ptp(n) > 1000  # a real excursion, not a still wheel
    assert np.max(np.abs(n - np.round(n))) < 0.01
    for a in angle[:: max(1, angle.size // 2000)]:
        back = decode_wheel_reply(encode_wheel_reply(WheelReply(float(a), 0.0, 0.0))).angle_rad
        assert back == pytest.approx(a, abs=1e-6)
