"""Steerlab's own CiA 402 driver (:class:`~hardware.can.cia402.CiA402Drive`, the one the live
loop uses) against a node it did not write: canopen's reference node side (``LocalNode``) with a
vendor-style EDS (``vendor_servo.eds``: an SD-400 servo drive, modelled on real servo drives'
files: more objects, other defaults, the CiA 402 predefined PDO set, 16-bit analog input as the
column torque channel, velocity in rpm, a gearbox). The drive's firmware is played here, in the
LocalNode's SDO callbacks and PDO / SYNC / NMT subscriptions, with its own CiA 402 state machine
and mechanics, so nothing of Steerlab's simulated drive (``hardware.can.sim_node``) is involved.

The figures the driver reports are checked against the firmware's own state, computed with the
firmware's formulas (not :class:`~hardware.can.scaling.DriveScaling`).
"""

from __future__ import annotations

import math
import threading
import time
import uuid
from functools import partial
from pathlib import Path

import can
import canopen
import pytest
from canopen.sdo import SdoAbortedError

from steerlab.hardware.can import (
    CiA402Drive,
    DriveConfig,
    DriveEnableError,
    SafetyConfig,
    TorqueSensorConfig,
)
from tests.hardware import can_wire

EDS = Path(__file__).with_name("vendor_servo.eds")
NODE = 3
COUNTS_PER_REV = 4096  # motor encoder
RATED_NM = 2.5  # 0x6076 of the EDS: 2500 mN·m
GEAR = 4.0  # motor revolutions per wheel revolution
WHEEL_INERTIA = 0.3  # kg·m², wheel side
MV_PER_NM = 200.0  # the amplifier on analog input 1: 200 mV per N·m of column torque
HAND_NM = 0.75  # a constant column torque from the hand (wheel side)


#: Polls until true, up to 5 s: a loaded test machine, not a slow node.
wait_for = partial(can_wire.wait_for, timeout=5.0)


# CiA 402 device control: the command a controlword gives (table "command coding").
def _command(cw: int) -> str:
    if cw & 0x0080:
        return "fault reset"
    if cw & 0x0002 == 0:
        return "disable voltage"
    if cw & 0x0006 == 0x0002:
        return "quick stop"
    if cw & 0x0007 == 0x0006:
        return "shutdown"
    if cw & 0x000F == 0x0007:
        return "switch on"
    if cw & 0x000F == 0x000F:
        return "enable operation"
    return "none"


# (state, command) -> next state; the SD-400 allows READY TO SWITCH ON -> OPERATION ENABLED
# directly (transitions 3 + 4) and leaves QUICK STOP ACTIVE at once (0x605A = 2, torque mode).
_TRANSITIONS = {
    ("SOD", "shutdown"): "RTSO",
    ("RTSO", "switch on"): "SO",
    ("RTSO", "enable operation"): "OE",
    ("RTSO", "disable voltage"): "SOD",
    ("RTSO", "quick stop"): "SOD",
    ("SO", "enable operation"): "OE",
    ("SO", "shutdown"): "RTSO",
    ("SO", "disable voltage"): "SOD",
    ("SO", "quick stop"): "SOD",
    ("OE", "switch on"): "SO",
    ("OE", "shutdown"): "RTSO",
    ("OE", "disable voltage"): "SOD",
    ("OE", "quick stop"): "SOD",
}
# The SD-400's statuswords: state coding plus bit 9 (remote), bit 4 (voltage enabled) where
# the DC link is on, bit 5 (quick stop not active) and bit 10 (target reached) when enabled.
_STATUSWORD = {
    "SOD": 0x0250,
    "RTSO": 0x0231,
    "SO": 0x0233,
    "OE": 0x0637,
    "FAULT": 0x0218,
}


