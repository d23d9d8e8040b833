"""How a trial runs: the one place that turns "which rig, which subject, how fast" into the
session engine's trial loop (:class:`protocols.engine.TrialLoop`).

The ways, and who uses them:

- :func:`rig_loop`: a rig file (a lab's, or a simulated rig file). The control loop runs in real
  time in a process of its own over the drive of the rig's kind (:mod:`hardware.drives`) and its
  glove unit; a simulated rig file's devices run in a process of theirs
  (:class:`hardware.live.ProcessLoop`). ``steerlab run``, ``steerlab rig-check``, ``steerlab gui
  --rig``, the live benchmarks.
- :func:`simulated_loop` with ``pace="paced"``: the built-in simulated rig, one sample per cycle
  through the device interfaces at wall-clock pace, in this process (``steerlab gui`` without a
  rig file, ``steerlab simulate --realtime``).
- :func:`simulated_loop` with ``pace="stepped"``: the same, without waiting for the clock
  (tests of what the GUI runs).
- :func:`simulated_loop` with ``pace="batch"``: the built-in simulated rig, whole blocks inside
  the compiled world, as fast as it computes (``steerlab simulate``). Same samples as "paced" for
  the same seed, and the same channels but ``host_time_s`` (a block computed at once has no
  instant of a read).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from steerlab.hardware.loop import DEFAULT_BLOCK_S

if TYPE_CHECKING:
    from steerlab.hardware.interfaces import Display
    from steerlab.hardware.live import ProcessLoop
    from steerlab.hardware.sim.physiology import PopulationSpread, SubjectPhysiology
    from steerlab.hardware.sim.rig import SimulatedRig
    from steerlab.hardware.sim.world import WorldConfig
    from steerlab.protocols.engine import TrialLoop
    from steerlab.protocols.protocol import VirtualWheel

Pace = Literal["paced", "stepped", "batch"]


def rig_loop(
    rig_path: str | None,
    subject_number: int,
    *,
    block_s: float = DEFAULT_BLOCK_S,
    simulated_devices: str = "process",
    start_timeout_s: float = 60.0,
) -> ProcessLoop:
    """The real-time loop over the devices of the rig file ``rig_path`` (None: the shipped
    simulated rig file), for subject ``subject_number`` (a simulated rig file seats that
    subject of its population). :raises hardware.live.RigError: the rig did not come up."""
    from steerlab.hardware.live import ProcessLoop

    return ProcessLoop(
        rig_path,
        subject_number,
        block_s=block_s,
        simulated_devices=simulated_devices,
        start_timeout_s=start_timeout_s,
    )


def simulated_loop(
    physiology: SubjectPhysiology,
    world: WorldConfig,
    wheel: VirtualWheel | None = None,
    *,
    pace: Pace,
    spread: PopulationSpread | None = None,
    block_s: float = DEFAULT_BLOCK_S,
    display: Display | None = None,
) -> tuple[TrialLoop, SimulatedRig]:
    """The built-in simulated rig with ``physiology`` at the wheel, and the loop that runs it
    at ``pace``; the rig is returned too (its drive and world, for a GUI and tests).
    ``display``: the subject's display the loop shows the condition and angle on."""
    from steerlab.hardware.sim.rig import simulated_rig

    rig = simulated_rig(physiology, world, wheel, spread)
    if display is not None:
        rig.display = display
    if pace in ("paced", "stepped"):
        return rig.device_loop(realtime=pace == "paced", block_s=block_s), rig
    if pace == "batch":
        return rig.batch_loop(), rig
    raise ValueError(f"pace: 'paced', 'stepped' or 'batch', not {pace!r}")
