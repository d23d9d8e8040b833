"""End to end through a real pseudo-terminal: SimulatedGloveUnit -> serial.Serial -> unit."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator

import pytest
import serial

from steerlab.hardware.glove.calibration import GloveCalibration
from steerlab.hardware.glove.simulated import GloveFaults, SimulatedGloveUnit
from steerlab.hardware.glove.unit import SerialGloveUnit

CAL = GloveCalibration.from_config(
    {
        "left": {"gain_n_per_count": 0.01, "offset_counts": 1000},
        "right": {"gain_n_per_count": 0.02, "offset_counts": 500},
    }
)


def ramp(t: float) -> tuple[float, float]:
    return 12.5, 30.0 + 10.0 * t


def wait_for(condition: Callable[[], object], timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)


def open_fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


@pytest.fixture(autouse=True)
def no_leaks():
    fds = open_fds()
    yield
    leftovers = [t.name for t in threading.enumerate() if t.name.startswith("glove-")]
    assert not leftovers, f"threads still running: {leftovers}"
    assert open_fds() <= fds, "file descriptors leaked"


class Rig:
    def __init__(self, **sim_options) -> None:
        self.errors: list[BaseException] = []
        self.sim = SimulatedGloveUnit(sim_options.pop("source", ramp), CAL, **sim_options)
        # Open the port before the simulator streams: pyserial flushes input on open.
        self.port = serial.Serial(self.sim.port, timeout=0.05)
        self.unit = SerialGloveUnit(self.port, CAL, on_error=self.errors.append).start()
        self.sim.start()

    def frames_after(self, n: int) -> None:
        target = self.unit.stats().frames + n
        wait_for(lambda: self.unit.stats().frames >= target)

    def close(self) -> None:
        self.unit.close()
        self.sim.close()


@pytest.fixture
def rig() -> Iterator[Callable[..., Rig]]:
    rigs: list[Rig] = []

    def make(**options) -> Rig:
        rigs.append(Rig(**options))
        return rigs[-1]

    yield make
    for r in rigs:
        r.close()


def test_frames_arrive_at_about_100_hz_calibrated(rig):
    r = rig()
    assert r.sim.port.startswith("/dev/")
    wait_for(lambda: r.unit.latest() is not None)
    t_first = r.unit.latest().host_time_s
    time.sleep(1.0)
    reading = r.unit.latest()
    stats = r.unit.stats()
    assert 80.0 < stats.rate_hz < 120.0
    assert 75 <= stats.frames <= 130
    assert (stats.crc_errors, stats.dropped_frames, stats.resyncs, stats.bad_headers) == (0,) * 4
    assert r.unit.stream_alive(timeout_s=0.2)
    # One count is 0.01 N left, 0.02 N right.
    assert reading.left_n == pytest.approx(12.5, abs=0.005)
    frame = r.unit.latest_frame()
    t_sim = frame.device_time_us * 1e-6  # the simulator starts its device clock at 0
    assert reading.right_n == pytest.approx(30.0 + 10.0 * t_sim, abs=0.011)
    assert reading.host_time_s - t_first == pytest.approx(t_sim, abs=0.1)
    assert r.unit.error is None and r.sim.error is None


def test_injected_faults_are_counted_exactly(rig):
    r = rig()
    r.frames_after(5)

    def delta(before, field):
        return getattr(r.unit.stats(), field) - getattr(before, field)

    before = r.unit.stats()
    r.sim.drop_next(3)
    r.frames_after(5)
    assert delta(before, "dropped_frames") == 3
    assert delta(before, "resyncs") == 0

    before = r.unit.stats()
    r.sim.crc_error_next(2)
    r.frames_after(5)
    assert delta(before, "crc_errors") == 2
    assert delta(before, "dropped_frames") == 2  # rejected frames leave sequence gaps too
    assert delta(before, "bytes_discarded") == 2 * 22

    before = r.unit.stats()
    r.sim.send_garbage(b"\x00\x13\x37" * 5)
    r.frames_after(3)
    assert delta(before, "resyncs") == 1
    assert delta(before, "bytes_discarded") == 15
    assert delta(before, "dropped_frames") == 0

    before = r.unit.stats()
    r.sim.out_of_range_next()
    r.frames_after(3)
    assert delta(before, "out_of_range") == 1
    assert delta(before, "dropped_frames") == 0  # a CRC-valid out-of-range frame is no gap
    assert r.unit.error is None
    assert r.sim.stats().faults_injected == 2 + 1 + 1


def test_stopped_stream_is_detected_and_resumes_with_a_gap(rig):
    r = rig()
    r.frames_after(3)
    r.sim.stop_streaming()
    wait_for(lambda: not r.unit.stream_alive(timeout_s=0.1))
    assert r.unit.age_s() > 0.1
    assert r.unit.error is None  # quiet is not broken: the engine decides from the age
    r.sim.resume_streaming()
    r.frames_after(3)
    assert r.unit.stream_alive(timeout_s=0.1)
    assert r.unit.stats().dropped_frames >= 9


def test_pty_closed_mid_stream_surfaces_an_error(rig):
    r = rig()
    r.frames_after(5)
    r.sim.hang_up()
    wait_for(lambda: r.unit.error is not None)
    wait_for(lambda: not r.unit.running)
    assert isinstance(r.unit.error, serial.SerialException | OSError)
    assert r.errors == [r.unit.error]
    assert not r.unit.stream_alive(timeout_s=60.0)
    with pytest.raises(RuntimeError, match="glove reader failed"):
        r.unit.check()


def test_random_faults_soak(rig):
    faults = GloveFaults(corrupt_byte=0.05, crc_error=0.05, drop=0.05, garbage=0.05)
    r = rig(faults=faults, seed=3, start_sequence=65_500, start_time_us=2**32 - 200_000)
    r.frames_after(80)
    stats = r.unit.stats()
    assert stats.crc_errors + stats.bad_headers > 0
    assert stats.dropped_frames > 0 and stats.resyncs > 0
    assert stats.sequence_resets == 0 and stats.duplicates == 0  # wrapped at 65536 cleanly
    first_seq = 65_500
    last = r.unit.latest_frame()
    # Every sequence number up to the newest is either accepted or counted as dropped.
    assert stats.frames + stats.dropped_frames <= last.sequence_ext - first_seq + 1
    assert last.sequence_ext > 65_536
    assert r.unit.error is None and r.sim.error is None


def test_pressure_maps_end_to_end(rig):
    left, right = bytes(range(200)) + bytes(149), bytes([42]) * 349
    r = rig(pressure_map=lambda t: (left, right))
    r.frames_after(3)
    frame = r.unit.latest_frame()
    assert frame.cells_left == left and frame.cells_right == right
    assert r.unit.latest().left_n == pytest.approx(12.5, abs=0.005)


def test_simulator_alone_cleans_up_even_without_a_reader():
    # Nobody reads: the pty fills up, frames overflow, close() must still be prompt.
    sim = SimulatedGloveUnit(ramp, CAL, rate_hz=2000.0, pressure_map=lambda t: (bytes(349),) * 2)
    sim.start()
    wait_for(lambda: sim.stats().overflows > 0)
    t0 = time.monotonic()
    sim.close()
    assert time.monotonic() - t0 < 0.5
    sim.close()  # idempotent


def test_simulator_reports_a_failing_source():
    errors = []

    def broken(t):
        raise ValueError("world exploded")

    sim = SimulatedGloveUnit(broken, CAL, on_error=errors.append).start()
    wait_for(lambda: not sim.running)
    assert isinstance(sim.error, ValueError) and errors == [sim.error]
    sim.close()


def test_fault_options_are_validated():
    with pytest.raises(ValueError, match="GloveFaults.drop"):
        GloveFaults(drop=1.5)
