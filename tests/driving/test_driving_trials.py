"""Driving trials through the protocol, the engine, both loops and the session file (issue 19)."""

from __future__ import annotations

import json
from dataclasses import replace

import h5py
import numpy as np
import pytest

from steerlab.hardware.safety import SafetyLimits, loop_command
from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.rig import simulated_rig
from steerlab.hardware.sim.world import TRUTH_CHANNELS
from steerlab.hardware.vehicle import DRIVING_CHANNELS
from steerlab.protocols.datafile import (
    SessionFile,
    SessionWriter,
    session_bytes,
    trial_channels,
)
from steerlab.protocols.engine import LoopControl, SessionEngine
from steerlab.protocols.events import SamplesAcquired
from steerlab.protocols.protocol import ProtocolError, load_protocol, parse_protocol
from steerlab.protocols.session import build_plan
from tests.helpers import fast_protocol_text

DRIVES = """
[[conditions]]
name = "D15"
task = "driving"
speed_mps = 15.0
friction = 1.0
perturbation_level = 1.0

[[conditions]]
name = "D25_FREE"
task = "driving"
speed_mps = 25.0
friction = 0.5
perturbation_level = 0.0
"""


def _protocol(extra: str = DRIVES, fs: float = 200.0):
    return parse_protocol(fast_protocol_text(fs) + extra, "drive.toml")


def _trial(plan, name):
    return next(t for t in plan.trials if t.condition == name and not t.familiarization)


def _batch(setup, subject=1, seed=3, safety=None):
    rig = simulated_rig(make_population(subject, seed=seed)[subject - 1])
    if safety is not None:
        rig.world.safety = safety
    blocks = list(rig.batch_loop().run_trial(setup, LoopControl()))
    return rig, {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}


def test_the_shipped_driving_protocol_is_found_by_name_and_reads():
    p = load_protocol("driving.toml")
    drives = [c for c in p.conditions if c.driving is not None]
    assert {c.name for c in drives} >= {"D15_DRY", "D25_WET", "D20_FREE"}
    assert p.stationary_condition_names == ["RT", "BT18", "BT12", "BT8", "BT5", "PT"]
    assert p.condition("D20_FREE").driving.perturbation_level == 0.0
    assert p.condition("D15_WET").driving.friction == 0.5
    assert all(c.boundary_deg == float("inf") for c in drives)
    # The default protocol has no driving condition and the default vehicle and road.
    d = load_protocol()
    assert all(c.driving is None for c in d.conditions)


@pytest.mark.parametrize(
    "edit, where",
    [
        (("speed_mps = 15.0", "speed_mps = 0.0"), "#7 (D15).speed_mps"),
        (("speed_mps = 15.0\n", ""), "#7 (D15).speed_mps: required"),
        (("friction = 0.5", "friction = 3.0"), "#8 (D25_FREE).friction"),
        (
            ("perturbation_level = 0.0", "perturbation_level = -1.0"),
            "(D25_FREE).perturbation_level",
        ),
        (('task = "driving"\nspeed_mps = 15.0', 'task = "drive"\nspeed_mps = 15.0'), "(D15).task"),
        (("friction = 1.0\n", "friction = 1.0\nboundary_deg = 5.0\n"), "(D15).boundary_deg"),
        (("speed_mps = 15.0", "speed_mps = nan"), "#7.speed_mps: must be a finite number"),
    ],
)
def test_bad_driving_conditions_name_the_file_and_field(edit, where):
    text = DRIVES.replace(*edit)
    assert text != DRIVES
    with pytest.raises(ProtocolError) as e:
        _protocol(text)
    assert str(e.value).startswith("drive.toml: [[conditions]]"), str(e.value)
    assert where in str(e.value), str(e.value)


@pytest.mark.parametrize(
    "table, message",
    [
        ("[vehicle]\nmass_kg = -1.0\n", "drive.toml: [vehicle].mass_kg: must be > 0"),
        ("[vehicle]\nwheels = 4\n", "drive.toml: [vehicle]: unknown field(s) ['wheels']"),
        ("[road]\nseed = 1.5\n", "drive.toml: [road].seed: expected a whole number"),
        ("[road]\nmin_radius_m = 900.0\n", "drive.toml: [road].min_radius_m: must not exceed"),
        ("[vehicle]\nsteering_ratio = inf\n", "drive.toml: [vehicle].steering_ratio: must be a"),
    ],
)
def test_bad_vehicle_and_road_tables_name_the_field(table, message):
    text = fast_protocol_text()
    head, conds = text.split("[[conditions]]", 1)
    with pytest.raises(ProtocolError) as e:
        parse_protocol(head + table + "[[conditions]]" + conds + DRIVES, "drive.toml")
    assert str(e.value).startswith(message), str(e.value)


