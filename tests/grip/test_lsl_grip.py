"""Grip force from an LSL stream (``[glove] kind = "lsl"``), against a real pylsl outlet in the
test process standing in for a glove; then short simulated sessions whose grip comes from the
simulated rig's own LSL outlet, in this process and (as ``steerlab run`` has it) in the
simulated lab's process.

Every stream here has a name of its own: the test workers of one machine share its loopback."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import replace

import numpy as np
import pylsl
import pytest

from steerlab.hardware.grip.common import ForceScale, HandScale
from steerlab.hardware.grip.lsl_source import (
    KIND,
    LslGripConfig,
    LslGripSource,
    SimulatedLslGrip,
    open_lsl,
)
from steerlab.hardware.grip.reader import GripSourceError
from steerlab.hardware.interfaces import GripSource
from tests.grip.conftest import lenient, nearest_gap
from tests.helpers import ROOT, assert_no_threads, closing_factory, wait_for

LABELS = ["time", "grip_L", "grip_R", "aux"]
RAW = ForceScale("raw", HandScale(0.5, 10.0), HandScale(0.25, -2.0))


@pytest.fixture(autouse=True)
def no_thread_left_behind():
    yield
    assert_no_threads("grip-lsl")


class Glove:
    """An LSL outlet in the test process standing in for a glove: 4 float channels labelled
    ``LABELS``, pushed by the test (``push``) or at 100 Hz by a thread (``stream``)."""

    def __init__(self, labels=LABELS, fmt=pylsl.cf_float32, source_id: str | None = None,
                 name: str | None = None) -> None:  # fmt: skip
        self.name = name or f"TestGlove-{uuid.uuid4().hex[:8]}"
        info = pylsl.StreamInfo(self.name, "Grip", len(labels), 100.0, fmt,
                                source_id or self.name)  # fmt: skip
        info.set_channel_labels(labels)
        self.outlet: pylsl.StreamOutlet | None = pylsl.StreamOutlet(info)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.value = [0.0, 30.0, 10.0, 99.0]

    def push(self, sample) -> None:
        assert self.outlet is not None
        self.outlet.push_sample(sample)

    def stream(self) -> None:
        def run():
            while not self._stop.wait(0.01):
                if self.outlet is not None:
                    self.outlet.push_sample(self.value)

        self._thread = threading.Thread(target=run, name="test-outlet", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)

    def vanish(self) -> None:
        """The glove's program exits: its outlet is destroyed."""
        self.stop()
        self.outlet = None

    def config(self, left=1, right=2, scale=RAW, **fields) -> LslGripConfig:
        return LslGripConfig(self.name, None, None, left, right, scale, 2.0, "rig.toml",
                             **fields)  # fmt: skip


@pytest.fixture
def glove() -> Iterator[Callable[..., Glove]]:
    yield from closing_factory(Glove, Glove.vanish)


@pytest.fixture
def opened() -> Iterator[Callable[..., GripSource]]:
    yield from closing_factory(open_lsl)


def test_values_arrive_calibrated_by_channel_index(glove, opened):
    g = glove()
    src = opened(g.config(left=1, right=2))
    assert isinstance(src, GripSource) and src.latest() is None and src.age_s() is None
    assert src.describe() == f"LSL stream {g.name!r} of type 'Grip'"
    g.push([5.0, 30.0, 10.0, 99.0])
    wait_for(lambda: src.latest() is not None)
    r = src.latest()
    assert (r.left_n, r.right_n, r.sequence) == (0.5 * (30 - 10), 0.25 * (10 + 2), 1)
    assert src.latest_device_time_s() == pytest.approx(pylsl.local_clock(), abs=1.0)
    for i in range(20):
        g.push([5.0, 30.0 + i, 10.0, 99.0])
    wait_for(lambda: src.stats().samples == 21)
    assert src.latest().left_n == pytest.approx(0.5 * (49 - 10))
    assert src.stream_alive(timeout_s=1.0) and src.problem(1.0) is None
    st = src.stats()
    assert st.running and st.error is None and st.bad_samples == 0


def test_channels_by_label_and_values_in_newtons(glove, opened):
    g = glove()
    src = opened(g.config(left="grip_L", right="grip_R", scale=ForceScale("N")))
    g.push([5.0, 31.5, 12.25, 99.0])
    wait_for(lambda: src.latest() is not None)
    assert (src.latest().left_n, src.latest().right_n) == (31.5, 12.25)
    # The other way round: the hands are whichever channels the rig file names.
    src2 = opened(g.config(left="grip_R", right=0, scale=ForceScale("N")))
    g.push([7.0, 31.5, 12.25, 99.0])
    wait_for(lambda: src2.latest() is not None)
    assert (src2.latest().left_n, src2.latest().right_n) == (12.25, 7.0)