class SD400Firmware:
    """The vendor drive behind canopen's LocalNode: NMT and heartbeat producer are canopen's
    own; the firmware adds the CiA 402 state machine, synchronous PDOs, EMCY, the consumer
    heartbeat (0x1016) with the abort connection option (0x6007), and the mechanics."""

    def __init__(self, channel: str) -> None:
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.connect(interface="virtual", channel=channel, receive_own_messages=False)
        self.node = canopen.LocalNode(NODE, str(EDS))
        self.network.add_node(self.node)
        self.lock = threading.RLock()
        self.state = "SOD"
        self.controlword = 0
        self.target = 0
        self.error_code = 0
        self.sync_count = 0
        self.rpdo_pending: dict[int, list[tuple[int, int, int]]] = {}
        self.host_last: dict[int, float] = {}  # producer node -> time.monotonic()
        self.host_lost = 0
        # mechanics, motor side: angle rad, velocity rad/s, torque N·m
        self.angle = self.velocity = self.torque = 0.0
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        self.network.subscribe(0x000, self._on_nmt)  # after the LocalNode's own NMT slave
        self.network.subscribe(0x080, self._on_sync)
        for pdo in self.node.rpdo.values():
            pdo.add_callback(self._on_rpdo)
        self._stop = threading.Event()
        self._watch = threading.Thread(target=self._watchdog, daemon=True, name="SD-400 guard")
        self._watch.start()
        # power on: boot-up, PRE-OPERATIONAL (canopen's NMT slave sends the boot-up message)
        self.node.nmt.send_command(0x81)
        self.node.nmt.send_command(0x80)

    def close(self) -> None:
        self._stop.set()
        self._watch.join(1.0)
        self.node.nmt.stop_heartbeat()
        self.network.disconnect()

    # -- process data --------------------------------------------------------------------------

    @property
    def statusword(self) -> int:
        return _STATUSWORD[self.state]

    @property
    def motor_torque_nm(self) -> float:
        """What the power stage applies (motor side)."""
        with self.lock:
            return self.torque

    def _value(self, index: int, subindex: int) -> int | None:
        if index == 0x6041:
            return self.statusword
        if index == 0x6061:
            return self.node.sdo[0x6060].raw
        if index == 0x6064:
            return round(self.angle / (2 * math.pi) * COUNTS_PER_REV)
        if index == 0x606C:
            return round(self.velocity * 60 / (2 * math.pi))  # rpm
        if index == 0x6077:
            return round(self.torque / RATED_NM * 1000)
        if index == 0x603F:
            return self.error_code
        if (index, subindex) == (0x2400, 1):
            wheel_angle = self.angle / GEAR
            return round((HAND_NM + 0.5 * wheel_angle) * MV_PER_NM)
        if index == 0x6040:
            return self.controlword
        if index == 0x6071:
            return self.target
        return None

    def _on_read(self, index: int, subindex: int, od, **_) -> int | None:
        with self.lock:
            return self._value(index, subindex)

    def _on_write(self, index: int, subindex: int, od, data: bytes, **_) -> None:
        value = od.decode_raw(data)
        with self.lock:
            if index == 0x6060:
                supported = self.node.sdo[0x6502].raw
                bit = {1: 0, 3: 2, 4: 3, 6: 5, 7: 6, 8: 7, 9: 8, 10: 9}.get(value)
                if value != 0 and (bit is None or not supported >> bit & 1):
                    raise SdoAbortedError(0x06090030)
            elif index == 0x6040:
                self._controlword(value)
            elif index == 0x6071:
                self.target = value
            elif index == 0x1016:
                producer = (value >> 16) & 0x7F
                if producer:
                    self.network.subscribe(0x700 + producer, self._on_host_heartbeat)

    def _controlword(self, cw: int) -> None:
        command = _command(cw)
        rising_reset = cw & 0x80 and not self.controlword & 0x80
        self.controlword = cw
        if self.state == "FAULT":
            if command == "fault reset" and rising_reset:
                self.state, self.error_code = "SOD", 0
                self.node.emcy.reset()
            return
        self.state = _TRANSITIONS.get((self.state, command), self.state)
        self._power_stage()

    def _power_stage(self) -> None:
        if self.state != "OE":
            self.torque = 0.0

    def fault(self, code: int) -> None:
        """An over-current: FAULT at once, EMCY with the error register's current bit."""
        with self.lock:
            self.state, self.error_code = "FAULT", code
            self._power_stage()
            self.node.emcy.send(code, 0x03)

    # -- NMT, PDO, SYNC ------------------------------------------------------------------------

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if data[1] not in (0, NODE):
            return
        with self.lock:
            if data[0] == 0x01:  # start: take the PDO set-up the master wrote
                self.node.rpdo.read()
                self.node.tpdo.read()
                self.rpdo_pending.clear()
            elif self.state == "OE":  # leaving OPERATIONAL: no PDO channel, no torque
                self.state = "SOD"
                self._power_stage()

    def _on_rpdo(self, pdo: canopen.pdo.PdoMap) -> None:
        if self.node.nmt.state != "OPERATIONAL":
            return
        values = [(v.index, v.subindex, v.raw) for v in pdo]
        with self.lock:
            if pdo.trans_type is not None and pdo.trans_type <= 240:
                self.rpdo_pending[pdo.cob_id] = values  # acts at the next SYNC
            else:
                self._apply(values)

    def _apply(self, values: list[tuple[int, int, int]]) -> None:
        for index, _sub, value in values:
            if index == 0x6040:
                self._controlword(value)
            elif index == 0x6071:
                self.target = value

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.node.nmt.state != "OPERATIONAL":
            return
        with self.lock:
            self.sync_count += 1
            for values in self.rpdo_pending.values():
                self._apply(values)
            self.rpdo_pending.clear()
            # mechanics over one SYNC period: the wheel under gear × motor torque
            if self.state == "OE" and self.node.sdo[0x6060].raw == 10:
                limit = self.node.sdo[0x6072].raw
                self.torque = max(-limit, min(limit, self.target)) * RATED_NM / 1000
            dt = self.node.sdo[0x1006].raw * 1e-6
            wheel_acc = GEAR * self.torque / WHEEL_INERTIA
            self.velocity += GEAR * wheel_acc * dt  # motor side
            self.angle += self.velocity * dt
            for pdo in self.node.tpdo.values():
                if pdo.enabled and pdo.trans_type and pdo.trans_type <= 240:
                    if self.sync_count % pdo.trans_type == 0:
                        for var in pdo:
                            var.raw = self._value(var.index, var.subindex)
                        pdo.transmit()

    # -- the drive's guard on its host ---------------------------------------------------------

    def _on_host_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.host_last[can_id - 0x700] = time.monotonic()

    def _watchdog(self) -> None:
        while not self._stop.wait(0.002):
            with self.lock:
                entry = self.node.sdo[0x1016][1].raw
                producer, timeout_ms = (entry >> 16) & 0x7F, entry & 0xFFFF
                last = self.host_last.get(producer)
                if not producer or not timeout_ms or last is None:
                    continue
                if time.monotonic() - last <= timeout_ms / 1000:
                    continue
                del self.host_last[producer]  # lost: watch again from its next heartbeat
                self.host_lost += 1
                option = self.node.sdo[0x6007].raw
                if self.state == "OE" and option == 1:
                    self.state, self.error_code = "FAULT", 0x8130
                elif self.state == "OE" and option in (2, 3):
                    self.state = "SOD"
                self._power_stage()
                self.node.emcy.send(0x8130, 0x11)