def test_a_boundary_condition_may_not_carry_driving_fields():
    text = fast_protocol_text().replace('name = "BT12"', 'name = "BT12"\nspeed_mps = 10.0')
    with pytest.raises(ProtocolError, match=r"\(BT12\)\.speed_mps: only for a driving condition"):
        parse_protocol(text, "drive.toml")


def test_a_simulated_drive_keeps_the_lane_and_the_arm_follows_the_road():
    p = _protocol()
    plan = build_plan(p, 1)
    setup = plan.setup(_trial(plan, "D15"))
    assert setup.driving is not None and setup.schedule is None
    _, out = _batch(setup)
    for c in (*DRIVING_CHANNELS, *TRUTH_CHANNELS):
        assert c in out and np.all(np.isfinite(out[c])), c
    y, w = out["lateral_position_m"], out["lane_width_m"]
    margin = (w - p.vehicle.width_m) / 2
    assert np.mean(np.abs(y) < margin) > 0.99  # the driver drives: inside the lane
    assert np.std(out["heading_error_rad"]) < 0.05
    # The road alternates wide and narrow; narrow sections bring more grip and a stiffer arm.
    narrow, wide = w < 2.8, w > 3.4
    assert narrow.sum() > 1000 and wide.sum() > 1000
    k, g = out["true_k_i_Nm_per_rad"], out["true_grip_mean_N"]
    assert k[narrow].mean() > 1.3 * k[wide].mean()
    assert g[narrow].mean() > 1.3 * g[wide].mean()
    # The command is loop_command of (perturbation + aligning torque), sample by sample.
    limits = SafetyLimits(loop_stall_s=1.0).kernel_vector(setup.fs_hz)
    prev = 0.0
    for i in range(len(y)):
        prev_cmd = out["motor_command_Nm"][i - 1] if i else 0.0
        tp = out["perturbation_torque_Nm"][i] + out["aligning_torque_Nm"][i]
        prev = loop_command(
            tp,
            out["wheel_angle_rad"][i],
            out["wheel_velocity_rad_s"][i],
            prev_cmd,
            setup.wheel_k,
            setup.wheel_b,
            limits,
        )
        if i % 97 == 0:
            assert out["motor_command_Nm"][i] == prev
    # Aligning torque opposes the wheel angle most of the time (it centres the wheel).
    ta, th = out["aligning_torque_Nm"], out["wheel_angle_rad"]
    big = np.abs(th) > np.radians(10)
    assert np.mean(np.sign(ta[big]) == -np.sign(th[big])) > 0.8


def test_a_drive_without_perturbation_and_the_faster_road():
    p = _protocol()
    plan = build_plan(p, 2)
    setup = plan.setup(_trial(plan, "D25_FREE"))
    assert np.all(setup.perturbation_nm == 0.0)
    _, out = _batch(setup, subject=2)
    assert np.all(out["perturbation_torque_Nm"] == 0.0)
    assert out["road_distance_m"][-1] == pytest.approx(
        25.0 * len(setup.perturbation_nm) / 200, rel=0.01
    )
    margin = (out["lane_width_m"] - p.vehicle.width_m) / 2
    assert np.mean(np.abs(out["lateral_position_m"]) < margin) > 0.99


def test_batch_and_live_loop_give_the_same_drive():
    p = _protocol()
    subj = make_population(2, seed=11)[1]
    plan = build_plan(p, 2)
    short = replace(plan, trials=(_trial(plan, "D15"),))

    def collect(loop):
        got: dict = {}

        def sub(e):
            if isinstance(e, SamplesAcquired):
                for k, v in e.channels.items():
                    got.setdefault(k, []).append(np.asarray(v))

        eng = SessionEngine(short, loop)
        eng.subscribe(sub)
        eng.run()
        return {c: np.concatenate(v) for c, v in got.items()}

    batch_rig, live_rig = simulated_rig(subj), simulated_rig(subj)
    batch = collect(batch_rig.batch_loop(block_s=0.7))
    live = collect(live_rig.device_loop(block_s=0.05))
    assert batch.keys() == live.keys() - {"host_time_s"}  # batch: no read instants
    assert set(DRIVING_CHANNELS) | set(TRUTH_CHANNELS) <= set(batch)
    for c in batch:
        np.testing.assert_allclose(live[c], batch[c], rtol=0, atol=1e-12, err_msg=c)
    # The subject's display was shown the car (the dashboard's road view reads these).
    assert set(live_rig.display.vehicle) == set(DRIVING_CHANNELS)


