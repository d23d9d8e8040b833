"""Round trip, names from data, and damaged files (issue 15, items 3, 4 and 5)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.rig import simulated_rig
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols.datafile import DataFileError, SessionFile, SessionWriter
from steerlab.protocols.engine import SessionEngine
from steerlab.protocols.interchange import InterchangeError, export_study, import_study
from steerlab.protocols.protocol import ProtocolError, parse_protocol
from steerlab.protocols.session import build_plan
from tests.helpers import ROOT, edit, fast_protocol_text


def steerlab(*args, timeout=600):
    return subprocess.run(
        [sys.executable, "-m", "steerlab", *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _session(dirpath: Path, n_trials: int = 3, subject: int = 2) -> Path:
    protocol = parse_protocol(fast_protocol_text(), "fast.toml")
    plan = build_plan(protocol, subject)
    plan = replace(plan, trials=plan.trials[:n_trials])
    rig = simulated_rig(make_population(subject, seed=1)[subject - 1], WorldConfig(fs_hz=200.0))
    eng = SessionEngine(plan, rig.batch_loop())
    dirpath.mkdir(parents=True, exist_ok=True)
    path = dirpath / f"{plan.subject}.h5"
    w = SessionWriter(
        path,
        extra_attributes={"simulated": True, "simulation_seed": 7, "world": {"fs_hz": 200.0}},
    )
    eng.subscribe(w)
    eng.run()
    w.close()
    return path


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    return _session(tmp_path_factory.mktemp("rt") / "sessions")


def _all_attrs(path: Path) -> tuple[dict, dict, dict]:
    with h5py.File(path, "r") as f:
        root = dict(f.attrs)
        trials = {k: dict(g.attrs) for k, g in f["trials"].items()}
        marks = {k: g["marks"][()].tolist() for k, g in f["trials"].items()}
    return root, trials, marks


def _equal(a, b) -> bool:
    if isinstance(a, np.ndarray | list) or isinstance(b, np.ndarray | list):
        return np.array_equal(np.asarray(a), np.asarray(b))
    return a == b


def test_export_then_import_gives_back_every_attribute(session, tmp_path):
    export_study(session.parent, tmp_path / "csv")
    (back,) = import_study(tmp_path / "csv", tmp_path / "back")
    root0, trials0, marks0 = _all_attrs(session)
    root1, trials1, marks1 = _all_attrs(back)
    # Session level: protocol, Latin-square row, simulated flag, ... every one of them.
    for k in ("protocol_toml", "latin_square_row", "simulated", "condition_order"):
        assert k in root0
    lost = {k for k in root0 if k not in root1 or not _equal(root0[k], root1[k])}
    assert not lost, {k: (root0[k], root1.get(k)) for k in lost}
    # Trial level, group by group under the same names.
    assert sorted(trials0) == sorted(trials1)
    for key, a0 in trials0.items():
        a1 = trials1[key]
        lost = {k for k in a0 if k not in a1 or not _equal(a0[k], a1[k])}
        assert not lost, (key, {k: (a0[k], a1.get(k)) for k in lost})
        assert marks0[key] == marks1[key]
    for r0, r1 in zip(SessionFile(session).records(), SessionFile(back).records(), strict=True):
        np.testing.assert_array_equal(r0.wheel_angle_rad, r1.wheel_angle_rad)
        assert r0.wheel_angle_rad.dtype == r1.wheel_angle_rad.dtype


def test_export_refuses_a_non_empty_folder_unless_told(session, tmp_path):
    out = tmp_path / "csv"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    r = steerlab("export", session.parent, "--out", out)
    assert r.returncode == 2 and "not empty" in r.stderr and "--overwrite" in r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]
    r = steerlab("export", session.parent, "--out", out, "--overwrite")
    assert r.returncode == 0, r.stderr
    assert len(list(out.glob("*.csv"))) == 3 and not (out / "mine.txt").exists()
    # An empty folder is fine without --overwrite.
    (tmp_path / "empty").mkdir()
    assert steerlab("export", session.parent, "--out", tmp_path / "empty").returncode == 0


# -- names from data are data ------------------------------------------------------------------
def _exported(session: Path, tmp_path: Path) -> Path:
    csv = tmp_path / "csv"
    export_study(session.parent, csv)
    return csv


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("subject", "../../../x", r"field 'subject': '../../../x' is not a safe name"),
        ("subject", "S01\x00", r"field 'subject': .* is not a safe name"),
        ("condition", "BT/8", r"field 'condition': 'BT/8' is not a safe name"),
        ("condition", "..", r"field 'condition': '..' is not a safe name"),
        ("subject", "", r"field 'subject': '' is not a safe name"),
    ],
)
def test_names_from_imported_data_are_checked(session, tmp_path, field, value, message):
    csv = _exported(session, tmp_path)
    for j in csv.glob("*.json"):
        meta = json.loads(j.read_text())
        meta[field] = value
        j.write_text(json.dumps(meta))
    out = tmp_path / "a" / "b" / "out"
    r = steerlab("import", csv, "--out", out)
    assert r.returncode == 2 and ".json" in r.stderr, r.stderr
    import re

    assert re.search(message, r.stderr), r.stderr
    assert not (tmp_path / "a").exists() and not (tmp_path / "x.h5").exists()


def test_the_protocol_and_the_gui_check_names(tmp_path, fast_protocol):
    text = fast_protocol_text()
    for bad in ("BT/8", "..", "B T", "BT8\\u0000"):
        with pytest.raises(ProtocolError, match=r"\[\[conditions\]\] #4.*name.*not a safe name"):
            parse_protocol(edit(text, 'name = "BT8"', f'name = "{bad}"'), "p.toml")
    from steerlab.app.gui.controller import ControlError, SessionController

    ctl = SessionController(fast_protocol, tmp_path)
    plan = build_plan(fast_protocol, 1, subject="../x")
    with pytest.raises(ControlError, match="not a safe name"):
        ctl._open(plan, tmp_path / "../x.h5", None)


def test_nothing_is_written_through_a_link(session, tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "S02.h5").write_text("not yours")
    # import: a link where a session file goes is refused even with --overwrite.
    csv = _exported(session, tmp_path)
    out = tmp_path / "imported"
    out.mkdir()
    os.symlink(outside / "S02.h5", out / "S02.h5")
    for extra in ((), ("--overwrite",)):
        r = steerlab("import", csv, "--out", out, *extra)
        assert r.returncode == 2 and "S02.h5" in r.stderr, r.stderr
    assert (outside / "S02.h5").read_text() == "not yours"
    # export: a link in --out is never written through; --overwrite replaces the link itself.
    ex = tmp_path / "exported"
    ex.mkdir()
    name = sorted(csv.glob("*.csv"))[0].name
    os.symlink(outside / "S02.h5", ex / name)
    r = steerlab("export", session.parent, "--out", ex)
    assert r.returncode == 2
    r = steerlab("export", session.parent, "--out", ex, "--overwrite")
    assert r.returncode == 0, r.stderr
    assert (outside / "S02.h5").read_text() == "not yours"
    assert not (ex / name).is_symlink() and (ex / name).read_text().startswith("time_s,")


# -- damage is detected, quickly ---------------------------------------------------------------
def _chunk(path: Path, key: str, channel: str) -> tuple[int, int]:
    with h5py.File(path, "r") as f:
        info = f["trials"][key][channel].id.get_chunk_info(0)
        return info.byte_offset, info.size


def test_every_dataset_is_checksummed(session):
    with h5py.File(session, "r") as f:
        for g in f["trials"].values():
            for name, d in g.items():
                assert d.fletcher32, name


def test_truncated_file_is_an_error_within_seconds(session, tmp_path):
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "S02.h5").write_bytes(session.read_bytes()[:2048])
    for cmd in ("report", "export", "diagnose"):
        t0 = time.monotonic()
        r = steerlab(cmd, cut, "--out", tmp_path / f"o-{cmd}", timeout=60)
        took = time.monotonic() - t0
        assert r.returncode == 2, (cmd, r.stderr)
        assert str(cut / "S02.h5") in r.stderr and "truncated" in r.stderr, r.stderr
        assert took < 10, (cmd, took)
        assert not (tmp_path / f"o-{cmd}").exists() or not any((tmp_path / f"o-{cmd}").iterdir())


def test_damaged_chunk_skips_that_trial_and_keeps_the_others(session, tmp_path):
    bad = tmp_path / "bad" / "S02.h5"
    bad.parent.mkdir()
    bad.write_bytes(session.read_bytes())
    key = sorted(SessionFile(bad).trial_keys)[1]
    off, size = _chunk(bad, key, "driver_torque_Nm")
    with open(bad, "r+b") as fh:  # overwrite raw data: a few bytes in the middle of a chunk
        fh.seek(off + size // 2)
        fh.write(b"\x00\x01\x02\x03\x04\x05\x06\x07")
    # Before: read without complaint. Now: that trial is damaged, the others are intact.
    recs = SessionFile(bad).records()
    status = {r.source.rsplit("/", 1)[-1]: r for r in recs}
    assert status[key].status == "damaged" and "checksum" in status[key].abort_reason
    good = [r for k, r in status.items() if k != key]
    assert good and all(r.status == "complete" and r.n_samples == 9600 for r in good)
    # export leaves it out, saying so; the analysis lists it as skipped with the reason.
    r = steerlab("export", bad.parent, "--out", tmp_path / "csv")
    assert r.returncode == 0, r.stderr
    assert f"skipped a damaged trial: {bad}:/trials/{key}" in r.stderr
    assert len(list((tmp_path / "csv").glob("*.csv"))) == len(good)
    from steerlab.analysis.study import _skip_reason

    assert "checksum" in _skip_reason(status[key])


def test_damaged_metadata_names_the_file(session, tmp_path):
    bad = tmp_path / "meta" / "S02.h5"
    bad.parent.mkdir()
    raw = bytearray(session.read_bytes())
    raw[60:400] = bytes(340)  # the root group's object header
    bad.write_bytes(bytes(raw))
    t0 = time.monotonic()
    with pytest.raises(DataFileError, match=str(bad)):
        SessionFile(bad).records()
    assert time.monotonic() - t0 < 5


def test_import_leaves_nothing_when_a_file_is_bad(session, tmp_path):
    csv = _exported(session, tmp_path)
    last = sorted(csv.glob("*.json"))[-1]
    meta = json.loads(last.read_text())
    meta["status"] = "bogus"
    last.write_text(json.dumps(meta))
    with pytest.raises(InterchangeError, match=r"field 'status' must be one of"):
        import_study(csv, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_blind_export_leaves_out_only_what_the_simulation_knows(session, tmp_path):
    export_study(session.parent, tmp_path / "csv", blind=True)
    text = "".join(p.read_text() for p in (tmp_path / "csv").glob("*.json"))
    assert '"world"' not in text and '"simulated_subject"' not in text
    (back,) = import_study(tmp_path / "csv", tmp_path / "back")
    root0, _, _ = _all_attrs(session)
    root1, _, _ = _all_attrs(back)
    assert {"world", "simulated", "simulation_seed"} & set(root1) == set()
    kept = {k for k in root0 if k not in ("world", "simulated", "simulation_seed")}
    assert all(_equal(root0[k], root1[k]) for k in kept)
