"""Every bad input gives exit 2 naming the file and the field or row, writes nothing, and takes
time linear in its size (issue 15, item 6).

Two tables (interchange import, protocol files) of inputs and the message fragments expected,
run through the command line's own entry point; then a property-based fuzz (hypothesis) of the
JSON/CSV import and of the protocol loader: whatever the input, the only outcomes are a clean
result or the reader's own error naming the file.
"""

from __future__ import annotations

import json
import math
import re
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from steerlab.app.cli import main
from steerlab.protocols.datafile import load_study
from steerlab.protocols.interchange import InterchangeError, read_trial
from steerlab.protocols.protocol import ProtocolError, parse_protocol
from tests.helpers import edit, fast_protocol_text

HEADER = "time_s,perturbation_torque_Nm,driver_torque_Nm,wheel_angle_rad,grip_force_N"
# A 3 s period, so that the 3 s trial below holds one whole period (import refuses less).
DESIGN = {
    "period_s": 3.0,
    "bins": [1, 2],
    "amplitudes_Nm": [1.0, 1.0],
    "phases_rad": [0.0, 0.0],
    "band_of_bin": [0, 0],
}
PLAIN = {"subject": "S01", "condition": "RT", "repetition": 1, "fs_hz": 100.0}
META = {**PLAIN, "perturbation_design": DESIGN}


def _rows(n=300, fs=100.0) -> str:
    t = np.arange(n) / fs
    x = np.sin(2 * np.pi * 0.5 * t)
    return "\n".join(
        f"{a!r},{b!r},{b!r},{b!r},{b + 10!r}" for a, b in zip(t.tolist(), x.tolist(), strict=True)
    )


def _trial_dir(tmp_path: Path, csv: bytes | str, meta: dict | bytes | str) -> Path:
    d = tmp_path / "in"
    d.mkdir(exist_ok=True)
    (d / "t.csv").write_bytes(csv.encode() if isinstance(csv, str) else csv)
    raw = json.dumps(meta) if isinstance(meta, dict) else meta
    (d / "t.json").write_bytes(raw.encode() if isinstance(raw, str) else raw)
    return d


def _run(capsys, *argv) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


GOOD_CSV = HEADER + "\n" + _rows() + "\n"
M = META


