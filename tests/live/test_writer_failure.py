"""A failing session writer is a fault: the trial ends as aborted with zero torque at the drive,
and the file keeps every sample written before the failure. Disk full for real (a small tmpfs
filled by another writer), an injected ENOSPC, the file removed; and the free-space check
before a session."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from steerlab.hardware.live import ProcessLoop
from steerlab.protocols import events as ev
from steerlab.protocols.datafile import (
    DataFileError,
    SessionFile,
    SessionWriter,
    check_free_space,
    load_unsaved,
    unsaved_path,
)
from steerlab.protocols.engine import SessionEngine, State
from steerlab.protocols.session import build_plan
from tests.hardware.can_wire import wait_for
from tests.helpers import ROOT
from tests.live.conftest import SHORT_TRIAL_SAMPLES, on_fresh_rigs


@pytest.fixture
def tiny_disk(tmp_path):
    d = tmp_path / "disk"
    d.mkdir()
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(d)], capture_output=True, text=True
    )
    if r.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {r.stderr.strip()}")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


def _session(loop, protocol, path, inject, at_samples=1500):
    eng = SessionEngine(build_plan(protocol, 2), loop)
    writer = SessionWriter(path)
    eng.subscribe(writer)
    seen = []
    eng.subscribe(seen.append)
    fired = threading.Event()
    info: dict = {}

    def on(e):
        if isinstance(e, ev.SamplesAcquired) and e.start >= at_samples and not fired.is_set():
            fired.set()
            info["t"] = time.monotonic()
            info.update(inject(writer) or {})

    eng.subscribe(on)
    state = eng.run()
    ends = [e for e in seen if isinstance(e, ev.TrialEnded)]
    emitted = sum(e.n for e in seen if isinstance(e, ev.SamplesAcquired))
    return state, ends, emitted, writer, info


def _motor_off(devices):
    assert not devices.drive.enabled
    assert wait_for(lambda: devices.node.applied_torque_nm == 0.0, timeout=2.0)
    assert devices.node.target_torque_permille == 0


def test_disk_filled_mid_trial(devices, rig_config, short_protocol, tiny_disk, tmp_path):
    def fill(_writer):  # another program fills the disk
        free = shutil.disk_usage(tiny_disk).free
        with open(tiny_disk / "filler", "wb") as f:
            f.write(b"\0" * (free - 1_000_000))

    def run(rig, _where):
        for leftover in tiny_disk.iterdir():  # a starved attempt's file and filler
            leftover.unlink()
        loop = rig.device_loop()
        path = tiny_disk / "S02.h5"
        state, ends, emitted, _writer, _ = _session(loop, short_protocol, path, fill)
        return state, ends, emitted, path, loop

    with on_fresh_rigs(devices, rig_config, tmp_path, run) as (result, rig):
        state, (end,), emitted, path, loop = result
        assert state is State.IDLE and end.status == "aborted"
        assert "session writer failed" in end.reason and "disk full" in end.reason
        assert "below the writer's reserve" in end.reason
        _motor_off(rig)
        # The loop stopped at the block the writer refused, and the file holds every sample,
        # that block's too (the writer failed on it, before the subscribers after it saw it).
        (r,) = SessionFile(path).records()
        assert r.status == "aborted" and "disk full" in r.abort_reason
        assert r.n_samples == loop.trial_stats()["samples"] == emitted + 50 >= 1500


def _runner(protocol, inject):
    """``_session`` as ``on_fresh_rigs`` runs it (again on a fresh rig while a host starved of
    the CPU ended the trial before the fault): its result, the file's path and the loop."""

    def run(rig, where):
        loop = rig.device_loop()
        path = where / "S02.h5"
        state, ends, *rest = _session(loop, protocol, path, lambda w: inject(w, path))
        return (state, ends, *rest, path, loop)

    return run


def test_io_error_mid_trial(devices, rig_config, short_protocol, tmp_path):
    def break_disk(writer, _path):
        def write_out():
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        writer._write_out = write_out
        return {"written": writer._written}

    run = _runner(short_protocol, break_disk)
    with on_fresh_rigs(devices, rig_config, tmp_path, run) as (result, rig):
        state, (end,), emitted, writer, info, path, loop = result
        assert end.status == "aborted" and "No space left on device" in end.reason
        assert writer.failure is not None
        _motor_off(rig)
        assert loop.trial_stats()["samples"] == emitted + 50  # nothing after the failing block
        (r,) = SessionFile(path).records()  # readable
        assert r.status == "aborted" and "No space left on device" in r.abort_reason
        # every sample written before the failure (the writer writes every 0.5 s)
        assert r.n_samples >= info["written"] >= 1000
        assert r.n_samples <= emitted
        # The samples the file did not take (the buffer and the failing block) are in the
        # unsaved-samples file next to it, named in the reason: together, every sample the loop
        # took, contiguous, with the values the loop gave.
        samples = loop.trial_stats()["samples"]
        assert writer.unsaved_file == unsaved_path(path, end.key)
        assert str(writer.unsaved_file) in end.reason
        first, unsaved = load_unsaved(writer.unsaved_file)
        assert first == r.n_samples and first + len(unsaved["time_s"]) == samples
        t = np.concatenate([r.time_s, unsaved["time_s"]])
        np.testing.assert_array_equal(t, np.arange(samples) / 1000.0)
        assert np.all(np.isfinite(unsaved["wheel_angle_rad"]))


