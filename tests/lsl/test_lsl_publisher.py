"""Steerlab on the lab's clock: a session's own streams reach an LSL inlet, sample for sample
and marker for marker, on the time line its session file records (``lsl_clock_s``)."""

from __future__ import annotations

import logging
import threading
import time
import uuid
from dataclasses import replace

import numpy as np
import pytest

from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.rig import simulated_rig
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols import events as ev
from steerlab.protocols import lsl_publisher as lp
from steerlab.protocols.datafile import SessionFile, SessionWriter
from steerlab.protocols.engine import SessionEngine, State, TrialFault
from steerlab.protocols.lsl_publisher import (
    HOST,
    SIGNAL_CHANNELS,
    SYNTHETIC,
    LabClock,
    LslPublisher,
    lab_clock_for,
    publish_default,
    source_id_for,
)
from steerlab.protocols.records import CORE_CHANNELS
from steerlab.protocols.session import build_plan
from tests.helpers import cli

from .conftest import Receiver

FAULT = "glove stream stopped (injected)"


def _rig(fs=200.0):
    return simulated_rig(make_population(1, seed=3)[0], WorldConfig(fs_hz=fs))


class FaultAfter:
    """A real loop whose trial ``trial_index`` is aborted by a fault after ``blocks`` blocks."""

    def __init__(self, loop, trial_index: int, blocks: int) -> None:
        self.loop, self.trial_index, self.blocks = loop, trial_index, blocks

    def run_trial(self, setup, control):
        for i, b in enumerate(self.loop.run_trial(setup, control)):
            if setup.spec.trial_index == self.trial_index and i == self.blocks:
                raise TrialFault(FAULT)
            yield b

    def emergency_stop(self):
        self.loop.emergency_stop()

    def trial_stats(self):
        return self.loop.trial_stats()


def _session(tmp_path, plan, loop, source, **publisher):
    """Engine, writer and publisher for ``plan`` on ``loop``; (engine, publisher, path).
    ``source``: the clock's, or None: the one :func:`lab_clock_for` chooses for ``loop``."""
    clock = LabClock(source) if source else lab_clock_for(loop)
    path = tmp_path / f"{plan.subject}.h5"
    eng = SessionEngine(plan, loop)
    pub = LslPublisher(
        clock, rig=f"test-{uuid.uuid4().hex[:8]}", session_path=path, **publisher
    ).attach(eng)
    eng.subscribe(SessionWriter(path, first_sample_attributes=clock.first_sample_attributes))
    return eng, pub, path


def _source_id(pub: LslPublisher, plan) -> str:
    return source_id_for(pub.rig, plan.subject, pub.session_path)


