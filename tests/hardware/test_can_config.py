"""Rig file [drive] / [drive.torque_sensor] / [safety]: loading and error messages."""

from __future__ import annotations

import math
import re
from pathlib import Path

import can
import pytest

from steerlab.hardware.can import (
    CiA402Drive,
    ConfigError,
    DriveConfig,
    SafetyConfig,
    TorqueSensorConfig,
    driver_filters,
    load_drive_config,
    open_bus,
)
from tests.helpers import assert_rig_error, edit, write_rig

ROOT = Path(__file__).resolve().parents[2]
SIMULATED = ROOT / "hardware" / "rigs" / "simulated.toml"

GOOD = """
[glove]               # other tables belong to other loaders and are ignored here
port = "/dev/ttyUSB0"

[drive]
node_id = 3
interface = "socketcan"
channel = "can0"
bitrate = 1_000_000
encoder_counts_per_rev = 131072
rated_torque_nm = 7.5
gear_ratio = 3.0
sign = -1

[drive.torque_sensor]
source = "pdo"
index = 0x2001
subindex = 2
bits = 16
nm_per_count = 0.01

[safety]
max_torque_nm = 15.0
max_slew_nm_per_s = 300.0
soft_angle_limit_deg = 360.0
"""


def test_simulated_rig_file_loads():
    cfg = load_drive_config(SIMULATED)
    assert cfg.interface == "virtual"
    assert cfg.loop_rate_hz == 1000
    assert cfg.torque_sensor.source == "pdo"
    assert cfg.source == str(SIMULATED)
    assert cfg.bus_load < 0.8


def test_good_file_values_and_defaults(tmp_path):
    cfg = load_drive_config(write_rig(tmp_path, GOOD))
    assert (cfg.node_id, cfg.interface, cfg.channel, cfg.sign) == (3, "socketcan", "can0", -1)
    assert cfg.torque_sensor == TorqueSensorConfig("pdo", 0x2001, 2, 16, 0.01, 1)
    assert cfg.safety == SafetyConfig(15.0, 300.0, 360.0)
    assert cfg.heartbeat_ms == 100 and cfg.heartbeat_timeout_ms == 250
    # 15 N·m at the wheel = 5 N·m at the motor = 666.7 ‰ of 7.5 N·m rated
    assert cfg.max_torque_permille == 667


@pytest.mark.parametrize(
    ("old", "new", "section", "field", "expected"),
    [
        ("node_id = 3\n", "", "drive", "node_id", "required field is missing"),
        ("node_id = 3", 'node_id = "three"', "drive", "node_id", "expected an integer"),
        ("node_id = 3", "node_id = 128", "drive", "node_id", "1..127"),
        ("node_id = 3", "node_id = true", "drive", "node_id", "expected an integer"),
        (
            'interface = "socketcan"',
            'interface = "sockcan"',
            "drive",
            "interface",
            "expected one of",
        ),
        ("bitrate = 1_000_000", "bitrate = 999", "drive", "bitrate", "expected one of"),
        (
            "bitrate = 1_000_000",
            "bitrate = 250_000",
            "drive",
            "bitrate",
            "cannot carry one control cycle",
        ),
        ("gear_ratio = 3.0", "gear_ratio = 0", "drive", "gear_ratio", "> 0"),
        ("gear_ratio = 3.0", "gear_ratio = nan", "drive", "gear_ratio", "finite"),
        ("sign = -1", "sign = -1\nsdo_timeout_s = 0", "drive", "sdo_timeout_s", "> 0"),
        ("sign = -1", "sign = 0", "drive", "sign", "expected one of 1, -1"),
        (
            "sign = -1",
            "sign = -1\nheartbeat_ms = 300",
            "drive",
            "heartbeat_timeout_ms",
            "longer than heartbeat_ms",
        ),
        (
            "sign = -1",
            "sign = -1\ntpdo_timeout_ms = 1.5",
            "drive",
            "tpdo_timeout_ms",
            "shorter than the loop period",
        ),
        ("sign = -1", "sign = -1\ngear_ration = 2", "drive", "gear_ration", "unknown field"),
        (
            'source = "pdo"',
            'source = "can"',
            "drive.torque_sensor",
            "source",
            "expected one of 'pdo', 'node', 'none'",
        ),
        ("index = 0x2001", "index = 0x1000", "drive.torque_sensor", "index", "8192..40959"),
        ("bits = 16", "bits = 24", "drive.torque_sensor", "bits", "expected one of 16, 32"),
        (
            'source = "pdo"',
            'source = "node"\nnode_id = 3',
            "drive.torque_sensor",
            "node_id",
            "must differ from the drive's",
        ),
        ("max_torque_nm = 15.0", "max_torque_nm = -1.0", "safety", "max_torque_nm", "> 0"),
        ("max_torque_nm = 15.0", "max_torque_nm = 1e6", "safety", "max_torque_nm", "32767"),
        (
            "soft_angle_limit_deg = 360.0\n",
            "",
            "safety",
            "soft_angle_limit_deg",
            "required field is missing",
        ),
    ],
)
def test_errors_name_file_section_field(tmp_path, old, new, section, field, expected):
    assert_rig_error(tmp_path, edit(GOOD, old, new), section, field, expected)


