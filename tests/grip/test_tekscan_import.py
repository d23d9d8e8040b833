"""``steerlab import-tekscan`` on the real TekScan exports: their frames kept exactly (Raw Sum
and all), a known lag recovered by cross-correlation within its reported uncertainty, a sync
frame used as given, the recorded channels untouched, and bad input said."""

from __future__ import annotations

import math
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from steerlab.analysis.alignment import (
    AlignmentError,
    align_by_sync,
    align_by_xcorr,
    choose_method,
    resample,
)
from steerlab.hardware.grip.tekscan import read_tekscan
from steerlab.protocols.datafile import SessionFile
from steerlab.protocols.tekscan_import import TekscanImportError, import_tekscan
from tests.helpers import cli

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tekscan"
FSCAN = DATA / "fscan_testL.asf"  # UNITS KPa, 205 frames at 0.032 s (walking: quasi-periodic)
ISCAN = DATA / "iscan_test.csv"  # UNITS raw, 309 frames at ~0.1 s, Raw Sum on each frame line

FS = 200.0
TRIAL_S = 17.5  # run-in 2 s + one 15 s period + fade-out 0.5 s
KEY = "01_BT12_rep1_a1"
N_PER_RAW = 0.0125

PROTOCOL = """
name = "tekscan-test"
loop_rate_hz = 200.0
[trial]
periods = 1
run_in_s = 2.0
fade_in_s = 0.5
fade_out_s = 0.5
familiarization_trials = 0
repetitions = 1
break_between_trials_s = 0.0
break_between_conditions_s = 0.0
[perturbation]
period_s = 15.0
n_bands = 10
first_bin = 3
f_max_hz = 5.0
seed = 1
[[conditions]]
name = "BT12"
boundary_deg = 12.0
"""


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    if not (FSCAN.is_file() and ISCAN.is_file()):
        pytest.skip(f"the public TekScan exports are not in {DATA} (a clone outside the lab"
                    " workspace)")  # fmt: skip
    from steerlab.app.simulate import simulate_study

    root = tmp_path_factory.mktemp("tekscan-session")
    (root / "p.toml").write_text(PROTOCOL)
    simulate_study(1, root / "s", protocol_path=str(root / "p.toml"), jobs=1, seed=4)
    return root / "s" / "S01.h5"


@pytest.fixture
def session(simulated, tmp_path):
    """A copy of the simulated session (S01.h5, one 17.5 s trial at 200 Hz) in its own folder."""
    d = tmp_path / "sessions"
    d.mkdir()
    shutil.copy2(simulated, d / "S01.h5")
    return d / "S01.h5"


def _force(movie):
    return movie.force_n(n_per_raw=N_PER_RAW) if movie.units == "raw" else movie.force_n()


def _glove_saw(h5, movie, lag, *, channel="grip_force_N", noise=0.2, seed=0):
    """Make the trial's glove channel the movie's force shifted by ``lag`` (trial time = movie
    time + lag; linear between frames, the movie's mean outside it) plus white noise of
    ``noise`` × its SD: the glove and the TekScan sensor saw the same grip."""
    f = _force(movie)
    rng = np.random.default_rng(seed)
    with h5py.File(h5, "r+", locking=False) as hf:
        g = hf["trials"][KEY]
        t = g["time_s"][()]
        x = np.interp(t - lag, movie.frame_times_s, f, left=f.mean(), right=f.mean())
        x = x + noise * f.std() * rng.standard_normal(len(t))
        g[channel][...] = x.astype(np.float32)
    return t


def _snapshot(h5):
    with h5py.File(h5, "r", locking=False) as f:
        g = f["trials"][KEY]
        out = {k: repr(v) for k, v in g.attrs.items()}
        for name, d in g.items():
            if isinstance(d, h5py.Dataset):
                out[name] = (str(d.dtype), d[()].tobytes(), dict(d.attrs))
        return out


def _stated_raw_sums(path):
    """The Raw Sum of each frame line, read from the text (not through the reader)."""
    return [int(m.group(1)) for m in re.finditer(r"Raw Sum=,,(\d+)", path.read_text())]


# -- the frames, exactly ---------------------------------------------------------------------------
def test_the_frames_are_kept_and_their_raw_sums_are_the_files_own(session):
    code, err = cli("import-tekscan", ISCAN, "--session", session, "--trial", "1",
                    "--n-per-raw", N_PER_RAW, "--sync-frame", 1)  # fmt: skip
    assert code == 0, err
    stated = _stated_raw_sums(ISCAN)
    assert len(stated) == 309
    with h5py.File(session, "r", locking=False) as f:
        g = f["trials"][KEY]["imported/tekscan_total"]
        assert g["stated_raw_sum"][()].tolist() == stated
        assert g["totals"][()].tolist() == stated  # the cells add up to it, frame by frame
        np.testing.assert_array_equal(g["force_N"][()], np.array(stated) * N_PER_RAW)
        assert g["frame_numbers"][()].tolist() == list(range(1, 310))
        assert g.attrs["movie_units"] == "raw" and g.attrs["n_per_raw"] == N_PER_RAW
        assert g.attrs["source_file"] == str(ISCAN)