def test_a_simulated_session_reaches_an_inlet(tmp_path, short_protocol):
    """Batch: every sample of every trial in order with the file's values, the markers in
    order with their conditions and the abort's reason, time stamps on the recorded line."""
    plan = build_plan(short_protocol, 2)
    plan = replace(plan, trials=plan.trials[:3])
    loop = FaultAfter(_rig().batch_loop(block_s=0.25), trial_index=3, blocks=2)
    eng, pub, path = _session(tmp_path, plan, loop, SYNTHETIC, wait_for_consumers_s=30)
    rx = Receiver(_source_id(pub, plan))
    try:
        assert eng.run() is State.IDLE  # the third trial was aborted
    finally:
        rx.stop()
        pub.close()
    assert pub.problem is None

    # The streams say what they are.
    assert rx.info.name() == f"Steerlab {plan.subject}" and rx.info.type() == "Steerlab"
    assert rx.info.nominal_srate() == short_protocol.loop_rate_hz
    import pylsl

    assert rx.info.channel_format() == pylsl.cf_double64  # the loop's values as they are
    ch = rx.info.desc().child("channels").first_child()
    labels, units = [], []
    while not ch.empty():
        labels.append(ch.child_value("label"))
        units.append(ch.child_value("unit"))
        ch = ch.next_sibling()
    assert tuple(labels) == SIGNAL_CHANNELS
    assert units[:3] == ["rad", "N·m", "N·m"] and units[3] == "N"
    assert rx.marker_info.type() == "Markers" and rx.marker_info.channel_format() == pylsl.cf_string

    # Every sample of every trial, in order, with the file's values (stored as float32).
    recs = sorted(SessionFile(path).records(), key=lambda r: r.trial_index)
    keys = sorted(SessionFile(path).trial_keys)
    assert [r.status for r in recs] == ["complete", "complete", "aborted"]
    assert recs[2].abort_reason == FAULT and 0 < recs[2].n_samples < recs[0].n_samples
    data, stamps = rx.data, np.asarray(rx.stamps)
    assert len(data) == sum(r.n_samples for r in recs)
    k = 0
    for r in recs:
        n = r.n_samples
        for j, c in enumerate(SIGNAL_CHANNELS):
            stored = getattr(r, c) if c in CORE_CHANNELS else r.extra[c]
            np.testing.assert_array_equal(data[k : k + n, j].astype(np.float32), stored, c)
        # On the time line the file records: sample 0 at lsl_clock_s, then 1/fs apart.
        assert r.attrs["lsl_clock_source"] == "synthetic"
        assert stamps[k] == r.attrs["lsl_clock_s"]
        np.testing.assert_allclose(np.diff(stamps[k : k + n]), 1 / r.fs_hz, rtol=1e-6)
        k += n
    # Synthetic trials follow one another without overlapping.
    for a, b in zip(recs, recs[1:], strict=False):
        assert b.attrs["lsl_clock_s"] >= a.attrs["lsl_clock_s"] + a.n_samples / a.fs_hz - 1e-9

    # The markers, in order, with conditions and the abort's reason.
    assert rx.events() == [
        "session_start",
        "trial_start", "trial_stop",
        "trial_start", "trial_stop",
        "trial_start", "abort", "trial_stop",
        "session_stop",
    ]  # fmt: skip
    m = [x for x, _ in rx.markers]
    ts = [t for _, t in rx.markers]
    assert ts == sorted(ts)
    assert m[0]["subject"] == plan.subject and m[0]["n_trials"] == 3
    starts = [(x, t) for x, t in rx.markers if x["event"] == "trial_start"]
    stops = [x for x in m if x["event"] == "trial_stop"]
    for r, (s, t), e in zip(recs, starts, stops, strict=True):
        assert s["key"] == e["key"] == keys[r.trial_index - 1]
        assert (s["trial_index"], s["condition"], s["repetition"], s["attempt"]) == (
            r.trial_index,
            r.condition,
            r.repetition,
            1,
        )
        assert t == r.attrs["lsl_clock_s"]  # a trial starts at its first sample
        assert (e["status"], e["n_samples"], e["condition"]) == (r.status, r.n_samples, r.condition)
    assert m[6] == {"event": "abort", "key": stops[2]["key"], "trial_index": 3, "reason": FAULT}
    assert stops[2]["reason"] == FAULT and stops[0]["reason"] is None
    assert m[-1]["event"] == "session_stop" and m[-1]["state"] == "idle"
    assert (m[-1]["completed"], m[-1]["remaining"]) == (2, 1)


