"""Rig configuration of the CAN drive: the ``[drive]``, ``[drive.torque_sensor]`` and ``[safety]``
tables of a rig TOML file (see ``docs/rig-config.md`` and ``hardware/rigs/simulated.toml``).

Every value is checked when the config is built, so a wrong rig file fails at load time with a
:class:`ConfigError` naming the file, the table and the field, never halfway through a session.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, Literal

import can

from .frames import (
    NMT_COB_ID,
    SYNC_COB_ID,
    emcy_cob_id,
    heartbeat_cob_id,
    rpdo_cob_id,
    sdo_rx_cob_id,
    sdo_tx_cob_id,
    tpdo_cob_id,
)

TorqueSensorSource = Literal["pdo", "node", "none"]
VelocityUnit = Literal["counts_per_s", "rpm"]

#: Steerlab's own interface: a bus shared between processes of this machine
#: (:mod:`hardware.can.udp_bus`), for simulated devices in a process of their own.
UDP_LOOPBACK = "udp_loopback"

CAN_BITRATES = (10_000, 20_000, 50_000, 100_000, 125_000, 250_000, 500_000, 800_000, 1_000_000)


def _frame_bits(data_bytes: int) -> int:
    """Worst-case bits of one standard data frame: 47 bits of overhead + data + bit stuffing."""
    return 47 + 8 * data_bytes + (34 + 8 * data_bytes - 1) // 4


# Worst-case bits of one control cycle on the wire: RPDO (4 data bytes) + SYNC (0) + TPDO1 (8) +
# TPDO2 (8). Used to refuse a bitrate that cannot carry the loop; the real bus also carries
# heartbeats and any other nodes. A torque sensor node adds its frame (counted as 8 bytes: we do
# not know how long the sensor's own frame is).
_CYCLE_BITS = sum(_frame_bits(n) for n in (4, 0, 8, 8))
_SENSOR_FRAME_BITS = _frame_bits(8)
MAX_BUS_LOAD = 0.8

#: The longest the drive may keep torque on after losing its host (``host_heartbeat_timeout_ms``).
MAX_HOST_TIMEOUT_MS = 100
#: CiA 402 0x6007 abort connection option codes the rig file may choose (0, "no action", would
#: leave the torque on the wheel).
ABORT_CONNECTION_OPTIONS = {1: "fault", 2: "disable voltage", 3: "quick stop"}

_PYTHON = "<python>"


class ConfigError(ValueError):
    """A rig file (or a config built in code) is missing a field or has a wrong value.

    ``file``, ``section`` and ``field`` say where; the message says what was expected.
    """

    def __init__(self, file: str, section: str | None, field: str | None, problem: str):
        self.file = file
        self.section = section
        self.field = field
        self.problem = problem
        where = file
        if section is not None:
            where += f": [{section}]"
        if field is not None:
            where += f" {field}"
        super().__init__(f"{where}: {problem}")


@dataclass(frozen=True)
class TorqueSensorConfig:
    """Where the column (driver) torque comes from.

    - ``"pdo"``: the drive samples the sensor and maps it into its TPDO2 (object ``index``:
      ``subindex``, ``bits`` wide, signed); value in N·m = ``sign * nm_per_count * raw``.
    - ``"node"``: a separate CAN node ``node_id`` (e.g. a strain-gauge amplifier) sends it on
      every SYNC in its own frame ``cob_id`` (default 0x180 + ``node_id``, its TPDO1): a signed
      little-endian integer of ``bits`` at ``byte_offset``; same scaling. The host starts the
      node (NMT start) at enable() and writes nothing else to it. With
      ``heartbeat_timeout_ms`` > 0 the node's own heartbeat is watched as well (0: the node
      produces none, or it is not watched).
    - ``"none"``: no column torque sensor.

    Sign convention: positive = the torque the wheel exerts on the hands towards positive angle.
    """

    source: TorqueSensorSource = "pdo"
    index: int = 0x2000
    subindex: int = 0
    bits: int = 32
    nm_per_count: float = 0.001
    sign: int = 1
    node_id: int | None = None
    cob_id: int | None = None
    byte_offset: int = 0
    heartbeat_timeout_ms: int = 0

    @property
    def frame_cob_id(self) -> int | None:
        """COB-ID of the sensor node's frame (``source = "node"`` only, else None)."""
        if self.source != "node" or self.node_id is None:
            return None
        return self.cob_id if self.cob_id is not None else tpdo_cob_id(1, self.node_id)