def vendor_config(channel: str, **changes) -> DriveConfig:
    fields = dict(
        node_id=NODE,
        interface="virtual",
        channel=channel,
        bitrate=1_000_000,
        encoder_counts_per_rev=COUNTS_PER_REV,
        rated_torque_nm=RATED_NM,
        gear_ratio=GEAR,
        sign=1,
        velocity_unit="rpm",
        safety=SafetyConfig(4.0, 100.0, 360.0),
        # The firmware runs in canopen's Python notifier thread on a loaded test machine: a
        # slow loop with a generous TPDO wait (the lab runs 1 kHz against real firmware).
        loop_rate_hz=50.0,
        tpdo_timeout_ms=15.0,
        state_timeout_s=3.0,
        heartbeat_timeout_ms=1000,
        torque_sensor=TorqueSensorConfig(
            source="pdo", index=0x2400, subindex=1, bits=16, nm_per_count=1 / MV_PER_NM
        ),
    )
    fields.update(changes)
    return DriveConfig(**fields)


@pytest.fixture
def vendor_rig():
    channel = f"vendor-{uuid.uuid4()}"
    firmware = SD400Firmware(channel)
    host_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    cfg = vendor_config(channel)
    drive = CiA402Drive(host_bus, cfg)
    yield drive, firmware, host_bus, cfg
    drive.close()
    firmware.close()
    host_bus.shutdown()


def _run(drive: CiA402Drive, torque_nm: float, cycles: int) -> None:
    for _ in range(cycles):
        drive.set_torque(torque_nm)
        drive.sync()


def _settled_sync(drive: CiA402Drive, torque_nm: float) -> None:
    """Cycles until two in a row had all their TPDOs in time, so the reading is of the last
    SYNC (after a miss, a late TPDO could be taken for the next cycle's)."""
    in_time = 0
    for _ in range(100):
        missed = drive.missed_tpdo
        drive.set_torque(torque_nm)
        drive.sync()
        in_time = in_time + 1 if drive.missed_tpdo == missed else 0
        if in_time == 2:
            return
    pytest.fail("no two cycles in a row with all TPDOs in time in 100 tries")


