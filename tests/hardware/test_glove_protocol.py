"""The wire format against the spec (docs/glove-protocol.md), not against itself."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from steerlab.hardware.glove import protocol as p
from steerlab.hardware.glove.protocol import crc16_ccitt_false, encode_frame


def crc_bitwise(data: bytes) -> int:
    """The spec's bitwise reference, written out independently of the module."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def test_crc_check_value():
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert crc_bitwise(b"123456789") == 0x29B1


@given(st.binary(max_size=800))
def test_crc_matches_bitwise_reference(data):
    assert crc16_ccitt_false(data) == crc_bitwise(data)


def test_force_frame_golden_bytes():
    # seq 258, device time 1_000_000 us, left 1000, right 70_000 -- the doc's example.
    covered = bytes(
        [
            0x01,  # version
            0x10,  # FORCE
            0x0E, 0x00,  # payload length 14
            0x02, 0x01,  # sequence 0x0102
            0x40, 0x42, 0x0F, 0x00,  # 1_000_000 = 0x000F4240
            0xE8, 0x03, 0x00, 0x00,  # 1000
            0x70, 0x11, 0x01, 0x00,  # 70_000 = 0x00011170
        ]
    )  # fmt: skip
    expected = b"\xa5\x5a" + covered + b"\xe5\x15"  # CRC 0x15E5, low byte first
    assert crc_bitwise(covered) == 0x15E5
    assert encode_frame(258, 1_000_000, 1000, 70_000) == expected
    assert expected.hex(" ") == "a5 5a 01 10 0e 00 02 01 40 42 0f 00 e8 03 00 00 70 11 01 00 e5 15"


def test_force_map_frame_layout():
    left = bytes(range(256)) + bytes(93)
    right = bytes([7]) * 349
    frame = encode_frame(65535 + 3, 2**32 + 5, 0, p.FORCE_RAW_MAX, left, right)
    assert len(frame) == 720
    assert frame[:6] == bytes([0xA5, 0x5A, 0x01, 0x11, 0xC8, 0x02])  # length 712 = 0x02C8
    assert frame[6:8] == bytes([0x02, 0x00])  # sequence reduced modulo 2**16
    assert frame[8:12] == bytes([0x05, 0, 0, 0])  # device time reduced modulo 2**32
    assert frame[12:16] == bytes(4)
    assert frame[16:20] == bytes([0xFF, 0xFF, 0xFF, 0x00])
    assert frame[20:369] == left
    assert frame[369:718] == right
    assert frame[718:] == crc_bitwise(frame[2:718]).to_bytes(2, "little")


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"left_raw": p.FORCE_RAW_MAX + 1}, "left_raw"),
        ({"right_raw": -1}, "right_raw"),
        ({"cells_left": bytes(349)}, "both"),
        ({"cells_left": bytes(348), "cells_right": bytes(349)}, "cells_left: expected 349"),
        ({"cells_left": bytes(349), "cells_right": [256] * 349}, "cells_right"),
    ],
)
def test_encoder_refuses_invalid_input(kwargs, message):
    args = {"sequence": 0, "device_time_us": 0, "left_raw": 0, "right_raw": 0, **kwargs}
    with pytest.raises(ValueError, match=message):
        encode_frame(**args)


def test_encoder_can_send_out_of_range_totals_for_fault_injection():
    frame = encode_frame(0, 0, p.FORCE_RAW_MAX + 1, 0, validate=False)
    assert frame[12:16] == bytes([0, 0, 0, 1])
