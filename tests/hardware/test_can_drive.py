"""CiA402Drive against the simulated drive node on a virtual bus: behaviour, faults, timing."""

from __future__ import annotations

import math
import statistics
import threading
import time
import uuid
from dataclasses import replace
from pathlib import Path

import can
import canopen
import numpy as np
import pytest
from scipy.linalg import expm

from steerlab.hardware.can import (
    CiA402Drive,
    DriveConfig,
    DriveEnableError,
    DriveFault,
    DriveFaultError,
    SafetyConfig,
    SimulatedDrive,
    State402,
    load_drive_config,
)
from steerlab.hardware.can.sim_node import SIMULATED_DRIVE_EDS
from steerlab.hardware.interfaces import TorqueSensor, WheelDrive
from tests.hardware.can_wire import wait_for

ROOT = Path(__file__).resolve().parents[2]


class SpringDamperWheel:
    """J θ'' + b θ' + k θ = u: a wheel held by a spring-damper arm, integrated exactly for
    piecewise-constant torque (zero-order hold), so samples equal the continuous solution."""

    def __init__(
        self, dt: float, inertia: float = 0.05, damping: float = 0.2, stiffness: float = 2.0
    ):
        self.j, self.b, self.k = inertia, damping, stiffness
        m = np.zeros((3, 3))
        m[:2, :2] = [[0.0, 1.0], [-stiffness / inertia, -damping / inertia]]
        m[1, 2] = 1.0 / inertia
        e = expm(m * dt)
        self.ad, self.bd = e[:2, :2], e[:2, 2]
        self.x = np.zeros(2)
        self.u = 0.0
        self.steps = 0

    def step(self, motor_torque_nm: float) -> None:
        self.u = motor_torque_nm
        self.x = self.ad @ self.x + self.bd * motor_torque_nm
        self.steps += 1

    def read(self) -> tuple[float, float, float, float]:
        angle, velocity = float(self.x[0]), float(self.x[1])
        # the torque the wheel exerts on the hands = what the arm's spring-damper resists
        return angle, velocity, self.u, self.k * angle + self.b * velocity

    def analytic_step(self, u: float, t: float) -> tuple[float, float]:
        wn = math.sqrt(self.k / self.j)
        zeta = self.b / (2 * math.sqrt(self.k * self.j))
        sigma, wd = zeta * wn, wn * math.sqrt(1 - zeta**2)
        decay = math.exp(-sigma * t)
        angle = u / self.k * (1 - decay * (math.cos(wd * t) + sigma / wd * math.sin(wd * t)))
        velocity = u / self.k * decay * math.sin(wd * t) * wn**2 / wd
        return angle, velocity


def base_config(channel: str, **changes) -> DriveConfig:
    cfg = DriveConfig(
        node_id=7,
        interface="virtual",
        channel=channel,
        bitrate=1_000_000,
        encoder_counts_per_rev=131072,
        rated_torque_nm=10.0,
        gear_ratio=3.0,
        sign=-1,
        safety=SafetyConfig(max_torque_nm=8.0, max_slew_nm_per_s=100.0, soft_angle_limit_deg=360.0),
        # generous TPDO timeout: these tests check behaviour, not timing, on a busy machine
        heartbeat_ms=20,
        heartbeat_timeout_ms=100,
        loop_rate_hz=20.0,
        tpdo_timeout_ms=45.0,
        state_timeout_s=0.2,
        sdo_timeout_s=2.0,  # a loaded machine answers late, not a slow drive
    )
    return replace(cfg, **changes)


class Rig:
    def __init__(self, cfg: DriveConfig, plant=None, *, with_sim: bool = True, **sim_kwargs):
        self.cfg = cfg
        self.host_bus = can.Bus(
            interface="virtual", channel=cfg.channel, receive_own_messages=False
        )
        self.drive_bus = can.Bus(
            interface="virtual", channel=cfg.channel, receive_own_messages=False
        )
        self.plant = plant if plant is not None else SpringDamperWheel(0.01)
        self.sim = (
            SimulatedDrive(self.drive_bus, cfg, self.plant, **sim_kwargs) if with_sim else None
        )
        self.faults: list[DriveFault] = []
        self.fault_event = threading.Event()
        self.drive = CiA402Drive(self.host_bus, cfg, on_fault=self._on_fault)

    def _on_fault(self, fault: DriveFault) -> None:
        self.faults.append(fault)
        self.fault_event.set()

    def close(self) -> None:
        self.drive.close()
        if self.sim is not None:
            self.sim.close()
        self.host_bus.shutdown()
        self.drive_bus.shutdown()


