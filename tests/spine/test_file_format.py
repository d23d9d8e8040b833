"""Session file format: lossless compression, counts channels, native attributes, old files.

The values the writer stores are checked against the engine's own events (an independent
subscriber keeps a copy of every block), the layout against h5py's view of the filters, and the
old format against a file written by the writer before this format (tests/data).
"""

from __future__ import annotations

import itertools
import json
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from steerlab.app.simulate import sensor_quanta
from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.rig import simulated_rig
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols import events as ev
from steerlab.protocols.datafile import (
    COUNTS_ASIDE,
    SessionFile,
    SessionWriter,
    native_attr,
    read_channel,
)
from steerlab.protocols.engine import SessionEngine
from steerlab.protocols.protocol import parse_protocol
from steerlab.protocols.records import CORE_CHANNELS
from steerlab.protocols.session import build_plan

DATA = Path(__file__).parent.parent / "data"
OLD_FILE = DATA / "session_format_v1.h5"  # written by the writer of commit 903afbb


def _record(fast_protocol, path: Path, *, clock=None, block_s: float = 1.0, trials: int = 2):
    """Run ``trials`` trials into ``path``; return every block the engine sent, per trial."""
    plan = build_plan(fast_protocol, 3)
    plan = replace(plan, trials=plan.trials[:trials])
    world = WorldConfig(fs_hz=fast_protocol.loop_rate_hz)
    rig = simulated_rig(make_population(3, seed=5)[2], world)
    eng = SessionEngine(plan, rig.batch_loop(block_s=block_s))
    kw = {"clock": clock} if clock is not None else {}
    writer = SessionWriter(
        path, quanta=sensor_quanta(world), extra_attributes={"simulated": True}, **kw
    )
    sent: dict[str, list[dict[str, np.ndarray]]] = {}
    eng.subscribe(writer)
    eng.subscribe(
        lambda e: (
            sent.setdefault(e.key, []).append(dict(e.channels))
            if isinstance(e, ev.SamplesAcquired)
            else None
        )
    )
    eng.run()
    writer.close()
    return {k: {c: np.concatenate([b[c] for b in v]) for c in v[0]} for k, v in sent.items()}


def _filters(d: h5py.Dataset) -> list[int]:
    pl = d.id.get_create_plist()
    return [pl.get_filter(i)[0] for i in range(pl.get_nfilters())]


def test_compressed_losslessly_with_counts_and_checksums(fast_protocol, tmp_path):
    path = tmp_path / "S03.h5"
    sent = _record(fast_protocol, path)
    q = sensor_quanta(WorldConfig())
    with h5py.File(path, "r", locking=False) as f:
        for key, channels in sent.items():
            g = f["trials"][key]
            for name, values in channels.items():
                d = g[name]
                # shuffle, then deflate, then Fletcher-32 over the stored (compressed) bytes
                assert _filters(d) == [
                    h5py.h5z.FILTER_SHUFFLE,
                    h5py.h5z.FILTER_DEFLATE,
                    h5py.h5z.FILTER_FLETCHER32,
                ], name
                if name in q:
                    assert d.dtype == np.int32 and d.attrs["scale_factor"] == q[name], name
                    # bit for bit the values the sensor model gave (float64)
                    np.testing.assert_array_equal(read_channel(d), values, err_msg=name)
                elif name in ("time_s", "host_time_s"):  # float64: a time line
                    assert d.dtype == np.float64, name
                    np.testing.assert_array_equal(d[()], values)
                else:
                    assert d.dtype == np.float32, name
                    np.testing.assert_array_equal(d[()], values.astype(np.float32), err_msg=name)
    # The reader gives the values in their units.
    recs = {r.source.rsplit("/", 1)[-1]: r for r in SessionFile(path).records()}
    for key, channels in sent.items():
        np.testing.assert_array_equal(recs[key].wheel_angle_rad, channels["wheel_angle_rad"])
        np.testing.assert_array_equal(recs[key].driver_torque_Nm, channels["driver_torque_Nm"])
    raw = sum(v.nbytes // (2 if v.dtype == np.float64 else 1) for c in sent.values()
                  for k, v in c.items() if k != "time_s")  # fmt: skip
    # Smaller than the float32 samples alone (the goal, ≤ 300 MB for the demo, is a benchmark).
    assert path.stat().st_size < raw


