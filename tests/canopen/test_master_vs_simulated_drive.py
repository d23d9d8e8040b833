"""The simulated drive as a CANopen tool sees it: canopen's OWN master code (``BaseNode402``,
``RemoteNode`` with the drive's EDS file, ``PdoMap``, the EMCY and heartbeat consumers, the SYNC
producer) drives the node; nothing of Steerlab's driver is used.

Under load, the master's own timeouts (0.2–0.8 s by default) are raised: what is asserted is
behaviour (a state is reached, a frame arrives or does not), not how fast.
"""

from __future__ import annotations

import math
import time
import uuid
from dataclasses import replace
from functools import partial

import can
import canopen
import pytest
from canopen.profiles.p402 import BaseNode402
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from steerlab.hardware.can import SimulatedDrive, State402, build_object_dictionary
from steerlab.hardware.can.config import load_drive_config
from steerlab.hardware.can.sim_node import SIMULATED_DRIVE_EDS
from tests.hardware import can_wire
from tests.helpers import ROOT

NODE = 9


class Wheel:
    """Inertia 0.3 kg·m² under the motor torque, nothing else (hardware.can.Plant)."""

    def __init__(self, fs_hz: float = 1000.0) -> None:
        self.dt = 1.0 / fs_hz
        self.angle = self.velocity = self.motor = 0.0

    def step(self, motor_torque_nm: float) -> None:
        self.motor = motor_torque_nm
        self.velocity += motor_torque_nm / 0.3 * self.dt
        self.angle += self.velocity * self.dt

    def read(self) -> tuple[float, float, float, float]:
        return self.angle, self.velocity, self.motor, 0.0


#: Polls until true, up to 5 s: a loaded test machine, not a slow node.
wait_for = partial(can_wire.wait_for, timeout=5.0)


def frames(bus: can.BusABC, timeout: float = 0.05, max_s: float = 0.5) -> list[can.Message]:
    """What the monitor got: until ``timeout`` of silence, at most ``max_s`` (the factory
    TPDO1/TPDO2 event timers keep the bus from ever going silent for long)."""
    out = []
    end = time.monotonic() + max_s
    while time.monotonic() < end and (m := bus.recv(timeout)) is not None:
        out.append(m)
    return out


class Rig:
    """The simulated drive on a virtual bus, canopen's master for it, and a bus monitor."""

    def __init__(self) -> None:
        channel = f"master-{uuid.uuid4()}"
        shipped = load_drive_config(ROOT / "hardware" / "rigs" / "simulated.toml")
        self.config = replace(shipped, node_id=NODE, channel=channel)
        self.drive_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.monitor = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.plant = Wheel()
        self.sim = SimulatedDrive(self.drive_bus, self.config, self.plant)
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05  # quick teardown
        self.network.connect(interface="virtual", channel=channel, receive_own_messages=False)
        self.node = BaseNode402(NODE, str(SIMULATED_DRIVE_EDS))
        self.network.add_node(self.node)
        node = self.node
        node.sdo.RESPONSE_TIMEOUT = 2.0  # a loaded machine, not a slow drive
        node.TIMEOUT_SWITCH_STATE_FINAL = 10.0
        node.TIMEOUT_SWITCH_STATE_SINGLE = 3.0
        node.TIMEOUT_SWITCH_OP_MODE = 3.0
        node.TIMEOUT_CHECK_TPDO = 2.0

    def close(self) -> None:
        self.network.sync.stop()
        for pdo in self.node.rpdo.values():
            pdo.stop()
        self.network.disconnect()
        self.sim.close()
        self.drive_bus.shutdown()
        self.monitor.shutdown()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()
    assert r.sim.errors == []


