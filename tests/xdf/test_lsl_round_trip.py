"""The whole way round, without hardware: a simulated session published on LSL beside an "EMG"
outlet, recorded by our recorder (protocols/xdf_writer.py) into XDF, imported back by
``steerlab import-xdf``: every sample of Steerlab's own stream in place (at its trial sample's
time, with the session file's values), and the EMG on the trials' samples.

Two publishers: Steerlab's own (protocols/lsl_publisher.py, on the engine), and a small one in
this file that plays a session file's samples back on LSL the way that one does (a stream of
type Steerlab, JSON trial_start markers at each trial's sample 0), so that the recorder and the
import are checked whatever the session-side publisher does."""

from __future__ import annotations

import json
import threading
import uuid

import h5py
import numpy as np
import pytest
import pyxdf

from steerlab.protocols.datafile import SessionFile, read_channel
from steerlab.protocols.xdf_import import import_xdf
from steerlab.protocols.xdf_writer import LslRecorder

from .conftest import SHORT_TRIAL_SAMPLES

EMG_HZ, EMG_F = 1000.0, 4.0


def _emg_outlet(pylsl, source_id):
    info = pylsl.StreamInfo("EMG", "EMG", 1, EMG_HZ, "double64", source_id)
    ch = info.desc().append_child("channels").append_child("channel")
    ch.append_child_value("label", "biceps")
    ch.append_child_value("unit", "mV")
    return pylsl.StreamOutlet(info)


def _push_emg(outlet, t_from, t_to):
    """A sine over [t_from, t_to) on the LSL clock, stamped sample by sample."""
    t = np.arange(t_from, t_to, 1 / EMG_HZ)
    for k in range(0, len(t), 500):
        tt = t[k : k + 500]
        outlet.push_chunk(np.sin(2 * np.pi * EMG_F * tt)[:, None].tolist(), tt.tolist())


class _Recording:
    """Our recorder, started on a thread (the session's streams appear only once it runs)."""

    def __init__(self, path, source_ids, expect):
        self.rec = LslRecorder(path, source_ids=source_ids, expect=expect, resolve_s=30.0)
        self.error = None
        self.thread = threading.Thread(target=self._start, daemon=True)
        self.thread.start()

    def _start(self):
        try:
            self.rec.start()
        except BaseException as e:
            self.error = e

    def started(self):
        self.thread.join(60)
        assert not self.thread.is_alive(), "the recorder did not find its streams"
        if self.error is not None:
            raise self.error
        return self

    def stop(self):
        path = self.rec.stop()
        assert not self.rec.errors, self.rec.errors
        return path


def _check_round_trip(xdf, session_dir, h5, n_trials):
    """Every trial's samples in place in Steerlab's stream; the EMG on every trial sample."""
    res = import_xdf(xdf, session_dir)
    assert len(res.windows) == n_trials
    assert all("marker trial_start" in w.matched_by for w in res.windows)
    assert len(res.checks) == n_trials
    for c in res.checks:
        assert c.all_in_place, c.summary()
        assert c.n_found == c.n_trial == SHORT_TRIAL_SAMPLES
        assert {"wheel_angle_rad", "driver_torque_Nm", "grip_force_N"} <= set(c.channels)
    assert not [p for p in res.problems if "Steerlab's own stream" in p], res.problems
    # The Steerlab stream, read by pyxdf itself: exactly the session's samples, no more.
    streams, _ = pyxdf.load_xdf(str(xdf), dejitter_timestamps=False)
    sig = next(s for s in streams if s["info"]["type"] == ["Steerlab"])
    recs = sorted(SessionFile(h5).records(), key=lambda r: r.trial_index)
    assert len(sig["time_stamps"]) == sum(r.n_samples for r in recs)
    labels = [c["label"][0] for c in sig["info"]["desc"][0]["channels"][0]["channel"]]
    k = 0
    with h5py.File(h5, "r", locking=False) as f:
        for r in recs:
            g = f["trials"][r.source.rsplit("/", 1)[1]]
            for j, label in enumerate(labels):
                if label not in g:
                    continue
                d = g[label]
                got = sig["time_series"][k : k + r.n_samples, j]
                if d.dtype == np.float32:
                    np.testing.assert_array_equal(got.astype(np.float32), d[()], label)
                else:
                    np.testing.assert_array_equal(got, read_channel(d), label)
            k += r.n_samples
    # The EMG, resampled (linear: 1 kHz ≥ 200 Hz) onto each trial's samples.
    for r in SessionFile(h5).records():
        t = r.attrs["lsl_clock_s"] + r.time_s
        # Interpolation's error, and 100 µs of time: each stream's clock offsets, measured by
        # LSL on this machine (tens of µs), move each stream on its own.
        bound = (2 * np.pi * EMG_F) ** 2 / EMG_HZ**2 / 8 + 2 * np.pi * EMG_F * 1e-4
        np.testing.assert_allclose(r.extra["xdf_EMG_biceps"], np.sin(2 * np.pi * EMG_F * t),
                                   atol=bound, rtol=0)  # fmt: skip
    return res


