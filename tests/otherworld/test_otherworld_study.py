"""A study from the independent world goes through ``steerlab import`` and ``steerlab report``.

Nothing but the interchange files crosses over: the CSVs and JSONs are read by Steerlab's CLI,
the truth stays in ``truth.json`` and is compared here with the report's ``per_subject.csv``.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from steerlab.app.cli import main as steerlab
from steerlab.benchmarks.otherworld import (
    DEFAULT_ARM,
    WORLDS,
    Multisine,
    OtherworldError,
    generate_study,
    grip_of_stiffness,
    recovery,
)

ROOT = Path(__file__).resolve().parents[2]
FAST = dict(fs_hz=125.0, n_periods=1, run_in_s=(3.0, 6.0))


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """3 subjects × 3 conditions (45 s period, as a lab would record), imported and reported."""
    root = tmp_path_factory.mktemp("ow")
    truth = generate_study(root / "csv", subjects=3, conditions=("RT", "BT8", "PT"), seed=7, **FAST)
    assert steerlab(["import", str(root / "csv"), "--out", str(root / "sessions")]) == 0
    assert steerlab(["report", str(root / "sessions"), "--out", str(root / "report")]) == 0
    return root, truth


def test_study_files_follow_the_interchange_format(study):
    root, truth = study
    csvs = sorted((root / "csv").glob("*.csv"))
    assert len(csvs) == 3 * 3 * 2 == truth["n_trials"]
    for p in csvs:
        meta = json.loads(p.with_suffix(".json").read_text())
        assert meta["familiarization"] is False
        assert meta["repetition"] in (1, 2)
        assert meta["fs_hz"] == 125.0
        t = truth["trials"][p.stem]
        assert meta["trial_index"] == t["trial_index"]
        with open(p) as fh:
            header = next(csv.reader(fh))
        assert header == [
            "time_s",
            "perturbation_torque_Nm",
            "driver_torque_Nm",
            "wheel_angle_rad",
            "grip_force_N",
        ]
    # trial indices of a subject are 1..6 with both repetitions of a condition back to back
    s1 = sorted(
        (t["trial_index"], t["condition"], t["repetition"])
        for t in truth["trials"].values()
        if t["subject"] == "S01"
    )
    assert [i for i, _, _ in s1] == list(range(1, 7))
    assert all(s1[i][1] == s1[i + 1][1] and s1[i][2] == 1 for i in (0, 2, 4))


def test_trials_start_at_the_recorded_phase(study):
    root, truth = study
    d = Multisine(
        truth["perturbation"]["period_s"],
        np.array(truth["perturbation"]["bins"]),
        np.array(truth["perturbation"]["amplitudes_Nm"]),
        np.array(truth["perturbation"]["phases_rad"]),
    )
    offsets = []
    for name, t in list(truth["trials"].items())[:4]:
        data = np.loadtxt(root / "csv" / f"{name}.csv", delimiter=",", skiprows=1)
        after_fade = data[:, 0] > 1.0
        np.testing.assert_allclose(
            data[after_fade, 1], d.value(data[after_fade, 0] + t["phase_offset_s"]), atol=1e-6
        )
        offsets.append(t["phase_offset_s"])
    assert len(set(offsets)) == len(offsets)  # any phase, not aligned to the period


def test_grip_rises_with_stiffness(study):
    root, truth = study
    means = {}
    for name, t in truth["trials"].items():
        grip = np.loadtxt(root / "csv" / f"{name}.csv", delimiter=",", skiprows=1)[:, 4]
        means.setdefault(t["condition"], []).append(grip.mean())
        # slow 5 % fluctuation + 1 N noise around the map of this trial's stiffness
        assert grip.mean() == pytest.approx(grip_of_stiffness(t["arm"]["k_i"]), rel=0.1)
    assert np.mean(means["RT"]) < np.mean(means["BT8"]) < np.mean(means["PT"])


def test_report_runs_and_its_estimates_follow_the_truth(study):
    root, truth = study
    rep = root / "report"
    assert (rep / "index.html").exists() and (rep / "results.json").exists()
    rec = recovery(truth, rep / "per_subject.csv")
    assert len(rec["cells"]) == 9
    # every cell estimated (finite), and the stiffness ordering of the conditions comes out
    for k in ("k_i", "k_c", "b_i", "b_c"):
        assert rec["parameters"][k]["n"] == 9
    by = {}
    with open(rep / "per_subject.csv") as fh:
        for row in csv.DictReader(fh):
            if row["quantity"] == "k_i":
                by.setdefault(row["condition"], []).append(float(row["value"]))
    assert np.median(by["RT"]) < np.median(by["BT8"]) < np.median(by["PT"])
    # The size of the error is what issue 13 is about and is measured, not asserted, here:
    # recovery() is the tool; see the report of this branch for the figures.


def test_report_on_two_subjects_three_conditions(tmp_path):
    # The issue-18 study shape; Mauchly's test used to divide by zero here (n = 2, d = 2).
    generate_study(tmp_path / "csv", subjects=2, conditions=("BT18", "BT8", "PT"), seed=1, **FAST)
    assert steerlab(["import", str(tmp_path / "csv"), "--out", str(tmp_path / "s")]) == 0
    assert steerlab(["report", str(tmp_path / "s"), "--out", str(tmp_path / "r")]) == 0


def test_generate_study_checks_its_options(tmp_path):
    with pytest.raises(OtherworldError, match="unknown option"):
        generate_study(tmp_path / "a", subjects=1, conditions=("PT",), arm_intertia=0.1)
    with pytest.raises(OtherworldError, match="unknown condition"):
        generate_study(tmp_path / "a", subjects=1, conditions=("BT7",))
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "x.csv").write_text("")
    with pytest.raises(OtherworldError, match="not empty"):
        generate_study(tmp_path / "b", subjects=1, conditions=("PT",))


def test_population_defaults_follow_the_paper_trends():
    order = ["RT", "BT18", "BT12", "BT8", "BT5", "PT"]
    for k in ("k_i", "k_c", "b_c"):
        v = [DEFAULT_ARM[c][k] for c in order]
        assert all(a < b for a, b in zip(v, v[1:], strict=False)), k
    assert 10 <= DEFAULT_ARM["RT"]["k_i"] and DEFAULT_ARM["PT"]["k_i"] <= 500


def test_cli_writes_a_study_and_rejects_bad_input(tmp_path):
    out = tmp_path / "cli"
    cmd = [sys.executable, "-m", "steerlab.benchmarks.otherworld", "--out", str(out)]
    r = subprocess.run(
        cmd + ["--subjects", "1", "--conditions", "PT", "--fs", "100", "--periods", "1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["trials"] == 2 and summary["integrators"] == ["expm"]
    assert (out / "truth.json").exists()
    bad = subprocess.run(
        cmd + ["--overwrite", "--mechanism", "friction:sticky"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2
    assert "friction: form 'sticky'" in bad.stderr


@pytest.mark.parametrize("name", sorted(WORLDS))
def test_every_named_world_generates(tmp_path, name):
    truth = generate_study(
        tmp_path / name,
        subjects=1,
        conditions=("BT8",),
        seed=2,
        period_s=10.0,
        n_periods=1,
        run_in_s=(2.0, 2.0),
        **WORLDS[name],
    )
    for k, v in WORLDS[name].items():
        assert truth["options"][k] == v
    fs = truth["options"]["fs_hz"]
    data = np.loadtxt(next((tmp_path / name).glob("*.csv")), delimiter=",", skiprows=1)
    assert len(data) == int(12.0 * fs) and np.all(np.isfinite(data))
    assert 0.005 < data[:, 3].std() < 0.5  # a plausible wheel angle (rad)
