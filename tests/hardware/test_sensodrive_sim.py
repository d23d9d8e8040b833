"""The simulated SENSO-Wheel, probed by a host of the tests' own (``sensodrive_host``: struct
and the protocol notes, not Steerlab's codec or driver): the clients' enable sequences, the
drive-rendered spring and damper, directions, limits, the hand sensor, watchdog and faults."""

from __future__ import annotations

import math
import subprocess
import sys
import time
import uuid

import can
import pytest

from steerlab.hardware.can.sensodrive_sim import (
    END_STOP_STIFFNESS_NM_PER_RAD,
    SimulatedSensoDrive,
)
from tests.hardware.sensodrive_host import (
    CLEAR_ERROR,
    ERROR,
    KEEP,
    OFF,
    ON,
    READY,
    VOLTS_PER_COUNT,
    Host,
    jd_hand_torque,
    sensor_volts_per_nm,
)

DT = 1e-3
NO_REPLY_S = 0.05  # how long a test waits before calling a request unanswered


class Wheel:
    """A wheel of inertia 0.3 kg·m² with an optional spring-damper hand (Steerlab's
    direction); column torque = the torque the wheel exerts on the hand, plus an offset."""

    def __init__(self, inertia=0.3, k_hand=0.0, b_hand=0.0, offset_nm=0.0):
        self.j, self.k, self.b, self.offset = inertia, k_hand, b_hand, offset_nm
        self.angle = self.velocity = self.motor = 0.0
        self.steps = 0

    def hand_torque(self) -> float:
        return -(self.k * self.angle + self.b * self.velocity)

    def step(self, motor_torque_nm: float) -> None:
        self.motor = motor_torque_nm
        self.velocity += (motor_torque_nm + self.hand_torque()) / self.j * DT
        self.angle += self.velocity * DT
        self.steps += 1

    def read(self) -> tuple[float, float, float, float]:
        return self.angle, self.velocity, self.motor, -self.hand_torque() + self.offset


@pytest.fixture
def rig():
    """``make(**kwargs)`` → (node, host, wheel) on a fresh virtual channel."""
    made: list[tuple[SimulatedSensoDrive, can.BusABC, can.BusABC]] = []

    def make(wheel: Wheel | None = None, **kwargs):
        channel = f"senso-{uuid.uuid4()}"
        node_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        host_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        wheel = wheel or Wheel()
        node = SimulatedSensoDrive(node_bus, wheel, **kwargs)
        node.start()
        made.append((node, node_bus, host_bus))
        return node, Host(host_bus), wheel

    yield make
    for node, node_bus, host_bus in made:
        node.close()
        node_bus.shutdown()
        host_bus.shutdown()


def enable(host: Host, **limits) -> None:
    assert host.state(OFF, **limits) == OFF
    assert host.state(READY, **limits) == READY
    assert host.state(ON, **limits) == ON


# -- states --------------------------------------------------------------------------------------


def test_joan_sequence_reaches_on_and_back_to_off(rig):
    node, host, _ = rig()
    assert host.state(KEEP) == OFF
    assert host.state(KEEP) == OFF
    for command, state in [(OFF, OFF), (READY, READY), (ON, ON), (ON, ON)]:
        assert host.state(command) == state
    assert node.status()["state"] == "on"
    assert host.state(READY) == READY
    assert host.state(OFF) == OFF
    s = node.status()
    assert s["state"] == "off"
    assert s["requests"]["0x200"] == 8


def test_lflipse_sequence_reaches_on_and_ends_with_clear_error(rig):
    node, host, _ = rig()
    for command, state in [(CLEAR_ERROR, OFF), (READY, READY), (ON, ON)]:
        assert host.state(command, 10313, 120, 100) == state
    assert node.status()["end_stop_deg"] == 10313
    assert node.status()["torque_limits_percent"] == (120, 100)
    for command, state in [(ON, ON), (READY, READY), (CLEAR_ERROR, OFF)]:
        assert host.state(command, 10313, 120, 100) == state


def test_on_from_off_is_refused(rig):
    node, host, _ = rig()
    assert host.state(ON) == OFF
    assert host.state(CLEAR_ERROR) == OFF
    assert host.state(ON) == OFF
    host.wheel(torque_nm=1.0)
    assert node.status()["applied_torque_nm"] == 0.0


