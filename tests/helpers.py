"""Helpers shared by test modules."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from steerlab.hardware.can import ConfigError, load_drive_config

ROOT = Path(__file__).resolve().parents[1]


def fast_protocol_text(loop_rate_hz: float = 200.0, run_in_s: float = 2.0, periods: int = 1) -> str:
    """The paper's protocol at a lower loop rate: same design, 5× fewer samples."""
    text = (ROOT / "protocols" / "pronker2017.toml").read_text()
    text = text.replace("loop_rate_hz = 1000.0", f"loop_rate_hz = {loop_rate_hz}")
    text = text.replace("run_in_s = 5.0 ", f"run_in_s = {run_in_s} ")
    text = text.replace("periods = 1 ", f"periods = {periods} ")
    return text


#: The safety limits a behaviour test relaxes (timing belongs to benchmarks/live_loop.py): a late
#: cycle, a heartbeat gap or a late glove frame on a loaded or idle-halting machine must not end
#: a trial before what the test looks at. Every one stays a real, checked limit.
LENIENT_LIMITS = {
    "loop_stall_s": "0.5",
    "glove_timeout_s": "2.0",
    "heartbeat_timeout_ms": "2000",
    "max_missed_tpdo": "1000",
    "host_heartbeat_timeout_ms": "100",  # the longest a rig file may set (docs/rig-config.md)
    "sdo_timeout_s": "2.0",
}


def short_protocol_text(loop_rate_hz: float = 200.0, no_breaks: bool = False) -> str:
    """The paper's protocol at ``loop_rate_hz`` with a 2 s period: 4.75 s trials; with
    ``no_breaks``, no break between trials or conditions either."""
    text = fast_protocol_text(loop_rate_hz=loop_rate_hz, run_in_s=0.5, periods=2)
    values = {
        "period_s": "2.0",
        "n_bands": "8",
        "first_bin": "1",
        "fade_in_s": "0.25",
        "fade_out_s": "0.25",
    }
    if no_breaks:
        values |= {"break_between_trials_s": "0.0", "break_between_conditions_s": "0.0"}
    for key, value in values.items():
        text, n = re.subn(rf"(?m)^{key} = \S+", f"{key} = {value}", text)
        assert n == 1, key
    return text


def lenient_rig_text(text: str | None = None, **limits: str) -> str:
    """The shipped simulated rig (or ``text``) with :data:`LENIENT_LIMITS` (and ``limits``)."""
    import re

    if text is None:
        text = (ROOT / "hardware" / "rigs" / "simulated.toml").read_text()
    for key, value in (LENIENT_LIMITS | limits).items():
        text, n = re.subn(rf"(?m)^{key} = \S+", f"{key} = {value}", text)
        assert n == 1, f"rig text: {key} found {n} times"  # a stale edit fails loudly
    return text


def write_rig(tmp_path: Path, text: str) -> Path:
    """``text`` as ``tmp_path/rig.toml``."""
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def edit(text: str, old: str, new: str) -> str:
    """``text`` with ``old`` replaced; fails if ``old`` is not there (a stale test edit)."""
    assert old in text, old
    return text.replace(old, new)


def assert_rig_error(tmp_path: Path, text: str, section: str, field: str, expected: str) -> None:
    """Loading ``text`` as a rig file raises a ConfigError that names the file, the section and
    the field, in that order at the start of its message, and says ``expected``."""
    path = write_rig(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_drive_config(path)
    err = info.value
    assert (err.file, err.section, err.field) == (str(path), section, field)
    message = str(err)
    assert message.startswith(f"{path}: [{section}] {field}: "), message
    assert expected in message, message


def cli(*args) -> tuple[int, str]:
    """``steerlab ARGS`` in this process: (exit code, stderr). What a subprocess would run,
    without its two seconds of imports; the tests that are about the process itself (signals,
    locks held by another process, the installed entry point) still start one."""
    import contextlib
    import io

    from steerlab.app.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in args])
        except SystemExit as e:  # argparse's refusals
            code = int(e.code or 0)
    return code, err.getvalue()


def wait_for(condition, timeout_s: float = 5.0) -> None:
    """Poll ``condition()`` until it is true; AssertionError after ``timeout_s`` (generous: a
    loaded machine is slow, and a test that passes does not wait it out)."""
    import time

    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)


def assert_no_threads(prefix: str) -> None:
    """No thread whose name starts with ``prefix`` is still running (a source or simulator
    that a test closed must have stopped its thread)."""
    import threading

    leftovers = [t.name for t in threading.enumerate() if t.name.startswith(prefix)]
    assert not leftovers, f"threads still running: {leftovers}"


def closing_factory(make, close=lambda made: made.close()):
    """For a fixture to ``yield from``: a function that calls ``make`` and keeps what it made,
    each closed (``close``) once the test is over."""
    made: list = []

    def factory(*args, **kwargs):
        made.append(make(*args, **kwargs))
        return made[-1]

    yield factory
    for each in made:
        close(each)
