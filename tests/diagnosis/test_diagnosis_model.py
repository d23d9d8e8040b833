"""model.toml: written by the diagnosis, read by ``simulate --model``, and the extended model
as the diagnosis' new baseline (diagnosing data simulated with it gives ``none``)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import pytest

from steerlab.analysis.diagnosis import run_diagnosis
from steerlab.app.simulate import simulate_study
from steerlab.hardware.sim import mechanisms as m
from steerlab.hardware.sim.model_file import (
    ModelFileError,
    ModelWorldConfig,
    load_world_model,
    world_model_text,
)
from steerlab.hardware.sim.physiology import NOMINAL, make_population
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols.interchange import export_study, import_study
from tests.helpers import fast_protocol_text

CONDITIONS = ("RT", "BT12", "PT")


def protocol() -> str:
    text = fast_protocol_text()
    head, _, rest = text.partition("[[conditions]]")
    blocks = ["[[conditions]]" + b for b in rest.split("[[conditions]]")]
    return head + "".join(b for b in blocks if any(f'name = "{c}"' in b for c in CONDITIONS))


def study(root: Path, world: WorldConfig, seed: int) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "p.toml").write_text(protocol())
    simulate_study(1, root / "a", seed=seed, protocol_path=str(root / "p.toml"), jobs=1,
                   world=world)  # fmt: skip
    export_study(root / "a", root / "b")
    import_study(root / "b", root / "c")
    shutil.rmtree(root / "a")
    shutil.rmtree(root / "b")
    return root / "c"


@pytest.mark.slow
def test_extended_model_is_the_new_baseline(tmp_path):
    hidden = m.Mechanisms(reflex_delay=m.ReflexDelay(k_p=6.0, k_v=0.6))
    first = run_diagnosis(
        study(tmp_path / "x", WorldConfig(fs_hz=200.0, mechanisms=hidden), 31),
        tmp_path / "d1",
    )
    assert first.cause == "reflex_delay"
    model = tmp_path / "d1" / "model.toml"
    cfg = load_world_model(model)
    assert isinstance(cfg, ModelWorldConfig) and cfg.mechanisms.active() == ["reflex_delay"]
    assert cfg.mechanisms.reflex_delay.k_p == pytest.approx(
        first.candidates["reflex_delay"]["parameters"][0]["value"], rel=1e-5
    )
    # New data from the extended model (another seed), diagnosed against it: nothing missing.
    data = study(tmp_path / "y", cfg, 32)
    again = run_diagnosis(data, tmp_path / "d2", model=model)
    assert again.cause == "none", again.summary()
    assert again.unexplained["within_noise"]
    # Against the paper's baseline the same data still need the reflex.
    plain = run_diagnosis(data, None)
    assert plain.cause == "reflex_delay"


def test_model_file_round_trip_and_population(tmp_path):
    base = {
        "RT": {
            "I_i_kgm2": 0.1, "b_i_Nms_per_rad": 1.2, "k_i_Nm_per_rad": 7.5,
            "b_c_Nms_per_rad": 2.0, "k_c_Nm_per_rad": 70.0, "grip_mean_N": 50.0,
            "grip_sd_N": 5.0, "remnant_sd_Nm": 0.3, "remnant_corner_Hz": 0.5, "n_subjects": 3,
        }
    }  # fmt: skip
    mech = m.Mechanisms(coulomb_friction=m.CoulombFriction(0.12))
    fitted = {"coulomb_friction": [{"parameter": "torque_nm", "value": 0.12, "se": 0.01,
                                    "ci95": [0.1, 0.14]}]}  # fmt: skip
    path = tmp_path / "model.toml"
    path.write_text(world_model_text(base, mech, fitted, {"fs_hz": 200.0}))
    cfg = load_world_model(path)
    assert cfg.mechanisms == mech
    assert cfg.baseline["RT"].arm.k_i == 7.5 and cfg.baseline["RT"].remnant_corner_hz == 0.5
    assert cfg.baseline["PT"] == NOMINAL["PT"]  # not in the file: the simulator's nominal
    # simulate draws its population around the model's baseline.
    (tmp_path / "p.toml").write_text(protocol())
    simulate_study(1, tmp_path / "s", seed=3, protocol_path=str(tmp_path / "p.toml"), jobs=1,
                   world=cfg)  # fmt: skip
    with h5py.File(next((tmp_path / "s").glob("*.h5")), "r") as f:
        subj = json.loads(f.attrs["simulated_subject"])
        world = json.loads(f.attrs["world"])
    assert world["mechanisms"]["coulomb_friction"]["torque_nm"] == 0.12
    # The same random draws as the default population, around the model's value instead.
    default = make_population(1, seed=3)[0].behaviour["RT"].arm.k_i
    assert subj["behaviour"]["RT"]["arm"]["k_i"] / default == pytest.approx(7.5 / 6.0)


@pytest.mark.parametrize(
    "text, message",
    [
        ('format = "other"\n', "not a Steerlab world model"),
        ('format = "steerlab-world-model"\n[mechanisms.magic]\nx = 1\n', "unknown mechanism"),
        ('format = "steerlab-world-model"\n[baseline.RT]\nk_i_Nm_per_rad = 5\n', "missing"),
        ('format = "steerlab-world-model"\n[mechanisms.coulomb_friction]\ntorque_nm = "a"\n',
         "finite number"),
        ("format = = \n", "not valid TOML"),
    ],
)  # fmt: skip
def test_bad_model_files_name_the_problem(tmp_path, text, message):
    p = tmp_path / "model.toml"
    p.write_text(text)
    with pytest.raises(ModelFileError, match=message):
        load_world_model(p)
