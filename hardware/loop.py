"""The control loop that runs one trial through the device interfaces, one sample per cycle.

Per cycle: check the rig's health and the emergency stop, read the drive (angle, velocity) and
the torque sensor, take the newest glove reading, compute the motor command (virtual wheel +
perturbation within the safety limits, :func:`hardware.safety.loop_command`), command the drive,
end the cycle (SYNC). Samples go out in blocks for the engine, each with the host's
``time.monotonic()`` at its read (``host_time_s``: the lab clock's stamp, however late the block
reaches the engine).

Whatever ends the trial (the end, an abort, a fault, an exception, the generator being closed),
the finalizer leaves the motor at zero torque and disabled.

One-off work (a device's first use: the simulated world compiling its kernels, or loading them
from numba's cache; the vehicle's functions) is done by :meth:`DeviceLoop.warm_up` before the
drive is enabled and the clock starts, once per kind of trial: it can take seconds, and in the
first cycle it would abort the trial as stalled.

Faults that end a trial as aborted (:class:`protocols.engine.TrialFault`, with the reason):
the emergency stop; a rig health problem (``health()`` returns a reason: lost drive heartbeat,
drive fault/EMCY, CAN send failure, glove stream stopped or broken); a cycle later than
``SafetyLimits.loop_stall_s``. In real time a watchdog thread also quick-stops the drive if the
loop itself hangs.

Time-varying trials (``setup.schedule``): the display is told each change of task at its sample.
``sample_extras``, if given, is read once per cycle (after the sensors) and its values are logged
as extra channels (the simulated rig's true arm parameters).

Driving trials (``setup.driving``): the host's vehicle (:class:`hardware.vehicle.VehicleRenderer`)
gives the aligning torque for the measured angle each cycle; it is added to the perturbation
inside ``loop_command`` (same limits and guard), its state is logged (``DRIVING_CHANNELS``) and
shown to a display that has ``show_vehicle`` every 20 cycles.

Pause: with ``pause_fades_out`` (a real rig, where time cannot stop) the perturbation fades out
and the trial ends as aborted, to be run again; without it (the simulated rig) the loop simply
waits, with the simulated world, until the engine asks for the next block.
"""

from __future__ import annotations

import gc
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence

import numpy as np

from steerlab.hardware.interfaces import Display, GloveUnit, TorqueSensor, WheelDrive
from steerlab.hardware.safety import SafetyLimits, loop_command, nonfinite_input, warm_up
from steerlab.hardware.vehicle import DRIVING_CHANNELS, VehicleRenderer
from steerlab.hardware.vehicle import warm_up as vehicle_warm_up
from steerlab.protocols.engine import LoopControl, TrialFault
from steerlab.protocols.session import TrialSetup

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
#: Per sample, the host's ``time.monotonic()`` at the cycle's read of the sensors: what puts
#: each sample on the lab's clock (``protocols.lsl_publisher.LabClock``) however late its block
#: reaches the engine. Beside the measured channels: a batch simulation has no such instant,
#: and gives the time it computed the sample (``hardware.sim.rig.BatchLoop``).
HOST_TIME_CHANNEL = "host_time_s"
#: What every block of a trial loop carries (at least).
BLOCK_CHANNELS = (*LOOP_CHANNELS, HOST_TIME_CHANNEL)
PAUSE_FADE_S = 0.5
SPIN_S = 0.25e-3
LATE_S = 0.5e-3  # a cycle later than this counts as late
DEFAULT_BLOCK_S = 0.05  # length of the blocks the loop hands its consumer, s (headless)


