"""A study with time-varying trials: stationary analysis skips them, the report tracks them, and
the live tracker loads its calibration from the report's results.json."""

from __future__ import annotations

import json

import pytest

from steerlab.analysis.report import write_report
from steerlab.analysis.study import AnalysisOptions
from steerlab.analysis.tracking.online import OnlineTracker
from steerlab.app.simulate import simulate_study
from tests.helpers import fast_protocol_text

pytestmark = pytest.mark.filterwarnings("ignore:The inplace keyword")

SWITCH = """
[[conditions]]
name = "SWITCH"
segments = [{condition = "BT18", duration_s = 12.0}, {condition = "PT", duration_s = 12.0}]
"""

ONE_WEIGHTING = AnalysisOptions(compare_weightings=False)


def test_report_with_time_varying_trials(tmp_path):
    proto = tmp_path / "tv.toml"
    text = fast_protocol_text().replace("familiarization_trials = 1", "familiarization_trials = 0")
    proto.write_text(text.replace("repetitions = 2", "repetitions = 1") + SWITCH)
    # Three subjects: with two, analysis.stats.epsilon_hf divides by zero (not this issue).
    simulate_study(3, tmp_path / "s", protocol_path=str(proto), jobs=1, seed=3)
    # The stationary analysis's second weighting (the report's side-by-side table) is not what
    # is tested here; without it the report takes half the time.
    rep = write_report(tmp_path / "s", tmp_path / "r", options=ONE_WEIGHTING)
    doc = json.loads(rep.results_json.read_text(encoding="utf-8"))
    assert "SWITCH" not in doc["conditions"]
    skipped = [s for s in doc["skipped_trials"] if "SWITCH" in s["source"]]
    assert len(skipped) == 3 and all("time-varying" in s["reason"] for s in skipped)
    trk = doc["tracking"]
    assert len(trk["trials"]) == 3 and not trk["problems"]
    for t in trk["trials"]:
        assert t["schedule"]["conditions"][:2] == ["BT18", "PT"]
        assert set(t["trackers"]) == {"lpv", "grip_ekf"}
        assert t["trackers"]["grip_ekf"]["vaf_percent"] > 50.0
    page = rep.index_html.read_text(encoding="utf-8")
    assert 'id="tracking"' in page and "grip_ekf" in page
    live = OnlineTracker.from_results(rep.results_json, fs_hz=200.0)
    assert live.calibration.disturbance.angle_sd_rad == pytest.approx(
        trk["calibration"]["disturbance"]["angle_sd_rad"]
    )
