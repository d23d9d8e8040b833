"""The simulated driver of the driving task: how it steers, and how its arm adapts to the road.

Steering: the two-point visual preview model of Salvucci & Gray (2004, Perception 33): the
driver looks at a near point (lane centre ``near_s`` seconds ahead, at least ``near_min_m``)
and a far point (``far_s`` ahead) and changes its intended wheel angle θ_ref as

    θ_ref' = k_far θ_far' + k_near θ_near' + k_int θ_near          (visual angles, rad)

The intention reaches the wheel through the same arm model as every other torque: the arm's
intrinsic spring is centred on θ_ref (equilibrium-point control), i.e. the hands add
k_i(t) · θ_ref to the arm's intrinsic torque, where k_i(t) is the arm's stiffness at that
sample. So a stiffer arm resists the perturbation more without steering differently, and the
remnant still acts on top. The gains are ours, tuned on this vehicle so that the car stays in
a 2.6-m lane at 10–25 m/s (Salvucci & Gray give the form, not gains for our units).

Adaptation: the driver's arm and grip follow the road as in the time-varying boundary tasks
(``hardware/sim/schedule.py``): a *target* behaviour, then a first-order response on the log
scale with the subject's ``adaptation_tau_s`` (arm, remnant) and ``grip_adaptation_tau_s``
(grip). The target is the subject's own boundary-task behaviour at an *equivalent boundary*
(ours):

    b_eq = 12 °/m · margin · sqrt(15 m/s / U) / (1 + 3 a_y / (μ g))

margin = (narrowest lane width in the next second − car width) / 2, a_y = U² · the largest
|curvature| in the next second. A 3.6-m lane at 15 m/s on a straight is between BT12 and BT8
(10.8°), a 2.6-m lane about BT5; faster, curvier and slipperier roads lower b_eq (stiffer, more
grip). (With 20 °/m, a 3.6-m lane as BT18, the most compliant simulated subjects let the
perturbation weave the car out of the lane in one drive in ten: real drivers stiffen first.)
The target's log-behaviour is interpolated linearly in b_eq between PT (0°), BT5, BT8, BT12 and BT18
(held beyond 18°). The road position is taken as U·t (the car keeps its speed; its arc length
differs from U·t by the cosine of its heading error, well below a metre per minute), so the
behaviour is computed in the world's noise blocks like a schedule, and the batch and
sample-by-sample paths see the same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from steerlab.hardware.sim.physiology import ArmParams, ConditionBehaviour
from steerlab.hardware.sim.schedule import DEFAULT_TAU_S, LogLag, _log_row
from steerlab.hardware.vehicle import preview_angle
from steerlab.protocols.driving import G_MPS2, DrivingSetup

#: The boundary tasks whose behaviours the driver interpolates, by boundary width (deg).
ANCHORS = (("PT", 0.0), ("BT5", 5.0), ("BT8", 8.0), ("BT12", 12.0), ("BT18", 18.0))
BOUNDARY_PER_MARGIN_DEG_PER_M = 12.0
REFERENCE_SPEED_MPS = 15.0
LATERAL_DEMAND_GAIN = 3.0
ANTICIPATION_S = 1.0


@dataclass(frozen=True)
class PreviewDriver:
    near_s: float = 0.5
    near_min_m: float = 5.0
    far_s: float = 2.0
    k_far: float = 5.0  # rad of wheel per rad of visual angle
    k_near: float = 6.0
    k_int: float = 5.0  # 1/s
    max_ref_rad: float = 2.0  # the intention stays within ±115°

    def vector(self, speed_mps: float) -> np.ndarray:
        near = max(self.near_min_m, self.near_s * speed_mps)
        return np.array(
            [near, self.far_s * speed_mps, self.k_far, self.k_near, self.k_int, self.max_ref_rad]
        )


#: Driver state: [θ_ref, θ_near last, θ_far last, started]
N_DRIVER_STATE = 4


@njit(cache=True)
def driver_cycle(d, dp, x, road, grid, k_i, dt):
    """The hands' voluntary torque this sample (N·m, on the arm's intrinsic side), then update
    the intention from what the driver sees of the car ``x`` now."""
    torque = k_i * d[0]
    near = preview_angle(x, road, grid, dp[0])
    far = preview_angle(x, road, grid, dp[1])
    if d[3] == 0.0:
        d[1], d[2], d[3] = near, far, 1.0
    ref = d[0] + dp[2] * (far - d[2]) + dp[3] * (near - d[1]) + dp[4] * near * dt
    lim = dp[5]
    d[0] = min(max(ref, -lim), lim)
    d[1], d[2] = near, far
    return torque


def equivalent_boundary_deg(
    width_m: np.ndarray, curvature_1pm: np.ndarray, setup: DrivingSetup
) -> np.ndarray:
    """b_eq for the narrowest width and largest |curvature| the driver anticipates."""
    c = setup.condition
    margin = np.maximum((width_m - setup.vehicle.width_m) / 2.0, 0.0)
    ay = c.speed_mps**2 * np.abs(curvature_1pm)
    speed = math.sqrt(REFERENCE_SPEED_MPS / c.speed_mps)
    return (
        BOUNDARY_PER_MARGIN_DEG_PER_M
        * margin
        * speed
        / (1.0 + LATERAL_DEMAND_GAIN * ay / (c.friction * G_MPS2))
    )


@dataclass(frozen=True)
class DrivingBehaviour:
    """What the simulated driver's arm and grip do along a drive (a schedule for the world)."""

    setup: DrivingSetup
    anchors: dict[str, ConditionBehaviour]  # the subject's behaviour in PT, BT5 … BT18
    tau_arm_s: float = DEFAULT_TAU_S
    tau_grip_s: float = DEFAULT_TAU_S
    driver: PreviewDriver = PreviewDriver()

    def __post_init__(self) -> None:
        missing = [c for c, _ in ANCHORS if c not in self.anchors]
        if missing:
            raise KeyError(f"no simulated behaviour for condition(s) {missing}")
        if len({self.anchors[c].arm.I_i for c, _ in ANCHORS}) > 1:
            raise ValueError("arm inertia must not change within a trial")

    def table(self) -> tuple[np.ndarray, np.ndarray]:
        """(boundary widths, log-behaviour rows) of the anchors."""
        b = np.array([w for _, w in ANCHORS])
        return b, np.array([_log_row(self.anchors[c]) for c, _ in ANCHORS])

    def target_log(self, t_s: np.ndarray) -> np.ndarray:
        """(n, 7) log-behaviour target at times t (s) of the drive."""
        road, u = self.setup.road, self.setup.condition.speed_mps
        s = u * np.asarray(t_s, dtype=float)
        ahead = [s + u * ANTICIPATION_S * f for f in (0.0, 0.5, 1.0)]
        width = np.min([road.at(a, road.lane_width_m) for a in ahead], axis=0)
        kappa = np.max([np.abs(road.at(a, road.curvature_1pm)) for a in ahead], axis=0)
        beq = equivalent_boundary_deg(width, kappa, self.setup)
        bx, rows = self.table()
        return np.column_stack([np.interp(beq, bx, rows[:, j]) for j in range(rows.shape[1])])

    def base(self) -> ConditionBehaviour:
        """The behaviour at the drive's start (the world's base for the trial)."""
        v = np.exp(self.target_log(np.zeros(1))[0])
        ref = self.anchors["BT18"]
        arm = ArmParams(ref.arm.I_i, v[0], v[1], v[2], v[3])
        return ConditionBehaviour(arm, v[4], v[5], v[6], ref.remnant_corner_hz)

    def response(self, fs_hz: float) -> DrivingResponse:
        return DrivingResponse(self, fs_hz)


class DrivingResponse:
    """Stateful: the driver's true behaviour for consecutive blocks of samples (the same
    interface as :class:`hardware.sim.schedule.ScheduleResponse`)."""

    def __init__(self, beh: DrivingBehaviour, fs_hz: float) -> None:
        self.beh, self.fs = beh, fs_hz
        # the drive starts settled
        self.lag = LogLag(beh.tau_arm_s, beh.tau_grip_s, fs_hz, beh.target_log(np.zeros(1))[0])
        self.k = 0

    def next_block(self, n: int) -> dict[str, np.ndarray]:
        target = self.beh.target_log(np.arange(self.k, self.k + n) / self.fs)
        self.k += n
        return self.lag.response(target, np.zeros(n, dtype=int))
