"""The control loop that runs one trial through the device interfaces, one sample per cycle.

Per cycle: read the drive (angle, velocity) and the torque sensor, take the newest glove
reading, render the virtual wheel plus the perturbation, command the drive, end the cycle
(SYNC). Samples go out in blocks for the engine. Whatever ends the trial, the finalizer leaves
the motor at zero torque and disabled.

The same loop serves the lab rig and the simulated rig (whose devices sit on the simulated
world), paced at wall-clock speed (``realtime=True``) or as fast as possible.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from hardware.interfaces import Display, GloveUnit, TorqueSensor, WheelDrive
from hardware.safety import SafetyLimits, loop_command
from protocols.engine import LoopControl, TrialFault
from protocols.session import TrialSetup

LOOP_CHANNELS = (
    "time_s",
    "perturbation_torque_Nm",
    "driver_torque_Nm",
    "wheel_angle_rad",
    "wheel_velocity_rad_s",
    "motor_command_Nm",
    "motor_torque_Nm",
    "grip_force_N",
    "grip_force_left_N",
    "grip_force_right_N",
)


class DeviceLoop:
    def __init__(
        self,
        drive: WheelDrive,
        torque_sensor: TorqueSensor,
        glove: GloveUnit,
        display: Display | None = None,
        *,
        realtime: bool = False,
        block_s: float = 0.05,
        trial_hooks: Sequence[Callable[[TrialSetup], None]] = (),
        clock: Callable[[], float] = time.perf_counter,
        safety: SafetyLimits | None = None,
    ) -> None:
        self.safety = safety or SafetyLimits()
        self.drive, self.sensor, self.glove, self.display = drive, torque_sensor, glove, display
        self.realtime = realtime
        self.block_s = block_s
        self.trial_hooks = list(trial_hooks)
        self.clock = clock
        self._stats: dict = {}

    def emergency_stop(self) -> None:
        self.drive.quick_stop()
        self.drive.disable()

    def trial_stats(self) -> dict:
        return dict(self._stats)

    def run_trial(self, setup: TrialSetup, control: LoopControl) -> Iterator[dict]:
        for hook in self.trial_hooks:
            hook(setup)
        if self.display is not None:
            self.display.show_condition(setup.spec.condition, setup.spec.boundary_deg)
        fs = setup.fs_hz
        period = 1.0 / fs
        n_total = setup.n_samples
        blk = max(1, int(round(self.block_s * fs)))
        tp_all = setup.perturbation_nm
        k_sw, b_sw = setup.wheel_k, setup.wheel_b
        limits = self.safety.kernel_vector(fs)
        cmd = 0.0
        late = 0
        errors: list[float] = []
        self._stats = {}
        self.drive.enable()
        try:
            t0 = self.clock()
            k = 0
            while k < n_total:
                m = min(blk, n_total - k)
                buf = {c: np.empty(m) for c in LOOP_CHANNELS}
                for j in range(m):
                    if self.realtime:
                        due = t0 + (k + j) * period
                        now = self.clock()
                        if due - now > 0.002:
                            time.sleep(due - now - 0.001)
                        while self.clock() < due:
                            pass
                        err = self.clock() - due
                        errors.append(err)
                        if err > 0.5e-3:
                            late += 1
                    r = self.drive.read()
                    td = self.sensor.read()
                    g = self.glove.latest()
                    if g is None:
                        raise TrialFault("no grip-force reading from the glove unit")
                    tp = tp_all[k + j]
                    cmd = loop_command(tp, r.angle_rad, r.velocity_rad_s, cmd, k_sw, b_sw, limits)
                    self.drive.set_torque(cmd)
                    self.drive.sync()
                    buf["time_s"][j] = (k + j) / fs
                    buf["perturbation_torque_Nm"][j] = tp
                    buf["driver_torque_Nm"][j] = td
                    buf["wheel_angle_rad"][j] = r.angle_rad
                    buf["wheel_velocity_rad_s"][j] = r.velocity_rad_s
                    buf["motor_command_Nm"][j] = cmd
                    buf["motor_torque_Nm"][j] = r.torque_actual_nm
                    buf["grip_force_left_N"][j] = g.left_n
                    buf["grip_force_right_N"][j] = g.right_n
                    buf["grip_force_N"][j] = g.left_n + g.right_n
                    if self.display is not None and (k + j) % 20 == 0:
                        self.display.show_angle(r.angle_rad)
                k += m
                yield buf
                if control.stop_requested:
                    return
        finally:
            # Whatever ended the trial: no torque on the wheel, power stage off.
            try:
                self.drive.set_torque(0.0)
            finally:
                self.drive.disable()
            if errors:
                e = np.abs(np.asarray(errors)) * 1e3
                self._stats = {
                    "period_error_p50_ms": float(np.percentile(e, 50)),
                    "period_error_p99_ms": float(np.percentile(e, 99)),
                    "period_error_max_ms": float(e.max()),
                    "late_cycles": int(late),
                    "cycles": len(errors),
                }
