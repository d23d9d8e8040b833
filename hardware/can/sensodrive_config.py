"""Rig configuration of a SensoDrive SENSO-Wheel (``[drive] kind = "sensodrive"``): the
``[drive]``, ``[drive.torque_sensor]`` and ``[safety]`` tables of a rig TOML file.

The protocol facts behind the fields (and what is only inferred) are in the team's
``docs/sensodrive-protocol.md``; the frames are :mod:`hardware.can.sensodrive_frames`. As for the
CiA 402 drive, every value is checked when the config is built, so a wrong rig file fails at
load time with a :class:`~hardware.can.config.ConfigError` naming the file, table and field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import can

from .config import (
    _PYTHON,
    CAN_BITRATES,
    MAX_BUS_LOAD,
    UDP_LOOPBACK,
    ConfigError,
    SafetyConfig,
    _Check,
    _frame_bits,
    _known,
    _table,
)
from .sensodrive_frames import NM_PER_TORQUE_LSB, RAD_PER_ANGLE_INCREMENT

HandTorqueSource = Literal["hand_sensor", "reconstructed", "none"]
HAND_TORQUE_SOURCES: tuple[str, ...] = ("hand_sensor", "reconstructed", "none")

#: Loop rates the driver supports: the public clients ran 100 Hz to 1 kHz; a faster loop would
#: send the next 0x201 before the ~1 ms the drive's answer can take (docs/sensodrive-protocol.md).
MIN_LOOP_RATE_HZ = 100.0
MAX_LOOP_RATE_HZ = 1000.0
_INT16_MAX = 0x7FFF
_UINT8_LIMIT_MAX = 254  # the clients' GUI spin box stops there; 255 is left alone
#: Largest torque the 0x201 torque field holds (int16 mN·m).
MAX_FIELD_TORQUE_NM = _INT16_MAX * NM_PER_TORQUE_LSB

# Bits per cycle on the wire (worst case, with stuffing): 0x201 + 0x211 always; with the hand
# sensor 0x20A (2 data bytes) + 0x21A; 0x200 + 0x210 once every state_poll_cycles.
_WHEEL_BITS = _frame_bits(8) + _frame_bits(8)
_HAND_SENSOR_BITS = _frame_bits(2) + _frame_bits(8)
_STATE_BITS = _frame_bits(8) + _frame_bits(8)

# Which [drive.torque_sensor] fields belong to which source: a field of the other source is
# an error, not silently ignored (a calibration typed under the wrong source would be lost).
_HAND_SENSOR_FIELDS = ("sensitivity_a", "sensitivity_b", "supply_v", "sign", "rim_inertia_kgm2")
_RECONSTRUCTED_FIELDS = ("inertia_kgm2", "coulomb_nm", "gravity_nm", "filter_hz")


@dataclass(frozen=True)
class HandTorqueConfig:
    """Where the driver (hand) torque comes from on a SENSO-Wheel.

    - ``"hand_sensor"``: the optional hand-torque sensor ("SensoWheel LMS", 0x20A/0x21A). Its
      two voltages give T = (U_a − U_b) / ((S_a − S_b)·U_v/5) (the sensor manual's formula as
      the joan client uses it), in the drive's direction. The joan client reads T as the
      torque the hands put on the wheel (it adds the rim's J·θ̈ to get the hands' torque);
      Steerlab records the torque the wheel exerts on the hands, so ``sign`` is −1 by default
      (+1 for a sensor wired or mounted the other way round: docs/sensodrive.md, check 5).
      The sensor sits below the rim: ``rim_inertia_kgm2`` (the rim, hub and any added mass
      above it) is subtracted as J·θ̈, since the sensor also carries the torque that
      accelerates them (θ̈ from the angle through a 4th-order low-pass at 50 Hz, about 8 ms
      late).
    - ``"reconstructed"``: no sensor; the driver torque is computed from the wheel model a rig
      check measures (``inertia_kgm2``, ``coulomb_nm``, ``gravity_nm``), the torque the host
      itself commanded, and the angle's derivatives through a filter at ``filter_hz``. Errors
      of the model become errors of the driver torque.
    - ``"none"``: no driver torque; a session refuses to start, a hands-off rig check can run.
    """

    source: HandTorqueSource = "none"
    # hand_sensor
    sensitivity_a: float = -1.0 / 14.696
    sensitivity_b: float = 1.0 / 14.832
    supply_v: float = 5.0
    sign: int = -1
    rim_inertia_kgm2: float = 0.0
    # reconstructed
    inertia_kgm2: float | None = None  # None: [drive] wheel_inertia_kgm2
    coulomb_nm: float = 0.0
    gravity_nm: float = 0.0
    filter_hz: float = 40.0

    @property
    def v_per_nm(self) -> float:
        """Volts of U_a − U_b per N·m of torque in the drive's direction (sensor sign not
        applied): (S_a − S_b)·U_v/5."""
        return (self.sensitivity_a - self.sensitivity_b) * self.supply_v / 5.0


@dataclass(frozen=True, kw_only=True)
class SensoDriveConfig:
    """One SENSO-Wheel on one CAN bus, in wheel units (:mod:`hardware.interfaces`)."""

    kind: ClassVar[str] = "sensodrive"

    interface: str
    channel: str | int
    #: The physical wheel's inertia, added masses included. The drive has no inertia field:
    #: this is the inertia the subject feels, whatever the protocol's virtual wheel says.
    wheel_inertia_kgm2: float
    safety: SafetyConfig
    bitrate: int = 1_000_000
    loop_rate_hz: float = 1000.0
    # The clients' evidence (docs/sensodrive-protocol.md, "Sign conventions") is that the drive's
    # positive direction is clockwise as seen by the driver; Steerlab's is counter-clockwise.
    sign: int = -1
    end_stop_deg: int = 180
    torque_limit_percent: int = 100
    torque_limit_beyond_percent: int = 100
    #: What 100 % of the torque limit bytes means, in N·m. Not documented anywhere public: the
    #: wheel's stated 20 N·m peak at the clients' 200 % maximum suggests 10 N·m (an inference;
    #: measure it on the wheel).
    full_scale_torque_nm: float = 10.0
    friction_nm: float = 0.0
    reply_timeout_ms: float = 0.8
    max_missed_replies: int = 20
    state_timeout_s: float = 0.5
    state_poll_cycles: int = 10
    torque_sensor: HandTorqueConfig = field(default_factory=HandTorqueConfig)
    source: str = field(default=_PYTHON, compare=False)

    def __post_init__(self) -> None:
        _validate(self)

    def describe(self) -> dict[str, Any]:
        """The fields that identify this drive, for a session file's rig record."""
        return {
            "drive_kind": self.kind,
            "drive_interface": self.interface,
            "drive_channel": str(self.channel),
            "drive_sign": self.sign,
            "drive_torque_sensor": self.torque_sensor.source,
            "drive_wheel_inertia_kgm2": self.wheel_inertia_kgm2,
        }

    @property
    def angle_quantum_rad(self) -> float:
        """The smallest angle step the drive reports: 0.009° (40 000 per turn)."""
        return RAD_PER_ANGLE_INCREMENT

    @property
    def period_s(self) -> float:
        return 1.0 / self.loop_rate_hz

    @property
    def has_hand_sensor(self) -> bool:
        return self.torque_sensor.source == "hand_sensor"

    @property
    def hand_sensor_v_per_nm(self) -> float:
        """Volts of U_a − U_b per N·m (drive direction) of the hand sensor's calibration."""
        return self.torque_sensor.v_per_nm

    @property
    def model_inertia_kgm2(self) -> float:
        """The inertia the reconstruction subtracts (``[drive.torque_sensor] inertia_kgm2``,
        else ``wheel_inertia_kgm2``)."""
        i = self.torque_sensor.inertia_kgm2
        return self.wheel_inertia_kgm2 if i is None else float(i)

    @property
    def torque_limit_nm(self) -> float:
        """The drive's own torque limit between the end stops, in N·m (via full scale)."""
        return self.torque_limit_percent / 100.0 * self.full_scale_torque_nm

    @property
    def cycle_bits(self) -> float:
        """Worst-case bits one control cycle puts on the bus, the state poll averaged in."""
        bits = _WHEEL_BITS + _STATE_BITS / self.state_poll_cycles
        return bits + (_HAND_SENSOR_BITS if self.has_hand_sensor else 0)

    @property
    def bus_load(self) -> float:
        """Worst-case fraction of the bus the control cycle uses at ``loop_rate_hz``."""
        return self.cycle_bits * self.loop_rate_hz / self.bitrate


