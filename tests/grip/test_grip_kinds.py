"""Grip sources by name: a rig file's ``[glove] kind`` chooses the module (as ``[drive] kind``
does the drive); each kind checks its own ``[glove]`` fields, naming the file, table and field."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import pytest

from steerlab.hardware import grips
from steerlab.hardware.can import ConfigError
from steerlab.hardware.glove.calibration import GloveCalibration
from steerlab.hardware.grip.common import ForceScale, HandScale
from steerlab.hardware.grip.lsl_source import LslGripConfig
from steerlab.hardware.grip.steerlab_kind import GloveConfig
from steerlab.hardware.grip.text_source import TextGripConfig
from steerlab.hardware.rig import load_rig
from tests.helpers import write_rig

ROOT = Path(__file__).resolve().parents[2]
RIGS = ROOT / "hardware" / "rigs"
BASE = (RIGS / "simulated.toml").read_text()


def at(text: str, table: str) -> int:
    """Where the line ``[table]`` starts in a rig file's text (the end if it has none)."""
    m = re.search(rf"(?m)^\[{re.escape(table)}\]", text)
    return m.start() if m else len(text)


def glove_of(text: str) -> str:
    return text[at(text, "glove") : at(text, "simulation")]


STEERLAB_GLOVE = glove_of(BASE)


def with_glove(glove: str, text: str = BASE) -> str:
    """The rig file's text (the shipped simulated rig's) with ``glove`` as its ``[glove]``."""
    return text.replace(glove_of(text), glove.strip() + "\n\n")


LSL = """
[glove]
kind = "lsl"
name = "GripGlove"
type = "Grip"
unit = "raw"
[glove.channels]
left = 0
right = "grip_right"
[glove.calibration.left]
gain = 0.5
offset = 10
[glove.calibration.right]
gain = 0.25
offset = -2.5
"""

TEXT = """
[glove]
kind = "serial-text"
port = "/dev/ttyACM0"
baudrate = 9600
separator = ";"
unit = "N"
time_unit = "us"
[glove.columns]
left = 2
right = 1
time = 0
"""


