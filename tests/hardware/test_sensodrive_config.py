"""Rig file of a SensoDrive SENSO-Wheel (``[drive] kind = "sensodrive"``): loading, defaults
and an error naming file, table and field for every field."""

from __future__ import annotations

import math
import tomllib

import pytest

from steerlab.hardware.can.config import ConfigError
from steerlab.hardware.can.sensodrive_config import SensoDriveConfig, sensodrive_config
from steerlab.hardware.drives import DriveSettings, drive_config, drive_kind
from tests.helpers import edit

SOURCE = "lab/senso.toml"

GOOD = """
[glove]                      # other tables belong to other loaders
port = "/dev/ttyUSB0"

[drive]
kind = "sensodrive"
interface = "pcan"
channel = "PCAN_USBBUS1"
wheel_inertia_kgm2 = 0.3

[drive.torque_sensor]
source = "hand_sensor"

[safety]
max_torque_nm = 8.0
max_slew_nm_per_s = 400.0
soft_angle_limit_deg = 90.0
"""

RECONSTRUCTED = edit(
    GOOD,
    'source = "hand_sensor"',
    'source = "reconstructed"\ncoulomb_nm = 0.1\ngravity_nm = 0.3\nfilter_hz = 30.0',
)


DRIVE = "wheel_inertia_kgm2 = 0.3"


def load(text: str) -> SensoDriveConfig:
    return sensodrive_config(tomllib.loads(text), SOURCE)


