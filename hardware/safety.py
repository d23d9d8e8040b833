"""Safety rules applied to every motor command, in the lab and in simulation alike.

Per cycle, ``loop_command`` turns the perturbation and the measured wheel state into the motor
command:

1. soft angle limits: within ``fade_zone`` of ``soft_angle_limit`` the perturbation fades to
   zero, and beyond the limit a braking damper opposes outward motion;
2. the virtual wheel (Table 1's spring and damper) is rendered;
3. the command is saturated at ``max_torque`` and its change per cycle limited to
   ``max_slew · dt`` (no torque step reaches the hands).

The perturbation's own fade-in and fade-out live in the trial's perturbation signal
(``protocols.session``). Watchdogs (loop stall, lost drive heartbeat, stopped glove stream) are
in :mod:`hardware.loop`; they end the trial and leave the motor at zero torque.

One compiled function serves the batch simulator's kernel and the live loop, so both apply the
same rules to the same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass(frozen=True)
class SafetyLimits:
    max_torque_nm: float = 8.0
    max_slew_nm_per_s: float = 400.0
    soft_angle_limit_deg: float = 90.0
    fade_zone_deg: float = 15.0
    brake_damping_nms_per_rad: float = 5.0
    loop_stall_s: float = 0.02  # a cycle later than this: quick stop, trial aborted
    glove_timeout_s: float = 0.25  # no glove frame for this long: trial aborted

    def problems(self) -> list[tuple[str, str]]:
        """(field, what is wrong) for every field out of range; empty when usable."""
        out = []
        for name in ("max_torque_nm", "max_slew_nm_per_s", "soft_angle_limit_deg",
                     "loop_stall_s", "glove_timeout_s"):  # fmt: skip
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                out.append((name, f"must be a finite number > 0, got {v!r}"))
        if not 0 <= self.fade_zone_deg < self.soft_angle_limit_deg:
            out.append(("fade_zone_deg", "must be ≥ 0 and below soft_angle_limit_deg, "
                        f"got {self.fade_zone_deg}"))  # fmt: skip
        b = self.brake_damping_nms_per_rad
        if not (isinstance(b, int | float) and math.isfinite(b) and b >= 0):
            out.append(("brake_damping_nms_per_rad", f"must be a finite number ≥ 0, got {b!r}"))
        return out

    def kernel_vector(self, fs_hz: float) -> np.ndarray:
        """The numbers ``loop_command`` takes, in SI units per cycle."""
        lim = math.radians(self.soft_angle_limit_deg)
        zone = math.radians(self.fade_zone_deg)
        return np.array(
            [
                self.max_torque_nm,
                self.max_slew_nm_per_s / fs_hz,
                lim,
                zone,
                self.brake_damping_nms_per_rad,
            ]
        )


@njit(cache=True)
def perturbation_gain(angle: float, limit: float, zone: float) -> float:
    a = abs(angle)
    if a >= limit:
        return 0.0
    if zone <= 0.0 or a <= limit - zone:
        return 1.0
    return (limit - a) / zone


@njit(cache=True)
def inputs_finite(
    tp: float, angle: float, velocity: float, previous: float, k_sw: float, b_sw: float
) -> bool:
    return (
        math.isfinite(tp)
        and math.isfinite(angle)
        and math.isfinite(velocity)
        and math.isfinite(previous)
        and math.isfinite(k_sw)
        and math.isfinite(b_sw)
    )


def nonfinite_input(**values: float) -> str | None:
    """``"name = value"`` of the first non-finite value, or None: the reason a caller records when
    :func:`loop_command` returned its zero for a non-finite input."""
    for name, v in values.items():
        if not math.isfinite(v):
            return f"{name} = {float(v)!r}"
    return None


@njit(cache=True)
def loop_command(
    tp: float,
    angle: float,
    velocity: float,
    previous: float,
    k_sw: float,
    b_sw: float,
    s: np.ndarray,
) -> float:
    """Motor command (N·m) for one cycle; ``s`` is ``SafetyLimits.kernel_vector(fs)``.

    No non-finite value reaches the motor: any NaN or infinite input (a broken sensor value, a
    protocol's inf) gives exactly 0.0, zero torque at once (no slew limit: cutting the torque
    is the safe act). The caller treats a 0.0 with :func:`inputs_finite` false as a fault."""
    if not inputs_finite(tp, angle, velocity, previous, k_sw, b_sw):
        return 0.0
    max_t, max_step, limit, zone, b_brake = s[0], s[1], s[2], s[3], s[4]
    g = perturbation_gain(angle, limit, zone)
    cmd = g * tp - b_sw * velocity - k_sw * angle
    if abs(angle) > limit and angle * velocity > 0.0:
        cmd -= b_brake * velocity
    if cmd > max_t:
        cmd = max_t
    elif cmd < -max_t:
        cmd = -max_t
    step = cmd - previous
    if step > max_step:
        cmd = previous + max_step
    elif step < -max_step:
        cmd = previous - max_step
    if not math.isfinite(cmd):  # non-finite limits: no torque rather than an unknown one
        return 0.0
    return cmd


def warm_up() -> None:
    """Compile ``loop_command`` now, not in the first cycle of a trial (a stall there trips
    the watchdog)."""
    loop_command(0.0, 0.0, 0.0, 0.0, 4.2, 2.0, SafetyLimits().kernel_vector(1000.0))
