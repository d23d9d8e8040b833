"""The steerlab command line, run as a user runs it (a subprocess)."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from collections import defaultdict

import numpy as np
import pytest

from steerlab.protocols.latin_square import williams_square
from steerlab.protocols.perturbation import design_multisine
from tests.helpers import ROOT, cli

CONDS = ["RT", "BT18", "BT12", "BT8", "BT5", "PT"]


def steerlab(*args, timeout=600):
    return subprocess.run(
        [sys.executable, "-m", "steerlab", *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_help_lists_the_commands():
    r = steerlab("--help")
    assert r.returncode == 0
    for cmd in ("simulate", "export", "import", "report"):
        assert cmd in r.stdout


def test_version_and_one_import_name(tmp_path):
    r = steerlab("--version")
    assert r.returncode == 0 and r.stdout.startswith("steerlab "), r.stdout + r.stderr
    # From outside the checkout, the code is reached as steerlab.<package> and the generic
    # folder names are not importable (they would collide with users' own modules).
    code = (
        "import importlib.util as u, steerlab.analysis, steerlab.hardware, steerlab.protocols,"
        " steerlab.app; print([m for m in ('app', 'analysis', 'hardware', 'protocols',"
        " 'benchmarks') if u.find_spec(m)])"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_simulate_refuses_existing_output_and_bad_input(tmp_path, fast_protocol_file):
    out = tmp_path / "s"
    sim = ("simulate", "--subjects", 1, "--out", out, "--protocol", fast_protocol_file)
    # Once as the user runs it (a process of its own), then in this process.
    assert steerlab(*sim).returncode == 0
    before = (out / "S01.h5").stat().st_mtime_ns
    code, err = cli(*sim)
    assert code == 2 and "--overwrite" in err
    assert (out / "S01.h5").stat().st_mtime_ns == before
    code, err = cli(*sim, "--overwrite")
    assert code == 0 and (out / "S01.h5").stat().st_mtime_ns != before
    code, err = cli(*sim, "--resume")
    assert code == 0  # nothing left to do
    bad = tmp_path / "bad.toml"
    bad.write_text(fast_protocol_file.read_text().replace("run_in_s = 2.0", "run_in_s = -1"))
    code, err = cli("simulate", "--subjects", 1, "--out", tmp_path / "n",
                      "--protocol", bad)  # fmt: skip
    assert code == 2
    assert str(bad) in err and "run_in_s" in err and "Traceback" not in err
    assert not (tmp_path / "n").exists()
    code, err = cli("simulate", "--subjects", 0, "--out", tmp_path / "z")
    assert code == 2 and "--subjects" in err


@pytest.mark.slow
def test_six_subjects_then_export_gives_108_trials_as_designed(tmp_path):
    """The issue's acceptance run, at the default protocol's 1 kHz."""
    out, csv = tmp_path / "study", tmp_path / "csv"
    r = steerlab("simulate", "--subjects", 6, "--out", out, "--seed", 1)
    assert r.returncode == 0, r.stderr
    assert "108/108" in r.stderr  # the progress bar reached the end
    r = steerlab("export", out, "--out", csv)
    assert r.returncode == 0, r.stderr
    metas = sorted(csv.glob("*.json"))
    assert len(metas) == 108 and len(list(csv.glob("*.csv"))) == 108
    design = design_multisine()
    by_subject = defaultdict(list)
    rms = defaultdict(list)
    grip = defaultdict(list)
    for m in metas:
        meta = json.loads(m.read_text())
        by_subject[meta["subject"]].append(meta)
        if meta["familiarization"]:
            continue
        data = np.loadtxt(m.with_suffix(".csv"), delimiter=",", skiprows=1, usecols=range(5))
        seg = slice(meta["measured_start"], meta["measured_stop"])
        tp = data[seg, 1]
        # Perturbation: exactly the design's bins, SD 2.26 within 1 %.
        spec = np.abs(np.fft.rfft(tp)) ** 2
        excited = np.flatnonzero(spec > 1e-6 * spec.max())
        assert excited.tolist() == design.bins.tolist()
        assert tp.std() == pytest.approx(2.26, rel=0.01)
        rms[meta["condition"]].append(data[seg, 3].std())
        grip[meta["condition"]].append(data[seg, 4].mean())
    square = williams_square(6)
    orders = []
    for subj, ms in sorted(by_subject.items()):
        ms.sort(key=lambda x: x["trial_index"])
        assert [x["trial_index"] for x in ms] == list(range(1, 19))
        order = [x["condition"] for x in ms][::3]
        assert order == [CONDS[i] for i in square[int(subj[1:]) - 1]]
        assert [(x["familiarization"], x["repetition"]) for x in ms[:3]] == [
            (True, 0),
            (False, 1),
            (False, 2),
        ]
        orders.append(order)
    # Balanced over the six subjects: each condition once per position, each pair once.
    for pos in range(6):
        assert sorted(o[pos] for o in orders) == sorted(CONDS)
    pairs = [(o[i], o[i + 1]) for o in orders for i in range(5)]
    assert sorted(pairs) == sorted(itertools.permutations(CONDS, 2))
    # Physiology: the wheel moves less and the grip rises as the boundary narrows.
    mean_rms = [np.mean(rms[c]) for c in CONDS]
    mean_grip = [np.mean(grip[c]) for c in CONDS]
    assert all(a > b for a, b in zip(mean_rms, mean_rms[1:], strict=False)), mean_rms
    assert all(a < b for a, b in zip(mean_grip[1:], mean_grip[2:], strict=False)), mean_grip
    assert abs(mean_grip[0] - mean_grip[1]) < 0.15 * mean_grip[0]  # RT ≈ BT18
