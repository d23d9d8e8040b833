"""Wire format of the glove acquisition unit (protocol version 1).

The normative description, with a byte table and an example frame, is docs/glove-protocol.md;
this module is its executable form. Everything is little-endian.

    offset  size  field
    0       2     sync            0xA5 0x5A
    2       1     version         1
    3       1     frame type      0x10 FORCE, 0x11 FORCE_MAP
    4       2     payload length  14 (FORCE) or 712 (FORCE_MAP): bytes from offset 6 up to the CRC
    6       2     sequence        uint16, +1 per sampled frame, wraps 65535 -> 0
    8       4     device time     uint32 microseconds, wraps every 2**32 us (about 71.6 min)
    12      4     left total      uint32 raw ADC counts, valid 0..FORCE_RAW_MAX (24-bit converter)
    16      4     right total     uint32, same
    20      698   (FORCE_MAP only) 349 left cells then 349 right cells, uint8 each
    end-2   2     CRC             CRC-16/CCITT-FALSE over bytes 2 .. end-3 (all but sync and CRC)
"""

from __future__ import annotations

import binascii
import struct
from collections.abc import Sequence
from typing import Final

SYNC: Final = b"\xa5\x5a"
PROTOCOL_VERSION: Final = 1

FRAME_FORCE: Final = 0x10
FRAME_FORCE_MAP: Final = 0x11

CELLS_PER_GLOVE: Final = 349  # Pronker et al. 2017: 349 sensing cells per glove
CELL_MAX: Final = 0xFF

FORCE_RAW_MAX: Final = 0xFF_FFFF  # totals come from a 24-bit converter in a uint32 field
SEQUENCE_MODULUS: Final = 1 << 16
DEVICE_TIME_MODULUS: Final = 1 << 32  # microseconds

NOMINAL_RATE_HZ: Final = 100.0

HEADER = struct.Struct("<2sBBH")  # sync, version, type, payload length
BODY = struct.Struct("<HIII")  # sequence, device time, left total, right total
CRC = struct.Struct("<H")

HEADER_LEN: Final = HEADER.size  # 6
CRC_LEN: Final = CRC.size  # 2

PAYLOAD_LEN: Final[dict[int, int]] = {
    FRAME_FORCE: BODY.size,  # 14
    FRAME_FORCE_MAP: BODY.size + 2 * CELLS_PER_GLOVE,  # 712
}
FRAME_LEN: Final[dict[int, int]] = {t: HEADER_LEN + n + CRC_LEN for t, n in PAYLOAD_LEN.items()}
MAX_FRAME_LEN: Final = max(FRAME_LEN.values())  # 720


def crc16_ccitt_false(data: bytes | bytearray | memoryview, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, xorout 0x0000.

    Check value: crc16_ccitt_false(b"123456789") == 0x29B1.
    """
    # binascii.crc_hqx is exactly this CRC when started at 0xFFFF, and runs in C.
    return binascii.crc_hqx(data, crc)


def encode_frame(
    sequence: int,
    device_time_us: int,
    left_raw: int,
    right_raw: int,
    cells_left: Sequence[int] | bytes | None = None,
    cells_right: Sequence[int] | bytes | None = None,
    *,
    validate: bool = True,
) -> bytes:
    """One complete frame, sync to CRC.

    Sequence and device time are reduced modulo their wrap, so a caller can pass a running count.
    With pressure maps (both or neither) the frame is FORCE_MAP, else FORCE.
    ``validate=False`` lets a simulator send totals above FORCE_RAW_MAX (still < 2**32) to
    exercise the receiver's range check; it raises ValueError otherwise for bad totals.
    """
    if (cells_left is None) != (cells_right is None):
        raise ValueError("pressure maps: give both cells_left and cells_right, or neither")
    limit = FORCE_RAW_MAX if validate else 0xFFFF_FFFF
    for name, value in (("left_raw", left_raw), ("right_raw", right_raw)):
        if not 0 <= value <= limit:
            raise ValueError(f"{name} must be in 0..{limit}, got {value}")

    body = BODY.pack(
        sequence % SEQUENCE_MODULUS, device_time_us % DEVICE_TIME_MODULUS, left_raw, right_raw
    )
    if cells_left is None:
        frame_type = FRAME_FORCE
    else:
        frame_type = FRAME_FORCE_MAP
        body += _cells(cells_left, "cells_left") + _cells(cells_right, "cells_right")

    covered = HEADER.pack(SYNC, PROTOCOL_VERSION, frame_type, len(body))[2:] + body
    return SYNC + covered + CRC.pack(crc16_ccitt_false(covered))


def _cells(cells: Sequence[int] | bytes | None, name: str) -> bytes:
    assert cells is not None
    try:
        raw = bytes(cells)  # raises ValueError for any value outside 0..255
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: cells must be integers 0..{CELL_MAX}") from exc
    if len(raw) != CELLS_PER_GLOVE:
        raise ValueError(f"{name}: expected {CELLS_PER_GLOVE} cells, got {len(raw)}")
    return raw