def sensodrive_config(document: dict[str, Any], source: str) -> SensoDriveConfig:
    """The :class:`SensoDriveConfig` of a parsed rig file (its ``[drive]`` with
    ``[drive.torque_sensor]``, and ``[safety]``; other tables are left to their loaders).

    :raises ConfigError: a table or field is missing, unknown or wrong.
    """
    drive = _table(document, "drive", source, required=True)
    safety_table = _table(document, "safety", source, required=True)
    assert drive is not None and safety_table is not None  # required: _table raised otherwise
    sensor_table = _table(drive, "torque_sensor", source, required=False, section="drive")
    # ``kind`` chose this module (hardware.drives); it is not a setting of the drive.
    drive = {k: v for k, v in drive.items() if k not in ("torque_sensor", "kind")}

    sensor = _hand_torque(sensor_table, source)
    safety = SafetyConfig(**_known(safety_table, SafetyConfig, source, "safety"))
    kwargs = _known(
        drive, SensoDriveConfig, source, "drive", exclude={"safety", "torque_sensor", "source"}
    )
    return SensoDriveConfig(**kwargs, safety=safety, torque_sensor=sensor, source=source)


def _hand_torque(table: dict[str, Any] | None, source: str) -> HandTorqueConfig:
    section = "drive.torque_sensor"
    if table is None:
        return HandTorqueConfig()
    kwargs = _known(table, HandTorqueConfig, source, section)
    if "source" not in kwargs:
        raise ConfigError(
            source,
            section,
            "source",
            "required field is missing: 'hand_sensor', 'reconstructed' or 'none'",
        )
    chosen = kwargs["source"]
    if chosen in HAND_TORQUE_SOURCES:
        belongs = {"hand_sensor": _HAND_SENSOR_FIELDS, "reconstructed": _RECONSTRUCTED_FIELDS}
        for key in kwargs:
            if key == "source":
                continue
            owner = next(s for s, names in belongs.items() if key in names)
            if owner != chosen:
                raise ConfigError(
                    source, section, key, f"only for source = {owner!r}, not {chosen!r}"
                )
    return HandTorqueConfig(**kwargs)