IMPORT_CASES = [
    # (id, csv, meta, expected fragments in the one-line message)
    ("boundary word", GOOD_CSV, {**M, "boundary_deg": "wide"}, ["t.json", "'boundary_deg'"]),
    ("boundary list", GOOD_CSV, {**M, "boundary_deg": [1]}, ["t.json", "'boundary_deg'"]),
    ("boundary negative", GOOD_CSV, {**M, "boundary_deg": -3}, ["t.json", "'boundary_deg'"]),
    ("json not utf-8", GOOD_CSV, b'{"subject": "S\xff01"}', ["t.json", "not UTF-8"]),
    (
        "csv not utf-8",
        GOOD_CSV.encode().replace(b"0.01,", b"0.0\xfe,", 1),
        M,
        ["t.csv", "row 3", "not UTF-8"],
    ),
    ("NUL in subject", GOOD_CSV, {**M, "subject": "S\x0001"}, ["t.json", "'subject'", "safe"]),
    ("NUL in csv", GOOD_CSV.replace("0.01,", "0.01\x00,", 1), M, ["t.csv", "row 3", "NUL"]),
    ("subject path", GOOD_CSV, {**M, "subject": "../../../x"}, ["t.json", "'subject'"]),
    ("condition slash", GOOD_CSV, {**M, "condition": "BT/8"}, ["t.json", "'condition'"]),
    (
        "measured_start text",
        GOOD_CSV,
        {**M, "measured_start": "abc"},
        ["t.json", "'measured_start'"],
    ),
    (
        "measured reversed",
        GOOD_CSV,
        {**M, "measured_start": 200, "measured_stop": 100},
        ["t.json", "'measured_start'", "before the stop"],
    ),
    (
        "design junk",
        GOOD_CSV,
        {**M, "perturbation_design": {"period_s": "x"}},
        ["t.json", "'perturbation_design'"],
    ),
    (
        "design string",
        GOOD_CSV,
        {**M, "perturbation_design": "junk"},
        ["t.json", "'perturbation_design'"],
    ),
    (
        "design lengths",
        GOOD_CSV,
        {
            **M,
            "perturbation_design": {
                "period_s": 3.0,
                "bins": [1, 2],
                "amplitudes_Nm": [1.0],
                "phases_rad": [0.0, 0.0],
                "band_of_bin": [0, 0],
            },
        },
        ["t.json", "'perturbation_design'", "length"],
    ),
    ("status bogus", GOOD_CSV, {**M, "status": "bogus"}, ["t.json", "'status'", "bogus"]),
    ("two rows", HEADER + "\n0,0,0,0,0\n0.01,0,0,0,0\n", M, ["t.csv", "2 data row"]),
    (
        "float32 overflow",
        GOOD_CSV.replace("\n0.01,", "\n0.01,1e308,0,0,0\n0.01,", 1)
        .replace("0.01,1e308,0,0,0\n0.01,", "0.01,1e308,0,0,0\nX", 1)
        .split("\nX")[0]
        + "\n"
        + "\n".join(GOOD_CSV.splitlines()[3:])
        + "\n",
        {**M, "dtypes": {"perturbation_torque_Nm": "float32"}},
        ["t.csv", "row 3", "'perturbation_torque_Nm'", "float32"],
    ),
    (
        "fs nan text",
        GOOD_CSV,
        '{"subject": "S01", "condition": "RT", "repetition": 1, "fs_hz": NaN}',
        ["t.json", "NaN"],
    ),
    ("fs huge", GOOD_CSV, {**M, "fs_hz": 1e300}, ["t.json", "'fs_hz'"]),
    # Other labs number trials from 0 (accepted); a negative index is not a position.
    ("trial_index negative", GOOD_CSV, {**M, "trial_index": -1}, ["t.json", "'trial_index'"]),
    (
        "sample_timing word",
        GOOD_CSV,
        {**M, "sample_timing": "middle"},
        ["t.json", "'sample_timing'"],
    ),
    ("torque_timing huge", GOOD_CSV, {**M, "torque_timing": 1e9}, ["t.json", "'torque_timing'"]),
    (
        "rendering word",
        GOOD_CSV,
        {**M, "wheel_rendering": "rendered"},
        ["t.json", "'wheel_rendering'"],
    ),
    ("attempt text", GOOD_CSV, {**M, "attempt": "2"}, ["t.json", "'attempt'"]),
    ("repetition huge", GOOD_CSV, {**M, "repetition": 2**70}, ["t.json", "'repetition'"]),
    (
        "attribute NUL",
        GOOD_CSV,
        {**M, "trial_attributes": {"x": "a\x00b"}},
        ["t.json", "'trial_attributes'", "NUL"],
    ),
    (
        "attribute object",
        GOOD_CSV,
        {**M, "session_attributes": {"x": {"y": 1}}},
        ["t.json", "'session_attributes'"],
    ),
    ("marks junk", GOOD_CSV, {**M, "marks": [{"sample": "a"}]}, ["t.json", "'marks'"]),
    ("unbalanced quote", HEADER + '\n"0,0,0,0,0\n', M, ["t.csv"]),
    ("json array", GOOD_CSV, "[1, 2]", ["t.json", "JSON object"]),
    ("deep json", GOOD_CSV, "[" * 100000 + "]" * 100000, ["t.json", "JSON"]),
    # A number is not a subject name: 1 would have become "1.h5" beside "S01.h5".
    ("subject number", GOOD_CSV, {**M, "subject": 1}, ["t.json", "'subject'", '"S01"', "got 1"]),
    ("condition number", GOOD_CSV, {**M, "condition": 12}, ["t.json", "'condition'", "string"]),
    (
        "condition unknown",
        GOOD_CSV,
        {**M, "condition": "BT13"},
        ["t.json", "'condition'", "'BT13'", "did you mean", "BT12", '"condition_declared": true'],
    ),
    (
        "condition_declared text",
        GOOD_CSV,
        {**M, "condition": "BT13", "condition_declared": "yes"},
        ["t.json", "'condition_declared'", "true or false"],
    ),
    (
        "shorter than the paper's period",
        HEADER + "\n" + _rows(800) + "\n",
        PLAIN,
        ["t.csv", "800 data rows at 100 Hz = 8 s", "one perturbation period: 45 s (4500 rows"],
    ),
    (
        "shorter than its design's period",
        GOOD_CSV,
        {**M, "perturbation_design": {**DESIGN, "period_s": 5.0}},
        ["t.csv", "= 3 s", "period: 5 s (500 rows", "'perturbation_design'"],
    ),
]