@dataclass(frozen=True)
class SafetyConfig:
    """Limits the safety layer enforces. The drive stack itself only uses ``max_torque_nm``: it
    is written to the drive's max torque (0x6072) so the drive clamps even if the host fails."""

    max_torque_nm: float
    max_slew_nm_per_s: float
    soft_angle_limit_deg: float
    # Used by the control loop (hardware.safety.SafetyLimits), not by the drive stack:
    fade_zone_deg: float = 15.0
    brake_damping_nms_per_rad: float = 5.0
    loop_stall_s: float = 0.02
    glove_timeout_s: float = 0.25


@dataclass(frozen=True)
class DriveConfig:
    """One CiA 402 servo drive on one CAN bus, in wheel units.

    ``gear_ratio`` is motor revolutions per wheel revolution; ``encoder_counts_per_rev`` and
    ``rated_torque_nm`` are on the motor side (as the drive reports them in 0x608F / 0x6076);
    ``sign`` is +1 if the drive's positive direction is the wheel's positive direction
    (counter-clockwise seen by the driver), else −1.
    """

    node_id: int
    interface: str
    channel: str | int
    bitrate: int
    encoder_counts_per_rev: int
    rated_torque_nm: float
    gear_ratio: float
    sign: int
    safety: SafetyConfig
    heartbeat_ms: int = 100
    heartbeat_timeout_ms: int = 250
    # The drive's own guard against a lost host (CiA 301 0x1016, CiA 402 0x6007):
    host_node_id: int = 127
    host_heartbeat_ms: int = 20
    host_heartbeat_timeout_ms: int = 80
    abort_connection_option: int = 2
    loop_rate_hz: float = 1000.0
    tpdo_timeout_ms: float = 0.8
    max_missed_tpdo: int = 20
    state_timeout_s: float = 0.5
    # How long the host waits for each SDO answer (canopen's own default, 0.3 s). A drive
    # answers in milliseconds; a busy host may see the answer late.
    sdo_timeout_s: float = 0.3
    velocity_unit: VelocityUnit = "counts_per_s"
    torque_sensor: TorqueSensorConfig = field(default_factory=TorqueSensorConfig)
    source: str = field(default=_PYTHON, compare=False)
    #: the rig file's ``[drive] kind`` (:mod:`hardware.drives`)
    kind: ClassVar[str] = "cia402"

    def __post_init__(self) -> None:
        _validate(self)

    @property
    def angle_quantum_rad(self) -> float:
        """The smallest angle step the drive reports: one encoder count on the wheel."""
        from .scaling import DriveScaling

        return abs(DriveScaling(self).counts_to_angle(1))

    def describe(self) -> dict[str, Any]:
        """The fields that identify this drive, for a session file's rig record."""
        return {
            "drive_kind": self.kind,
            "drive_interface": self.interface,
            "drive_channel": str(self.channel),
            "drive_node_id": self.node_id,
        }

    @property
    def sync_period_s(self) -> float:
        return 1.0 / self.loop_rate_hz

    @property
    def max_torque_permille(self) -> int:
        """``safety.max_torque_nm`` as the drive's 0x6072 value (0.1 % of rated motor torque)."""
        return round(self.safety.max_torque_nm / (self.gear_ratio * self.rated_torque_nm) * 1000)

    @property
    def cycle_bits(self) -> int:
        """Worst-case bits one control cycle puts on the bus (with the sensor node's frame)."""
        node = (
            isinstance(self.torque_sensor, TorqueSensorConfig)
            and self.torque_sensor.source == "node"
        )
        return _CYCLE_BITS + (_SENSOR_FRAME_BITS if node else 0)

    @property
    def bus_load(self) -> float:
        """Worst-case fraction of the bus the control cycle uses at ``loop_rate_hz``."""
        return self.cycle_bits * self.loop_rate_hz / self.bitrate