def test_a_session_published_by_steerlab_recorded_and_imported_back(tmp_path):
    lp = pytest.importorskip("steerlab.protocols.lsl_publisher")
    import pylsl

    from steerlab.hardware.sim.physiology import make_population
    from steerlab.hardware.sim.rig import simulated_rig
    from steerlab.hardware.sim.world import WorldConfig
    from steerlab.protocols.datafile import SessionWriter
    from steerlab.protocols.engine import SessionEngine, State
    from steerlab.protocols.protocol import parse_protocol
    from steerlab.protocols.session import build_plan

    from .conftest import SHORT_PROTOCOL

    protocol = parse_protocol(SHORT_PROTOCOL, "short.toml")
    plan = build_plan(protocol, 1)
    session_dir = tmp_path / "sessions"
    session_dir.mkdir()
    h5 = session_dir / f"{plan.subject}.h5"
    rig = f"xdf-{uuid.uuid4().hex[:8]}"
    clock = lp.LabClock(lp.SYNTHETIC)
    engine = SessionEngine(
        plan,
        simulated_rig(make_population(1, seed=3)[0], WorldConfig(fs_hz=200.0)).batch_loop(0.25),
    )
    engine.subscribe(SessionWriter(h5, first_sample_attributes=clock.first_sample_attributes))
    pub = lp.LslPublisher(clock, rig=rig, session_path=h5, wait_for_consumers_s=30).attach(engine)
    sid = lp.source_id_for(rig, plan.subject, h5)
    emg_sid = f"emg-{uuid.uuid4().hex}"
    emg = _emg_outlet(pylsl, emg_sid)
    xdf = tmp_path / "lab.xdf"
    rec = _Recording(xdf, (sid, emg_sid), expect=3)
    try:
        assert engine.run() is State.DONE
        rec.started()
        clocks = [a["lsl_clock_s"] for a in SessionFile(h5).trial_attrs.values()]
        _push_emg(emg, min(clocks) - 1.0, max(clocks) + 5.0)
    finally:
        pub.close()
    path = rec.stop()
    assert path == xdf
    names = {s.type: s.samples for s in rec.rec.streams}
    assert names["Steerlab"] == 2 * SHORT_TRIAL_SAMPLES
    _check_round_trip(xdf, session_dir, h5, n_trials=2)


def _playback_outlets(pylsl, source_id):
    """Outlets like Steerlab's (a signal stream of type Steerlab, a marker stream), for the
    tests to play a session file's samples back on: each trial's sample 0 at the time they set
    as its lsl_clock_s, then 1/fs apart; a JSON trial_start marker at its sample 0."""
    labels = ["wheel_angle_rad", "driver_torque_Nm", "perturbation_torque_Nm", "grip_force_N"]
    info = pylsl.StreamInfo("Steerlab S01", "Steerlab", len(labels), 200.0, "double64",
                            source_id)  # fmt: skip
    chs = info.desc().append_child("channels")
    for c in labels:
        chs.append_child("channel").append_child_value("label", c)
    info.desc().append_child("steerlab").append_child_value("subject", "S01")
    minfo = pylsl.StreamInfo("Steerlab S01 markers", "Markers", 1, 0, "string",
                             f"{source_id}:markers")  # fmt: skip
    minfo.desc().append_child("steerlab").append_child_value("subject", "S01")
    return pylsl.StreamOutlet(info), pylsl.StreamOutlet(minfo), labels


