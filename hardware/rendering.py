"""The wheel's virtual dynamics, rendered by the control loop.

The motor torque command that makes the wheel feel like Table 1's spring and damper (the
physical wheel supplies the inertia), plus the perturbation torque:

    T_motor = T_p − b_sw·ω − k_sw·θ

One compiled function serves the live loop (called from Python once per cycle) and the batch
simulator (called inside its compiled loop), so both paths compute the same command.
"""

from __future__ import annotations

from numba import njit

from protocols.protocol import VirtualWheel

__all__ = ["VirtualWheel", "render_torque"]


@njit(cache=True)
def render_torque(tp: float, angle: float, velocity: float, k_sw: float, b_sw: float) -> float:
    return tp - b_sw * velocity - k_sw * angle