class DeviceLoop:
    def __init__(
        self,
        drive: WheelDrive,
        torque_sensor: TorqueSensor,
        glove: GloveUnit,
        display: Display | None = None,
        *,
        realtime: bool = False,
        block_s: float = DEFAULT_BLOCK_S,
        trial_hooks: Sequence[Callable[[TrialSetup], object]] = (),  # return values unused
        pre_trial: Callable[[], None] | None = None,
        health: Callable[[], str | None] | None = None,
        estop: threading.Event | None = None,
        pause_fades_out: bool = False,
        clock: Callable[[], float] = time.perf_counter,
        safety: SafetyLimits | None = None,
        sample_extras: Callable[[], Mapping[str, float]] | None = None,
        sample_sink: Callable[[int, dict, int], None] | None = None,
    ) -> None:
        self.drive, self.sensor, self.glove, self.display = drive, torque_sensor, glove, display
        self.sample_extras = sample_extras
        # Called once per sample, as soon as it is complete: (sample index, block buffer, row).
        self.sample_sink = sample_sink
        self.realtime = realtime
        self.block_s = block_s
        self.trial_hooks = list(trial_hooks)
        self.pre_trial = pre_trial
        self.health = health
        self.estop = estop
        self.pause_fades_out = pause_fades_out
        self.clock = clock
        self.safety = safety or SafetyLimits()
        self._stats: dict = {}
        #: Record when each phase of each cycle ends (``trace_summary`` in the trial's stats):
        #: what makes a cycle late. Costs four clock reads per cycle.
        self.trace = False
        warm_up()
        self._warmed: set[tuple[bool, bool, bool]] = set()
        self._last_cycle = 0.0
        self._suspended = False
        self._stall: str | None = None

    def emergency_stop(self) -> None:
        if self.estop is not None:
            self.estop.set()
        try:
            self.drive.quick_stop()
        finally:
            self.drive.disable()

    def trial_stats(self) -> dict:
        return dict(self._stats)

    # -- watchdog --------------------------------------------------------------------------------
    def _watch(self, stop: threading.Event) -> None:
        """Quick-stop the drive if the loop stops cycling (it is stuck, not merely late)."""
        limit = self.safety.loop_stall_s
        while not stop.wait(limit / 4):
            if self._suspended:
                continue  # a simulated rig waiting, with its world, for the engine
            late = self.clock() - self._last_cycle
            if late > limit and self._stall is None:
                self._stall = f"control loop stalled: no cycle for {late * 1e3:.1f} ms"
                try:
                    self.drive.quick_stop()
                except Exception:  # the loop's finalizer still disables the drive
                    pass

    # -- warm-up -----------------------------------------------------------------------------------
    def warm_up(self, setup: TrialSetup) -> None:
        """Do now, with the drive disabled, the one-off work of a trial like ``setup``.

        The trial hooks, then one dry cycle through every device call a cycle makes (health,
        drive, torque sensor, glove, extras; zero torque, which a disabled drive ignores, and
        the SYNC): whatever a device does the first time (the simulated world compiles its
        kernels, or loads them from numba's cache, and draws its first noise block) happens
        here, not in the first timed cycle. What the calls return is not looked at: a fault
        they would show is found by the trial's first cycle. The trial's own hooks run again at
        its start and set the devices up afresh.

        Once per kind of trial (driving, time-varying, hands-off): later calls return at once.
        :meth:`run_trial` calls it; call it between trials only (the drive must be disabled).
        """
        kind = (setup.driving is not None, setup.schedule is not None, setup.hands_off)
        if kind in self._warmed:
            return
        if setup.driving is not None:
            vehicle_warm_up()
        for hook in self.trial_hooks:
            hook(setup)
        if self.health is not None:
            self.health()
        self.drive.read()
        self.sensor.read()
        if self.glove is not None:  # a drive test may run without one
            self.glove.latest()
        if self.sample_extras is not None:
            self.sample_extras()
        self.drive.set_torque(0.0)
        self.drive.sync()
        self._warmed.add(kind)

    # -- the trial ---------------------------------------------------------------------------------
    def run_trial(self, setup: TrialSetup, control: LoopControl) -> Iterator[dict]:
        # Before anything is timed: the watchdog and the stall check arm only for cycles in
        # steady state.
        self.warm_up(setup)
        for hook in self.trial_hooks:
            hook(setup)
        if self.display is not None:
            self.display.show_condition(setup.spec.condition, setup.spec.boundary_deg)
        changes = []
        if setup.schedule is not None and self.display is not None:
            changes = setup.schedule.display_changes()[1:]  # the first is shown above
        next_change = changes[0][0] if changes else -1
        extras_of = self.sample_extras
        fs = setup.fs_hz
        period = 1.0 / fs
        n_total = setup.n_samples
        blk = max(1, int(round(self.block_s * fs)))
        tp_all = setup.perturbation_nm
        k_sw, b_sw = setup.wheel_k, setup.wheel_b
        # A drive that renders the spring and damper in its own fields (free of the host's
        # latency and jitter) is sent the command less what it adds itself: the safety layer
        # still limits, slews and records the whole torque on the wheel, as for any drive.
        renders_wheel = bool(getattr(self.drive, "renders_wheel", False))
        set_wheel = getattr(self.drive, "set_wheel", None) if renders_wheel else None
        limits = self.safety.kernel_vector(fs)
        # A driving trial: the vehicle's aligning torque joins the perturbation in the command.
        vehicle = None
        if setup.driving is not None:
            vehicle = VehicleRenderer(setup.driving, fs)  # compiled by warm_up()
        ta = 0.0
        stall_s = self.safety.loop_stall_s
        cmd = 0.0
        errors: list[float] = []
        self._stats = {}
        self._stall = None
        self._samples = 0  # samples complete (handed out or about to be)
        fade = 1.0  # perturbation gain while a pause fades it out
        fade_step = 1.0 / max(1, int(round(PAUSE_FADE_S * fs)))
        watchdog_stop = threading.Event()
        watchdog = None
        # Per cycle, s after its due time: the previous cycle's end, the sleep's return, the
        # command computed (health, sensors, glove, loop_command), the SYNC answered.
        trace = np.full((n_total, 4), np.nan) if self.trace else None
        self.drive.enable()
        # No collection pauses inside a real-time trial (a full collection in a big process,
        # such as a test runner's, takes hundreds of ms); collected at the trial's end. Only
        # once the drive is enabled: a failed enable leaves the process as it was.
        gc_was_enabled = gc.isenabled()
        try:
            if self.realtime:
                gc.disable()
            if self.pre_trial is not None:
                self.pre_trial()
            if set_wheel is not None:
                # After the zeroing, which measures the sensor on a wheel left to itself.
                set_wheel(k_sw, b_sw)
            self._last_cycle = self.clock()
            if self.realtime:
                watchdog = threading.Thread(
                    target=self._watch, args=(watchdog_stop,), name="loop-watchdog", daemon=True
                )
                watchdog.start()
            t0 = self.clock()
            k = 0
            while k < n_total:
                m = min(blk, n_total - k)
                buf = {c: np.empty(m) for c in BLOCK_CHANNELS}
                if vehicle is not None:
                    # One copy per cycle into a 2-D block; the channels are its rows (views).
                    drv = np.empty((len(DRIVING_CHANNELS), m))
                    buf.update({c: drv[i] for i, c in enumerate(DRIVING_CHANNELS)})
                filled = 0  # samples of this block complete
                try:
                    for j in range(m):
                        if self.realtime:
                            due = t0 + (k + j) * period
                            now = self.clock()
                            # Sleep most of the wait (other threads and processes run), spin the
                            # last SPIN_S: sleep wakes up to ~0.1 ms late, the spin does not.
                            if due - now > SPIN_S + 1e-4:
                                time.sleep(due - now - SPIN_S)
                            woke = self.clock()
                            while self.clock() < due:
                                pass
                            err = self.clock() - due
                            errors.append(err)
                            if trace is not None:
                                trace[k + j, 0] = now - due  # the previous cycle's end
                                trace[k + j, 1] = woke - due
                            if err > stall_s:
                                raise TrialFault(
                                    f"control loop stalled: cycle {err * 1e3:.1f} ms late"
                                )
                        self._last_cycle = self.clock()
                        if self.estop is not None and self.estop.is_set():
                            raise TrialFault("emergency stop")
                        if self._stall is not None:
                            raise TrialFault(self._stall)
                        if self.health is not None:
                            problem = self.health()
                            if problem is not None:
                                raise TrialFault(problem)
                        # The instant the sample is of: just before its sensors are read.
                        read_at = time.monotonic()
                        r = self.drive.read()
                        td = self.sensor.read()
                        g = self.glove.latest()
                        if g is None:
                            raise TrialFault("no grip-force reading from the glove unit")
                        if extras_of is not None:
                            for name, v in extras_of().items():
                                if name not in buf:
                                    buf[name] = np.empty(m)
                                buf[name][j] = v
                        tp = tp_all[k + j]
                        if fade < 1.0 or (self.pause_fades_out and control.paused.is_set()):
                            fade = max(0.0, fade - fade_step)
                            tp *= fade
                        ang, vel = r.angle_rad, r.velocity_rad_s
                        if vehicle is not None:
                            ta = vehicle.cycle(ang)
                            drv[:, j] = vehicle.row
                        cmd = loop_command(tp + ta, ang, vel, cmd, k_sw, b_sw, limits)
                        if cmd == 0.0:  # loop_command's answer to a non-finite input, or a zero
                            bad = nonfinite_input(
                                perturbation_torque_Nm=tp,
                                aligning_torque_Nm=ta,
                                wheel_angle_rad=r.angle_rad,
                                wheel_velocity_rad_s=r.velocity_rad_s,
                                wheel_k=k_sw,
                                wheel_b=b_sw,
                            )
                            if bad is not None:
                                self.drive.set_torque(0.0)
                                self.drive.sync()  # the zero is applied at once
                                raise TrialFault(f"non-finite motor command input: {bad}")
                        if trace is not None:
                            trace[k + j, 2] = self.clock() - due if self.realtime else 0.0
                        if renders_wheel:
                            self.drive.set_torque(cmd + k_sw * ang + b_sw * vel)
                        else:
                            self.drive.set_torque(cmd)
                        self.drive.sync()
                        if trace is not None:
                            trace[k + j, 3] = self.clock() - due if self.realtime else 0.0
                        buf["time_s"][j] = (k + j) / fs
                        buf[HOST_TIME_CHANNEL][j] = read_at
                        buf["perturbation_torque_Nm"][j] = tp
                        buf["driver_torque_Nm"][j] = td
                        buf["wheel_angle_rad"][j] = r.angle_rad
                        buf["wheel_velocity_rad_s"][j] = r.velocity_rad_s
                        buf["motor_command_Nm"][j] = cmd
                        buf["motor_torque_Nm"][j] = r.torque_actual_nm
                        buf["grip_force_left_N"][j] = g.left_n
                        buf["grip_force_right_N"][j] = g.right_n
                        buf["grip_force_N"][j] = g.left_n + g.right_n
                        filled = j + 1
                        if self.sample_sink is not None:
                            self.sample_sink(k + j, buf, j)
                        if self.display is not None and (k + j) % 20 == 0:
                            self.display.show_angle(r.angle_rad)
                            if vehicle is not None and hasattr(self.display, "show_vehicle"):
                                self.display.show_vehicle(vehicle.channels())
                        if k + j == next_change and self.display is not None:
                            _, cond, bd = changes.pop(0)
                            self.display.show_condition(cond, bd)
                            next_change = changes[0][0] if changes else -1
                        if fade == 0.0:
                            # Faded out for a pause: end here (the samples so far are yielded
                            # below); the trial is run again later.
                            raise TrialFault(
                                "paused mid-trial by the experimenter; run the trial again"
                            )
                except TrialFault:
                    # The samples of this block taken before the fault go to the file too.
                    if filled:
                        self._samples = k + filled
                        yield {c: v[:filled] for c, v in buf.items()}
                    raise
                k += m
                self._samples = k
                t_yield = self.clock()
                # Only a loop whose world waits with it (simulated) may be suspended; a real
                # rig's loop is consumed continuously (ProcessLoop), so there the watchdog stays.
                self._suspended = not self.pause_fades_out
                yield buf
                self._suspended = False
                if control.stop_requested:
                    return
                suspended = self.clock() - t_yield
                if self.realtime and not self.pause_fades_out and suspended > 2 * period:
                    # A simulated rig waits with its world while the engine is paused: carry on
                    # from now rather than running the missed cycles back to back.
                    t0 += suspended
                    self._last_cycle = self.clock()
        finally:
            watchdog_stop.set()
            # Whatever ended the trial: no torque on the wheel, power stage off.
            try:
                self.drive.set_torque(0.0)
            except Exception:
                pass
            finally:
                self.drive.disable()
            if watchdog is not None:
                watchdog.join(1.0)
            if self.realtime and gc_was_enabled:
                gc.enable()
                gc.collect()
            self._stats = {"samples": self._samples}
            if errors:
                e = np.abs(np.asarray(errors)) * 1e3
                late = int(np.count_nonzero(np.asarray(errors) > LATE_S))
                self._stats |= {
                    "period_error_p50_ms": float(np.percentile(e, 50)),
                    "period_error_p99_ms": float(np.percentile(e, 99)),
                    "period_error_max_ms": float(e.max()),
                    "late_cycles": int(late),
                    "late_fraction": float(late / len(errors)),
                    "cycles": len(errors),
                    # What "late" and "stalled" meant in this trial, for whoever reports it.
                    "late_threshold_ms": LATE_S * 1e3,
                    "stall_limit_ms": stall_s * 1e3,
                }
                if trace is not None:
                    self._stats["trace_summary"] = trace_summary(trace, np.asarray(errors))