def test_the_eds_imports_and_the_node_answers_every_object_it_lists(rig):
    od = canopen.import_od(str(SIMULATED_DRIVE_EDS), NODE)
    assert od.device_information.product_name == "Steerlab simulated drive"
    assert od.device_information.nr_of_RXPDO == 4 and od.device_information.nr_of_TXPDO == 4
    # the node's own dictionary is this EDS for the shipped rig (rated torque 10 N·m, column
    # torque at 0x2000)
    built = build_object_dictionary(rig.config)
    assert sorted(built) == sorted(od)
    mine = {(v.index, v.subindex): v for v in _variables(built)}
    for v in _variables(od):
        b = mine[(v.index, v.subindex)]
        assert (b.data_type, b.access_type, b.pdo_mappable) == (
            v.data_type,
            v.access_type,
            v.pdo_mappable,
        ), f"0x{v.index:04X}:{v.subindex:02X}"
        assert b.default == v.default, f"0x{v.index:04X}:{v.subindex:02X}"
    # every readable object of the EDS is uploaded with its type's size; the configuration
    # objects hold the EDS defaults (COB-IDs with $NODEID resolved)
    dynamic = {0x1001, 0x6041, 0x6061, 0x6064, 0x606C, 0x6077, 0x2000, 0x603F, 0x6040, 0x6071}
    for v in _variables(od):
        if not v.readable:
            continue
        raw = rig.node.sdo.upload(v.index, v.subindex)
        if v.index == 0x1008:
            assert raw.decode() == v.default
            continue
        assert len(raw) * 8 == len(v), f"0x{v.index:04X}:{v.subindex:02X}"
        if v.index not in dynamic:
            assert v.decode_raw(raw) == v.default, f"0x{v.index:04X}:{v.subindex:02X}"
    assert rig.node.sdo[0x1000].raw == 0x0002_0192  # CiA 402 servo drive
    assert rig.node.sdo[0x1014].raw == 0x80 + NODE
    assert rig.node.sdo[0x6502].raw == 0x200  # cyclic synchronous torque only
    with pytest.raises(SdoAbortedError) as info:
        rig.node.sdo.upload(0x6080, 0)  # max motor speed: not implemented
    assert info.value.code == 0x06020000
    with pytest.raises(SdoAbortedError) as info:
        rig.node.sdo.upload(0x1018, 5)
    assert info.value.code == 0x06090011


def _variables(od: canopen.ObjectDictionary):
    for obj in od.values():
        if isinstance(obj, canopen.objectdictionary.ODVariable):
            yield obj
        else:
            yield from obj.values()


def test_nmt_and_heartbeat_consumer_and_no_sdo_in_stopped(rig):
    node = rig.node

    def reported(state: str) -> bool:  # the heartbeat (canopen's consumer) reports it
        return wait_for(lambda: node.nmt.wait_for_heartbeat(2) == state)

    node.nmt.state = "RESET"
    node.nmt.wait_for_bootup(5)
    assert rig.sim.nmt_state == 0x7F
    node.sdo[0x1017].raw = 20  # producer heartbeat time, ms
    assert node.nmt.wait_for_heartbeat(5) == "PRE-OPERATIONAL"
    node.nmt.state = "OPERATIONAL"
    assert reported("OPERATIONAL")

    node.nmt.state = "STOPPED"
    assert reported("STOPPED")  # the heartbeat goes on in STOPPED
    node.sdo.RESPONSE_TIMEOUT = 0.3
    with pytest.raises(SdoCommunicationError):  # CiA 301: no SDO server in STOPPED
        node.sdo.upload(0x1000, 0)
    with pytest.raises(SdoCommunicationError):
        node.sdo.download(0x6040, 0, b"\x06\x00")
    assert rig.sim.state is State402.SWITCH_ON_DISABLED  # the download was not executed
    node.sdo.RESPONSE_TIMEOUT = 2.0
    node.nmt.state = "PRE-OPERATIONAL"
    assert reported("PRE-OPERATIONAL")
    assert node.sdo[0x1000].raw == 0x0002_0192
    assert node.sdo["Manufacturer device name"].raw == "Steerlab simulated drive"  # segmented

    node.nmt.state = "RESET COMMUNICATION"
    node.nmt.wait_for_bootup(5)
    assert node.sdo[0x1017].raw == 0  # communication objects back to their defaults
    assert node.nmt.state == "PRE-OPERATIONAL"


def test_402_state_walk_and_op_mode_with_the_factory_pdos_and_no_sync(rig):
    """canopen's usual sequence, out of the box: RPDO1 (controlword) and TPDO1 (statusword)
    are asynchronous (255), so no SYNC producer is needed."""
    node, sim = rig.node, rig.sim
    node.nmt.state = "PRE-OPERATIONAL"
    node.setup_402_state_machine()
    assert node.tpdo[1].trans_type == 255 and [v.index for v in node.tpdo[1]] == [0x6041]
    assert node.rpdo[1].trans_type == 255 and [v.index for v in node.rpdo[1]] == [0x6040]
    assert node.is_op_mode_supported("CYCLIC SYNCHRONOUS TORQUE")
    assert not node.is_op_mode_supported("PROFILED POSITION")
    with pytest.raises(TypeError):
        node.op_mode = "PROFILED POSITION"
    node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
    assert node.op_mode == "CYCLIC SYNCHRONOUS TORQUE"
    assert node.sdo[0x6060].raw == 10

    node.nmt.state = "OPERATIONAL"
    node.state = "OPERATION ENABLED"
    assert sim.state is State402.OPERATION_ENABLED and node.state == "OPERATION ENABLED"
    assert sim.sync_count == 0  # no SYNC was needed
    node.state = "QUICK STOP ACTIVE"
    assert sim.state is State402.QUICK_STOP_ACTIVE
    node.state = "OPERATION ENABLED"
    node.state = "SWITCH ON DISABLED"
    assert sim.state is State402.SWITCH_ON_DISABLED

    sim.inject_fault(0x2310)
    assert wait_for(lambda: node.state == "FAULT")  # TPDO1 is event-driven: no polling
    node.reset_from_fault()  # canopen's fault reset, then on to OPERATION ENABLED
    assert sim.state is State402.OPERATION_ENABLED and node.state == "OPERATION ENABLED"