def test_age_grows_once_the_outlet_stops_and_the_trial_stops_naming_the_stream(glove, opened):
    g = glove()
    g.stream()
    src = opened(g.config())
    wait_for(lambda: src.stats().samples >= 10)
    assert src.stream_alive(timeout_s=0.5) and src.problem(0.25) is None
    # Samples keep arriving; how fast on a loaded machine is the benchmarks' business.
    seen = src.stats().samples
    wait_for(lambda: src.stats().samples > seen)
    assert src.stats().rate_hz > 0
    g.stop()
    time.sleep(0.4)
    age = src.age_s()
    assert age >= 0.35 and not src.stream_alive(timeout_s=0.25)
    problem = src.problem(0.25)
    assert problem.startswith("glove stream stopped: no valid sample for ")
    assert problem.endswith(f" s from LSL stream {g.name!r} of type 'Grip'")
    assert src.error is None  # a quiet stream is not a failed reader


def test_a_vanished_stream_is_a_stopped_stream_naming_it(glove, opened):
    g = glove()
    g.stream()
    src = opened(g.config())
    wait_for(lambda: src.stats().samples >= 5)
    g.vanish()
    time.sleep(0.4)
    assert not src.stream_alive(timeout_s=0.25) and src.age_s() >= 0.35
    assert f"from LSL stream {g.name!r}" in src.problem(0.25)
    assert src.error is None and src.running  # it keeps waiting: LSL reconnects if it returns


def test_a_failed_reader_stops_the_trial_naming_the_stream():
    class Info:
        def name(self):
            return "GripGlove"

        def type(self):
            return "Grip"

    class BrokenInlet:
        def pull_sample(self, timeout):
            raise OSError("the inlet broke")

        def close_stream(self):
            pass

    src = LslGripSource(BrokenInlet(), Info(), 0, 1, ForceScale("N")).start()
    try:
        wait_for(lambda: src.error is not None)
        assert src.problem(60.0) == "LSL stream 'GripGlove' of type 'Grip' failed: the inlet broke"
    finally:
        src.close()


def test_no_such_stream_is_named(opened):
    name = f"NoSuchGlove-{uuid.uuid4().hex[:8]}"
    config = LslGripConfig(name, "Grip", None, 0, 1, ForceScale("N"), 0.3, "lab.toml")
    with pytest.raises(GripSourceError) as info:
        opened(config)
    message = str(info.value)
    assert f"no LSL stream named {name!r} of type 'Grip' found within 0.3 s" in message
    assert "(lab.toml: [glove])" in message


def test_a_channel_that_is_not_there_is_named(glove, opened):
    g = glove()
    with pytest.raises(GripSourceError) as info:
        opened(g.config(left="grip_left"))
    assert f"LSL stream {g.name!r} has no channel labelled 'grip_left'" in str(info.value)
    assert "([glove.channels] left)" in str(info.value)
    assert "'time', 'grip_L', 'grip_R', 'aux'" in str(info.value)
    with pytest.raises(GripSourceError, match=r"has 4 channels \(0..3\): \[glove.channels\] "
                       r"right = 4 is not one of them"):  # fmt: skip
        opened(g.config(right=4))


def test_two_streams_that_match_are_listed_and_a_source_id_picks_one(glove, opened):
    name = f"TwinGlove-{uuid.uuid4().hex[:8]}"
    a = glove(name=name, source_id=f"{name}-a")
    b = glove(name=name, source_id=f"{name}-b")
    config = a.config()
    with pytest.raises(GripSourceError) as info:
        opened(config)
    assert f"2 LSL streams named {name!r} answer" in str(info.value)
    assert f"'{name}-a'" in str(info.value) and f"'{name}-b'" in str(info.value)
    src = opened(replace(config, source_id=f"{name}-b"))
    b.push([0.0, 20.0, 10.0, 0.0])
    a.push([0.0, 40.0, 10.0, 0.0])
    wait_for(lambda: src.latest() is not None)
    time.sleep(0.1)
    assert src.stats().samples == 1 and src.latest().left_n == 5.0


