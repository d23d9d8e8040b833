"""Devices by name: the rig file's ``kind`` chooses the module that knows a device.

As python-can chooses a bus backend by its ``interface`` name, a rig file chooses its drive
(``[drive] kind``, :mod:`hardware.drives`) and its grip source (``[glove] kind``,
:mod:`hardware.grips`) by name. A registry maps each name to ``"module:attribute"`` of the
kind's object, imported only when a rig file names it.
"""

from __future__ import annotations

import importlib
from typing import Any

from steerlab.hardware.can.config import ConfigError


def checked_name(registry: dict[str, str], name: object, source: str, table: str, what: str) -> str:
    """``name`` if ``registry`` knows it; else a :class:`ConfigError` naming the file, the
    table's ``kind`` field and the known names (``what``: "drive kind", say)."""
    if not isinstance(name, str) or name not in registry:
        raise ConfigError(source, table, "kind", _unknown(registry, name, what))
    return name


def load_kind(registry: dict[str, str], name: str, what: str) -> Any:
    """The kind object ``registry`` names ``name`` (imported now)."""
    try:
        where = registry[name]
    except KeyError:
        raise ValueError(_unknown(registry, name, what)) from None
    module, attribute = where.split(":")
    return getattr(importlib.import_module(module), attribute)


def _unknown(registry: dict[str, str], name: object, what: str) -> str:
    return f"unknown {what} {name!r} (known: {', '.join(sorted(registry))})"
