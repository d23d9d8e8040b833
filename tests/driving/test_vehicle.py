"""The driving task's vehicle and road, checked against analytic results (issue 19)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from steerlab.hardware.vehicle import (
    DRIVING_CHANNELS,
    X_PSI,
    X_R,
    X_V,
    X_Y,
    aligning_torque,
    preview_angle,
    vehicle_cycle,
)
from steerlab.protocols.driving import (
    DrivingCondition,
    DrivingSetup,
    RoadSpec,
    VehicleSpec,
)

STRAIGHT = RoadSpec(min_radius_m=1e9, max_radius_m=1e9)  # curvature 1e-9: a straight road


def _settle(setup: DrivingSetup, angle: float, seconds: float = 20.0, dt: float = 1e-3):
    vp, road = setup.vehicle_vector(), setup.road.table()
    x, row = np.zeros(5), np.zeros(len(DRIVING_CHANNELS))
    for _ in range(int(seconds / dt)):
        vehicle_cycle(x, vp, road, setup.road.grid_m, angle, dt, row)
    return x, vp


@pytest.mark.parametrize("speed", [8.0, 15.0, 25.0, 35.0])
def test_steady_state_yaw_rate_is_the_bicycle_models(speed):
    veh = VehicleSpec()
    # Tiny steer, ample friction: the tyres are linear, so the textbook steady state holds.
    setup = DrivingSetup(
        DrivingCondition(speed, friction=1.5), veh, STRAIGHT.generate(speed * 25 + 50)
    )
    wheel = math.radians(2.0)
    x, _ = _settle(setup, wheel)
    delta = wheel / veh.steering_ratio
    # Independent: the linear steady state solved as a 2×2 system (no formula shared).
    m, a, b = veh.mass_kg, veh.cg_to_front_m, veh.cg_to_rear_m
    cf, cr, u = veh.front_cornering_N_per_rad, veh.rear_cornering_N_per_rad, speed
    A = np.array([[-(cf + cr) / u, -(a * cf - b * cr) / u - m * u],
                  [-(a * cf - b * cr) / u, -(a * a * cf + b * b * cr) / u]])  # fmt: skip
    v_ss, r_ss = np.linalg.solve(A, -np.array([cf * delta, a * cf * delta]))
    assert x[X_R] == pytest.approx(r_ss, rel=2e-3)
    assert x[X_V] == pytest.approx(v_ss, rel=2e-3, abs=1e-6)
    # And the understeer-gradient form r/δ = U / (L + K U²), K = m/L (b/C_f − a/C_r).
    L = a + b
    K = m / L * (b / cf - a / cr)
    assert x[X_R] / delta == pytest.approx(u / (L + K * u * u), rel=2e-3)
    assert veh.steady_yaw_rate_gain(u) == pytest.approx(u / (L + K * u * u), rel=1e-12)
    assert K > 0  # this car understeers: the yaw gain falls below the neutral U/L
    assert x[X_R] / delta < u / L


def test_aligning_torque_pulls_the_wheel_back_to_centre():
    setup = DrivingSetup(DrivingCondition(20.0), VehicleSpec(), STRAIGHT.generate(100.0))
    vp, x = setup.vehicle_vector(), np.zeros(5)
    for ang in (0.05, 0.3, 1.0):
        assert aligning_torque(x, vp, ang) < 0.0 < aligning_torque(x, vp, -ang)
    assert aligning_torque(x, vp, 0.0) == 0.0
    # In a steady left turn the wheel is still pulled to the right (towards centre).
    xs, _ = _settle(setup, 0.3, seconds=10.0)
    assert xs[X_R] > 0 and aligning_torque(xs, vp, 0.3) < 0.0
    # Released with only its inertia and the aligning torque, the wheel swings back through 0.
    th, om, dt, Iw, bw = 0.3, 0.0, 1e-3, 0.3, 2.0
    x = np.zeros(5)
    row = np.zeros(len(DRIVING_CHANNELS))
    crossed = False
    for _ in range(3000):
        t = vehicle_cycle(x, vp, setup.road.table(), setup.road.grid_m, th, dt, row)
        om += dt * (t - bw * om) / Iw
        th += dt * om
        crossed |= th < 0.0
    assert crossed


def test_aligning_torque_depends_on_speed_and_friction():
    veh = VehicleSpec()
    road = STRAIGHT.generate(1000.0)

    def steady_torque(speed, mu, wheel):
        setup = DrivingSetup(DrivingCondition(speed, friction=mu), veh, road)
        x, vp = _settle(setup, wheel, seconds=8.0)
        return aligning_torque(x, vp, wheel)

    # Same wheel angle, faster: more lateral acceleration, more front slip, more torque.
    assert abs(steady_torque(25.0, 1.0, 0.1)) > abs(steady_torque(10.0, 1.0, 0.1))
    # Large slip on a slippery road: the tyre saturates and the pneumatic trail collapses,
    # so the wheel goes light (the classic cue of lost grip).
    x, vp1 = np.zeros(5), DrivingSetup(DrivingCondition(20.0, 1.0), veh, road).vehicle_vector()
    vp03 = DrivingSetup(DrivingCondition(20.0, 0.3), veh, road).vehicle_vector()
    assert abs(aligning_torque(x, vp03, 1.5)) < 0.5 * abs(aligning_torque(x, vp1, 1.5))
    # Small slip: linear tyre, friction does not matter.
    assert aligning_torque(x, vp03, 0.01) == pytest.approx(aligning_torque(x, vp1, 0.01), rel=0.05)
    # Magnitude: −feel · trail · C_f · δ / G at small slip.
    d = 0.01 / veh.steering_ratio
    lin = -veh.feel_gain * (veh.pneumatic_trail_m + veh.mechanical_trail_m)
    lin *= veh.front_cornering_N_per_rad * d / veh.steering_ratio
    assert aligning_torque(x, vp1, 0.01) == pytest.approx(lin, rel=0.01)


def test_the_car_follows_a_bend_with_the_kinematic_steer_and_preview_sees_it():
    # A constant-radius left bend (curvature positive): with the steady-state steer for that
    # radius the car keeps its lateral position and heading error near zero.
    radius = 200.0
    spec = RoadSpec(lead_in_m=0.0, curvature_taper_m=0.0, straight_min_m=5000.0,
                    straight_max_m=5000.0, curve_min_m=5000.0, curve_max_m=5000.0,
                    min_radius_m=radius, max_radius_m=radius)  # fmt: skip
    for seed in range(20):  # a seed whose first curve bends left
        road = spec.generate(1000.0, seed=seed)
        if road.curvature_1pm[10] > 0:
            break
    veh, u = VehicleSpec(), 15.0
    setup = DrivingSetup(DrivingCondition(u, friction=1.5), veh, road)
    delta = (u / radius) / veh.steady_yaw_rate_gain(u)
    x = np.zeros(5)
    # Start in the steady state of that turn (v, r from the linear model).
    setup_s = DrivingSetup(DrivingCondition(u, friction=1.5), veh, STRAIGHT.generate(600.0))
    xs, _ = _settle(setup_s, delta * veh.steering_ratio)
    x[X_V], x[X_R] = xs[X_V], xs[X_R]
    # Its velocity, not its nose, follows the lane: heading error = −sideslip, tan ψ_e = −v/U.
    x[X_PSI] = -math.atan(xs[X_V] / u)
    vp, table = setup.vehicle_vector(), road.table()
    row = np.zeros(len(DRIVING_CHANNELS))
    for _ in range(20000):
        vehicle_cycle(x, vp, table, road.grid_m, delta * veh.steering_ratio, 1e-3, row)
    assert abs(x[X_Y]) < 0.1  # after 300 m of bend (first-order integration at 1 kHz)
    assert x[X_PSI] == pytest.approx(-math.atan(xs[X_V] / u), abs=1e-3)
    assert row[3] == pytest.approx(1 / radius, rel=1e-6)
    assert preview_angle(x, table, road.grid_m, 30.0) > 0  # the lane centre bends left ahead


def test_road_is_seeded_smooth_and_alternates_wide_and_narrow():
    spec = RoadSpec()
    a, b = spec.generate(3000.0), spec.generate(3000.0)
    np.testing.assert_array_equal(a.curvature_1pm, b.curvature_1pm)
    c = spec.generate(3000.0, seed=spec.seed + 1)
    assert not np.array_equal(a.curvature_1pm, c.curvature_1pm)
    longer = spec.generate(4000.0)
    n = int(2500 / spec.grid_m)  # a longer road starts with the same road
    np.testing.assert_allclose(longer.curvature_1pm[:n], a.curvature_1pm[:n], atol=1e-15)
    k = a.curvature_1pm
    assert np.abs(k).max() <= 1 / spec.min_radius_m + 1e-12
    assert (k > 1e-4).any() and (k < -1e-4).any()
    # Smooth: curvature changes over the taper, never in a step.
    assert np.abs(np.diff(k)).max() < 2.5 * (1 / spec.min_radius_m) * spec.grid_m / 40.0
    w = a.lane_width_m
    assert w.min() == pytest.approx(spec.narrow_lane_m, abs=1e-9)
    assert w.max() == pytest.approx(spec.wide_lane_m, abs=1e-9)
    np.testing.assert_allclose(w[: int(spec.lead_in_m / spec.grid_m) - 100], spec.wide_lane_m)
    # Heading is the integral of curvature; position follows the heading.
    assert a.heading_rad[-1] == pytest.approx(np.trapezoid(k, dx=spec.grid_m), rel=1e-9)
    step = np.hypot(np.diff(a.x_m), np.diff(a.y_m))
    np.testing.assert_allclose(step, spec.grid_m, rtol=1e-6)


def test_vehicle_spec_kernel_vector_orders_the_axle_loads():
    veh = replace(VehicleSpec(), cg_to_front_m=1.0, cg_to_rear_m=2.0)
    vp = veh.kernel_vector()
    fzf, fzr = vp[10], vp[11]
    assert fzf + fzr == pytest.approx(veh.mass_kg * 9.81)
    assert fzf == pytest.approx(2 * fzr)  # the front axle is nearer the centre of mass