def assert_error(text: str, section: str | None, field: str | None, expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        load(text)
    err = info.value
    assert (err.file, err.section, err.field) == (SOURCE, section, field), str(err)
    prefix = f"{SOURCE}: [{section}] {field}: " if field else f"{SOURCE}: [{section}]"
    assert str(err).startswith(prefix), str(err)
    assert expected in str(err), str(err)


# -- a good file ---------------------------------------------------------------------------------


def test_a_good_file_loads_with_the_documented_defaults():
    cfg = load(GOOD)
    assert isinstance(cfg, DriveSettings)
    assert cfg.kind == "sensodrive"
    assert (cfg.interface, cfg.channel, cfg.wheel_inertia_kgm2) == ("pcan", "PCAN_USBBUS1", 0.3)
    assert cfg.bitrate == 1_000_000
    assert cfg.loop_rate_hz == 1000
    assert cfg.sign == -1
    assert cfg.end_stop_deg == 180
    assert (cfg.torque_limit_percent, cfg.torque_limit_beyond_percent) == (100, 100)
    assert cfg.full_scale_torque_nm == 10.0
    assert cfg.friction_nm == 0.0
    assert (cfg.reply_timeout_ms, cfg.max_missed_replies) == (0.8, 20)
    assert (cfg.state_timeout_s, cfg.state_poll_cycles) == (0.5, 10)
    assert cfg.safety.max_torque_nm == 8.0
    assert cfg.source == SOURCE
    assert cfg.angle_quantum_rad == pytest.approx(math.radians(0.009))
    ts = cfg.torque_sensor
    assert ts.source == "hand_sensor"
    assert ts.sensitivity_a == pytest.approx(-1 / 14.696)
    assert ts.sensitivity_b == pytest.approx(1 / 14.832)
    # −1: the formula gives the hands' torque on the wheel, Steerlab records the wheel's on them
    assert (ts.supply_v, ts.sign, ts.rim_inertia_kgm2) == (5.0, -1, 0.0)
    assert cfg.has_hand_sensor


def test_the_hand_sensor_calibration_gives_volts_per_newton_metre():
    cfg = load(GOOD)
    assert cfg.hand_sensor_v_per_nm == pytest.approx(-1 / 14.696 - 1 / 14.832)
    half = load(edit(GOOD, 'source = "hand_sensor"', 'source = "hand_sensor"\nsupply_v = 2.5'))
    assert half.hand_sensor_v_per_nm == pytest.approx(cfg.hand_sensor_v_per_nm / 2)


def test_the_reconstruction_takes_the_wheel_inertia_unless_it_names_its_own():
    cfg = load(RECONSTRUCTED)
    ts = cfg.torque_sensor
    assert (ts.source, ts.coulomb_nm, ts.gravity_nm, ts.filter_hz) == (
        "reconstructed",
        0.1,
        0.3,
        30.0,
    )
    assert cfg.model_inertia_kgm2 == 0.3
    own = load(edit(RECONSTRUCTED, "filter_hz = 30.0", "inertia_kgm2 = 0.31"))
    assert own.model_inertia_kgm2 == 0.31
    assert own.torque_sensor.filter_hz == 40.0  # default


def test_without_a_torque_sensor_table_there_is_no_driver_torque():
    cfg = load(edit(GOOD, '[drive.torque_sensor]\nsource = "hand_sensor"\n', ""))
    assert cfg.torque_sensor.source == "none"
    assert not cfg.has_hand_sensor


def test_the_kind_registry_finds_this_kind_by_name():
    cfg = drive_config(tomllib.loads(GOOD), SOURCE)
    assert isinstance(cfg, SensoDriveConfig)
    assert drive_kind("sensodrive").name == "sensodrive"
    record = cfg.describe()
    assert record["drive_kind"] == "sensodrive"
    assert record["drive_channel"] == "PCAN_USBBUS1"
    assert record["drive_torque_sensor"] == "hand_sensor"


def test_the_bus_load_counts_the_hand_sensor_and_the_state_poll():
    with_sensor = load(GOOD)
    without = load(edit(GOOD, 'source = "hand_sensor"', 'source = "none"'))
    assert with_sensor.cycle_bits > without.cycle_bits
    # 0x201 + 0x211 (8 bytes each, worst-case stuffing: 135 bits) + 0x200/0x210 every 10th
    assert without.cycle_bits == pytest.approx(270 + 27)
    assert with_sensor.bus_load == pytest.approx(with_sensor.cycle_bits * 1000 / 1e6)
    # 500 kbit/s carries the plain cycle at 1 kHz (59 %), not with the hand sensor's (101 %)
    plain = edit(GOOD, 'source = "hand_sensor"', 'source = "none"')
    assert load(edit(plain, DRIVE, f"{DRIVE}\nbitrate = 500000")).bus_load < 0.6
    assert_error(
        edit(GOOD, DRIVE, f"{DRIVE}\nbitrate = 500000"), "drive", "bitrate", "needs ≥ 633750 bit/s"
    )


# -- every field's error names the file, the table and the field ---------------------------------


@pytest.mark.parametrize(
    ("line", "field", "expected"),
    [
        ("bogus = 1", "bogus", "unknown field"),
        ("bitrate = 333", "bitrate", "expected one of"),
        ("bitrate = 500000", "bitrate", "cannot carry one control cycle"),
        ("loop_rate_hz = 2000", "loop_rate_hz", "expected 100 to 1000 Hz"),
        ("loop_rate_hz = 50", "loop_rate_hz", "expected 100 to 1000 Hz"),
        ("loop_rate_hz = 'fast'", "loop_rate_hz", "expected a number"),
        ("sign = 2", "sign", "expected one of 1, -1"),
        ("end_stop_deg = 90", "end_stop_deg", "beyond [safety] soft_angle_limit_deg"),
        ("end_stop_deg = 40000", "end_stop_deg", "1..32767"),
        ("end_stop_deg = 200.5", "end_stop_deg", "expected an integer"),
        ("torque_limit_percent = 255", "torque_limit_percent", "0..254"),
        ("torque_limit_beyond_percent = -1", "torque_limit_beyond_percent", "0..254"),
        ("full_scale_torque_nm = 0", "full_scale_torque_nm", "finite number > 0"),
        ("friction_nm = -0.1", "friction_nm", "expected 0 to"),
        ("friction_nm = 40.0", "friction_nm", "expected 0 to"),
        ("reply_timeout_ms = 1.0", "reply_timeout_ms", "shorter than the loop period"),
        ("max_missed_replies = 0", "max_missed_replies", "≥ 1"),
        ("state_timeout_s = -1", "state_timeout_s", "finite number > 0"),
        ("state_poll_cycles = 0", "state_poll_cycles", "≥ 1"),
        ("wheel_inertia_kgm2 = true", "wheel_inertia_kgm2", "expected a number"),
    ],
)
def test_a_wrong_drive_field_is_named(line, field, expected):
    text = edit(GOOD, DRIVE, line if field == "wheel_inertia_kgm2" else f"{DRIVE}\n{line}")
    assert_error(text, "drive", field, expected)


@pytest.mark.parametrize(
    ("line", "field", "expected"),
    [
        ('interface = "carrier-pigeon"', "interface", "expected one of"),
        ('channel = ""', "channel", "non-empty string"),
        ("channel = 1.5", "channel", "non-empty string"),
    ],
)
def test_a_wrong_bus_field_is_named(line, field, expected):
    old = next(ln for ln in GOOD.splitlines() if ln.startswith(f"{field} ="))
    assert_error(edit(GOOD, old, line), "drive", field, expected)


@pytest.mark.parametrize("field", ["interface", "channel", "wheel_inertia_kgm2"])
def test_a_missing_required_drive_field_is_named(field):
    lines = [ln for ln in GOOD.splitlines() if not ln.startswith(f"{field} =")]
    assert_error("\n".join(lines), "drive", field, "required field is missing")


@pytest.mark.parametrize(
    ("line", "field", "expected"),
    [
        ("bogus = 1", "bogus", "unknown field"),
        ("max_torque_nm = 12.0", "max_torque_nm", "would clip the command"),
        ("max_torque_nm = 'x'", "max_torque_nm", "expected a number"),
        ("max_slew_nm_per_s = 0", "max_slew_nm_per_s", "finite number > 0"),
        ("soft_angle_limit_deg = -5", "soft_angle_limit_deg", "finite number > 0"),
    ],
)
def test_a_wrong_safety_field_is_named(line, field, expected):
    text = GOOD
    old = next((ln for ln in GOOD.splitlines() if ln.startswith(f"{field} =")), None)
    text = edit(text, old, line) if old else edit(text, "[safety]", f"[safety]\n{line}")
    assert_error(text, "safety", field, expected)


def test_a_higher_limit_or_full_scale_allows_a_larger_max_torque():
    raised = edit(GOOD, "max_torque_nm = 8.0", "max_torque_nm = 15.0")
    load(edit(raised, DRIVE, f"{DRIVE}\ntorque_limit_percent = 150"))
    load(edit(raised, DRIVE, f"{DRIVE}\nfull_scale_torque_nm = 15.0"))


def test_a_missing_safety_table_or_field_is_named():
    assert_error(GOOD.split("[safety]")[0], "safety", None, "table is missing")
    assert_error(
        edit(GOOD, "max_torque_nm = 8.0\n", ""), "safety", "max_torque_nm", "required field"
    )


SENSOR = 'source = "hand_sensor"'


@pytest.mark.parametrize(
    ("text", "field", "expected"),
    [
        (edit(GOOD, SENSOR, 'source = "strain gauge"'), "source", "expected one of"),
        (edit(GOOD, SENSOR, "sign = 1"), "source", "required field is missing"),
        (edit(GOOD, SENSOR, f"{SENSOR}\nbogus = 1"), "bogus", "unknown field"),
        (edit(GOOD, SENSOR, f"{SENSOR}\nsensitivity_a = 'x'"), "sensitivity_a", "a number"),
        (
            edit(GOOD, SENSOR, f"{SENSOR}\nsensitivity_a = 0.1\nsensitivity_b = 0.1"),
            "sensitivity_b",
            "equal",
        ),
        (edit(GOOD, SENSOR, f"{SENSOR}\nsupply_v = 0"), "supply_v", "> 0"),
        (edit(GOOD, SENSOR, f"{SENSOR}\nsign = 0"), "sign", "expected one of 1, -1"),
        (edit(GOOD, SENSOR, f"{SENSOR}\nrim_inertia_kgm2 = -0.1"), "rim_inertia_kgm2", "≥ 0"),
        (edit(GOOD, SENSOR, f"{SENSOR}\nfilter_hz = 30"), "filter_hz", "only for source"),
        (
            edit(RECONSTRUCTED, "coulomb_nm = 0.1", "coulomb_nm = 0.1\nsupply_v = 5"),
            "supply_v",
            "only for source = 'hand_sensor'",
        ),
        (edit(GOOD, SENSOR, 'source = "none"\nsign = -1'), "sign", "only for source"),
        (edit(RECONSTRUCTED, "filter_hz = 30.0", "filter_hz = 500"), "filter_hz", "below half"),
        (edit(RECONSTRUCTED, "filter_hz = 30.0", "inertia_kgm2 = 0"), "inertia_kgm2", "> 0"),
        (edit(RECONSTRUCTED, "coulomb_nm = 0.1", "coulomb_nm = -0.1"), "coulomb_nm", "≥ 0"),
        (edit(RECONSTRUCTED, "gravity_nm = 0.3", "gravity_nm = 'x'"), "gravity_nm", "a number"),
    ],
)
def test_a_wrong_torque_sensor_field_is_named(text, field, expected):
    assert_error(text, "drive.torque_sensor", field, expected)


def test_tables_of_the_wrong_type_are_named():
    text = edit(GOOD, "[drive.torque_sensor]\n" + SENSOR + "\n", "")
    text = edit(text, DRIVE, f'{DRIVE}\ntorque_sensor = "hand_sensor"')
    with pytest.raises(ConfigError) as info:
        load(text)
    assert (info.value.section, info.value.field) == ("drive", "torque_sensor")
