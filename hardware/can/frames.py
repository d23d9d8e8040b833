"""CANopen frame layouts used by the drive stack (CiA 301 communication, CiA 402 drive profile).

Pure functions and constants, shared by the driver (:mod:`hardware.can.cia402`) and the simulated
nodes (:mod:`hardware.can.sim_node`, :mod:`hardware.can.sim_sensor`) so both sides read the same
bytes the same way. Parsers raise only :class:`FrameError` on malformed payloads.

COB-IDs (11-bit, predefined connection set, node id ``n``):

==============  ============  ==============================================
NMT             0x000         [command, node id]
SYNC            0x080         no data (host is the SYNC producer)
EMCY            0x080 + n     [code lo, code hi, error register, 5 vendor bytes]
TPDO1 / TPDO2   0x180 / 0x280 + n
RPDO1           0x200 + n
SDO response    0x580 + n
SDO request     0x600 + n
Heartbeat       0x700 + n     [NMT state]
Torque sensor   0x180 + s     sensor node ``s`` (``[drive.torque_sensor] source = "node"``):
                (or cob_id)   signed value, 16 or 32 bit little-endian, at byte_offset
==============  ============  ==============================================
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum, IntEnum

# -- COB-IDs ------------------------------------------------------------------------------------

NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080


def emcy_cob_id(node_id: int) -> int:
    return 0x080 + node_id


def tpdo_cob_id(number: int, node_id: int) -> int:
    return 0x080 + 0x100 * number + node_id


def rpdo_cob_id(number: int, node_id: int) -> int:
    return 0x100 + 0x100 * number + node_id


def sdo_tx_cob_id(node_id: int) -> int:
    """Server → client (the drive's answers)."""
    return 0x580 + node_id


def sdo_rx_cob_id(node_id: int) -> int:
    """Client → server (the host's requests)."""
    return 0x600 + node_id


def heartbeat_cob_id(node_id: int) -> int:
    return 0x700 + node_id


# PDO COB-ID (sub 1 of 0x14xx / 0x18xx) bit 31: PDO does not exist / is not valid.
PDO_INVALID = 0x8000_0000


class NmtCommand(IntEnum):
    START = 0x01
    STOP = 0x02
    PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """States as sent in the heartbeat."""

    BOOTUP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


# -- CiA 402 objects and state machine ----------------------------------------------------------

CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
MOTOR_RATED_TORQUE = 0x6076
TORQUE_ACTUAL = 0x6077
ERROR_CODE = 0x603F
MODE_CST = 10  # cyclic synchronous torque

ERROR_REGISTER = 0x1001
COMM_CYCLE_PERIOD = 0x1006
CONSUMER_HEARTBEAT = 0x1016  # sub 1..n: (producer node id << 16) | consumer time ms
PRODUCER_HEARTBEAT = 0x1017
ABORT_CONNECTION_OPTION = 0x6007  # CiA 402: reaction to a lost connection (heartbeat, bus-off)
EMCY_HEARTBEAT_ERROR = 0x8130  # CiA 301: life guard error or heartbeat error


class Controlword(IntEnum):
    """Device control commands (CiA 402 controlword bits 0–3 and 7)."""

    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007  # also "disable operation" from OPERATION ENABLED
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080  # acts on the rising edge of bit 7


class State402(Enum):
    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"
    UNKNOWN = "UNKNOWN"


# (mask, value) on the statusword, CiA 402 table "state coding".
_STATE_CODING: tuple[tuple[int, int, State402], ...] = (
    (0x4F, 0x00, State402.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State402.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State402.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State402.SWITCHED_ON),
    (0x6F, 0x27, State402.OPERATION_ENABLED),
    (0x6F, 0x07, State402.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State402.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State402.FAULT),
)

# Statusword the simulated drive reports in each state: the state coding plus bit 4 (voltage
# enabled) where the power stage is on and bit 9 (remote: controlled over the network).
STATUSWORD_OF: dict[State402, int] = {
    State402.NOT_READY_TO_SWITCH_ON: 0x0200,
    State402.SWITCH_ON_DISABLED: 0x0240,
    State402.READY_TO_SWITCH_ON: 0x0221,
    State402.SWITCHED_ON: 0x0233,
    State402.OPERATION_ENABLED: 0x0237,
    State402.QUICK_STOP_ACTIVE: 0x0217,
    State402.FAULT_REACTION_ACTIVE: 0x021F,
    State402.FAULT: 0x0208,
}


def decode_statusword(statusword: int) -> State402:
    for mask, value, state in _STATE_CODING:
        if statusword & mask == value:
            return state
    return State402.UNKNOWN


# -- PDO layouts --------------------------------------------------------------------------------


class FrameError(ValueError):
    """A received payload does not have the layout the protocol defines."""


_STRUCT_CODES = {
    (8, False): "B",
    (8, True): "b",
    (16, False): "H",
    (16, True): "h",
    (32, False): "I",
    (32, True): "i",
}


@dataclass(frozen=True)
class MappedObject:
    index: int
    subindex: int
    bits: int
    signed: bool
    name: str = ""

    @property
    def mapping_entry(self) -> int:
        """The value written to a PDO mapping sub-entry (0x16xx / 0x1Axx): index, sub, bits."""
        return self.index << 16 | self.subindex << 8 | self.bits


class PdoLayout:
    """Byte layout of one PDO: the mapped objects back to back, little-endian (CiA 301)."""

    def __init__(self, objects: Sequence[MappedObject]):
        self.objects = tuple(objects)
        try:
            codes = "".join(_STRUCT_CODES[(o.bits, o.signed)] for o in self.objects)
        except KeyError as exc:
            raise ValueError(f"only 8/16/32-bit objects can be mapped, got {exc}") from None
        self._struct = struct.Struct("<" + codes)
        if self._struct.size > 8:
            raise ValueError(f"PDO of {self._struct.size} bytes exceeds 8 bytes")

    @property
    def size(self) -> int:
        return self._struct.size

    def encode(self, values: Sequence[int]) -> bytes:
        """:raises FrameError: a value does not fit its object's width."""
        try:
            return self._struct.pack(*values)
        except struct.error as exc:
            raise FrameError(f"cannot encode {tuple(values)} into {self}: {exc}") from None

    def decode(self, data: bytes | bytearray) -> tuple[int, ...]:
        """Decode a received PDO. Extra trailing bytes are ignored, as CiA 301 allows.

        :raises FrameError: fewer bytes than the mapping needs.
        """
        if len(data) < self._struct.size:
            raise FrameError(f"PDO has {len(data)} bytes, mapping needs {self._struct.size}")
        return self._struct.unpack_from(data)

    def __repr__(self) -> str:
        names = ", ".join(o.name or f"0x{o.index:04X}:{o.subindex:02X}" for o in self.objects)
        return f"PdoLayout({names})"


@dataclass(frozen=True)
class SensorFrame:
    """The frame of a column torque sensor node: a signed little-endian integer of ``bits``
    (16 or 32) starting at byte ``byte_offset``. Other bytes (status, other channels of the
    amplifier) are not read; when encoding (the simulated sensor) they are zero.

    :raises ValueError: at construction, if the value does not fit in 8 bytes.
    """

    byte_offset: int
    bits: int

    def __post_init__(self) -> None:
        if self.bits not in (16, 32):
            raise ValueError(f"sensor value must be 16 or 32 bits, got {self.bits}")
        if not 0 <= self.byte_offset <= 8 - self.bits // 8:
            raise ValueError(
                f"a {self.bits}-bit value at byte {self.byte_offset} does not fit in 8 bytes"
            )

    @property
    def size(self) -> int:
        """Bytes up to the end of the value: the shortest frame that carries it."""
        return self.byte_offset + self.bits // 8

    def decode(self, data: bytes | bytearray) -> int:
        """The raw value. Trailing bytes after it are ignored, as in a PDO.

        :raises FrameError: the frame ends before the value does.
        """
        if len(data) < self.size:
            raise FrameError(
                f"sensor frame has {len(data)} bytes, the value needs "
                f"{self.size} ({self.bits} bits at byte {self.byte_offset})"
            )
        return int.from_bytes(data[self.byte_offset : self.size], "little", signed=True)

    def encode(self, raw: int) -> bytes:
        """``size`` bytes: zeros, then the value.

        :raises FrameError: ``raw`` does not fit in ``bits`` signed bits.
        """
        try:
            value = raw.to_bytes(self.bits // 8, "little", signed=True)
        except OverflowError:
            raise FrameError(f"{raw} does not fit in a signed {self.bits}-bit value") from None
        return bytes(self.byte_offset) + value


CONTROLWORD_OBJ = MappedObject(CONTROLWORD, 0, 16, False, "controlword")
TARGET_TORQUE_OBJ = MappedObject(TARGET_TORQUE, 0, 16, True, "target torque")
STATUSWORD_OBJ = MappedObject(STATUSWORD, 0, 16, False, "statusword")
POSITION_ACTUAL_OBJ = MappedObject(POSITION_ACTUAL, 0, 32, True, "position actual")
TORQUE_ACTUAL_OBJ = MappedObject(TORQUE_ACTUAL, 0, 16, True, "torque actual")
VELOCITY_ACTUAL_OBJ = MappedObject(VELOCITY_ACTUAL, 0, 32, True, "velocity actual")

RPDO1 = PdoLayout([CONTROLWORD_OBJ, TARGET_TORQUE_OBJ])
TPDO1 = PdoLayout([STATUSWORD_OBJ, POSITION_ACTUAL_OBJ, TORQUE_ACTUAL_OBJ])


def tpdo2_layout(sensor: MappedObject | None) -> PdoLayout:
    """Velocity actual, then the column torque sensor value when the drive carries it."""
    return PdoLayout([VELOCITY_ACTUAL_OBJ] + ([sensor] if sensor is not None else []))


# -- EMCY and heartbeat -------------------------------------------------------------------------

_EMCY_TEXT: dict[int, str] = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2000: "current",
    0x2100: "current, device input side",
    0x2200: "current inside the device",
    0x2300: "current, device output side",
    0x2310: "continuous over-current",
    0x2320: "short circuit / earth leakage",
    0x2330: "earth leakage",
    0x2340: "short circuit",
    0x3000: "voltage",
    0x3100: "mains voltage",
    0x3200: "voltage inside the device",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x3300: "output voltage",
    0x4000: "temperature",
    0x4100: "ambient temperature",
    0x4200: "device temperature",
    0x4210: "excess temperature, device",
    0x4300: "drive temperature",
    0x4310: "excess temperature, drive",
    0x5000: "device hardware",
    0x5400: "power section / output stage",
    0x6000: "device software",
    0x6100: "internal software",
    0x6200: "user software",
    0x6300: "data set",
    0x7000: "additional modules",
    0x7121: "motor blocked",
    0x7300: "sensor",
    0x7305: "incremental sensor 1 fault",
    0x8000: "monitoring",
    0x8100: "communication",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8200: "protocol error",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8250: "RPDO timeout",
    0x8400: "velocity / speed controller",
    0x8611: "following error",
    0x9000: "external error",
    0xF000: "additional functions",
    0xFF00: "device specific",
}


def emcy_text(code: int) -> str:
    """Text for an EMCY error code: the exact CiA 301/402 entry, else its group or class."""
    for mask in (0xFFFF, 0xFFF0, 0xFF00, 0xF000):
        text = _EMCY_TEXT.get(code & mask)
        if text is not None:
            return text if mask == 0xFFFF else f"{text} (0x{code:04X})"
    return f"unknown error code 0x{code:04X}"


@dataclass(frozen=True)
class Emcy:
    code: int
    error_register: int
    vendor_data: bytes
    timestamp: float = 0.0

    @property
    def is_reset(self) -> bool:
        """Code 0x00xx: the drive reports that its errors are cleared."""
        return self.code & 0xFF00 == 0

    @property
    def text(self) -> str:
        return emcy_text(self.code)

    def __str__(self) -> str:
        return (
            f"EMCY 0x{self.code:04X} ({self.text}), error register "
            f"0x{self.error_register:02X}, vendor data {self.vendor_data.hex() or '-'}"
        )


def parse_emcy(data: bytes | bytearray, timestamp: float = 0.0) -> Emcy:
    """CiA 301 EMCY: error code (U16), error register (U8), 5 manufacturer bytes.

    Shorter frames are accepted down to code + register, because a fault report must not be
    lost to a sloppy manufacturer layout.

    :raises FrameError: fewer than 3 or more than 8 bytes.
    """
    if not 3 <= len(data) <= 8:
        raise FrameError(f"EMCY must have 3 to 8 bytes, got {len(data)}")
    code, register = struct.unpack_from("<HB", data)
    return Emcy(code, register, bytes(data[3:]), timestamp)


def emcy_payload(code: int, error_register: int, vendor_data: bytes = b"") -> bytes:
    if len(vendor_data) > 5:
        raise ValueError("EMCY vendor data is at most 5 bytes")
    return struct.pack("<HB", code, error_register) + vendor_data.ljust(5, b"\x00")


def parse_heartbeat(data: bytes | bytearray) -> int:
    """NMT state byte of a heartbeat (bit 7, the node-guarding toggle bit, masked off).

    :raises FrameError: not exactly one byte.
    """
    if len(data) != 1:
        raise FrameError(f"heartbeat must have 1 byte, got {len(data)}")
    return data[0] & 0x7F


def nmt_state_name(state: int) -> str:
    try:
        return NmtState(state).name
    except ValueError:
        return f"0x{state:02X}"