def test_in_real_time_the_stamps_are_the_host_clock_and_a_pause_is_on_the_line(
    tmp_path, short_protocol
):
    """Host monotonic: each sample's time stamp is its host_time_s (when the loop read its
    sensors) on the LSL clock, also after a pause in mid-trial; the pause and resume markers
    sit at their sample. Behaviour only: how closely the loop keeps its schedule is the
    benchmarks' business."""
    plan = build_plan(short_protocol, 1)
    plan = replace(plan, trials=plan.trials[:1])
    loop = _rig().device_loop(realtime=True, block_s=0.05)
    eng, pub, path = _session(tmp_path, plan, loop, None, wait_for_consumers_s=30)
    assert pub.clock.source == HOST
    pause_at, pause_s = 200, 0.4

    def on(e):
        if isinstance(e, ev.SamplesAcquired) and e.start + e.n == pause_at:
            eng.pause()
        if isinstance(e, ev.StateChanged) and e.new == "paused":
            threading.Timer(pause_s, eng.resume).start()

    eng.subscribe(on)
    rx = Receiver(_source_id(pub, plan))
    try:
        assert eng.run() is State.DONE
    finally:
        rx.stop()
        pub.close()
    (rec,) = SessionFile(path).records()
    stamps = np.asarray(rx.stamps)
    host = rec.extra["host_time_s"]
    assert host.dtype == np.float64
    assert len(stamps) == rec.n_samples == len(host)
    assert np.all(np.diff(host) > 0)
    assert rec.attrs["lsl_clock_source"] == "host monotonic"
    offset = rec.attrs["lsl_clock_offset_s"]
    assert offset == pub.clock.offset_s
    assert rec.attrs["lsl_clock_s"] == host[0] + offset == stamps[0]
    # Every sample where the loop read it: no arrival, no resync in the stamps.
    np.testing.assert_array_equal(stamps, host + offset)
    assert pub.clock.resyncs == 0
    # The pause is on the line: a gap of about its length between two samples.
    gaps = np.diff(stamps)
    assert gaps[pause_at - 1] > pause_s * 0.9
    assert np.all(gaps > 0)
    marks = {x["event"]: (x, t) for x, t in rx.markers}
    assert marks["pause"][0]["sample"] == marks["resume"][0]["sample"] == pause_at
    assert marks["pause"][1] == stamps[pause_at - 1] + 1 / rec.fs_hz
    # The resume when it was asked for; the loop's next sample after it.
    assert stamps[pause_at] > marks["resume"][1]
    # The trial ends a period after its last sample, on the samples' line, not the nominal one.
    assert marks["trial_stop"][1] == stamps[-1] + 1 / rec.fs_hz
    assert [m["kind"] for m in rec.attrs["marks"]] == ["pause", "resume"]


def test_nothing_is_published_when_off_and_the_clock_is_still_recorded(
    tmp_path, short_protocol_file, outlets
):
    from steerlab.app.simulate import simulate_study

    simulate_study(1, tmp_path / "off", protocol_path=str(short_protocol_file))
    assert outlets.made == []  # simulate publishes only when asked
    recs = SessionFile(tmp_path / "off" / "S01.h5").records()
    assert recs and all(r.attrs["lsl_clock_source"] == "synthetic" for r in recs)
    clocks = [r.attrs["lsl_clock_s"] for r in sorted(recs, key=lambda r: r.trial_index)]
    assert clocks == sorted(clocks)


def test_simulate_lsl_publishes(tmp_path, short_protocol_file, outlets, monkeypatch):
    import steerlab.app.simulate as sim

    made = []
    real = sim.lab_subscriber

    def keep(*a, **kw):
        made.append(real(*a, **kw))
        return made[-1]

    monkeypatch.setattr(sim, "lab_subscriber", keep)
    code, err = cli("simulate", "--subjects", "1", "--out", tmp_path / "on", "--protocol",
                    short_protocol_file, "--lsl")  # fmt: skip
    assert code == 0, err
    assert outlets.made == ["Steerlab S01 markers", "Steerlab S01"]
    (pub,) = made
    assert isinstance(pub, LslPublisher) and pub.problem is None
    assert pub.source_id == source_id_for("simulated", "S01", tmp_path / "on" / "S01.h5")


