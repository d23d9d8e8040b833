"""Time-varying trials: the segments reach the simulated driver, the display and the file."""

from __future__ import annotations

from dataclasses import replace

import h5py
import numpy as np
import pytest

from steerlab.hardware.sim.physiology import NOMINAL, make_population
from steerlab.hardware.sim.rig import SimulatedSubject, simulated_rig
from steerlab.hardware.sim.schedule import BehaviourSchedule
from steerlab.hardware.sim.world import NOISELESS_SENSORS as NOISELESS
from steerlab.hardware.sim.world import TRUTH_CHANNELS, World, WorldConfig
from steerlab.protocols.datafile import SessionFile, SessionWriter
from steerlab.protocols.engine import LoopControl, SessionEngine
from steerlab.protocols.events import SamplesAcquired
from steerlab.protocols.protocol import ProtocolError, load_protocol, parse_protocol
from steerlab.protocols.session import ConditionSchedule, build_plan
from tests.helpers import fast_protocol_text

SWITCH = """
[[conditions]]
name = "SWITCH"
instructions = "Follow the lines as they move."
segments = [
  {condition = "BT18", duration_s = 10.0},
  {condition = "PT", duration_s = 7.5},
  {condition = "BT8", duration_s = 12.0},
]
"""
RAMP = """
[[conditions]]
name = "RAMP"
transition = "ramp"
transition_s = 4.0
segments = [{condition = "RT", duration_s = 8.0}, {condition = "BT5", duration_s = 9.0},
            {condition = "BT12", duration_s = 9.0}]
"""


def _protocol(extra: str = SWITCH + RAMP, fs: float = 200.0):
    return parse_protocol(fast_protocol_text(fs) + extra, "tv.toml")


def _trial(plan, name: str):
    return next(t for t in plan.trials if t.condition == name and not t.familiarization)


def _run_batch(setup, subject_number=1, seed=5, **subject_kw):
    phys = make_population(subject_number, seed=seed)[subject_number - 1]
    rig = simulated_rig(phys)
    rig.subject = SimulatedSubject(phys, **subject_kw)
    blocks = list(rig.batch_loop().run_trial(setup, LoopControl()))
    return rig, {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}


def test_protocol_reads_segments_and_builds_the_schedule():
    p = _protocol()
    sw, rp = p.condition("SWITCH"), p.condition("RAMP")
    assert sw.time_varying and not p.condition("PT").time_varying
    assert sw.boundary_deg == 18.0 and sw.transition == "step"  # the first segment's lines
    assert rp.transition == "ramp" and rp.transition_s == 4.0
    assert p.stationary_condition_names == ["RT", "BT18", "BT12", "BT8", "BT5", "PT"]
    plan = build_plan(p, 1)
    setup = plan.setup(_trial(plan, "SWITCH"))
    sch = setup.schedule
    fs = p.loop_rate_hz
    # Segments cycle until the trial's end.
    assert sch.starts[:5] == (0, 2000, 3500, 5900, 7900)
    assert sch.conditions[:4] == ("BT18", "PT", "BT8", "BT18")
    assert sch.starts[-1] < setup.n_samples <= sch.starts[-1] + 12.0 * fs
    assert ConditionSchedule.from_dict(sch.to_dict()) == sch
    assert plan.setup(_trial(plan, "PT")).schedule is None
    # A ramp blends over transition_s and the display follows it in small steps.
    r = plan.setup(_trial(plan, "RAMP")).schedule
    prev, cur, w = r.blend(r.starts[2] - 1, 3)
    assert list(cur) == [1, 2, 2] and w[0] == 1.0 and w[1] == pytest.approx(1 / 800)
    changes = [c for c in r.display_changes() if r.starts[2] <= c[0] < r.starts[3]]
    assert changes[0][2] == pytest.approx(5.0 + 7.0 / 800) and changes[-1][2] == 12.0
    # From RT (no lines) the lines appear at once rather than ramping from infinity.
    assert [c for c in r.display_changes() if r.starts[1] <= c[0] < r.starts[2]] == [
        (r.starts[1], "BT5", 5.0)
    ]