# -- validation ---------------------------------------------------------------------------------


def _validate(cfg: SensoDriveConfig) -> None:
    src = cfg.source
    c = _Check(cfg, src, "drive")
    c.choice("interface", tuple(sorted(can.interfaces.VALID_INTERFACES | {UDP_LOOPBACK})))
    if isinstance(cfg.channel, bool) or not isinstance(cfg.channel, str | int) or cfg.channel == "":
        raise c.fail("channel", f"expected a non-empty string or an integer, {c.got('channel')}")
    c.choice("bitrate", CAN_BITRATES)
    rate = c.float_("loop_rate_hz")
    if not MIN_LOOP_RATE_HZ <= rate <= MAX_LOOP_RATE_HZ:
        raise c.fail(
            "loop_rate_hz",
            f"expected {MIN_LOOP_RATE_HZ:g} to {MAX_LOOP_RATE_HZ:g} Hz, got {rate:g}",
        )
    c.choice("sign", (1, -1))
    c.float_("wheel_inertia_kgm2")
    full_scale = c.float_("full_scale_torque_nm")
    limit = c.int_("torque_limit_percent", 0, _UINT8_LIMIT_MAX)
    c.int_("torque_limit_beyond_percent", 0, _UINT8_LIMIT_MAX)
    friction = c.float_("friction_nm", positive=False)
    if not 0.0 <= friction <= MAX_FIELD_TORQUE_NM:
        raise c.fail("friction_nm", f"expected 0 to {MAX_FIELD_TORQUE_NM:g} N·m, got {friction:g}")
    period_ms = 1000.0 / rate
    timeout = c.float_("reply_timeout_ms")
    if timeout >= period_ms:
        raise c.fail(
            "reply_timeout_ms",
            f"must be shorter than the loop period ({period_ms:g} ms at loop_rate_hz "
            f"{rate:g}), got {timeout:g}",
        )
    c.int_("max_missed_replies", 1)
    c.float_("state_timeout_s")
    c.int_("state_poll_cycles", 1)
    if not isinstance(cfg.safety, SafetyConfig):
        raise ConfigError(src, "safety", None, "expected a [safety] table")
    if not isinstance(cfg.torque_sensor, HandTorqueConfig):
        raise ConfigError(src, "drive.torque_sensor", None, "expected a table")

    s = _Check(cfg.safety, src, "safety")
    max_t = s.float_("max_torque_nm")
    s.float_("max_slew_nm_per_s")
    soft = s.float_("soft_angle_limit_deg")
    end_stop = c.int_("end_stop_deg", 1, _INT16_MAX)
    if end_stop <= soft:
        raise c.fail(
            "end_stop_deg",
            f"must lie beyond [safety] soft_angle_limit_deg ({soft:g}°), got {end_stop}",
        )
    allowed = limit / 100.0 * full_scale
    if max_t > allowed:
        raise s.fail(
            "max_torque_nm",
            f"{max_t:g} N·m is more than the drive's own torque limit, [drive] "
            f"torque_limit_percent {limit} % of full_scale_torque_nm {full_scale:g} N·m = "
            f"{allowed:g} N·m: the drive would clip the command without telling",
        )
    if max_t > MAX_FIELD_TORQUE_NM:
        raise s.fail(
            "max_torque_nm",
            f"{max_t:g} N·m does not fit the 0x201 torque field (≤ {MAX_FIELD_TORQUE_NM:g} N·m)",
        )

    _validate_hand_torque(cfg, rate)

    if cfg.bus_load > MAX_BUS_LOAD:
        need = math.ceil(cfg.cycle_bits * rate / MAX_BUS_LOAD)
        raise c.fail(
            "bitrate",
            f"{cfg.bitrate} bit/s cannot carry one control cycle (~{cfg.cycle_bits:.0f} bits) "
            f"at loop_rate_hz {rate:g} within {MAX_BUS_LOAD:.0%} bus load "
            f"(needs ≥ {need} bit/s)",
        )