def test_pdo_map_read_save_and_sync_driven_control(rig):
    node, sim, cfg = rig.node, rig.sim, rig.config
    node.nmt.state = "PRE-OPERATIONAL"
    node.tpdo.read()
    node.rpdo.read()
    # what the EDS says the drive ships with
    assert [(k, p.enabled, p.trans_type) for k, p in node.tpdo.items()] == [
        (1, True, 255),
        (2, True, 255),
        (3, True, 1),
        (4, True, 1),
    ]
    assert [p.enabled for p in node.rpdo.values()] == [True, False, False, False]
    assert node.tpdo[1].cob_id == 0x180 + NODE and node.rpdo[1].cob_id == 0x200 + NODE

    # A new set-up, saved with canopen's PdoMap.save(): synchronous control in RPDO1/TPDO1,
    # an asynchronous RPDO2 and two event-driven TPDOs.
    r1, r2, t1, t2, t3, t4 = (
        node.rpdo[1],
        node.rpdo[2],
        node.tpdo[1],
        node.tpdo[2],
        node.tpdo[3],
        node.tpdo[4],
    )
    r1.clear()
    r1.add_variable(0x6040)
    r1.add_variable(0x6071)
    r1.trans_type = 1
    r2.clear()
    r2.add_variable(0x6072)  # max torque
    r2.add_variable(0x6060)  # modes of operation
    r2.trans_type = 255
    r2.enabled = True
    t1.clear()
    t1.add_variable(0x6041)
    t1.add_variable(0x6064)
    t1.add_variable(0x6077)
    t1.trans_type = 1
    t2.clear()
    t2.add_variable(0x606C)
    t2.add_variable(0x2000)
    t2.trans_type = 2  # every 2nd SYNC
    t3.clear()
    t3.add_variable(0x6061)
    t3.trans_type = 254
    t3.event_timer = 20  # ms: sent every 20 ms though it never changes
    t3.inhibit_time = 0
    t4.clear()
    t4.add_variable(0x6041)
    t4.trans_type = 255
    t4.inhibit_time = 500  # 50 ms between two TPDO4
    t4.event_timer = 0
    node.rpdo.save()
    node.tpdo.save()
    assert sim.od_value(0x1600, 0) == 2 and sim.od_value(0x1601, 2) == 0x6060_0008
    assert sim.od_value(0x1802, 5) == 20 and sim.od_value(0x1803, 3) == 500

    # read back by a second master that knows nothing of the above
    other = canopen.RemoteNode(NODE, str(SIMULATED_DRIVE_EDS))
    other.sdo.RESPONSE_TIMEOUT = 2.0
    second = canopen.Network()
    second.NOTIFIER_CYCLE = 0.05
    second.connect(interface="virtual", channel=cfg.channel, receive_own_messages=False)
    second.add_node(other)
    try:
        other.tpdo.read()
        other.rpdo.read()
    finally:
        second.disconnect()
    assert [v.index for v in other.tpdo[1]] == [0x6041, 0x6064, 0x6077]
    assert [v.index for v in other.tpdo[2]] == [0x606C, 0x2000]
    assert (other.tpdo[3].trans_type, other.tpdo[3].event_timer) == (254, 20)
    assert (other.tpdo[4].trans_type, other.tpdo[4].inhibit_time) == (255, 500)
    assert [v.index for v in other.rpdo[2]] == [0x6072, 0x6060] and other.rpdo[2].enabled

    # asynchronous RPDO2 acts at once, without SYNC
    node.setup_402_state_machine(read_pdos=False)
    node.nmt.state = "OPERATIONAL"
    r2["Max torque"].raw = 500
    r2["Modes of operation"].raw = 10
    r2.transmit()
    assert wait_for(lambda: sim.od_value(0x6072) == 500 and sim.od_value(0x6060) == 10)
    assert sim.sync_count == 0

    # TPDO3: the event timer sends it again and again with no change and no SYNC
    got = []
    for _ in range(3):
        assert t3.wait_for_reception(2.0) is not None
        got.append(t3["Modes of operation display"].raw)
    assert got == [10, 10, 10] and sim.sync_count == 0

    # synchronous control: canopen's SYNC producer and its periodic RPDO1; the state walk
    # goes through SYNC now (controlword in a synchronous RPDO, statusword in a synchronous
    # TPDO, both "periodic" for BaseNode402)
    tpdo4 = []
    node.network.subscribe(0x480 + NODE, lambda cid, data, ts: tpdo4.append((ts, bytes(data))))
    node.network.sync.start(0.005)
    r1.start(0.005)
    node.state = "OPERATION ENABLED"
    assert sim.state is State402.OPERATION_ENABLED
    r1["Target torque"].raw = 100  # 0.1 % of rated: 10 % of 10 N·m
    assert wait_for(lambda: math.isclose(sim.applied_torque_nm, 1.0))
    assert t1.wait_for_reception(2.0) is not None
    assert t1["Torque actual value"].raw == 100
    # TPDO2 on every 2nd SYNC only
    assert t2.wait_for_reception(2.0) is not None
    assert t2.period is None or t2.period >= 0.005
    # The wheel moves under 1 N·m, at whatever pace the SYNCs come (a starved test process may
    # have sent only one or two by now, too few for a whole encoder count).
    assert wait_for(lambda: sim.scaling.angle_to_counts(rig.plant.angle) != 0)
    node.state = "SWITCH ON DISABLED"
    assert wait_for(lambda: sim.applied_torque_nm == 0.0)
    node.network.sync.stop()
    r1.stop()
    # the last TPDO1 carries the plant's state after the last SYNC (the wheel moved under 1 N·m)
    counts = sim.scaling.angle_to_counts(rig.plant.angle)
    assert counts != 0
    assert wait_for(lambda: t1["Position actual value"].raw == counts)
    # TPDO4 (statusword, event-driven, inhibit 50 ms): it went out on entering OPERATIONAL
    # and on changes, never two within the inhibit time, and the last one is the state now
    assert wait_for(lambda: tpdo4 and tpdo4[-1][1] == bytes.fromhex("40 02"))
    gaps = [b[0] - a[0] for a, b in zip(tpdo4, tpdo4[1:], strict=False)]
    assert len(tpdo4) >= 2 and min(gaps) >= 0.050 - 0.002  # bus timestamps, 2 ms tick