@pytest.mark.parametrize(
    "extra, message",
    [
        (SWITCH.replace('"PT"', '"XX"'), r"segments\[2\]\.condition: 'XX' is not a stationary"),
        (SWITCH.replace("duration_s = 7.5", "duration_s = -1"), r"segments\[2\]\.duration_s"),
        (SWITCH.replace("duration_s = 7.5", 'duration_s = "x"'), r"segments\[2\]\.duration_s"),
        (SWITCH.replace('{condition = "PT", duration_s = 7.5}', '{condition = "PT"}'), "required"),
        (SWITCH.replace("duration_s = 7.5}", "duration_s = 7.5, gain = 2}"), "unknown field"),
        (
            SWITCH.replace('instructions = "Follow', 'boundary_deg = 3\ninstructions = "F'),
            "not all",
        ),
        (SWITCH.replace('name = "SWITCH"', 'name = "SWITCH"\ntransition = "jump"'), "transition"),
        (SWITCH.replace('name = "SWITCH"', 'name = "SWITCH"\ntransition_s = 2.0'), "only with"),
        (RAMP.replace("transition_s = 4.0", "transition_s = 20.0"), r"RAMP\)\.transition_s"),
        (RAMP.replace("transition_s = 4.0\n", ""), r"RAMP\)\.transition_s"),
        (
            SWITCH.replace("segments = [", 'segments = [{condition = "SWITCH", duration_s = 1},'),
            "SW",
        ),
        ('[[conditions]]\nname = "ONE"\nsegments = [{condition = "PT", duration_s = 1}]', "two"),
        ('[[conditions]]\nname = "PT2"\nboundary_deg = 1\ntransition = "ramp"', "only for"),
    ],
)
def test_bad_time_varying_conditions_name_file_and_field(tmp_path, extra, message):
    path = tmp_path / "tv.toml"
    path.write_text(fast_protocol_text() + extra)
    with pytest.raises(ProtocolError, match=message) as e:
        load_protocol(path)
    assert str(path) in str(e.value) and "[[conditions]] #7" in str(e.value)


def test_true_stiffness_follows_the_segments_first_order():
    p = _protocol()
    plan = build_plan(p, 1)
    setup = plan.setup(_trial(plan, "SWITCH"))
    tau = 0.25
    rig, d = _run_batch(setup, adaptation_tau_s=tau, grip_adaptation_tau_s=tau)
    sch, fs = setup.schedule, setup.fs_hz
    subj = rig.subject
    k_true = d["true_k_i_Nm_per_rad"]
    for i in range(1, 5):
        k0 = sch.starts[i]
        new = subj._behaviour_in(sch.conditions[i], setup, rig.cfg)
        old = subj._behaviour_in(sch.conditions[i - 1], setup, rig.cfg)
        # Settled in the old condition before the change, in the new one 8 τ after it.
        assert k_true[k0 - 1] == pytest.approx(old.arm.k_i, rel=1e-3)
        assert k_true[k0 + int(8 * tau * fs)] == pytest.approx(new.arm.k_i, rel=1e-3)
        # One τ after the change: 1 − 1/e of the way, on a log scale.
        frac = np.log(k_true[k0 + int(tau * fs) - 1] / old.arm.k_i) / np.log(
            new.arm.k_i / old.arm.k_i
        )
        assert frac == pytest.approx(1 - np.exp(-1), abs=0.01)
        g = d["true_grip_mean_N"][k0 + int(8 * tau * fs)]
        assert g == pytest.approx(new.grip_mean_n, rel=1e-3)
    # The measured grip force moves with the task (its SD is the condition's own).
    grip = d["grip_force_N"]
    pt, bt18 = sch.conditions.index("PT"), sch.conditions.index("BT18")
    in_pt = grip[sch.starts[pt] + int(2 * fs) : sch.starts[pt + 1]].mean()
    assert in_pt > 2.0 * grip[sch.starts[bt18] : sch.starts[bt18 + 1]].mean()
    assert set(TRUTH_CHANNELS) <= set(d)
    # The display was told the last change of task.
    last = sch.display_changes()[-1]
    assert (rig.display.condition, rig.display.boundary_deg) == (last[1], last[2])


def test_ramp_moves_the_target_linearly_on_a_log_scale():
    p = _protocol()
    plan = build_plan(p, 1)
    setup = plan.setup(_trial(plan, "RAMP"))
    rig, d = _run_batch(setup, adaptation_tau_s=0.0, grip_adaptation_tau_s=0.0)
    sch, fs, subj = setup.schedule, setup.fs_hz, rig.subject
    k0, n = sch.starts[2], sch.transition_samples
    a = subj._behaviour_in(sch.conditions[1], setup, rig.cfg).arm.k_i
    b = subj._behaviour_in(sch.conditions[2], setup, rig.cfg).arm.k_i
    got = np.log(d["true_k_i_Nm_per_rad"][k0 : k0 + n])
    want = np.log(a) + (np.log(b) - np.log(a)) * (np.arange(n) + 1) / n
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert n == int(4.0 * fs)


