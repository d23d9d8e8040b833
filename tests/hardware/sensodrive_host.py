"""A minimal SensoDrive host for the tests, written from the protocol notes
(``sensodrive-protocol.md``) with ``struct`` alone: it shares no code with Steerlab's codec
(``hardware/can/sensodrive_frames.py``) nor with the driver, so a mistake in either shows up
as a disagreement here instead of cancelling out.

Conversions are the public clients': SI → drive units with truncating ``int()``, little-endian
fields, torque in mN·m, damping in mN·m per rpm, stiffness in mN·m per degree, angle in
0.009° increments, rate in rpm. Every value here is in the drive's own direction.
"""

from __future__ import annotations

import math
import struct
import time

import can

OFF, READY, ON, ERROR = 0x10, 0x12, 0x14, 0x18
KEEP, CLEAR_ERROR = 0x11, 0x1F

# J-D's hand-torque sensor formula: T = (Ua − Ub) / ((Sa − Sb)·Uv/5)
SENSOR_SA = -1 / 14.696
SENSOR_SB = 1 / 14.832
SENSOR_UV = 5.0
VOLTS_PER_COUNT = 10.0 / 2048.0


def jd_hand_torque(u_a: float, u_b: float) -> float:
    """J-D's conversion of the sensor's two voltages to a torque (N·m)."""
    return (u_a - u_b) / ((SENSOR_SA - SENSOR_SB) * SENSOR_UV / 5.0)


def sensor_volts_per_nm() -> float:
    """The voltage difference per N·m that J-D's formula assumes."""
    return (SENSOR_SA - SENSOR_SB) * SENSOR_UV / 5.0


class Host:
    """Request/response over ``bus``: one request in flight, the reply is the next frame on
    the request's identifier + 0x10."""

    def __init__(self, bus: can.BusABC, timeout: float = 0.5):
        self.bus = bus
        self.timeout = timeout

    def request(self, can_id: int, data: bytes, timeout: float | None = None) -> bytes | None:
        self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
        end = time.monotonic() + (self.timeout if timeout is None else timeout)
        while (left := end - time.monotonic()) > 0:
            msg = self.bus.recv(left)
            if msg is not None and msg.arbitration_id == can_id + 0x10:
                return bytes(msg.data)
        return None

    def state(
        self,
        command: int,
        end_stop_deg: int = 360,
        limit_pct: int = 200,
        beyond_pct: int = 200,
        timeout: float | None = None,
    ) -> int | None:
        """Send ``0x200``; the state byte of the ``0x210`` answer (None: no answer)."""
        data = struct.pack("<BBhBBBB", command, 0, end_stop_deg, 0, 0, limit_pct, beyond_pct)
        reply = self.request(0x200, data, timeout)
        return None if reply is None else reply[0]

    def wheel_raw(
        self,
        torque_nm: float = 0.0,
        friction_nm: float = 0.0,
        damping_nms_per_rad: float = 0.0,
        stiffness_nm_per_rad: float = 0.0,
        timeout: float | None = None,
    ) -> tuple[int, int, int] | None:
        """Send ``0x201``; the raw (angle increments, rpm, mN·m) of the ``0x211`` answer."""
        data = struct.pack(
            "<hhhh",
            int(torque_nm * 1000.0),
            int(friction_nm * 1000.0),
            int(damping_nms_per_rad * 1000.0 * 2.0 * math.pi / 60.0),
            int(stiffness_nm_per_rad * 1000.0 * math.pi / 180.0),
        )
        reply = self.request(0x201, data, timeout)
        return None if reply is None else struct.unpack("<ihh", reply)

    def wheel(self, *args: float, **kwargs: float) -> tuple[float, float, float] | None:
        """As :meth:`wheel_raw`, in SI: (angle rad, rate rad/s, torque N·m)."""
        raw = self.wheel_raw(*args, **kwargs)
        if raw is None:
            return None
        increments, rpm, milli_nm = raw
        return math.radians(increments * 0.009), rpm * 2.0 * math.pi / 60.0, milli_nm / 1000.0

    def hand_sensor(self, timeout: float | None = None) -> tuple[float, float] | None:
        """Send ``0x20A``; (U_a, U_b) in V from the ``0x21A`` answer (A at 4–5, B at 2–3)."""
        reply = self.request(0x20A, bytes(2), timeout)
        if reply is None:
            return None
        b, a = struct.unpack_from("<hh", reply, 2)
        return a * VOLTS_PER_COUNT, b * VOLTS_PER_COUNT

    def pedals(self, timeout: float | None = None) -> tuple[int, int] | None:
        """Send ``0x20C``; raw (throttle, brake) from the ``0x21C`` answer."""
        reply = self.request(0x20C, b"\x01", timeout)
        if reply is None:
            return None
        throttle, brake = struct.unpack_from("<HH", reply, 2)
        return throttle, brake
