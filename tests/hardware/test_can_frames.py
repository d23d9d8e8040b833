"""Frame parsing (incl. fuzzing), CiA 402 state decoding and SI ↔ drive unit scaling."""

from __future__ import annotations

import math
import uuid
from dataclasses import replace

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from steerlab.hardware.can import CiA402Drive, DriveConfig, DriveScaling, SafetyConfig, State402
from steerlab.hardware.can.frames import (
    RPDO1,
    TPDO1,
    VELOCITY_ACTUAL_OBJ,
    FrameError,
    MappedObject,
    PdoLayout,
    decode_statusword,
    emcy_payload,
    emcy_text,
    parse_emcy,
    parse_heartbeat,
    tpdo2_layout,
)

payloads = st.binary(min_size=0, max_size=8)


def config(**changes) -> DriveConfig:
    cfg = DriveConfig(
        node_id=4,
        interface="virtual",
        channel="frames",
        bitrate=1_000_000,
        encoder_counts_per_rev=131072,
        rated_torque_nm=10.0,
        gear_ratio=1.0,
        sign=1,
        safety=SafetyConfig(8.0, 100.0, 360.0),
    )
    return replace(cfg, **changes)


# -- parsing ------------------------------------------------------------------------------------


def test_heartbeat_states():
    assert parse_heartbeat(b"\x05") == 5
    assert parse_heartbeat(b"\x7f") == 0x7F
    assert parse_heartbeat(b"\x85") == 5  # node-guarding toggle bit ignored
    with pytest.raises(FrameError):
        parse_heartbeat(b"")
    with pytest.raises(FrameError):
        parse_heartbeat(b"\x05\x00")


def test_emcy_layout():
    e = parse_emcy(bytes.fromhex("10 32 05 aa bb cc dd ee"))
    assert (e.code, e.error_register, e.vendor_data) == (0x3210, 0x05, bytes.fromhex("aabbccddee"))
    assert e.text == "DC link over-voltage" and not e.is_reset
    assert "EMCY 0x3210 (DC link over-voltage), error register 0x05" in str(e)
    assert parse_emcy(bytes(8)).is_reset
    assert parse_emcy(b"\x00\x81\x11").code == 0x8100  # short but usable
    assert emcy_payload(0x2310, 0x03, b"\x01") == bytes.fromhex("10 23 03 01 00 00 00 00")


@pytest.mark.parametrize(
    ("code", "text"),
    [
        (0x2310, "continuous over-current"),
        (0x2311, "continuous over-current (0x2311)"),  # exact entry absent: nearest group
        (0x4399, "drive temperature (0x4399)"),
        (0x3FFF, "voltage (0x3FFF)"),
        (0xFF42, "device specific (0xFF42)"),
        (0xE000, "unknown error code 0xE000"),
    ],
)
def test_emcy_text(code, text):
    assert emcy_text(code) == text


@pytest.mark.parametrize(
    ("statusword", "state"),
    [
        (0x0000, State402.NOT_READY_TO_SWITCH_ON),
        (0x0250, State402.SWITCH_ON_DISABLED),  # bit 4 (voltage) does not matter here
        (0x0221, State402.READY_TO_SWITCH_ON),
        (0x0233, State402.SWITCHED_ON),
        (0x1637, State402.OPERATION_ENABLED),  # mode-specific and remote bits ignored
        (0x0207, State402.QUICK_STOP_ACTIVE),
        (0x021F, State402.FAULT_REACTION_ACTIVE),
        (0x0208, State402.FAULT),
        (0x0228, State402.FAULT),
        (0x0001, State402.UNKNOWN),
    ],
)
def test_statusword_decoding(statusword, state):
    assert decode_statusword(statusword) is state


def test_pdo_layouts():
    assert RPDO1.encode((0x000F, -150)) == bytes.fromhex("0f 00 6a ff")
    assert TPDO1.decode(bytes.fromhex("37 02 00 f8 ff ff 6a ff")) == (0x0237, -2048, -150)
    assert TPDO1.decode(bytes.fromhex("37 02 00 f8 ff ff 6a ff 99")) == (0x0237, -2048, -150)
    assert tpdo2_layout(None).size == 4
    sensor = MappedObject(0x2000, 0, 16, True, "column")
    assert tpdo2_layout(sensor).decode(bytes.fromhex("01 00 00 00 ff ff")) == (1, -1)
    with pytest.raises(FrameError):
        TPDO1.decode(bytes(7))
    with pytest.raises(FrameError):
        RPDO1.encode((0x000F, 40_000))
    with pytest.raises(ValueError):
        PdoLayout([VELOCITY_ACTUAL_OBJ] * 3)  # 12 bytes