@pytest.mark.parametrize(
    "csv, meta, fragments", [c[1:] for c in IMPORT_CASES], ids=[c[0] for c in IMPORT_CASES]
)
def test_bad_import_exits_2_naming_file_and_field(tmp_path, capsys, csv, meta, fragments):
    src = _trial_dir(tmp_path, csv, meta)
    out = tmp_path / "out"
    code, err = _run(capsys, "import", src, "--out", out)
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("steerlab import: error: "), err
    for f in fragments:
        assert f in err, (f, err)
    assert not out.exists()


def test_a_declared_new_condition_is_imported_and_round_trips(tmp_path):
    src = _trial_dir(tmp_path, GOOD_CSV, {**M, "condition": "BT13", "condition_declared": True})
    assert main(["import", str(src), "--out", str(tmp_path / "out")]) == 0
    (rec,) = load_study(tmp_path / "out")
    assert rec.condition == "BT13"
    # Exported again, the declaration travels among the trial's attributes.
    assert main(["export", str(tmp_path / "out"), "--out", str(tmp_path / "csv")]) == 0
    assert main(["import", str(tmp_path / "csv"), "--out", str(tmp_path / "back")]) == 0
    (back,) = load_study(tmp_path / "back")
    assert back.condition == "BT13"


def test_a_short_trial_that_ended_early_is_imported(tmp_path):
    csv = HEADER + "\n" + _rows(800) + "\n"
    src = _trial_dir(tmp_path, csv, {**PLAIN, "status": "aborted", "abort_reason": "stop"})
    assert main(["import", str(src), "--out", str(tmp_path / "out")]) == 0


def test_trials_numbered_from_zero_are_imported(tmp_path):
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "t.csv").write_text(GOOD_CSV)
    (tmp_path / "in" / "t.json").write_text(json.dumps({**M, "trial_index": 0}))
    assert main(["import", str(tmp_path / "in"), "--out", str(tmp_path / "out")]) == 0
    (rec,) = load_study(tmp_path / "out")
    assert rec.trial_index == 0


NUMBER_CASES = [
    # (id, argv, the option argparse names)
    ("simulate jobs 0", ["simulate", "--subjects", "1", "--jobs", "0"], "--jobs"),
    ("simulate jobs negative", ["simulate", "--subjects", "1", "--jobs", "-2"], "--jobs"),
    ("simulate subjects 0", ["simulate", "--subjects", "0"], "--subjects"),
    ("simulate subjects negative", ["simulate", "--subjects", "-3"], "--subjects"),
    ("simulate subjects text", ["simulate", "--subjects", "two"], "--subjects"),
    ("simulate seed negative", ["simulate", "--subjects", "1", "--seed", "-1"], "--seed"),
    ("report jobs 0", ["report", "DIR", "--jobs", "0"], "--jobs"),
    ("report inertia negative", ["report", "DIR", "--inertia-value", "-1"], "--inertia-value"),
    ("report inertia nan", ["report", "DIR", "--inertia-value", "nan"], "--inertia-value"),
    ("diagnose jobs 0", ["diagnose", "DIR", "--jobs", "0"], "--jobs"),
    ("rig-check periods 0", ["rig-check", "--periods", "0"], "--periods"),
    ("run subject 0", ["run", "--subject", "0"], "--subject"),
    ("stop subject negative", ["stop", "--subject", "-1"], "--subject"),
]


@pytest.mark.parametrize(
    "argv, option", [c[1:] for c in NUMBER_CASES], ids=[c[0] for c in NUMBER_CASES]
)
def test_bad_numbers_are_refused_naming_the_option(tmp_path, capsys, argv, option):
    out = tmp_path / "out"
    argv = [str(tmp_path) if a == "DIR" else a for a in argv] + ["--out", str(out)]
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2, err
    assert f"error: argument {option}" in err and "must be" in err, err
    assert not out.exists()


