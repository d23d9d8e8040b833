"""The diagnosis on studies recorded by another lab's system (``shared/data/outside-worlds``).

Those studies come from a closed-loop simulator the team did not write: its wheel's damping and
spring are physical, it reads the angle and the driver torque at the end of the interval over
which it held the perturbation, its arm inertia is 0.07 kg·m² and its remnant enters at the arm.
They reach the diagnosis only through ``steerlab import`` of their interchange files; their
``truth.json`` is read by the test alone. Before the rig and the timing were identified from
the data, the null study was called "unexplained" (260× the noise power) and the reflex and
stiffening studies too.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from steerlab.analysis.diagnosis import run_diagnosis
from steerlab.analysis.rig_from_data import identify
from steerlab.app.cli import main as cli_main
from steerlab.protocols.datafile import load_study

ROOT = Path(
    os.environ.get(
        "STEERLAB_OUTSIDE_WORLDS",
        Path(__file__).resolve().parents[3] / "shared" / "data" / "outside-worlds",
    )
)
CASES = ("null", "sensor_delay", "reflex_delay", "stiffness_nonlinearity")

needs_data = pytest.mark.skipif(
    not (ROOT / "null" / "trials").is_dir(),
    reason=f"the outside studies are not at {ROOT} (set STEERLAB_OUTSIDE_WORLDS)",
)


def expected(case: str) -> str:
    """What the diagnosis should name, from the study's own truth (its ``case``)."""
    truth = json.loads((ROOT / case / "truth.json").read_text())
    kind = truth["case"]
    return "none" if kind == "null" else kind.split(":", 1)[1]


@pytest.fixture(scope="module")
def imported(tmp_path_factory) -> dict[str, Path]:
    out = {}
    for case in CASES:
        d = tmp_path_factory.mktemp(case)
        assert cli_main(["import", str(ROOT / case / "trials"), "--out", str(d / "s")]) == 0
        out[case] = d / "s"
    return out


@needs_data
def test_the_rig_and_timing_of_the_outside_system_are_found_in_its_data(imported):
    found = identify(load_study(imported["null"]))
    c = found.convention
    # Its makers' description: outputs read at the end of the interval, a physical wheel of
    # Table 1's values.
    assert c.rendering == "continuous" and found.rendering_told
    assert c.theta_offset_samples == 1.0 and c.torque_offset_samples == 1.0
    v = found.fits["continuous/free"].values
    assert v["inertia_kgm2"] == pytest.approx(0.3, rel=0.01)
    assert v["damping_Nms_per_rad"] == pytest.approx(2.0, rel=0.02)
    assert v["stiffness_Nm_per_rad"] == pytest.approx(4.2, rel=0.02)
    e = found.fits["continuous/nominal"].sem
    assert 0 < e["inertia_kgm2"] < 0.003 and 0 < e["theta_offset_samples"] < 0.05


@needs_data
def test_a_stated_torque_timing_alone_is_used_and_the_angle_found(imported):
    found = identify(load_study(imported["null"]), stated={"torque_offset_samples": -0.5})
    c = found.convention
    assert c.torque_offset_samples == -0.5 and c.theta_offset_samples == 1.0
    assert c.source["timing"] == "stated in part"


@needs_data
@pytest.mark.parametrize("case", ["null", "sensor_delay"])
def test_outside_study_is_diagnosed_as_its_truth(imported, case, tmp_path):
    res = run_diagnosis(imported[case], tmp_path / "d")
    assert res.cause == expected(case), res.summary()
    if case == "null":
        assert res.unexplained["within_noise"], res.unexplained
    # The convention is stated in every output, and never named as a mechanism.
    assert "rendered continuously" in res.summary()
    doc = json.loads((tmp_path / "d" / "diagnosis.json").read_text())
    conv = doc["rig_from_data"]["convention"]
    assert conv["rendering"] == "continuous" and conv["theta_offset_samples"] == 1.0
    assert "The rig and the timing, from the data" in (tmp_path / "d" / "index.html").read_text()
    if case == "sensor_delay":
        # Recorded 12 ms late: three samples, more than a convention's skew; the mechanism's.
        assert conv["torque_offset_samples"] == 1.0
        delay = res.candidates["sensor_delay"]["parameters"][0]["value"]
        assert delay == pytest.approx(0.012, abs=0.002)


@needs_data
@pytest.mark.slow
@pytest.mark.parametrize("case", ["reflex_delay", "stiffness_nonlinearity"])
def test_outside_arm_mechanism_is_named(imported, case):
    res = run_diagnosis(imported[case], None, jobs=2)
    assert res.cause == expected(case), res.summary()
