"""``steerlab import-xdf``: another device's streams onto a session's trials, on the trials' own
LSL clock or by Steerlab's markers; the recorded channels untouched; bad input said."""

from __future__ import annotations

import json

import h5py
import numpy as np

from steerlab.protocols.datafile import SessionFile
from steerlab.protocols.writelock import WriterLock
from steerlab.protocols.xdf_import import read_xdf
from steerlab.protocols.xdf_writer import ChannelSpec, XdfWriter, stream_header_xml
from tests.helpers import cli

from .conftest import MINIMAL, SHORT_TRIAL_SAMPLES, needs_public_files

FS = 200.0
T0 = {"01_BT12_rep1_a1": 1000.0, "02_PT_rep1_a1": 1010.0}  # the trials' LSL clock, s
EMG_HZ, EMG_F = 1000.0, (3.0, 7.5)  # the EMG stream's rate, and its two channels' sines


def _set_clock(path, clocks=T0):
    with h5py.File(path, "r+", locking=False) as f:
        for key, t0 in clocks.items():
            if t0 is None:
                f["trials"][key].attrs.pop("lsl_clock_s", None)
            else:
                f["trials"][key].attrs["lsl_clock_s"] = t0


def _emg(t):
    return np.column_stack([np.sin(2 * np.pi * f * t) for f in EMG_F])


def _header(name, typ, fmt, n, srate, **kw):
    return stream_header_xml(name=name, type=typ, channel_count=n, nominal_srate=srate,
                             channel_format=fmt, **kw)  # fmt: skip


def _write_xdf(path, *, emg_span=(995.0, 1020.0), extra=None):
    """EMG (1 kHz, two sines, mV) over ``emg_span`` on the session's clock, a 20 Hz force in N,
    and a string stream of events."""
    t = np.arange(emg_span[0], emg_span[1], 1 / EMG_HZ)
    ft = np.arange(999.0, 1016.0, 0.05)
    with XdfWriter(path) as w:
        e = w.add_stream(_header("EMG", "EMG", "double64", 2, EMG_HZ, channels=[
            ChannelSpec("flexor", "mV"), ChannelSpec("extensor", "mV")]))  # fmt: skip
        w.write_samples(e, t, _emg(t))
        f = w.add_stream(_header("Plate", "Force", "float32", 1, 20, channels=[
            ChannelSpec("Fz", "N")]))  # fmt: skip
        w.write_samples(f, ft, (10 * ft).astype(np.float32)[:, None])
        m = w.add_stream(_header("Cues", "Markers", "string", 1, 0))
        w.write_samples(m, [1001.0, 1011.5], [["go"], ["stop"]])
        if extra:
            extra(w)
    return t, ft


def _snapshot(path):
    """Every recorded dataset's bytes and attributes, and every attribute of the file."""
    out = {}
    with h5py.File(path, "r", locking=False) as f:
        out["/"] = {k: repr(v) for k, v in f.attrs.items()}
        for key, g in f["trials"].items():
            out[key] = {k: repr(v) for k, v in g.attrs.items()}
            for name, d in g.items():
                if isinstance(d, h5py.Dataset):
                    out[f"{key}/{name}"] = (
                        str(d.dtype),
                        d[()].tobytes(),
                        {k: repr(v) for k, v in d.attrs.items()},
                    )
    return out


def _trials(path):
    return {r.source.rsplit("/", 1)[1]: r for r in SessionFile(path).records()}


