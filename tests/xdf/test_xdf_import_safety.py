"""``steerlab import-xdf`` into several session files at once: all or nothing; names that two
streams would share kept apart; a failed write said, naming the file; each trial placed by its
own subject's clock, and by its samples' host times where the session recorded them."""

from __future__ import annotations

import errno
import json

import h5py
import numpy as np
import pytest

import steerlab.protocols.trial_extras as trial_extras
from steerlab.protocols.writelock import WriterLock
from steerlab.protocols.xdf_writer import ChannelSpec, XdfWriter
from tests.helpers import cli

from .test_xdf_import import T0, _emg, _header, _marker_stream, _set_clock, _trials, _write_xdf


def _s02_starts(folder):
    """S02's trials (its own order of conditions) at 1002 s and 1012 s on the LSL clock."""
    with h5py.File(folder / "S02.h5", "r", locking=False) as f:
        return dict(zip(sorted(f["trials"]), (1002.0, 1012.0), strict=True))


@pytest.fixture
def two_sessions(tmp_path, short_protocol_file):
    """S01.h5 and S02.h5 (two trials each, 800 samples at 200 Hz) on the recording's clock."""
    from steerlab.app.simulate import simulate_study

    out = tmp_path / "sessions"
    simulate_study(2, out, protocol_path=str(short_protocol_file), jobs=1, seed=0)
    _set_clock(out / "S01.h5")
    _set_clock(out / "S02.h5", _s02_starts(out))
    return out


def _bytes(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.glob("*.h5"))}


def test_a_locked_second_file_leaves_the_first_unwritten(tmp_path, two_sessions):
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf)
    before = _bytes(two_sessions)
    with WriterLock(two_sessions / "S02.h5", command="steerlab run --subject 2"):
        code, err = cli("import-xdf", xdf, "--session", two_sessions)
    assert code == 2
    assert "being written by process" in err and "steerlab run --subject 2" in err
    assert "nothing written to any of the session files" in err
    assert _bytes(two_sessions) == before


def test_names_taken_in_the_second_file_leave_the_first_unwritten(tmp_path, two_sessions):
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf)
    s02 = two_sessions / "S02.h5"
    assert cli("import-xdf", xdf, "--session", s02)[0] == 0
    before = _bytes(two_sessions)
    code, err = cli("import-xdf", xdf, "--session", two_sessions)
    assert code == 2
    assert f"{s02}: nothing written: /trials/01_PT_rep1_a1/xdf_EMG_flexor exists" in err
    assert "nothing written to any of the session files" in err
    assert _bytes(two_sessions) == before
    assert cli("import-xdf", xdf, "--session", two_sessions, "--replace")[0] == 0
    for h5 in (two_sessions / "S01.h5", s02):
        assert all("xdf_EMG_flexor" in r.extra for r in _trials(h5).values())


def test_a_write_failing_midway_says_which_files_were_written(tmp_path, two_sessions, monkeypatch):
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf)
    s01, s02 = two_sessions / "S01.h5", two_sessions / "S02.h5"
    before = s02.read_bytes()
    real = trial_extras.shutil.copy2

    def full_disk_on_s02(src, dst, *a, **kw):
        if str(src).endswith("S02.h5"):
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        return real(src, dst, *a, **kw)

    monkeypatch.setattr(trial_extras.shutil, "copy2", full_disk_on_s02)
    code, err = cli("import-xdf", xdf, "--session", two_sessions)
    assert code == 2
    assert f"{s02}: writing the imported data failed (No space left on device" in err
    assert f"already written: {s01}; not written: {s02}" in err
    assert "Traceback" not in err
    assert s02.read_bytes() == before
    assert not list(two_sessions.glob("*.importing"))
    assert "xdf_EMG_flexor" in _trials(s01)["01_BT12_rep1_a1"].extra