def test_the_wheel_command_is_answered_in_every_state_and_steps_the_plant_once(rig):
    node, host, wheel = rig()
    assert host.wheel(torque_nm=1.0) == (0.0, 0.0, 0.0)  # OFF: answered, no torque
    assert wheel.steps == 1
    enable(host)
    host.wheel()
    assert wheel.steps == 2
    s = node.status()
    assert s["enabled_cycles"] == 1
    assert s["requests"]["0x201"] == 2


# -- rendering -----------------------------------------------------------------------------------


def test_a_released_wheel_settles_as_the_rendered_spring_and_damper_say(rig):
    node, host, wheel = rig(sign=-1)
    enable(host)
    theta0 = 0.5
    wheel.angle = theta0
    # what the fields render after the clients' truncation: 73 mN·m/deg, 209 mN·m/rpm
    k = 73 * 180 / math.pi / 1000
    b = 209 * 60 / (2 * math.pi) / 1000
    wn = math.sqrt(k / 0.3)
    zeta = b / (2 * math.sqrt(k * 0.3))
    wd = wn * math.sqrt(1 - zeta**2)
    worst = 0.0
    for n in range(1, 1501):
        reply = host.wheel(damping_nms_per_rad=2.0, stiffness_nm_per_rad=4.2)
        assert reply is not None
        t = n * DT
        expected = math.exp(-zeta * wn * t) * (
            theta0 * math.cos(wd * t) + zeta * wn * theta0 / wd * math.sin(wd * t)
        )
        worst = max(worst, abs(-reply[0] - expected))  # the drive's angle is −Steerlab's
    assert worst < 0.004 * theta0  # the sampled simulation vs the continuous solution
    assert abs(wheel.angle) < 0.01 and abs(wheel.velocity) < 0.05
    assert node.status()["enabled_cycles"] == 1500


def test_a_positive_steerlab_torque_goes_out_negative_and_turns_the_wheel_positive(rig):
    node, host, wheel = rig(sign=-1)
    enable(host)
    steerlab_torque = 1.0
    for _ in range(50):
        reply = host.wheel(torque_nm=-1 * steerlab_torque)  # drive value = sign × Steerlab
    assert reply is not None
    angle, rate, torque = reply
    assert wheel.angle > 0 and wheel.velocity > 0
    assert angle < 0 and rate < 0
    assert torque == pytest.approx(-1.0)
    assert wheel.motor == pytest.approx(1.0)
    assert node.status()["applied_torque_nm"] == pytest.approx(1.0)
    assert node.status()["last_command"]["torque_nm"] == pytest.approx(-1.0)


def test_with_sign_plus_one_the_directions_agree(rig):
    _, host, wheel = rig(sign=1)
    enable(host)
    for _ in range(20):
        angle, _, torque = host.wheel(torque_nm=0.5)
    assert wheel.angle > 0 and angle > 0 and torque == pytest.approx(0.5)


def test_friction_opposes_the_motion(rig):
    _, host, wheel = rig(sign=-1)
    enable(host)
    wheel.velocity = 1.0  # Steerlab; −1 rad/s for the drive
    _, _, torque = host.wheel(friction_nm=0.5)
    assert torque == pytest.approx(0.5, abs=1e-3)  # drive direction: against its −1 rad/s
    assert wheel.motor == pytest.approx(-0.5, abs=1e-3)
    wheel.velocity = 0.0
    _, _, torque = host.wheel(friction_nm=0.5)
    assert torque == 0.0  # at rest: no torque out of nothing


def test_the_limit_bytes_clamp_the_torque(rig):
    node, host, wheel = rig(sign=1, full_scale_torque_nm=10.0)
    enable(host, limit_pct=10, beyond_pct=50)
    _, _, torque = host.wheel(torque_nm=5.0)
    assert torque == pytest.approx(1.0)  # 10 % of 10 N·m
    _, _, torque = host.wheel(torque_nm=-5.0)
    assert torque == pytest.approx(-1.0)
    assert node.status()["applied_torque_nm"] == pytest.approx(-1.0)


