"""What the CAN tests see on the wire: frames as (COB-ID, hex bytes), the expedited SDO
exchanges with node 5, and waiting for a condition the bus threads bring about."""

from __future__ import annotations

import math
import time

import can

U8, U16, U32 = "2f", "2b", "23"  # expedited download of 1, 2, 4 bytes (CiA 301)


def drain(bus: can.BusABC, timeout: float = 0.02, max_s: float = math.inf) -> list[tuple[int, str]]:
    """Frames until the bus is quiet for ``timeout`` (or ``max_s`` passed: heartbeats)."""
    frames = []
    end = time.monotonic() + max_s
    while time.monotonic() < end and (msg := bus.recv(timeout)) is not None:
        frames.append((msg.arbitration_id, msg.data.hex(" ")))
    return frames


def f(cob_id: int, data: str) -> tuple[int, str]:
    return (cob_id, data.lower())


def sdo_write(index_lo_hi: str, sub: str, cmd_and_value: tuple[str, str]) -> list:
    """Expedited download request (0x605) and its confirmation (0x585)."""
    cmd, value = cmd_and_value
    return [
        f(0x605, f"{cmd} {index_lo_hi} {sub} {value}"),
        f(0x585, f"60 {index_lo_hi} {sub} 00 00 00 00"),
    ]


def sdo_read(index_lo_hi: str, sub: str, answer: str) -> list:
    return [f(0x605, f"40 {index_lo_hi} {sub} 00 00 00 00"), f(0x585, answer)]


def wait_for(predicate, timeout: float = 1.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.002)
    return predicate()
