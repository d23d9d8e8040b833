"""Session files: layout, crash safety (SIGKILL mid-trial), concurrent readers, damaged files."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from dataclasses import replace

import h5py
import numpy as np
import pytest

from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.rig import simulated_rig
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols.datafile import DataFileError, SessionFile, SessionWriter
from steerlab.protocols.engine import SessionEngine
from steerlab.protocols.h5status import status_flags
from steerlab.protocols.perturbation import PerturbationDesign
from steerlab.protocols.session import build_plan
from tests.helpers import ROOT


def _cli(*args, **kw):
    return subprocess.Popen(
        [sys.executable, "-m", "steerlab", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def test_layout_and_attributes(fast_protocol, tmp_path):
    plan = build_plan(fast_protocol, 4)
    plan = replace(plan, trials=plan.trials[:3])
    rig = simulated_rig(make_population(4, seed=1)[3], WorldConfig(fs_hz=200.0))
    eng = SessionEngine(plan, rig.batch_loop())
    eng.subscribe(SessionWriter(tmp_path / "S04.h5"))
    eng.run()
    with h5py.File(tmp_path / "S04.h5", "r") as f:
        a = f.attrs
        assert a["format"] == "steerlab-session" and a["subject"] == "S04"
        assert a["latin_square_row"] == 3
        # Native types (docs/data-format.md): a string array, booleans as uint8 0/1.
        assert list(a["condition_order"]) == list(plan.condition_order)
        assert "driver_torque_Nm: the torque the wheel exerts on the hands" in a["sign_conventions"]
        assert a["protocol_toml"] == fast_protocol.source_text
        assert a["software_version"]
        keys = sorted(f["trials"])
        assert keys == ["01_BT8_fam_a1", "02_BT8_rep1_a1", "03_BT8_rep2_a1"]
        g = f["trials"]["02_BT8_rep1_a1"]
        assert g.attrs["condition"] == "BT8" and g.attrs["repetition"] == 1
        assert g.attrs["familiarization"] == 0 and g.attrs["familiarization"].dtype == np.uint8
        assert g.attrs["trial_index"] == 2
        assert g.attrs["fs_hz"] == 200.0 and g.attrs["status"] == "complete"
        assert g.attrs["measured_start"] == 400 and g.attrs["measured_stop"] == 400 + 9000
        assert json.loads(g.attrs["units"])["wheel_angle_rad"] == "rad"
        assert g["wheel_angle_rad"].attrs["units"] == "rad"
        for c in (
            "time_s",
            "perturbation_torque_Nm",
            "driver_torque_Nm",
            "wheel_angle_rad",
            "wheel_velocity_rad_s",
            "motor_command_Nm",
            "grip_force_N",
            "grip_force_left_N",
            "grip_force_right_N",
        ):
            assert g[c].shape == (9600,), c
        design = PerturbationDesign.from_json(g.attrs["perturbation_design"])
        assert np.array_equal(design.bins, plan.design.bins)
        tot = g["grip_force_N"][()]
        np.testing.assert_allclose(
            tot, g["grip_force_left_N"][()] + g["grip_force_right_N"][()], rtol=1e-6
        )


def test_sigkill_mid_trial_leaves_a_readable_file_then_resume(fast_protocol_file, tmp_path):
    out = tmp_path / "study"
    proc = _cli(
        "simulate",
        "--subjects",
        "1",
        "--out",
        str(out),
        "--realtime",
        "--protocol",
        str(fast_protocol_file),
    )
    path = out / "S01.h5"
    seen = 0
    growth = []  # wall times at which this (other) process saw new samples
    deadline = time.monotonic() + 60
    try:
        # Read the file from this process while the other one writes it (SWMR).
        while time.monotonic() < deadline and seen < 500:
            time.sleep(0.2)
            if not path.exists():
                continue
            try:
                with h5py.File(path, "r", libver="latest", swmr=True, locking=False) as f:
                    for g in f["trials"].values():
                        if "wheel_angle_rad" in g:
                            d = g["wheel_angle_rad"]
                            d.refresh()
                            if d.shape[0] > seen:
                                growth.append(time.monotonic())
                            seen = max(seen, d.shape[0])
            except (OSError, KeyError):
                continue  # the writer is between trial set-up steps
        assert seen >= 500, f"reader saw only {seen} samples"
        # Flushed at least every second of wall time (0.5 s interval + this reader's 0.2 s poll).
        gaps = np.diff(growth)
        assert len(gaps) >= 3 and gaps.max() < 1.0, gaps
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    sf = SessionFile(path)
    (rec,) = sf.records()
    assert rec.status == "incomplete" and rec.trial_index == 1
    # Every sample up to the last flush: at least what the reader saw, evenly spaced from 0.
    assert rec.n_samples >= seen
    np.testing.assert_allclose(np.diff(rec.time_s), 1 / 200.0, rtol=1e-9)
    assert rec.time_s[0] == 0.0 and np.all(np.isfinite(rec.wheel_angle_rad))
    kept = rec.wheel_angle_rad.copy()

    # Without --resume the files are not touched.
    p = _cli(
        "simulate", "--subjects", "1", "--out", str(out), "--protocol", str(fast_protocol_file)
    )
    _, err = p.communicate(timeout=120)
    assert p.returncode == 2 and "--resume" in err and "S01" in err
    # --resume completes the session; the killed attempt stays as it was.
    p = _cli(
        "simulate",
        "--subjects",
        "1",
        "--out",
        str(out),
        "--resume",
        "--protocol",
        str(fast_protocol_file),
    )
    _, err = p.communicate(timeout=300)
    assert p.returncode == 0, err
    sf = SessionFile(path)
    att = sf.attempts()
    assert sorted(att[1]) == [(1, "incomplete"), (2, "complete")]
    assert all(any(s == "complete" for _, s in v) for v in att.values()) and len(att) == 18
    old = [r for r in sf.records() if r.trial_index == 1 and r.attrs["attempt"] == 1][0]
    np.testing.assert_array_equal(old.wheel_angle_rad, kept)
    # Recovered in place (the "open for write" flag cleared, as h5clear -s): no copies, no
    # lock file left behind, and the file closed cleanly.
    assert sorted(p.name for p in out.iterdir()) == ["S01.h5"]
    assert status_flags(path) == 0


def test_truncated_and_foreign_files_give_one_clear_message(tmp_path, fast_protocol):
    plan = build_plan(fast_protocol, 1)
    eng = SessionEngine(
        replace(plan, trials=plan.trials[:1]),
        simulated_rig(make_population(1)[0], WorldConfig(fs_hz=200.0)).batch_loop(),
    )
    good = tmp_path / "S01.h5"
    eng.subscribe(SessionWriter(good))
    eng.run()
    data = good.read_bytes()
    bad = tmp_path / "cut" / "S01.h5"
    bad.parent.mkdir()
    bad.write_bytes(data[: len(data) // 3])
    with pytest.raises(DataFileError, match=str(bad)):
        SessionFile(bad).records()
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["x"] = [1, 2, 3]
    with pytest.raises(DataFileError, match="not a Steerlab session file"):
        SessionFile(foreign)
    junk = tmp_path / "junk.h5"
    junk.write_text("hello")
    with pytest.raises(DataFileError, match="not a readable HDF5 file"):
        SessionFile(junk)
    # The command line says the same in one line, exits 2, and writes nothing.
    p = _cli("export", str(bad.parent), "--out", str(tmp_path / "csv"))
    _, err = p.communicate(timeout=120)
    assert p.returncode == 2
    assert err.count("\n") == 1 and str(bad) in err
    assert not (tmp_path / "csv").exists() or not any((tmp_path / "csv").iterdir())
