"""Bad or thin input: a clear message of what is missing, and what can still be said."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from steerlab.analysis.diagnosis import DiagnosisError, run_diagnosis
from steerlab.analysis.diagnosis.data import prepare_study
from steerlab.analysis.diagnosis.simulate import NOISELESS, ReplayBlocks
from steerlab.app.cli import main as cli_main
from steerlab.app.simulate import simulate_study
from steerlab.hardware.sim import mechanisms as m
from steerlab.hardware.sim.physiology import NOMINAL
from steerlab.hardware.sim.world import NoiseBlocks, World, WorldConfig
from steerlab.protocols.datafile import load_study
from steerlab.protocols.interchange import export_study, import_study
from tests.helpers import fast_protocol_text


def protocol(conditions=("RT", "BT12", "PT"), repetitions=2, wheel=None) -> str:
    text = fast_protocol_text()
    text = text.replace("repetitions = 2 ", f"repetitions = {repetitions} ")
    if wheel is not None:
        text = text.replace("stiffness_Nm_per_rad = 4.2", f"stiffness_Nm_per_rad = {wheel}")
    head, _, rest = text.partition("[[conditions]]")
    blocks = ["[[conditions]]" + b for b in rest.split("[[conditions]]")]
    return head + "".join(b for b in blocks if any(f'name = "{c}"' in b for c in conditions))


def exported(root: Path, text: str, seed: int = 41) -> Path:
    """Simulated study exported to CSV + JSON (so tests can damage it), raw files removed."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "p.toml").write_text(text)
    simulate_study(1, root / "a", seed=seed, protocol_path=str(root / "p.toml"), jobs=1,
                   world=WorldConfig(fs_hz=200.0))  # fmt: skip
    export_study(root / "a", root / "b")
    shutil.rmtree(root / "a")
    return root / "b"


def rewrite(csv_dir: Path, fn) -> None:
    """Apply fn(header, rows as array) → array to every trial CSV."""
    for p in csv_dir.glob("*.csv"):
        header = p.read_text().splitlines()[0].split(",")
        arr = np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)
        arr = fn(header, arr)
        np.savetxt(p, arr, delimiter=",", header=",".join(header), comments="", fmt="%.9g")


@pytest.fixture(scope="module")
def csv_study(tmp_path_factory) -> Path:
    return exported(tmp_path_factory.mktemp("in"), protocol(conditions=("BT12",)))


def imported(csv_dir: Path, dest: Path) -> Path:
    import_study(csv_dir, dest)
    return dest


def test_no_perturbation_is_refused_with_what_is_missing(csv_study, tmp_path):
    work = tmp_path / "b"
    shutil.copytree(csv_study, work)
    rewrite(work, lambda h, a: np.where(np.arange(a.shape[1]) == h.index(
        "perturbation_torque_Nm"), 0.0, a))  # fmt: skip
    with pytest.raises(DiagnosisError, match="no perturbation") as e:
        run_diagnosis(imported(work, tmp_path / "c"), None)
    assert "grip-force" in str(e.value)  # what can still be said


