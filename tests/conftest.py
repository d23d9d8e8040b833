"""Shared fixtures. Qt runs offscreen in every test (no display on CI)."""

from __future__ import annotations

import gc
import os
import sys
from pathlib import Path

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from steerlab.protocols.protocol import load_protocol, parse_protocol  # noqa: E402
from tests.helpers import fast_protocol_text, lenient_rig_text  # noqa: E402


def pytest_collection_finish(session):
    """Freeze what collection built (every test module, numpy, scipy, Qt, canopen's parsed EDS
    files...) so that the collector stops walking it.

    Many tests run a simulated drive node and its host in this one process, with heartbeat and
    SDO deadlines of 100-300 ms. A full collection of a test process walks some hundred
    thousand objects holding the GIL (80-117 ms measured), which in the lab would stall nobody:
    there the drive is its own device and the loop process pauses the collector during a trial
    (DeviceLoop.run_trial). Frozen, a collection walks only what the tests create later."""
    gc.collect()
    gc.freeze()


@pytest.fixture
def default_protocol():
    return load_protocol()


@pytest.fixture
def fast_protocol():
    return parse_protocol(fast_protocol_text(), "fast.toml")


@pytest.fixture
def fast_protocol_file(tmp_path):
    p = tmp_path / "fast.toml"
    p.write_text(fast_protocol_text())
    return p


@pytest.fixture
def lenient_rig(tmp_path):
    """The simulated rig with the limits a behaviour test relaxes (tests/helpers.py)."""
    p = tmp_path / "lenient-rig.toml"
    p.write_text(lenient_rig_text())
    return p
