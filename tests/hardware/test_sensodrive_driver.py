"""The SensoDrive driver against the simulated SENSO-Wheel (``hardware/can/sensodrive_sim.py``)
on python-can's virtual bus: enabling, the fields it sends, directions, the 1 kHz cycle,
stopping, every fault it must report, and the driver torque (hand sensor, reconstruction)."""

from __future__ import annotations

import math
import threading
import time
import uuid

import can
import numpy as np
import pytest
from scipy import signal

from steerlab.hardware.can.cia402 import DriveEnableError, DriveError
from steerlab.hardware.can.sensodrive import LowPassDerivatives, SensoDrive
from steerlab.hardware.can.sensodrive_config import SensoDriveConfig, sensodrive_config
from steerlab.hardware.can.sensodrive_frames import (
    NM_PER_RAD_PER_STIFFNESS_LSB,
    NMS_PER_RAD_PER_DAMPING_LSB,
    STATE_REQUEST_ID,
    Command,
    State,
    StateCommand,
    encode_state_command,
    encode_state_reply,
    reply_id,
)
from steerlab.hardware.drives import drive_kind
from steerlab.hardware.interfaces import ColumnTorque, RigDrive

FS = 1000.0
DT = 1.0 / FS
KIND = drive_kind("sensodrive")


class Wheel:
    """A wheel of known inertia with a spring-damper hand on it, and optionally its own dry
    friction and gravity imbalance (the sign conventions of hardware/sim/mechanisms.py), in
    Steerlab's direction. Column torque = the torque the wheel exerts on the hand."""

    def __init__(self, inertia=0.3, k_hand=5.0, b_hand=1.0, coulomb=0.0, gravity=0.0):
        self.j, self.k, self.b = inertia, k_hand, b_hand
        self.coulomb, self.gravity = coulomb, gravity
        self.angle = self.velocity = self.motor = 0.0

    def hand_on_wheel(self) -> float:
        return -(self.k * self.angle + self.b * self.velocity)

    def step(self, motor_torque_nm: float) -> None:
        self.motor = motor_torque_nm
        own = -self.coulomb * math.tanh(self.velocity / 0.01) - self.gravity * math.sin(self.angle)
        self.velocity += (motor_torque_nm + self.hand_on_wheel() + own) / self.j * DT
        self.angle += self.velocity * DT

    def read(self) -> tuple[float, float, float, float]:
        return self.angle, self.velocity, self.motor, -self.hand_on_wheel()


def rig_document(channel: str, sensor: dict | None = None, **drive) -> dict:
    table = {
        "kind": "sensodrive",
        "interface": "virtual",
        "channel": channel,
        "wheel_inertia_kgm2": 0.3,
        "state_timeout_s": 0.2,
        **drive,
    }
    if sensor is not None:
        table["torque_sensor"] = sensor
    safety = {"max_torque_nm": 8.0, "max_slew_nm_per_s": 400.0, "soft_angle_limit_deg": 90.0}
    return {"drive": table, "safety": safety}


class Rig:
    def __init__(self, config: SensoDriveConfig, node, drive: SensoDrive, wheel: Wheel):
        self.config, self.node, self.drive, self.wheel = config, node, drive, wheel


@pytest.fixture
def rig():
    """``make(wheel=None, sensor=None, start=True, **drive_fields)`` → a :class:`Rig`: the
    simulated node (built by the kind, as a simulated lab does) and the driver (opened by the
    kind) on a fresh virtual channel."""
    made: list[tuple[object, SensoDrive, list[can.BusABC]]] = []

    def make(
        wheel: Wheel | None = None,
        sensor: dict | None = None,
        start=True,
        unhurried=False,
        **drive,
    ):
        channel = f"senso-{uuid.uuid4()}"
        config = KIND.config(rig_document(channel, sensor, **drive), "test.toml")
        wheel = wheel or Wheel()
        buses: list[can.BusABC] = []

        def open_bus() -> can.BusABC:
            bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
            buses.append(bus)
            return bus

        node = KIND.simulate(config, wheel, open_bus)
        if start:
            node.start()
        driver = KIND.open(config)
        if unhurried:
            # Cycles the test does not pace: waiting longer for each answer changes nothing
            # but the test's dependence on how this shared machine schedules the simulated
            # drive's thread (the config keeps a real loop's timeout below its period).
            driver._timeout_s = 0.05
        made.append((node, driver, buses))
        return Rig(config, node, driver, wheel)

    yield make
    for node, driver, buses in made:
        driver.close()
        node.close()
        for bus in buses:
            bus.shutdown()


