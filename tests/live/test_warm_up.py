"""The loop's one-off work (a device's first use: the simulated world compiling its kernels, or
loading them from numba's cache) is done before the first trial's first timed cycle, with the
drive disabled, so that it cannot make that cycle late and abort the trial as stalled."""

from __future__ import annotations

import time
from dataclasses import replace

from steerlab.app.gui.rig import make_rig_loop
from steerlab.hardware.interfaces import DriveReading, GripReading
from steerlab.hardware.loop import DeviceLoop
from steerlab.protocols.engine import LoopControl, SessionEngine
from steerlab.protocols.events import TrialEnded
from steerlab.protocols.session import build_plan


class LoggedDevices:
    """A drive, torque sensor and glove that log each call, the drive's enable state with it."""

    def __init__(self) -> None:
        self.log: list[str] = []
        self.enabled = False

    # drive
    def enable(self) -> None:
        self.enabled = True
        self.log.append("enable")

    def disable(self) -> None:
        self.enabled = False
        self.log.append("disable")

    def quick_stop(self) -> None:
        self.log.append("quick_stop")

    def set_torque(self, torque_nm: float) -> None:
        self.log.append(f"set_torque {'on' if self.enabled else 'off'}")

    def sync(self) -> None:
        self.log.append(f"sync {'on' if self.enabled else 'off'}")

    def read(self) -> DriveReading:
        self.log.append(f"read {'on' if self.enabled else 'off'}")
        return DriveReading(0.0, 0.0, 0.0)

    def hook(self, setup) -> None:
        self.log.append("hook")

    def health(self) -> str | None:
        self.log.append("health")
        return None


class Sensor:
    def read(self) -> float:
        return 0.0

    def zero(self) -> None:
        pass


class Glove:
    def latest(self) -> GripReading:
        return GripReading(10.0, 10.0, time.monotonic())


def test_the_devices_are_used_once_before_the_drive_is_enabled(short_protocol):
    plan = build_plan(short_protocol, 1)
    dev = LoggedDevices()
    loop = DeviceLoop(dev, Sensor(), Glove(), trial_hooks=[dev.hook], health=dev.health)
    setup = plan.setup(plan.trials[0], 1)
    blocks = list(loop.run_trial(setup, LoopControl()))
    assert sum(len(b["time_s"]) for b in blocks) == setup.n_samples
    first = dev.log.index("enable")
    before = dev.log[:first]
    # A whole dry cycle, drive off (zero torque ignored), then the trial's own hooks.
    assert before == ["hook", "health", "read off", "set_torque off", "sync off", "hook"]
    # Every timed cycle reads with the drive on: the dry cycle is not one of the trial's.
    reads = [e for e in dev.log[first:] if e.startswith("read")]
    assert reads == ["read on"] * setup.n_samples

    # Once per kind of trial: the next trial of the same kind starts at once.
    dev.log.clear()
    list(loop.run_trial(plan.setup(plan.trials[1], 1), LoopControl()))
    assert dev.log[:2] == ["hook", "enable"]


def test_a_slow_first_use_does_not_stall_the_first_trial(short_protocol):
    """The GUI's simulated rig (its world in this process, at wall-clock pace): the simulated
    drive's first read and first step take longer than the loop's stall limit, as compiling the
    world's kernels does on a fresh install. The first trial of a fresh session completes."""
    handle = make_rig_loop(None, 1, short_protocol, realtime=True)
    loop = handle.loop
    assert isinstance(loop, DeviceLoop)
    slow_s = loop.safety.loop_stall_s * 1.5
    drive = handle.drive
    for name in ("read", "sync"):
        method = getattr(drive, name)

        def slow_first(method=method, done=[]):  # noqa: B006 (one flag per method)
            if not done:
                done.append(True)
                time.sleep(slow_s)
            return method()

        setattr(drive, name, slow_first)
    plan = build_plan(short_protocol, 1)
    plan = replace(plan, trials=plan.trials[:1])
    ends: list[TrialEnded] = []
    engine = SessionEngine(plan, loop)
    engine.subscribe(lambda e: ends.append(e) if isinstance(e, TrialEnded) else None)
    engine.run()
    assert [(e.status, e.reason) for e in ends] == [("complete", None)]
    assert ends[0].n_samples == plan.setup(plan.trials[0], 1).n_samples
