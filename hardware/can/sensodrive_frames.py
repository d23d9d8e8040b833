"""The SensoDrive SENSO-Wheel's vendor frames (not CANopen): layouts and drive units ↔ SI.

Pure functions and constants for a SensoDrive driver and a simulated SensoDrive to share, so
both read the same bytes the same way. The facts are those of the two public clients
(tud-hri/joan, lflipse/gt-state-feedback-observer) as gathered in the team's
``docs/sensodrive-protocol.md``; the vendor's manual is not public. Parsers raise only
:class:`~hardware.can.frames.FrameError`; encoders raise it for a value the field cannot hold
(never wrap or clip silently: a wrapped torque is a torque of the other sign).

Every request to ``0x20n`` is answered by one frame at ``0x21n``; 11-bit identifiers,
little-endian fields, 1 Mbit/s:

==========  ===  ==========  ============================================================
request     DLC  reply       content
``0x200``   8    ``0x210``   state command, end stop (int16, degrees, ±), two torque
                             limits (uint8, percent: between and beyond the end stops);
                             the reply's byte 0 is the state
``0x201``   8    ``0x211``   torque, friction (int16, mN·m), damping (int16, mN·m per
                             rpm), stiffness (int16, mN·m per degree); the reply: angle
                             (int32, 0.009° increments), rate (int16, rpm), torque
                             (int16, mN·m)
``0x20A``   2    ``0x21A``   the optional hand-torque sensor: two voltages (int16,
                             2048 counts = 10 V; B at bytes 2–3, A at bytes 4–5)
==========  ===  ==========  ============================================================

Values here are in the drive's own direction: which way is positive for the driver is the
rig's ``sign`` (the clients' evidence points to clockwise as seen by the driver, the opposite
of Steerlab's convention), applied by the driver, not by these functions. Encoders round to
the nearest step (the clients truncate with ``int()``; rounding halves the worst error and
renders the Pronker wheel's 4.2 N·m/rad and 2 N·m·s/rad as the clients do: 73 and 209).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

from .frames import FrameError

# -- identifiers --------------------------------------------------------------------------------

STATE_REQUEST_ID = 0x200
WHEEL_COMMAND_ID = 0x201
HAND_SENSOR_REQUEST_ID = 0x20A
PEDAL_REQUEST_ID = 0x20C
REPLY_OFFSET = 0x10
STATE_REPLY_ID = STATE_REQUEST_ID + REPLY_OFFSET
WHEEL_REPLY_ID = WHEEL_COMMAND_ID + REPLY_OFFSET
HAND_SENSOR_REPLY_ID = HAND_SENSOR_REQUEST_ID + REPLY_OFFSET
BITRATE = 1_000_000


def reply_id(request_id: int) -> int:
    """The identifier the drive answers a request on."""
    return request_id + REPLY_OFFSET


class Command(IntEnum):
    """Byte 0 of ``0x200``."""

    OFF = 0x10
    KEEP = 0x11  # no transition: a plain state request
    READY = 0x12
    ON = 0x14
    CLEAR_ERROR = 0x1F


class State(IntEnum):
    """Byte 0 of ``0x210``."""

    OFF = 0x10
    READY = 0x12
    ON = 0x14
    ERROR = 0x18


# -- units --------------------------------------------------------------------------------------

#: One angle increment: 40 000 per turn.
RAD_PER_ANGLE_INCREMENT = math.radians(0.009)
#: Torque and friction: 1 mN·m.
NM_PER_TORQUE_LSB = 1e-3
#: Damping: 1 mN·m per rpm, in N·m·s/rad.
NMS_PER_RAD_PER_DAMPING_LSB = 1e-3 * 60.0 / (2.0 * math.pi)
#: Stiffness: 1 mN·m per degree, in N·m/rad.
NM_PER_RAD_PER_STIFFNESS_LSB = 1e-3 * 180.0 / math.pi
#: The rate field: 1 rpm, in rad/s (coarse: 0.105 rad/s).
RAD_S_PER_RATE_LSB = 2.0 * math.pi / 60.0
#: The hand-torque sensor's voltages: 2048 counts = 10 V.
VOLTS_PER_SENSOR_COUNT = 10.0 / 2048.0

_INT16 = (-0x8000, 0x7FFF)
_INT32 = (-0x8000_0000, 0x7FFF_FFFF)
_UINT8 = (0, 0xFF)


def _steps(value: float, per_step: float, limits: tuple[int, int], field: str) -> int:
    if not math.isfinite(value):
        raise FrameError(f"{field}: {value!r} is not a finite number")
    n = round(value / per_step)
    if not limits[0] <= n <= limits[1]:
        lo, hi = (x * per_step for x in limits)
        raise FrameError(f"{field}: {value:g} is outside what the field holds ({lo:g} to {hi:g})")
    return n


def _payload(data: bytes | bytearray, size: int, what: str) -> bytes:
    data = bytes(data)
    if len(data) < size:
        raise FrameError(f"{what}: {len(data)} data bytes, at least {size} expected")
    return data[:size]


# -- 0x200 / 0x210: state -----------------------------------------------------------------------


@dataclass(frozen=True)
class StateCommand:
    """A ``0x200`` frame: every one carries the end stop and the torque limits."""

    command: Command
    end_stop_deg: int = 360
    torque_limit_pct: int = 200  # between the end stops
    torque_limit_beyond_pct: int = 200  # beyond them


def encode_state_command(c: StateCommand) -> bytes:
    end = _steps(float(c.end_stop_deg), 1.0, (0, _INT16[1]), "end stop (degrees)")
    lim = _steps(float(c.torque_limit_pct), 1.0, _UINT8, "torque limit (%)")
    beyond = _steps(float(c.torque_limit_beyond_pct), 1.0, _UINT8, "torque limit beyond (%)")
    return struct.pack("<BBhBBBB", int(c.command), 0, end, 0, 0, lim, beyond)


def decode_state_command(data: bytes | bytearray) -> StateCommand:
    cmd, _, end, _, _, lim, beyond = struct.unpack("<BBhBBBB", _payload(data, 8, "0x200"))
    try:
        command = Command(cmd)
    except ValueError:
        raise FrameError(f"0x200: unknown state command 0x{cmd:02X}") from None
    return StateCommand(command, end, lim, beyond)


def encode_state_reply(state: State | int, error_info: int = 0) -> bytes:
    """A ``0x210`` frame; bytes 2–3 carry error information whose meaning is unknown."""
    return struct.pack("<BBHxxxx", int(state), 0, error_info & 0xFFFF)


def decode_state_reply(data: bytes | bytearray) -> tuple[State | int, int]:
    """The state (a :class:`State`, or the raw byte when it is none of them) and bytes 2–3."""
    raw, _, info = struct.unpack("<BBH", _payload(data, 4, "0x210"))
    try:
        return State(raw), info
    except ValueError:
        return raw, info


# -- 0x201 / 0x211: the wheel -------------------------------------------------------------------


@dataclass(frozen=True)
class WheelCommand:
    """A ``0x201`` frame in SI units (the drive's direction): the torque to apply, and the
    friction, damping and spring the drive renders itself."""

    torque_nm: float = 0.0
    friction_nm: float = 0.0
    damping_nms_per_rad: float = 0.0
    stiffness_nm_per_rad: float = 0.0


def encode_wheel_command(c: WheelCommand) -> bytes:
    return struct.pack(
        "<hhhh",
        _steps(c.torque_nm, NM_PER_TORQUE_LSB, _INT16, "torque (N·m)"),
        _steps(c.friction_nm, NM_PER_TORQUE_LSB, _INT16, "friction (N·m)"),
        _steps(c.damping_nms_per_rad, NMS_PER_RAD_PER_DAMPING_LSB, _INT16, "damping (N·m·s/rad)"),
        _steps(c.stiffness_nm_per_rad, NM_PER_RAD_PER_STIFFNESS_LSB, _INT16, "stiffness (N·m/rad)"),
    )


def decode_wheel_command(data: bytes | bytearray) -> WheelCommand:
    t, f, b, k = struct.unpack("<hhhh", _payload(data, 8, "0x201"))
    return WheelCommand(
        t * NM_PER_TORQUE_LSB,
        f * NM_PER_TORQUE_LSB,
        b * NMS_PER_RAD_PER_DAMPING_LSB,
        k * NM_PER_RAD_PER_STIFFNESS_LSB,
    )


@dataclass(frozen=True)
class WheelReply:
    """A ``0x211`` frame in SI units (the drive's direction). ``torque_nm`` is what the drive
    reports; whether it is the command, the motor's output or a measurement is unknown."""

    angle_rad: float
    rate_rad_s: float
    torque_nm: float


def encode_wheel_reply(r: WheelReply) -> bytes:
    return struct.pack(
        "<ihh",
        _steps(r.angle_rad, RAD_PER_ANGLE_INCREMENT, _INT32, "angle (rad)"),
        _steps(r.rate_rad_s, RAD_S_PER_RATE_LSB, _INT16, "rate (rad/s)"),
        _steps(r.torque_nm, NM_PER_TORQUE_LSB, _INT16, "torque (N·m)"),
    )


def decode_wheel_reply(data: bytes | bytearray) -> WheelReply:
    a, w, t = struct.unpack("<ihh", _payload(data, 8, "0x211"))
    return WheelReply(a * RAD_PER_ANGLE_INCREMENT, w * RAD_S_PER_RATE_LSB, t * NM_PER_TORQUE_LSB)


# -- 0x20A / 0x21A: the hand-torque sensor ------------------------------------------------------

HAND_SENSOR_REQUEST = bytes(2)


def encode_hand_sensor_reply(u_a_volts: float, u_b_volts: float) -> bytes:
    return struct.pack(
        "<xxhhxx",
        _steps(u_b_volts, VOLTS_PER_SENSOR_COUNT, _INT16, "voltage B (V)"),
        _steps(u_a_volts, VOLTS_PER_SENSOR_COUNT, _INT16, "voltage A (V)"),
    )


def decode_hand_sensor_reply(data: bytes | bytearray) -> tuple[float, float]:
    """The sensor's two voltages (A, B), in V."""
    b, a = struct.unpack("<xxhh", _payload(data, 6, "0x21A"))
    return a * VOLTS_PER_SENSOR_COUNT, b * VOLTS_PER_SENSOR_COUNT