def _too_busy(status: dict) -> None:
    """Every try had a reply the shared machine did not schedule in time (the simulated drive
    answers on a thread of this process): what the test measures needs every answer, so it
    cannot say anything on this run. Timing itself is measured by the benchmarks."""
    pytest.skip(
        "the test machine was too busy to answer every request within the reply timeout "
        f"(last try: {status['missed_replies']} missed, {status['late_replies']} late)"
    )


def wait_for(condition, timeout=1.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.001)
    return condition()


def run(drive: SensoDrive, n: int, torque=0.0) -> None:
    for i in range(n):
        drive.set_torque(torque(i) if callable(torque) else torque)
        drive.sync()


def send_state(bus_channel: str, command: Command) -> None:
    """Another host on the bus commands the drive (the driver sees the 0x210 as well)."""
    with can.Bus(interface="virtual", channel=bus_channel, receive_own_messages=False) as bus:
        data = encode_state_command(StateCommand(command, 180, 100, 100))
        bus.send(can.Message(arbitration_id=STATE_REQUEST_ID, data=data, is_extended_id=False))


# -- the interface -------------------------------------------------------------------------------


def test_the_driver_is_a_rig_drive_that_renders_the_wheel(rig):
    r = rig(sensor={"source": "hand_sensor"})
    assert isinstance(r.drive, RigDrive)
    assert r.drive.renders_wheel
    assert isinstance(r.drive.torque_sensor, ColumnTorque)
    assert r.drive.angle_quantum_rad == pytest.approx(math.radians(0.009))
    assert r.drive.torque_sensor is r.drive.torque_sensor  # one instance: the offset persists


def test_without_a_driver_torque_source_the_torque_sensor_refuses(rig):
    r = rig()  # no [drive.torque_sensor]: source "none"
    with pytest.raises(DriveError, match="source is 'none'"):
        _ = r.drive.torque_sensor
    # the drive itself still works (a hands-off rig check needs no driver torque)
    r.drive.enable()
    run(r.drive, 10)
    assert r.drive.problem() is None


# -- enabling ------------------------------------------------------------------------------------


def test_enable_from_off_reaches_on_with_end_stop_and_limits(rig):
    r = rig(end_stop_deg=270, torque_limit_percent=120, torque_limit_beyond_percent=30)
    assert r.node.status()["state"] == "off"
    r.drive.enable()
    status = r.node.status()
    assert status["state"] == "on"
    assert status["end_stop_deg"] == 270
    assert status["torque_limits_percent"] == (120, 30)
    assert r.drive.status()["drive_state"] == "on"
    assert r.drive.status()["drive_enabled"] is True
    assert r.drive.problem() is None


def test_enable_from_the_error_state_clears_it_first(rig):
    r = rig()
    r.node.inject("error")
    r.drive.sync()  # the driver has not asked yet: it knows nothing of the error
    r.drive.enable()
    assert r.node.status()["state"] == "on"
    assert r.drive.problem() is None


def test_enable_fails_naming_the_state_when_the_drive_does_not_answer(rig):
    r = rig()
    r.node.inject("go_silent")
    t0 = time.monotonic()
    with pytest.raises(DriveEnableError, match=r"stayed in no answer \(no 0x210\)"):
        r.drive.enable()
    assert time.monotonic() - t0 < 0.2 + 0.1  # state_timeout_s, once
    assert not r.drive.enabled
    assert "enable failed" in r.drive.problem()


class StuckInReady:
    """A node that answers every 0x200 with READY and ignores everything else."""

    def __init__(self, channel: str):
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.notifier = can.Notifier(self.bus, [self.on_message])

    def on_message(self, msg: can.Message) -> None:
        if msg.arbitration_id == STATE_REQUEST_ID:
            reply = can.Message(
                arbitration_id=reply_id(STATE_REQUEST_ID),
                data=encode_state_reply(State.READY),
                is_extended_id=False,
            )
            self.bus.send(reply)

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


