"""SI wheel units ↔ drive units, from one :class:`DriveConfig`.

The driver and the simulated drive both convert through this class, so a sign or gear error
shows up in the round-trip tests instead of as a simulated rig that disagrees with the lab.

Drive units (CiA 402): position in encoder counts (motor side, INTEGER32, wraps), velocity in
counts/s or motor rpm, torque in 0.1 % of rated motor torque (INTEGER16). Wheel units
(hardware.interfaces): rad, rad/s, N·m on the wheel axis, positive counter-clockwise seen by the
driver.
"""

from __future__ import annotations

import math

from .config import DriveConfig, TorqueSensorConfig

_INT16 = (-0x8000, 0x7FFF)
_TWO_PI = 2.0 * math.pi


def _saturate(value: float, lo: int, hi: int) -> int:
    return max(lo, min(hi, round(value)))


def _wrap32(value: int) -> int:
    return (value + 0x8000_0000) % 0x1_0000_0000 - 0x8000_0000


class DriveScaling:
    def __init__(self, config: DriveConfig):
        self.sign = config.sign
        self._nm_per_permille = config.sign * config.gear_ratio * config.rated_torque_nm / 1000.0
        self._rad_per_count = (
            config.sign * _TWO_PI / (config.encoder_counts_per_rev * config.gear_ratio)
        )
        if config.velocity_unit == "rpm":
            self._rad_s_per_vel_unit = config.sign * _TWO_PI / 60.0 / config.gear_ratio
        else:
            self._rad_s_per_vel_unit = self._rad_per_count
        sensor: TorqueSensorConfig = config.torque_sensor
        self._nm_per_sensor_count = sensor.sign * sensor.nm_per_count
        self._sensor_range = (-(1 << (sensor.bits - 1)), (1 << (sensor.bits - 1)) - 1)

    # torque (target 0x6071, actual 0x6077)
    def torque_to_permille(self, torque_nm: float) -> int:
        """Rounded and saturated to the INTEGER16 range; NaN is the caller's bug (ValueError)."""
        return _saturate(torque_nm / self._nm_per_permille, *_INT16)

    def permille_to_torque(self, permille: int) -> float:
        return permille * self._nm_per_permille

    @property
    def torque_resolution_nm(self) -> float:
        return abs(self._nm_per_permille)

    # position (0x6064)
    def counts_to_angle(self, counts: int) -> float:
        return counts * self._rad_per_count

    def angle_to_counts(self, angle_rad: float) -> int:
        """Wrapped to INTEGER32 like a drive's position counter."""
        return _wrap32(round(angle_rad / self._rad_per_count))

    # velocity (0x606C)
    def velocity_to_rad_s(self, value: int) -> float:
        return value * self._rad_s_per_vel_unit

    def rad_s_to_velocity(self, velocity_rad_s: float) -> int:
        return _wrap32(round(velocity_rad_s / self._rad_s_per_vel_unit))

    # column torque sensor
    def sensor_to_torque(self, counts: int) -> float:
        return counts * self._nm_per_sensor_count

    def torque_to_sensor(self, torque_nm: float) -> int:
        return _saturate(torque_nm / self._nm_per_sensor_count, *self._sensor_range)
