"""A simulated CiA 402 servo drive: a CANopen node on a python-can bus (normally the virtual bus)
that answers the real protocol, so the real driver (:class:`~hardware.can.cia402.CiA402Drive`)
runs unchanged against it, and so does canopen's own master (``RemoteNode``, ``BaseNode402``,
``PdoMap``) with the node's EDS file, :data:`SIMULATED_DRIVE_EDS` (``hardware/sim/
steerlab_drive.eds``; object by object in ``docs/simulated-drive.md``).

What it speaks (CiA 301 / CiA 402):

- NMT slave: start, stop, pre-operational, reset node / communication with boot-up. In STOPPED
  it answers nothing but NMT (and keeps producing and consuming heartbeats): no SDO, no PDO,
  no EMCY.
- SDO server (canopen's :class:`canopen.LocalNode`) over the object dictionary of the EDS file.
- PDOs: four RPDOs and four TPDOs with generic mapping (any mappable object, up to 64 bits,
  mapped the way drives require: PDO invalid, count 0, entries, count). RPDO transmission types
  0–240 act at the next SYNC, 254/255 at once. TPDO types 1–240 go out every n-th SYNC, 0 after
  a SYNC when a mapped value changed, 254/255 when a mapped value changes (event), when the
  event timer (sub 5, ms) expires, and once on entering OPERATIONAL, never twice within the
  inhibit time (sub 3, 100 µs). PDOs only in NMT OPERATIONAL.
- SYNC consumer on the COB-ID of 0x1005; EMCY producer on the COB-ID of 0x1014 (none while
  its bit 31 is set), with the error history 0x1003; heartbeat producer (0x1017) and consumer
  (0x1016) with the abort connection option 0x6007.
- The CiA 402 state machine, cyclic synchronous torque (mode 10, the one mode of 0x6502).

On each SYNC: the synchronous RPDOs received since the last SYNC are applied (controlword,
target torque, ...), the plant advances one sample with the resulting motor torque (zero unless
OPERATION ENABLED in mode 10; clamped at max torque 0x6072), and the synchronous TPDOs go out
with the plant's new state. A real drive latches its actual values at the SYNC instant instead,
so on hardware the values read after sync() are one sample older than in this simulation. SYNC
is also the simulation's clock: the plant advances on every SYNC, whatever the NMT state.

Fault injection for tests: :meth:`SimulatedDrive.stop_heartbeat`, :meth:`~SimulatedDrive.go_silent`
(the drive disappears), :meth:`~SimulatedDrive.inject_fault` (EMCY + FAULT state),
``refuse_enable`` (stays SWITCHED ON), ``mute_pdo`` (no TPDO goes out).

With ``[drive.torque_sensor] source = "node"`` the column torque comes from a node of its own
(:mod:`hardware.can.sim_sensor`); the drive then still steps the plant, through the
:class:`~hardware.can.sim_sensor.SharedPlant` both nodes read.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Protocol

import can
import canopen
from canopen.objectdictionary import (
    INTEGER8,
    INTEGER16,
    INTEGER32,
    UNSIGNED8,
    UNSIGNED16,
    UNSIGNED32,
    ObjectDictionary,
    ODRecord,
    ODVariable,
)
from canopen.sdo import SdoAbortedError

from .config import DriveConfig
from .frames import (
    ABORT_CONNECTION_OPTION,
    CONSUMER_HEARTBEAT,
    CONTROLWORD,
    EMCY_HEARTBEAT_ERROR,
    ERROR_CODE,
    ERROR_REGISTER,
    MAX_TORQUE,
    MODE_CST,
    MODES_OF_OPERATION,
    MODES_OF_OPERATION_DISPLAY,
    MOTOR_RATED_TORQUE,
    NMT_COB_ID,
    PDO_INVALID,
    POSITION_ACTUAL,
    STATUSWORD,
    STATUSWORD_OF,
    TARGET_TORQUE,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
    FrameError,
    MappedObject,
    NmtCommand,
    NmtState,
    PdoLayout,
    State402,
    emcy_payload,
    sdo_rx_cob_id,
)
from .scaling import DriveScaling
from .transport import BusReader

log = logging.getLogger(__name__)

#: The simulated drive's EDS file, as the shipped simulated rig configures the node.
SIMULATED_DRIVE_EDS: Path = Path(
    str(resources.files("steerlab.hardware.sim").joinpath("steerlab_drive.eds"))
)

DEVICE_TYPE_SERVO = 0x0002_0192  # CiA 402 (0x192), servo drive
PRE_DEFINED_ERROR_FIELD = 0x1003
COB_ID_SYNC = 0x1005
COB_ID_EMCY = 0x1014
SUPPORTED_DRIVE_MODES = 0x6502
SENSOR_OBJECT = 0x2000  # column torque in the EDS (the shipped rig's [drive.torque_sensor])
_EDS_SENSOR = (SENSOR_OBJECT, 0, 32)
_SIGNED = (INTEGER8, INTEGER16, INTEGER32)
_BITS = {INTEGER8: 8, INTEGER16: 16, INTEGER32: 32, UNSIGNED8: 8, UNSIGNED16: 16, UNSIGNED32: 32}
_ERROR_HISTORY = 8  # sub-indices of 0x1003 in the EDS
_COB_EXTENDED = 0x2000_0000  # COB-ID bit 29: 29-bit identifier (not supported)
_SYNC_PRODUCER = 0x4000_0000  # 0x1005 bit 30: this node generates SYNC (it does not)

ABORT_NOT_EXIST = 0x0602_0000
ABORT_NOT_MAPPABLE = 0x0604_0041
ABORT_PDO_LENGTH = 0x0604_0042
ABORT_VALUE_RANGE = 0x0609_0030
ABORT_UNSUPPORTED_ACCESS = 0x0601_0000
ABORT_DEVICE_STATE = 0x0800_0022

EMCY_INTERNAL_SOFTWARE = 0x6100
EMCY_PDO_LENGTH = 0x8210

_NMT_TARGET = {
    NmtCommand.START: NmtState.OPERATIONAL,
    NmtCommand.STOP: NmtState.STOPPED,
    NmtCommand.PRE_OPERATIONAL: NmtState.PRE_OPERATIONAL,
}


class Plant(Protocol):
    """The simulated world behind the motor shaft, in wheel units (hardware.interfaces)."""

    def step(self, motor_torque_nm: float) -> None:
        """Advance one sample with this motor torque on the wheel axis."""

    def read(self) -> tuple[float, float, float, float]:
        """(angle rad, velocity rad/s, motor torque actual N·m, column torque N·m)."""


# -- object dictionary --------------------------------------------------------------------------


def _var(
    name: str,
    index: int,
    subindex: int,
    data_type: int,
    access: str,
    default: int | None = None,
    mappable: bool = False,
) -> ODVariable:
    v = ODVariable(name, index, subindex)
    v.data_type = data_type
    v.access_type = access
    v.default = default
    v.pdo_mappable = mappable
    return v


def build_object_dictionary(
    config: DriveConfig, *, motor_rated_torque_nm: float | None = None
) -> ObjectDictionary:
    """The simulated drive's object dictionary: :data:`SIMULATED_DRIVE_EDS` for node
    ``config.node_id``, with the rig's motor rated torque (0x6076, or ``motor_rated_torque_nm``
    to simulate a drive that disagrees with the rig file) and its column torque object
    (``[drive.torque_sensor]``; absent unless ``source = "pdo"``).

    Defaults mimic a drive out of the box: the predefined PDO set with a mapping the driver has
    to replace, TPDO3/TPDO4 enabled on SYNC, no heartbeat until configured."""
    od = canopen.import_od(str(SIMULATED_DRIVE_EDS), config.node_id)
    od.bitrate = config.bitrate
    rated = config.rated_torque_nm if motor_rated_torque_nm is None else motor_rated_torque_nm
    rated_var = od.get_variable(MOTOR_RATED_TORQUE)
    assert rated_var is not None  # in the EDS
    rated_var.default = round(rated * 1000)

    sensor = config.torque_sensor
    if sensor.source == "pdo" and (sensor.index, sensor.subindex, sensor.bits) == _EDS_SENSOR:
        return od
    del od[SENSOR_OBJECT]
    if sensor.source != "pdo":
        return od
    dtype = INTEGER32 if sensor.bits == 32 else INTEGER16
    obj = _var("Column torque", sensor.index, sensor.subindex, dtype, "ro", 0, mappable=True)
    if sensor.subindex == 0:
        od.add_object(obj)
    else:
        record = ODRecord("Column torque sensor", sensor.index)
        record.add_member(
            _var(
                "Highest sub-index supported",
                sensor.index,
                0,
                UNSIGNED8,
                "const",
                sensor.subindex,
            )
        )
        record.add_member(obj)
        od.add_object(record)
    return od


# -- PDO state ----------------------------------------------------------------------------------


@dataclass
class _Rpdo:
    cob_id: int
    synchronous: bool  # transmission type 0–240: act at the next SYNC; 254/255: at once
    layout: PdoLayout
    pending: tuple[int, ...] | None = None


@dataclass
class _Tpdo:
    cob_id: int
    trans_type: int
    layout: PdoLayout
    inhibit_s: float = 0.0
    event_timer_s: float = 0.0  # 0: no event timer
    last_values: tuple[int, ...] | None = None  # None: not sent since entering OPERATIONAL
    last_sent: float = -math.inf  # time.monotonic()

    @property
    def event_driven(self) -> bool:
        return self.trans_type >= 254


# -- the node -----------------------------------------------------------------------------------


class SimulatedDrive:
    """CiA 402 drive node ``config.node_id`` on ``bus``, driving ``plant``.

    Runs its own receive thread from :meth:`start` (called by the constructor unless
    ``autostart=False``) until :meth:`close`. Exceptions in that thread (a plant that raises,
    a bus that fails) are kept in :attr:`errors`; a plant failure also puts the drive into
    FAULT with EMCY 0x6100, as a real drive's firmware error would.
    """

    def __init__(
        self,
        bus: can.BusABC,
        config: DriveConfig,
        plant: Plant,
        *,
        autostart: bool = True,
        motor_rated_torque_nm: float | None = None,
    ):
        self.config = config
        self.plant = plant
        self.scaling = DriveScaling(config)
        self._bus = bus
        n = config.node_id
        self.node_id = n
        self._od = build_object_dictionary(config, motor_rated_torque_nm=motor_rated_torque_nm)
        self._network = canopen.Network(bus)
        self._node = canopen.LocalNode(n, self._od)
        self._network.add_node(self._node)
        self._node.add_read_callback(self._on_sdo_read)
        self._node.add_write_callback(self._on_sdo_write)
        self._sdo_rx_id = sdo_rx_cob_id(n)
        self._lock = threading.RLock()

        self.state = State402.NOT_READY_TO_SWITCH_ON
        self._nmt = NmtState.BOOTUP
        self._controlword = 0
        self._target = 0
        self._fault_code = 0
        self._error_register = 0
        self._fault_resettable = True
        self._errors_history: list[int] = []  # 0x1003, newest first
        # communication objects as configured (rebuilt from the object dictionary when dirty)
        self._comm_dirty = True
        self._sync_id = 0
        self._emcy_id: int | None = None
        self._rpdos: dict[int, _Rpdo] = {}  # by COB-ID, in PDO number order
        self._sync_tpdos: list[_Tpdo] = []
        self._event_tpdos: list[_Tpdo] = []
        self._pos = self._vel = self._torque_actual = self._column = 0
        self._applied = 0.0
        #: time.monotonic() since which the applied torque is zero (None while it is not);
        #: CLOCK_MONOTONIC is system-wide, so another process can compare it with its own.
        self.zero_torque_since: float | None = time.monotonic()
        # consumer heartbeat (0x1016:01): producer node, timeout s, last heartbeat (None:
        # not monitoring; CiA 301 starts monitoring at the first heartbeat after configuration)
        self._consumer: tuple[int, float] | None = None
        self._consumer_last: float | None = None  # bus timestamp (time.time()) of the last one
        self._bus_time: float | None = None  # bus timestamp of the newest frame since the tick
        self.host_heartbeats_lost = 0
        self.connection_lost_at: float | None = None

        self.refuse_enable = False
        self.mute_pdo = False
        self._silent = False
        self.sync_count = 0
        self.enabled_syncs = 0  # SYNCs met in OPERATION ENABLED: the host's control cycles
        self.ignored_frames = 0
        self.errors: list[BaseException] = []
        self._reader = BusReader(
            bus,
            self._on_frame,
            self._on_reader_failure,
            name=f"SimulatedDrive node {n} rx",
            on_tick=self._on_tick,
            poll_s=0.002,
        )
        self._started = False
        if autostart:
            self.start()

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> None:
        """Power on: boot-up message, NMT PRE-OPERATIONAL, CiA 402 SWITCH ON DISABLED."""
        with self._lock:
            self._latch_plant()
            self._power_on()
        if not self._started:
            self._started = True
            self._reader.start()

    def close(self) -> None:
        """Stop heartbeat and the receive thread. The bus stays open."""
        self._node.nmt.stop_heartbeat()
        self._reader.stop()

    def __enter__(self) -> SimulatedDrive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- fault injection -----------------------------------------------------------------------

    def stop_heartbeat(self) -> None:
        self._node.nmt.stop_heartbeat()

    def go_silent(self) -> None:
        """The drive disappears: no heartbeat, no answer to anything."""
        with self._lock:
            self._silent = True
            self._node.nmt.stop_heartbeat()

    def inject_fault(
        self,
        code: int = 0x2310,
        error_register: int = 0x03,
        vendor_data: bytes = b"",
        *,
        resettable: bool = True,
    ) -> None:
        """Go to FAULT (power stage off) and send EMCY ``code``. With ``resettable=False`` a
        fault reset leaves the drive in FAULT (the cause persists)."""
        with self._lock:
            self._enter_fault(code, error_register | 0x01, vendor_data)
            self._fault_resettable = resettable
            self._power_stage()
            self._service_event_tpdos(time.monotonic())

    @property
    def watching_host(self) -> bool:
        """The consumer heartbeat (0x1016) is configured and monitoring its producer."""
        return self._consumer is not None and self._consumer_last is not None

    @property
    def applied_torque_nm(self) -> float:
        """The torque the power stage applies now (N·m, wheel axis)."""
        return self._applied

    def _apply(self, torque_nm: float) -> None:
        if torque_nm == 0.0:
            if self._applied != 0.0 or self.zero_torque_since is None:
                self.zero_torque_since = time.monotonic()
        else:
            self.zero_torque_since = None
        self._applied = torque_nm

    @property
    def statusword(self) -> int:
        return STATUSWORD_OF[self.state]

    @property
    def nmt_state(self) -> int:
        """NMT state as the heartbeat reports it (:class:`~hardware.can.frames.NmtState`)."""
        return int(self._nmt)

    @property
    def target_torque_permille(self) -> int:
        return self._target

    @property
    def error_history(self) -> list[int]:
        """0x1003: the EMCY error codes sent, newest first (at most 8)."""
        return list(self._errors_history)

    def od_value(self, index: int, subindex: int = 0) -> int:
        """Current value of a stored object (configuration written by SDO, or its default).

        :raises KeyError: no such object in the object dictionary.
        """
        var = self._od.get_variable(index, subindex)
        if var is None:
            raise KeyError(f"0x{index:04X}:{subindex:02X} is not in the object dictionary")
        data = self._node.data_store.get(index, {}).get(subindex)
        if data is not None:
            return int(var.decode_raw(data))
        value = var.value if var.value is not None else var.default
        return 0 if value is None else int(value)

    # -- frames --------------------------------------------------------------------------------

    def _on_frame(self, msg: can.Message) -> None:
        cid = msg.arbitration_id
        with self._lock:
            if self._silent:
                return
            self._bus_time = msg.timestamp
            try:
                self._refresh_comm()
                if cid == NMT_COB_ID:
                    self._on_nmt(bytes(msg.data))
                elif cid == self._sync_id and len(msg.data) <= 1:
                    self._on_sync()
                elif self._consumer is not None and cid == 0x700 + self._consumer[0]:
                    # CiA 301: the heartbeat consumer works in every NMT state.
                    self._consumer_last = msg.timestamp
                elif self._nmt is NmtState.STOPPED:
                    # CiA 301: in STOPPED only NMT (and heartbeat / node guarding) is served.
                    self.ignored_frames += 1
                elif cid == self._sdo_rx_id:
                    if len(msg.data) == 8:  # SDO requests are always 8 bytes (CiA 301)
                        self._network.notify(cid, msg.data, msg.timestamp)
                    else:
                        self.ignored_frames += 1
                elif (rpdo := self._rpdos.get(cid)) is not None:
                    self._on_rpdo(rpdo, bytes(msg.data))
            except (struct.error, SdoAbortedError, FrameError):
                # A real drive ignores frames it cannot parse; so do we (counted for tests).
                self.ignored_frames += 1
            self._power_stage()
            self._service_event_tpdos(time.monotonic())

    def _power_stage(self) -> None:
        # Out of OPERATION ENABLED the power stage is off at once, SYNC or not.
        if self._applied != 0.0 and self.state is not State402.OPERATION_ENABLED:
            self._apply(0.0)

    def _on_tick(self, now: float) -> None:
        """The drive's own timers, run at least every 2 ms even on a silent bus: the watch on
        its host (consumer heartbeat) and the event-driven TPDOs' event timers.

        Heartbeat times are the frames' bus timestamps (wall clock at sending): a real drive
        sees each frame when it is on the wire, whereas this thread may run late on a busy
        computer and find frames queued. Until the queue is drained, the newest frame taken is
        "now"."""
        with self._lock:
            self._service_event_tpdos(now)  # nothing while silent: the link is cut
            last = self._consumer_last
            if self._consumer is None or last is None:
                return
            bus_now = self._bus_time if self._bus_time is not None else time.time()
            self._bus_time = None  # the next idle tick (no frame meanwhile) uses the clock
            if bus_now - last <= self._consumer[1]:
                return
            # CiA 301 heartbeat consumer: the producer is lost; monitoring stops until its
            # next heartbeat. CiA 402: react per the abort connection option code 0x6007.
            self._consumer_last = None
            self.host_heartbeats_lost += 1
            self.connection_lost_at = now
            self._connection_lost()
            self._power_stage()
            self._service_event_tpdos(now)

    def _connection_lost(self) -> None:
        option = self.od_value(ABORT_CONNECTION_OPTION)
        active = self.state in (State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE)
        if option == 1 and active:
            self._enter_fault(EMCY_HEARTBEAT_ERROR, 0x11)  # FAULT, power stage off
            return
        if active and option == 2:
            self.state = State402.SWITCH_ON_DISABLED  # disable voltage
        elif self.state is State402.OPERATION_ENABLED and option == 3:
            self.state = State402.QUICK_STOP_ACTIVE  # in torque mode: zero torque at once
        self._send_emcy(EMCY_HEARTBEAT_ERROR, 0x11)

    def _on_reader_failure(self, exc: BaseException) -> None:
        self.errors.append(exc)

    # -- NMT -----------------------------------------------------------------------------------

    def _on_nmt(self, data: bytes) -> None:
        if len(data) != 2 or data[1] not in (0, self.node_id):
            self.ignored_frames += 1
            return
        command = data[0]
        if command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            if command == NmtCommand.RESET_NODE:
                self._node.data_store.clear()
                self._errors_history.clear()
            else:
                for index in [i for i in self._node.data_store if 0x1000 <= i <= 0x1FFF]:
                    del self._node.data_store[index]
            self._comm_dirty = True
            self._consumer = self._consumer_last = None
            self._node.nmt.stop_heartbeat()
            self._power_on(keep_drive_state=command == NmtCommand.RESET_COMMUNICATION)
            return
        try:
            target = _NMT_TARGET[NmtCommand(command)]
        except (ValueError, KeyError):
            self.ignored_frames += 1
            return
        was_operational = self._nmt is NmtState.OPERATIONAL
        self._set_nmt(NmtCommand(command), target)
        if target is not NmtState.OPERATIONAL:
            for rpdo in self._rpdos.values():
                rpdo.pending = None
            if was_operational and self.state in (
                State402.OPERATION_ENABLED,
                State402.QUICK_STOP_ACTIVE,
            ):
                # Losing the PDO channel must not leave torque on (CiA 402 0x6007 "disable
                # voltage" reaction).
                self.state = State402.SWITCH_ON_DISABLED
        elif not was_operational:
            self._refresh_comm()
            for tpdo in self._event_tpdos + self._sync_tpdos:
                tpdo.last_values = None  # event-driven TPDOs go out once on entering

    def _set_nmt(self, command: NmtCommand, state: NmtState) -> None:
        # canopen's NMT slave keeps the heartbeat producer's state byte (and sends the boot-up)
        self._nmt = state
        self._node.nmt.send_command(int(command))

    def _power_on(self, keep_drive_state: bool = False) -> None:
        self._set_nmt(NmtCommand.RESET_NODE, NmtState.BOOTUP)  # sends the boot-up message
        # PRE-OPERATIONAL starts the heartbeat per 0x1017
        self._set_nmt(NmtCommand.PRE_OPERATIONAL, NmtState.PRE_OPERATIONAL)
        for rpdo in self._rpdos.values():
            rpdo.pending = None
        if not keep_drive_state:
            self._controlword = 0
            self._target = 0
            if self.state is not State402.FAULT:
                self.state = State402.SWITCH_ON_DISABLED

    # -- PDO, SYNC, EMCY -----------------------------------------------------------------------

    def _on_rpdo(self, rpdo: _Rpdo, data: bytes) -> None:
        if self._nmt is not NmtState.OPERATIONAL:
            return
        if len(data) < rpdo.layout.size:
            # CiA 301: a too-short RPDO is not processed and reported with EMCY 0x8210.
            self._send_emcy(EMCY_PDO_LENGTH, 0x11)
            return
        values = rpdo.layout.decode(data)
        if rpdo.synchronous:
            rpdo.pending = values
        else:
            self._apply_rpdo(rpdo.layout, values)

    def _apply_rpdo(self, layout: PdoLayout, values: tuple[int, ...]) -> None:
        for obj, value in zip(layout.objects, values, strict=True):
            self._write_object(obj.index, obj.subindex, value)

    def _on_sync(self) -> None:
        self.sync_count += 1
        operational = self._nmt is NmtState.OPERATIONAL
        if operational:
            for rpdo in self._rpdos.values():
                if rpdo.pending is not None:
                    values, rpdo.pending = rpdo.pending, None
                    self._apply_rpdo(rpdo.layout, values)
        torque = self._motor_torque_nm()
        self._apply(torque)
        if self.state is State402.OPERATION_ENABLED:
            self.enabled_syncs += 1
        try:
            self.plant.step(torque)
            self._latch_plant()
        except Exception as exc:
            self.errors.append(exc)
            log.exception("simulated drive node %d: plant failed", self.node_id)
            self._enter_fault(EMCY_INTERNAL_SOFTWARE, 0x81)
        if operational and not self.mute_pdo:
            for tpdo in self._sync_tpdos:
                if tpdo.trans_type == 0:  # synchronous acyclic: after a SYNC, if changed
                    values = self._tpdo_values(tpdo)
                    if values != tpdo.last_values:
                        self._send_tpdo(tpdo, values, time.monotonic())
                elif self.sync_count % tpdo.trans_type == 0:
                    self._send_tpdo(tpdo, self._tpdo_values(tpdo), time.monotonic())

    def _tpdo_values(self, tpdo: _Tpdo) -> tuple[int, ...]:
        return tuple(self._read_object(o.index, o.subindex) for o in tpdo.layout.objects)

    def _send_tpdo(self, tpdo: _Tpdo, values: tuple[int, ...], now: float) -> None:
        self._send(tpdo.cob_id, tpdo.layout.encode(values))
        tpdo.last_values = values
        tpdo.last_sent = now

    def _service_event_tpdos(self, now: float) -> None:
        """Send the event-driven TPDOs that are due: a mapped value changed (or none was sent
        since entering OPERATIONAL) or the event timer expired, and the inhibit time is over.
        An event within the inhibit time is sent when it ends (by a later tick)."""
        if self._nmt is not NmtState.OPERATIONAL or self.mute_pdo or self._silent:
            return
        self._refresh_comm()
        for tpdo in self._event_tpdos:
            values = self._tpdo_values(tpdo)
            timer_due = tpdo.event_timer_s > 0 and now - tpdo.last_sent >= tpdo.event_timer_s
            if values == tpdo.last_values and not timer_due:
                continue
            if now - tpdo.last_sent < tpdo.inhibit_s:
                continue
            try:
                self._send_tpdo(tpdo, values, now)
            except FrameError as exc:  # a mapped value that does not fit: a bug, not the bus
                self.errors.append(exc)

    def _latch_plant(self) -> None:
        angle, velocity, torque_actual, column = self.plant.read()
        s = self.scaling
        self._pos = s.angle_to_counts(angle)
        self._vel = s.rad_s_to_velocity(velocity)
        self._torque_actual = s.torque_to_permille(torque_actual)
        self._column = s.torque_to_sensor(column)

    def _motor_torque_nm(self) -> float:
        if self.state is not State402.OPERATION_ENABLED:
            return 0.0
        if self.od_value(MODES_OF_OPERATION) != MODE_CST:
            return 0.0
        limit = self.od_value(MAX_TORQUE)
        permille = max(-limit, min(limit, self._target))
        return self.scaling.permille_to_torque(permille)

    def _send(self, cob_id: int, data: bytes) -> None:
        if self._silent:
            return
        self._network.send_message(cob_id, data)

    def _send_emcy(self, code: int, register: int, vendor_data: bytes = b"") -> None:
        if code & 0xFF00:
            self._errors_history.insert(0, code)
            del self._errors_history[_ERROR_HISTORY:]
        self._refresh_comm()
        # CiA 301: no EMCY in STOPPED, none while 0x1014 marks it invalid.
        if self._emcy_id is None or self._nmt is NmtState.STOPPED:
            return
        self._send(self._emcy_id, emcy_payload(code, register, vendor_data))

    def _enter_fault(self, code: int, register: int, vendor_data: bytes = b"") -> None:
        # FAULT REACTION ACTIVE is instantaneous here: the power stage is simply off.
        self.state = State402.FAULT
        self._fault_code = code
        self._error_register = register
        self._send_emcy(code, register, vendor_data)

    # -- CiA 402 state machine -----------------------------------------------------------------

    def _apply_controlword(self, cw: int) -> None:
        rising_reset = bool(cw & 0x80) and not (self._controlword & 0x80)
        self._controlword = cw
        s = self.state
        S = State402
        if s is S.FAULT:
            if rising_reset and self._fault_resettable:
                self.state = S.SWITCH_ON_DISABLED
                self._fault_code = 0
                self._error_register = 0
                self._send_emcy(0x0000, 0x00)  # CiA 301: errors cleared
            return
        if cw & 0x80:
            return  # fault reset outside FAULT: no transition
        disable_voltage = cw & 0x02 == 0
        quick_stop = cw & 0x06 == 0x02
        shutdown = cw & 0x07 == 0x06
        switch_on = cw & 0x0F == 0x07
        enable_op = cw & 0x0F == 0x0F
        if s is S.SWITCH_ON_DISABLED:
            if shutdown:
                self.state = S.READY_TO_SWITCH_ON
        elif s is S.READY_TO_SWITCH_ON:
            if disable_voltage or quick_stop:
                self.state = S.SWITCH_ON_DISABLED
            elif switch_on:
                self.state = S.SWITCHED_ON
            elif enable_op:
                self.state = S.SWITCHED_ON if self.refuse_enable else S.OPERATION_ENABLED
        elif s is S.SWITCHED_ON:
            if disable_voltage or quick_stop:
                self.state = S.SWITCH_ON_DISABLED
            elif shutdown:
                self.state = S.READY_TO_SWITCH_ON
            elif enable_op and not self.refuse_enable:
                self.state = S.OPERATION_ENABLED
        elif s is S.OPERATION_ENABLED:
            if disable_voltage:
                self.state = S.SWITCH_ON_DISABLED
            elif quick_stop:
                self.state = S.QUICK_STOP_ACTIVE
            elif shutdown:
                self.state = S.READY_TO_SWITCH_ON
            elif switch_on:
                self.state = S.SWITCHED_ON
        elif s is S.QUICK_STOP_ACTIVE:
            if disable_voltage:
                self.state = S.SWITCH_ON_DISABLED
            elif enable_op and not self.refuse_enable:
                self.state = S.OPERATION_ENABLED

    # -- object access -------------------------------------------------------------------------

    def _dynamic(self, index: int, subindex: int) -> int | None:
        sensor = self.config.torque_sensor
        if index == STATUSWORD:
            return self.statusword
        if index == MODES_OF_OPERATION_DISPLAY:
            return self.od_value(MODES_OF_OPERATION)
        if index == POSITION_ACTUAL:
            return self._pos
        if index == VELOCITY_ACTUAL:
            return self._vel
        if index == TORQUE_ACTUAL:
            return self._torque_actual
        if index == CONTROLWORD:
            return self._controlword
        if index == TARGET_TORQUE:
            return self._target
        if index == ERROR_CODE:
            return self._fault_code
        if index == ERROR_REGISTER:
            return self._error_register
        if index == PRE_DEFINED_ERROR_FIELD:
            history = self._errors_history
            if subindex == 0:
                return len(history)
            return history[subindex - 1] if subindex <= len(history) else 0
        if sensor.source == "pdo" and (index, subindex) == (sensor.index, sensor.subindex):
            return self._column
        return None

    def _read_object(self, index: int, subindex: int) -> int:
        value = self._dynamic(index, subindex)
        return self.od_value(index, subindex) if value is None else value

    def _write_object(self, index: int, subindex: int, value: int) -> None:
        """A value received in an RPDO, written as an SDO download would write it."""
        if index == CONTROLWORD:
            self._apply_controlword(value)
        elif index == TARGET_TORQUE:
            self._target = value
        else:
            var = self._od.get_variable(index, subindex)
            assert var is not None  # the mapping was checked against the dictionary
            try:
                self._node.set_data(index, subindex, var.encode_raw(value))
            except SdoAbortedError:
                self.ignored_frames += 1  # a value the drive refuses (e.g. a mode it lacks)

    def _on_sdo_read(self, index: int, subindex: int, od: ODVariable, **_: object) -> int | None:
        return self._dynamic(index, subindex)

    def _on_sdo_write(
        self, index: int, subindex: int, od: ODVariable, data: bytes, **_: object
    ) -> None:
        value = od.decode_raw(data)
        if not isinstance(value, int):
            return  # every writable object of this node is an integer; nothing to act on
        if index == MODES_OF_OPERATION and value not in (0, MODE_CST):
            raise SdoAbortedError(ABORT_VALUE_RANGE)  # 0x6502: cyclic synchronous torque only
        if 0x1400 <= index <= 0x1BFF:
            self._check_pdo_write(index, subindex, value)
            self._comm_dirty = True
        elif index == COB_ID_SYNC:
            if value & (_SYNC_PRODUCER | _COB_EXTENDED):
                raise SdoAbortedError(ABORT_VALUE_RANGE)  # not a SYNC producer; 11-bit only
            self._comm_dirty = True
        elif index == COB_ID_EMCY:
            self._check_cob_id_change(index, 0, value)
            self._comm_dirty = True
        elif index == PRE_DEFINED_ERROR_FIELD:
            if value != 0:
                raise SdoAbortedError(ABORT_VALUE_RANGE)  # CiA 301: only 0 (clear) is allowed
            self._errors_history.clear()
        if index in (CONTROLWORD, TARGET_TORQUE):
            self._write_object(index, subindex, value)
        if index == CONSUMER_HEARTBEAT and subindex == 1:
            node, ms = (value >> 16) & 0x7F, value & 0xFFFF
            self._consumer = (node, ms / 1000.0) if node and ms else None
            self._consumer_last = None

    def _check_cob_id_change(self, index: int, subindex: int, value: int) -> None:
        """CiA 301: bit 29 (29-bit identifiers) is not supported, and the identifier of a valid
        object (bit 31 clear) may only change together with making it invalid."""
        if value & _COB_EXTENDED:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        current = self.od_value(index, subindex)
        if (
            not current & PDO_INVALID
            and not value & PDO_INVALID
            and (value & 0x7FF) != (current & 0x7FF)
        ):
            raise SdoAbortedError(ABORT_VALUE_RANGE)

    def _check_pdo_write(self, index: int, subindex: int, value: int) -> None:
        """The CiA 301 rules drives enforce, so a driver that maps in the wrong order fails
        here as it would on the bench."""
        receive = index < 0x1800
        is_comm = (index & 0xFF00) in (0x1400, 0x1800)
        if is_comm:
            if subindex == 1:
                self._check_cob_id_change(index, 1, value)
            elif subindex == 2:
                # 252/253 (RTR) are not supported, 241–251 are reserved
                if not (value <= 240 or value >= 254):
                    raise SdoAbortedError(ABORT_VALUE_RANGE)
            elif subindex == 3 and not self.od_value(index, 1) & PDO_INVALID:
                raise SdoAbortedError(ABORT_DEVICE_STATE)  # inhibit time: only while invalid
            return
        comm = index - 0x200
        if subindex == 0:
            if value and not self.od_value(comm, 1) & PDO_INVALID:
                raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)
            if value > 8:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            bits = 0
            for sub in range(1, value + 1):
                bits += self._mapping_target(self.od_value(index, sub), receive).bits
            if bits > 64:
                raise SdoAbortedError(ABORT_PDO_LENGTH)
            return
        if self.od_value(index, 0) != 0:
            raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)
        self._mapping_target(value, receive)

    def _mapping_target(self, entry: int, receive: bool) -> MappedObject:
        index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        obj = self._od.get_variable(index, subindex)
        if obj is None:
            raise SdoAbortedError(ABORT_NOT_EXIST)
        usable = obj.writable if receive else obj.readable
        if not obj.pdo_mappable or not usable or _BITS.get(obj.data_type or 0) != bits:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        return MappedObject(index, subindex, bits, obj.data_type in _SIGNED, obj.name)

    def _layout(self, mapping: int, receive: bool) -> PdoLayout:
        count = self.od_value(mapping, 0)
        return PdoLayout(
            [
                self._mapping_target(self.od_value(mapping, sub), receive)
                for sub in range(1, count + 1)
            ]
        )

    def _refresh_comm(self) -> None:
        """Rebuild the communication set-up from the object dictionary after a change."""
        if not self._comm_dirty:
            return
        self._comm_dirty = False
        self._sync_id = self.od_value(COB_ID_SYNC) & 0x7FF
        emcy = self.od_value(COB_ID_EMCY)
        self._emcy_id = None if emcy & PDO_INVALID else emcy & 0x7FF
        self._rpdos = {}
        for k in range(4):
            cob = self.od_value(0x1400 + k, 1)
            if cob & PDO_INVALID:
                continue
            try:
                layout = self._layout(0x1600 + k, receive=True)
            except (SdoAbortedError, ValueError):
                continue  # a mapping the drive cannot use: the PDO stays off
            trans = self.od_value(0x1400 + k, 2)
            self._rpdos[cob & 0x7FF] = _Rpdo(cob & 0x7FF, trans <= 240, layout)
        self._sync_tpdos, self._event_tpdos = [], []
        for k in range(4):
            comm = 0x1800 + k
            cob = self.od_value(comm, 1)
            if cob & PDO_INVALID:
                continue
            try:
                layout = self._layout(0x1A00 + k, receive=False)
            except (SdoAbortedError, ValueError):
                continue
            tpdo = _Tpdo(
                cob & 0x7FF,
                self.od_value(comm, 2),
                layout,
                inhibit_s=self.od_value(comm, 3) * 1e-4,  # 100 µs units
                event_timer_s=self.od_value(comm, 5) * 1e-3,  # ms
            )
            (self._event_tpdos if tpdo.event_driven else self._sync_tpdos).append(tpdo)