def test_enable_fails_naming_the_state_the_drive_stayed_in():
    channel = f"senso-{uuid.uuid4()}"
    config = sensodrive_config(rig_document(channel), "test.toml")
    node = StuckInReady(channel)
    drive = KIND.open(config)
    try:
        with pytest.raises(DriveEnableError) as info:
            drive.enable()
        message = str(info.value)
        assert "on (0x200/0x14)" in message
        assert "did not reach ON (0x14)" in message
        assert "stayed in READY (0x12)" in message
    finally:
        drive.close()
        node.close()


def test_disable_cancels_an_enable_that_is_waiting(rig):
    r = rig()
    r.node.inject("go_silent")
    errors: list[BaseException] = []

    def enable():
        try:
            r.drive.enable()
        except DriveEnableError as exc:
            errors.append(exc)

    t = threading.Thread(target=enable)
    t0 = time.monotonic()
    t.start()
    time.sleep(0.02)
    r.drive.disable()
    t.join(1.0)
    assert time.monotonic() - t0 < 0.15  # well before state_timeout_s (0.2 s)
    assert errors and "cancelled" in str(errors[0])


# -- what the driver sends -----------------------------------------------------------------------


def test_set_wheel_friction_and_torque_reach_the_drive_while_enabled(rig):
    r = rig(friction_nm=0.05)
    r.drive.set_wheel(4.2, 2.0)
    r.drive.set_torque(0.5)
    r.drive.sync()  # not enabled yet: all zero
    assert r.node.status()["last_command"] == {
        "torque_nm": 0.0,
        "friction_nm": 0.0,
        "damping_nms_per_rad": 0.0,
        "stiffness_nm_per_rad": 0.0,
    }
    r.drive.enable()
    r.drive.set_torque(0.5)
    r.drive.sync()
    sent = r.node.status()["last_command"]
    assert sent["torque_nm"] == pytest.approx(-0.5)  # sign −1
    assert sent["friction_nm"] == pytest.approx(0.05)
    # the Pronker wheel's fields: 209 mN·m/rpm and 73 mN·m/deg
    assert sent["damping_nms_per_rad"] == pytest.approx(209 * NMS_PER_RAD_PER_DAMPING_LSB)
    assert sent["stiffness_nm_per_rad"] == pytest.approx(73 * NM_PER_RAD_PER_STIFFNESS_LSB)


def test_set_wheel_refuses_what_the_fields_cannot_hold(rig):
    r = rig()
    with pytest.raises(ValueError, match="stiffness"):
        r.drive.set_wheel(-1.0, 0.0)
    with pytest.raises(ValueError, match="not renderable"):
        r.drive.set_wheel(0.0, 1000.0)


@pytest.mark.parametrize("sign", [-1, 1])
def test_directions_follow_the_sign(rig, sign):
    r = rig(wheel=Wheel(k_hand=0.0, b_hand=0.0), sign=sign)
    r.drive.enable()
    run(r.drive, 200, 1.0)
    assert r.node.status()["last_command"]["torque_nm"] == pytest.approx(sign * 1.0)
    reading = r.drive.read()
    assert reading.angle_rad > 0 and reading.velocity_rad_s > 0  # Steerlab's direction
    assert reading.angle_rad == pytest.approx(r.wheel.angle, abs=math.radians(0.009))
    assert reading.torque_actual_nm == pytest.approx(1.0)


def test_a_torque_the_field_cannot_hold_is_a_fault_and_commands_zero(rig):
    r = rig()
    r.drive.enable()
    r.drive.set_torque(40.0)
    r.drive.sync()
    assert r.node.status()["last_command"]["torque_nm"] == 0.0
    assert "torque not sent" in r.drive.problem()
    with pytest.raises(ValueError):
        r.drive.set_torque(math.nan)


def test_the_velocity_is_the_filtered_derivative_of_the_angle_not_the_rpm_field(rig):
    r = rig(wheel=Wheel(k_hand=0.0, b_hand=2.0))
    r.drive.enable()
    run(r.drive, 1500, 0.1)  # settles at 0.05 rad/s: under one rpm step (0.105 rad/s)
    velocities = []
    for _ in range(500):
        run(r.drive, 1, 0.1)
        velocities.append(r.drive.read().velocity_rad_s)
    assert np.mean(velocities) == pytest.approx(0.05, rel=0.01)
    assert np.std(velocities) < 0.1 * 0.105  # the angle's 0.009° steps, filtered