def test_a_stream_on_the_sessions_clock_lands_on_every_trial_sample(tmp_path, session_dir):
    h5 = session_dir / "S01.h5"
    _set_clock(h5)
    before = _snapshot(h5)
    xdf = tmp_path / "lab.xdf"
    t_emg, ft = _write_xdf(xdf)
    code, err = cli("import-xdf", xdf, "--session", session_dir)
    assert code == 0, err
    # The recorded channels and attributes are byte for byte what they were.
    after = _snapshot(h5)
    for k, v in before.items():
        if "/" in k and k != "/":
            assert after[k] == v, k
    assert {k: v for k, v in after.items() if k in before and "/" not in k} == \
        {k: v for k, v in before.items() if "/" not in k}  # fmt: skip
    recs = _trials(h5)
    for key, t0 in T0.items():
        r = recs[key]
        assert r.n_samples == SHORT_TRIAL_SAMPLES
        t = t0 + r.time_s
        # Linear interpolation of a 1 kHz sine: error ≤ (2πf)² dt² / 8.
        for k, name in enumerate(("xdf_EMG_flexor", "xdf_EMG_extensor")):
            bound = (2 * np.pi * EMG_F[k]) ** 2 / EMG_HZ**2 / 8
            np.testing.assert_allclose(r.extra[name], _emg(t)[:, k], atol=bound * 1.01, rtol=0)
        # The 20 Hz force is held (zero-order hold): the latest sample at or before each time.
        i = np.searchsorted(ft, t, side="right") - 1
        np.testing.assert_array_equal(r.extra["xdf_Plate_Fz"], (10 * ft).astype(np.float32)[i])
    with h5py.File(h5, "r", locking=False) as f:
        g = f["trials/01_BT12_rep1_a1"]
        d = g["xdf_EMG_flexor"]
        assert d.attrs["units"] == "mV" and d.attrs["resample_method"] == "linear"
        assert d.attrs["stream_name"] == "EMG" and d.attrs["imported_by"] == "steerlab import-xdf"
        assert "lsl_clock_s" in d.attrs["matched_by"]
        assert g["xdf_Plate_Fz"].attrs["resample_method"] == "hold"
        assert g["xdf_Plate_Fz"].attrs["units"] == "N"
        # The stream's own samples within the trial, as recorded, on the trial's time line.
        src = g["imported/xdf_EMG"]
        inside = (t_emg >= 1000.0 - 0.0025) & (t_emg <= 1000.0 + 3.995 + 0.0025)
        np.testing.assert_array_equal(src["values"][()], _emg(t_emg[inside]))
        np.testing.assert_allclose(src["time_s"][()], t_emg[inside] - 1000.0, atol=1e-9)
        assert src.attrs["n_source_samples"] == inside.sum()
        cues = g["imported/xdf_Cues"]
        assert [x.decode() for x in cues["text"][()].ravel()] == ["go"]
        assert cues["time_s"][()].tolist() == [1.0]
        assert "xdf_Cues_ch1" not in g  # text gets no channel


def test_importing_twice_is_refused_and_replace_replaces(tmp_path, session_dir):
    h5 = session_dir / "S01.h5"
    _set_clock(h5)
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf)
    assert cli("import-xdf", xdf, "--session", h5)[0] == 0
    once = _snapshot(h5)
    code, err = cli("import-xdf", xdf, "--session", h5)
    assert code == 2
    assert f"{h5}: nothing written" in err
    assert "/trials/01_BT12_rep1_a1/xdf_EMG_flexor exists" in err and "--replace" in err
    assert _snapshot(h5) == once
    code, err = cli("import-xdf", xdf, "--session", h5, "--replace")
    assert code == 0, err
    assert {k: v for k, v in _snapshot(h5).items() if "xdf_" not in k} == \
        {k: v for k, v in once.items() if "xdf_" not in k}  # fmt: skip
    assert len(h5py.File(h5, "r", locking=False)["trials/01_BT12_rep1_a1/imported"]) == 3


def test_a_stream_without_samples_in_a_trial_is_named_and_the_others_imported(
    tmp_path, session_dir
):
    h5 = session_dir / "S01.h5"
    _set_clock(h5)
    xdf = tmp_path / "lab.xdf"

    def short_emg(w):  # a second EMG stream that stopped before the second trial
        s = w.add_stream(_header("EMG2", "EMG", "float32", 1, 500))
        t = np.arange(999.0, 1005.0, 0.002)
        w.write_samples(s, t, np.ones((len(t), 1), np.float32))
        late = w.add_stream(_header("Late", "EMG", "float32", 1, 500))
        t = np.arange(2000.0, 2001.0, 0.002)
        w.write_samples(late, t, np.ones((len(t), 1), np.float32))
        w.add_stream(_header("Silent", "EMG", "float32", 1, 500))

    _write_xdf(xdf, extra=short_emg)
    code, err = cli("import-xdf", xdf, "--session", session_dir)
    assert code == 0, err
    assert (
        f"{xdf}: stream 'EMG2' (id 4, type EMG): no samples in trial S01.h5:/trials/02_PT_rep1_a1"
        " (1010.000–1013.995 s on the recording's clock; the stream has 999.000–1004.998 s);"
        " not imported for that trial"
    ) in err
    assert (
        f"{xdf}: stream 'Late' (id 5, type EMG): its samples (2000.000–2000.998 s on the"
        " recording's clock) overlap no trial (the trials span 1000.000–1013.995 s); nothing"
        " imported from it"
    ) in err
    assert f"{xdf}: stream 'Silent' (id 6, type EMG): no samples in the recording" in err
    recs = _trials(h5)
    assert "xdf_EMG2_ch1" in recs["01_BT12_rep1_a1"].extra
    assert "xdf_EMG2_ch1" not in recs["02_PT_rep1_a1"].extra
    assert "xdf_EMG_flexor" in recs["02_PT_rep1_a1"].extra  # the other streams go on
    assert not any(k.startswith("xdf_Late") for r in recs.values() for k in r.extra)


