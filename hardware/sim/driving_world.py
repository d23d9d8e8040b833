"""The simulated world with a car on a road: the driving task's wheel, arm, driver and vehicle.

:class:`DrivingWorld` is a :class:`hardware.sim.world.World` that, for a driving trial, also
carries the vehicle (:mod:`hardware.vehicle`) and the simulated driver's steering
(:mod:`hardware.sim.driver`). Outside driving trials it *is* the plain World (every method
defers to it), so boundary tasks simulate byte for byte as before.

Per sample k, in both paths:

1. the sensors are read (the same ``_measure`` as the World's kernel);
2. the driver's voluntary torque k_i(k)·θ_ref is added to the remnant on the arm, and the
   driver updates θ_ref from what it sees of the car now;
3. the vehicle (:func:`hardware.vehicle.vehicle_cycle`) gives the aligning torque for the
   measured angle and advances;
4. the World's kernel advances one sample, the motor command being
   ``loop_command(perturbation + aligning torque, …)``.

In the batch path (:meth:`DrivingWorld.run`) the vehicle is the loop's own and the command is
computed inside; in the live path the host's :class:`hardware.vehicle.VehicleRenderer` gives
the command and the world keeps its own copy of the vehicle for the simulated driver's eyes,
driven by the same measured angle (so it is the same vehicle, number for number: tested).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from steerlab.hardware.sim.driver import N_DRIVER_STATE, DrivingBehaviour, driver_cycle
from steerlab.hardware.sim.physiology import ConditionBehaviour
from steerlab.hardware.sim.schedule import BehaviourSchedule
from steerlab.hardware.sim.world import (
    P_DT,
    P_HAS_DPAR,
    World,
    _advance,
    _measure,
)
from steerlab.hardware.vehicle import DRIVING_CHANNELS, N_VEHICLE_STATE, vehicle_cycle


@njit(cache=True)
def _advance_driving(
    x, st, p, Ad, Bd, ring_r, ring_s, tp, hand, remnant, vel_noise, td_noise, dpar, out,
    i0, n, safety, vx, vp, road, grid, ds, dp, k_i, rows,
):  # fmt: skip
    """Advance n samples of a driving trial with the loop's command computed inside."""
    tp1 = np.empty(1)
    dt = p[P_DT]
    for j in range(n):
        k = i0 + j
        if p[P_HAS_DPAR] != 0.0:
            ang = _measure(x, st, p, ring_s, vel_noise[k], td_noise[k], dpar[k, 3], dpar[k, 2])[0]
        else:
            ang = _measure(x, st, p, ring_s, vel_noise[k], td_noise[k])[0]
        hand[k] = remnant[k] + driver_cycle(ds, dp, vx, road, grid, k_i[k], dt)
        ta = vehicle_cycle(vx, vp, road, grid, ang, dt, rows[:, j])
        tp1[0] = tp[j] + ta
        _advance(
            x, st, p, Ad, Bd, ring_r, ring_s, tp1, tp1, True, hand, vel_noise, td_noise, dpar,
            out[:, j : j + 1], k, 1, safety,
        )  # fmt: skip


@njit(cache=True)
def _driver_sample(x, st, p, ring_s, vel_noise, td_noise, dpar, k, hand, remnant, vx, vp, road,
                   grid, ds, dp, k_i, row):  # fmt: skip
    """Steps 1–3 for one sample of the live path (the command comes from outside)."""
    dt = p[P_DT]
    if p[P_HAS_DPAR] != 0.0:
        ang = _measure(x, st, p, ring_s, vel_noise[k], td_noise[k], dpar[k, 3], dpar[k, 2])[0]
    else:
        ang = _measure(x, st, p, ring_s, vel_noise[k], td_noise[k])[0]
    hand[k] = remnant[k] + driver_cycle(ds, dp, vx, road, grid, k_i[k], dt)
    vehicle_cycle(vx, vp, road, grid, ang, dt, row)


