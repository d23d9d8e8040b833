"""The simulated drive as a CANopen node, probed with canopen's own client (not our driver)."""

from __future__ import annotations

import math
import uuid

import can
import canopen
import pytest
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo import SdoAbortedError
from hypothesis import given, settings
from hypothesis import strategies as st

from steerlab.hardware.can import DriveConfig, SafetyConfig, SimulatedDrive, State402

NODE = 9


class StillPlant:
    def __init__(self) -> None:
        self.torques: list[float] = []

    def step(self, motor_torque_nm: float) -> None:
        self.torques.append(motor_torque_nm)

    def read(self) -> tuple[float, float, float, float]:
        return math.pi / 2, 0.0, self.torques[-1] if self.torques else 0.0, 0.0


def make_config(channel: str) -> DriveConfig:
    return DriveConfig(
        node_id=NODE,
        interface="virtual",
        channel=channel,
        bitrate=1_000_000,
        encoder_counts_per_rev=4096,
        rated_torque_nm=5.0,
        gear_ratio=1.0,
        sign=1,
        safety=SafetyConfig(4.0, 100.0, 360.0),
    )


@pytest.fixture
def node():
    channel = f"sim-{uuid.uuid4()}"
    cfg = make_config(channel)
    drive_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    monitor = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    plant = StillPlant()
    sim = SimulatedDrive(drive_bus, cfg, plant)
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05  # quick teardown
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    remote = network.add_node(NODE, ObjectDictionary())
    yield sim, remote, network, monitor, plant
    network.disconnect()
    sim.close()
    drive_bus.shutdown()
    monitor.shutdown()
    assert sim.errors == []


def frames(bus: can.BusABC, timeout: float = 0.02) -> list[tuple[int, bytes]]:
    out = []
    while (m := bus.recv(timeout)) is not None:
        out.append((m.arbitration_id, bytes(m.data)))
    return out


def u32(value: int) -> bytes:
    return value.to_bytes(4, "little")


def test_bootup_and_reset_node():
    channel = f"sim-{uuid.uuid4()}"
    monitor = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    drive_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    sim = SimulatedDrive(drive_bus, make_config(channel), StillPlant())
    try:
        assert frames(monitor) == [(0x709, b"\x00")]  # boot-up
        assert sim.nmt_state == 0x7F and sim.state is State402.SWITCH_ON_DISABLED
        monitor.send(can.Message(arbitration_id=0, data=[0x81, NODE], is_extended_id=False))
        assert frames(monitor) == [(0x709, b"\x00")]
        monitor.send(can.Message(arbitration_id=0, data=[0x81, NODE + 1], is_extended_id=False))
        assert frames(monitor) == []  # another node's reset
    finally:
        sim.close()
        monitor.shutdown()
        drive_bus.shutdown()


def test_only_cyclic_synchronous_torque_is_accepted(node):
    sim, remote, *_ = node
    with pytest.raises(SdoAbortedError) as info:
        remote.sdo.download(0x6060, 0, b"\x08")  # CSP
    assert info.value.code == 0x06090030
    remote.sdo.download(0x6060, 0, b"\x0a")
    assert remote.sdo.upload(0x6061, 0) == b"\x0a"


def test_pdo_mapping_rules_are_enforced(node):
    _, remote, *_ = node
    with pytest.raises(SdoAbortedError) as info:  # mapping entry while count != 0
        remote.sdo.download(0x1A00, 1, u32(0x60640020))
    assert info.value.code == 0x06010000
    with pytest.raises(SdoAbortedError) as info:  # count while the PDO is valid
        remote.sdo.download(0x1A00, 0, b"\x00")
        remote.sdo.download(0x1A00, 0, b"\x01")
    assert info.value.code == 0x06010000
    remote.sdo.download(0x1800, 1, u32(0x8000_0189))
    remote.sdo.download(0x1A00, 0, b"\x00")
    with pytest.raises(SdoAbortedError) as info:  # not mappable
        remote.sdo.download(0x1A00, 1, u32(0x10170010))
    assert info.value.code == 0x06040041
    with pytest.raises(SdoAbortedError) as info:  # wrong length
        remote.sdo.download(0x1A00, 1, u32(0x60640010))
    assert info.value.code == 0x06040041
    with pytest.raises(SdoAbortedError) as info:  # object does not exist
        remote.sdo.download(0x1A00, 1, u32(0x50000020))
    assert info.value.code == 0x06020000
    for sub in (1, 2, 3):
        remote.sdo.download(0x1A00, sub, u32(0x60640020))
    with pytest.raises(SdoAbortedError) as info:  # 96 bits
        remote.sdo.download(0x1A00, 0, b"\x03")
    assert info.value.code == 0x06040042