def test_nothing_overlapping_writes_nothing_and_says_why(tmp_path, session_dir):
    h5 = session_dir / "S01.h5"
    _set_clock(h5, {"01_BT12_rep1_a1": 5000.0, "02_PT_rep1_a1": 5010.0})
    before = h5.read_bytes()
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf)
    code, err = cli("import-xdf", xdf, "--session", session_dir)
    assert code == 2
    assert (
        f"{xdf}: no trial lies within the recording (995.000–1019.999 s on its clock): by their"
        " lsl_clock_s (no clock offsets of Steerlab's streams in the file: the session's LSL"
        " clock taken as the recording's) the 2 trial(s) span 5000.000–5013.995 s; nothing"
        " imported"
    ) in err
    assert h5.read_bytes() == before


def test_trials_without_a_clock_and_no_markers_are_refused(tmp_path, session_dir):
    h5 = session_dir / "S01.h5"
    _set_clock(h5, {"01_BT12_rep1_a1": None, "02_PT_rep1_a1": None})
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf)
    code, err = cli("import-xdf", xdf, "--session", session_dir)
    assert code == 2
    assert "no Steerlab marker stream and no trial records lsl_clock_s" in err


def _marker_stream(w, subject):
    """The header of Steerlab's marker stream of ``subject``, added to ``w``; its stream id."""
    from xml.etree import ElementTree as ET

    desc = ET.Element("desc")
    ET.SubElement(ET.SubElement(desc, "steerlab"), "subject").text = subject
    return w.add_stream(
        stream_header_xml(
            name=f"Steerlab {subject} markers",
            type="Markers",
            channel_count=1,
            nominal_srate=0,
            channel_format="string",
            source_id=f"steerlab:test:{subject}:markers",
            desc=desc,
        )
    )


def _steerlab_streams(w, *, subject="S01", offset=0.0, starts=T0, recorder_ahead=0.0):
    """Steerlab's marker stream as protocols/lsl_publisher.py makes it (JSON markers stamped at
    each trial's sample 0), on a session computer whose clock is ``recorder_ahead`` s behind
    the recorder's (clock offsets say so)."""
    m = _marker_stream(w, subject)
    texts, stamps = [], []
    for k, (key, t0) in enumerate(starts.items()):
        texts.append([json.dumps({"event": "trial_start", "key": key, "trial_index": k + 1})])
        stamps.append(t0 + offset)
        texts.append([json.dumps({"event": "trial_stop", "key": key, "n_samples": 800})])
        stamps.append(t0 + offset + 4.0)
    w.write_samples(m, stamps, texts)
    for t in (990.0, 1005.0, 1020.0):
        w.write_clock_offset(m, t, recorder_ahead)


def test_markers_match_trials_by_key_and_put_them_on_the_recorders_clock(tmp_path, session_dir):
    h5 = session_dir / "S01.h5"
    # The session computer's clock runs 2.5 s behind the recorder's; the trials were recorded
    # there (their lsl_clock_s), the EMG on the recorder. Markers say where each trial is.
    _set_clock(h5, {k: t0 - 2.5 for k, t0 in T0.items()})
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf, extra=lambda w: _steerlab_streams(w, offset=-2.5, recorder_ahead=2.5))
    code, err = cli("import-xdf", xdf, "--session", session_dir, "--stream", "EMG")
    assert code == 0, err
    recs = _trials(h5)
    for key, t0 in T0.items():
        r = recs[key]
        np.testing.assert_allclose(r.extra["xdf_EMG_flexor"], _emg(t0 + r.time_s)[:, 0],
                                   atol=5e-5)  # fmt: skip
        assert "xdf_Plate_Fz" not in r.extra  # --stream EMG: only that one
    with h5py.File(h5, "r", locking=False) as f:
        by = f["trials/02_PT_rep1_a1/xdf_EMG_flexor"].attrs["matched_by"]
        assert by.startswith("marker trial_start of stream 'Steerlab S01 markers'")
    # By the clock, the same place: lsl_clock_s moved by the marker stream's clock offsets.
    code, err = cli("import-xdf", xdf, "--session", h5, "--stream", "EMG", "--match", "clock",
                    "--replace")  # fmt: skip
    assert code == 0, err
    for key, t0 in T0.items():
        r = _trials(h5)[key]
        np.testing.assert_allclose(r.extra["xdf_EMG_flexor"], _emg(t0 + r.time_s)[:, 0],
                                   atol=5e-5)  # fmt: skip