def test_trials_shorter_than_a_period_are_refused(csv_study, tmp_path):
    work = tmp_path / "b"
    shutil.copytree(csv_study, work)
    rewrite(work, lambda h, a: a[: a.shape[0] // 2])
    with pytest.raises(DiagnosisError, match="shorter than one perturbation period"):
        run_diagnosis(imported(work, tmp_path / "c"), None)


def test_flipped_torque_sign_is_named(csv_study, tmp_path):
    work = tmp_path / "b"
    shutil.copytree(csv_study, work)
    rewrite(work, lambda h, a: a * np.where(np.arange(a.shape[1]) == h.index(
        "driver_torque_Nm"), -1.0, 1.0))  # fmt: skip
    with pytest.raises(DiagnosisError, match="sign"):
        run_diagnosis(imported(work, tmp_path / "c"), None)


def test_data_of_another_rig_are_refused(tmp_path):
    csv = exported(tmp_path / "r", protocol(conditions=("BT12",), wheel=12.0))
    with pytest.raises(DiagnosisError, match="do not come from the rig") as e:
        prepare_study(load_study(imported(csv, tmp_path / "c")))
    assert "steerlab report" in str(e.value)
    # The command line reports it as bad input: one message, exit status 2.
    assert cli_main(["diagnose", str(tmp_path / "c"), "--out", str(tmp_path / "o")]) == 2


def test_one_repetition_and_one_condition_still_diagnose_with_their_limits(tmp_path, capsys):
    csv = exported(tmp_path / "r", protocol(conditions=("PT",), repetitions=1))
    data = imported(csv, tmp_path / "c")
    assert cli_main(["diagnose", str(data), "--out", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    assert "cause: none" in out
    assert "one measured repetition" in out and "single condition" in out
    res = run_diagnosis(data, None, candidates=("sensor_delay", "drift"))
    assert res.cause == "none" and res.gain["held_out"] is False
    assert (tmp_path / "o" / "index.html").exists() and (tmp_path / "o" / "model.toml").exists()


def test_replay_blocks_keep_the_worlds_noise_block_contract():
    """The diagnosis drives the world through its noise-block object: same keys, same
    samples when fed the world's own blocks."""
    cfg = WorldConfig(fs_hz=200.0, sensors=NOISELESS, mechanisms=m.Mechanisms(
        grip_scheduled_stiffness=m.GripScheduledStiffness(0.8)))  # fmt: skip
    b = NOMINAL["BT12"]
    ref = NoiseBlocks(cfg, b, 0.5, seed=7)
    blocks = [ref.next_block() for _ in range(12)]
    rem = np.concatenate([x["remnant_Nm"] for x in blocks])
    grip = np.concatenate([x["grip_true_N"] for x in blocks])
    replay = ReplayBlocks(200.0, grip, rem)
    assert set(replay.next_block()) == set(blocks[0])
    tp = np.sin(np.arange(len(rem)) / 15.0)
    w1 = World(cfg)
    w1.begin_trial(b, 0.5, seed=7)
    a = w1.run(tp)
    w2 = World(cfg)
    w2.begin_trial(b, 0.5, seed=0)
    w2.noise = ReplayBlocks(200.0, grip, rem)
    c = w2.run(tp)
    for k in ("wheel_angle_rad", "driver_torque_Nm"):
        np.testing.assert_allclose(c[k], a[k], rtol=0, atol=1e-12)
    # The whole series as one block (as the diagnosis replays a trial): the same samples.
    w3 = World(cfg)
    w3.begin_trial(b, 0.5, seed=0)
    w3.noise = ReplayBlocks(200.0, grip, rem, block=len(tp))
    d = w3.run(tp)
    for k in ("wheel_angle_rad", "driver_torque_Nm"):
        np.testing.assert_allclose(d[k], a[k], rtol=0, atol=1e-12)


def test_the_candidates_figure_marks_a_held_out_gain_not_tried_rather_than_zero():
    from types import SimpleNamespace

    from steerlab.analysis.diagnosis.report import fig_candidates

    cand = {
        "reflex_delay": {"delta_bic": -40.0, "held_out_gain_minus2loglik": 12.0, "retained": True},
        "sensor_delay": {"delta_bic": 3.0, "held_out_gain_minus2loglik": None,
                         "reason": "not better on BIC (so not tried on held-out data)"},
    }  # fmt: skip
    fig = fig_candidates(SimpleNamespace(candidates=cand))
    held_out = fig.axes[1]
    assert len(held_out.patches) == 1  # one bar: the candidate that was tried
    assert [t.get_text().strip() for t in held_out.texts] == ["not tried (ΔBIC)"]
    # A study without held-out data (one repetition): no candidate has a gain, none "failed".
    cand["reflex_delay"].update(held_out_gain_minus2loglik=None, reason="better on BIC (no "
                                "held-out check possible)")  # fmt: skip
    cand["sensor_delay"]["reason"] = "not better on BIC"
    texts = [
        t.get_text().strip() for t in fig_candidates(SimpleNamespace(candidates=cand)).axes[1].texts
    ]
    assert texts == ["none", "none"]