class DrivingWorld(World):
    """A World that can also run driving trials (``begin_trial(..., driving=...)``)."""

    driving: DrivingBehaviour | None = None

    def begin_trial(
        self,
        behaviour: ConditionBehaviour,
        left_share: float,
        seed,
        schedule: BehaviourSchedule | DrivingBehaviour | None = None,
    ) -> None:
        super().begin_trial(behaviour, left_share, seed, schedule)  # type: ignore[arg-type]
        self.driving = schedule if isinstance(schedule, DrivingBehaviour) else None
        if self.driving is None:
            return
        setup = self.driving.setup
        self.vp = setup.vehicle_vector()
        self.road = setup.road.table()
        self.grid = float(setup.road.grid_m)
        self.dp = self.driving.driver.vector(setup.condition.speed_mps)
        self.vx = np.zeros(N_VEHICLE_STATE)
        self.ds = np.zeros(N_DRIVER_STATE)
        self._row = np.zeros(len(DRIVING_CHANNELS))
        self._hand_of: dict | None = None
        self._hand = np.zeros(0)

    def warm_up(self, behaviour: ConditionBehaviour) -> None:
        """Compile (or load) the driving paths too, so a drive's first live cycle is not a
        compile (the simulated drive node would miss its SYNCs)."""
        super().warm_up(behaviour)
        from steerlab.hardware.sim.driver import ANCHORS
        from steerlab.protocols.driving import DrivingCondition, DrivingSetup, RoadSpec, VehicleSpec

        setup = DrivingSetup(DrivingCondition(10.0), VehicleSpec(), RoadSpec().generate(50.0))
        drive = DrivingBehaviour(setup, {c: behaviour for c, _ in ANCHORS})
        self.begin_trial(drive.base(), 0.5, seed=0, schedule=drive)
        self.run(np.zeros(2))
        self.read()
        self.step(0.0)
        self._trial = False
        self.driving = None

    def _hand_block(self) -> np.ndarray:
        """The arm's extra torque of the current noise block: remnant + the driver's steering
        (filled sample by sample as the driver acts)."""
        blk, truth = self._blk, self._truth
        if blk is None or truth is None:  # a driving trial's driver is scheduled: truth recorded
            raise RuntimeError("DrivingWorld: a driving sample before its block was drawn")
        if self._hand_of is not blk:
            self._hand_of = blk
            self._hand = np.array(blk["remnant_Nm"], dtype=float)
            self._k_i = np.ascontiguousarray(truth[:, 1])  # the arm's stiffness now
        return self._hand

    def run(self, tp: np.ndarray) -> dict[str, np.ndarray]:
        if self.driving is None:
            return super().run(tp)
        rows = np.empty((len(DRIVING_CHANNELS), len(tp)))
        done = 0

        def advance(b: dict, tp_block: np.ndarray, out_block: np.ndarray, m: int) -> None:
            nonlocal done
            _advance_driving(
                self.x, self.st, self.p, self.Ad, self.Bd, self.ring_r, self.ring_s,
                tp_block, self._hand_block(), b["remnant_Nm"], b["velocity_noise"],
                b["torque_noise"], self._dpar, out_block, self._k, m,
                self.safety_vec, self.vx, self.vp, self.road, self.grid, self.ds, self.dp,
                self._k_i, rows[:, done : done + m],
            )  # fmt: skip
            done += m

        res = self._run_blocks(tp, advance, with_truth=True)
        res.update({c: rows[i] for i, c in enumerate(DRIVING_CHANNELS)})
        return res

    def step(self, motor_command_nm: float) -> None:
        if self.driving is None:
            super().step(motor_command_nm)
            return
        b = self._ensure_block()
        hand = self._hand_block()
        _driver_sample(
            self.x, self.st, self.p, self.ring_s, b["velocity_noise"], b["torque_noise"],
            self._dpar, self._k, hand, b["remnant_Nm"], self.vx, self.vp, self.road, self.grid,
            self.ds, self.dp, self._k_i, self._row,
        )  # fmt: skip
        self._cmd1[0] = motor_command_nm
        _advance(
            self.x, self.st, self.p, self.Ad, self.Bd, self.ring_r, self.ring_s, self._cmd1,
            self._cmd1, False, hand, b["velocity_noise"], b["torque_noise"], self._dpar,
            self._out1, self._k, 1, self.safety_vec,
        )  # fmt: skip
        self._k += 1
        self._n += 1
