"""Which rig the GUI drives: the seam between the GUI and the hardware stacks. Qt-free.

:func:`make_rig_loop` returns a :class:`RigHandle`: the engine's trial loop, a status function
the GUI polls, and what the dashboard shows.

- ``rig_path=None``: the simulated rig, a simulated subject on the simulated world behind the
  device interfaces, at wall-clock pace in this process (on the engine's worker thread):
  :func:`hardware.trial_loops.simulated_loop`.
- a rig file: :func:`hardware.trial_loops.rig_loop`, the lab's loop in a process of its own
  (the drive of the rig's kind, the glove unit; or their simulations for a simulated rig file).

Status interface (:class:`RigStatus`): a plain dict the GUI thread reads about twice a second.
``status()`` must be cheap, must not block, and must be safe to call from a thread other than
the loop's (read attributes only; never talk to the bus from it). A rig fills what it has.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypedDict

from steerlab.hardware.sim.physiology import SubjectPhysiology, make_population
from steerlab.hardware.sim.world import WorldConfig
from steerlab.hardware.trial_loops import rig_loop, simulated_loop
from steerlab.protocols.engine import TrialLoop
from steerlab.protocols.protocol import Protocol

#: Samples per block the loop hands to the engine. Smaller than the headless default (50 ms)
#: because the dashboard's indicator lags by up to one block (ours: 20 ms).
GUI_BLOCK_S = 0.02


class RigError(ValueError):
    """The rig asked for cannot be used; the message says why and what to do."""


class RigStatus(TypedDict, total=False):
    rig: str  # a name for the status bar: "simulated" or the rig file's name
    simulated: bool
    drive_state: str  # human-readable drive state ("operation enabled", "disabled", …)
    drive_enabled: bool
    glove_rate_hz: float | None  # frames per second from the glove unit; None: not a stream
    glove_note: str  # what to show when there is no rate
    faults: list[str]  # active faults, each one human-readable message


class DisplayState:
    """The subject's display as the loop sees it (:class:`hardware.interfaces.Display`).

    The loop calls ``show_angle`` every few cycles on its own thread; the dashboard polls the
    attributes from the Qt thread. Plain attribute stores and loads are atomic in CPython, so
    neither side locks, and the loop never touches Qt.
    """

    def __init__(self) -> None:
        self.condition: str | None = None
        self.boundary_deg = math.inf
        self.angle_rad = 0.0
        self.updates = 0
        self.vehicle: dict[str, float] | None = None

    def show_condition(self, condition: str, boundary_deg: float) -> None:
        self.condition, self.boundary_deg = condition, float(boundary_deg)

    def show_angle(self, angle_rad: float) -> None:
        self.angle_rad = float(angle_rad)
        self.updates += 1

    def show_vehicle(self, channels: dict[str, float]) -> None:
        """A driving trial: the car on the road (app/gui/road_view.py reads it)."""
        self.vehicle = channels  # one reference swap: the Qt thread sees the old or the new


@dataclass
class RigHandle:
    name: str
    loop: TrialLoop
    status: Callable[[], RigStatus]
    display: DisplayState
    simulated: bool = True
    close: Callable[[], None] = lambda: None
    drive: Any = None  # the wheel drive, for status and tests (``drive.enabled``)
    #: The rig's world advances one sample per loop cycle, not with the clock (the built-in
    #: simulated rig): a late cycle changes no recorded value (app/gui/quality.py).
    steps_by_sample: bool = False
    extra_attributes: dict[str, Any] = field(default_factory=dict)  # stored in the session file


def check_rig_path(rig_path: str | None) -> None:
    """Fail early, before any window opens, when ``rig_path`` cannot be used."""
    if rig_path is None:
        return
    p = Path(rig_path)
    if not p.is_file():
        raise RigError(f"{rig_path}: no such rig file (omit --rig to use the simulated rig)")


def _lab_status(loop: Any, name: str) -> Callable[[], RigStatus]:
    from steerlab.hardware.realtime import realtime_warnings

    # What the loop process did not get (priority, locked memory, a core): shown with the
    # faults, in red, for the whole session (issue 14).
    warnings = [f"warning: {w}" for w in realtime_warnings(getattr(loop, "realtime", None) or {})]

    def status() -> RigStatus:
        raw = dict(getattr(loop, "status", {}) or {})
        glove = raw.get("glove_rate_hz")
        return RigStatus(
            rig=name,
            simulated=False,
            drive_state=str(raw.get("drive_state", "unknown")),
            drive_enabled=bool(raw.get("drive_enabled", False)),
            glove_rate_hz=float(glove) if glove is not None else None,
            glove_note="no frames yet" if glove is None else "",
            faults=[str(f) for f in raw.get("faults", [])]
            + ([] if raw.get("drive_ok", True) else ["drive not ready"])
            + warnings,
        )

    return status


def make_rig_loop(
    rig_path: str | None,
    subject: int | SubjectPhysiology,
    protocol: Protocol,
    *,
    realtime: bool = True,
    seed: int = 0,
    block_s: float = GUI_BLOCK_S,
) -> RigHandle:
    """The trial loop for ``rig_path`` (None: the simulated rig with simulated ``subject``).

    ``subject`` is the subject number (its simulated physiology is
    ``make_population(n, seed)[n - 1]``, as in ``steerlab simulate``) or a physiology; a rig
    file gets the number (a simulated rig file seats that simulated subject).
    """
    display = DisplayState()
    if rig_path is not None:
        check_rig_path(rig_path)
        number = subject if isinstance(subject, int) else 1
        try:
            loop = rig_loop(rig_path, number, block_s=block_s)
        except Exception as e:  # the rig did not come up: one message for the experimenter
            raise RigError(f"{rig_path}: {e}") from e
        name = Path(rig_path).name
        # The dashboard of a lab rig is fed from the samples (the loop's display is in the
        # loop's process): see ExperimenterWindow._display_angle.
        return RigHandle(
            name=name,
            loop=loop,
            status=_lab_status(loop, name),
            display=display,
            simulated=False,
            close=loop.close,
            extra_attributes={"rig_file": str(rig_path)}
            | ({"simulated_subject": loop.physiology} if getattr(loop, "physiology", None) else {}),
        )
    if isinstance(subject, SubjectPhysiology):
        phys = subject
    else:
        if int(subject) < 1:
            raise RigError(f"subject number must be ≥ 1, got {subject}")
        phys = make_population(int(subject), seed=seed)[int(subject) - 1]
    world = WorldConfig(fs_hz=protocol.loop_rate_hz)
    sim_loop, rig = simulated_loop(
        phys,
        world,
        protocol.wheel,
        pace="paced" if realtime else "stepped",
        block_s=block_s,
        display=display,  # the dashboard reads what the loop shows
    )

    def status() -> RigStatus:
        enabled = bool(rig.drive.enabled)
        return RigStatus(
            rig="simulated",
            simulated=True,
            drive_state="operation enabled" if enabled else "disabled (no torque)",
            drive_enabled=enabled,
            glove_rate_hz=None,
            glove_note="simulated glove, read every cycle",
            faults=[],
        )

    return RigHandle(
        name="simulated",
        loop=sim_loop,
        status=status,
        display=display,
        simulated=True,
        drive=rig.drive,
        steps_by_sample=True,  # WorldDrive.sync() steps the world; reads never advance it
        extra_attributes={
            "simulated": True,
            "simulation_seed": seed,
            "simulated_subject": phys.to_dict(),
            "world": world.to_dict(),
        },
    )