def test_a_full_disk_is_said_and_the_file_kept(tmp_path, session_dir, monkeypatch):
    h5 = session_dir / "S01.h5"
    _set_clock(h5)
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf)
    before = h5.read_bytes()

    def full(src, dst, *a, **kw):
        raise OSError(errno.ENOSPC, "No space left on device", str(dst))

    monkeypatch.setattr(trial_extras.shutil, "copy2", full)
    code, err = cli("import-xdf", xdf, "--session", h5)
    assert code == 2
    assert f"{h5}: writing the imported data failed (No space left on device" in err
    assert "the file is as it was" in err and "Traceback" not in err
    assert h5.read_bytes() == before
    assert not (session_dir / "S01.h5.importing").exists()


def test_channel_names_two_streams_would_share_are_kept_apart(tmp_path, session_dir):
    h5 = session_dir / "S01.h5"
    _set_clock(h5)
    xdf = tmp_path / "clash.xdf"
    t = np.arange(995.0, 1020.0, 0.001)
    with XdfWriter(xdf) as w:
        a = w.add_stream(_header("EMG", "EMG", "double64", 1, 1000, channels=[
            ChannelSpec("a_b", "mV")]))  # fmt: skip
        w.write_samples(a, t, np.full((len(t), 1), 1.0))
        b = w.add_stream(_header("EMG_a", "EMG", "double64", 1, 1000, channels=[
            ChannelSpec("b", "mV")]))  # fmt: skip
        w.write_samples(b, t, np.full((len(t), 1), 2.0))
    code, err = cli("import-xdf", xdf, "--session", h5)
    assert code == 0, err
    assert (
        "xdf_EMG_a_b would be written by stream 'EMG' (id 1, type EMG) and by stream 'EMG_a'" in err
    )
    assert "'EMG' → xdf_EMG_1, 'EMG_a' → xdf_EMG_a_2" in err
    extra = _trials(h5)["01_BT12_rep1_a1"].extra
    assert "xdf_EMG_a_b" not in extra
    np.testing.assert_array_equal(extra["xdf_EMG_1_a_b"], 1.0)
    np.testing.assert_array_equal(extra["xdf_EMG_a_2_b"], 2.0)
    with h5py.File(h5, "r", locking=False) as f:
        assert set(f["trials/01_BT12_rep1_a1/imported"]) == {"xdf_EMG_1", "xdf_EMG_a_2"}


def _markers(w, subject, recorder_ahead, starts):
    """A Steerlab marker stream of ``subject``, whose computer runs ``recorder_ahead`` s behind
    the recorder (its clock offsets), stamped at each trial start."""
    m = _marker_stream(w, subject)
    texts = [[json.dumps({"event": "trial_start", "key": k})] for k in starts]
    w.write_samples(m, [t - recorder_ahead for t in starts.values()], texts)
    for t in (990.0, 1005.0, 1020.0):
        w.write_clock_offset(m, t, recorder_ahead)


def test_by_the_clock_each_trial_follows_its_own_subjects_offsets(tmp_path, two_sessions):
    """S01's computer runs 2.5 s behind the recorder, S02's on it: one line through both
    streams' offsets would misplace both."""
    s01, s02 = two_sessions / "S01.h5", two_sessions / "S02.h5"
    _set_clock(s01, {k: t - 2.5 for k, t in T0.items()})
    s02_starts = _s02_starts(two_sessions)
    xdf = tmp_path / "lab.xdf"
    _write_xdf(
        xdf, extra=lambda w: (_markers(w, "S01", 2.5, T0), _markers(w, "S02", 0.0, s02_starts))
    )
    code, err = cli("import-xdf", xdf, "--session", two_sessions, "--match", "clock",
                    "--stream", "EMG")  # fmt: skip
    assert code == 0, err
    for h5, starts in ((s01, T0), (s02, s02_starts)):
        for key, t0 in starts.items():
            r = _trials(h5)[key]
            np.testing.assert_allclose(r.extra["xdf_EMG_flexor"], _emg(t0 + r.time_s)[:, 0],
                                       atol=5e-5)  # fmt: skip
    with h5py.File(s01, "r", locking=False) as f:
        by = f["trials/01_BT12_rep1_a1/xdf_EMG_flexor"].attrs["matched_by"]
        assert "clock offsets of stream 'Steerlab S01 markers'" in by


