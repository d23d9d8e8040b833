"""The vehicle of the driving task: a single-track (bicycle) model on a road, and the
self-aligning torque it renders on the steering wheel (issue 19).

Host side, like :mod:`hardware.safety`: the live loop (:class:`VehicleRenderer`) and the batch
simulator's kernel call the same compiled :func:`vehicle_cycle`, so both give the same numbers.

Model (constant forward speed U; lateral velocity v, yaw rate r; ISO 8855 signs, y left)::

    δ   = θ / steering_ratio                          road-wheel angle from the wheel angle θ
    α_f = δ − (v + a r)/U,   α_r = −(v − b r)/U        slip angles
    F_y = μ F_z tanh(C α / (μ F_z))                   linear tyre, saturating at μ F_z (per axle)
    m (v' + U r) = F_yf + F_yr,   I_z r' = a F_yf − b F_yr
    s'  = (U cos ψ_e − v sin ψ_e) / (1 − y κ)         road frame: arc length s, lateral
    y'  = U sin ψ_e + v cos ψ_e                        position y, heading error ψ_e,
    ψ_e' = r − κ(s) s'                                 road curvature κ

Aligning torque on the wheel (N·m, positive counter-clockwise like θ)::

    trail = t_mech + t_pneu (1 − |F_yf| / (μ F_zf))    the pneumatic trail shrinks as the tyre
    T_align = −feel_gain · trail · F_yf / steering_ratio   saturates (the wheel goes light)

so it opposes the front slip: it pulls the wheel back to centre, grows with the slip the speed
brings, and falls as friction runs out. The loop adds it to the perturbation inside
:func:`hardware.safety.loop_command`, so the same saturation, slew limit, soft-limit fade and
non-finite guard apply to it.

Integration: explicit Euler for (v, r), then the road-frame kinematics with the new (v, r)
(semi-implicit), at the loop rate. Its steady state is the continuous model's exactly (the
understeer-gradient test checks it).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from steerlab.protocols.driving import DrivingSetup

# vehicle_vector() indices
V_M, V_IZ, V_A, V_B, V_CF, V_CR, V_G, V_TP, V_TM, V_FEEL, V_FZF, V_FZR, V_U, V_MU = range(14)
# state indices
X_S, X_Y, X_PSI, X_V, X_R = range(5)
N_VEHICLE_STATE = 5
# road table rows
R_KAPPA, R_WIDTH, R_HEAD, R_X, R_Y = range(5)

#: Channels the driving trial logs per sample (docs/data-format.md), in the kernel's row order.
DRIVING_CHANNELS = (
    "road_distance_m",
    "lateral_position_m",
    "heading_error_rad",
    "road_curvature_1pm",
    "lane_width_m",
    "aligning_torque_Nm",
)


@njit(cache=True)
def road_value(road, grid, s, row):
    """Linear interpolation of a road row at arc length s (held beyond either end)."""
    n = road.shape[1]
    u = s / grid
    if u <= 0.0:
        return road[row, 0]
    i = int(u)
    if i >= n - 1:
        return road[row, n - 1]
    f = u - i
    return road[row, i] * (1.0 - f) + road[row, i + 1] * f


@njit(cache=True)
def tyre_force(c, alpha, mu, fz):
    cap = mu * fz
    return cap * math.tanh(c * alpha / cap)


@njit(cache=True)
def aligning_torque(x, vp, angle):
    """Torque on the steering wheel (N·m) for the state x and the wheel angle (rad)."""
    u = vp[V_U]
    delta = angle / vp[V_G]
    alpha_f = delta - (x[X_V] + vp[V_A] * x[X_R]) / u
    f = tyre_force(vp[V_CF], alpha_f, vp[V_MU], vp[V_FZF])
    trail = vp[V_TM] + vp[V_TP] * (1.0 - abs(f) / (vp[V_MU] * vp[V_FZF]))
    return -vp[V_FEEL] * trail * f / vp[V_G]


@njit(cache=True)
def vehicle_cycle(x, vp, road, grid, angle, dt, row):
    """One loop cycle: write this sample's channels (DRIVING_CHANNELS order) into ``row``,
    return the aligning torque, advance the state by dt with the wheel at ``angle``."""
    u = vp[V_U]
    s, y, psi, v, r = x[X_S], x[X_Y], x[X_PSI], x[X_V], x[X_R]
    kappa = road_value(road, grid, s, R_KAPPA)
    ta = aligning_torque(x, vp, angle)
    row[0] = s
    row[1] = y
    row[2] = psi
    row[3] = kappa
    row[4] = road_value(road, grid, s, R_WIDTH)
    row[5] = ta
    delta = angle / vp[V_G]
    a, b = vp[V_A], vp[V_B]
    ff = tyre_force(vp[V_CF], delta - (v + a * r) / u, vp[V_MU], vp[V_FZF])
    fr = tyre_force(vp[V_CR], -(v - b * r) / u, vp[V_MU], vp[V_FZR])
    v_n = v + dt * ((ff + fr) / vp[V_M] - u * r)
    r_n = r + dt * (a * ff - b * fr) / vp[V_IZ]
    sd = (u * math.cos(psi) - v_n * math.sin(psi)) / (1.0 - y * kappa)
    x[X_S] = s + dt * sd
    x[X_Y] = y + dt * (u * math.sin(psi) + v_n * math.cos(psi))
    x[X_PSI] = psi + dt * (r_n - kappa * sd)
    x[X_V] = v_n
    x[X_R] = r_n
    return ta


@njit(cache=True)
def preview_angle(x, road, grid, distance):
    """Visual angle (rad, positive left) from the car's heading to the lane centre
    ``distance`` metres further along the road (the driver's near and far points)."""
    s, y = x[X_S], x[X_Y]
    h = road_value(road, grid, s, R_HEAD)
    cx = road_value(road, grid, s, R_X) - y * math.sin(h)
    cy = road_value(road, grid, s, R_Y) + y * math.cos(h)
    px = road_value(road, grid, s + distance, R_X)
    py = road_value(road, grid, s + distance, R_Y)
    a = math.atan2(py - cy, px - cx) - (h + x[X_PSI])
    return math.atan2(math.sin(a), math.cos(a))


class VehicleRenderer:
    """The host's vehicle for one driving trial (the live loop calls :meth:`cycle` per cycle)."""

    def __init__(self, setup: DrivingSetup, fs_hz: float) -> None:
        self.vp = setup.vehicle_vector()
        self.road = setup.road.table()
        self.grid = float(setup.road.grid_m)
        self.dt = 1.0 / fs_hz
        self.x = np.zeros(N_VEHICLE_STATE)
        self.row = np.zeros(len(DRIVING_CHANNELS))

    def cycle(self, angle_rad: float) -> float:
        """Aligning torque (N·m) for this cycle; the channels are in ``self.row`` after."""
        return float(
            vehicle_cycle(self.x, self.vp, self.road, self.grid, angle_rad, self.dt, self.row)
        )

    def channels(self) -> dict[str, float]:
        return {c: float(v) for c, v in zip(DRIVING_CHANNELS, self.row, strict=True)}


def warm_up() -> None:
    """Compile the vehicle's functions before a trial's first cycle."""
    from steerlab.protocols.driving import DrivingCondition, RoadSpec, VehicleSpec

    setup = DrivingSetup(DrivingCondition(10.0), VehicleSpec(), RoadSpec().generate(50.0))
    r = VehicleRenderer(setup, 1000.0)
    r.cycle(0.0)
    preview_angle(r.x, r.road, r.grid, 10.0)