def _validate_hand_torque(cfg: SensoDriveConfig, rate: float) -> None:
    t = _Check(cfg.torque_sensor, cfg.source, "drive.torque_sensor")
    chosen = t.choice("source", HAND_TORQUE_SOURCES)
    if chosen == "hand_sensor":
        for name in ("sensitivity_a", "sensitivity_b"):
            t.float_(name, positive=False)
        t.float_("supply_v")
        t.choice("sign", (1, -1))
        _non_negative(t, "rim_inertia_kgm2")
        if cfg.torque_sensor.v_per_nm == 0.0:
            raise t.fail(
                "sensitivity_b", "sensitivity_a and sensitivity_b are equal: no torque is seen"
            )
    elif chosen == "reconstructed":
        if cfg.torque_sensor.inertia_kgm2 is not None:
            t.float_("inertia_kgm2")
        _non_negative(t, "coulomb_nm")
        t.float_("gravity_nm", positive=False)
        f = t.float_("filter_hz")
        if f >= rate / 2.0:
            raise t.fail(
                "filter_hz",
                f"must be below half the loop rate ({rate / 2.0:g} Hz at loop_rate_hz "
                f"{rate:g}), got {f:g}",
            )


def _non_negative(t: _Check, name: str) -> float:
    value = t.float_(name, positive=False)
    if value < 0:
        raise t.fail(name, f"expected a number ≥ 0, got {value:g}")
    return value
