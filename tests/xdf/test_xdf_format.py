"""XDF: our writer read back by pyxdf exactly, and the public example files read by pyxdf and
by Steerlab's import path alike."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import pyxdf

from steerlab.protocols.xdf_import import XdfImportError, read_xdf
from steerlab.protocols.xdf_writer import (
    CHUNK_SAMPLES,
    ChannelSpec,
    XdfWriteError,
    XdfWriter,
    stream_header_xml,
    varlen_int,
)

from .conftest import CLOCK_RESETS, EMPTY_STREAMS, MINIMAL, needs_public_files


def _raw(path):
    """pyxdf's reading with no processing: the stamps and values as written."""
    streams, header = pyxdf.load_xdf(str(path), synchronize_clocks=False, dejitter_timestamps=False)
    return {s["info"]["name"][0]: s for s in streams}, header


def _header(name, fmt, n, srate, **kw):
    return stream_header_xml(
        name=name, type=kw.pop("type", "Test"), channel_count=n, nominal_srate=srate,
        channel_format=fmt, **kw,
    )  # fmt: skip


# -- our writer ------------------------------------------------------------------------------------
NUMERIC = {
    "float32": np.float32,
    "double64": np.float64,
    "int8": np.int8,
    "int16": np.int16,
    "int32": np.int32,
    "int64": np.int64,
}


def test_every_numeric_format_comes_back_from_pyxdf_exactly(tmp_path):
    rng = np.random.default_rng(7)
    path = tmp_path / "formats.xdf"
    expected = {}
    with XdfWriter(path) as w:
        for fmt, dt in NUMERIC.items():
            n = CHUNK_SAMPLES + 37 if fmt == "float32" else 50  # several Samples chunks
            if np.dtype(dt).kind == "f":
                v = (rng.standard_normal((n, 3)) * 1e3).astype(dt)
                v[0, 0] = np.nan if fmt == "double64" else v[0, 0]
            else:
                info = np.iinfo(dt)
                v = rng.integers(info.min, info.max, size=(n, 3), dtype=dt, endpoint=True)
            # Irregular stamps far from 0, which no rate would let a reader deduce.
            t = 123456.0 + np.cumsum(rng.uniform(0.0005, 0.0015, n))
            sid = w.add_stream(
                _header(
                    fmt,
                    fmt,
                    3,
                    1000,
                    channels=[
                        ChannelSpec("a", "mV", "EMG"),
                        ChannelSpec("b", "µV"),
                        ChannelSpec("c"),
                    ],
                )
            )
            # Written in two calls, as a recorder's pulls come.
            w.write_samples(sid, t[:10], v[:10])
            w.write_samples(sid, t[10:], v[10:])
            expected[fmt] = (t, v)
    streams, header = _raw(path)
    assert header["info"]["version"] == ["1.0"]
    for fmt, (t, v) in expected.items():
        s = streams[fmt]
        assert s["info"]["channel_format"] == [fmt]
        assert s["time_series"].dtype == v.dtype
        np.testing.assert_array_equal(s["time_series"], v)  # NaN in place too
        np.testing.assert_array_equal(s["time_stamps"], t)
        chans = s["info"]["desc"][0]["channels"][0]["channel"]
        assert [c["label"][0] for c in chans] == ["a", "b", "c"]
        assert chans[1]["unit"] == ["µV"] and chans[0]["type"] == ["EMG"]
        footer = s["footer"]["info"]
        assert int(footer["sample_count"][0]) == len(t)
        assert float(footer["first_timestamp"][0]) == t[0]
        assert float(footer["last_timestamp"][0]) == t[-1]