@pytest.fixture
def make_rig():
    rigs: list[Rig] = []

    def make(plant=None, *, with_sim: bool = True, sim_kwargs=None, **changes) -> Rig:
        cfg = base_config(f"drive-{uuid.uuid4()}", **changes)
        rig = Rig(cfg, plant, with_sim=with_sim, **(sim_kwargs or {}))
        rigs.append(rig)
        return rig

    yield make
    for rig in rigs:
        rig.close()
    time.sleep(0.05)
    left = [
        t.name
        for t in threading.enumerate()
        if t.name.startswith(("CiA402Drive", "SimulatedDrive"))
    ]
    assert left == [], f"threads left running: {left}"


def test_implements_the_device_interfaces(make_rig):
    rig = make_rig()
    assert isinstance(rig.drive, WheelDrive)
    assert isinstance(rig.drive.torque_sensor, TorqueSensor)


def test_enable_leaves_the_drive_in_the_drivers_synchronous_pdo_setup(make_rig):
    """Whatever the drive ships with (the simulated one: TPDO1/TPDO2 event-driven, type 255,
    with a 100 ms event timer), after enable() it has the set-up the driver wrote, as canopen's
    own PdoMap reads it back, and behaves by it: nothing between SYNCs, one TPDO1 and one TPDO2
    on each SYNC."""
    rig = make_rig()
    n = rig.cfg.node_id
    monitor = can.Bus(interface="virtual", channel=rig.cfg.channel, receive_own_messages=False)
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05
    network.connect(interface="virtual", channel=rig.cfg.channel, receive_own_messages=False)
    node = canopen.RemoteNode(n, str(SIMULATED_DRIVE_EDS))
    node.sdo.RESPONSE_TIMEOUT = 2.0  # a loaded machine, not a slow drive
    network.add_node(node)
    try:
        rig.drive.enable()
        node.tpdo.read()
        node.rpdo.read()
        tpdo, rpdo = node.tpdo, node.rpdo
        assert [(tpdo[k].enabled, tpdo[k].trans_type) for k in (1, 2)] == [(True, 1), (True, 1)]
        assert [v.index for v in tpdo[1]] == [0x6041, 0x6064, 0x6077]
        assert [v.index for v in tpdo[2]] == [0x606C, 0x2000]
        assert (rpdo[1].enabled, rpdo[1].trans_type) == (True, 1)
        assert [v.index for v in rpdo[1]] == [0x6040, 0x6071]
        assert [tpdo[k].enabled for k in (3, 4)] + [rpdo[k].enabled for k in (2, 3, 4)] == [
            False
        ] * 5

        def pdos_seen(s: float) -> list[int]:
            ids, end = [], time.monotonic() + s
            while (m := monitor.recv(max(0.0, end - time.monotonic()))) is not None:
                if 0x180 < m.arbitration_id < 0x500 and m.arbitration_id & 0x7F == n:
                    ids.append(m.arbitration_id)
            return ids

        pdos_seen(0.05)  # what enable() left in the monitor's queue
        assert pdos_seen(0.35) == []  # no event timer any more, no SYNC: silence
        for _ in range(20):
            rig.drive.sync()
        seen = pdos_seen(0.2)
        assert seen.count(0x180 + n) == 20 and seen.count(0x280 + n) == 20, seen
        assert len(seen) == 40 + seen.count(0x200 + n)  # and nothing else but RPDO1s
        assert rig.drive.missed_tpdo == 0
    finally:
        network.disconnect()
        monitor.shutdown()


def test_step_response_matches_the_analytic_solution(make_rig):
    # It checks every one of 150 exchanges, so a TPDO late beyond the usual 45 ms (a loaded
    # 2-core CI machine once) would fail it: 10x the room, at a 2-Hz loop it still fits.
    rig = make_rig(loop_rate_hz=2.0, tpdo_timeout_ms=450.0)
    drive, plant = rig.drive, rig.plant
    drive.enable()
    u = 2.1  # N·m at the wheel: 70 ‰ of 10 N·m × gear 3, exactly representable
    dt = 0.01  # the plant's sample time: one step per SYNC
    counts_per_rad = 131072 * 3 / (2 * math.pi)
    worst_angle = worst_velocity = 0.0
    for i in range(1, 151):
        drive.set_torque(u)
        drive.sync()
        r = drive.read()
        angle, velocity = plant.analytic_step(u, i * dt)
        worst_angle = max(worst_angle, abs(r.angle_rad - angle))
        worst_velocity = max(worst_velocity, abs(r.velocity_rad_s - velocity))
        assert r.torque_actual_nm == pytest.approx(u)
        column = plant.k * angle + plant.b * velocity
        assert drive.column_torque_nm() == pytest.approx(column, abs=2e-3)
    assert drive.missed_tpdo == 0
    # half a count of quantization (positions and counts/s)
    assert worst_angle <= 0.5 / counts_per_rad + 1e-12
    assert worst_velocity <= 0.5 / counts_per_rad + 1e-12
    assert max(abs(r.angle_rad), 0) > 0.5  # it really moved (steady state u/k = 1.05 rad)
    assert plant.steps == 150