# -- the cycle -----------------------------------------------------------------------------------


def paced_run(r: Rig, cycles: int) -> int:
    """``cycles`` at 1 kHz on the wall clock; how many started more than a period late."""
    t0 = time.perf_counter()
    late = 0
    for i in range(cycles):
        due = t0 + i * DT
        while (now := time.perf_counter()) < due:
            if due - now > 3e-4:
                time.sleep(1e-4)
        late += now - due > DT
        r.drive.set_torque(0.5 * math.sin(2 * math.pi * 1.0 * i * DT))
        r.drive.sync()
    return late


def test_a_1khz_loop_of_2000_cycles_misses_no_reply(rig):
    # In-process, the simulated drive shares the test's CPU: a loaded 2-core machine can hold
    # an answer beyond the timeout now and then (the most the config allows below the 1 ms
    # period is used). Five tries: the claim is that the driver keeps up, not that every run
    # on a busy machine is scheduled in time.
    for _attempt in range(5):
        r = rig(sensor={"source": "hand_sensor"}, reply_timeout_ms=0.95)
        r.drive.set_wheel(4.2, 2.0)
        r.drive.enable()
        late = paced_run(r, 2000)
        status = r.drive.status()
        if status["missed_replies"] == 0 and status["missed_hand_sensor_replies"] == 0:
            break
    else:
        _too_busy(status)
    assert status["missed_replies"] == 0, status
    assert status["missed_hand_sensor_replies"] == 0, status
    assert status["late_replies"] == 0 and status["unsolicited_replies"] == 0, status
    assert r.drive.problem() is None
    assert r.node.status()["enabled_cycles"] == 2000
    assert r.node.status()["requests"]["0x200"] >= 2000 // 10  # the state poll
    assert late < 20


# -- stopping ------------------------------------------------------------------------------------


def test_disable_ends_off_with_zero_fields_and_forgets_the_wheel(rig):
    r = rig(friction_nm=0.05)
    r.drive.set_wheel(4.2, 2.0)
    r.drive.enable()
    run(r.drive, 20, 1.0)
    r.drive.disable()
    r.drive.disable()  # repeatable
    assert wait_for(lambda: r.node.status()["state"] == "off")
    assert set(r.node.status()["last_command"].values()) == {0.0}
    assert r.node.status()["applied_torque_nm"] == 0.0
    # enabled again without set_wheel: no spring, no damper
    r.drive.enable()
    run(r.drive, 2, 0.0)
    sent = r.node.status()["last_command"]
    assert sent["stiffness_nm_per_rad"] == sent["damping_nms_per_rad"] == 0.0


def test_disable_from_another_thread_while_the_loop_runs(rig):
    r = rig()
    r.drive.enable()
    stop = threading.Event()

    def loop():
        while not stop.is_set():
            r.drive.set_torque(1.0)
            r.drive.sync()

    t = threading.Thread(target=loop)
    t.start()
    time.sleep(0.05)
    t0 = time.perf_counter()
    r.drive.disable()
    took = time.perf_counter() - t0
    time.sleep(0.02)
    stop.set()
    t.join(1.0)
    assert took < 0.01
    assert wait_for(lambda: r.node.status()["state"] == "off")
    assert r.node.status()["last_command"]["torque_nm"] == 0.0
    assert r.drive.problem() is None


def test_quick_stop_switches_off_at_once(rig):
    r = rig()
    r.drive.enable()
    run(r.drive, 10, 1.0)
    r.drive.quick_stop()
    assert wait_for(lambda: r.node.status()["state"] == "off")
    assert r.node.status()["applied_torque_nm"] == 0.0
    assert not r.drive.enabled


def test_close_disables_and_never_raises(rig):
    r = rig()
    r.drive.enable()
    run(r.drive, 5, 1.0)
    r.drive.close()
    r.drive.close()
    assert wait_for(lambda: r.node.status()["state"] == "off")


# -- faults --------------------------------------------------------------------------------------