def test_the_gui_publishes_by_default_and_not_when_told(tmp_path, short_protocol, outlets):
    from steerlab.app.gui.controller import SessionController
    from steerlab.app.gui.rig import make_rig_loop

    def factory(path, subject, protocol):
        return make_rig_loop(None, subject, protocol, realtime=False)

    for lsl, expected in ((None, 2), (False, 0)):
        outlets.made.clear()
        c = SessionController(short_protocol, tmp_path / str(lsl), rig_factory=factory, lsl=lsl)
        c.open_new(1)
        c.start()
        deadline = time.monotonic() + 60
        while not c.between_trials and c.worker_alive and time.monotonic() < deadline:
            time.sleep(0.05)
        c.shutdown()
        assert len(outlets.made) == expected
        assert isinstance(c.lab, LslPublisher) is bool(expected)
        (rec,) = SessionFile(c.path).records()
        assert rec.attrs["lsl_clock_source"] == "synthetic"  # the stepped loop


def test_the_env_setting_and_its_errors(monkeypatch):
    assert publish_default(True, {}) is True and publish_default(False, {}) is False
    assert publish_default(True, {"STEERLAB_LSL": "off"}) is False
    assert publish_default(False, {"STEERLAB_LSL": "ON"}) is True
    with pytest.raises(ValueError, match="STEERLAB_LSL"):
        publish_default(True, {"STEERLAB_LSL": "maybe"})
    assert publish_default(True, {"STEERLAB_LSL": "maybe"}, strict=False) is True
    monkeypatch.setenv("STEERLAB_LSL", "maybe")
    code, err = cli("simulate", "--subjects", "1", "--out", "/nonexistent/x")
    assert code == 2 and "STEERLAB_LSL" in err


def test_an_outlet_that_cannot_be_made_does_not_stop_the_session(
    tmp_path, short_protocol, monkeypatch
):
    import pylsl

    def broken(*a, **kw):
        raise RuntimeError("could not create outlet (injected)")

    monkeypatch.setattr(pylsl, "StreamOutlet", broken)
    plan = build_plan(short_protocol, 1)
    plan = replace(plan, trials=plan.trials[:2])
    said: list[str] = []
    eng, pub, path = _session(tmp_path, plan, _rig().batch_loop(), SYNTHETIC, warn=said.append)
    assert eng.run() is State.DONE
    assert len(said) == 1 and "injected" in said[0] and "go on" in said[0]
    assert "injected" in pub.problem and not pub.publishing
    recs = SessionFile(path).records()
    assert [r.status for r in recs] == ["complete", "complete"]
    assert all(r.n_samples == plan.setup(plan.trials[0]).n_samples for r in recs)
    assert all("lsl_clock_s" in r.attrs for r in recs)  # nothing lost, the clock included


def test_an_outlet_that_fails_in_mid_session_is_given_up(tmp_path, short_protocol):
    plan = build_plan(short_protocol, 1)
    plan = replace(plan, trials=plan.trials[:2])
    said: list[str] = []
    eng, pub, path = _session(tmp_path, plan, _rig().batch_loop(), SYNTHETIC, warn=said.append)
    pushed = []

    def on(e):
        if isinstance(e, ev.TrialStarted) and e.trial_index == 2:

            def push_chunk(*a, **kw):
                pushed.append(1)
                raise OSError("network gone (injected)")

            pub.signals.push_chunk = push_chunk

    eng.subscribe(on)
    assert eng.run() is State.DONE
    assert pushed == [1] and len(said) == 1 and "network gone" in said[0]
    assert [r.status for r in SessionFile(path).records()] == ["complete", "complete"]