def rig_error(tmp_path: Path, text: str) -> ConfigError:
    path = write_rig(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_rig(path)
    assert info.value.file == str(path)
    return info.value


def test_every_kind_is_a_module_with_a_kind_object():
    assert set(grips.GRIP_KINDS) == {"steerlab", "lsl", "serial-text"}
    for name in grips.GRIP_KINDS:
        kind = grips.grip_kind(name)
        assert kind.name == name
        for method in ("config", "open", "simulate", "at"):
            assert callable(getattr(kind, method)), (name, method)
    with pytest.raises(ValueError, match="unknown grip source kind 'tekscan'.*lsl, serial-text"):
        grips.grip_kind("tekscan")


def test_the_shipped_rig_files_name_their_grip_kinds():
    kinds = {p.name: load_rig(p).glove.kind for p in sorted(RIGS.glob("*.toml"))}
    assert kinds["simulated.toml"] == "steerlab" == grips.DEFAULT_KIND
    assert kinds["simulated-lsl-grip.toml"] == "lsl"
    assert kinds["simulated-text-grip.toml"] == "serial-text"


def test_the_new_rig_files_differ_from_the_simulated_rig_in_glove_only(tmp_path):
    for name in ("simulated-lsl-grip.toml", "simulated-text-grip.toml"):
        text = (RIGS / name).read_text()
        glove = glove_of(text)
        for first, then in (("drive", "glove"), ("simulation", "end")):
            assert text[at(text, first) : at(text, then)] == BASE[at(BASE, first) : at(BASE, then)]
        copied = load_rig(write_rig(tmp_path, with_glove(glove))).glove
        assert replace(copied, source="") == replace(load_rig(RIGS / name).glove, source="")


def test_a_glove_table_without_a_kind_is_steerlabs_own_unit(tmp_path):
    assert "kind" not in STEERLAB_GLOVE
    rig = load_rig(RIGS / "simulated.toml")
    assert isinstance(rig.glove, GloveConfig) and isinstance(rig.glove, grips.GripSettings)
    assert rig.glove.kind == "steerlab" and rig.glove.simulated
    assert (rig.glove.port, rig.glove.baudrate) == ("simulated", 115200)
    assert rig.glove.calibration == GloveCalibration.from_config(
        {
            "left": {"gain_n_per_count": 0.01, "offset_counts": 0},
            "right": {"gain_n_per_count": 0.01, "offset_counts": 0},
        }
    )
    assert rig.describe()["glove_kind"] == "steerlab"
    assert rig.describe()["glove_port"] == "simulated"
    # kind = "steerlab" said outright is the same
    said = load_rig(write_rig(tmp_path, BASE.replace("[glove]", '[glove]\nkind = "steerlab"\n#')))
    assert said.glove.kind == "steerlab" and said.glove.port == "simulated"
    assert said.glove.calibration == rig.glove.calibration


def test_an_unknown_kind_names_the_file_table_and_field(tmp_path):
    err = rig_error(tmp_path, with_glove('[glove]\nkind = "tekscan"\nport = "x"'))
    assert (err.section, err.field) == ("glove", "kind")
    assert "'tekscan'" in str(err) and "lsl, serial-text, steerlab" in str(err)


def test_an_lsl_table_is_read_field_by_field(tmp_path):
    rig = load_rig(write_rig(tmp_path, with_glove(LSL)))
    g = rig.glove
    assert isinstance(g, LslGripConfig) and not g.simulated
    assert (g.name, g.type, g.source_id, g.left, g.right) == (
        "GripGlove", "Grip", None, 0, "grip_right",
    )  # fmt: skip
    assert g.scale == ForceScale("raw", HandScale(0.5, 10.0), HandScale(0.25, -2.5))
    assert g.scale.to_newtons(30.0, 2.5) == (10.0, 1.25)
    assert g.scale.from_newtons(10.0, 1.25) == (30.0, 2.5)
    assert g.resolve_timeout_s == 5.0
    assert g.predicate() == "name='GripGlove' and type='Grip'"
    assert g.wanted() == "named 'GripGlove' of type 'Grip'"
    record = rig.describe()
    assert record["glove_kind"] == "lsl" and "glove_port" not in record
    assert record["glove_stream"] == {"name": "GripGlove", "type": "Grip"}
    assert record["glove_channels"] == {"left": 0, "right": "grip_right"}
    assert record["glove_left_gain"] == 0.5 and record["glove_right_offset"] == -2.5
    at = grips.grip_kind("lsl").at(g, "steerlab-sim-abc")
    assert at.source_id == "steerlab-sim-abc"
    assert at.predicate() == "name='GripGlove' and type='Grip' and source_id='steerlab-sim-abc'"


def test_a_serial_text_table_is_read_field_by_field(tmp_path):
    text = BASE.split("\n[simulation]")[0].replace('interface = "virtual"', 'interface = "pcan"')
    rig = load_rig(write_rig(tmp_path, with_glove(TEXT, text)))
    g = rig.glove
    assert isinstance(g, TextGripConfig) and not g.simulated and not rig.simulated
    assert (g.port, g.baudrate, g.separator) == ("/dev/ttyACM0", 9600, ";")
    assert g.columns == {"left": 2, "right": 1, "time": 0} and g.time_unit == "us"
    assert g.scale == ForceScale("N")
    assert g.parse(" 1500000 ; 3.5;12.25\r") == (12.25, 3.5, 1.5)
    assert rig.describe()["glove_port"] == "/dev/ttyACM0"
    assert grips.grip_kind("serial-text").at(g, "/dev/pts/9").port == "/dev/pts/9"


def test_a_whitespace_separator_splits_on_runs_of_spaces_and_tabs(tmp_path):
    rig = load_rig(write_rig(tmp_path, with_glove(TEXT.replace('";"', '"\\t"'))))
    assert rig.glove.parse("7\t 2.0  \t 3.0") == (3.0, 2.0, 7e-6)


def test_a_simulated_port_needs_a_simulation_table(tmp_path):
    text = BASE.split("\n[simulation]")[0].replace('interface = "virtual"', 'interface = "pcan"')
    glove = TEXT.replace('"/dev/ttyACM0"', '"simulated"')
    err = rig_error(tmp_path, with_glove(glove, text))
    assert (err.section, err.field) == ("glove", "port") and "[simulation]" in str(err)


def _bad(old: str, new: str, base: str) -> str:
    assert old in base, old
    return base.replace(old, new, 1)


LSL_ERRORS = [
    # (what, old, new, section, field, the message says)
    ("no stream", 'name = "GripGlove"\ntype = "Grip"\n', "", "glove", "name", "name or its type"),
    ("a quote", 'name = "GripGlove"', "name = \"Joe's glove\"", "glove", "name", "single quote"),
    ("an empty type", 'type = "Grip"', 'type = ""', "glove", "type", "non-empty string"),
    ("no unit", 'unit = "raw"\n', "", "glove", "unit", "required"),
    ("a unit", 'unit = "raw"', 'unit = "kg"', "glove", "unit", "'N' or 'raw'"),
    ("a typo", 'type = "Grip"', 'typ = "Grip"', "glove", "typ", "unknown field"),
    ("a timeout", 'type = "Grip"', 'type = "Grip"\nresolve_timeout_s = 0', "glove",
     "resolve_timeout_s", "> 0"),
    ("no channels", "[glove.channels]\nleft = 0\nright = \"grip_right\"\n", "",
     "glove.channels", None, "required table is missing"),
    ("no right", 'right = "grip_right"\n', "", "glove.channels", "right", "index"),
    ("a negative index", "left = 0", "left = -1", "glove.channels", "left", "≥ 0"),
    ("a float index", "left = 0", "left = 1.0", "glove.channels", "left", "got 1.0"),
    ("the same channel", 'right = "grip_right"', "right = 0", "glove.channels", "right",
     "already the left"),
    ("a channel typo", "left = 0", "left = 0\nmiddle = 2", "glove.channels", "middle",
     "unknown field"),
    ("no calibration", "[glove.calibration.left]\ngain = 0.5\noffset = 10\n"
     "[glove.calibration.right]\ngain = 0.25\noffset = -2.5\n", "", "glove.calibration",
     None, "required table is missing"),
    ("a calibration in N", 'unit = "raw"', 'unit = "N"', "glove", "calibration",
     'unit = "raw"'),
    ("a zero gain", "gain = 0.5", "gain = 0", "glove.calibration.left", "gain", "> 0"),
    ("a nan offset", "offset = 10", "offset = nan", "glove.calibration.left", "offset",
     "finite"),
    ("the glove unit's fields", "gain = 0.25\noffset = -2.5",
     "gain_n_per_count = 0.25\noffset_counts = 0", "glove.calibration.right",
     "gain_n_per_count", "known: gain, offset"),
    ("a hand missing", "[glove.calibration.right]\ngain = 0.25\noffset = -2.5\n", "",
     "glove.calibration", "right", "gain and offset"),
]  # fmt: skip

TEXT_ERRORS = [
    ("no port", 'port = "/dev/ttyACM0"\n', "", "glove", "port", "serial device path"),
    ("a baud rate", "baudrate = 9600", "baudrate = 0", "glove", "baudrate", "≥ 1"),
    ("a digit separator", 'separator = ";"', 'separator = "0"', "glove", "separator",
     "digits"),
    ("a dot separator", 'separator = ";"', 'separator = "."', "glove", "separator", "'.'"),
    ("an empty separator", 'separator = ";"', 'separator = ""', "glove", "separator",
     "non-empty"),
    ("a line-end separator", 'separator = ";"', 'separator = "\\n"', "glove", "separator",
     "line end"),
    ("no columns", "[glove.columns]\nleft = 2\nright = 1\ntime = 0\n", "", "glove.columns",
     None, "required table is missing"),
    ("no left", "left = 2\n", "", "glove.columns", "left", "missing"),
    ("a negative column", "right = 1", "right = -1", "glove.columns", "right", "≥ 0"),
    ("a shared column", "time = 0", "time = 2", "glove.columns", "time", "already left"),
    ("a column typo", "time = 0", "tme = 0", "glove.columns", "tme", "unknown field"),
    ("no time unit", 'time_unit = "us"\n', "", "glove", "time_unit", "'s' or 'ms' or 'us'"),
    ("a time unit", 'time_unit = "us"', 'time_unit = "min"', "glove", "time_unit", "got 'min'"),
    ("a time unit without a time", "time = 0\n", "", "glove", "time_unit",
     "without a time column"),
    ("raw without calibration", 'unit = "N"', 'unit = "raw"', "glove.calibration", None,
     "required table is missing"),
]  # fmt: skip


@pytest.mark.parametrize(
    "kind, what, old, new, section, field, says",
    [("lsl", *case) for case in LSL_ERRORS] + [("serial-text", *case) for case in TEXT_ERRORS],
    ids=[f"lsl: {c[0]}" for c in LSL_ERRORS] + [f"serial-text: {c[0]}" for c in TEXT_ERRORS],
)
def test_each_problem_names_the_file_table_and_field(
    tmp_path, kind, what, old, new, section, field, says
):
    glove = _bad(old, new, LSL if kind == "lsl" else TEXT)
    err = rig_error(tmp_path, with_glove(glove))
    assert (err.section, err.field) == (section, field), str(err)
    where = f"[{section}]" + (f" {field}" if field else "")
    assert str(err).startswith(f"{err.file}: {where}: "), str(err)
    assert says in str(err), str(err)


def test_the_steerlab_kind_keeps_its_messages(tmp_path):
    err = rig_error(tmp_path, BASE.replace('port = "simulated"', "port = 3"))
    assert (err.section, err.field) == ("glove", "port")
    err = rig_error(tmp_path, BASE.replace("baudrate = 115200", "baudrate = true"))
    assert (err.section, err.field) == ("glove", "baudrate")
    err = rig_error(tmp_path, BASE.replace("baudrate = 115200", "baud = 115200"))
    assert (err.section, err.field) == ("glove", "baud")
    assert re.search(r"known: baudrate, calibration, kind, port", str(err))
    err = rig_error(tmp_path, BASE.replace("offset_counts = 0\n", "", 1))
    assert err.section == "glove.calibration" and "offset_counts" in str(err)
    err = rig_error(tmp_path, "glove = 3\n" + BASE.replace(STEERLAB_GLOVE, ""))
    assert (err.section, err.field) == ("glove", None)
    err = rig_error(tmp_path, BASE.replace(STEERLAB_GLOVE, ""))
    assert (err.section, err.field) == ("glove", None) and "missing" in str(err)


# -- the host's rig file of a simulated lab -------------------------------------------------------


def _host_text(rig_text: str, pty: str | None = None) -> dict:
    """:func:`host_rig_text` of a lab at ``pty`` (a serial device) or with an LSL source id."""
    import tomllib
    from types import SimpleNamespace

    from steerlab.hardware.sim.lab import host_rig_text

    lab = SimpleNamespace(channel="127.0.0.1:5000", pty=pty, grip=pty or "steerlab-sim-0123")
    return tomllib.loads(host_rig_text(lab, rig_text))


def test_the_host_rig_of_a_simulated_lsl_lab_finds_the_labs_stream():
    text = (RIGS / "simulated-lsl-grip.toml").read_text()
    glove = _host_text(text)["glove"]
    assert glove["source_id"] == "steerlab-sim-0123" and glove["name"] == "SteerlabSimulatedGrip"
    # A rig file that already names a source id has it replaced: a TOML key may not repeat.
    given = text.replace('kind = "lsl"\n', 'kind = "lsl"\nsource_id = "the-lab-glove"\n', 1)
    assert given != text
    host = _host_text(given)
    assert host["glove"]["source_id"] == "steerlab-sim-0123"
    assert host["glove"]["channels"] == glove["channels"] and "simulation" not in host


def test_the_host_rig_of_a_simulated_serial_lab_opens_the_labs_pty():
    glove = _host_text((RIGS / "simulated-text-grip.toml").read_text(), pty="/dev/pts/9")["glove"]
    assert glove["port"] == "/dev/pts/9" and "source_id" not in glove