def test_a_silent_drive_is_reported_after_max_missed_replies(rig):
    r = rig(max_missed_replies=5)
    r.drive.enable()
    r.node.inject("go_silent")
    run(r.drive, 5)
    assert r.drive.problem() is None  # five in a row are tolerated
    run(r.drive, 1)
    assert r.drive.problem() == (
        "SensoDrive: no answer to 0x201 for 6 cycles in a row (timeout 0.8 ms)"
    )
    assert r.drive.status()["missed_replies"] == 6
    assert not r.drive.status()["drive_ok"]


def test_mute_replies_is_reported_as_missing_answers(rig):
    r = rig()
    r.drive.enable()
    run(r.drive, 10)
    r.node.inject("mute_replies")
    run(r.drive, 21)
    # The node's thread takes the injection in its own time: on a busy machine a cycle or two
    # after it may still be answered, and the count of misses in a row starts after them.
    for _ in range(20):
        if r.drive.problem() is not None:
            break
        run(r.drive, 1)
    assert r.drive.problem().startswith("SensoDrive: no answer to 0x201 for 21 cycles in a row")


def test_the_error_state_is_reported_within_a_state_poll(rig):
    r = rig(state_poll_cycles=5)
    r.drive.enable()
    run(r.drive, 3)
    r.node.inject("error")
    run(r.drive, 5)
    assert wait_for(lambda: r.drive.problem() is not None, 0.1)
    assert r.drive.problem() == "SensoDrive reports its error state (0x18), error bytes 0x0000"
    assert not r.drive.enabled  # the driver stops commanding torque
    assert r.drive.status()["drive_state"] == "error"
    run(r.drive, 1, 1.0)
    assert r.node.status()["last_command"]["torque_nm"] == 0.0


def test_the_drive_leaving_on_by_itself_is_reported(rig):
    r = rig(state_poll_cycles=5)
    r.drive.enable()
    run(r.drive, 3)
    send_state(r.config.channel, Command.OFF)
    run(r.drive, 5)
    assert wait_for(lambda: r.drive.problem() is not None, 0.1)
    assert r.drive.problem() == "SensoDrive left ON by itself: state OFF (0x10)"


def test_a_dropped_bus_is_reported(rig):
    r = rig()
    r.drive.enable()
    run(r.drive, 5)
    r.drive.drop_bus()
    run(r.drive, 1)
    problem = r.drive.problem()
    assert problem is not None
    assert "SensoDrive: CAN frame not sent: 0x201" in problem or "receive thread" in problem
    assert wait_for(lambda: any("receive thread stopped" in f for f in r.drive.status()["faults"]))
    r.drive.disable()  # never raises, on a dead bus either
    r.drive.quick_stop()


def test_enable_clears_the_faults_of_the_last_trial(rig):
    r = rig(max_missed_replies=2)
    r.drive.enable()
    r.node.inject("mute_replies")
    run(r.drive, 3)
    assert r.drive.problem() is not None
    r.drive.disable()
    r.node._mute_replies = False  # the cause is gone (a test-only shortcut)
    r.drive.enable()
    run(r.drive, 3)
    assert r.drive.problem() is None
    assert len(r.drive.faults) == 1  # the history keeps it


# -- the driver torque ---------------------------------------------------------------------------


def multisine(i: int, amplitude=1.0) -> float:
    t = i * DT
    return amplitude * sum(
        math.sin(2 * math.pi * f * t + p) / n
        for n, (f, p) in enumerate(((0.3, 0.0), (1.1, 1.0), (2.3, 2.0), (4.7, 0.5)), start=1)
    )


@pytest.mark.parametrize("sign", [-1, 1])
def test_the_hand_sensor_reads_the_plants_column_torque(rig, sign):
    r = rig(sensor={"source": "hand_sensor"}, sign=sign, unhurried=True)
    r.drive.set_wheel(1.0, 0.5)
    r.drive.enable()
    errors, truth = [], []
    for i in range(1500):
        missed = r.drive.status()["missed_hand_sensor_replies"]
        r.drive.set_torque(multisine(i, 2.0))
        r.drive.sync()
        truth.append(r.wheel.read()[3])
        if r.drive.status()["missed_hand_sensor_replies"] == missed:  # a fresh value
            errors.append(r.drive.torque_sensor.read() - truth[-1])
    assert len(errors) > 1400
    # one count (10/2048 V) on each voltage: 0.036 N·m at the sensor's 0.135 V/N·m
    assert np.max(np.abs(errors)) < 0.037
    assert np.std(truth) > 0.3  # the test did push the hand