# -- alignment by cross-correlation ----------------------------------------------------------------
@pytest.mark.parametrize(
    ("path", "hand", "channel", "lag"),
    [(ISCAN, "total", "grip_force_N", 3.217), (FSCAN, "left", "grip_force_left_N", 6.183)],
    ids=["iscan", "fscan"],
)
def test_a_known_lag_is_recovered_within_its_uncertainty(session, path, hand, channel, lag):
    movie = read_tekscan(path)
    t = _glove_saw(session, movie, lag, channel=channel)
    before = _snapshot(session)
    args = ["--n-per-raw", N_PER_RAW] if movie.units == "raw" else []
    code, err = cli("import-tekscan", path, "--hand", hand, "--session", session.parent,
                    "--trial", KEY, *args)  # fmt: skip
    assert code == 0, err
    name = "grip_force_tekscan_N" if hand == "total" else f"grip_force_tekscan_{hand}_N"
    with h5py.File(session, "r", locking=False) as f:
        d = f["trials"][KEY][name]
        a = dict(d.attrs)
        values = d[()]
    assert a["alignment_method"] == "cross_correlation" and a["reference_channel"] == channel
    frame = float(np.median(np.diff(movie.frame_times_s)))
    assert abs(a["lag_s"] - lag) <= 3 * a["lag_sem_s"], a
    assert 0 < a["lag_sem_s"] < frame / 4  # a fraction of a frame
    assert a["peak_correlation"] > 0.9
    assert "moving-block bootstrap" in a["alignment_detail"]
    # The force on the trial's samples: the latest frame at or before each (hold: the movie is
    # slower than the trial), NaN before its first frame and after its last.
    assert a["resample_method"] == "hold" and a["units"] == "N"
    trial_t = movie.frame_times_s + a["lag_s"]
    i = np.searchsorted(trial_t, t, side="right") - 1
    ok = (i >= 0) & (t - trial_t[np.maximum(i, 0)] <= 2.5 * frame)
    np.testing.assert_array_equal(values, np.where(ok, _force(movie)[np.maximum(i, 0)], np.nan))
    # The recorded channels, the glove's among them, are as they were.
    after = _snapshot(session)
    assert {k: v for k, v in after.items() if k in before} == before
    rec = next(r for r in SessionFile(session).records() if r.source.endswith(KEY))
    np.testing.assert_array_equal(rec.extra[name], values)


def test_sync_frame_aligns_by_the_frame(session):
    movie = read_tekscan(ISCAN)
    code, err = cli("import-tekscan", ISCAN, "--session", session, "--trial", KEY,
                    "--n-per-raw", N_PER_RAW, "--sync-frame", 21, "--sync-sample", 400,
                    "--method", "linear")  # fmt: skip
    assert code == 0, err
    with h5py.File(session, "r", locking=False) as f:
        g = f["trials"][KEY]
        a = dict(g["grip_force_tekscan_N"].attrs)
        values = g["grip_force_tekscan_N"][()]
        t = g["time_s"][()]
    # Frame 21 (at 2.02 s of the movie, as its frame line says) at trial sample 400 (2.0 s).
    assert movie.frame_times_s[20] == 2.02
    assert a["alignment_method"] == "sync" and a["lag_s"] == pytest.approx(-0.02, abs=1e-12)
    assert a["lag_sem_s"] == pytest.approx(math.sqrt(0.1**2 + 0.005**2) / math.sqrt(12))
    assert "reference_channel" not in a and a["resample_method"] == "linear"
    expected = np.interp(t, movie.frame_times_s - 0.02, _force(movie))
    np.testing.assert_allclose(values, expected, rtol=1e-12)


def test_importing_twice_is_refused_and_replace_replaces(session):
    args = ("import-tekscan", FSCAN, "--hand", "left", "--session", session, "--trial", "1",
            "--sync-frame", 1)  # fmt: skip
    assert cli(*args)[0] == 0
    once = session.read_bytes()
    code, err = cli(*args)
    assert code == 2
    assert "grip_force_tekscan_left_N exists" in err and "--replace" in err
    assert session.read_bytes() == once
    assert cli(*args, "--replace")[0] == 0
    assert cli("import-tekscan", FSCAN, "--hand", "right", "--session", session, "--trial", "1",
               "--sync-frame", 1)[0] == 0  # the other hand beside it  # fmt: skip
    with h5py.File(session, "r", locking=False) as f:
        g = f["trials"][KEY]
        assert {"grip_force_tekscan_left_N", "grip_force_tekscan_right_N"} <= set(g)
        assert set(g["imported"]) == {"tekscan_left", "tekscan_right"}


