"""The simulated rig: a simulated subject on the simulated world, behind the device interfaces.

``simulated_rig(subject)`` builds it in one call. Two loops run it:
- :class:`BatchLoop` advances whole blocks inside the compiled world (fast: ``steerlab
  simulate``);
- :class:`hardware.loop.DeviceLoop` over the simulated devices advances one sample per cycle,
  exactly as with the lab's drive and gloves (``--realtime``, and the live path).
Both give the same samples for the same seed (tested).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from steerlab.hardware.interfaces import Display, DriveReading, GripReading
from steerlab.hardware.loop import LOOP_CHANNELS, DeviceLoop
from steerlab.hardware.safety import SafetyLimits
from steerlab.hardware.sim.driver import ANCHORS, DrivingBehaviour
from steerlab.hardware.sim.driving_world import DrivingWorld
from steerlab.hardware.sim.physiology import (
    ArmParams,
    ConditionBehaviour,
    PopulationSpread,
    SubjectPhysiology,
)
from steerlab.hardware.sim.schedule import DEFAULT_TAU_S, BehaviourSchedule, schedule_for
from steerlab.hardware.sim.world import TRUTH_CHANNELS, World, WorldConfig
from steerlab.hardware.vehicle import DRIVING_CHANNELS
from steerlab.protocols.engine import LoopControl, TrialFault
from steerlab.protocols.protocol import VirtualWheel
from steerlab.protocols.session import TrialSetup

#: A hands-off trial (rig check): the arm is detached from the wheel (no contact stiffness or
#: damping), so the wheel moves alone; the arm's own states stay at rest.
HANDS_OFF = ConditionBehaviour(ArmParams(0.1, 1.0, 6.0, 0.0, 0.0), 0.0, 0.0, 0.0)


@dataclass
class SimulatedSubject:
    """Decides the arm's behaviour for each trial, from the condition shown on the display."""

    physiology: SubjectPhysiology
    spread: PopulationSpread = field(default_factory=PopulationSpread)
    # How fast the driver follows a change of task within a trial (first order, log scale).
    adaptation_tau_s: float = DEFAULT_TAU_S
    grip_adaptation_tau_s: float = DEFAULT_TAU_S

    def _behaviour_in(
        self, condition: str, setup: TrialSetup, cfg: WorldConfig
    ) -> ConditionBehaviour:
        b = self.physiology.for_trial(condition, setup.spec.trial_index, self.spread)
        drift = cfg.mechanisms.drift
        if drift.active:
            f = drift.factor(setup.spec.trial_index)
            k_c = f if "k_c" in drift.stiffnesses else 1.0
            b = replace(b, arm=b.arm.scaled(k_i=f, k_c=k_c))
        return b

    def behaviour(self, setup: TrialSetup, cfg: WorldConfig) -> ConditionBehaviour:
        """The trial's behaviour; for a time-varying trial, its first segment's (the base)."""
        sch = setup.schedule
        cond = setup.spec.condition if sch is None else sch.conditions[0]
        return self._behaviour_in(cond, setup, cfg)

    def behaviour_schedule(self, setup: TrialSetup, cfg: WorldConfig) -> BehaviourSchedule | None:
        """For a time-varying trial: the behaviour of every segment's condition."""
        sch = setup.schedule
        if sch is None:
            return None
        of = {c: self._behaviour_in(c, setup, cfg) for c in set(sch.conditions)}
        return schedule_for(sch, of, self.adaptation_tau_s, self.grip_adaptation_tau_s)

    def driving_behaviour(self, setup: TrialSetup, cfg: WorldConfig) -> DrivingBehaviour:
        """For a driving trial: arm and grip following the road (hardware/sim/driver.py)."""
        if setup.driving is None:
            raise ValueError(f"trial {setup.key} is not a driving trial")
        anchors = {c: self._behaviour_in(c, setup, cfg) for c, _ in ANCHORS}
        return DrivingBehaviour(
            setup.driving, anchors, self.adaptation_tau_s, self.grip_adaptation_tau_s
        )

    def trial_seed(self, setup: TrialSetup) -> list[int]:
        return [self.physiology.seed, setup.spec.trial_index, setup.attempt]


class SimulatedRig:
    """World + subject, and the four simulated devices that expose them."""

    def __init__(
        self,
        subject: SimulatedSubject,
        cfg: WorldConfig | None = None,
        wheel: VirtualWheel | None = None,
    ) -> None:
        self.cfg = cfg or WorldConfig()
        self.subject = subject
        self.world = DrivingWorld(self.cfg, wheel)  # the plain World outside driving trials
        self.drive = WorldDrive(self.world)
        self.torque_sensor = WorldTorqueSensor(self.world)
        self.glove = SimulatedGlove(self.world)
        # The GUI puts its own in (app.gui.rig.DisplayState): any Display will do.
        self.display: Display = SimulatedDisplay()

    def begin_trial(self, setup: TrialSetup) -> ConditionBehaviour:
        if abs(setup.fs_hz - self.cfg.fs_hz) > 1e-9:
            self.cfg = replace(self.cfg, fs_hz=setup.fs_hz)
            self.world.cfg = self.cfg
        schedule: BehaviourSchedule | DrivingBehaviour | None
        if setup.hands_off:
            b, schedule = HANDS_OFF, None
        elif setup.driving is not None:
            drive = self.subject.driving_behaviour(setup, self.cfg)
            b, schedule = drive.base(), drive
        else:
            b = self.subject.behaviour(setup, self.cfg)
            schedule = self.subject.behaviour_schedule(setup, self.cfg)
        self.world.begin_trial(
            b, self.subject.physiology.left_share, self.subject.trial_seed(setup), schedule
        )
        self.drive.command = 0.0
        return b

    def truth(self) -> dict[str, float]:
        """The simulated driver's true parameters this sample (time-varying trials only)."""
        return self.world.truth()

    def device_loop(self, realtime: bool = False, **kw) -> DeviceLoop:
        # In-process and simulated: a late cycle harms nobody, so only a real hang aborts.
        kw.setdefault("safety", SafetyLimits(loop_stall_s=1.0))
        return DeviceLoop(
            self.drive,
            self.torque_sensor,
            self.glove,
            self.display,
            realtime=realtime,
            trial_hooks=[self.begin_trial],
            sample_extras=self.truth,
            **kw,
        )

    def batch_loop(self, block_s: float = 1.0) -> BatchLoop:
        return BatchLoop(self, block_s)


