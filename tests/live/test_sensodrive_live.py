"""A SensoDrive rig end to end: ``steerlab run``'s code on the simulated SENSO-Wheel (its own
process, udp_loopback), the fault benchmark's rows for the faults only a SensoDrive host can
answer, and a rig that gives no driver torque."""

from __future__ import annotations

import json
import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from steerlab.app.run import RunError, run_session
from steerlab.hardware.rig import load_rig
from steerlab.protocols.datafile import SessionFile
from steerlab.protocols.engine import State

from .conftest import SHORT_PROTOCOL

ROOT = Path(__file__).resolve().parents[2]
SENSODRIVE_SIM = ROOT / "hardware" / "rigs" / "sensodrive-sim.toml"


def _rig(tmp_path: Path, *, rate_hz: float = 1000.0, **replace: str) -> Path:
    text = SENSODRIVE_SIM.read_text()
    text = re.sub(r"(?m)^loop_rate_hz = .*$", f"loop_rate_hz = {rate_hz:g}", text)
    # A shared, loaded test machine: only a real hang may abort (behaviour, not timing).
    text = re.sub(r"(?m)^loop_stall_s = .*$", "loop_stall_s = 0.5", text)
    for line, new in replace.items():
        text = re.sub(rf"(?m)^{line} = .*$", f"{line} = {new}", text)
    path = tmp_path / f"sensodrive-{rate_hz:g}.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("rate_hz", [500.0, 1000.0])
def test_a_session_runs_on_the_simulated_sensodrive(tmp_path, rate_hz):
    protocol = tmp_path / "short.toml"
    protocol.write_text(
        SHORT_PROTOCOL.replace("loop_rate_hz = 1000.0", f"loop_rate_hz = {rate_hz}")
    )
    said: list[str] = []
    state = run_session(
        str(_rig(tmp_path, rate_hz=rate_hz)), 1, tmp_path / "out",
        protocol_path=str(protocol), breaks=False, say=said.append, on_abort="stop",
    )  # fmt: skip
    assert state == State.DONE, said
    # The inertia the drive cannot render is said, not hidden.
    assert any("renders no inertia" in line and "0.3 kg·m²" in line for line in said), said
    sf = SessionFile(tmp_path / "out" / "S01.h5")
    recs = sf.records()
    assert [r.status for r in recs] == ["complete", "complete"]
    expected = round(4.0 * rate_hz)  # run-in 1 s + one 2.5 s period + fade-out 0.5 s
    for r in recs:
        assert r.n_samples == expected and r.fs_hz == rate_hz
        assert np.all(np.isfinite(r.driver_torque_Nm)) and np.all(np.isfinite(r.wheel_angle_rad))
        # The angle is the drive's 0.009° grid, in Steerlab's direction (sign −1 applied).
        steps = r.wheel_angle_rad / np.radians(0.009)
        assert np.max(np.abs(steps - np.round(steps))) < 1e-6
        # The hand sensor sees the perturbation pass through the wheel to the hands.
        assert np.corrcoef(r.perturbation_torque_Nm, r.driver_torque_Nm)[0, 1] > 0.3
    with h5py.File(tmp_path / "out" / "S01.h5", "r") as f:
        rig = json.loads(f.attrs["rig"])
    # What drove the wheel and what the subject felt, recorded with the session.
    assert rig["drive_kind"] == "sensodrive" and rig["drive_torque_sensor"] == "hand_sensor"
    assert rig["drive_wheel_inertia_kgm2"] == 0.3


@pytest.mark.parametrize(
    "name", ["host process killed", "CAN bus-off", "drive error state", "drive answers lost"]
)
def test_each_sensodrive_fault_ends_with_the_torque_off(tmp_path, name):
    """The fault benchmark's rows (``python -m benchmarks faults --drive sensodrive``): the
    simulated SENSO-Wheel has no watchdog of its own, so a killed loop process and a bus-off
    leave the torque to the host's side: the engine's process, and the driver's reopened bus."""
    from steerlab.benchmarks.faults import FAULTS_BY_KIND, run_fault

    (fault,) = [f for f in FAULTS_BY_KIND["sensodrive"] if f[0] == name]
    row = run_fault(*fault, tmp_path, stall_s=0.5, drive="sensodrive")
    assert row["status"] == "aborted" and re.search(fault[3], row["reason"]), row
    assert row["torque_before_nm"] != 0.0 and row["lost_samples"] == 0, row
    assert row["zero_torque_ms"] is not None, row
    assert 0 <= row["zero_torque_ms"] <= (row["timeout_ms"] or 0) + 100, row
    if name == "host process killed":
        assert row["guard_ms"] is not None and row["guard_ms"] < 100, row