def test_the_driver_configures_and_enables_a_vendor_drive(vendor_rig):
    drive, fw, _, cfg = vendor_rig
    drive.enable()
    assert drive.ok and drive.enabled and fw.state == "OE"
    assert fw.node.nmt.state == "OPERATIONAL"
    sdo = fw.node.sdo  # the firmware's own view of what the driver wrote
    assert sdo[0x6060].raw == 10
    assert (sdo[0x1400][1].raw, sdo[0x1400][2].raw) == (0x200 + NODE, 1)
    assert [sdo[0x1600][s].raw for s in range(sdo[0x1600][0].raw + 1)][1:] == [
        0x6040_0010,
        0x6071_0010,
    ]
    assert [sdo[0x1A00][s].raw for s in range(1, sdo[0x1A00][0].raw + 1)] == [
        0x6041_0010,
        0x6064_0020,
        0x6077_0010,
    ]
    assert [sdo[0x1A01][s].raw for s in range(1, sdo[0x1A01][0].raw + 1)] == [
        0x606C_0020,
        0x2400_0110,  # the analog input the rig file names as the column torque channel
    ]
    # the predefined set the vendor ships is switched off, as far as the driver does not use it
    assert all(sdo[0x1400 + k][1].raw & 0x8000_0000 for k in (1, 2, 3))
    assert all(sdo[0x1800 + k][1].raw & 0x8000_0000 for k in (2, 3))
    assert sdo[0x1006].raw == 20_000  # µs
    assert sdo[0x6072].raw == cfg.max_torque_permille == 400
    assert sdo[0x6007].raw == 2  # disable voltage on a lost host (the vendor default is 1)
    assert sdo[0x1016][1].raw == (127 << 16) | 80
    assert sdo[0x1017].raw == 100


def test_the_control_loop_reads_what_the_vendor_drive_reports(vendor_rig):
    drive, fw, _, cfg = vendor_rig
    drive.enable()
    _run(drive, 1.0, 20)  # 1 N·m on the wheel
    # firmware side: the motor torque is wheel torque / gear
    assert wait_for(lambda: math.isclose(fw.motor_torque_nm, 1.0 / GEAR, abs_tol=RATED_NM / 1000))
    _settled_sync(drive, 1.0)
    with fw.lock:
        angle_w, velocity_w, torque_w = fw.angle / GEAR, fw.velocity / GEAR, fw.torque * GEAR
        rpm = round(fw.velocity * 60 / (2 * math.pi))
    assert angle_w > 0 and velocity_w > 0  # the wheel turns under the torque
    reading = drive.read()
    assert reading.angle_rad == pytest.approx(angle_w, abs=2 * math.pi / (COUNTS_PER_REV * GEAR))
    assert reading.velocity_rad_s == pytest.approx(rpm * 2 * math.pi / 60 / GEAR, rel=1e-9)
    assert reading.torque_actual_nm == pytest.approx(torque_w, abs=GEAR * RATED_NM / 1000)
    column = HAND_NM + 0.5 * angle_w
    assert drive.column_torque_nm() == pytest.approx(column, abs=1 / MV_PER_NM)
    # the drive's own limit (0x6072, written by the driver) caps a larger command
    _run(drive, 50.0, 5)
    assert wait_for(lambda: math.isclose(fw.motor_torque_nm, 400 * RATED_NM / 1000))
    drive.disable()
    assert fw.state == "SOD" and fw.motor_torque_nm == 0.0
    assert drive.ok


def test_a_vendor_emcy_is_a_fault_and_enable_resets_it(vendor_rig):
    drive, fw, _, _ = vendor_rig
    drive.enable()
    _run(drive, 0.5, 5)
    fw.fault(0x2310)
    assert wait_for(lambda: not drive.ok)
    emcy = [f for f in drive.faults if f.kind == "emcy"]
    assert emcy and emcy[0].code == 0x2310
    _run(drive, 0.5, 3)
    assert fw.state == "FAULT" and fw.motor_torque_nm == 0.0
    drive.enable()  # fault reset on the rising edge of bit 7, then on to OPERATION ENABLED
    assert drive.ok and fw.state == "OE" and fw.error_code == 0


def test_a_vendor_drive_without_cyclic_synchronous_torque_is_refused(vendor_rig):
    drive, fw, _, _ = vendor_rig
    fw.node.sdo[0x6502].od.default = 0x0000_0001  # profile position only
    with pytest.raises(DriveEnableError, match="0x6060"):
        drive.enable()
    assert fw.state == "SOD" and not drive.enabled


def test_the_vendor_drive_cuts_the_torque_when_the_hosts_bus_goes_off(vendor_rig):
    drive, fw, host_bus, cfg = vendor_rig
    drive.enable()
    _run(drive, 1.0, 5)
    assert wait_for(lambda: fw.motor_torque_nm > 0)
    time.sleep(0.2)  # the driver's host heartbeat (20 ms) keeps the vendor's 0x1016 fed
    assert fw.host_lost == 0 and fw.state == "OE"
    host_bus.shutdown()  # nothing the host sends reaches the drive any more
    drive.set_torque(1.0)
    drive.sync()
    assert not drive.ok
    assert wait_for(lambda: fw.host_lost == 1 and fw.motor_torque_nm == 0.0)
    assert fw.state == "SOD"  # 0x6007 = 2 as the driver set it: disable voltage