class WorldDrive:
    """The in-process simulated rig's drive: a command straight into the world, no protocol
    (the simulated drives that speak a real drive's protocol are in :mod:`hardware.can`)."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.enabled = False
        self.command = 0.0

    def enable(self) -> None:
        self.enabled = True

    def disable(self) -> None:
        self.command = 0.0
        self.enabled = False

    def quick_stop(self) -> None:
        self.command = 0.0

    def set_torque(self, torque_nm: float) -> None:
        self.command = float(torque_nm) if self.enabled else 0.0

    def sync(self) -> None:
        self.world.step(self.command)

    def read(self) -> DriveReading:
        r = self.world.read()
        return DriveReading(r["wheel_angle_rad"], r["wheel_velocity_rad_s"], r["motor_torque_Nm"])


class WorldTorqueSensor:
    def __init__(self, world: World) -> None:
        self.world = world

    def read(self) -> float:
        return float(self.world.read()["driver_torque_Nm"])

    def zero(self) -> None:
        pass  # the simulated sensor has no offset


class SimulatedGlove:
    def __init__(self, world: World) -> None:
        self.world = world

    def latest(self) -> GripReading | None:
        r = self.world.read()
        return GripReading(r["grip_force_left_N"], r["grip_force_right_N"], time.monotonic())


class SimulatedDisplay:
    """Records what the subject would see (the simulated subject reads the trial directly)."""

    def __init__(self) -> None:
        self.condition: str | None = None
        self.boundary_deg = float("inf")
        self.angle_rad = 0.0
        self.vehicle: dict[str, float] = {}

    def show_condition(self, condition: str, boundary_deg: float) -> None:
        self.condition, self.boundary_deg = condition, boundary_deg

    def show_angle(self, angle_rad: float) -> None:
        self.angle_rad = angle_rad

    def show_vehicle(self, channels: dict[str, float]) -> None:
        """A driving trial: the car on the road (``hardware.vehicle.DRIVING_CHANNELS``)."""
        self.vehicle = dict(channels)


class BatchLoop:
    """Runs a trial on the simulated rig in blocks inside the compiled world."""

    def __init__(self, rig: SimulatedRig, block_s: float = 1.0) -> None:
        self.rig = rig
        self.block_s = block_s

    def emergency_stop(self) -> None:
        self.rig.drive.disable()

    def trial_stats(self) -> dict:
        return {}

    def run_trial(self, setup: TrialSetup, control: LoopControl) -> Iterator[dict]:
        rig = self.rig
        rig.begin_trial(setup)
        rig.display.show_condition(setup.spec.condition, setup.spec.boundary_deg)
        changes = [] if setup.schedule is None else setup.schedule.display_changes()[1:]
        fs = setup.fs_hz
        blk = max(1, int(round(self.block_s * fs)))
        n = setup.n_samples
        tp = setup.perturbation_nm
        rig.drive.enable()
        try:
            for k in range(0, n, blk):
                m = min(blk, n - k)
                out = rig.world.run(tp[k : k + m])
                left, right = out["grip_force_left_N"], out["grip_force_right_N"]
                block = {
                    "time_s": np.arange(k, k + m) / fs,
                    "perturbation_torque_Nm": np.array(tp[k : k + m]),
                    "driver_torque_Nm": out["driver_torque_Nm"],
                    "wheel_angle_rad": out["wheel_angle_rad"],
                    "wheel_velocity_rad_s": out["wheel_velocity_rad_s"],
                    "motor_command_Nm": out["motor_command_Nm"],
                    "motor_torque_Nm": out["motor_torque_Nm"],
                    "grip_force_N": left + right,
                    "grip_force_left_N": left,
                    "grip_force_right_N": right,
                }
                assert tuple(block) == LOOP_CHANNELS
                if rig.world.scheduled:
                    block.update({c: out[c] for c in TRUTH_CHANNELS})
                if setup.driving is not None:
                    block.update({c: out[c] for c in DRIVING_CHANNELS})
                while changes and changes[0][0] < k + m:
                    _, cond, bd = changes.pop(0)
                    rig.display.show_condition(cond, bd)
                rig.display.show_angle(float(out["wheel_angle_rad"][-1]))
                yield block
                if rig.world.nonfinite_commands:
                    raise TrialFault(
                        f"non-finite motor command input in {rig.world.nonfinite_commands} "
                        "cycles (perturbation, wheel or sensor value): zero torque applied"
                    )
                if control.stop_requested:
                    return
        finally:
            rig.drive.disable()


def simulated_rig(
    physiology: SubjectPhysiology,
    cfg: WorldConfig | None = None,
    wheel: VirtualWheel | None = None,
    spread: PopulationSpread | None = None,
) -> SimulatedRig:
    return SimulatedRig(SimulatedSubject(physiology, spread or PopulationSpread()), cfg, wheel)
