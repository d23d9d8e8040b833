"""The XDF tests keep every LSL packet on this machine's loopback: liblsl reads ``LSLAPICFG``
once, when pylsl is first imported, so it is set here, before any test module of this folder
imports it (``tests/conftest.py`` does it too, for the whole suite)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests.session_helpers import short_protocol

_CFG = Path(__file__).resolve().parents[3] / "shared" / "config" / "lsl_api.cfg"
if _CFG.is_file():
    os.environ.setdefault("LSLAPICFG", str(_CFG))

#: The public XDF example files (xdf-modules/example-files), read from the workspace.
XDF_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "xdf"
MINIMAL = XDF_DATA / "minimal.xdf"
CLOCK_RESETS = XDF_DATA / "clock_resets.xdf"
EMPTY_STREAMS = XDF_DATA / "empty_streams.xdf"

needs_public_files = pytest.mark.skipif(
    not all(p.is_file() for p in (MINIMAL, CLOCK_RESETS, EMPTY_STREAMS)),
    reason=f"the public XDF example files are not in {XDF_DATA} (a clone outside the lab"
    " workspace)",
)

SHORT_PROTOCOL = short_protocol("xdf-test", loop_rate_hz=200.0)
# One trial of SHORT_PROTOCOL at 200 Hz: run-in 1 s + one 2.5 s period + fade-out 0.5 s.
SHORT_TRIAL_SAMPLES = 800


@pytest.fixture
def short_protocol_file(tmp_path):
    p = tmp_path / "short.toml"
    p.write_text(SHORT_PROTOCOL)
    return p


@pytest.fixture
def session_dir(tmp_path, short_protocol_file):
    """A simulated session (S01.h5: two trials of 800 samples at 200 Hz) in its own folder."""
    from steerlab.app.simulate import simulate_study

    out = tmp_path / "sessions"
    simulate_study(1, out, protocol_path=str(short_protocol_file), jobs=1, seed=0)
    return out