def test_emcy_consumer_error_history_and_cob_id_emcy(rig):
    node, sim = rig.node, rig.sim
    node.nmt.state = "OPERATIONAL"
    sim.inject_fault(0x2310, vendor_data=b"\x01\x02")
    emcy = node.emcy.wait(0x2310, timeout=5)
    assert emcy is not None and emcy.register & 0x01 and emcy.data[:2] == b"\x01\x02"
    assert [e.code for e in node.emcy.active] == [0x2310]
    assert node.sdo[0x1001].raw & 0x01
    assert node.sdo[0x603F].raw == 0x2310
    assert node.sdo[0x1003][0].raw == 1 and node.sdo[0x1003][1].raw == 0x2310
    node.sdo[0x6040].raw = 0x0000
    node.sdo[0x6040].raw = 0x0080  # fault reset: EMCY 0x0000, canopen clears the active list
    assert wait_for(lambda: node.emcy.log[-1].code == 0x0000)
    assert node.emcy.active == []
    assert node.sdo[0x1003][0].raw == 1  # the history keeps it until cleared
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[0x1003][0].raw = 1
    assert info.value.code == 0x06090030
    node.sdo[0x1003][0].raw = 0
    assert node.sdo[0x1003][0].raw == 0

    # 0x1014: the COB-ID cannot change while valid; invalid (bit 31) means no EMCY at all
    with pytest.raises(SdoAbortedError):
        node.sdo[0x1014].raw = 0x0A0 + NODE
    node.sdo[0x1014].raw = 0x8000_0000 | (0x80 + NODE)
    frames(rig.monitor)
    sim.inject_fault(0x4210)
    assert [m for m in frames(rig.monitor, 0.2) if m.arbitration_id == 0x80 + NODE] == []
    assert sim.error_history[0] == 0x4210  # recorded though not sent
    node.sdo[0x1014].raw = 0x8000_0000 | 0x0A0
    node.sdo[0x1014].raw = 0x0A0  # a new COB-ID, valid again
    sim.inject_fault(0x5400)
    sent = [m for m in frames(rig.monitor, 0.2) if m.arbitration_id == 0x0A0]
    assert [bytes(m.data[:2]) for m in sent] == [b"\x00\x54"]

    # CiA 301: no EMCY in STOPPED
    node.sdo[0x1014].raw = 0x8000_0000 | 0x0A0
    node.sdo[0x1014].raw = 0x80 + NODE
    node.nmt.state = "STOPPED"
    time.sleep(0.05)
    frames(rig.monitor)
    sim.inject_fault(0x3210)
    assert [m for m in frames(rig.monitor, 0.2) if m.arbitration_id == 0x80 + NODE] == []


