"""LSL stays on the loopback here: the tests, the benchmarks and the processes they start point
liblsl at a configuration that keeps every packet on 127.0.0.1 (``LSLAPICFG``, set by
``benchmarks/_lsl_loopback.py`` before pylsl is imported), and liblsl really read it."""

from __future__ import annotations

import configparser
import json
import os
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from steerlab.benchmarks import _lsl_loopback
from tests.helpers import ROOT


def _settings(path: str | Path) -> configparser.ConfigParser:
    cfg = configparser.ConfigParser(inline_comment_prefixes=(";",))
    cfg.optionxform = str  # liblsl's keys keep their case
    assert cfg.read(path), f"{path}: unreadable"
    return cfg


def _assert_loopback(cfg: configparser.ConfigParser) -> None:
    assert cfg["multicast"]["ResolveScope"] == "machine"
    assert cfg["multicast"]["MachineAddresses"] == "{127.0.0.1}"
    assert cfg["lab"]["KnownPeers"] == "{127.0.0.1}"
    assert cfg["ports"]["IPv6"] == "disable"
    # Nothing that would widen the scope again.
    assert "LinkAddresses" not in cfg["multicast"] and "SiteAddresses" not in cfg["multicast"]


def test_lslapicfg_is_set_to_a_loopback_configuration():
    path = os.environ.get("LSLAPICFG")
    assert path, "LSLAPICFG is not set: tests/conftest.py sets it before pylsl is imported"
    assert Path(path).is_file(), path
    _assert_loopback(_settings(path))


def test_the_shipped_copy_keeps_the_same_settings():
    shipped = _settings(_lsl_loopback.SHIPPED)
    _assert_loopback(shipped)
    if _lsl_loopback.SHARED.is_file():
        shared = _settings(_lsl_loopback.SHARED)
        assert {s: dict(shared[s]) for s in shared.sections()} == {
            s: dict(shipped[s]) for s in shipped.sections()
        }
        assert _lsl_loopback.loopback_config() == _lsl_loopback.SHARED
    assert _lsl_loopback.SHIPPED.parent == ROOT / "benchmarks"


def test_pylsl_came_after_the_setting_and_liblsl_read_it():
    """The conftest set LSLAPICFG before anything imported pylsl; an outlet made now carries
    the file's SessionID (liblsl's default is "default") and no IPv6 port (disabled)."""
    assert _lsl_loopback.pylsl_imported_first is False
    import pylsl

    info = pylsl.StreamInfo("loopback-check", "Test", 1, 0, "float32", uuid.uuid4().hex)
    outlet = pylsl.StreamOutlet(info)
    try:
        mine = outlet.get_info()
        expected = _settings(os.environ["LSLAPICFG"])["lab"]["SessionID"]
        assert mine.session_id() == expected != "default"
        assert "<v6data_port>0</v6data_port>" in mine.as_xml()
    finally:
        del outlet


CHILD = """
import json, os, sys
assert "pylsl" not in sys.modules
from steerlab.benchmarks._lsl_loopback import keep_lsl_on_loopback
path = keep_lsl_on_loopback()
assert os.environ["LSLAPICFG"] == path
import pylsl
sid = sys.argv[1]
outlet = pylsl.StreamOutlet(pylsl.StreamInfo("loopback-child", "Test", 1, 0, "float32", sid))
found = pylsl.resolve_byprop("source_id", sid, 1, 10.0)
print(json.dumps({
    "cfg": path,
    "session_id": outlet.get_info().session_id(),
    "found": [f.session_id() for f in found],
    "v6": outlet.get_info().as_xml().count("<v6data_port>0</v6data_port>"),
}))
"""


def _child_env() -> dict:
    env = {k: v for k, v in os.environ.items() if k != "LSLAPICFG"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return env


def test_a_fresh_process_that_calls_the_helper_stays_on_the_loopback(tmp_path):
    """A process started without LSLAPICFG (a benchmark run by hand) gets it from the helper
    before pylsl is imported, and liblsl reads it: its streams carry the loopback SessionID
    and are found there."""
    sid = uuid.uuid4().hex
    out = subprocess.run(
        [sys.executable, "-c", CHILD, sid],
        env=_child_env(),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["cfg"] == str(_lsl_loopback.loopback_config())
    expected = _settings(got["cfg"])["lab"]["SessionID"]
    assert got["session_id"] == expected and got["found"] == [expected]
    assert got["v6"] == 1


@pytest.mark.parametrize("preset", [None, "/somewhere/else.cfg"])
def test_the_benchmarks_entry_point_sets_it_unless_set(tmp_path, preset):
    env = _child_env()
    if preset:
        env["LSLAPICFG"] = preset
    code = (
        "import os, sys; import steerlab.benchmarks.__main__; "
        "print(os.environ.get('LSLAPICFG')); print('pylsl' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    cfg, pylsl_loaded = out.stdout.split()
    assert cfg == (preset or str(_lsl_loopback.loopback_config()))
    assert pylsl_loaded == "False"