def test_by_the_clock_only_the_files_subjects_are_placed(tmp_path, two_sessions):
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf, extra=lambda w: _markers(w, "S01", 0.0, T0))
    before = (two_sessions / "S02.h5").read_bytes()
    code, err = cli("import-xdf", xdf, "--session", two_sessions, "--match", "clock")
    assert code == 0, err
    assert "2 trial(s) of subject(s) S02 not placed: the file's Steerlab streams are of S01" in err
    assert (two_sessions / "S02.h5").read_bytes() == before
    assert "xdf_EMG_flexor" in _trials(two_sessions / "S01.h5")["02_PT_rep1_a1"].extra


# -- each sample's host time (a loop that paused) -------------------------------------------------
PAUSE_AT, PAUSE_S, OFFSET = 300, 0.4, 700.0  # the loop stalls 0.4 s before sample 300


def _host_times(h5, source="host monotonic"):
    """Give each trial ``host_time_s`` (monotonic, with a pause) and ``lsl_clock_offset_s``, as
    a real-time session records them; returns each trial's true LSL times."""
    out = {}
    with h5py.File(h5, "r+", locking=False) as f:
        for key, t0 in T0.items():
            g = f["trials"][key]
            time_s = g["time_s"][()]
            lsl = t0 + time_s + np.where(np.arange(len(time_s)) >= PAUSE_AT, PAUSE_S, 0.0)
            if "host_time_s" in g:  # a simulated loop's own, replaced by one that paused
                del g["host_time_s"]
            g.create_dataset("host_time_s", data=lsl - OFFSET)
            g.attrs["lsl_clock_s"] = t0
            g.attrs["lsl_clock_offset_s"] = OFFSET
            g.attrs["lsl_clock_source"] = source
            out[key] = lsl
    return out


@pytest.mark.parametrize("match", ["clock", "markers"])
def test_a_paused_trial_is_placed_by_its_samples_host_times(tmp_path, session_dir, match):
    h5 = session_dir / "S01.h5"
    lsl = _host_times(h5)
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf, extra=lambda w: _markers(w, "S01", 0.0, T0))
    code, err = cli("import-xdf", xdf, "--session", h5, "--match", match, "--stream", "EMG")
    assert code == 0, err
    recs = _trials(h5)
    for key, t in lsl.items():
        got = recs[key].extra["xdf_EMG_flexor"]
        np.testing.assert_allclose(got, _emg(t)[:, 0], atol=5e-5)
        # Without the host times, the samples after the pause would be 0.4 s early.
        assert np.abs(got[PAUSE_AT:] - _emg(t[PAUSE_AT:] - PAUSE_S)[:, 0]).max() > 0.1
    if match == "clock":
        with h5py.File(h5, "r", locking=False) as f:
            by = f["trials/01_BT12_rep1_a1/xdf_EMG_flexor"].attrs["matched_by"]
            assert by.startswith("lsl_clock_s and its samples' host_time_s")


def test_a_synthetic_clock_keeps_lsl_clock_plus_time_s(tmp_path, session_dir):
    h5 = session_dir / "S01.h5"
    _host_times(h5, source="synthetic")
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf)
    code, err = cli("import-xdf", xdf, "--session", h5, "--stream", "EMG")
    assert code == 0, err
    for key, t0 in T0.items():
        r = _trials(h5)[key]
        np.testing.assert_allclose(r.extra["xdf_EMG_flexor"], _emg(t0 + r.time_s)[:, 0],
                                   atol=5e-5)  # fmt: skip
