"""Grip sources by name: the rig file's ``[glove] kind`` chooses the module that reads the grip.

As the drive is chosen by ``[drive] kind`` (:mod:`hardware.drives`), a rig file chooses where
its grip force comes from by ``[glove] kind``:

- ``"steerlab"`` (the default when ``kind`` is absent): Steerlab's own glove unit on a serial
  port, its framed protocol (``docs/glove-protocol.md``);
- ``"lsl"``: any Lab Streaming Layer stream, found by name and/or type;
- ``"serial-text"``: a device that prints one text line per sample on a serial port (an FSR
  glove on a microcontroller).

Everything else (the control loop, the engine's safety checks, the GUI) talks to the source
through :class:`hardware.interfaces.GripSource` and never asks which kind it is. A kind module
defines ``KIND``, an object with:

- ``name``: the name a rig file gives;
- ``config(table, source)``: the rig file's ``[glove]`` table, checked, as a frozen config
  (:class:`GripSettings`); every problem a :class:`hardware.can.ConfigError` naming the file,
  the table and the field;
- ``open(config)``: the source, its reader started; a device that cannot be reached raises
  :class:`hardware.grip.reader.GripSourceError` naming it;
- ``simulate(config, grip)``: a simulated device of this kind (:class:`SimulatedGrip`, not
  started) that produces ``grip(t) -> (left_N, right_N)`` (t in s since it started) in the
  kind's real form: frames on a pty, samples on an LSL outlet, text lines on a pty;
- ``at(config, address)``: ``config`` reaching the simulated device at ``address``
  (:attr:`SimulatedGrip.address`: a pty's path, an LSL stream's source id). A simulated lab
  in a process of its own reports the address; the host's config is this.

A new kind is one module and one line in :data:`GRIP_KINDS`. Docs: ``docs/grip-sources.md``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

from steerlab.hardware.can.config import ConfigError
from steerlab.hardware.interfaces import GripSource
from steerlab.hardware.kinds import checked_name, load_kind

#: kind name → "module:attribute" of its KIND. Imported only when a rig file names it.
GRIP_KINDS: dict[str, str] = {
    "steerlab": "steerlab.hardware.grip.steerlab_kind:KIND",
    "lsl": "steerlab.hardware.grip.lsl_source:KIND",
    "serial-text": "steerlab.hardware.grip.text_source:KIND",
}
#: The kind of a ``[glove]`` table that names none (every rig file before kinds existed).
DEFAULT_KIND = "steerlab"
#: A serial grip device's ``port`` in a simulated rig: a pty fed by the simulated device.
SIMULATED_PORT = "simulated"

GripFunction = Callable[[float], tuple[float, float]]
"""t (s since the simulated device started, host clock) -> (left_N, right_N)."""


@runtime_checkable
class GripSettings(Protocol):
    """What every kind's config has (each kind adds its own fields)."""

    kind: str
    source: str

    @property
    def simulated(self) -> bool:
        """The config names the simulated device itself (``port = "simulated"``): only a
        simulated rig (one with ``[simulation]``) may."""
        ...

    def describe(self) -> dict[str, Any]:
        """The config's identifying fields for a session file's rig record."""
        ...


@runtime_checkable
class SimulatedGrip(Protocol):
    """A simulated grip device of some kind, producing a simulated subject's grip."""

    #: fault names :meth:`inject` knows (a simulated lab lists them)
    faults: tuple[str, ...]

    @property
    def address(self) -> str:
        """Where the host reaches it (a pty's path, an LSL stream's source id)."""
        ...

    def start(self) -> Any: ...

    def close(self) -> None: ...

    def stop_streaming(self) -> None:
        """The device stops sending (the line goes quiet; an LSL outlet stops pushing)."""

    def resume_streaming(self) -> None: ...

    def hang_up(self) -> None:
        """The device goes away (its pty closes; its LSL outlet is destroyed)."""

    def inject(self, fault: str) -> None:
        """A simulated lab's glove fault, by name (:attr:`faults`)."""


WHAT = "grip source kind"


class GripKind(Protocol):
    name: str

    def config(self, table: dict[str, Any], source: str) -> GripSettings: ...

    def open(self, config: Any) -> GripSource: ...

    def simulate(self, config: Any, grip: GripFunction) -> SimulatedGrip: ...

    def at(self, config: Any, address: str) -> GripSettings: ...


def kind_name(table: dict[str, Any], source: str) -> str:
    """The grip kind a ``[glove]`` table names (``kind``; :data:`DEFAULT_KIND` if none)."""
    return checked_name(GRIP_KINDS, table.get("kind", DEFAULT_KIND), source, "glove", WHAT)


def grip_kind(name: str) -> GripKind:
    """The kind called ``name`` (a key of :data:`GRIP_KINDS`)."""
    return load_kind(GRIP_KINDS, name, WHAT)


def grip_config(document: dict[str, Any], source: str) -> GripSettings:
    """The checked ``[glove]`` config of a parsed rig file, of whichever kind it names."""
    table = document.get("glove")
    if table is None:
        raise ConfigError(source, "glove", None, "required table is missing")
    if not isinstance(table, dict):
        raise ConfigError(source, "glove", None, f"expected a table, got {type(table).__name__}")
    return grip_kind(kind_name(table, source)).config(table, source)