def test_strings_clock_offsets_and_boundaries_come_back(tmp_path):
    path = tmp_path / "markers.xdf"
    texts = [["trial_start", "ü"], ["", "a,b"], ['{"event": "x"}', "x" * 300]]
    with XdfWriter(path) as w:
        m = w.add_stream(_header("M", "string", 2, 0, type="Markers"))
        e = w.add_stream(_header("E", "double64", 1, 100))
        w.write_samples(m, [10.0, 10.5, 11.25], texts)
        w.write_boundary()
        w.write_samples(e, 10 + np.arange(200) / 100, np.arange(200.0)[:, None])
        for k in range(4):
            w.write_clock_offset(e, 10.0 + k, 0.25 + 0.001 * k)
    streams, _ = _raw(path)
    assert streams["M"]["time_series"] == texts
    assert list(streams["M"]["time_stamps"]) == [10.0, 10.5, 11.25]
    assert streams["E"]["clock_times"] == [10.0, 11.0, 12.0, 13.0]
    assert streams["E"]["clock_values"] == [0.25, 0.251, 0.252, 0.253]
    # pyxdf applies them: the recorder's clock is the stream's + the fitted offset.
    synced, _ = pyxdf.load_xdf(str(path), dejitter_timestamps=False)
    e_sync = next(s for s in synced if s["info"]["name"] == ["E"])
    t = 10 + np.arange(200) / 100
    np.testing.assert_allclose(e_sync["time_stamps"], t + 0.25 + 0.001 * (t - 10), atol=1e-6)


def test_the_file_has_its_name_only_when_complete(tmp_path):
    path = tmp_path / "r.xdf"
    w = XdfWriter(path)
    sid = w.add_stream(_header("E", "float32", 1, 10))
    w.write_samples(sid, [1.0], [[1.0]])
    assert not path.exists() and w.part.exists()
    w.close()
    assert path.exists() and not w.part.exists()
    with pytest.raises(XdfWriteError, match="exists; not overwriting"):
        XdfWriter(path)


def test_bad_samples_are_refused_with_what_is_wrong(tmp_path):
    with XdfWriter(tmp_path / "bad.xdf") as w:
        sid = w.add_stream(_header("I", "int16", 2, 10))
        with pytest.raises(XdfWriteError, match=r"shape \(3,\), expected \(3, 2\)"):
            w.write_samples(sid, [1, 2, 3], [1, 2, 3])
        with pytest.raises(XdfWriteError, match="not whole numbers for int16"):
            w.write_samples(sid, [1], [[1.5, 2]])
        with pytest.raises(XdfWriteError, match="time stamp is not finite"):
            w.write_samples(sid, [np.nan], [[1, 2]])
        with pytest.raises(XdfWriteError, match="no stream with id 99"):
            w.write_samples(99, [1], [[1, 2]])
        with pytest.raises(XdfWriteError, match="channel_format 'int12'"):
            w.add_stream(_header("X", "int12", 1, 10))


def test_variable_length_integers_are_the_specs():
    assert varlen_int(5) == b"\x01\x05"
    assert varlen_int(256) == b"\x04" + struct.pack("<I", 256)
    assert varlen_int(1 << 32) == b"\x08" + struct.pack("<Q", 1 << 32)


# -- the public example files ----------------------------------------------------------------------
@needs_public_files
def test_minimal_through_pyxdf_and_through_our_reader():
    raw, _ = pyxdf.load_xdf(str(MINIMAL))
    rec = read_xdf(MINIMAL)
    by_id = {s.stream_id: s for s in rec.streams}
    assert sorted(by_id) == [0, 46202862]
    eeg, text = by_id[0], by_id[46202862]
    assert (eeg.name, eeg.type, eeg.channel_format, eeg.nominal_srate) == (
        "SendDataC",
        "EEG",
        "int16",
        10.0,
    )
    assert eeg.n_samples == 9 and text.n_samples == 9
    # The README's values; the clock offsets (−0.1 s) are applied, the stamps not dejittered.
    assert eeg.values[0].tolist() == [192, 255, 238] and eeg.values[-1].tolist() == [15, 25, 35]
    np.testing.assert_allclose(eeg.time_stamps, np.arange(5.1, 5.95, 0.1) - 0.1, atol=1e-9)
    assert eeg.clock_times.tolist() == [6.1, 7.1] and eeg.clock_values.tolist() == [-0.1, -0.1]
    assert [r[0] for r in text.values[1:5]] == ["Hello", "World", "from", "LSL"]
    np.testing.assert_allclose(text.time_stamps, np.arange(5.1, 5.95, 0.1), atol=1e-9)
    assert [c.unit for c in eeg.channels] == ["unknown"] * 3
    # The same samples as pyxdf's own (with its default processing, the same stamps up to its
    # dejittering of a regular stream).
    p_eeg = next(s for s in raw if s["info"]["stream_id"] == 0)
    np.testing.assert_array_equal(p_eeg["time_series"], eeg.values)
    np.testing.assert_allclose(p_eeg["time_stamps"], eeg.time_stamps, atol=1e-9)
    assert rec.notes == []