def test_beyond_the_end_stop_a_stiff_spring_pushes_back_up_to_its_limit(rig):
    node, host, wheel = rig(sign=1, full_scale_torque_nm=10.0)
    enable(host, end_stop_deg=10, limit_pct=200, beyond_pct=200)
    wheel.angle = math.radians(10.5)
    _, _, torque = host.wheel()
    expected = -END_STOP_STIFFNESS_NM_PER_RAD * math.radians(0.5)
    assert torque == pytest.approx(expected, abs=2e-3)
    assert host.state(ON, end_stop_deg=10, limit_pct=200, beyond_pct=30) == ON
    wheel.angle, wheel.velocity = math.radians(-40), 0.0
    _, _, torque = host.wheel()
    assert torque == pytest.approx(3.0)  # 30 % of 10 N·m, pushing back towards the centre


def test_the_angle_is_on_the_0_009_degree_grid(rig):
    _, host, wheel = rig(sign=-1)
    for angle in (0.0, 1e-5, 0.123456, -2.5, 7.0, -20.0):
        wheel.angle = angle
        increments, _, _ = host.wheel_raw()
        assert abs(increments * 0.009 - math.degrees(-angle)) <= 0.0045 + 1e-9


# -- the optional sensors ------------------------------------------------------------------------


@pytest.mark.parametrize("sign", [-1, 1])
def test_the_hand_sensor_decodes_to_the_column_torque_by_jds_formula(rig, sign):
    wheel = Wheel(k_hand=5.0, b_hand=1.0, offset_nm=0.05)
    node, host, wheel = rig(wheel, sign=sign, hand_sensor_v_per_nm=sensor_volts_per_nm())
    one_count_nm = VOLTS_PER_COUNT / abs(sensor_volts_per_nm())
    for angle in (0.0, 0.3, -0.7, 1.5):
        wheel.angle = angle
        host.wheel()
        u_a, u_b = host.hand_sensor()
        assert (u_a + u_b) / 2 == pytest.approx(2.5, abs=VOLTS_PER_COUNT)
        column = wheel.read()[3]
        # J-D's formula: the hands' torque on the wheel, minus the wheel's on the hands
        assert abs(jd_hand_torque(u_a, u_b) - sign * -column) <= one_count_nm
    assert node.status()["requests"]["0x20A"] == 4


def test_without_a_hand_sensor_its_request_is_not_answered(rig):
    _, host, _ = rig()
    assert host.hand_sensor(timeout=NO_REPLY_S) is None
    assert host.state(KEEP) == OFF  # and the node still answers the rest


def test_the_pedals_are_at_rest(rig):
    _, host, _ = rig()
    assert host.pedals() == (1100, 1)


# -- watchdog ------------------------------------------------------------------------------------


def test_without_a_watchdog_the_torque_stays_when_the_host_goes_quiet(rig):
    node, host, _ = rig(sign=1)
    enable(host)
    host.wheel(torque_nm=0.5)
    time.sleep(0.2)
    s = node.status()
    assert s["state"] == "on" and s["applied_torque_nm"] == pytest.approx(0.5)
    assert s["watching_host"] is False


def test_the_watchdog_cuts_the_torque_and_goes_to_error(rig):
    node, host, _ = rig(sign=1, watchdog_s=0.05)
    enable(host)
    host.wheel(torque_nm=0.5)
    assert node.status()["zero_torque_since"] is None
    before = time.monotonic()
    time.sleep(0.2)
    s = node.status()
    assert s["watching_host"] is True
    assert s["state"] == "error" and s["applied_torque_nm"] == 0.0
    assert s["zero_torque_since"] > before + 0.04  # ~0.05 s after the last frame
    assert host.wheel(torque_nm=0.5)[2] == 0.0
    assert host.state(ON) == ERROR
    assert host.state(CLEAR_ERROR) == OFF


def test_the_watchdog_stays_quiet_while_the_host_keeps_sending(rig):
    node, host, _ = rig(sign=1, watchdog_s=0.05)
    enable(host)
    end = time.monotonic() + 0.2
    while time.monotonic() < end:
        host.wheel(torque_nm=0.5)
        time.sleep(0.005)
    assert node.status()["state"] == "on"


# -- faults --------------------------------------------------------------------------------------