def test_samples_that_are_not_numbers_are_skipped_and_counted(glove, opened):
    g = glove()
    src = opened(g.config())
    g.push([0.0, 30.0, 10.0, 0.0])
    g.push([0.0, float("nan"), 10.0, 0.0])
    g.push([0.0, 32.0, 10.0, 0.0])
    wait_for(lambda: src.stats().samples == 2)
    st = src.stats()
    assert st.bad_samples == 1 and "channel 1 (left) = nan" in st.last_bad_reason
    assert src.latest().left_n == 11.0


def test_a_text_stream_is_refused(glove, opened):
    g = glove(fmt=pylsl.cf_string)
    with pytest.raises(GripSourceError, match="sends text"):
        opened(g.config())


def test_the_simulated_outlet_publishes_the_grip_as_configured(opened):
    config = LslGripConfig(None, f"SimGrip{uuid.uuid4().hex[:6]}", None, 3, "grip_right", RAW)
    grip = [(20.0, 30.0)]
    sim = SimulatedLslGrip(lambda t: grip[0], config)
    sim.start()
    try:
        src = opened(KIND.at(config, sim.address))
        assert src.describe() == f"LSL stream 'SteerlabSimulatedGrip' of type {config.type!r}"
        wait_for(lambda: src.stats().samples >= 5)
        assert (src.latest().left_n, src.latest().right_n) == (pytest.approx(20.0),
                                                              pytest.approx(30.0))  # fmt: skip
        grip[0] = (5.0, 7.5)
        wait_for(lambda: src.latest().left_n == pytest.approx(5.0))
        sim.stop_streaming()
        time.sleep(0.3)
        assert not src.stream_alive(timeout_s=0.2)
        sim.resume_streaming()
        wait_for(lambda: src.stream_alive(timeout_s=0.2))
        sim.inject("glove_hang_up")
        time.sleep(0.3)
        assert not src.stream_alive(timeout_s=0.2) and sim.samples_skipped > 0
    finally:
        sim.close()


# -- sessions whose grip comes from the simulated rig's LSL outlet --------------------------------

LSL_RIG = ROOT / "hardware" / "rigs" / "simulated-lsl-grip.toml"


@pytest.fixture
def lsl_rig():
    return lenient(LSL_RIG)


def test_a_simulated_session_records_the_lsl_streams_grip(lsl_rig, grip_session, world_grip):
    state, (r,), _, devices = grip_session(lsl_rig)
    assert r.status == "complete", r.abort_reason
    assert devices.glove.describe() == "LSL stream 'SteerlabSimulatedGrip' of type 'Grip'"
    assert devices.glove_config.source_id == devices.glove_sim.address  # this rig's, no other
    # Every recorded grip force is one the simulated subject produced (float32 on the wire:
    # within 1e-4 N), and it followed the subject at ~100 Hz.
    assert nearest_gap(r.grip_force_N, world_grip).max() < 1e-4
    assert np.count_nonzero(np.diff(r.grip_force_N)) > 100
    assert np.std(r.grip_force_N) > 0.1


def test_a_stream_that_vanishes_mid_trial_aborts_it_naming_the_stream_keeping_every_sample(
    lsl_rig, grip_session
):
    state, (r,), seen, devices = grip_session(lsl_rig, inject=lambda d: d.glove_sim.hang_up())
    assert r.status == "aborted"
    assert r.abort_reason.startswith("glove stream stopped: no valid sample for ")
    assert r.abort_reason.endswith(" s from LSL stream 'SteerlabSimulatedGrip' of type 'Grip'")
    emitted = sum(e.n for e in seen)
    assert r.n_samples == emitted >= 1000
    assert r.attrs["marks"][-1]["kind"] == "abort"
    assert not devices.drive.enabled


def test_steerlab_run_path_the_lab_process_publishes_the_stream(lab_session):
    """The simulated lab in a process of its own (``steerlab run`` on a simulated rig) publishes
    the grip; the loop's process finds it by the source id the lab reports, and a stream that
    stops there aborts the next trial, naming it."""
    (first, *rest), address, pty = lab_session(
        LSL_RIG, trials=2, between=lambda loop: loop.lab.inject("glove_stop")
    )
    assert address.startswith("steerlab-sim-") and pty is None
    assert first.status == "complete", first.abort_reason
    assert np.count_nonzero(np.diff(first.grip_force_N)) > 100
    assert np.all(np.isfinite(first.grip_force_N)) and np.std(first.grip_force_N) > 0.1
    assert rest and rest[0].status == "aborted"
    assert rest[0].abort_reason.startswith("glove stream stopped: no valid sample for ")
    assert "from LSL stream 'SteerlabSimulatedGrip'" in rest[0].abort_reason
