"""A rig check on a recording with hands on the wheel warns, in what it prints and in its page;
so does one whose values the recording does not determine. A hands-off recording does not.
With hands on the wheel the verdict is NOT VALID, not a pass or fail against the tolerances."""

from __future__ import annotations

import json
import os
import re
from dataclasses import replace
from pathlib import Path

import h5py
import pytest

from steerlab.app.cli import main
from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.rig import simulated_rig
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols.datafile import SessionWriter
from steerlab.protocols.engine import SessionEngine
from steerlab.protocols.protocol import parse_protocol
from steerlab.protocols.session import build_plan
from tests.helpers import fast_protocol_text
from tests.rigcheck.test_rigcheck_sim import hands_off_trial, world


@pytest.fixture(scope="module")
def held(tmp_path_factory):
    """A subject's familiarization and first measured trial (the subject holds the wheel)."""
    d = tmp_path_factory.mktemp("held")
    protocol = parse_protocol(fast_protocol_text(), "fast.toml")
    plan = build_plan(protocol, 2)
    plan = replace(plan, trials=plan.trials[:2])
    rig = simulated_rig(make_population(2, seed=1)[1], WorldConfig(fs_hz=200.0))
    engine = SessionEngine(plan, rig.batch_loop())
    path = d / f"{plan.subject}.h5"
    writer = SessionWriter(path, extra_attributes={"simulated": True})
    engine.subscribe(writer)
    engine.run()
    writer.close()
    with h5py.File(path, "r") as f:
        (key,) = [k for k in f["trials"] if "_rep1_" in k]
    return path, key


def _rig_check(capsys, out, *argv):
    code = main(["rig-check", *map(str, argv), "--out", str(out)])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    page = (out / "index.html").read_text()
    rig = json.loads((out / "rig.json").read_text())
    return printed.out, page, rig


def _vaf_shown(printed: str, page: str) -> tuple[str, str]:
    term = re.search(r"^\s*VAF\s+(\S+ %)$", printed, re.M)
    html = re.search(r"<tr><td>VAF</td><td>([^<]+)</td>", page)
    assert term and html, (printed, page)
    return term.group(1), html.group(1)


def _assert_not_valid(printed, page, rig):
    """The verdict is NOT VALID everywhere, and no check is called a pass or a FAIL."""
    assert "verdict: NOT VALID (hands on the wheel)" in printed, printed
    assert "FAIL" not in printed and "PASS" not in printed, printed
    assert "Rig check: <span class=bad>NOT VALID (hands on the wheel)</span>" in page
    assert "FAIL" not in page and ">pass<" not in page and "not judged" in page
    v = rig["verdict"]
    assert v["status"] == "NOT VALID" and v["passed"] is False
    assert v["not_valid_reason"] == "hands on the wheel"
    assert len(v["checks"]) == 7 and "tolerances" in v  # the comparisons stay, for the record
    term, html = _vaf_shown(printed, page)
    assert term == html == f"{rig['vaf_percent']:.2f} %", (term, html)
    # A held wheel's SEMs are large: written as numbers (± 130), not as 1.3e+02.
    assert not re.search(r"\de[+-]\d", printed + page), printed


def _assert_hands_on(printed, page, rig):
    warnings = rig["warnings"]
    assert "warning: hands on the wheel? driver_torque_Nm varies by" in printed, printed
    assert "warning: hands on the wheel? grip_force_N averages" in printed, printed
    # The values it cannot determine (a held wheel's stiffness and imbalance, here).
    assert "its SEM" in printed and "exceeds the value itself" in printed, printed
    assert "<h2 class=bad>Warnings</h2>" in page
    assert "hands on the wheel? driver_torque_Nm" in page and "exceeds the value itself" in page
    assert "<li>none</li>" not in page
    assert any(w.startswith("hands on the wheel?") for w in warnings)


def test_a_held_trial_of_a_session_file_warns(held, tmp_path, capsys):
    path, key = held
    printed, page, rig = _rig_check(capsys, tmp_path / "rc", "--recording", path,
                                    "--trial", key)  # fmt: skip
    _assert_hands_on(printed, page, rig)
    _assert_not_valid(printed, page, rig)
    assert "the trial is not a hands-off trial" in printed


def test_a_held_trial_exported_as_csv_warns(held, tmp_path, capsys):
    path, key = held
    assert main(["export", str(path.parent), "--out", str(tmp_path / "csv")]) == 0
    (csv,) = (tmp_path / "csv").glob("*_rep1.csv")
    capsys.readouterr()
    shown = _rig_check(capsys, tmp_path / "rc", "--recording", csv)
    _assert_hands_on(*shown)
    _assert_not_valid(*shown)


def test_a_hands_off_recording_has_no_warning(tmp_path, capsys):
    # Friction and imbalance near zero carry SEMs larger than themselves but well inside their
    # tolerances: a clear "none", not a warning.
    path = hands_off_trial(tmp_path / "rc.h5", world(), periods=1)
    printed, page, rig = _rig_check(capsys, tmp_path / "rc", "--recording", path)
    assert "warning" not in printed and rig["warnings"] == [], printed
    assert "Warnings</h2>" not in page and "<li>none</li>" in page
    v = rig["verdict"]
    assert v["status"] in ("PASS", "FAIL") and v["not_valid_reason"] is None
    assert v["passed"] is (v["status"] == "PASS") is all(c["passed"] for c in v["checks"])
    assert f"verdict: {v['status']}" in printed and "NOT VALID" not in printed + page
    term, html = _vaf_shown(printed, page)
    assert term == html == f"{rig['vaf_percent']:.2f} %", (term, html)


REAL = Path(
    os.environ.get(
        "STEERLAB_REAL_SENSODRIVE",
        Path(__file__).resolve().parents[3] / "shared" / "data" / "real-sensodrive",
    )
)


@pytest.mark.skipif(
    not (REAL / "sensodrive_handsoff.csv").is_file(),
    reason=f"the real SensoDrive recording is not at {REAL} (set STEERLAB_REAL_SENSODRIVE)",
)
def test_a_real_hands_off_recording_is_judged_not_taken_for_hands_on(tmp_path, capsys):
    # A real SENSO-Wheel, nobody touching it (the drive rendered 0.4 N·m·s/rad of damping):
    # the hands-on evidence must not fire on a wheel we did not simulate.
    out = tmp_path / "rc"
    assert main(["rig-check", "--recording", str(REAL / "sensodrive_handsoff.csv"),
                 "--out", str(out)]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    d = json.loads((out / "rig.json").read_text())
    assert d["warnings"] == [] and "hands on" not in printed, printed
    assert d["verdict"]["status"] in ("PASS", "FAIL") and "NOT VALID" not in printed
    assert d["damping_Nms_per_rad"]["value"] == pytest.approx(0.4, rel=0.05)