def test_a_session_file_played_back_on_lsl_recorded_and_imported_back(tmp_path, session_dir):
    import pylsl

    h5 = session_dir / "S01.h5"
    sid = f"steerlab:playback-{uuid.uuid4().hex[:8]}:S01"
    emg_sid = f"emg-{uuid.uuid4().hex}"
    sig, mk, labels = _playback_outlets(pylsl, sid)
    emg = _emg_outlet(pylsl, emg_sid)
    xdf = tmp_path / "lab.xdf"
    rec = _Recording(xdf, (sid, emg_sid), expect=3).started()
    t = pylsl.local_clock() + 1.0
    with h5py.File(h5, "r+", locking=False) as f:
        for key in sorted(f["trials"]):
            g = f["trials"][key]
            g.attrs["lsl_clock_s"] = t
            n = len(g["time_s"])
            data = np.column_stack([read_channel(g[c]) for c in labels])
            mk.push_sample([json.dumps({"event": "trial_start", "key": key})], t)
            stamps = t + read_channel(g["time_s"])
            for k in range(0, n, 100):
                sig.push_chunk(data[k : k + 100].tolist(), stamps[k : k + 100].tolist())
            mk.push_sample([json.dumps({"event": "trial_stop", "key": key})], t + n / 200.0)
            t += n / 200.0 + 0.5
    first = min(SessionFile(h5).trial_attrs[k]["lsl_clock_s"] for k in SessionFile(h5).trial_keys)
    _push_emg(emg, first - 1.0, t + 1.0)
    rec.stop()
    res = _check_round_trip(xdf, session_dir, h5, n_trials=2)
    assert all(c.channels == labels for c in res.checks)


def test_a_trial_missing_from_the_recorded_stream_is_reported(tmp_path, session_dir):
    """A stream that lost samples (here: the second trial published with a gap) is caught by
    the check against the session file."""
    import pylsl

    h5 = session_dir / "S01.h5"
    sid = f"steerlab:playback-{uuid.uuid4().hex[:8]}:S01"
    sig, mk, labels = _playback_outlets(pylsl, sid)
    xdf = tmp_path / "lab.xdf"
    emg_sid = f"emg-{uuid.uuid4().hex}"
    emg = _emg_outlet(pylsl, emg_sid)
    rec = _Recording(xdf, (sid, emg_sid), expect=3).started()
    t = pylsl.local_clock() + 1.0
    with h5py.File(h5, "r+", locking=False) as f:
        keys = sorted(f["trials"])
        for j, key in enumerate(keys):
            g = f["trials"][key]
            g.attrs["lsl_clock_s"] = t
            data = np.column_stack([read_channel(g[c]) for c in labels])
            stamps = t + read_channel(g["time_s"])
            keep = np.ones(len(stamps), bool)
            if j == 1:
                keep[100:150] = False  # 50 samples lost on the way
            mk.push_sample([json.dumps({"event": "trial_start", "key": key})], t)
            sig.push_chunk(data[keep].tolist(), stamps[keep].tolist())
            t += len(stamps) / 200.0 + 0.5
    _push_emg(emg, t - 10.0, t)
    rec.stop()
    res = import_xdf(xdf, session_dir, dry_run=True)
    by = {c.where: c for c in res.checks}
    assert by["S01.h5:/trials/01_BT12_rep1_a1"].all_in_place
    bad = by["S01.h5:/trials/02_PT_rep1_a1"]
    assert (bad.n_found, bad.n_trial) == (SHORT_TRIAL_SAMPLES - 50, SHORT_TRIAL_SAMPLES)
    assert any("02_PT_rep1_a1: stream 'Steerlab S01'" in p and "750 of its 800" in p
               for p in res.problems), res.problems  # fmt: skip


def test_record_lsl_records_every_sample_from_when_it_starts(tmp_path):
    """``steerlab record-lsl``: a counter stream, pushed before, during and after the
    recording; the file holds one unbroken run of it, with the stream's time stamps."""
    import pylsl

    from tests.helpers import cli

    name = f"counter-{uuid.uuid4().hex}"
    outlet = pylsl.StreamOutlet(pylsl.StreamInfo(name, "Counter", 1, 500.0, "int32", f"src-{name}"))
    stop = threading.Event()
    pushed = {}

    def push():
        k = 0
        while not stop.is_set():
            t = pylsl.local_clock()
            outlet.push_chunk([[k + j] for j in range(10)], [t + j / 500 for j in range(10)])
            for j in range(10):
                pushed[k + j] = t + j / 500
            k += 10
            stop.wait(0.02)

    pusher = threading.Thread(target=push, daemon=True)
    pusher.start()
    try:
        out = tmp_path / "rec.xdf"
        code, err = cli("record-lsl", "--out", out, "--name", name, "--duration", 1.5)
    finally:
        stop.set()
        pusher.join(5)
    assert code == 0, err
    streams, _ = pyxdf.load_xdf(str(out), synchronize_clocks=False, dejitter_timestamps=False)
    (s,) = streams
    assert s["info"]["name"] == [name] and s["info"]["channel_format"] == ["int32"]
    got = s["time_series"][:, 0]
    assert len(got) > 100
    np.testing.assert_array_equal(got, np.arange(got[0], got[0] + len(got)))  # no gap
    np.testing.assert_array_equal(s["time_stamps"], [pushed[int(k)] for k in got])
    assert len(s["clock_times"]) >= 1
