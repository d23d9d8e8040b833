"""Drives by name: the rig file's ``[drive] kind`` chooses the module that knows that drive.

As python-can chooses a bus backend by its ``interface`` name, a rig file chooses its drive by
``kind``; everything else (the session engine, the control loop, the GUI, the simulated lab)
talks to the drive through :class:`hardware.interfaces.RigDrive` and never asks which kind it
is. A kind module defines ``KIND``, an object with:

- ``name``: the name a rig file gives;
- ``config(document, source)``: the rig file's ``[drive]`` (with its sub-tables) and
  ``[safety]`` tables, checked, as a frozen config (:class:`DriveSettings`); every problem a
  :class:`hardware.can.ConfigError` naming the file, table and field;
- ``open(config)``: the driver, on the bus the config names (any python-can interface), ready
  to ``enable()``; its ``close()`` also closes that bus;
- ``simulate(config, plant, open_bus, simulation)``: a simulated drive of this kind (a
  :class:`SimulatedDriveNode`) that answers the kind's real protocol on the bus ``open_bus()``
  opens, over ``plant`` (:class:`hardware.can.Plant`, the wheel and whoever holds it);
  ``simulation`` is the rig file's ``[simulation]`` table (``hardware.rig.SimulationConfig``)
  or None;
- optionally ``emergency_off(config)``: turn the drive off from another process, for a drive
  that may not guard itself against a silent host (the engine's process calls it when the
  loop process dies; :class:`hardware.live.ProcessLoop`).

A new kind is one module and one line in :data:`DRIVE_KINDS`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any, Protocol, cast, runtime_checkable

import can

from steerlab.hardware.can.config import SafetyConfig
from steerlab.hardware.interfaces import RigDrive
from steerlab.hardware.kinds import checked_name, load_kind

#: kind name → "module:attribute" of its KIND. Imported only when a rig file names it.
DRIVE_KINDS: dict[str, str] = {
    "cia402": "steerlab.hardware.can.cia402_kind:KIND",
    "sensodrive": "steerlab.hardware.can.sensodrive_kind:KIND",
}
#: The kind of a rig file whose ``[drive]`` names none (every rig file before kinds existed).
DEFAULT_KIND = "cia402"


@runtime_checkable
class DriveSettings(Protocol):
    """What every kind's config has (each kind adds its own fields)."""

    kind: str
    interface: str
    channel: str | int
    bitrate: int
    loop_rate_hz: float
    sign: int
    safety: SafetyConfig
    source: str
    #: where the driver torque comes from: its ``source`` ("none": the rig gives none)
    torque_sensor: Any

    @property
    def angle_quantum_rad(self) -> float:
        """The smallest angle step the drive reports, rad."""
        ...

    def describe(self) -> dict[str, Any]:
        """The config's identifying fields for a session file's rig record."""
        ...


@runtime_checkable
class SimulatedDriveNode(Protocol):
    """A simulated drive (and any node that comes with it) on a bus, over a plant."""

    #: fault names :meth:`inject` knows (a simulated lab lists them)
    faults: tuple[str, ...]

    def start(self) -> None: ...

    def close(self) -> None: ...

    def inject(self, fault: str) -> None:
        """Make the drive misbehave now, as a real one can (tests and the fault benchmark)."""

    def status(self) -> dict[str, Any]:
        """At least ``applied_torque_nm`` (the torque on the wheel now), ``zero_torque_since``
        (time.monotonic() since when it has been zero, or None), ``state`` (a word),
        ``enabled_cycles`` (control cycles run with the power stage on) and ``errors``."""
        ...


class DriveKind(Protocol):
    name: str

    def config(self, document: dict[str, Any], source: str) -> DriveSettings: ...

    def open(self, config: Any) -> RigDrive: ...

    def simulate(
        self,
        config: Any,
        plant: Any,
        open_bus: Callable[[], can.BusABC],
        simulation: Any = None,
    ) -> SimulatedDriveNode: ...


def on_bus(config: DriveSettings, interface: str, channel: str | int) -> DriveSettings:
    """``config`` on another bus (every kind's config is a frozen dataclass): a simulated lab's
    channel, a channel of its own for one simulated rig among several in a process."""
    return replace(cast(Any, config), interface=interface, channel=channel)


def kind_name(document: dict[str, Any], source: str) -> str:
    """The drive kind a parsed rig file names (``[drive] kind``; :data:`DEFAULT_KIND` if none)."""
    drive = document.get("drive")
    name = drive.get("kind", DEFAULT_KIND) if isinstance(drive, dict) else DEFAULT_KIND
    return checked_name(DRIVE_KINDS, name, source, "drive", "drive kind")


def drive_kind(name: str) -> DriveKind:
    """The kind called ``name`` (a key of :data:`DRIVE_KINDS`)."""
    return load_kind(DRIVE_KINDS, name, "drive kind")


def drive_config(document: dict[str, Any], source: str) -> DriveSettings:
    """The checked drive config of a parsed rig file, of whichever kind it names."""
    return drive_kind(kind_name(document, source)).config(document, source)