def test_attributes_are_native_types(fast_protocol, tmp_path):
    path = tmp_path / "S03.h5"
    _record(fast_protocol, path, trials=1)
    seen = []

    def check(obj):
        for k in obj.attrs:
            tid = obj.attrs.get_id(k).get_type()
            assert tid.get_class() != h5py.h5t.ENUM, (obj.name, k)
            v = obj.attrs[k]
            if isinstance(v, str) and v.startswith(("[", "{")):
                # JSON only for a structure: a mapping, or a list holding one
                doc = json.loads(v)
                assert isinstance(doc, dict) or any(isinstance(x, dict) for x in doc), (k, v)
            seen.append(k)

    with h5py.File(path, "r", locking=False) as f:
        check(f)
        f.visit(lambda name: check(f[name]))
        assert f.attrs["simulated"] == 1 and f.attrs["simulated"].dtype == np.uint8
        order = f.attrs["condition_order"]
        assert order.dtype.kind == "O" and len(order) == 6  # variable-length strings
    assert {"familiarization", "simulated", "condition_order", "units"} <= set(seen)


def test_native_attr_conversions():
    assert native_attr(True) == 1 and native_attr(True).dtype == np.uint8
    assert native_attr(np.bool_(False)) == 0
    assert list(native_attr(["RT", "PT"])) == ["RT", "PT"]
    np.testing.assert_array_equal(native_attr((1.5, 2)), [1.5, 2.0])
    assert json.loads(native_attr({"a": [1]})) == {"a": [1]}
    assert json.loads(native_attr([{"a": 1}])) == [{"a": 1}]
    assert native_attr(np.array(["x", "y"], dtype=object)).dtype == h5py.string_dtype()
    assert native_attr("text") == "text" and native_attr(3) == 3


def test_a_file_of_the_previous_format_reads_as_before():
    with h5py.File(
        OLD_FILE, "r", locking=False
    ) as f:  # it is the old format: enum booleans, JSON, float32
        g = f["trials"]["02_BT18_rep1_a1"]
        assert g.attrs.get_id("familiarization").get_type().get_class() == h5py.h5t.ENUM
        assert isinstance(f.attrs["condition_order"], str)
        assert g["wheel_angle_rad"].dtype == np.float32 and g["wheel_angle_rad"].compression is None
        stored = g["wheel_angle_rad"][()]
    sf = SessionFile(OLD_FILE)
    assert sf.attrs["simulated"] is True
    assert json.loads(sf.attrs["condition_order"])[0] == "BT18"
    fam, rep = sf.records()
    assert fam.familiarization is True and rep.familiarization is False
    assert rep.status == "complete" and rep.n_samples == len(stored) == 1800
    np.testing.assert_array_equal(rep.wheel_angle_rad, stored.astype(float))
    assert rep.design is not None and rep.attrs["marks"] == []


def test_resuming_an_old_file_appends_in_the_new_format(fast_protocol, tmp_path):
    path = tmp_path / "old.h5"
    shutil.copy(OLD_FILE, path)
    with h5py.File(path, "a", locking=False) as f:
        f.attrs["protocol_toml"] = fast_protocol.source_text  # resume checks the protocol
    # The writer opens it for append (with the 1.10 format bounds) and adds a trial.
    w = SessionWriter(path, quanta={"wheel_angle_rad": 1e-3})
    w(ev.TrialStarted("03_X_rep1_a1", 3, 1, "X", {"subject": "S02"}, 100))
    w(ev.SamplesAcquired("03_X_rep1_a1", 0, {"time_s": np.arange(100) / 100.0,
                                            "wheel_angle_rad": np.arange(100) * 1e-3}))  # fmt: skip
    w(ev.TrialEnded("03_X_rep1_a1", 3, "complete", None, 100))
    w.close()
    with h5py.File(path, "r", locking=False) as f:
        assert f["trials"]["03_X_rep1_a1"]["wheel_angle_rad"].dtype == np.int32
        assert f["trials"]["02_BT18_rep1_a1"]["wheel_angle_rad"].dtype == np.float32