def test_pdos_only_in_operational_and_rpdo_timing_by_transmission_type(node):
    sim, remote, network, monitor, plant = node
    sync = can.Message(arbitration_id=0x80, is_extended_id=False)

    def pdos(*cob_ids: int) -> list[tuple[int, bytes]]:
        return [f for f in frames(monitor) if f[0] in cob_ids]

    frames(monitor)
    monitor.send(sync)
    assert [f for f in frames(monitor) if f[0] != 0x709] == []  # pre-operational: silent
    remote.nmt.send_command(0x01)
    # out of the box TPDO1 and TPDO2 are event-driven (255): they go out on entering
    # OPERATIONAL (and every 100 ms, their event timer)
    got = pdos(0x189, 0x289)
    assert got[:2] == [(0x189, bytes.fromhex("40 02")), (0x289, bytes.fromhex("40 02") + u32(1024))]
    monitor.send(sync)
    # TPDO3 (statusword) and TPDO4 (position) go out on every SYNC
    assert pdos(0x389, 0x489) == [(0x389, bytes.fromhex("40 02")), (0x489, u32(4096 // 4))]
    # default RPDO1 = controlword, asynchronous (255): it acts at once, and the event-driven
    # TPDO1 reports the new statusword without a SYNC
    monitor.send(can.Message(arbitration_id=0x209, data=b"\x06\x00", is_extended_id=False))
    got = pdos(0x189)
    assert sim.state is State402.READY_TO_SWITCH_ON
    assert got[0] == (0x189, bytes.fromhex("21 02"))
    # made synchronous (type 1), RPDO1 takes effect at the next SYNC, not on reception
    remote.nmt.send_command(0x80)
    remote.sdo.download(0x1400, 2, b"\x01")
    remote.nmt.send_command(0x01)
    monitor.send(can.Message(arbitration_id=0x209, data=b"\x07\x00", is_extended_id=False))
    frames(monitor)
    assert sim.state is State402.READY_TO_SWITCH_ON
    monitor.send(sync)
    frames(monitor)
    assert sim.state is State402.SWITCHED_ON
    assert sim.sync_count == 3 and len(plant.torques) == 3


def test_state_machine_by_sdo(node):
    sim, remote, *_ = node

    def cw(value: int) -> int:
        remote.sdo.download(0x6040, 0, value.to_bytes(2, "little"))
        return int.from_bytes(remote.sdo.upload(0x6041, 0), "little")

    assert cw(0x000F) == 0x0240  # enable from SWITCH ON DISABLED: no transition
    assert cw(0x0006) == 0x0221
    assert cw(0x000F) == 0x0237  # READY → OPERATION ENABLED directly (transitions 3 + 4)
    assert cw(0x0002) == 0x0217  # quick stop
    assert cw(0x000F) == 0x0237  # transition 16
    assert cw(0x0007) == 0x0233  # disable operation
    assert cw(0x0006) == 0x0221
    assert cw(0x0000) == 0x0240
    sim.inject_fault(0x5400)
    assert cw(0x0006) == 0x0208  # nothing but a fault reset leaves FAULT
    assert remote.sdo.upload(0x603F, 0) == b"\x00\x54"
    assert cw(0x0080) == 0x0240
    assert remote.sdo.upload(0x1001, 0) == b"\x00"


@pytest.fixture(scope="module")
def fuzz_sim():
    channel = f"sim-fuzz-{uuid.uuid4()}"
    bus = can.Bus(interface="virtual", channel=channel)
    sim = SimulatedDrive(bus, make_config(channel), StillPlant())
    yield sim
    sim.close()
    bus.shutdown()


@settings(max_examples=400, deadline=None)
@given(
    cob_id=st.one_of(st.sampled_from([0x000, 0x080, 0x209, 0x609]), st.integers(0, 0x7FF)),
    data=st.binary(max_size=8),
)
def test_fuzz_simulated_node_ignores_garbage(fuzz_sim, cob_id, data):
    fuzz_sim._on_frame(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))
    assert fuzz_sim.errors == []
