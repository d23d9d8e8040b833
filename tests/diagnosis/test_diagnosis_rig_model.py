"""The diagnosis with the wheel a rig check measured (`diagnose --rig-model`, or the measured
wheel the session files record) instead of the nominal one, and the report naming it.

A study simulated with a non-nominal wheel (heavier, dry friction, an unbalanced wheel, a
lagging torque loop: `simulate --rig-model`) departs from the nominal wheel's simulation, and
the diagnosis names wheel-side mechanisms; simulated with the measured wheel, the baseline
explains it. The wheel is also fitted from the data alone (Tp − Td = (I s² + b s + k) θ at the
excited bins, an equation-error regression on the measured spectra that shares nothing with
the simulated world), which must find the rig.json's inertia, not Table 1's.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import pytest

from steerlab.analysis.diagnosis import DiagnosisError, run_diagnosis
from steerlab.analysis.diagnosis.wheel import choose_wheel
from steerlab.analysis.rigcheck import load_rig_model, rig_check_record
from steerlab.app.cli import main as cli_main
from steerlab.app.simulate import simulate_study
from steerlab.protocols.interchange import export_study, import_study
from tests.helpers import fast_protocol_text

# A rig unlike Table 1 (0.3 kg·m², no friction, no imbalance, no lag) where it matters most
# to a relaxed driver (RT): 20 % more inertia, 0.15 N·m of dry friction, 0.4 N·m of imbalance,
# 4 ms of actuator lag. b and k render as nominal.
WHEEL = {
    "inertia_kgm2": 0.36,
    "damping_Nms_per_rad": 2.0,
    "stiffness_Nm_per_rad": 4.2,
    "coulomb_Nm": 0.15,
    "gravity_Nm": 0.4,
    "delay_s": 0.004,
}
WHEEL_SIDE = {"actuator_lag", "coulomb_friction", "unexplained"}


def rig_json(path: Path, values: dict | None = None) -> Path:
    """A rig.json as `steerlab rig-check` writes it (the keys the simulator and the
    diagnosis read)."""
    d: dict = {k: {"value": v, "sem": 0.001} for k, v in (values or WHEEL).items()}
    d.update(
        format="steerlab-rig-check",
        vaf_percent=99.9,
        model={"friction_eps_rad_s": 0.01},
        verdict={"passed": False},
    )
    path.write_text(json.dumps(d))
    return path


def rt_protocol() -> str:
    head, _, rest = fast_protocol_text().partition("[[conditions]]")
    return head + "".join("[[conditions]]" + b for b in rest.split("[[conditions]]") if
                          'name = "RT"' in b)  # fmt: skip


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> tuple[Path, Path]:
    """(session directory, rig.json): one subject, RT only, two repetitions, 200 Hz,
    simulated with the measured wheel."""
    root = tmp_path_factory.mktemp("rigstudy")
    (root / "p.toml").write_text(rt_protocol())
    rig = rig_json(root / "rig.json")
    simulate_study(1, root / "s", seed=5, protocol_path=str(root / "p.toml"), jobs=1,
                   rig_model=rig)  # fmt: skip
    return root / "s", rig


@pytest.mark.slow
def test_measured_wheel_explains_what_the_nominal_one_names(study, tmp_path, capsys):
    data, rig = study
    # The nominal wheel: the rig's departure is named, on the wheel's side.
    nominal = run_diagnosis(
        data, None, nominal_wheel=True, candidates=("coulomb_friction", "actuator_lag")
    )
    assert nominal.wheel["source"] == "nominal" and nominal.wheel["chosen_by"] == "--nominal-wheel"
    assert nominal.cause in WHEEL_SIDE and set(nominal.causes) <= WHEEL_SIDE, nominal.summary()
    # The measured wheel (the command line, as a researcher runs it): nothing left to name.
    out = tmp_path / "d"
    argv = ["diagnose", str(data), "--out", str(out), "--rig-model", str(rig)]
    assert cli_main(argv) == 0
    printed = capsys.readouterr().out
    assert f"wheel: measured by a rig check ({rig}; --rig-model)" in printed
    assert "cause: none" in printed
    res = json.loads((out / "diagnosis.json").read_text())
    assert res["cause"] == "none" and res["unexplained"]["within_noise"]
    # The baseline's misfit: over ten times smaller with the measured wheel (74051 → 6836 in
    # −2 log L when written).
    m2ll = res["comparison"]["fit_quality"]["baseline"]["minus2loglik"]
    assert m2ll < nominal.comparison["fit_quality"]["baseline"]["minus2loglik"] / 5
    # Which wheel: in the results, the report and the model file.
    w = res["wheel"]
    assert w["source"] == "measured" and w["rig_json"] == str(rig)
    assert w["chosen_by"] == "--rig-model"
    assert (w["inertia_kgm2"], w["coulomb_Nm"], w["gravity_Nm"]) == (0.36, 0.15, 0.4)
    html = (out / "index.html").read_text()
    assert "<b>Wheel</b>: measured by a rig check (" in html and str(rig) in html
    model = (out / "model.toml").read_text()
    assert 'wheel = "measured"' in model and f'rig_model = "{rig}"' in model
    # Independent of the simulated world: the wheel fitted from the data's spectra is the
    # rig.json's (0.36 kg·m²; k + m·g·r = 4.6 N·m/rad at small angles), not Table 1's, and
    # the measured wheel fits the data better than the nominal one.
    for r in (w, nominal.wheel):
        fit = r["check"]["fitted_from_data"]
        assert fit["I_kgm2"] == pytest.approx(0.36, rel=0.05)
        assert fit["k_Nm_per_rad"] == pytest.approx(4.2 + 0.4, rel=0.05)
    assert w["check"]["misfit_percent"] < 0.7 * w["check"]["misfit_nominal_percent"]
    assert nominal.wheel["check"]["misfit_percent"] == w["check"]["misfit_nominal_percent"]


def test_default_is_the_wheel_the_session_files_record(study, tmp_path):
    data, rig = study
    choice = choose_wheel(data)
    assert choice.chosen_by == "recorded in the session files"
    wheel = choice.wheel(200.0)
    assert wheel.measured and wheel.rig_json == str(rig) and wheel.values == WHEEL
    assert wheel.rendered.inertia_kgm2 == 0.36
    assert wheel.mechanisms.wheel_imbalance.torque_nm == 0.4
    # --rig-model gives the same world; --nominal-wheel overrides, and says so.
    assert choose_wheel(data, rig_model=rig).wheel(200.0).mechanisms == wheel.mechanisms
    nominal = choose_wheel(data, nominal=True)
    assert nominal.rig_model is None and "overrides the measured wheel" in nominal.notes[0]
    # The record survives the interchange format (it is not simulation truth, even --blind).
    export_study(data, tmp_path / "csv", blind=True)
    import_study(tmp_path / "csv", tmp_path / "back")
    assert choose_wheel(tmp_path / "back").wheel(200.0).values == WHEEL
    # A rig session's record of its last rig check (`run --rig-check`) counts the same.
    other = tmp_path / "run"
    other.mkdir()
    f = shutil.copy(next(data.glob("*.h5")), other)
    with h5py.File(f, "r+") as h:
        del h.attrs["wheel_used"]
        h.attrs["rig_check"] = json.dumps(rig_check_record(load_rig_model(rig)))
    assert choose_wheel(other).wheel(200.0).values == WHEEL


def test_files_recording_different_wheels_are_refused(study, tmp_path, capsys):
    data, _ = study
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    src = next(data.glob("*.h5"))
    shutil.copy(src, mixed / "S01.h5")
    shutil.copy(src, mixed / "S02.h5")
    with h5py.File(mixed / "S02.h5", "r+") as h:
        h.attrs["wheel_used"] = json.dumps({"source": "nominal", "detail": "protocol x"})
    with pytest.raises(DiagnosisError, match="record different wheels"):
        choose_wheel(mixed)
    assert cli_main(["diagnose", str(mixed), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "S02.h5: nominal" in err and "--rig-model" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "content, field",
    [
        (None, "cannot read"),  # missing
        ("{not json", "not valid JSON"),
        ({k: v for k, v in WHEEL.items() if k != "coulomb_Nm"}, "coulomb_Nm"),
        ({**WHEEL, "inertia_kgm2": "heavy"}, "inertia_kgm2"),
        ({**WHEEL, "inertia_kgm2": -0.3}, "inertia_kgm2.value: must be > 0"),
        ({**WHEEL, "delay_s": -0.001}, "delay_s.value: must be ≥ 0"),
    ],
)
def test_bad_rig_json_names_the_file_and_the_field(study, tmp_path, capsys, content, field):
    data, _ = study
    path = tmp_path / "rig.json"
    if isinstance(content, str):
        path.write_text(content)
    elif isinstance(content, dict):
        rig_json(path, content)
    out = tmp_path / "o"
    assert cli_main(["diagnose", str(data), "--out", str(out), "--rig-model", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the progress line
    assert err.startswith(f"steerlab diagnose: error: {path}: ") and field in err
    assert not out.exists()  # nothing half-written
