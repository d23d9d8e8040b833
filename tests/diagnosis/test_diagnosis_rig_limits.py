"""The rig's command limits, as the session files record them, are the ones simulated.

``steerlab run`` writes the rig's safety limits into every session file (``attrs["rig"]``). A
rig configured to clip at 3 N·m applies another torque than Steerlab's default 8 N·m would in
simulation; the diagnosis must simulate the recorded limits, or it reads the clipping as a
mechanism.
"""

from __future__ import annotations

import json
import shutil
import tomllib
from dataclasses import asdict
from pathlib import Path

import h5py
import pytest

from steerlab.analysis.diagnosis import run_diagnosis
from steerlab.analysis.diagnosis.data import recorded_rig_limits
from steerlab.analysis.rig_from_data import identify
from steerlab.hardware.safety import SafetyLimits
from steerlab.hardware.sim import world as world_module
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols.datafile import load_study
from tests.diagnosis.test_diagnosis_hidden import protocol

LOW = SafetyLimits(max_torque_nm=3.0)  # the fast protocol's multisine peaks at 5.3 N·m


@pytest.fixture(scope="module")
def clipped_study(tmp_path_factory) -> Path:
    """One subject, BT12 and PT at 200 Hz, on a simulated rig that clips at 3 N·m; the
    session files do not say so yet."""
    from steerlab.app.simulate import simulate_study

    root = tmp_path_factory.mktemp("clipped")
    (root / "p.toml").write_text(protocol(("BT12", "PT")))
    # The simulated world clips with SafetyLimits() unless given limits; simulate_study has
    # no option for a rig's limits (a simulated study is Steerlab's default rig).
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(world_module, "SafetyLimits", lambda: LOW)
        simulate_study(1, root / "a", seed=21, protocol_path=str(root / "p.toml"), jobs=1,
                       world=WorldConfig(fs_hz=200.0))  # fmt: skip
    with h5py.File(next((root / "a").glob("*.h5")), "r") as f:
        cmd = max(abs(g["motor_command_Nm"][:]).max() for g in f["trials"].values())
    assert cmd == pytest.approx(3.0)  # the command did clip
    return root / "a"


def _with_rig_record(src: Path, dst: Path, safety: dict) -> Path:
    shutil.copytree(src, dst)
    for p in dst.glob("*.h5"):
        with h5py.File(p, "a") as f:
            f.attrs["rig"] = json.dumps({"source": "lab.toml", "safety": safety})
    return dst


def test_recorded_limits_are_read_and_unusable_ones_named(clipped_study, tmp_path):
    assert recorded_rig_limits(clipped_study) == ({}, [])  # a simulated study records none
    d = _with_rig_record(clipped_study, tmp_path / "rec", asdict(LOW))
    limits, notes = recorded_rig_limits(d)
    assert list(limits.values()) == [LOW] and notes == []
    # Keys Steerlab does not know (a newer rig file's) are left out, not an error.
    newer = _with_rig_record(clipped_study, tmp_path / "newer", {**asdict(LOW), "jerk": 1.0})
    assert list(recorded_rig_limits(newer)[0].values()) == [LOW]
    bad = _with_rig_record(clipped_study, tmp_path / "bad", {"max_torque_nm": -1.0})
    limits, notes = recorded_rig_limits(bad)
    assert limits == {} and len(notes) == 1
    assert "S01.h5" in notes[0] and "rig.safety.max_torque_nm" in notes[0], notes
    # A record that is not JSON, or whose limits are not a table: named, and the defaults used.
    for i, raw in enumerate(("{not json", json.dumps({"safety": 8.0}))):
        d = tmp_path / f"raw{i}"
        shutil.copytree(clipped_study, d)
        with h5py.File(next(d.glob("*.h5")), "a") as f:
            f.attrs["rig"] = raw
        limits, notes = recorded_rig_limits(d)
        assert limits == {} and len(notes) == 1 and "unusable" in notes[0], notes


def test_steerlabs_own_recording_keeps_steerlabs_conventions(clipped_study):
    """Steerlab's own simulated rig, clipping its command (the wheel's equation then leaves
    2.3× the noise): the data's rig is Steerlab's (sampled, read at the command, the rig's
    inertia), whatever the clipping bends."""
    found = identify(load_study(clipped_study))
    assert found.convention.is_steerlab, found.sentence()
    assert found.convention.inertia_kgm2 == 0.3 and found.convention.sensor_skew_samples == 0.0


def test_a_study_clipped_by_its_rig_is_simulated_with_the_recorded_limits(clipped_study, tmp_path):
    d = _with_rig_record(clipped_study, tmp_path / "rec", asdict(LOW))
    res = run_diagnosis(d, tmp_path / "out")
    assert res.cause == "none", res.summary()
    assert any("limits the session files record (3 N·m" in n for n in res.notes), res.notes
    model = tomllib.loads((tmp_path / "out" / "model.toml").read_text())
    assert model["rig_command_limits"] == {"max_torque_nm": 3.0, "max_slew_nm_per_s": 400.0}


@pytest.mark.slow
def test_without_the_record_the_clipping_is_a_false_alarm(clipped_study):
    """The counterpart of the test above: the recorded limits are what make it ``none``
    (neither Steerlab's 8 N·m nor no limit reproduces a 3 N·m clip)."""
    res = run_diagnosis(clipped_study, None)
    assert res.cause != "none", res.summary()