def test_the_rim_above_the_hand_sensor_is_taken_off_as_its_inertia_torque(rig):
    """The sensor carries the torque that accelerates the rim too: the driver torque is the
    sensor's minus J_rim·θ̈ (the simulated sensor reports the hand's torque: the difference is
    exactly that term)."""
    for _attempt in range(3):  # until a run has every answer in time (a busy machine)
        r = rig(sensor={"source": "hand_sensor", "rim_inertia_kgm2": 0.05}, unhurried=True)
        r.drive.enable()
        accel = LowPassDerivatives(50.0, DT, order=4)
        diffs, acc = [], []
        for i in range(2000):
            r.drive.set_torque(multisine(i, 2.0))
            r.drive.sync()
            diffs.append(r.drive.torque_sensor.read() - r.wheel.read()[3])
            acc.append(accel.step(r.drive.read().angle_rad)[2])
        status = r.drive.status()
        if status["missed_replies"] == status["missed_hand_sensor_replies"] == 0:
            break
    else:
        _too_busy(status)
    diffs, acc = np.array(diffs)[200:], np.array(acc)[200:]
    assert np.dot(diffs, acc) / np.dot(acc, acc) == pytest.approx(-0.05, rel=0.05)


def test_zero_removes_the_offset_of_the_cycles_just_run(rig):
    r = rig(sensor={"source": "hand_sensor"}, wheel=Wheel(k_hand=5.0, b_hand=1.0))
    sensor = r.drive.torque_sensor
    with pytest.raises(DriveError, match="zero"):
        sensor.zero()
    r.drive.enable()
    run(r.drive, 300, 0.5)  # the wheel pushes the hand with about 0.5 N·m
    sensor.clear_recent()
    truth = []
    for _ in range(300):
        run(r.drive, 1, 0.5)
        truth.append(r.wheel.read()[3])
    sensor.zero()
    assert sensor.offset_nm == pytest.approx(np.mean(truth), abs=0.01)  # 300 counts averaged
    assert sensor.read() == pytest.approx(truth[-1] - sensor.offset_nm, abs=0.037)


def reconstruction_run(rig, filter_hz: float, model_inertia: float, cycles=4000):
    """:func:`one_reconstruction_run` until one has every answer in time (up to three tries:
    the simulated drive shares a possibly busy test machine's CPU; a reply that misses its
    cycle costs the filters a sample, which is not what these tests measure)."""
    for _attempt in range(3):
        result, status = one_reconstruction_run(rig, filter_hz, model_inertia, cycles)
        if status["missed_replies"] == status["late_replies"] == 0:
            return result
    _too_busy(status)


def one_reconstruction_run(rig, filter_hz: float, model_inertia: float, cycles: int):
    """A wheel of 0.3 kg·m² with its own friction and imbalance, which the rig file knows, held
    by a spring-damper hand, under a multisine; the drive renders the Pronker spring and damper
    and a friction field. Returns (reconstruction, true driver torque, the truth through the
    reconstruction's low-pass, the filtered θ̈ of the reported angle), the start cut off, and
    the driver's status."""
    wheel = Wheel(inertia=0.3, k_hand=5.0, b_hand=1.0, coulomb=0.1, gravity=0.3)
    sensor = {
        "source": "reconstructed",
        "inertia_kgm2": model_inertia,
        "coulomb_nm": 0.1,
        "gravity_nm": 0.3,
        "filter_hz": filter_hz,
    }
    r = rig(wheel=wheel, sensor=sensor, friction_nm=0.05, unhurried=True)
    r.drive.set_wheel(4.2, 2.0)
    r.drive.enable()
    accel = LowPassDerivatives(filter_hz, DT, order=4)
    recon, truth, acc = [], [], []
    for i in range(cycles):
        r.drive.set_torque(multisine(i, 3.0))
        r.drive.sync()
        recon.append(r.drive.torque_sensor.read())
        truth.append(r.wheel.read()[3])
        acc.append(accel.step(r.drive.read().angle_rad)[2])
    # the truth (a sampled continuous signal) through the same 4th-order Butterworth, by
    # scipy's first-order-hold discretization
    b, a = signal.butter(4, 2 * math.pi * filter_hz, analog=True)
    bd, ad, _ = signal.cont2discrete((b, a), DT, method="foh")
    filtered = signal.lfilter(bd.ravel(), ad, truth)
    cut = 500
    return [np.array(x)[cut:] for x in (recon, truth, filtered, acc)], r.drive.status()