def test_a_marker_naming_no_trial_is_said(tmp_path, session_dir):
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf, extra=lambda w: _steerlab_streams(
        w, starts={"01_BT12_rep1_a1": 1000.0, "07_RT_rep1_a1": 1010.0}))  # fmt: skip
    code, err = cli("import-xdf", xdf, "--session", session_dir, "--dry-run")
    assert code == 0, err
    assert "marker trial_start of '07_RT_rep1_a1' (subject S01) at 1010.000 s: no such trial" in err


def test_a_session_being_written_is_refused(tmp_path, session_dir):
    h5 = session_dir / "S01.h5"
    _set_clock(h5)
    xdf = tmp_path / "lab.xdf"
    _write_xdf(xdf)
    before = h5.read_bytes()
    with WriterLock(h5, command="steerlab run --subject 1"):
        code, err = cli("import-xdf", xdf, "--session", h5)
    assert code == 2
    assert "being written by process" in err and "steerlab run --subject 1" in err
    assert h5.read_bytes() == before


@needs_public_files
def test_the_public_minimal_file_onto_a_trial(tmp_path, session_dir):
    """minimal.xdf's int16 stream (10 Hz, clock offset −0.1 s) onto a trial whose LSL clock
    puts its first sample at 4.0 s: held (10 Hz < 200 Hz) from 5.0 s on; its strings kept."""
    h5 = session_dir / "S01.h5"
    _set_clock(h5, {"01_BT12_rep1_a1": 4.0, "02_PT_rep1_a1": 100.0})
    code, err = cli("import-xdf", MINIMAL, "--session", session_dir)
    assert code == 0, err
    assert (
        f"{MINIMAL}: 1 trial(s) lie outside the recording (5.000–5.900 s on its clock) and are"
        " not matched"
    ) in err  # the second trial, at 100 s
    r = _trials(h5)["01_BT12_rep1_a1"]
    x = r.extra["xdf_SendDataC_ch1"]
    stamps = read_xdf(MINIMAL).streams[0].time_stamps
    np.testing.assert_allclose(stamps, np.arange(9) * 0.1 + 5.0)  # 5.1 … 5.9, less 0.1 s
    expected = np.array([192, 12, 13, 14, 15, 12, 13, 14, 15], float)
    t = 4.0 + r.time_s
    i = np.searchsorted(stamps, t, side="right") - 1
    want = np.where((i >= 0) & (t - stamps[np.maximum(i, 0)] <= 0.25), expected[i], np.nan)
    np.testing.assert_array_equal(x, want)
    assert np.isfinite(x).sum() == 210  # held from 5.0 s to 5.8 s + 2.5 intervals (0.25 s)
    with h5py.File(h5, "r", locking=False) as f:
        g = f["trials/01_BT12_rep1_a1/imported"]
        assert g["xdf_SendDataC/values"].dtype == np.int16
        assert [v.decode() for v in g["xdf_SendDataString/text"][1:5, 0]] == [
            "Hello", "World", "from", "LSL"]  # fmt: skip


def test_a_slow_stream_is_held_across_a_trial_it_has_no_sample_in(tmp_path, session_dir):
    h5 = session_dir / "S01.h5"
    _set_clock(h5)
    xdf = tmp_path / "slow.xdf"
    with XdfWriter(xdf) as w:
        s = w.add_stream(
            _header("Room", "Temperature", "float32", 1, 0.1, channels=[ChannelSpec("T", "degC")])
        )
        w.write_samples(s, [995.0, 1005.0, 1015.0], np.array([[21.0], [21.5], [22.0]], np.float32))
    code, err = cli("import-xdf", xdf, "--session", session_dir)
    assert code == 0, err
    assert "no samples in trial" not in err
    recs = _trials(h5)
    np.testing.assert_array_equal(recs["01_BT12_rep1_a1"].extra["xdf_Room_T"], 21.0)
    np.testing.assert_array_equal(recs["02_PT_rep1_a1"].extra["xdf_Room_T"], 21.5)
    with h5py.File(h5, "r", locking=False) as f:
        d = f["trials/01_BT12_rep1_a1/xdf_Room_T"]
        assert d.attrs["resample_method"] == "hold" and d.attrs["n_source_samples"] == 0
        assert d.attrs["units"] == "degC"