def test_session_file_removed_mid_trial(devices, rig_config, short_protocol, tmp_path):
    run = _runner(short_protocol, lambda _w, path: path.unlink())
    with on_fresh_rigs(devices, rig_config, tmp_path, run) as (result, rig):
        state, (end,), emitted, writer, _, path, loop = result
        assert end.status == "aborted" and "removed or replaced" in end.reason
        assert not path.exists()
        _motor_off(rig)
        assert loop.trial_stats()["samples"] == emitted + 50  # stopped at the refused block


def test_writer_failure_stops_the_loop_process(lenient_rig, short_protocol, tmp_path):
    """The loop in its own process must not go on applying the perturbation (it did, for the
    rest of the trial) when the engine lets go of the trial; the samples it took meanwhile are
    kept (the unsaved-samples file: the session file takes no more)."""
    loop = ProcessLoop(str(lenient_rig), 2)
    try:

        def break_disk(writer):
            def write_out():
                raise OSError(errno.EIO, os.strerror(errno.EIO))

            writer._write_out = write_out

        path = tmp_path / "S02.h5"
        state, (end,), emitted, writer, info = _session(loop, short_protocol, path, break_disk)
        assert end.status == "aborted" and "Input/output error" in end.reason
        assert loop.status["drive_enabled"] is False
        samples = loop.trial_stats()["samples"]
        # Ended soon after the failure, not at the trial's end; the blocks the loop took
        # before it stopped were handed on too (take_unhanded), none dropped.
        assert samples < SHORT_TRIAL_SAMPLES
        assert end.n_samples == samples
        assert loop.lab is not None
        assert loop.lab.wait_zero_torque()["applied_torque_nm"] == 0.0
    finally:
        loop.close()
    (r,) = SessionFile(path).records()
    assert r.status == "aborted"
    first, unsaved = load_unsaved(writer.unsaved_file)
    assert first == r.n_samples and first + len(unsaved["time_s"]) == samples
    t = np.concatenate([r.time_s, unsaved["time_s"]])
    np.testing.assert_array_equal(t, np.arange(samples) / 1000.0)


def test_writer_failure_at_the_very_end_of_a_trial(lenient_rig, short_protocol, tmp_path):
    """The writer fails while recording the trial's end: the trial ends aborted with that
    reason (it was the engine left BROKEN), its samples kept, and the session can go on.
    The loop and simulated devices in their own (real-time) processes, as steerlab run has them:
    a host starved by the load would otherwise end the trial first (the drive's watch)."""
    loop = ProcessLoop(str(lenient_rig), 2)
    path = tmp_path / "S02.h5"
    try:
        plan = build_plan(short_protocol, 2)
        n_planned = plan.setup(plan.trials[0]).n_samples
        eng = SessionEngine(plan, loop)
        writer = SessionWriter(path)
        eng.subscribe(writer)
        seen: list = []
        eng.subscribe(seen.append)

        def on(e):  # after the last block was taken: the next write is the trial's end
            if isinstance(e, ev.SamplesAcquired) and e.start + e.n == n_planned:

                def write_out():
                    raise OSError(errno.EIO, os.strerror(errno.EIO))

                writer._write_out = write_out

        eng.subscribe(on)
        state = eng.run()
        assert loop.lab.wait_zero_torque()["applied_torque_nm"] == 0.0
    finally:
        loop.close()
    assert state is State.IDLE, eng.last_error
    ends = [e for e in seen if isinstance(e, ev.TrialEnded)]
    assert ends[-1].status == "aborted" and "session writer failed" in ends[-1].reason
    assert "Input/output error" in ends[-1].reason
    assert eng.status_of(plan.trials[0].trial_index) == "aborted"
    (r,) = SessionFile(path).records()
    assert r.status == "aborted" and "Input/output error" in r.abort_reason
    t = r.time_s
    if writer.unsaved_file is not None:  # else the last block had been written already
        first, unsaved = load_unsaved(writer.unsaved_file)
        assert first == r.n_samples
        t = np.concatenate([t, unsaved["time_s"]])
    np.testing.assert_array_equal(t, np.arange(n_planned) / 1000.0)


def test_free_space_check_names_both_figures(tmp_path):
    free = shutil.disk_usage(tmp_path).free
    assert check_free_space(tmp_path, 1000) == pytest.approx(free, rel=0.01)
    with pytest.raises(DataFileError) as e:
        check_free_space(tmp_path, 10 * free)
    msg = str(e.value)
    import re

    m = re.search(r"(\d+\.\d) MB free, the session needs (\d+\.\d) MB", msg)
    assert str(tmp_path) in msg and m, msg
    assert float(m.group(1)) == pytest.approx(free / 1e6, rel=0.01)
    assert float(m.group(2)) == pytest.approx(10 * free / 1e6, rel=1e-6)


def test_steerlab_run_refuses_a_disk_too_small_for_the_session(tiny_disk):
    p = subprocess.run(
        [sys.executable, "-m", "steerlab", "run", "--subject", "1", "--out", str(tiny_disk)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 2, p.stderr
    assert "not enough free space" in p.stderr and "MB free" in p.stderr
    assert "the session needs 55.1 MB" in p.stderr  # the paper's protocol: 18 trials
    assert not (tiny_disk / "S01.h5").exists()