def test_simulate_study_refuses_zero_jobs(tmp_path):
    from steerlab.app.simulate import SimulateError, simulate_study

    with pytest.raises(SimulateError, match="--jobs must be ≥ 1, got 0"):
        simulate_study(1, tmp_path / "out", jobs=0)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["report", "{missing}", "--out", "{out}"], "no such folder: {missing}"),
        (["export", "{missing}", "--out", "{out}"], "no such folder: {missing}"),
        (["diagnose", "{missing}", "--out", "{out}"], "no such folder: {missing}"),
        (["import", "{missing}", "--out", "{out}"], "no such folder: {missing}"),
        (["rig-check", "--recording", "{missing}.h5", "--out", "{out}"], "no such file: {missing}"),
    ],
    ids=["report", "export", "diagnose", "import", "rig-check"],
)
def test_a_missing_input_is_named_as_missing(tmp_path, capsys, argv, message):
    names = {"missing": tmp_path / "nowhere", "out": tmp_path / "out"}
    code, err = _run(capsys, *[a.format(**names) for a in argv])
    assert code == 2, err
    assert err.count("\n") == 1 and message.format(**names) in err, err
    assert "not a directory" not in err
    assert not (tmp_path / "out").exists()


def test_a_300000_column_header_takes_linear_time(tmp_path, capsys):
    cols = HEADER.split(",") + [f"c{i}" for i in range(300_000)]
    cols[-1] = "c7"  # one duplicate, at the very end
    src = _trial_dir(tmp_path, ",".join(cols) + "\n", M)
    t0 = time.monotonic()
    code, err = _run(capsys, "import", src, "--out", tmp_path / "out")
    took = time.monotonic() - t0
    assert code == 2 and "row 1 (header): duplicate column(s) ['c7']" in err, err
    assert took < 5, took  # the quadratic check took > 120 s


FAST = fast_protocol_text()
PROTOCOL_CASES = [
    ("period inf", ("period_s = 45.0", "period_s = inf"), "[perturbation].period_s"),
    ("periods huge", ("periods = 1 ", "periods = 100000 "), "[trial].periods"),
    ("sd nan", ("sd_nm = 2.26", "sd_nm = nan"), "[perturbation].sd_nm"),
    ("run-in inf", ("run_in_s = 2.0", "run_in_s = inf"), "[trial].run_in_s"),
    ("fade -inf", ("fade_out_s = 1.0", "fade_out_s = -inf"), "[trial].fade_out_s"),
    (
        "break inf",
        ("break_between_trials_s = 15.0", "break_between_trials_s = inf"),
        "[trial].break_between_trials_s",
    ),
    (
        "break huge",
        ("break_between_trials_s = 15.0", "break_between_trials_s = 1e9"),
        "[trial].break_between_trials_s",
    ),
    ("loop nan", ("loop_rate_hz = 200.0", "loop_rate_hz = nan"), "loop_rate_hz"),
    ("inertia inf", ("inertia_kgm2 = 0.3", "inertia_kgm2 = inf"), "[wheel].inertia_kgm2"),
    ("boundary nan", ("boundary_deg = 12.0", "boundary_deg = nan"), "boundary_deg"),
    ("boundary -inf", ("boundary_deg = 12.0", "boundary_deg = -inf"), "boundary_deg"),
    ("f_max inf", ("f_max_hz = 20.0", "f_max_hz = inf"), "[perturbation].f_max_hz"),
    (
        "ratio nan",
        ("reduced_power_ratio = 0.1", "reduced_power_ratio = nan"),
        "[perturbation].reduced_power_ratio",
    ),
    ("bands huge", ("n_bands = 31", "n_bands = 100000000"), "[perturbation].n_bands"),
    ("seed negative", ("seed = 2017", "seed = -1"), "[perturbation].seed"),
    ("repetitions huge", ("repetitions = 2", "repetitions = 1000000"), "[trial].repetitions"),
    ("condition slash", ('name = "BT8"', 'name = "BT/8"'), "name"),
    ("condition NUL", ('name = "BT8"', 'name = "BT8\\u0000"'), "name"),
]


@pytest.mark.parametrize(
    "change, fragment", [c[1:] for c in PROTOCOL_CASES], ids=[c[0] for c in PROTOCOL_CASES]
)
def test_bad_protocol_exits_2_naming_file_and_field(tmp_path, capsys, change, fragment):
    p = tmp_path / "bad.toml"
    p.write_text(edit(FAST, *change))
    out = tmp_path / "sessions"
    t0 = time.monotonic()
    code, err = _run(capsys, "simulate", "--subjects", 1, "--protocol", p, "--out", out)
    assert code == 2, err
    assert err.count("\n") == 1 and str(p) in err and fragment in err, err
    assert time.monotonic() - t0 < 10
    assert not out.exists()  # nothing half-written


