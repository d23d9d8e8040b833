"""The simulated devices of a simulated rig file, built in one place.

A simulated rig runs the lab's drivers against simulated devices that speak the real protocols:
a simulated drive of the rig file's kind on a CAN bus (:mod:`hardware.drives`), and a grip
device of the rig file's ``[glove]`` kind (:mod:`hardware.grips`: the glove unit's frames or
text lines on a pseudo-terminal, samples on an LSL outlet). Behind the drive's motor shaft is
a plant: the simulated subject's world (:class:`WorldPlant`) or, with no subject, a wheel held
by a relaxed hand (:class:`HeldWheel`, enough to see torque and motion in the fault tests).

:func:`simulated_devices` builds them; the live path (python-can's virtual bus, in the loop's
process) and the simulated lab process (``hardware.sim.lab``, over ``udp_loopback``) both call
it, with the bus of their choice.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import can
import numpy as np

from steerlab.hardware.drives import SimulatedDriveNode, drive_kind
from steerlab.hardware.grips import SimulatedGrip, grip_kind

if TYPE_CHECKING:
    from steerlab.hardware.rig import RigConfig
    from steerlab.protocols.session import TrialSetup


class WorldPlant:
    """The simulated world behind the simulated drive's motor shaft (hardware.can.Plant)."""

    def __init__(self, sim_rig, column_offset_nm: float, seed: int = 0) -> None:
        self.sim = sim_rig
        self.offset = column_offset_nm
        self.released = False  # the simulated subject lets go while the sensor is zeroed
        self._rng = np.random.default_rng(seed)
        self._grip = (0.0, 0.0)
        self._ready = False
        sim_rig.world.warm_up(next(iter(sim_rig.subject.physiology.behaviour.values())))

    def step(self, motor_torque_nm: float) -> None:
        if self._ready and not self.released:
            self.sim.world.step(motor_torque_nm)

    def read(self) -> tuple[float, float, float, float]:
        if not self._ready:
            return 0.0, 0.0, 0.0, self.offset
        r = self.sim.world.read()
        self._grip = (float(r["grip_force_left_N"]), float(r["grip_force_right_N"]))
        if self.released:
            noise = self.sim.cfg.sensors.torque_noise_sd
            column = self.offset + noise * self._rng.standard_normal()
            return r["wheel_angle_rad"], 0.0, r["motor_torque_Nm"], column
        return (
            r["wheel_angle_rad"],
            r["wheel_velocity_rad_s"],
            r["motor_torque_Nm"],
            r["driver_torque_Nm"] + self.offset,
        )

    def grip(self, _t: float) -> tuple[float, float]:
        # Called by the grip simulator's thread: a cached pair, never the world itself.
        return self._grip

    def begin_trial(self, setup: TrialSetup) -> None:
        self.sim.begin_trial(setup)
        self._ready = True


class HeldWheel:
    """Wheel inertia with a relaxed hand on it (hardware.can.Plant), stepped once per cycle."""

    def __init__(self, fs_hz: float, inertia=0.3, k_hand=5.0, b_hand=1.0, offset_nm=0.05):
        self.dt = 1.0 / fs_hz
        self.j, self.k, self.b, self.offset = inertia, k_hand, b_hand, offset_nm
        self.angle = self.velocity = self.motor = 0.0

    def hand_torque(self) -> float:
        return -(self.k * self.angle + self.b * self.velocity)

    def step(self, motor_torque_nm: float) -> None:
        self.motor = motor_torque_nm
        acc = (motor_torque_nm + self.hand_torque()) / self.j
        self.velocity += acc * self.dt  # semi-implicit Euler
        self.angle += self.velocity * self.dt

    def read(self) -> tuple[float, float, float, float]:
        # driver torque: the torque the wheel exerts on the hand (minus the hand's on the wheel)
        return self.angle, self.velocity, self.motor, -self.hand_torque() + self.offset

    def grip(self, _t: float) -> tuple[float, float]:
        return 20.0, 20.0


@dataclass
class SimulatedDevices:
    """What :func:`simulated_devices` built; ``close()`` stops it all."""

    plant: WorldPlant | HeldWheel
    drive: SimulatedDriveNode
    glove: SimulatedGrip  # of the rig's [glove] kind; the host reaches it at glove.address
    physiology: dict[str, Any] | None = None

    @property
    def world(self) -> WorldPlant | None:
        """The subject's world, or None for a wheel held by a relaxed hand."""
        return self.plant if isinstance(self.plant, WorldPlant) else None

    def close(self) -> None:
        for closer in (self.glove.close, self.drive.close):
            try:
                closer()
            except Exception:
                pass


def simulated_devices(
    rig: RigConfig,
    open_bus: Callable[[], can.BusABC],
    *,
    subject: int | None,
    drive_config: Any = None,
) -> SimulatedDevices:
    """The simulated drive (of the rig's kind, on ``open_bus()``) and grip device (of its
    ``[glove]`` kind) of ``rig``, started. ``subject``: subject N of the rig's population at
    the wheel (its ``[simulation]`` table), or None for a wheel held by a relaxed hand.
    ``drive_config``: the drive config the node answers as (default ``rig.drive``; a copy on
    another channel, say)."""
    config = drive_config if drive_config is not None else rig.drive
    physiology = None
    plant: WorldPlant | HeldWheel
    if subject is None:
        plant = HeldWheel(rig.loop_rate_hz)
    else:
        from steerlab.hardware.sim.physiology import make_population
        from steerlab.hardware.sim.rig import simulated_rig

        sim = rig.simulation
        if sim is None:
            raise ValueError(f"{rig.source}: a simulated subject needs a [simulation] table")
        phys = make_population(subject, seed=sim.seed)[subject - 1]
        physiology = phys.to_dict()
        sim_rig = simulated_rig(phys, sim.world_config(rig.loop_rate_hz))
        plant = WorldPlant(sim_rig, sim.column_torque_offset_nm, seed=phys.seed)
    node = drive_kind(config.kind).simulate(config, plant, open_bus, rig.simulation)
    try:
        node.start()
        glove = grip_kind(rig.glove.kind).simulate(rig.glove, plant.grip)
        glove.start()
    except BaseException:
        node.close()
        raise
    return SimulatedDevices(plant, node, glove, physiology)
