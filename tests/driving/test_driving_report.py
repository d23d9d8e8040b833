"""The report's driving section on a small simulated driving study (issue 19)."""

from __future__ import annotations

import json
import re

import pytest

from steerlab.analysis.report import write_report
from steerlab.analysis.study import AnalysisOptions
from steerlab.app.simulate import SimulationJob, run_subject
from steerlab.hardware.sim.world import WorldConfig
from tests.helpers import fast_protocol_text

DRIVES = """
[[conditions]]
name = "D15"
task = "driving"
speed_mps = 15.0
friction = 1.0

[[conditions]]
name = "D20_FREE"
task = "driving"
speed_mps = 20.0
friction = 0.5
perturbation_level = 0.0
"""


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp("drive")
    text = fast_protocol_text(200.0) + DRIVES
    text = re.sub(r"(?m)^familiarization_trials = \d+", "familiarization_trials = 0", text)
    text = re.sub(r"(?m)^repetitions = \d+", "repetitions = 1", text)
    proto = root / "drive.toml"
    proto.write_text(text)
    out = root / "sessions"
    out.mkdir()
    for n in (1, 2, 3):
        run_subject(SimulationJob(n, str(out), 7, str(proto), False, WorldConfig(), False))
    report = root / "report"
    # One weighting: the side-by-side table of the stationary analysis is not tested here.
    write_report(out, report, figures=True, options=AnalysisOptions(compare_weightings=False))
    return report


def test_the_report_has_a_driving_section(study):
    doc = json.loads((study / "results.json").read_text())
    page = (study / "index.html").read_text()
    assert 'id="driving"' in page and "data:image/png;base64" in page
    d = doc["driving"]
    assert not d["problems"], d["problems"]
    drives = d["drives"]
    assert len(drives) == 6  # 3 subjects × 2 drives
    # The boundary tasks are still analysed as before; the drives are not among them.
    assert doc["conditions"] == ["RT", "BT18", "BT12", "BT8", "BT5", "PT"]
    assert any("driving trial" in t["reason"] for t in doc["skipped_trials"])
    for x in drives:
        assert x["lane_departure_percent"] < 2.0, x["trial"]
        # Narrow sections: more grip and a stiffer arm (lower compliance), by the LPV and truly.
        n, w = x["sections"]["narrow"], x["sections"]["wide"]
        assert n["grip_N"] > w["grip_N"], x["trial"]
        assert n["lpv_compliance"] < w["lpv_compliance"], x["trial"]
        assert n["true_compliance"] < w["true_compliance"], x["trial"]
        assert "lpv" in x["vs_truth"]
        if x["perturbation_level"] == 0.0:
            assert x["lpv_vs_validator"] == {} and set(x["vs_truth"]) == {"lpv"}
        else:
            assert set(x["lpv_vs_validator"]) == {"sliding_window_10s", "grip_ekf"}
    s = d["summary"]
    # Admittance from grip alone, against the truth: within 25 % RMS on k_i (log).
    assert s["lpv_vs_truth"]["median_rms_log_k_i"] < 0.25
    assert s["lpv_vs_truth"]["drives"] == 6
    assert s["grip_ekf_vs_truth"]["drives"] == 3
    # Width: repeated-measures ANOVA over the 3 subjects, grip and true compliance.
    width = d["statistics"]["width"]
    assert width["grip_N"]["n_subjects"] == 3
    assert set(width["grip_N"]["conditions"]) == {"narrow", "wide"}
    assert width["grip_N"]["p"] < 0.05
    assert "speed" in d["statistics"] and "friction" in d["statistics"]
    assert d["drives"][0]["series_10Hz"]["lpv_k_i"]