def test_the_arm_moves_with_the_logged_parameters():
    """Noise-free: after a switch, the world's admittance is the logged parameters' (dpar path)."""
    from steerlab.protocols.perturbation import design_multisine

    fs = 1000.0
    design = design_multisine()
    n = int(45 * fs)
    sch = ConditionSchedule("X", ("BT18", "PT"), (18.0, 0.0), (0, 2000), "step", 0, 2 * n, fs)
    quiet = {c: replace(NOMINAL[c], remnant_sd_nm=0.0) for c in ("BT18", "PT")}
    w = World(WorldConfig(fs_hz=fs, sensors=NOISELESS))
    w.begin_trial(quiet["BT18"], 0.5, 1, BehaviourSchedule(sch, (quiet["BT18"], quiet["PT"])))
    out = w.run(design.signal(np.arange(2 * n) / fs))
    assert out["true_k_i_Nm_per_rad"][-1] == pytest.approx(NOMINAL["PT"].arm.k_i)
    seg = slice(n, 2 * n)
    H = (
        np.fft.rfft(out["wheel_angle_rad"][seg])[design.bins]
        / np.fft.rfft(out["driver_torque_Nm"][seg])[design.bins]
    )
    truth = NOMINAL["PT"].arm.admittance(design.frequencies_hz)
    # Settled: exact ZOH at the logged parameters, as a stationary trial (within aliasing).
    assert np.max(np.abs(H / truth - 1)) < 2e-3


def test_batch_and_sample_by_sample_agree_on_a_time_varying_trial():
    p = _protocol(SWITCH + RAMP)
    subj = make_population(2, seed=11)[1]
    plan = build_plan(p, 2)
    tv = [t for t in plan.trials if t.condition in ("SWITCH", "RAMP")][:2]
    short = replace(plan, trials=tuple(tv))

    def collect(loop):
        got: dict = {}

        def sub(e):
            if isinstance(e, SamplesAcquired):
                for k, v in e.channels.items():
                    got.setdefault(e.key, {}).setdefault(k, []).append(np.asarray(v))

        eng = SessionEngine(short, loop)
        eng.subscribe(sub)
        eng.run()
        return {k: {c: np.concatenate(v) for c, v in d.items()} for k, d in got.items()}

    batch_rig, live_rig = simulated_rig(subj), simulated_rig(subj)
    batch = collect(batch_rig.batch_loop(block_s=0.7))
    live = collect(live_rig.device_loop(block_s=0.05))
    assert batch.keys() == live.keys() and len(batch) == 2
    for key in batch:
        assert batch[key].keys() == live[key].keys() - {"host_time_s"}  # batch: no read instants
        assert set(TRUTH_CHANNELS) <= set(batch[key])
        for c in batch[key]:
            np.testing.assert_allclose(live[key][c], batch[key][c], rtol=0, atol=1e-12, err_msg=c)
        assert np.ptp(batch[key]["true_k_i_Nm_per_rad"]) > 5.0  # it did vary
    assert live_rig.display.boundary_deg == batch_rig.display.boundary_deg


def test_session_file_keeps_the_schedule_and_the_truth(tmp_path):
    p = _protocol(SWITCH)
    plan = build_plan(p, 1)
    short = replace(plan, trials=(_trial(plan, "SWITCH"), _trial(plan, "BT12")))
    rig = simulated_rig(make_population(1, seed=2)[0])
    eng = SessionEngine(short, rig.batch_loop())
    writer = SessionWriter(tmp_path / "S01.h5")
    eng.subscribe(writer)
    eng.run()
    writer.close()
    recs = {r.condition: r for r in SessionFile(tmp_path / "S01.h5").records()}
    tv, st = recs["SWITCH"], recs["BT12"]
    sch = ConditionSchedule.from_dict(__import__("json").loads(tv.attrs["schedule"]))
    assert sch.conditions[:3] == ("BT18", "PT", "BT8")
    assert set(TRUTH_CHANNELS) <= set(tv.extra) and not set(TRUTH_CHANNELS) & set(st.extra)
    assert "schedule" not in st.attrs
    with h5py.File(tmp_path / "S01.h5", "r") as f:
        g = f["trials"][next(k for k in f["trials"] if "SWITCH" in k)]
        assert g["true_k_i_Nm_per_rad"].attrs["units"] == "N·m/rad"