@needs_public_files
def test_clock_resets_is_read_with_pyxdfs_reset_handling():
    rec = read_xdf(CLOCK_RESETS)
    raw, _ = pyxdf.load_xdf(str(CLOCK_RESETS), dejitter_timestamps=False)
    by_name = {s.name: s for s in rec.streams}
    eeg, markers = by_name["BioSemi"], by_name["MyMarkerStream"]
    assert eeg.n_samples == 27815 and eeg.values.shape == (27815, 8)
    assert eeg.values.dtype == np.float32 and eeg.nominal_srate == 100.0
    assert markers.n_samples == 175 and markers.channel_format == "string"
    assert len(eeg.clock_times) == 115
    p_eeg = next(s for s in raw if s["info"]["name"] == ["BioSemi"])
    np.testing.assert_array_equal(eeg.time_stamps, p_eeg["time_stamps"])
    np.testing.assert_array_equal(eeg.values, p_eeg["time_series"])
    # The reset: the raw stamps jump back by ~650 000 s; synchronised, they run on.
    unsynced = read_xdf(CLOCK_RESETS, synchronize_clocks=False)
    raw_stamps = next(s for s in unsynced.streams if s.name == "BioSemi").time_stamps
    assert np.min(np.diff(raw_stamps)) < -1000
    assert np.min(np.diff(eeg.time_stamps)) > -1.0


@needs_public_files
def test_empty_streams_are_named_and_the_others_read():
    rec = read_xdf(EMPTY_STREAMS)
    counts = {s.name: s.n_samples for s in rec.streams}
    assert counts == {
        "Empty data stream: test stream 0 counter": 0,
        "Data stream: test stream 0 counter": 10,
        "ctrl": 1,
        "Empty marker stream: test stream 0 counter": 0,
    }
    assert len(rec.notes) == 2
    for note in rec.notes:
        assert str(EMPTY_STREAMS) in note and "no samples in the recording" in note
    assert any("'Empty data stream: test stream 0 counter' (id 3" in n for n in rec.notes)
    data = next(s for s in rec.streams if s.name.startswith("Data stream"))
    assert data.values[:, 0].tolist() == list(range(10))
    assert data.channels[0].label == "ch:00"


def test_a_file_that_is_not_xdf_is_named(tmp_path):
    bad = tmp_path / "notes.xdf"
    bad.write_bytes(b"hello")
    with pytest.raises(XdfImportError, match=f"{bad}: not an XDF file"):
        read_xdf(bad)
    with pytest.raises(XdfImportError, match="no such file"):
        read_xdf(tmp_path / "missing.xdf")


def test_a_recording_cut_short_is_read_up_to_the_cut_and_said(tmp_path):
    path = tmp_path / "whole.xdf"
    with XdfWriter(path) as w:
        sid = w.add_stream(_header("EMG", "float32", 1, 100))
        for k in range(10):  # ten Samples chunks of 100
            t = 100 + np.arange(k * 100, (k + 1) * 100) / 100
            w.write_samples(sid, t, np.arange(k * 100, (k + 1) * 100, dtype=np.float32)[:, None])
    data = path.read_bytes()
    cut = tmp_path / "cut.xdf"
    cut.write_bytes(data[: len(data) // 2])  # in the middle of the fifth chunk
    rec = read_xdf(cut)
    (s,) = rec.streams
    assert s.n_samples == 400
    np.testing.assert_array_equal(s.values[:, 0], np.arange(400))
    assert rec.notes == [
        f"{cut}: stream 'EMG' (id 1, type Test): no footer: the recording was cut short (a"
        " recorder that stopped without closing the file?); its 400 samples up to the cut are"
        " read"
    ]