def test_a_block_off_the_counts_grid_turns_the_channel_to_float64(tmp_path):
    path = tmp_path / "S01.h5"
    w = SessionWriter(path, quanta={"wheel_angle_rad": 0.5}, chunk_samples=64)
    key = "01_X_rep1_a1"
    w(ev.SessionStarted("S01", {"subject": "S01"}, "", "", 1))
    attrs = {"subject": "S01", "condition": "X", "repetition": 1, "fs_hz": 100.0}
    w(ev.TrialStarted(key, 1, 1, "X", attrs, 300))
    sent = []
    for i, off in enumerate((0.0, 0.0, 0.25, 0.0)):  # the third block is not on the grid
        v = np.arange(i * 70, i * 70 + 70) * 0.5 + off
        sent.append(v)
        block = {c: np.zeros(70) for c in CORE_CHANNELS} | {"wheel_angle_rad": v}
        w(ev.SamplesAcquired(key, i * 70, block))
    w(ev.TrialEnded(key, 1, "complete", None, 280))
    w.close()
    with h5py.File(path, "r", locking=False) as f:
        g = f["trials"][key]
        assert (
            g["wheel_angle_rad"].dtype == np.float64
            and "scale_factor" not in g["wheel_angle_rad"].attrs
        )
        assert not any(n.endswith(COUNTS_ASIDE) for n in g)
        np.testing.assert_array_equal(g["wheel_angle_rad"][()], np.concatenate(sent))
    # A writer killed while rewriting leaves the counts aside: the reader takes them.
    with h5py.File(path, "a", locking=False) as f:
        g = f["trials"][key]
        del g["wheel_angle_rad"]
        d = g.create_dataset("wheel_angle_rad" + COUNTS_ASIDE, data=np.arange(280, dtype="i4"))
        d.attrs["scale_factor"] = 0.5
    (rec,) = SessionFile(path).records()
    assert rec.status == "complete", rec.abort_reason
    np.testing.assert_array_equal(rec.wheel_angle_rad, np.arange(280) * 0.5)


def test_paced_writing_uses_small_chunks_and_stays_small(fast_protocol, tmp_path):
    """Paced like a real-time run at 1 kHz (a clock that advances one block per block, flushes
    every 0.5 s): each flush rewrites the last chunk part-full, so the chunks are small; the
    file stays smaller than the float32 samples alone."""
    ticks = itertools.count()
    clock = lambda: next(ticks) * 0.05  # noqa: E731
    path = tmp_path / "S03.h5"
    protocol = parse_protocol(
        fast_protocol.source_text.replace("loop_rate_hz = 200.0", "loop_rate_hz = 1000.0"), "1k"
    )
    assert protocol.loop_rate_hz == 1000.0
    sent = _record(protocol, path, clock=clock, block_s=0.05, trials=1)
    ((key, channels),) = sent.items()
    n = len(channels["time_s"])
    with h5py.File(path, "r", locking=False) as f:
        d = f["trials"][key]["driver_torque_Nm"]
        assert d.chunks[0] == 256  # 0.5 s at 1 kHz is 500 samples
        np.testing.assert_array_equal(read_channel(d), channels["driver_torque_Nm"])
    assert path.stat().st_size < n * (8 + 4 * (len(channels) - 1))


R_SCRIPT = """
library(hdf5r)
f <- H5File$new(commandArgs(TRUE)[1], mode = "r")
g <- f[[paste0("trials/", commandArgs(TRUE)[2])]]
d <- g[["wheel_angle_rad"]]
x <- d$read() * h5attr(d, "scale_factor")
cat(sprintf("%.17g", x[1:50]), h5attr(g, "familiarization"), h5attr(f, "condition_order"),
    sep = "\\n")
"""


@pytest.mark.skipif(
    shutil.which("Rscript") is None,
    reason="needs R with hdf5r (Debian: apt-get install r-base-core r-cran-hdf5r)",
)
def test_r_reads_a_trial(fast_protocol, tmp_path):
    """An independent reader (R's hdf5r on the system's HDF5 1.10) reads the file as written."""
    path = tmp_path / "S03.h5"
    key = sorted(_record(fast_protocol, path))[1]
    script = tmp_path / "read.R"
    script.write_text(R_SCRIPT)
    r = subprocess.run(["Rscript", str(script), str(path), key], capture_output=True, text=True)
    if "there is no package called" in r.stderr:
        pytest.skip("R has no hdf5r (apt-get install r-cran-hdf5r)")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.split()
    sf = SessionFile(path)
    (rec,) = [x for x in sf.records() if x.source.endswith("/" + key)]
    np.testing.assert_array_equal(np.array(lines[:50], dtype=float), rec.wheel_angle_rad[:50])
    assert lines[50] == "0"  # a measured repetition: familiarization 0
    assert lines[51:] == list(sf.attrs["condition_order"])