def test_report_on_a_folder_with_no_analysable_trial(tmp_path, capsys, fast_protocol):
    from tests.spine.test_integrity_io import _session

    d = tmp_path / "s"
    _session(d, n_trials=1)  # a session stopped after its familiarization trial
    code, err = _run(capsys, "report", d, "--out", tmp_path / "r")
    assert code == 2 and "no analysable trial among 1 (skipped: 1 familiarization" in err, err


# -- property-based fuzz --------------------------------------------------------------------------
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner,
                                                                 max_size=3),
    max_leaves=8,
)  # fmt: skip
meta_fields = st.sampled_from(
    [
        "subject",
        "condition",
        "repetition",
        "fs_hz",
        "familiarization",
        "trial_index",
        "attempt",
        "status",
        "abort_reason",
        "boundary_deg",
        "measured_start",
        "measured_stop",
        "latin_square_row",
        "dtypes",
        "perturbation_design",
        "marks",
        "trial_attributes",
        "session_attributes",
    ]  # fmt: skip
)
FUZZ = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@FUZZ
@given(changes=st.dictionaries(meta_fields, json_values, max_size=4))
def test_fuzz_import_metadata(tmp_path, changes):
    src = _trial_dir(tmp_path, GOOD_CSV, {**META, **changes})
    try:
        rec = read_trial(src / "t.csv")
    except InterchangeError as e:
        assert str(src / "t.json") in str(e) or str(src / "t.csv") in str(e)
        return
    assert rec.n_samples == 300 and rec.subject == str({**META, **changes}["subject"])


cells = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.text(alphabet=st.characters(codec="utf-8"), max_size=6),
    st.sampled_from(["", " ", '"', "1e309", "-0", "0x10", "1_0", "\r"]),
)


@FUZZ
@given(
    rows=st.lists(st.lists(cells, min_size=4, max_size=6), max_size=4),
    cut=st.integers(0, 300),
    junk=st.binary(max_size=8),
)
def test_fuzz_import_csv(tmp_path, rows, cut, junk):
    lines = GOOD_CSV.splitlines()
    lines[cut % len(lines) + 1 : cut % len(lines) + 1] = [",".join(r) for r in rows]
    data = ("\n".join(lines) + "\n").encode() + junk
    src = _trial_dir(tmp_path, data, META)
    try:
        rec = read_trial(src / "t.csv")
    except InterchangeError as e:
        assert str(src / "t.csv") in str(e)
        return
    assert all(np.all(np.isfinite(getattr(rec, c))) for c in ("time_s", "wheel_angle_rad"))


protocol_edits = st.lists(
    st.tuples(
        st.sampled_from(
            [
                "period_s = 45.0",
                "periods = 1 ",
                "run_in_s = 2.0",
                "sd_nm = 2.26",
                "n_bands = 31",
                "seed = 2017",
                "boundary_deg = 12.0",
                'name = "BT8"',
                "loop_rate_hz = 200.0",
                "repetitions = 2",
                "f_max_hz = 20.0",
                "inertia_kgm2 = 0.3",
                "gap_bins = 2",
                "first_bin = 3",
            ]  # fmt: skip
        ),
        st.one_of(
            st.floats(allow_nan=True, allow_infinity=True).map(
                lambda x: (
                    "nan"
                    if math.isnan(x)
                    else ("inf" if x == math.inf else ("-inf" if x == -math.inf else repr(x)))
                )
            ),  # fmt: skip
            st.integers(-(2**63), 2**63 - 1).map(str),
            st.text(alphabet="abc/.\\\"' ", max_size=6).map(json.dumps),
        ),
    ),
    max_size=3,
)


@settings(max_examples=60, deadline=None)
@given(changes=protocol_edits)
def test_fuzz_protocol_loader(changes):
    text = FAST
    for old, value in changes:
        key = old.split("=")[0]
        text = text.replace(old, f"{key}= {value} ", 1)
    t0 = time.monotonic()
    try:
        p = parse_protocol(text, "fuzz.toml")
    except ProtocolError as e:
        assert str(e).startswith("fuzz.toml: ")
        return
    finally:
        assert time.monotonic() - t0 < 5
    # Accepted: every number is usable.
    assert math.isfinite(p.perturbation.period_s) and p.trial_samples < 3600 * 10_000
    for c in p.conditions:
        assert re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.+-]*", c.name)
