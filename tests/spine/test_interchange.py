"""Trial interchange format: exact round trip, data from elsewhere, and precise errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from steerlab.app.simulate import simulate_study
from steerlab.protocols.datafile import SessionFile
from steerlab.protocols.interchange import InterchangeError, export_study, import_study
from tests.analysis.synthetic_trials import find_example

# The shared interchange example: $STEERLAB_EXAMPLES, the repository's docs/examples, or the
# team's shared folder beside the repository (tests/analysis/synthetic_trials.find_example).
_FOUND = find_example()
EXAMPLE = Path(_FOUND).parent if _FOUND else Path("/nonexistent")
HEADER = "time_s,perturbation_torque_Nm,driver_torque_Nm,wheel_angle_rad,grip_force_N"


@pytest.fixture(scope="module")
def small_study(tmp_path_factory):
    from tests.helpers import fast_protocol_text

    d = tmp_path_factory.mktemp("study")
    proto = d / "fast.toml"
    proto.write_text(fast_protocol_text())
    simulate_study(2, d / "sessions", seed=9, protocol_path=str(proto), jobs=1)
    return d / "sessions"


def test_export_then_import_gives_back_the_same_data(small_study, tmp_path):
    csv_dir = tmp_path / "csv"
    paths = export_study(small_study, csv_dir)
    assert len(paths) == 36
    first = paths[0].read_text().splitlines()[0]
    assert first.startswith(HEADER)
    meta = json.loads(paths[0].with_suffix(".json").read_text())
    for k in ("subject", "condition", "repetition", "fs_hz", "familiarization", "trial_index"):
        assert k in meta
    out = tmp_path / "back"
    import_study(csv_dir, out)
    for p in sorted(small_study.glob("*.h5")):
        a, b = SessionFile(p).records(), SessionFile(out / p.name).records()
        assert len(a) == len(b) == 18
        for x, y in zip(a, b, strict=True):
            assert (x.subject, x.condition, x.repetition, x.familiarization, x.trial_index) == (
                y.subject,
                y.condition,
                y.repetition,
                y.familiarization,
                y.trial_index,
            )
            assert x.fs_hz == y.fs_hz and x.measured_start == y.measured_start
            for c in (
                "time_s",
                "perturbation_torque_Nm",
                "driver_torque_Nm",
                "wheel_angle_rad",
                "grip_force_N",
            ):
                np.testing.assert_array_equal(getattr(x, c), getattr(y, c), err_msg=c)
            assert x.extra.keys() == y.extra.keys()
            for c in x.extra:
                np.testing.assert_array_equal(x.extra[c], y.extra[c], err_msg=c)
            assert x.design.to_json() == y.design.to_json()


@pytest.mark.skipif(
    _FOUND is None, reason="shared interchange example not found (set STEERLAB_EXAMPLES)"
)
def test_imports_the_shared_example_as_it_is(tmp_path):
    (path,) = import_study(EXAMPLE, tmp_path / "s")
    (rec,) = SessionFile(path).records()
    assert (rec.subject, rec.condition, rec.repetition, rec.fs_hz) == ("S01", "BT12", 1, 250.0)
    assert rec.trial_index == 2 and not rec.familiarization
    assert rec.n_samples == 13000 and rec.design is None and rec.measured_start is None
    raw = np.loadtxt(EXAMPLE / "example_BT12_rep1.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(rec.driver_torque_Nm, raw[:, 2])


def _write(dirpath: Path, csv_text: str, meta: dict | None = None, name: str = "t") -> Path:
    dirpath.mkdir(parents=True, exist_ok=True)
    (dirpath / f"{name}.csv").write_text(csv_text)
    m = {"subject": "S01", "condition": "BT12", "repetition": 1, "fs_hz": 100.0}
    if meta is not None:
        m = {**m, **meta}
    (dirpath / f"{name}.json").write_text(json.dumps(m))
    return dirpath


def _rows(n=300, fs=100.0, t0=3.21):
    t = t0 + np.arange(n) / fs
    return "\n".join(f"{x:.6f},{np.sin(x)},{np.cos(x)},{0.01 * x},{50 + x}" for x in t)


@pytest.mark.parametrize(
    "csv_text, meta, message",
    [
        (
            "time_s,driver_torque_Nm,wheel_angle_rad,grip_force_N\n1,2,3,4\n",
            None,
            r"row 1 \(header\): missing column\(s\) \['perturbation_torque_Nm'\]",
        ),
        (
            HEADER + "\n" + _rows().replace("\n", "\nbad\n", 1),
            None,
            r"row 3: 1 cells, the header has 5",
        ),
        (
            HEADER + "\n" + _rows().replace(",", ",x", 1),
            None,
            r"row 2, column 'perturbation_torque_Nm': not a number",
        ),
        (HEADER + "\n" + _rows(), {"fs_hz": 50.0}, r"fs_hz.*50.*≥ 100"),
        (HEADER + "\n" + _rows(), {"repetition": "one"}, r"'repetition'"),
        (HEADER + "\n" + _rows(), {"familiarization": "no"}, r"'familiarization'"),
        (HEADER + "\n" + _rows(fs=120.0), None, r"row 3, column 'time_s': step"),
        (HEADER + "\n" + _rows() + "\n1e9,nan,1,2,3", None, r"column 'time_s'|not finite"),
    ],
)
def test_bad_input_names_file_row_and_column_and_writes_nothing(tmp_path, csv_text, meta, message):
    src = _write(tmp_path / "in", csv_text, meta)
    out = tmp_path / "out"
    with pytest.raises(InterchangeError, match=message) as e:
        import_study(src, out)
    assert "t.csv" in str(e.value) or "t.json" in str(e.value)
    assert not out.exists()


def test_missing_metadata_field_and_missing_json(tmp_path):
    src = _write(tmp_path / "a", HEADER + "\n" + _rows())
    m = json.loads((src / "t.json").read_text())
    del m["condition"]
    (src / "t.json").write_text(json.dumps(m))
    with pytest.raises(InterchangeError, match=r"t\.json: missing field\(s\) \['condition'\]"):
        import_study(src, tmp_path / "o")
    (src / "t.json").unlink()
    with pytest.raises(InterchangeError, match="no metadata file t.json"):
        import_study(src, tmp_path / "o")


def test_one_bad_file_among_good_ones_writes_nothing(small_study, tmp_path):
    csv_dir = tmp_path / "csv"
    export_study(small_study, csv_dir)
    victim = sorted(csv_dir.glob("S02_*.csv"))[5]
    lines = victim.read_text().splitlines()
    lines[100] = lines[100].split(",", 1)[0] + ",oops" + "," * (lines[0].count(",") - 1)
    victim.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    with pytest.raises(
        InterchangeError, match=rf"{victim.name}: row 101, column 'perturbation_torque_Nm'"
    ):
        import_study(csv_dir, out)
    assert not out.exists() or not list(out.iterdir())


def test_accepts_other_rates_and_any_start_and_refuses_to_overwrite(tmp_path):
    src = _write(
        tmp_path / "in",
        HEADER
        + ",extra_col\n"
        + "\n".join(r + ",1" for r in _rows(n=500, fs=512.0, t0=17.3).splitlines()),
        {"fs_hz": 512.0},
    )
    (p,) = import_study(src, tmp_path / "out")
    (rec,) = SessionFile(p).records()
    assert rec.fs_hz == 512.0 and rec.time_s[0] == pytest.approx(17.3) and "extra_col" in rec.extra
    with pytest.raises(InterchangeError, match="exist already"):
        import_study(src, tmp_path / "out")
    shutil.rmtree(src)