def test_torque_beyond_max_is_clamped_by_the_drive(make_rig):
    rig = make_rig()
    rig.drive.enable()
    rig.drive.set_torque(-50.0)  # safety.max_torque_nm = 8 → 0x6072 = 267 ‰
    rig.drive.sync()
    assert rig.plant.u == pytest.approx(-267 * 0.03)
    assert rig.sim.target_torque_permille == round(-50.0 / (-1 * 3 * 10) * 1000)


def test_commands_are_ignored_while_disabled(make_rig):
    rig = make_rig()
    rig.drive.set_torque(1.0)  # never enabled
    rig.drive.sync()
    assert rig.sim.target_torque_permille == 0
    rig.drive.enable()
    rig.drive.disable()
    rig.drive.set_torque(1.0)
    rig.drive.sync()
    assert rig.plant.u == 0.0 and rig.sim.state is State402.SWITCH_ON_DISABLED


def test_non_finite_torque_commands_zero_then_raises(make_rig):
    rig = make_rig()
    rig.drive.enable()
    rig.drive.set_torque(1.5)
    with pytest.raises(ValueError, match="finite"):
        rig.drive.set_torque(math.nan)
    rig.drive.sync()
    assert rig.plant.u == 0.0
    assert [f.kind for f in rig.drive.active_faults] == ["command"]


def test_quick_stop_then_disable(make_rig):
    rig = make_rig()
    drive, sim = rig.drive, rig.sim
    drive.enable()
    drive.set_torque(3.0)
    drive.sync()
    drive.quick_stop()
    assert sim.state is State402.QUICK_STOP_ACTIVE
    drive.sync()
    assert rig.plant.u == 0.0
    assert drive.state is State402.QUICK_STOP_ACTIVE and not drive.enabled
    drive.set_torque(3.0)  # ignored after a quick stop
    drive.sync()
    assert rig.plant.u == 0.0
    drive.disable()
    assert sim.state is State402.SWITCH_ON_DISABLED
    drive.disable()  # idempotent
    assert sim.state is State402.SWITCH_ON_DISABLED


def test_reenable_after_disable(make_rig):
    rig = make_rig()
    rig.drive.enable()
    rig.drive.disable()
    rig.drive.enable()
    rig.drive.set_torque(0.3)
    rig.drive.sync()
    assert rig.plant.u == pytest.approx(0.3)
    assert rig.drive.ok


def test_emcy_is_a_fault_with_code_and_enable_resets_it(make_rig):
    rig = make_rig()
    drive, sim = rig.drive, rig.sim
    drive.enable()
    drive.set_torque(1.0)
    drive.sync()
    sim.inject_fault(0x2310, vendor_data=b"\x12\x34")
    assert rig.fault_event.wait(1.0)
    emcy = rig.faults[0]
    assert (emcy.kind, emcy.code) == ("emcy", 0x2310)
    assert "continuous over-current" in emcy.message and "node 7" in emcy.message
    assert not drive.ok
    with pytest.raises(DriveFaultError, match="0x2310"):
        drive.check()
    drive.sync()  # the statusword now says FAULT as well
    assert drive.state is State402.FAULT and not drive.enabled
    assert {f.kind for f in drive.active_faults} == {"emcy", "state"}
    assert rig.plant.u == 0.0  # power stage off

    drive.enable()  # fault reset → operation enabled
    assert drive.ok and drive.active_faults == ()
    drive.check()
    assert [e.code for e in drive.emergencies] == [0x2310, 0x0000]
    assert drive.emergencies[0].vendor_data == b"\x12\x34\x00\x00\x00"
    drive.set_torque(1.0)
    drive.sync()
    assert rig.plant.u == pytest.approx(1.0, abs=0.03)


def test_fault_that_does_not_reset_fails_enable(make_rig):
    rig = make_rig()
    rig.sim.inject_fault(0x7305, resettable=False)
    with pytest.raises(DriveEnableError, match=r"fault reset.*0x0208 \(FAULT\)"):
        rig.drive.enable()
    assert not rig.drive.enabled