def test_a_rig_without_a_driver_torque_refuses_a_session(tmp_path):
    rig = tmp_path / "no-sensor.toml"
    text = SENSODRIVE_SIM.read_text()
    table = text[text.index("[drive.torque_sensor]") : text.index("[safety]")]
    rig.write_text(text.replace(table, '[drive.torque_sensor]\nsource = "none"\n\n'))
    assert load_rig(rig).drive.torque_sensor.source == "none"
    with pytest.raises(RunError, match=r"source = \"none\".*gives no driver torque"):
        run_session(str(rig), 1, tmp_path / "out", breaks=False, say=lambda *_: None)
    assert not (tmp_path / "out" / "S01.h5").exists()


def test_a_wheel_lighter_than_the_protocols_is_said():
    from dataclasses import replace

    from steerlab.app.run import wheel_notes
    from steerlab.protocols.protocol import load_protocol

    rig = load_rig(SENSODRIVE_SIM)
    bare = replace(rig, drive=replace(rig.drive, wheel_inertia_kgm2=0.05))
    (note,) = wheel_notes(bare, load_protocol())
    assert "0.05 kg·m²" in note and "not the protocol's 0.3 kg·m²" in note
    assert wheel_notes(load_rig(None), load_protocol()) == []  # its rig file states none


def test_the_safety_layer_bounds_the_whole_torque_the_drive_applies(tmp_path):
    """The SENSO-Wheel adds the spring and damper itself; the host's limits must still hold
    for the torque on the wheel (the drive's own report of it, ``motor_torque_Nm``), not only
    for the part the host sends."""
    limit = 1.5  # well below what the perturbation, spring and damper together ask
    rig = _rig(tmp_path, max_torque_nm=f"{limit}")
    protocol = tmp_path / "short.toml"
    protocol.write_text(SHORT_PROTOCOL)
    state = run_session(
        str(rig), 1, tmp_path / "out", protocol_path=str(protocol), breaks=False,
        say=lambda *_: None, on_abort="stop",
    )  # fmt: skip
    assert state == State.DONE
    with h5py.File(tmp_path / "out" / "S01.h5", "r") as f:
        for name, g in f["trials"].items():
            command = g["motor_command_Nm"][()]
            applied = g["motor_torque_Nm"][()] * g["motor_torque_Nm"].attrs.get("scale_factor", 1)
            assert np.max(np.abs(command)) <= limit + 1e-6, name
            assert np.mean(np.abs(command) > limit - 0.01) > 0.01, name  # the limit did bind
            # The drive's damper sees its own velocity, the host's compensation a filtered one
            # (about 5.6 ms late): the whole torque is bounded up to b·Δω, a few tenths of a
            # N·m here. Sent uncompensated, the spring and damper took it to 2.4 N·m.
            assert np.max(np.abs(applied)) <= limit + 0.5, (name, np.max(np.abs(applied)))


def test_a_rig_without_a_driver_torque_still_runs_a_hands_off_rig_check(tmp_path):
    """The wheel alone needs no driver torque: the rig check's hands-off trial runs to its end
    (its driver torque recorded as NaN) on a rig whose file gives none."""
    from steerlab.app.rigcheck import run_rig_check

    rig = tmp_path / "no-sensor.toml"
    text = _rig(tmp_path).read_text()
    table = text[text.index("[drive.torque_sensor]") : text.index("[safety]")]
    rig.write_text(text.replace(table, '[drive.torque_sensor]\nsource = "none"\n\n'))
    protocol = tmp_path / "short.toml"
    protocol.write_text(SHORT_PROTOCOL)
    try:
        run_rig_check(
            str(rig), tmp_path / "check", periods=1, protocol_path=str(protocol),
            say=lambda *_: None,
        )  # fmt: skip
    except Exception as e:  # the fit of so short a trial may fail; the trial is what counts
        assert "driver torque" not in str(e), e
    (rec,) = SessionFile(tmp_path / "check" / "rigcheck.h5").records()
    assert rec.status == "complete", rec.abort_reason
    assert np.all(np.isnan(rec.driver_torque_Nm)) and np.std(rec.wheel_angle_rad) > 0
