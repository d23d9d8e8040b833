"""A text-line grip device (``[glove] kind = "serial-text"``) through a real pseudo-terminal:
lines written into the pty's master, read by :class:`TextGripSource` through ``serial.Serial``
on its slave, as from a microcontroller's USB serial port; then a short simulated session whose
grip comes from the simulated text-line device."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import replace

import numpy as np
import pytest
import serial

from steerlab.hardware.grip.common import ForceScale, HandScale
from steerlab.hardware.grip.pty import raw_pty
from steerlab.hardware.grip.reader import GripSourceError
from steerlab.hardware.grip.text_simulated import SimulatedTextDevice
from steerlab.hardware.grip.text_source import KIND, TextGripConfig, TextGripSource
from steerlab.hardware.interfaces import GripReading, GripSource
from tests.grip.conftest import lenient, nearest_gap
from tests.helpers import ROOT, assert_no_threads, closing_factory, wait_for

RAW = ForceScale("raw", HandScale(0.05, 12.0), HandScale(0.02, 9.0))
CONFIG = TextGripConfig("simulated", 115200, ",", 1, 2, 0, "ms", RAW, "rig.toml")


@pytest.fixture(autouse=True)
def no_thread_left_behind():
    yield
    assert_no_threads("grip-text")


class Line:
    """A pty whose master the test writes lines into; the source reads its slave."""

    def __init__(self, config: TextGripConfig = CONFIG, **options) -> None:
        self.master, self.slave, self.path = raw_pty()
        self.port = serial.Serial(self.path, timeout=0.05)
        self.source = TextGripSource(self.port, replace(config, port=self.path), **options)

    def write(self, text: str) -> None:
        os.write(self.master, text.encode("ascii", errors="surrogateescape"))

    def close(self) -> None:
        self.source.close()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


@pytest.fixture
def line() -> Iterator[Callable[..., Line]]:
    def make(config: TextGripConfig = CONFIG, **options) -> Line:
        made = Line(config, **options)
        made.source.start()
        return made

    yield from closing_factory(make)


def test_good_lines_arrive_calibrated_with_the_device_time(line):
    ln = line()
    src = ln.source
    assert isinstance(src, GripSource)
    assert src.latest() is None and src.age_s() is None and not src.stream_alive()
    # The first bytes may be the end of a line cut by the port's opening: dropped.
    ln.write("5,13.1\r\n1000,212,509\r\n1010,252.5,1009\r\n")
    wait_for(lambda: src.stats().lines == 2)
    r = src.latest()
    assert r == GripReading(
        pytest.approx(0.05 * (252.5 - 12)), pytest.approx(0.02 * (1009 - 9)), r.host_time_s, 2
    )
    assert src.latest_device_time_s() == pytest.approx(1.010)
    assert src.stream_alive(timeout_s=1.0) and src.problem(1.0) is None
    st = src.stats()
    assert (st.lines, st.bad_lines, st.bytes_discarded) == (2, 0, len("5,13.1\r\n"))
    assert st.running and st.error is None and st.rate_hz >= 0
    assert src.describe() == f"serial-text device {ln.path}"


def test_a_line_with_a_missing_column_is_counted_and_reported_not_fatal(line, caplog, monkeypatch):
    ln = line()
    src = ln.source
    # Another test in this process may have configured logging (the CLI does), disabling the
    # loggers that existed then.
    logger = logging.getLogger("steerlab.hardware.grip.text_source")
    monkeypatch.setattr(logger, "disabled", False)
    with caplog.at_level(logging.WARNING, logger=logger.name):
        ln.write("\n1000,212,509\n1010,250\n\n1020,abc,509\n1030,232,nan\n1040,222,609\n")
        wait_for(lambda: src.stats().lines == 2)
    st = src.stats()
    assert (st.lines, st.bad_lines, st.empty_lines) == (2, 3, 1)
    assert src.latest().sequence == 2 and src.latest().left_n == pytest.approx(0.05 * 210)
    assert src.recent_bad_lines() == [
        ("1010,250", "column 2 (right) is missing: the line has 2 columns"),
        ("1020,abc,509", "column 1 (left) is not a number: 'abc'"),
        ("1030,232,nan", "column 2 (right) is not a finite number: 'nan'"),
    ]
    assert (st.last_bad_line, st.last_bad_reason) == src.recent_bad_lines()[-1]
    # Each bad line is logged with the device and the line's content.
    logged = [r.getMessage() for r in caplog.records if "bad line" in r.getMessage()]
    assert len(logged) == 3
    assert f"serial-text device {ln.path}: bad line 1 '1010,250': column 2 (right)" in logged[0]
    assert src.error is None and src.running


def test_a_stream_of_bad_lines_stops_the_trial_naming_the_device_and_the_line(line):
    now = [100.0]
    ln = line(clock=lambda: now[0])
    src = ln.source
    ln.write("\n1000,212,509\n")
    wait_for(lambda: src.stats().lines == 1)
    ln.write("1010,250\n1020,251\n")
    wait_for(lambda: src.stats().bad_lines == 2)
    assert src.problem(0.25) is None
    now[0] += 0.3
    assert src.problem(0.25) == (
        f"glove stream stopped: no valid line for 0.30 s from serial-text device {ln.path} "
        "(2 bad lines so far; the last: '1020,251': column 2 (right) is missing: the line has "
        "2 columns)"
    )


def test_a_stream_that_never_started_says_so(line):
    ln = line()
    ln.write("a header line\nleft,right\n")
    wait_for(lambda: ln.source.stats().bad_lines == 1)
    problem = ln.source.problem(0.25)
    assert problem.startswith("glove stream stopped: no valid line for ever from serial-text")
    assert "(1 bad line so far; the last: 'left,right': column 1 (left) is not a number" in problem


def test_garbage_without_line_ends_and_non_text_bytes_are_bad_lines(line):
    ln = line()
    ln.write("\n")
    ln.write("x" * 1500)
    wait_for(lambda: ln.source.stats().bad_lines == 1)
    assert ln.source.stats().last_bad_reason == "no line end within 1024 bytes"
    os.write(ln.master, b"\n1,\xff\xfe,2\n1000,212,509\n")
    wait_for(lambda: ln.source.stats().lines == 1)
    st = ln.source.stats()
    assert st.last_bad_reason == "not a text line (bytes outside ASCII)"
    assert (st.bad_lines, st.empty_lines) == (2, 1)  # the "\n" after the cut garbage: empty


def test_the_devices_clock_going_back_is_counted(line):
    ln = line()
    ln.write("\n5000,212,509\n5010,212,509\n10,212,509\n")
    wait_for(lambda: ln.source.stats().lines == 3)
    assert ln.source.stats().time_steps_back == 1
    assert ln.source.latest_device_time_s() == pytest.approx(0.010)


def test_newtons_and_whitespace_and_no_time_column(line):
    config = TextGripConfig("simulated", 9600, "\t", 0, 1, None, None, ForceScale("N"))
    ln = line(config)
    ln.write("\n12.5\t 13.25\n")
    wait_for(lambda: ln.source.latest() is not None)
    r = ln.source.latest()
    assert (r.left_n, r.right_n) == (12.5, 13.25) and ln.source.latest_device_time_s() is None


def test_a_device_unplugged_fails_the_reader_naming_it(line):
    ln = line()
    ln.write("\n1000,212,509\n")
    wait_for(lambda: ln.source.latest() is not None)
    os.close(ln.master)
    wait_for(lambda: ln.source.error is not None)
    problem = ln.source.problem(60.0)
    assert problem.startswith(f"serial-text device {ln.path} failed: "), problem
    with pytest.raises(GripSourceError, match=f"serial-text device {ln.path} failed"):
        ln.source.check()


def test_the_kind_names_a_port_it_cannot_open():
    with pytest.raises(GripSourceError, match="serial-text device: cannot open serial port "
                       "'/dev/steerlab-no-such-port'"):  # fmt: skip
        KIND.open(replace(CONFIG, port="/dev/steerlab-no-such-port"))


def test_the_simulated_device_writes_what_the_reader_reads():
    grip = [(20.0, 30.0)]
    sim = SimulatedTextDevice(lambda t: grip[0], CONFIG)
    port = serial.Serial(sim.port, timeout=0.05)
    src = TextGripSource(port, replace(CONFIG, port=sim.port)).start()
    sim.start()
    try:
        wait_for(lambda: src.stats().lines >= 5)
        r = src.latest()
        assert (r.left_n, r.right_n) == (pytest.approx(20.0, abs=1e-5), pytest.approx(30.0))
        grip[0] = (5.0, 7.5)
        wait_for(lambda: src.latest().left_n == pytest.approx(5.0, abs=1e-5))
        t0 = src.latest_device_time_s()
        wait_for(lambda: src.latest_device_time_s() >= t0 + 0.05)  # ms, ~100 Hz
        sim.inject("bad_line")
        wait_for(lambda: src.stats().bad_lines == 1)
        assert "column 2 (right) is missing" in src.stats().last_bad_reason
        sim.stop_streaming()
        time.sleep(0.1)
        n = src.stats().lines
        time.sleep(0.1)
        assert src.stats().lines == n and sim.lines_skipped > 0
        sim.resume_streaming()
        wait_for(lambda: src.stats().lines > n)
        assert src.stats().time_steps_back == 0
    finally:
        src.close()
        sim.close()


# -- a session whose grip comes from the simulated text-line device -------------------------------

TEXT_RIG = ROOT / "hardware" / "rigs" / "simulated-text-grip.toml"


@pytest.fixture
def text_rig():
    return lenient(TEXT_RIG)


def test_a_simulated_session_records_the_text_devices_grip(text_rig, grip_session, world_grip):
    state, (r,), _, devices = grip_session(text_rig)
    assert r.status == "complete", r.abort_reason
    assert devices.glove.describe() == f"serial-text device {devices.glove_sim.port}"
    assert devices.glove_config.port == devices.glove_sim.port
    # Every recorded grip force is one the simulated subject produced (the lines' 4 decimals
    # of a raw value, times the gain: within 1e-5 N), and it followed the subject at ~100 Hz.
    assert nearest_gap(r.grip_force_N, world_grip).max() < 1e-4
    assert np.count_nonzero(np.diff(r.grip_force_N)) > 100
    assert np.std(r.grip_force_N) > 0.1
    assert devices.glove.stats().bad_lines == 0


def test_bad_lines_then_silence_abort_the_trial_naming_the_device_and_keep_every_sample(
    text_rig, grip_session
):
    def inject(devices):
        for _ in range(3):
            devices.glove_sim.inject("bad_line")
        time.sleep(0.05)
        devices.glove_sim.stop_streaming()

    state, (r,), seen, devices = grip_session(text_rig, inject=inject)
    assert r.status == "aborted"
    assert r.abort_reason.startswith("glove stream stopped: no valid line for ")
    assert f"from serial-text device {devices.glove_sim.port} (3 bad lines so far; " in (
        r.abort_reason
    )
    assert "column 2 (right) is missing" in r.abort_reason
    # Every sample the loop took is in the file, up to the abort.
    emitted = sum(e.n for e in seen)
    assert r.n_samples == emitted >= 1500


def test_steerlab_run_path_the_lab_process_writes_the_lines_into_its_pty(lab_session):
    """As ``steerlab run`` has it: the simulated lab in a process of its own writes the lines
    into its pty, which the loop's process opens as the rig's port."""
    (r,), address, pty = lab_session(TEXT_RIG)
    assert address == pty and pty.startswith("/dev/")
    assert r.status == "complete", r.abort_reason
    assert np.count_nonzero(np.diff(r.grip_force_N)) > 100 and np.std(r.grip_force_N) > 0.1