@settings(max_examples=300, deadline=None)
@given(payloads)
def test_fuzz_parsers_raise_only_frame_error(data):
    for parse in (
        parse_heartbeat,
        parse_emcy,
        TPDO1.decode,
        tpdo2_layout(None).decode,
        RPDO1.decode,
    ):
        try:
            parse(data)
        except FrameError:
            pass


@pytest.fixture(scope="module")
def idle_drive():
    """A driver on a bus with nobody else: its receive dispatch is fed frames directly."""
    channel = f"fuzz-{uuid.uuid4()}"
    bus = can.Bus(interface="virtual", channel=channel)
    drive = CiA402Drive(bus, config(channel=channel))
    yield drive
    drive.close()
    bus.shutdown()


@settings(max_examples=400, deadline=None)
@given(
    cob_id=st.one_of(st.sampled_from([0x084, 0x184, 0x284, 0x584, 0x704]), st.integers(0, 0x7FF)),
    data=payloads,
)
def test_fuzz_driver_dispatch_never_raises(idle_drive, cob_id, data):
    """Whatever arrives, the receive thread's handler records it and carries on."""
    msg = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)
    idle_drive._on_frame(msg)
    assert idle_drive._reader.alive


def test_malformed_frames_are_protocol_faults(idle_drive):
    idle_drive._on_frame(can.Message(arbitration_id=0x184, data=b"\x01\x02", is_extended_id=False))
    assert any(f.kind == "protocol" and "0x184" in f.message for f in idle_drive.faults)
    idle_drive._on_frame(
        can.Message(arbitration_id=0x084, data=bytes.fromhex("10 23 01"), is_extended_id=False)
    )
    assert any(f.kind == "emcy" and f.code == 0x2310 for f in idle_drive.faults)


# -- scaling ------------------------------------------------------------------------------------

configs = st.builds(
    config,
    encoder_counts_per_rev=st.integers(512, 1 << 20),
    gear_ratio=st.floats(0.2, 50.0),
    sign=st.sampled_from([1, -1]),
    rated_torque_nm=st.floats(0.5, 50.0),
    velocity_unit=st.sampled_from(["counts_per_s", "rpm"]),
    safety=st.just(SafetyConfig(0.1, 1.0, 1.0)),
)


@settings(max_examples=200, deadline=None)
@given(
    cfg=configs,
    angle=st.floats(-20.0, 20.0),
    velocity=st.floats(-50.0, 50.0),
    fraction=st.floats(-3.0, 3.0),
)
def test_scaling_round_trips_within_half_a_unit(cfg, angle, velocity, fraction):
    s = DriveScaling(cfg)
    counts_per_rad = cfg.encoder_counts_per_rev * cfg.gear_ratio / (2 * math.pi)
    assert s.counts_to_angle(s.angle_to_counts(angle)) == pytest.approx(
        angle, abs=0.5 / counts_per_rad + 1e-12
    )
    if cfg.velocity_unit == "rpm":
        unit = 2 * math.pi / 60 / cfg.gear_ratio  # rad/s of the wheel per motor rpm
    else:
        unit = 1 / counts_per_rad
    assert s.velocity_to_rad_s(s.rad_s_to_velocity(velocity)) == pytest.approx(
        velocity, abs=0.5 * unit + 1e-12
    )
    torque = fraction * cfg.rated_torque_nm * cfg.gear_ratio  # within ±3× rated
    assert s.permille_to_torque(s.torque_to_permille(torque)) == pytest.approx(
        torque, abs=0.5 * s.torque_resolution_nm + 1e-12
    )


def test_scaling_signs_and_gear_by_hand():
    s = DriveScaling(
        config(
            encoder_counts_per_rev=1000,
            gear_ratio=4.0,
            sign=-1,
            rated_torque_nm=2.0,
            velocity_unit="rpm",
        )
    )
    # one wheel turn = 4 motor turns = 4000 counts, negative because sign = −1
    assert s.angle_to_counts(2 * math.pi) == -4000
    # 60 motor rpm = 1 motor rev/s = 1/4 wheel rev/s, negated
    assert s.velocity_to_rad_s(60) == pytest.approx(-math.pi / 2)
    # 1 N·m at the wheel = 0.25 N·m at the motor = 125 ‰ of 2 N·m, negated
    assert s.torque_to_permille(1.0) == -125
    assert s.torque_to_permille(1e9) == -0x8000 and s.torque_to_permille(-1e9) == 0x7FFF
    assert s.angle_to_counts(1e9) in range(-(1 << 31), 1 << 31)  # wraps like the drive


def test_sensor_scaling():
    cfg = config()
    cfg = replace(
        cfg, torque_sensor=replace(cfg.torque_sensor, bits=16, sign=-1, nm_per_count=0.01)
    )
    s = DriveScaling(cfg)
    assert s.torque_to_sensor(1.5) == -150
    assert s.sensor_to_torque(-150) == pytest.approx(1.5)
    assert s.torque_to_sensor(1e6) == -0x8000