# -- bad input -------------------------------------------------------------------------------------
def _lines(path):
    return path.read_text().split("\n")


def test_a_malformed_header_is_named_and_nothing_written(session, tmp_path):
    lines = _lines(FSCAN)
    at = lines.index("ROWS 60") + 1
    lines[at - 1] = "ROWS=60"
    bad = tmp_path / "bad.asf"
    bad.write_text("\n".join(lines))
    before = session.read_bytes()
    code, err = cli("import-tekscan", bad, "--session", session, "--trial", "1")
    assert code == 2
    assert f"{bad}, line {at}: malformed header line 'ROWS=60'" in err
    assert session.read_bytes() == before


def test_a_frame_with_a_row_missing_is_named_and_nothing_written(session, tmp_path):
    lines = _lines(FSCAN)
    frame_3 = lines.index("Frame 3") + 1
    del lines[frame_3 + 10]
    bad = tmp_path / "short_frame.asf"
    bad.write_text("\n".join(lines))
    before = session.read_bytes()
    code, err = cli("import-tekscan", bad, "--session", session, "--trial", "1")
    assert code == 2
    assert f"{bad}, line " in err and f"frame 3 (line {frame_3}) has 59 rows, ROWS is 60" in err
    assert session.read_bytes() == before


def test_other_bad_input_is_said(session, tmp_path):
    def fails(*args, says):
        code, err = cli("import-tekscan", *args)
        assert code == 2, err
        assert says in err, err

    fails(ISCAN, "--session", session, "--trial", "1", says="--n-per-raw")
    fails(FSCAN, "--session", session, "--trial", "9", says=f"{session}: no trial with index 9")
    fails(FSCAN, "--session", session, "--trial", "x", says="no trial 'x'")
    fails(FSCAN, "--session", session, "--trial", "1", "--sync-frame", 999,
          says=f"{FSCAN}: no frame 999 (frames 1…205)")  # fmt: skip
    fails(FSCAN, "--session", session, "--trial", "1", "--sync-frame", 1, "--sync-sample",
          99999, says="no sample 99999")  # fmt: skip
    fails(FSCAN, "--session", session, "--trial", "1", "--sync-frame", 1, "--sync-mark",
          "sync", says="no mark of kind 'sync'")  # fmt: skip
    fails(FSCAN, "--session", session, "--trial", "1", "--sync-sample", 3,
          says="--sync-sample and --sync-mark need --sync-frame")  # fmt: skip
    fails(FSCAN, "--session", session, "--trial", "1", "--reference", "nope",
          says="no channel 'nope' for the reference")  # fmt: skip
    fails(tmp_path / "missing.asf", "--session", session, "--trial", "1", says="missing.asf")
    with pytest.raises(TekscanImportError, match="--hand must be one of left, right, total"):
        import_tekscan(FSCAN, session, trial="1", hand="both", dry_run=True)


# -- the computation alone -------------------------------------------------------------------------
def test_resampling_by_linear_interpolation_and_by_hold():
    t = np.array([0.0, 1.0, 2.0, 5.0])
    v = np.array([0.0, 10.0, 20.0, 50.0])
    q = np.array([-0.5, 0.0, 0.5, 1.0, 2.5, 4.9, 5.0, 5.1, 9.0])
    lin = resample(t, v, q, method="linear", max_gap_s=2.5)
    np.testing.assert_array_equal(lin, [np.nan, 0, 5, 10, np.nan, np.nan, 50, np.nan, np.nan])
    hold = resample(t, v, q, method="hold", max_gap_s=2.5)
    np.testing.assert_array_equal(hold, [np.nan, 0, 0, 10, 20, np.nan, 50, 50, np.nan])
    held = resample(t, v, q, method="hold")  # irregular: held for as long as it takes
    np.testing.assert_array_equal(held, [np.nan, 0, 0, 10, 20, 20, 50, 50, 50])
    assert choose_method(1000, 200) == "linear" and choose_method(10, 200) == "hold"
    assert choose_method(0, 200) == "hold"


def test_the_alignment_needs_something_to_correlate():
    t = np.arange(100) * 0.1
    with pytest.raises(AlignmentError, match="the recording is constant"):
        align_by_xcorr(t, np.ones(100), t, np.sin(t))
    with pytest.raises(AlignmentError, match="reference is constant"):
        align_by_xcorr(t, np.sin(t), t, np.ones(100))
    with pytest.raises(AlignmentError, match="10 are needed"):
        align_by_xcorr(t[:5], np.sin(t[:5]), t, np.sin(t))
    with pytest.raises(AlignmentError, match="no lag within"):
        align_by_xcorr(t, np.sin(t), t + 100, np.sin(t), max_lag_s=1.0)
    a = align_by_sync(2.0, 3.5, frame_interval_s=0.1)
    assert a.lag_s == 1.5 and a.sem_s == pytest.approx(0.1 / math.sqrt(12))
