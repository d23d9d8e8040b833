"""Keeps this process's Lab Streaming Layer traffic on the machine's loopback (``docs/lsl.md``).

LSL's default discovery sends multicast and broadcast packets on every network interface. On
a shared machine, in CI and in the tests and benchmarks, liblsl is pointed at a configuration
that keeps every packet on 127.0.0.1 (``ResolveScope = machine``, ``MachineAddresses`` and
``KnownPeers`` the loopback, IPv6 off): :func:`keep_lsl_on_loopback` sets ``LSLAPICFG`` to it,
before pylsl is first imported (liblsl reads its configuration once per process). Called at
the top of ``tests/conftest.py`` and by ``python -m benchmarks``; child processes inherit it.

Which file: ``../shared/config/lsl_api.cfg`` beside the repository, where there is one (the
machines the project is developed and tested on); else the copy shipped here,
``benchmarks/lsl_loopback.cfg`` (the same settings), so that a fresh clone stays on the
loopback too. An ``LSLAPICFG`` already set is left alone: whoever set it chose.

A lab's own network needs none of this: there LSL's defaults are what finds its devices.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ENV = "LSLAPICFG"
HERE = Path(__file__).resolve().parent
#: The machines' own loopback configuration, beside the repository.
SHARED = HERE.parent.parent / "shared" / "config" / "lsl_api.cfg"
#: The copy shipped with the repository (and the wheel).
SHIPPED = HERE / "lsl_loopback.cfg"

#: Whether pylsl was already imported the first time :func:`keep_lsl_on_loopback` ran in this
#: process (None: it has not run). liblsl reads its configuration at its first use, so a
#: pylsl imported but not used is still in time; the loopback test checks it is False.
pylsl_imported_first: bool | None = None


def loopback_config() -> Path:
    """The loopback configuration to use: the shared one, else the shipped copy."""
    return SHARED if SHARED.is_file() else SHIPPED


def keep_lsl_on_loopback() -> str:
    """Set ``LSLAPICFG`` (unless it is set already); the path in force."""
    global pylsl_imported_first
    if pylsl_imported_first is None:
        pylsl_imported_first = "pylsl" in sys.modules
    if not os.environ.get(ENV):
        os.environ[ENV] = str(loopback_config())
    return os.environ[ENV]