def test_missing_tables(tmp_path):
    path = write_rig(tmp_path, GOOD.split("[safety]")[0])
    with pytest.raises(ConfigError, match=re.escape(f"{path}: [safety]: table is missing")):
        load_drive_config(path)
    path = write_rig(tmp_path, "[glove]\nport = 1\n")
    with pytest.raises(ConfigError, match=re.escape(f"{path}: [drive]: table is missing")):
        load_drive_config(path)


def test_not_toml_and_missing_file(tmp_path):
    path = write_rig(tmp_path, "[drive\nnode_id = 1")
    with pytest.raises(ConfigError, match="not valid TOML") as info:
        load_drive_config(path)
    assert info.value.file == str(path)
    with pytest.raises(ConfigError, match="cannot read rig file"):
        load_drive_config(tmp_path / "nope.toml")


def test_config_built_in_code_is_validated_too():
    with pytest.raises(ConfigError, match=r"<python>: \[drive\] sign"):
        DriveConfig(1, "virtual", "x", 1_000_000, 4096, 1.0, 1.0, 2, SafetyConfig(1, 1, 1))


def test_node_torque_sensor_config_reaches_the_driver(tmp_path):
    # Behaviour of source = "node": tests/hardware/test_can_sensor_node.py
    text = edit(GOOD, 'source = "pdo"', 'source = "node"\nnode_id = 9\ncob_id = 0x189')
    text = edit(text, "index = 0x2001\nsubindex = 2\n", "")
    text = edit(
        text,
        'interface = "socketcan"\nchannel = "can0"',
        'interface = "virtual"\nchannel = "cfg-node-sensor"',
    )
    cfg = load_drive_config(write_rig(tmp_path, text))
    assert {"can_id": 0x189, "can_mask": 0x7FF, "extended": False} in driver_filters(cfg)
    bus = can.Bus(interface="virtual", channel="cfg-node-sensor")
    try:
        with CiA402Drive(bus, cfg) as drive:
            assert math.isnan(drive.torque_sensor.read())  # no sensor frame yet
    finally:
        bus.shutdown()


def test_open_bus_uses_rig_file_and_filters(tmp_path):
    text = edit(
        GOOD,
        'interface = "socketcan"\nchannel = "can0"',
        'interface = "virtual"\nchannel = "cfg-open-bus"',
    )
    cfg = load_drive_config(write_rig(tmp_path, text))
    bus = open_bus(cfg)
    other = can.Bus(interface="virtual", channel="cfg-open-bus")
    try:
        other.send(can.Message(arbitration_id=0x183, data=b"\x01", is_extended_id=False))
        other.send(can.Message(arbitration_id=0x184, data=b"\x02", is_extended_id=False))
        got = bus.recv(0.5)
        assert got is not None and got.arbitration_id == 0x183  # TPDO1 of node 3
        assert bus.recv(0.05) is None  # another node's TPDO is filtered out
    finally:
        bus.shutdown()
        other.shutdown()