@pytest.mark.parametrize(("filter_hz", "noise_limit_nm"), [(20.0, 0.05), (40.0, 0.2)])
def test_the_reconstruction_is_the_true_driver_torque_through_its_filter(
    rig, filter_hz, noise_limit_nm
):
    """With the wheel model right, the reconstruction is the true driver torque through the
    filter H, up to the angle's 0.009° quantization, amplified in θ̈ (I·θ̈ noise grows as
    filter_hz^2.5), and the simulated plant's own Euler step."""
    recon, truth, filtered, _ = reconstruction_run(rig, filter_hz, 0.3)
    rms = float(np.sqrt(np.mean(truth**2)))
    err_h = float(np.sqrt(np.mean((recon - filtered) ** 2)))
    err_raw = float(np.sqrt(np.mean((recon - truth) ** 2)))
    print(
        f"\nreconstruction at {filter_hz:g} Hz: T_d rms {rms:.3f} N·m; error vs H·T_d "
        f"{err_h:.3f} N·m rms ({err_h / rms:.1%}), vs T_d {err_raw:.3f} N·m ({err_raw / rms:.1%})"
    )
    assert rms > 0.5
    assert err_h < noise_limit_nm
    assert abs(np.mean(recon - filtered)) < 0.01  # no bias: friction and gravity are modelled


def test_a_wrong_inertia_shows_up_as_its_torque(rig):
    """The model's errors go straight into the driver torque: ΔI·θ̈ for a wrong inertia."""
    recon, _, filtered, acc = reconstruction_run(rig, 20.0, 0.25)
    error = recon - filtered
    slope = float(np.dot(error, acc) / np.dot(acc, acc))
    assert slope == pytest.approx(0.3 - 0.25, rel=0.1)


@pytest.mark.parametrize("order", [2, 4])
def test_the_low_pass_derivatives_of_a_sampled_sine_are_the_continuous_filters(order):
    f = LowPassDerivatives(40.0, DT, order=order)
    w = 2 * math.pi * 5.0
    t = np.arange(3000) * DT
    out = np.array([f.step(v) for v in np.sin(w * t)])[1000:]
    h = f.response(5.0)
    phase = w * t[1000:] + np.angle(h)
    expected = abs(h) * np.stack([np.sin(phase), w * np.cos(phase), -w * w * np.sin(phase)], 1)
    relative = np.max(np.abs(out - expected), axis=0) / (abs(h) * np.array([1.0, w, w * w]))
    assert np.all(relative < [1e-4, 1e-4, 1e-2]), relative  # θ̈: a sine is not linear in between
    assert abs(f.response(0.0)) == pytest.approx(1.0)
    assert abs(f.response(40.0)) == pytest.approx(1 / math.sqrt(2))


@pytest.mark.parametrize(("hold", "method"), [("step", "zoh"), ("linear", "foh")])
@pytest.mark.parametrize("order", [2, 4])
def test_the_low_pass_is_scipys_discretization_of_the_butterworth_filter(hold, method, order):
    f = LowPassDerivatives(40.0, DT, hold=hold, order=order)
    u = np.random.default_rng(0).normal(size=500)
    u[0] = 0.0
    ours = np.array([f.step(v)[0] for v in u])
    b, a = signal.butter(order, 2 * math.pi * 40.0, analog=True)
    bd, ad, _ = signal.cont2discrete((b, a), DT, method=method)
    theirs = signal.lfilter(bd.ravel(), ad, u)
    if hold == "step":  # ours: after the interval the sample is held over
        theirs = signal.lfilter(bd.ravel(), ad, np.append(u, 0.0))[1:]
    assert np.max(np.abs(ours - theirs)) < 1e-9