def test_without_a_working_liblsl_the_session_runs_and_says_so_once(
    tmp_path, short_protocol, monkeypatch, caplog
):
    monkeypatch.setattr(lp, "load_pylsl", lambda: (None, "LSL not available (injected)"))
    monkeypatch.setattr(lp, "_warned", set())
    plan = build_plan(short_protocol, 1)
    plan = replace(plan, trials=plan.trials[:2])
    with caplog.at_level(logging.WARNING, logger=lp.__name__):
        clocks = [LabClock(SYNTHETIC) for _ in range(2)]
        eng = SessionEngine(plan, _rig().batch_loop())
        path = tmp_path / "S01.h5"
        eng.subscribe(
            SessionWriter(path, first_sample_attributes=clocks[0].first_sample_attributes)
        )
        sub = lp.lab_subscriber(clocks[0], True)
        assert sub is clocks[0]  # nothing to publish with
        eng.subscribe(sub)
        assert eng.run() is State.DONE
    warned = [r for r in caplog.records if "injected" in r.getMessage()]
    assert len(warned) == 1 and "lsl_clock_s" in warned[0].getMessage()
    recs = SessionFile(path).records()
    assert [r.status for r in recs] == ["complete", "complete"]
    assert not any("lsl_clock_s" in r.attrs for r in recs)


def test_a_failing_clock_costs_the_writer_nothing(tmp_path, short_protocol, caplog):
    plan = build_plan(short_protocol, 1)
    plan = replace(plan, trials=plan.trials[:1])

    def broken(e):
        raise RuntimeError("clock broke (injected)")

    eng = SessionEngine(plan, _rig().batch_loop())
    eng.subscribe(SessionWriter(tmp_path / "S01.h5", first_sample_attributes=broken))
    with caplog.at_level(logging.WARNING):
        assert eng.run() is State.DONE
    assert any("clock broke" in r.getMessage() for r in caplog.records)
    (rec,) = SessionFile(tmp_path / "S01.h5").records()
    assert rec.status == "complete" and "lsl_clock_s" not in rec.attrs


def test_the_session_file_reads_the_clock_back_and_exports_it(tmp_path, short_protocol):
    plan = build_plan(short_protocol, 1)
    plan = replace(plan, trials=plan.trials[:1])
    clock = LabClock(HOST)
    eng = SessionEngine(plan, _rig().batch_loop())
    eng.subscribe(
        SessionWriter(tmp_path / "S01.h5", first_sample_attributes=clock.first_sample_attributes)
    )
    eng.subscribe(clock)
    before = clock.now()
    eng.run()
    (rec,) = SessionFile(tmp_path / "S01.h5").records()
    assert isinstance(rec.attrs["lsl_clock_s"], float)
    # Host monotonic: the first block's arrival less its span, after the session began.
    assert before - 1.0 < rec.attrs["lsl_clock_s"] < clock.now()
    assert rec.attrs["lsl_clock_source"] == "host monotonic"


def test_a_second_run_of_the_engine_keeps_the_same_streams(tmp_path, short_protocol, outlets):
    """A resume (the engine run again after an aborted trial) publishes on the same outlets,
    with a second session_start; the redo's attempt is a trial of its own."""
    plan = build_plan(short_protocol, 1)
    plan = replace(plan, trials=plan.trials[:2])
    loop = FaultAfter(_rig().batch_loop(block_s=0.25), trial_index=2, blocks=1)
    eng, pub, path = _session(tmp_path, plan, loop, SYNTHETIC, wait_for_consumers_s=30)
    rx = Receiver(_source_id(pub, plan))
    try:
        assert eng.run() is State.IDLE
        loop.trial_index = 0  # no more faults
        eng.redo(1)
        assert eng.run() is State.DONE
    finally:
        rx.stop()
        pub.close()
    assert len(outlets.made) == 2
    assert rx.events() == [
        "session_start", "trial_start", "trial_stop", "trial_start", "abort", "trial_stop",
        "session_stop", "superseded",
        "session_start", "trial_start", "trial_stop", "trial_start", "trial_stop",
        "session_stop",
    ]  # fmt: skip
    runs = [m["run"] for m, _ in rx.markers if m["event"] == "session_start"]
    assert runs == [1, 2]
    starts = [m for m, _ in rx.markers if m["event"] == "trial_start"]
    assert [(m["trial_index"], m["attempt"]) for m in starts] == [(1, 1), (2, 1), (1, 2), (2, 2)]
    recs = SessionFile(path).records()
    assert len(rx.stamps) == sum(r.n_samples for r in recs)
