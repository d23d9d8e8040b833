"""``steerlab run`` publishes its session on LSL by default, from the lab's real-time loop (in
a process of its own), on the host's clock; ``--no-lsl`` publishes nothing."""

from __future__ import annotations

import numpy as np

import steerlab.app.run as run_module
from steerlab.app.run import run_session
from steerlab.protocols.datafile import SessionFile
from steerlab.protocols.lsl_publisher import LslPublisher, source_id_for
from tests.session_helpers import SHORT_TRIALS_KW, short_protocol

from .conftest import Receiver

# Two short trials (1.75 s each at 1 kHz, the simulated rig's rate), no breaks.
TWO_TRIALS = short_protocol("lsl-run-test", **SHORT_TRIALS_KW)


def test_run_publishes_on_the_host_clock(tmp_path, lenient_rig, monkeypatch):
    protocol = tmp_path / "two.toml"
    protocol.write_text(TWO_TRIALS)
    out = tmp_path / "sessions"
    made = []
    real = run_module.lab_subscriber

    def waiting(*a, **kw):  # the test's inlets connect before the first marker
        made.append(real(*a, **kw, wait_for_consumers_s=60))
        return made[-1]

    monkeypatch.setattr(run_module, "lab_subscriber", waiting)
    said: list[str] = []
    rx = Receiver(source_id_for(lenient_rig.stem, "S01", out / "S01.h5"), timeout_s=120)
    try:
        run_session(
            str(lenient_rig), 1, out, protocol_path=str(protocol), breaks=False,
            say=said.append, on_abort="stop",
        )  # fmt: skip
    finally:
        rx.stop()
    (pub,) = made
    assert isinstance(pub, LslPublisher) and pub.problem is None
    assert any("publishing on LSL: 'Steerlab S01'" in s for s in said), said
    recs = sorted(SessionFile(out / "S01.h5").records(), key=lambda r: r.trial_index)
    assert recs, said
    stamps = np.asarray(rx.stamps)
    assert len(stamps) == sum(r.n_samples for r in recs)
    starts = [t for m, t in rx.markers if m["event"] == "trial_start"]
    stops = [m for m, _ in rx.markers if m["event"] == "trial_stop"]
    k = 0
    for r, t, stop in zip(recs, starts, stops, strict=True):
        assert r.attrs["lsl_clock_source"] == "host monotonic"
        assert stamps[k] == r.attrs["lsl_clock_s"] == t
        assert (stop["status"], stop["n_samples"]) == (r.status, r.n_samples)
        # Each sample at its host_time_s (taken in the loop's process, sent through the pipe).
        host = r.extra["host_time_s"]
        assert len(host) == r.n_samples and np.all(np.diff(host) > 0)
        assert r.attrs["lsl_clock_s"] == host[0] + r.attrs["lsl_clock_offset_s"]
        got = stamps[k : k + r.n_samples]
        np.testing.assert_array_equal(got, host + r.attrs["lsl_clock_offset_s"])
        k += r.n_samples
    # On the host's clock: the session's samples were stamped within the session's run.
    sessions = [t for m, t in rx.markers if m["event"] in ("session_start", "session_stop")]
    assert sessions[0] < stamps[0] and stamps[-1] < sessions[-1] + 0.1
    assert rx.events()[0] == "session_start" and rx.events()[-1] == "session_stop"


def test_run_no_lsl_publishes_nothing(tmp_path, lenient_rig, outlets):
    protocol = tmp_path / "two.toml"
    protocol.write_text(TWO_TRIALS.rsplit("[[conditions]]", 1)[0])  # one trial
    said: list[str] = []
    run_session(
        str(lenient_rig), 1, tmp_path / "s", protocol_path=str(protocol), breaks=False,
        say=said.append, on_abort="stop", lsl=False,
    )  # fmt: skip
    assert outlets.made == []
    assert not any("LSL" in s for s in said), said
    recs = SessionFile(tmp_path / "s" / "S01.h5").records()
    assert recs and all(r.attrs["lsl_clock_source"] == "host monotonic" for r in recs)