def load_drive_config(path: str | Path) -> DriveConfig:
    """Read ``[drive]``, ``[drive.torque_sensor]`` and ``[safety]`` from a rig TOML file.

    Other tables in the file (glove, display, …) are left to their own loaders.

    :raises ConfigError: the file is unreadable, not TOML, or a field is missing or wrong.
    """
    name = str(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as exc:
        raise ConfigError(name, None, None, f"cannot read rig file ({exc.strerror})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(name, None, None, f"not valid TOML: {exc}") from exc
    return drive_config_from_dict(data, source=name)


def drive_config_from_dict(data: dict[str, Any], *, source: str = "<dict>") -> DriveConfig:
    """Build a :class:`DriveConfig` from the parsed TOML document (all tables).

    :raises ConfigError: as :func:`load_drive_config`.
    """
    drive = _table(data, "drive", source, required=True)
    safety_table = _table(data, "safety", source, required=True)
    assert drive is not None and safety_table is not None  # required: _table raised otherwise
    sensor_table = _table(drive, "torque_sensor", source, required=False, section="drive")
    # ``kind`` chose this module (hardware.drives); it is not a CiA 402 setting.
    drive = {k: v for k, v in drive.items() if k not in ("torque_sensor", "kind")}

    sensor = TorqueSensorConfig(
        **_known(sensor_table or {}, TorqueSensorConfig, source, "drive.torque_sensor")
    )
    safety = SafetyConfig(**_known(safety_table, SafetyConfig, source, "safety"))
    kwargs = _known(
        drive, DriveConfig, source, "drive", exclude={"safety", "torque_sensor", "source"}
    )
    return DriveConfig(**kwargs, safety=safety, torque_sensor=sensor, source=source)


def _table(
    data: dict[str, Any], key: str, source: str, *, required: bool, section: str | None = None
) -> dict[str, Any] | None:
    value = data.get(key)
    full = f"{section}.{key}" if section else key
    if value is None:
        if required:
            raise ConfigError(source, full, None, "table is missing")
        return None
    if not isinstance(value, dict):
        raise ConfigError(
            source, section, key, f"expected a table [{full}], got {type(value).__name__}"
        )
    return value


def _known(
    table: dict[str, Any],
    cls: type,
    source: str,
    section: str,
    exclude: frozenset[str] | set[str] = frozenset(),
) -> dict[str, Any]:
    """Reject unknown keys (a typo must not silently fall back to a default) and missing
    required ones; type and range checks happen in ``_validate``."""
    names = {f.name for f in fields(cls)} - set(exclude)
    for key in table:
        if key not in names:
            raise ConfigError(
                source, section, key, f"unknown field (known fields: {', '.join(sorted(names))})"
            )
    for f in fields(cls):
        if f.name in names and f.name not in table and _is_required(f):
            raise ConfigError(source, section, f.name, "required field is missing")
    return dict(table)


def _is_required(f: Any) -> bool:
    return f.default is MISSING and f.default_factory is MISSING


# -- validation ---------------------------------------------------------------------------------


class _Check:
    def __init__(self, obj: Any, source: str, section: str):
        self.obj, self.source, self.section = obj, source, section

    def fail(self, name: str, problem: str) -> ConfigError:
        return ConfigError(self.source, self.section, name, problem)

    def got(self, name: str) -> str:
        return f"got {getattr(self.obj, name)!r}"

    def int_(self, name: str, lo: int, hi: int | None = None) -> int:
        value = getattr(self.obj, name)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(name, f"expected an integer, {self.got(name)}")
        if value < lo or (hi is not None and value > hi):
            rng = f"{lo}..{hi}" if hi is not None else f"≥ {lo}"
            raise self.fail(name, f"expected an integer in {rng}, got {value}")
        return value

    def float_(self, name: str, *, positive: bool = True) -> float:
        value = getattr(self.obj, name)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(name, f"expected a number, {self.got(name)}")
        if not math.isfinite(value) or (positive and value <= 0):
            raise self.fail(name, f"expected a finite number > 0, got {value}")
        return float(value)

    def choice(self, name: str, options: tuple[Any, ...]) -> Any:
        value = getattr(self.obj, name)
        if isinstance(value, bool) or value not in options:
            opts = ", ".join(repr(o) for o in options)
            raise self.fail(name, f"expected one of {opts}, {self.got(name)}")
        return value


def _validate(cfg: DriveConfig) -> None:
    src = cfg.source
    c = _Check(cfg, src, "drive")
    node_id = c.int_("node_id", 1, 127)
    c.choice("interface", tuple(sorted(can.interfaces.VALID_INTERFACES | {UDP_LOOPBACK})))
    if isinstance(cfg.channel, bool) or not isinstance(cfg.channel, str | int) or cfg.channel == "":
        raise c.fail("channel", f"expected a non-empty string or an integer, {c.got('channel')}")
    c.choice("bitrate", CAN_BITRATES)
    c.int_("encoder_counts_per_rev", 1)
    c.float_("rated_torque_nm")
    c.float_("gear_ratio")
    c.choice("sign", (1, -1))
    hb = c.int_("heartbeat_ms", 1, 0xFFFF)
    hb_timeout = c.int_("heartbeat_timeout_ms", 1)
    if hb_timeout <= hb:
        raise c.fail(
            "heartbeat_timeout_ms",
            f"must be longer than heartbeat_ms ({hb} ms), got {hb_timeout}; "
            "2 to 3 times heartbeat_ms is usual",
        )
    _validate_host_guard(c, cfg, node_id)
    rate = c.float_("loop_rate_hz")
    period_ms = 1000.0 / rate
    if round(period_ms * 1000) < 1:
        raise c.fail("loop_rate_hz", f"period must be at least 1 µs, got {rate} Hz")
    tpdo_timeout = c.float_("tpdo_timeout_ms")
    if tpdo_timeout >= period_ms:
        raise c.fail(
            "tpdo_timeout_ms",
            f"must be shorter than the loop period ({period_ms:g} ms at "
            f"loop_rate_hz {rate:g}), got {tpdo_timeout}",
        )
    c.int_("max_missed_tpdo", 1)
    c.float_("state_timeout_s")
    c.float_("sdo_timeout_s")
    c.choice("velocity_unit", ("counts_per_s", "rpm"))
    if not isinstance(cfg.safety, SafetyConfig):
        raise ConfigError(src, "safety", None, "expected a [safety] table")
    if not isinstance(cfg.torque_sensor, TorqueSensorConfig):
        raise ConfigError(src, "drive.torque_sensor", None, "expected a table")
    if cfg.bus_load > MAX_BUS_LOAD:
        need = math.ceil(cfg.cycle_bits * rate / MAX_BUS_LOAD)
        raise c.fail(
            "bitrate",
            f"{cfg.bitrate} bit/s cannot carry one control cycle (~{cfg.cycle_bits} bits) "
            f"at loop_rate_hz {rate:g} within {MAX_BUS_LOAD:.0%} bus load "
            f"(needs ≥ {need} bit/s)",
        )

    s = _Check(cfg.safety, src, "safety")
    max_t = s.float_("max_torque_nm")
    s.float_("max_slew_nm_per_s")
    s.float_("soft_angle_limit_deg")
    permille = max_t / (cfg.gear_ratio * cfg.rated_torque_nm) * 1000
    if permille > 0x7FFF:
        raise s.fail(
            "max_torque_nm",
            f"{max_t} N·m is {permille:.0f} ‰ of rated torque × gear, more than the "
            "drive's 16-bit torque objects can express (32767 ‰)",
        )

    t = _Check(cfg.torque_sensor, src, "drive.torque_sensor")
    source = t.choice("source", ("pdo", "node", "none"))
    if source == "none":
        return
    t.float_("nm_per_count")
    t.choice("sign", (1, -1))
    t.choice("bits", (16, 32))
    if source == "pdo":
        t.int_("index", 0x2000, 0x9FFF)
        t.int_("subindex", 0, 0xFE)
    else:
        _validate_sensor_node(t, cfg.torque_sensor, node_id)


def _validate_host_guard(c: _Check, cfg: DriveConfig, drive_id: int) -> None:
    """The drive's watch on the host: its consumer heartbeat time (0x1016) must be short enough
    to protect the person holding the wheel and long enough for the host's heartbeat period."""
    host = c.int_("host_node_id", 1, 127)
    if host == drive_id:
        raise c.fail("host_node_id", f"must differ from the drive's node_id {drive_id}")
    sensor = cfg.torque_sensor
    if isinstance(sensor, TorqueSensorConfig) and sensor.source == "node":
        if host == sensor.node_id:
            raise c.fail(
                "host_node_id",
                f"must differ from the torque sensor's node_id {sensor.node_id} "
                "([drive.torque_sensor])",
            )
    period = c.int_("host_heartbeat_ms", 1, 0xFFFF)
    timeout = c.int_("host_heartbeat_timeout_ms", 1, MAX_HOST_TIMEOUT_MS)
    if timeout <= period:
        raise c.fail(
            "host_heartbeat_timeout_ms",
            f"must be longer than host_heartbeat_ms ({period} ms), got {timeout}; "
            "3 to 4 times host_heartbeat_ms is usual",
        )
    c.choice("abort_connection_option", tuple(ABORT_CONNECTION_OPTIONS))


def _validate_sensor_node(t: _Check, sensor: TorqueSensorConfig, drive_id: int) -> None:
    if sensor.node_id is None:
        raise t.fail(
            "node_id", "required for source = 'node': the sensor's CANopen node id (1..127)"
        )
    sensor_id = t.int_("node_id", 1, 127)
    if sensor_id == drive_id:
        raise t.fail("node_id", f"must differ from the drive's [drive] node_id {drive_id}")
    if sensor.cob_id is not None:
        cob_id = t.int_("cob_id", 0x001, 0x7FF)
        # The driver dispatches frames by COB-ID alone: a sensor frame on one of these would be
        # taken for (or hide) the drive's frame, or a SYNC / NMT command.
        taken = {
            NMT_COB_ID: "NMT",
            SYNC_COB_ID: "SYNC",
            emcy_cob_id(drive_id): "the drive's EMCY",
            tpdo_cob_id(1, drive_id): "the drive's TPDO1",
            tpdo_cob_id(2, drive_id): "the drive's TPDO2",
            rpdo_cob_id(1, drive_id): "the drive's RPDO1",
            sdo_tx_cob_id(drive_id): "the drive's SDO response",
            sdo_rx_cob_id(drive_id): "the drive's SDO request",
            heartbeat_cob_id(drive_id): "the drive's heartbeat",
            heartbeat_cob_id(sensor_id): "the sensor's own heartbeat",
        }
        if cob_id in taken:
            raise t.fail("cob_id", f"0x{cob_id:03X} is already used by {taken[cob_id]}")
    size = sensor.bits // 8
    offset = sensor.byte_offset
    if isinstance(offset, bool) or not isinstance(offset, int):
        raise t.fail("byte_offset", f"expected an integer, {t.got('byte_offset')}")
    if not 0 <= offset <= 8 - size:
        raise t.fail(
            "byte_offset",
            f"a {sensor.bits}-bit value at byte_offset {offset} does not fit in an "
            f"8-byte CAN frame (byte_offset must be 0..{8 - size})",
        )
    t.int_("heartbeat_timeout_ms", 0)