def test_cob_id_sync_is_honoured(rig):
    node, sim = rig.node, rig.sim
    node.nmt.state = "PRE-OPERATIONAL"
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[0x1005].raw = 0x4000_0080  # "this node produces SYNC": it does not
    assert info.value.code == 0x06090030
    node.sdo[0x1005].raw = 0x7D0
    node.nmt.state = "OPERATIONAL"
    frames(rig.monitor)
    node.network.sync.transmit()  # 0x080, no longer the drive's SYNC
    got = frames(rig.monitor, 0.2)
    assert sim.sync_count == 0 and not [m for m in got if m.arbitration_id == 0x380 + NODE]
    sync = canopen.sync.SyncProducer(node.network)
    sync.cob_id = 0x7D0
    sync.transmit()
    assert wait_for(lambda: sim.sync_count == 1)
    got = frames(rig.monitor, 0.2)
    assert [m.arbitration_id for m in got if m.arbitration_id in (0x380 + NODE, 0x480 + NODE)] == [
        0x380 + NODE,
        0x480 + NODE,
    ]


def test_rpdo_mapping_refuses_read_only_objects_and_tpdo_rtr_types(rig):
    node = rig.node
    node.nmt.state = "PRE-OPERATIONAL"
    node.sdo[0x1401][1].raw = 0x8000_0300 + NODE
    node.sdo[0x1601][0].raw = 0
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[0x1601][1].raw = 0x6041_0010  # statusword is read-only: not in an RPDO
    assert info.value.code == 0x06040041
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[0x1800][2].raw = 253  # RTR-only: not supported
    assert info.value.code == 0x06090030
    with pytest.raises(SdoAbortedError) as info:
        node.sdo[0x1800][3].raw = 10  # inhibit time while the TPDO is valid
    assert info.value.code == 0x08000022


def test_rpdo3_and_rpdo4_act_and_a_short_rpdo_is_reported(rig):
    """Any RPDO, not just RPDO1: the controlword in RPDO4 (asynchronous), the target torque in
    RPDO3 (synchronous, at the next SYNC); a PDO shorter than its mapping is not processed and
    reported with EMCY 0x8210 (CiA 301)."""
    node, sim = rig.node, rig.sim
    node.nmt.state = "PRE-OPERATIONAL"
    node.rpdo.read()
    r1, r3, r4 = node.rpdo[1], node.rpdo[3], node.rpdo[4]
    r1.enabled = False
    r3.clear()
    r3.add_variable(0x6071)
    r3.trans_type = 1
    r3.enabled = True
    r4.clear()
    r4.add_variable(0x6040)
    r4.add_variable(0x6060)
    r4.trans_type = 255
    r4.enabled = True
    node.rpdo.save()
    node.nmt.state = "OPERATIONAL"
    for cw in (0x06, 0x07, 0x0F):
        r4["Controlword"].raw = cw
        r4["Modes of operation"].raw = 10
        r4.transmit()
    assert wait_for(lambda: sim.state is State402.OPERATION_ENABLED)
    r3["Target torque"].raw = -50
    r3.transmit()
    time.sleep(0.05)
    assert sim.target_torque_permille == 0 and sim.applied_torque_nm == 0.0  # waits for SYNC
    node.network.sync.transmit()
    assert wait_for(lambda: math.isclose(sim.applied_torque_nm, -0.5))
    # RPDO1 is off now: its frames are not the drive's any more
    node.network.send_message(0x200 + NODE, b"\x00\x00")
    time.sleep(0.05)
    assert sim.state is State402.OPERATION_ENABLED
    node.network.send_message(0x400 + NODE, b"\x0f")  # 1 byte for a 3-byte mapping
    assert wait_for(lambda: node.emcy.log and node.emcy.log[-1].code == 0x8210)
    assert sim.state is State402.OPERATION_ENABLED  # not processed
