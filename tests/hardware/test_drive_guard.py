"""The drive protects the person without the host: CiA 301 consumer heartbeat (0x1016) of the
host, and the CiA 402 abort connection option (0x6007).

First with canopen's own master and heartbeat producer (not our driver) against the simulated
drive, then with our driver: the bus-off of the host's bus and a silent link end with zero torque
*at the drive*, whatever the host does afterwards.
"""

from __future__ import annotations

import math
import time
import uuid
from dataclasses import replace

import can
import canopen
import pytest
from canopen.objectdictionary import ObjectDictionary

from steerlab.hardware.can import CiA402Drive, ConfigError, SimulatedDrive, State402, startup_writes
from tests.hardware.can_wire import node5_config, wait_for

HOST = 127
MARGIN_S = 0.4  # generous: a loaded test machine; timing goals are in benchmarks/faults.py


class Wheel:
    """Inertia on the motor shaft, so that a torque left on moves the wheel."""

    def __init__(self) -> None:
        self.angle = self.velocity = self.torque = 0.0

    def step(self, motor_torque_nm: float) -> None:
        self.torque = motor_torque_nm
        self.velocity += motor_torque_nm / 0.3 * 1e-3
        self.angle += self.velocity * 1e-3

    def read(self) -> tuple[float, float, float, float]:
        return self.angle, self.velocity, self.torque, 0.0


@pytest.fixture
def canopen_rig():
    """The simulated drive (node 5), canopen's master for it, and canopen's LocalNode as the
    host producing its heartbeat."""
    channel = f"guard-{uuid.uuid4()}"
    cfg = node5_config(channel)
    drive_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    sim = SimulatedDrive(drive_bus, cfg, Wheel())
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    remote = network.add_node(5, ObjectDictionary())
    remote.sdo.RESPONSE_TIMEOUT = 2.0  # a loaded test machine, not a slow drive
    host = canopen.LocalNode(HOST, ObjectDictionary())
    network.add_node(host)
    yield sim, remote, host, network
    host.nmt.stop_heartbeat()
    network.disconnect()
    sim.close()
    drive_bus.shutdown()
    assert sim.errors == []


def _enable_at_torque(remote, network, sim, permille: int) -> None:
    """Configure and enable the drive with canopen's SDO client and NMT master; the torque is
    applied at the next SYNC."""
    remote.sdo.download(0x6060, 0, b"\x0a")
    remote.sdo.download(0x6071, 0, permille.to_bytes(2, "little", signed=True))
    remote.nmt.send_command(0x01)  # start
    for cw in (0x06, 0x07, 0x0F):
        remote.sdo.download(0x6040, 0, cw.to_bytes(2, "little"))
    network.send_message(0x080, b"")  # SYNC
    assert wait_for(lambda: sim.applied_torque_nm != 0.0)


@pytest.mark.parametrize(
    ("option", "state"),
    [
        (1, State402.FAULT),
        (2, State402.SWITCH_ON_DISABLED),
        (3, State402.QUICK_STOP_ACTIVE),
        (0, State402.OPERATION_ENABLED),  # "no action": the drive holds the torque
    ],
)
def test_lost_host_heartbeat_reaction_per_abort_connection_option(canopen_rig, option, state):
    sim, remote, host, network = canopen_rig
    remote.sdo.download(0x6007, 0, option.to_bytes(2, "little", signed=True))
    remote.sdo.download(0x1016, 1, ((HOST << 16) | 50).to_bytes(4, "little"))  # 50 ms
    host.nmt.state = "OPERATIONAL"
    host.nmt.start_heartbeat(10)
    _enable_at_torque(remote, network, sim, 200)  # 20 % of 10 N·m, gear 2, sign −1
    assert sim.applied_torque_nm == pytest.approx(-4.0)
    time.sleep(0.3)  # six times the consumer time: a host that beats is not lost
    assert sim.state is State402.OPERATION_ENABLED and sim.host_heartbeats_lost == 0

    host.nmt.stop_heartbeat()
    t_stop = time.monotonic()
    # canopen's EMCY consumer decodes the drive's report: 0x8130, heartbeat error
    emcy = remote.emcy.wait(0x8130, timeout=2.0)
    assert emcy is not None and emcy.register & 0x11 == 0x11
    assert sim.host_heartbeats_lost == 1
    assert sim.connection_lost_at - t_stop < 0.05 + MARGIN_S
    assert sim.state is state
    if option == 0:
        assert sim.applied_torque_nm == pytest.approx(-4.0)  # why the driver must set 0x6007
        return
    assert sim.applied_torque_nm == 0.0
    # not before the consumer time after the last heartbeat (sent ≤ 10 ms before the stop)
    assert 0.05 - 0.015 <= sim.zero_torque_since - t_stop < 0.05 + MARGIN_S
    network.send_message(0x080, b"")  # a SYNC afterwards does not bring the torque back
    time.sleep(0.05)
    assert sim.applied_torque_nm == 0.0


