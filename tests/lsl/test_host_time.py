"""Each sample's host time (``host_time_s``: ``time.monotonic()`` at its cycle's read) from
every trial loop, and the lab's clock stamping from it: how late a block arrives, or a pause in
the trial, does not move a sample."""

from __future__ import annotations

import time

import numpy as np
import pytest

from steerlab.hardware.loop import BLOCK_CHANNELS, HOST_TIME_CHANNEL
from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.world import WorldConfig
from steerlab.hardware.trial_loops import simulated_loop
from steerlab.protocols import events as ev
from steerlab.protocols.engine import LoopControl
from steerlab.protocols.lsl_publisher import HOST, SYNTHETIC, LabClock
from steerlab.protocols.session import build_plan

OFFSET = 1000.0  # the fake LSL clock: the host's monotonic clock plus this
FS = 100.0


class FakeLsl:
    """A pylsl whose local_clock() is time.monotonic() + OFFSET; ``late`` s more, to play a
    block arriving late."""

    def __init__(self) -> None:
        self.late = 0.0

    def local_clock(self) -> float:
        return time.monotonic() + OFFSET + self.late


def _block(start: int, n: int, host0: float | None) -> ev.SamplesAcquired:
    ch = {"time_s": np.arange(start, start + n) / FS, "wheel_angle_rad": np.zeros(n)}
    if host0 is not None:
        ch[HOST_TIME_CHANNEL] = host0 + np.arange(n) / FS
    return ev.SamplesAcquired("T1", start, ch)


def _start(clock: LabClock) -> None:
    clock(ev.TrialStarted("T1", 1, 1, "RT", {"fs_hz": FS}, 10))


def test_blocks_with_host_times_are_stamped_at_them_however_late_they_come():
    lsl = FakeLsl()
    clock = LabClock(HOST, lsl=lsl)
    _start(clock)
    assert clock.offset_s == pytest.approx(OFFSET, abs=1e-3)
    b0 = _block(0, 5, host0=50.0)
    clock(b0)
    attrs = clock.first_sample_attributes(b0)
    assert attrs == {
        "lsl_clock_s": 50.0 + clock.offset_s,
        "lsl_clock_source": HOST,
        "lsl_clock_offset_s": clock.offset_s,
    }
    np.testing.assert_array_equal(clock.timestamps(b0), b0.channels["host_time_s"] + clock.offset_s)
    # A block that comes 3 s late, after a pause of 2 s in the trial: each sample where it was read.
    lsl.late = 3.0
    clock(ev.TrialMark("T1", 5, "pause"))
    clock(ev.TrialMark("T1", 5, "resume"))
    b1 = _block(5, 5, host0=52.0)
    clock(b1)
    np.testing.assert_array_equal(clock.timestamps(b1), b1.channels["host_time_s"] + clock.offset_s)
    assert clock.resyncs == 0
    # A sample after the newest: that many periods after the newest's stamp.
    assert clock.at_sample("T1", 10) == b1.channels["host_time_s"][-1] + clock.offset_s + 1 / FS
    assert clock.at_sample("T1", 0) == attrs["lsl_clock_s"]


def test_blocks_without_host_times_are_stamped_from_their_arrival():
    lsl = FakeLsl()
    clock = LabClock(HOST, lsl=lsl)
    _start(clock)
    b0 = _block(0, 5, host0=None)
    before = lsl.local_clock()
    clock(b0)
    attrs = clock.first_sample_attributes(b0)
    assert "lsl_clock_offset_s" not in attrs
    # Sample 0 at the block's arrival less its span.
    assert before - 0.04 <= attrs["lsl_clock_s"] <= lsl.local_clock() - 0.04
    np.testing.assert_allclose(np.diff(clock.timestamps(b0)), 1 / FS)


def test_a_synthetic_clock_ignores_host_times():
    lsl = FakeLsl()
    clock = LabClock(SYNTHETIC, lsl=lsl)
    _start(clock)
    b0 = _block(0, 5, host0=50.0)
    clock(b0)
    attrs = clock.first_sample_attributes(b0)
    assert attrs["lsl_clock_source"] == SYNTHETIC and "lsl_clock_offset_s" not in attrs
    assert attrs["lsl_clock_s"] > OFFSET  # the LSL clock now, not the host times given


def test_a_batch_simulation_records_no_host_times(short_protocol):
    """A block computed at once has no instant of a read; its clock is synthetic, and a
    float64 channel of 8 bytes a sample would cost an 18-subject demo a third of its size."""
    plan = build_plan(short_protocol, 1)
    loop, _ = simulated_loop(
        make_population(1, seed=3)[0], WorldConfig(fs_hz=200.0), pace="batch", block_s=0.25
    )
    blocks = list(loop.run_trial(plan.setup(plan.trials[0]), LoopControl()))
    assert blocks and all(HOST_TIME_CHANNEL not in b for b in blocks)


@pytest.mark.parametrize("pace", ["stepped"])
def test_every_simulated_loop_gives_host_times(pace, short_protocol):
    plan = build_plan(short_protocol, 1)
    loop, _ = simulated_loop(
        make_population(1, seed=3)[0], WorldConfig(fs_hz=200.0), pace=pace, block_s=0.25
    )
    t0 = time.monotonic()
    blocks = list(loop.run_trial(plan.setup(plan.trials[0]), LoopControl()))
    t1 = time.monotonic()
    assert all(set(BLOCK_CHANNELS) <= set(b) for b in blocks)
    host = np.concatenate([b[HOST_TIME_CHANNEL] for b in blocks])
    assert len(host) == sum(len(b["time_s"]) for b in blocks) > 0
    assert np.all(np.diff(host) >= 0) and t0 <= host[0] and host[-1] <= t1
