"""The simulated world: same signals by both paths, the arm's true admittance, physiology."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from steerlab.hardware.sim.mechanisms import (
    ActuatorLag,
    CoulombFriction,
    Drift,
    GripScheduledStiffness,
    Mechanisms,
    ReflexDelay,
    SensorDelay,
    StiffnessNonlinearity,
)
from steerlab.hardware.sim.physiology import CONDITIONS, NOMINAL, make_population
from steerlab.hardware.sim.rig import simulated_rig
from steerlab.hardware.sim.world import NOISELESS_SENSORS as NOISELESS
from steerlab.hardware.sim.world import SensorSpec, World, WorldConfig
from steerlab.protocols.engine import SessionEngine
from steerlab.protocols.events import SamplesAcquired
from steerlab.protocols.session import build_plan


def _collect(engine: SessionEngine) -> dict[str, dict[str, np.ndarray]]:
    got: dict[str, dict[str, list]] = {}

    def sub(e):
        if isinstance(e, SamplesAcquired):
            d = got.setdefault(e.key, {})
            for k, v in e.channels.items():
                d.setdefault(k, []).append(np.asarray(v))

    engine.subscribe(sub)
    engine.run()
    return {k: {c: np.concatenate(v) for c, v in d.items()} for k, d in got.items()}


def test_batch_and_sample_by_sample_give_the_same_signals(fast_protocol):
    """The fast batch loop and the per-sample device loop (the live path) on the same seed."""
    subj = make_population(2, seed=11)[1]
    plan = build_plan(fast_protocol, 2)
    short = replace(plan, trials=plan.trials[:2])
    batch = _collect(SessionEngine(short, simulated_rig(subj).batch_loop(block_s=0.7)))
    live = _collect(SessionEngine(short, simulated_rig(subj).device_loop(block_s=0.05)))
    assert batch.keys() == live.keys() and len(batch) == 2
    for key in batch:
        # The batch loop computes a block at once: no instant of a read (host_time_s).
        assert batch[key].keys() == live[key].keys() - {"host_time_s"}
        for c in batch[key]:
            np.testing.assert_allclose(live[key][c], batch[key][c], rtol=0, atol=1e-12, err_msg=c)
        assert np.std(batch[key]["wheel_angle_rad"]) > 0.01  # not trivially zero


def _excited_response(cond: str, sensors: SensorSpec, remnant: float, fs: float = 1000.0):
    from steerlab.protocols.perturbation import design_multisine

    d = design_multisine()
    b = replace(NOMINAL[cond], remnant_sd_nm=remnant)
    w = World(WorldConfig(fs_hz=fs, sensors=sensors))
    w.begin_trial(b, 0.5, seed=3)
    n = int(45 * fs)
    t = np.arange(2 * n) / fs
    out = w.run(d.signal(t))
    seg = slice(n, 2 * n)  # second period: transients gone
    th = np.fft.rfft(out["wheel_angle_rad"][seg])[d.bins]
    td = np.fft.rfft(out["driver_torque_Nm"][seg])[d.bins]
    return d, b, th / td


@pytest.mark.parametrize("cond", ["RT", "BT12", "PT"])
def test_noise_free_admittance_is_the_arm_models(cond):
    d, b, H = _excited_response(cond, NOISELESS, remnant=0.0)
    truth = b.arm.admittance(d.frequencies_hz)
    # Sampled ZOH simulation vs continuous formula: agreement to within aliasing at fs = 1 kHz.
    np.testing.assert_allclose(np.abs(H / truth), 1.0, atol=2e-3)
    np.testing.assert_allclose(np.angle(H / truth), 0.0, atol=2e-3)
    assert np.all(H.real[:5] > 0), "positive at low frequency (sign convention)"


def test_remnant_and_sensor_noise_perturb_the_estimate_mostly_at_low_frequency():
    d, b, H = _excited_response("BT12", SensorSpec(), remnant=0.4)
    err = np.abs(H / b.arm.admittance(d.frequencies_hz) - 1)
    assert err[:10].mean() > err[-20:].mean()
    assert err.max() > 1e-3  # there is noise
    assert np.median(err) < 0.2  # but the perturbation dominates


def test_sensor_resolution():
    w = World()
    w.begin_trial(NOMINAL["BT8"], 0.5, seed=1)
    out = w.run(np.sin(np.arange(3000) / 100.0))
    q = 2 * np.pi / 131072
    counts = out["wheel_angle_rad"] / q
    assert np.allclose(counts, np.round(counts), atol=1e-6)
    lsb = out["driver_torque_Nm"] / 0.001
    assert np.allclose(lsb, np.round(lsb), atol=1e-6)
    # The glove holds each frame for 10 loop samples (100 Hz glove, 1 kHz loop).
    changes = np.flatnonzero(np.diff(out["grip_force_left_N"]) != 0) + 1
    assert np.all(changes % 10 == 0)


def test_conditions_ordered_admittance_falls_grip_rises():
    f = np.array([0.1, 0.5, 1.0])
    gains = [np.abs(NOMINAL[c].arm.admittance(f)).mean() for c in CONDITIONS]
    grips = [NOMINAL[c].grip_mean_n for c in CONDITIONS]
    assert all(a > b for a, b in zip(gains, gains[1:], strict=False))
    assert all(a <= b for a, b in zip(grips, grips[1:], strict=False))
    assert grips[0] == pytest.approx(grips[1], rel=0.05)  # RT ≈ BT18 as in the paper
    assert 180 <= grips[-1] <= 220


def test_population_is_seeded_and_varies_between_subjects():
    a, b = make_population(18, seed=4), make_population(18, seed=4)
    assert [s.to_dict() for s in a] == [s.to_dict() for s in b]
    assert make_population(3, seed=5)[0].to_dict() != a[0].to_dict()
    # Subject k's draw does not depend on how many subjects were asked for.
    assert make_population(5, seed=4)[2].to_dict() == a[2].to_dict()
    k = np.array([s.behaviour["BT12"].arm.k_i for s in a])
    assert 0.1 < k.std() / k.mean() < 0.4
    # Condition order holds in the population mean.
    means = [np.mean([s.behaviour[c].arm.k_i for s in a]) for c in CONDITIONS]
    assert all(x < y for x, y in zip(means, means[1:], strict=False))


def _run_with(mech: Mechanisms, cond="BT12", n=20000, seed=2):
    w = World(WorldConfig(mechanisms=mech))
    w.begin_trial(NOMINAL[cond], 0.5, seed=seed)
    from steerlab.protocols.perturbation import design_multisine

    return w.run(design_multisine().signal(np.arange(n) / 1000.0))


@pytest.mark.parametrize(
    "mech",
    [
        Mechanisms(reflex_delay=ReflexDelay(k_p=5.0, k_v=0.5)),
        Mechanisms(coulomb_friction=CoulombFriction(torque_nm=0.3)),
        Mechanisms(stiffness_nonlinearity=StiffnessNonlinearity(k3_nm_per_rad3=200.0)),
        Mechanisms(actuator_lag=ActuatorLag(tau_s=0.01)),
        Mechanisms(sensor_delay=SensorDelay(delay_s=0.01)),
        Mechanisms(grip_scheduled_stiffness=GripScheduledStiffness(gain=1.0)),
    ],
    ids=lambda m: m.active()[0],
)
def test_mechanisms_plug_into_the_same_world(mech):
    base = _run_with(Mechanisms())
    out = _run_with(mech)
    assert mech.active() and not Mechanisms().active()
    diff = max(np.abs(out[c] - base[c]).max() for c in ("wheel_angle_rad", "driver_torque_Nm"))
    assert diff > 1e-3


def test_sensor_delay_is_a_pure_delay_of_driver_torque():
    base = _run_with(Mechanisms(), n=5000)
    # A pure measurement delay does not change the physics, only the reading.
    delayed = _run_with(Mechanisms(sensor_delay=SensorDelay(delay_s=0.007)), n=5000)
    np.testing.assert_array_equal(delayed["wheel_angle_rad"], base["wheel_angle_rad"])
    lag = 7
    a = delayed["driver_torque_Nm"][lag:] - base["driver_torque_Nm"][:-lag]
    assert np.abs(a).max() < 0.2  # same signal shifted, up to independent sensor noise draws


def test_actuator_lag_is_a_first_order_lag_of_the_command():
    out = _run_with(Mechanisms(actuator_lag=ActuatorLag(tau_s=0.02)), n=4000)
    cmd, tm = out["motor_command_Nm"], out["motor_torque_Nm"]
    alpha = 1 - np.exp(-0.001 / 0.02)
    pred = np.empty_like(tm)
    prev = 0.0
    for i, c in enumerate(cmd):
        pred[i] = prev  # reported at cycle i: applied during cycle i − 1
        prev = prev + alpha * (c - prev)
    np.testing.assert_allclose(tm, pred, atol=1e-12)


def test_drift_scales_stiffness_with_trial_index(fast_protocol):
    from steerlab.hardware.sim.rig import SimulatedSubject

    subj = SimulatedSubject(make_population(1, seed=0)[0])
    plan = build_plan(fast_protocol, 1)
    cfg = WorldConfig(fs_hz=200.0, mechanisms=Mechanisms(drift=Drift(rate_per_trial=0.02)))
    first = subj.behaviour(plan.setup(plan.trials[1]), cfg).arm.k_i
    plain = subj.behaviour(plan.setup(plan.trials[1]), WorldConfig(fs_hz=200.0)).arm.k_i
    assert first == pytest.approx(plain * 1.02)