def test_drive_refusing_to_enable(make_rig):
    rig = make_rig(sim_kwargs={})
    rig.sim.refuse_enable = True
    t0 = time.monotonic()
    with pytest.raises(DriveEnableError) as info:
        rig.drive.enable()
    assert time.monotonic() - t0 < 2.0
    message = str(info.value)
    assert "OPERATION ENABLED" in message and "0x0233 (SWITCHED ON)" in message
    assert rig.sim.state is State402.SWITCH_ON_DISABLED  # enable() disabled it again
    assert any(f.kind == "enable" for f in rig.drive.faults)


def test_wrong_rated_torque_in_rig_file_fails_enable(make_rig):
    rig = make_rig(sim_kwargs={"motor_rated_torque_nm": 12.5})
    with pytest.raises(DriveEnableError, match=r"12\.5 N·m \(0x6076\).*rated_torque_nm is 10"):
        rig.drive.enable()


def test_no_drive_on_the_bus(make_rig):
    # canopen's 0.3 s per SDO, not the tests' generous 2 s: what is tested is that no answer
    # ends enable() after the SDO timeout, not after a hang.
    rig = make_rig(with_sim=False, sdo_timeout_s=0.3)
    t0 = time.monotonic()
    with pytest.raises(DriveEnableError, match="mode of operation.*no SDO answer"):
        rig.drive.enable()
    assert time.monotonic() - t0 < 2.0  # SDO timeouts, not hangs


def test_sdo_timeout_is_the_rig_files(make_rig):
    rig = make_rig(with_sim=False, sdo_timeout_s=1.0)
    t0 = time.monotonic()
    with pytest.raises(DriveEnableError, match="no SDO answer"):
        rig.drive.enable()
    # canopen's own 0.3 s (one retry) would have given up after about 0.6 s.
    assert time.monotonic() - t0 >= 1.0


def test_heartbeat_loss_detected_within_the_configured_time(make_rig):
    rig = make_rig()
    drive = rig.drive
    drive.enable()
    assert drive.heartbeat_age_s() < 0.1
    assert not drive.heartbeat_lost
    rig.sim.stop_heartbeat()
    stopped = time.monotonic()
    assert rig.fault_event.wait(1.0)
    detected = time.monotonic() - stopped
    fault = rig.faults[0]
    assert fault.kind == "heartbeat" and "heartbeat lost" in fault.message
    # last heartbeat ≤ 20 ms before the stop, timeout 100 ms, watchdog tick 10 ms, plus slack
    # for a busy 2-core machine
    assert 0.075 <= detected <= 0.1 + 0.01 + 0.1, detected
    assert drive.heartbeat_lost and drive.heartbeat_age_s() > 0.1
    assert not drive.ok and not drive.enabled
    drive.sync()  # still never raises
    with pytest.raises(DriveFaultError, match="heartbeat lost"):
        drive.check()


def test_drive_disappears(make_rig):
    rig = make_rig(max_missed_tpdo=3, sdo_timeout_s=0.3)  # the disable's SDO times out
    drive = rig.drive
    drive.enable()
    rig.sim.go_silent()
    for _ in range(3):
        drive.sync()
    assert drive.missed_tpdo == 3
    assert any(f.kind == "tpdo" for f in drive.active_faults)
    t0 = time.monotonic()
    drive.disable()  # SDO goes unanswered: recorded, not raised
    assert time.monotonic() - t0 < 1.5
    assert any(f.kind == "disable" and "no SDO answer" in f.message for f in drive.faults)
    assert wait_for(lambda: drive.heartbeat_lost)


def test_drive_reboot_is_a_fault(make_rig):
    rig = make_rig()
    rig.drive.enable()
    rig.host_bus.send(can.Message(arbitration_id=0x000, data=[0x81, 7], is_extended_id=False))
    assert wait_for(lambda: any(f.kind == "heartbeat" for f in rig.drive.active_faults))
    assert "rebooted" in rig.drive.active_faults[0].message
    assert not rig.drive.enabled


def test_send_failure_is_recorded_not_raised(make_rig):
    rig = make_rig()
    drive = rig.drive
    drive.enable()
    drive.set_torque(1.0)
    drive.sync()
    rig.host_bus.shutdown()  # the adapter goes away: every send now raises CanOperationError
    drive.set_torque(1.0)
    drive.sync()
    drive.quick_stop()
    drive.disable()
    drive.disable()
    assert not drive.ok
    # the receive thread reports its own end (it notices within one poll interval)
    assert wait_for(lambda: any(f.kind == "thread" for f in drive.faults))
    assert {"bus", "disable", "quick stop"} <= {f.kind for f in drive.faults}
    bus_fault = next(f for f in drive.faults if f.kind == "bus")
    assert "not sent" in bus_fault.message and "closed bus" in bus_fault.message
    drive.close()


