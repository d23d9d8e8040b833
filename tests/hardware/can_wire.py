"""What the CAN tests see on the wire: frames as (COB-ID, hex bytes), the expedited SDO
exchanges with node 5, the node-5 drive those frames are worked out for, and waiting for a
condition the bus threads bring about."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import can

from steerlab.hardware.can import DriveConfig, SafetyConfig

U8, U16, U32 = "2f", "2b", "23"  # expedited download of 1, 2, 4 bytes (CiA 301)


HOST_HEARTBEAT = 0x77F  # node 127, the host's heartbeat the drive consumes (0x1016)


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


def node5_config(channel: str, **changes) -> DriveConfig:
    """The drive whose frames the exchange and sensor-node tests work out by hand: node 5,
    4096 counts per revolution, 10 N·m rated, gear 2 and sign −1 (so every conversion has to
    get both right); generous timeouts, as these tests check behaviour, not timing."""
    cfg = DriveConfig(
        node_id=5,
        interface="virtual",
        channel=channel,
        bitrate=1_000_000,
        encoder_counts_per_rev=4096,
        rated_torque_nm=10.0,
        gear_ratio=2.0,
        sign=-1,
        safety=SafetyConfig(max_torque_nm=8.0, max_slew_nm_per_s=100.0, soft_angle_limit_deg=360.0),
        heartbeat_ms=50,
        heartbeat_timeout_ms=150,
        # the host's heartbeat (0x77F) is rarer than drain()'s 20-ms quiet gap
        host_heartbeat_ms=60,
        host_heartbeat_timeout_ms=100,
        loop_rate_hz=20.0,
        tpdo_timeout_ms=45.0,
        sdo_timeout_s=2.0,  # a loaded machine answers late, not a slow drive
    )
    return replace(cfg, **changes)
