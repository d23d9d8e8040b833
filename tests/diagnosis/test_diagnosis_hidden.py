"""Hide one mechanism in simulated data; the diagnosis must name it and recover it.

Honesty: the studies are simulated with ``steerlab simulate``'s engine, then exported and
re-imported (only the interchange columns and trial metadata survive; the truth lives in the
session files' root attributes "world" and "simulated_subject", which import does not write),
under neutral directory names; the raw session files are deleted before the diagnosis runs.
Small studies keep this quick: 200 Hz, three conditions (RT, BT12, PT), one subject (two for
drift, which shows only between trials).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import pytest

from steerlab.analysis.diagnosis import run_diagnosis
from steerlab.hardware.sim import mechanisms as m
from steerlab.hardware.sim.world import WorldConfig
from tests.helpers import fast_protocol_text

CONDITIONS = ("RT", "BT12", "PT")

# (mechanism, world mechanisms, parameter checked, true value, seed, subjects)
CASES = [
    ("reflex_delay", m.Mechanisms(reflex_delay=m.ReflexDelay(k_p=6.0, k_v=0.6)), "k_p", 6.0, 11, 1),
    ("coulomb_friction", m.Mechanisms(coulomb_friction=m.CoulombFriction(0.15)), "torque_nm",
     0.15, 12, 1),
    ("stiffness_nonlinearity",
     m.Mechanisms(stiffness_nonlinearity=m.StiffnessNonlinearity(200.0)), "k3_nm_per_rad3",
     200.0, 13, 1),
    ("actuator_lag", m.Mechanisms(actuator_lag=m.ActuatorLag(0.005)), "tau_s", 0.005, 14, 1),
    ("sensor_delay", m.Mechanisms(sensor_delay=m.SensorDelay(0.005)), "delay_s", 0.005, 15, 1),
    ("grip_scheduled_stiffness",
     m.Mechanisms(grip_scheduled_stiffness=m.GripScheduledStiffness(1.0)), "gain", 1.0, 16, 1),
    ("drift", m.Mechanisms(drift=m.Drift(0.04)), "rate_per_trial", 0.04, 17, 2),
]  # fmt: skip


def protocol(conditions=CONDITIONS) -> str:
    text = fast_protocol_text()
    head, _, rest = text.partition("[[conditions]]")
    blocks = ["[[conditions]]" + b for b in rest.split("[[conditions]]")]
    return head + "".join(b for b in blocks if any(f'name = "{c}"' in b for c in conditions))


def hidden_study(root: Path, mech: m.Mechanisms, seed: int, n_subjects: int = 1) -> Path:
    from steerlab.app.simulate import simulate_study
    from steerlab.protocols.interchange import export_study, import_study

    (root / "p.toml").write_text(protocol())
    world = WorldConfig(fs_hz=200.0, mechanisms=mech)
    simulate_study(n_subjects, root / "a", seed=seed, protocol_path=str(root / "p.toml"),
                   jobs=1, world=world)  # fmt: skip
    export_study(root / "a", root / "b", blind=True)
    # The exported metadata carry trial-level keys only: nothing about the world.
    for js in (root / "b").glob("*.json"):
        meta = json.loads(js.read_text())
        assert not {"world", "simulated_subject", "simulated", "mechanisms"} & set(meta)
        assert "mechanism" not in js.read_text().lower()
    import_study(root / "b", root / "c")
    for h5 in (root / "c").glob("*.h5"):
        with h5py.File(h5, "r") as f:
            assert "world" not in f.attrs and "simulated_subject" not in f.attrs
    shutil.rmtree(root / "a")
    shutil.rmtree(root / "b")
    return root / "c"


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES, ids=[f"case{i}" for i in range(len(CASES))])
def test_hidden_mechanism_is_named_recovered_and_gains(case, tmp_path_factory):
    name, mech, param, truth, seed, n_subjects = case
    root = tmp_path_factory.mktemp("run")
    res = run_diagnosis(hidden_study(root, mech, seed, n_subjects), root / "out")
    assert res.cause == name, res.summary()
    c = res.candidates[name]
    p = next(p for p in c["parameters"] if p["parameter"] == param)
    lo, hi = p["ci95"]
    # Recovered within its interval. A correct 95 % interval misses one run in twenty, so with
    # seven cases the test widens it to 99.9 % (3.29 standard errors) to stay deterministic
    # in spirit; the benchmark reports the 95 % coverage over many runs.
    half = (hi - lo) / 2
    mid = (hi + lo) / 2
    assert abs(truth - mid) <= half * 3.29 / 1.96, (p, res.summary())
    assert c["held_out_gain_minus2loglik"] > 0
    if name == "drift":
        assert res.gain["drift"]["vaf_td_pp"] > 0 or res.gain["drift"]["vaf_theta_pp"] > 0
    else:
        assert res.gain["held_out"] and res.gain["delta_bic"] < -10
        o = res.gain["overall"]
        # The held-out prediction improves where the mechanism shows: in the frequency
        # domain (FIT%) or in the time domain (VAF), by a positive amount overall.
        assert max(o["vaf_theta_pp"], o["vaf_td_pp"], o["fit_pp"]) > 0
    # Outputs exist and are self-describing.
    d = json.loads((root / "out" / "diagnosis.json").read_text())
    assert d["cause"] == name and name in d["causes"]
    if name == "sensor_delay":
        # The retained model is fitted to its optimum: a later step's candidate improves it by
        # no more than noise. (The delay's fit once ended with a trial's contact spring at its
        # bound, and every later candidate then "improved" it by 13 000 units.)
        later = [s["delta_minus2loglik"] for c in d["candidates"].values()
                 for s in c.get("later_steps", [])]  # fmt: skip
        assert later and max(later) < 50, later
    if name == "reflex_delay":
        # The simulator's reflex (40 ms, van der Helm's activation) is one of the family's
        # forms: it is among those consistent with the data, and the other activation is not
        # (at k_p 6 the delay is poorly determined: 25–60 ms fitted within 1.4 units).
        consistent = d["candidates"][name]["forms_consistent_with_data"]
        assert "delay 40 ms, van der Helm activation (2.17 Hz, ζ 0.7)" in consistent, consistent
        assert not [f for f in consistent if "fast" in f], consistent
        assert "<td>form: delay " in (root / "out" / "index.html").read_text()
    assert (root / "out" / "index.html").read_text().count("data:image/png;base64") >= 5
    assert f"[mechanisms.{name}]" in (root / "out" / "model.toml").read_text()


@pytest.mark.slow
def test_null_data_give_none(tmp_path_factory):
    root = tmp_path_factory.mktemp("run")
    res = run_diagnosis(hidden_study(root, m.Mechanisms(), seed=21), root / "out")
    assert res.cause == "none", res.summary()
    assert res.causes == []
    assert res.unexplained["within_noise"]
    assert "\n[mechanisms." not in (root / "out" / "model.toml").read_text()


@pytest.mark.slow
def test_an_effect_outside_the_candidates_is_unexplained(tmp_path_factory):
    """A torque sensor reading 10 % high: no candidate models a gain error."""
    import numpy as np

    from steerlab.app.simulate import simulate_study
    from steerlab.protocols.interchange import export_study, import_study

    root = tmp_path_factory.mktemp("run")
    (root / "p.toml").write_text(protocol())
    simulate_study(1, root / "a", seed=22, protocol_path=str(root / "p.toml"), jobs=1,
                   world=WorldConfig(fs_hz=200.0))  # fmt: skip
    export_study(root / "a", root / "b", blind=True)
    shutil.rmtree(root / "a")
    for p in (root / "b").glob("*.csv"):
        header = p.read_text().splitlines()[0].split(",")
        a = np.loadtxt(p, delimiter=",", skiprows=1)
        a[:, header.index("driver_torque_Nm")] *= 1.1
        np.savetxt(p, a, delimiter=",", header=",".join(header), comments="", fmt="%.9g")
    import_study(root / "b", root / "c")
    res = run_diagnosis(root / "c", None)
    assert res.cause == "unexplained", res.summary()
    assert not res.unexplained["within_noise"]
    assert "wheel" in res.unexplained["description"]