def test_missed_tpdos_are_counted_and_become_a_fault(make_rig):
    rig = make_rig(max_missed_tpdo=5)
    drive = rig.drive
    drive.enable()
    drive.sync()
    good = drive.read()
    rig.sim.mute_pdo = True
    for _ in range(4):
        drive.sync()
    assert drive.missed_tpdo == 4 and drive.ok
    assert drive.read() == good  # last values held
    drive.sync()
    assert not drive.ok and drive.active_faults[0].kind == "tpdo"
    rig.sim.mute_pdo = False
    drive.sync()
    assert drive.consecutive_missed_tpdo == 0


def test_plant_failure_reaches_the_driver(make_rig):
    class Exploding(SpringDamperWheel):
        def step(self, motor_torque_nm: float) -> None:
            if self.steps == 2:
                raise RuntimeError("world diverged")
            super().step(motor_torque_nm)

    rig = make_rig(Exploding(0.01))
    rig.drive.enable()
    for _ in range(3):
        rig.drive.sync()
    assert rig.fault_event.wait(1.0)
    assert rig.faults[0].code == 0x6100
    assert [str(e) for e in rig.sim.errors] == ["world diverged"]
    rig.sim.errors.clear()


def test_column_torque_sensor_zero(make_rig):
    rig = make_rig()
    drive = rig.drive
    sensor = drive.torque_sensor
    drive.enable()
    for _ in range(20):
        drive.sync()  # wheel released, at rest: column torque 0
    sensor.zero()
    assert sensor.offset_nm == pytest.approx(0.0, abs=1e-3)
    for _ in range(50):
        drive.set_torque(1.2)
        drive.sync()
    assert sensor.read() == pytest.approx(drive.column_torque_nm() - sensor.offset_nm)
    assert sensor.read() > 0.5


def test_cycle_time_over_the_virtual_bus(make_rig, capsys):
    """Measures (does not assert) set_torque + sync + read at the simulated rig's settings."""
    sim_cfg = load_drive_config(ROOT / "hardware" / "rigs" / "simulated.toml")
    rig = make_rig(
        SpringDamperWheel(0.001),
        loop_rate_hz=sim_cfg.loop_rate_hz,
        tpdo_timeout_ms=sim_cfg.tpdo_timeout_ms,
        max_missed_tpdo=10_000,
    )
    drive = rig.drive
    drive.enable()
    for _ in range(200):  # warm up
        drive.set_torque(0.1)
        drive.sync()
    n = 3000
    totals, syncs = [], []
    perf = time.perf_counter
    for i in range(n):
        t0 = perf()
        drive.set_torque(0.5 * math.sin(i * 0.01))
        t1 = perf()
        drive.sync()
        drive.read()
        t2 = perf()
        totals.append(t2 - t0)
        syncs.append(t2 - t1)
    totals.sort()
    ms = [x * 1e3 for x in totals]
    line = (
        f"\ncycle (set_torque+sync+read) over virtual bus, {n} cycles back to back: "
        f"median {statistics.median(ms):.3f} ms, p90 {ms[int(0.9 * n)]:.3f} ms, "
        f"p99 {ms[int(0.99 * n)]:.3f} ms, max {ms[-1]:.3f} ms; "
        f"sync median {statistics.median(syncs) * 1e3:.3f} ms; "
        f"missed TPDO {drive.missed_tpdo - 0} of {drive.cycle_count}"
    )
    with capsys.disabled():
        print(line)


def test_a_failed_enable_leaves_garbage_collection_on(make_rig, fast_protocol):
    # A real-time trial pauses collection (DeviceLoop.run_trial); a drive that cannot be
    # enabled must not leave it paused for the rest of the process.
    import gc

    from steerlab.hardware.loop import DeviceLoop
    from steerlab.protocols.engine import LoopControl
    from steerlab.protocols.session import build_plan

    rig = make_rig(with_sim=False)
    plan = build_plan(fast_protocol, 1)
    loop = DeviceLoop(rig.drive, rig.drive.torque_sensor, glove=None, realtime=True)
    gc.enable()  # the tests pause it around this one (tests/conftest.py); the lab does not
    with pytest.raises(DriveEnableError):
        next(loop.run_trial(plan.setup(plan.trials[0]), LoopControl()))
    assert gc.isenabled()