def test_a_host_that_never_beat_is_not_watched(canopen_rig):
    """CiA 301: the consumer starts monitoring at the first heartbeat after its configuration."""
    sim, remote, host, network = canopen_rig
    remote.sdo.download(0x6007, 0, b"\x02\x00")
    remote.sdo.download(0x1016, 1, ((HOST << 16) | 50).to_bytes(4, "little"))
    _enable_at_torque(remote, network, sim, 100)
    time.sleep(0.2)
    assert sim.state is State402.OPERATION_ENABLED and sim.host_heartbeats_lost == 0


@pytest.fixture
def our_rig():
    """Our driver (with its own heartbeat producer) and the simulated drive."""
    channel = f"guard-{uuid.uuid4()}"
    cfg = node5_config(channel, loop_rate_hz=1000.0, tpdo_timeout_ms=0.9)
    host_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    drive_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    sim = SimulatedDrive(drive_bus, cfg, Wheel())
    drive = CiA402Drive(host_bus, cfg)
    drive.enable()
    assert sim.watching_host  # from the end of enable() on, before any torque
    for _ in range(5):
        drive.set_torque(2.0)
        drive.sync()
    assert wait_for(lambda: sim.applied_torque_nm == pytest.approx(2.0))
    yield drive, sim, host_bus, cfg
    drive.close()
    sim.close()
    for b in (host_bus, drive_bus):
        b.shutdown()


def test_our_driver_configures_the_guard(our_rig):
    _, sim, _, cfg = our_rig
    assert sim.od_value(0x6007) == 2
    assert sim.od_value(0x1016, 1) == (127 << 16) | cfg.host_heartbeat_timeout_ms
    time.sleep(0.3)  # our producer keeps the consumer fed
    assert sim.state is State402.OPERATION_ENABLED and sim.host_heartbeats_lost == 0


def test_bus_off_of_the_hosts_bus_leaves_zero_torque_at_the_drive(our_rig):
    drive, sim, host_bus, cfg = our_rig
    t_off = time.monotonic()
    host_bus.shutdown()  # nothing the host sends reaches the drive any more
    drive.set_torque(3.0)
    drive.sync()
    assert not drive.ok  # the host sees its bus fail …
    assert wait_for(lambda: sim.applied_torque_nm == 0.0, timeout=2.0)  # … the drive acts alone
    timeout_s = cfg.host_heartbeat_timeout_ms / 1000
    assert sim.zero_torque_since - t_off < timeout_s + MARGIN_S
    assert sim.state is State402.SWITCH_ON_DISABLED and sim.host_heartbeats_lost == 1


def test_silent_drive_link_leaves_zero_torque_at_the_drive(our_rig):
    drive, sim, _, cfg = our_rig
    t_cut = time.monotonic()
    sim.go_silent()  # the link is cut: the drive hears nothing and says nothing
    assert wait_for(lambda: sim.applied_torque_nm == 0.0, timeout=2.0)
    assert sim.zero_torque_since - t_cut < cfg.host_heartbeat_timeout_ms / 1000 + MARGIN_S
    assert sim.state is State402.SWITCH_ON_DISABLED
    for _ in range(30):  # the host meanwhile misses TPDOs and reports it
        drive.sync()
    assert not drive.ok and drive.consecutive_missed_tpdo >= 20


def test_startup_writes_name_the_host_and_its_timeout():
    cfg = node5_config("x", host_node_id=100, host_heartbeat_timeout_ms=90)
    writes = {(w.index, w.subindex): w for w in startup_writes(cfg)}
    assert writes[(0x1016, 1)].data == bytes([90, 0, 100, 0])
    assert writes[(0x6007, 0)].data == b"\x02\x00"
    assert writes[(0x6007, 0)].what.endswith("disable voltage")


@pytest.mark.parametrize(
    ("change", "field", "words"),
    [
        ({"host_heartbeat_timeout_ms": 150}, "host_heartbeat_timeout_ms", "1..100"),
        (
            {"host_heartbeat_ms": 50, "host_heartbeat_timeout_ms": 50},
            "host_heartbeat_timeout_ms",
            "longer than host_heartbeat_ms",
        ),
        ({"abort_connection_option": 0}, "abort_connection_option", "one of 1, 2, 3"),
        ({"host_node_id": 5}, "host_node_id", "differ from the drive"),
        ({"host_node_id": 128}, "host_node_id", "1..127"),
    ],
)
def test_guard_values_are_checked_at_load(change, field, words):
    with pytest.raises(ConfigError) as e:
        replace(node5_config("x"), **change, source="lab.toml")
    assert e.value.field == field and e.value.file == "lab.toml" and words in str(e.value)


def test_the_shipped_rig_asks_for_at_most_100_ms():
    from steerlab.hardware.rig import load_rig

    d = load_rig().drive
    assert d.host_heartbeat_timeout_ms <= 100 and d.abort_connection_option in (1, 2, 3)
    assert math.isclose(d.host_heartbeat_timeout_ms / d.host_heartbeat_ms, 4.0)