def test_session_file_keeps_the_drive(tmp_path):
    p = _protocol()
    plan = build_plan(p, 1)
    short = replace(plan, trials=(_trial(plan, "D15"), _trial(plan, "BT12")))
    rig = simulated_rig(make_population(1, seed=3)[0])
    eng = SessionEngine(short, rig.batch_loop())
    w = SessionWriter(tmp_path / "S01.h5")
    eng.subscribe(w)
    eng.run()
    w.close()
    recs = {r.condition: r for r in SessionFile(tmp_path / "S01.h5").records()}
    d, b = recs["D15"], recs["BT12"]
    assert d.driving and d.time_varying and not b.driving and not b.time_varying
    attrs = json.loads(d.attrs["driving"])
    assert attrs["speed_mps"] == 15.0 and attrs["friction"] == 1.0
    assert attrs["vehicle"]["steering_ratio"] == p.vehicle.steering_ratio
    for c in (*DRIVING_CHANNELS, *TRUTH_CHANNELS):
        assert len(d.extra[c]) == d.n_samples, c
    assert not any(c in b.extra for c in DRIVING_CHANNELS)
    # Every channel says its unit, and the free-space check budgets for every channel written.
    raw = 0
    with h5py.File(tmp_path / "S01.h5", "r") as f:
        for key, g in f["trials"].items():
            names = [n for n, o in g.items() if isinstance(o, h5py.Dataset) and n != "marks"]
            assert all(g[n].attrs["units"] for n in names), key
            setup = next(short.setup(s) for s in short.trials if s.key() == key)
            # at most: a batch loop has no host clock (host_time_s)
            assert len(names) <= trial_channels(setup) <= len(names) + 1, key
            raw += sum(g[n].size * g[n].dtype.itemsize for n in names)
    assert session_bytes(short) >= raw > 0
    assert session_bytes(short, channels=11) < session_bytes(short)


def test_the_aligning_torque_is_inside_the_safety_limits():
    p = _protocol()
    plan = build_plan(p, 1)
    setup = plan.setup(_trial(plan, "D15"))
    # An absurd feel gain: the aligning torque alone would exceed the motor's limit.
    heavy = replace(setup.driving, vehicle=replace(setup.driving.vehicle, feel_gain=2.0))
    limits = SafetyLimits(max_torque_nm=3.0)
    _, out = _batch(replace(setup, driving=heavy), safety=limits)
    assert np.abs(out["aligning_torque_Nm"]).max() > 3.0
    assert np.abs(out["motor_command_Nm"]).max() <= 3.0 + 1e-12
    # A non-finite vehicle parameter: zero torque and the trial ends as a fault.
    broken = replace(setup.driving, vehicle=replace(setup.driving.vehicle, feel_gain=np.nan))
    from steerlab.protocols.engine import TrialFault

    rig = simulated_rig(make_population(1, seed=3)[0])
    with pytest.raises(TrialFault, match="non-finite motor command input"):
        for block in rig.batch_loop().run_trial(replace(setup, driving=broken), LoopControl()):
            assert np.all(block["motor_command_Nm"] == 0.0)


def test_a_protocol_file_in_the_working_folder_wins_over_the_shipped_one(tmp_path, monkeypatch):
    own = fast_protocol_text().replace('name = "pronker2017"', 'name = "mine"')
    (tmp_path / "driving.toml").write_text(own)
    monkeypatch.chdir(tmp_path)
    assert load_protocol("driving.toml").name == "mine"
    (tmp_path / "driving.toml").unlink()
    assert load_protocol("driving.toml").name == "driving"  # the shipped one, by name
    with pytest.raises(ProtocolError, match="nothere.toml: cannot read protocol file"):
        load_protocol("nothere.toml")