def trace_summary(trace: np.ndarray, errors: np.ndarray) -> dict:
    """Why cycles were late (``DeviceLoop.trace``): each late cycle is put down to the previous
    cycle's work running past its due time, or to the sleep returning late (the OS or another
    thread holding the interpreter did not let the loop run), or to the spin itself."""
    rows = trace[: len(errors)]
    late = errors > LATE_S
    prev_end, woke = rows[:, 0], rows[:, 1]
    work = rows[:, 3] - rows[:, 1]  # from waking to the SYNC answered
    by_work = late & (prev_end > LATE_S)
    by_sleep = late & ~by_work & (woke > LATE_S)

    def ms(x: np.ndarray, q: float) -> float | None:
        x = x[np.isfinite(x)]
        return round(float(np.percentile(x, q)) * 1e3, 4) if x.size else None

    return {
        "late_cycles": int(late.sum()),
        "late_after_long_work": int(by_work.sum()),
        "late_after_late_wake": int(by_sleep.sum()),
        "late_other": int((late & ~by_work & ~by_sleep).sum()),
        "work_p50_ms": ms(work, 50),
        "work_p99_ms": ms(work, 99),
        "work_max_ms": ms(work, 100),
        "sync_p99_ms": ms(rows[:, 3] - rows[:, 2], 99),
        "compute_p99_ms": ms(rows[:, 2] - rows[:, 1], 99),
    }