def test_an_unknown_fault_is_refused_with_the_known_ones(rig):
    node, _, _ = rig()
    with pytest.raises(ValueError, match="go_silent, error, mute_replies"):
        node.inject("explode")


def test_go_silent_answers_nothing_and_its_watchdog_still_runs(rig):
    node, host, wheel = rig(sign=1, watchdog_s=0.05)
    enable(host)
    host.wheel(torque_nm=0.5)
    node.inject("go_silent")
    assert host.state(KEEP, timeout=NO_REPLY_S) is None
    assert host.wheel(torque_nm=0.5, timeout=NO_REPLY_S) is None
    assert wheel.steps == 1  # it did not hear the second 0x201
    time.sleep(0.1)
    s = node.status()
    assert s["state"] == "error" and s["applied_torque_nm"] == 0.0


def test_an_injected_error_cuts_the_torque_until_cleared(rig):
    node, host, _ = rig(sign=1)
    enable(host)
    host.wheel(torque_nm=0.5)
    node.inject("error")
    assert node.status()["applied_torque_nm"] == 0.0
    assert host.state(KEEP) == ERROR
    assert host.wheel(torque_nm=0.5)[2] == 0.0
    assert host.state(READY) == ERROR
    assert host.state(ON) == ERROR
    assert host.state(CLEAR_ERROR) == OFF
    enable(host)
    assert host.wheel(torque_nm=0.5)[2] == pytest.approx(0.5)


def test_mute_replies_keeps_applying_the_commands(rig):
    node, host, wheel = rig(sign=1)
    enable(host)
    node.inject("mute_replies")
    assert host.wheel(torque_nm=0.5, timeout=NO_REPLY_S) is None
    assert wheel.steps == 1 and wheel.motor == pytest.approx(0.5)
    assert node.status()["applied_torque_nm"] == pytest.approx(0.5)
    assert host.state(READY) == READY  # state commands are still answered
    assert node.status()["applied_torque_nm"] == 0.0


def test_malformed_frames_are_counted_and_not_answered(rig):
    node, host, _ = rig()
    assert host.request(0x201, bytes(7), timeout=NO_REPLY_S) is None
    assert host.request(0x200, bytes([0x02, 0, 0x68, 1, 0, 0, 200, 200]), NO_REPLY_S) is None
    assert host.request(0x20C, bytes(2), timeout=NO_REPLY_S) is None
    assert host.request(0x200, bytes(3), timeout=NO_REPLY_S) is None
    errors = node.status()["errors"]
    assert len(errors) == 4
    assert any("0x02" in e for e in errors)
    assert host.state(KEEP) == OFF  # the reader thread is alive


# -- across processes ----------------------------------------------------------------------------

CHILD = """
import sys
from steerlab.hardware.can.udp_bus import UdpLoopbackBus
from steerlab.hardware.can.sensodrive_sim import SimulatedSensoDrive

class Wheel:
    angle = velocity = motor = 0.0
    def step(self, torque):
        self.motor = torque
        self.velocity += torque / 0.3 * 1e-3
        self.angle += self.velocity * 1e-3
    def read(self):
        return self.angle, self.velocity, self.motor, 0.0

bus = UdpLoopbackBus(sys.argv[1])
node = SimulatedSensoDrive(bus, Wheel(), sign=-1)
node.start()
print("ready", flush=True)
sys.stdin.read()
print(node.status()["enabled_cycles"], flush=True)
node.close()
bus.shutdown()
"""


def test_across_processes_on_udp_loopback():
    from steerlab.hardware.can.udp_bus import UdpLoopbackBus

    channel = f"senso-{uuid.uuid4()}"
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, channel],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    bus = UdpLoopbackBus(channel)
    try:
        assert child.stdout.readline().strip() == "ready"
        host = Host(bus, timeout=1.0)
        assert host.state(CLEAR_ERROR) == OFF
        assert host.state(READY) == READY
        assert host.state(ON) == ON
        for _ in range(100):
            angle, _, torque = host.wheel(torque_nm=-0.3)  # +0.3 N·m for Steerlab
        assert angle < 0 and torque == pytest.approx(-0.3)
        assert host.state(READY) == READY
        out, _ = child.communicate("", timeout=10)
        assert out.strip() == "100"
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        bus.shutdown()
