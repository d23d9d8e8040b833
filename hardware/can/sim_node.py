"""A simulated CiA 402 servo drive: a CANopen node on a python-can bus (normally the virtual bus)
that answers the real protocol, so the real driver (:class:`~hardware.can.cia402.CiA402Drive`)
runs unchanged against it.

What it speaks: NMT (start, stop, pre-operational, reset node / communication with boot-up),
SDO server (canopen's :class:`canopen.LocalNode`) over an object dictionary built in code, PDO
mapping checked the way drives check it, synchronous RPDO/TPDO on SYNC, heartbeat producer,
EMCY producer, and the CiA 402 state machine with cyclic synchronous torque (mode 10).

On each SYNC (NMT OPERATIONAL): the RPDO received since the last SYNC is applied (controlword,
target torque), the plant advances one sample with the resulting motor torque (zero unless
OPERATION ENABLED in mode 10; clamped at max torque 0x6072), and the TPDOs go out with the
plant's new state. A real drive latches its actual values at the SYNC instant instead, so on
hardware the values read after sync() are one sample older than in this simulation.

Fault injection for tests: :meth:`SimulatedDrive.stop_heartbeat`, :meth:`~SimulatedDrive.go_silent`
(the drive disappears), :meth:`~SimulatedDrive.inject_fault` (EMCY + FAULT state),
``refuse_enable`` (stays SWITCHED ON), ``mute_pdo`` (SYNCs go unanswered).

With ``[drive.torque_sensor] source = "node"`` the column torque comes from a node of its own
(:mod:`hardware.can.sim_sensor`); the drive then still steps the plant, through the
:class:`~hardware.can.sim_sensor.SharedPlant` both nodes read.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
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
    COMM_CYCLE_PERIOD,
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
    PRODUCER_HEARTBEAT,
    QUICK_STOP_OPTION,
    STATUSWORD,
    STATUSWORD_OF,
    SYNC_COB_ID,
    TARGET_TORQUE,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
    MappedObject,
    NmtCommand,
    NmtState,
    PdoLayout,
    State402,
    emcy_payload,
    rpdo_cob_id,
    sdo_rx_cob_id,
    tpdo_cob_id,
)
from .scaling import DriveScaling
from .transport import BusReader

log = logging.getLogger(__name__)

DEVICE_TYPE_SERVO = 0x0002_0192  # CiA 402 (0x192), servo drive
_SIGNED = (INTEGER8, INTEGER16, INTEGER32)
_BITS = {INTEGER8: 8, INTEGER16: 16, INTEGER32: 32, UNSIGNED8: 8, UNSIGNED16: 16, UNSIGNED32: 32}

ABORT_NOT_EXIST = 0x0602_0000
ABORT_NOT_MAPPABLE = 0x0604_0041
ABORT_PDO_LENGTH = 0x0604_0042
ABORT_VALUE_RANGE = 0x0609_0030
ABORT_UNSUPPORTED_ACCESS = 0x0601_0000

EMCY_INTERNAL_SOFTWARE = 0x6100


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


def _record(name: str, index: int, members: list[ODVariable]) -> ODRecord:
    r = ODRecord(name, index)
    for m in members:
        r.add_member(m)
    return r


def _pdo_objects(
    od: ObjectDictionary,
    comm: int,
    mapping: int,
    label: str,
    cob_id: int,
    trans_type: int,
    entries: list[int],
    transmit: bool,
) -> None:
    comm_members = [
        _var("Highest sub-index supported", comm, 0, UNSIGNED8, "const", 5 if transmit else 2),
        _var("COB-ID", comm, 1, UNSIGNED32, "rw", cob_id),
        _var("Transmission type", comm, 2, UNSIGNED8, "rw", trans_type),
    ]
    if transmit:
        comm_members += [
            _var("Inhibit time", comm, 3, UNSIGNED16, "rw", 0),
            _var("Event timer", comm, 5, UNSIGNED16, "rw", 0),
        ]
    od.add_object(_record(f"{label} communication parameter", comm, comm_members))
    map_members = [_var("Number of mapped objects", mapping, 0, UNSIGNED8, "rw", len(entries))]
    for sub in range(1, 9):
        value = entries[sub - 1] if sub <= len(entries) else 0
        map_members.append(_var(f"Mapped object {sub}", mapping, sub, UNSIGNED32, "rw", value))
    od.add_object(_record(f"{label} mapping parameter", mapping, map_members))


def build_object_dictionary(
    config: DriveConfig, *, motor_rated_torque_nm: float | None = None
) -> ObjectDictionary:
    """The simulated drive's object dictionary. Defaults mimic a drive out of the box: the
    predefined PDO set with a mapping the driver has to replace, TPDO3/TPDO4 enabled on SYNC,
    no heartbeat until configured."""
    n = config.node_id
    od = ObjectDictionary()
    od.node_id = n
    od.bitrate = config.bitrate
    add = od.add_object
    add(_var("Device type", 0x1000, 0, UNSIGNED32, "ro", DEVICE_TYPE_SERVO))
    add(_var("Error register", ERROR_REGISTER, 0, UNSIGNED8, "ro", 0))
    add(_var("COB-ID SYNC", 0x1005, 0, UNSIGNED32, "rw", SYNC_COB_ID))
    add(_var("Communication cycle period", COMM_CYCLE_PERIOD, 0, UNSIGNED32, "rw", 0))
    add(_var("Producer heartbeat time", PRODUCER_HEARTBEAT, 0, UNSIGNED16, "rw", 0))
    add(
        _record(
            "Consumer heartbeat time",
            CONSUMER_HEARTBEAT,
            [
                _var("Highest sub-index supported", CONSUMER_HEARTBEAT, 0, UNSIGNED8, "const", 1),
                _var("Consumer heartbeat time 1", CONSUMER_HEARTBEAT, 1, UNSIGNED32, "rw", 0),
            ],
        )
    )
    add(
        _record(
            "Identity object",
            0x1018,
            [
                _var("Highest sub-index supported", 0x1018, 0, UNSIGNED8, "const", 4),
                _var("Vendor-ID", 0x1018, 1, UNSIGNED32, "ro", 0),
                _var("Product code", 0x1018, 2, UNSIGNED32, "ro", 0x5354_4C42),  # "STLB"
                _var("Revision number", 0x1018, 3, UNSIGNED32, "ro", 1),
                _var("Serial number", 0x1018, 4, UNSIGNED32, "ro", 0),
            ],
        )
    )
    for k in range(1, 5):
        default_map = [0x6040_0010] if k == 1 else []
        _pdo_objects(
            od,
            0x1400 + k - 1,
            0x1600 + k - 1,
            f"RPDO{k}",
            rpdo_cob_id(k, n) | (0 if k == 1 else PDO_INVALID),
            255,
            default_map,
            transmit=False,
        )
    tpdo_defaults = {
        1: [0x6041_0010],
        2: [0x6041_0010, 0x6064_0020],
        3: [0x6041_0010],
        4: [0x6064_0020],
    }
    for k in range(1, 5):
        _pdo_objects(
            od,
            0x1800 + k - 1,
            0x1A00 + k - 1,
            f"TPDO{k}",
            tpdo_cob_id(k, n),
            1 if k >= 3 else 255,
            tpdo_defaults[k],
            transmit=True,
        )

    sensor = config.torque_sensor
    if sensor.source == "pdo":
        dtype = INTEGER32 if sensor.bits == 32 else INTEGER16
        obj = _var("Column torque", sensor.index, sensor.subindex, dtype, "ro", 0, mappable=True)
        if sensor.subindex == 0:
            add(obj)
        else:
            add(
                _record(
                    "Column torque sensor",
                    sensor.index,
                    [
                        _var(
                            "Highest sub-index supported",
                            sensor.index,
                            0,
                            UNSIGNED8,
                            "const",
                            sensor.subindex,
                        ),
                        obj,
                    ],
                )
            )

    rated = config.rated_torque_nm if motor_rated_torque_nm is None else motor_rated_torque_nm
    add(_var("Error code", ERROR_CODE, 0, UNSIGNED16, "ro", 0, mappable=True))
    add(_var("Controlword", CONTROLWORD, 0, UNSIGNED16, "rw", 0, mappable=True))
    add(_var("Statusword", STATUSWORD, 0, UNSIGNED16, "ro", 0, mappable=True))
    add(_var("Quick stop option code", QUICK_STOP_OPTION, 0, INTEGER16, "rw", 6))
    # 0 (no action) out of the box, so that a driver that does not configure the guard is caught
    add(_var("Abort connection option code", ABORT_CONNECTION_OPTION, 0, INTEGER16, "rw", 0))
    add(_var("Modes of operation", MODES_OF_OPERATION, 0, INTEGER8, "rw", 0, mappable=True))
    add(
        _var(
            "Modes of operation display",
            MODES_OF_OPERATION_DISPLAY,
            0,
            INTEGER8,
            "ro",
            0,
            mappable=True,
        )
    )
    add(_var("Position actual value", POSITION_ACTUAL, 0, INTEGER32, "ro", 0, mappable=True))
    add(_var("Velocity actual value", VELOCITY_ACTUAL, 0, INTEGER32, "ro", 0, mappable=True))
    add(_var("Target torque", TARGET_TORQUE, 0, INTEGER16, "rw", 0, mappable=True))
    add(_var("Max torque", MAX_TORQUE, 0, UNSIGNED16, "rw", 1000, mappable=True))
    add(_var("Motor rated torque", MOTOR_RATED_TORQUE, 0, UNSIGNED32, "rw", round(rated * 1000)))
    add(_var("Torque actual value", TORQUE_ACTUAL, 0, INTEGER16, "ro", 0, mappable=True))
    return od


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
        self._controlword = 0
        self._target = 0
        self._fault_code = 0
        self._error_register = 0
        self._fault_resettable = True
        self._rpdo_pending: tuple[int, ...] | None = None
        self._layouts_dirty = True
        self._rpdo: tuple[int, PdoLayout] | None = None
        self._tpdos: list[tuple[int, int, PdoLayout]] = []
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
        return self._node.nmt._state

    @property
    def target_torque_permille(self) -> int:
        return self._target

    def od_value(self, index: int, subindex: int = 0) -> int:
        """Current value of a stored object (configuration written by SDO, or its default)."""
        obj = self._node._find_object(index, subindex)
        data = self._node.data_store.get(index, {}).get(subindex)
        if data is None:
            return 0 if obj.default is None else obj.default
        return obj.decode_raw(data)

    # -- frames --------------------------------------------------------------------------------

    def _on_frame(self, msg: can.Message) -> None:
        cid = msg.arbitration_id
        with self._lock:
            if self._silent:
                return
            self._bus_time = msg.timestamp
            try:
                if cid == SYNC_COB_ID and len(msg.data) <= 1:
                    self._on_sync()
                elif cid == NMT_COB_ID:
                    self._on_nmt(bytes(msg.data))
                elif cid == self._sdo_rx_id:
                    if len(msg.data) == 8:  # SDO requests are always 8 bytes (CiA 301)
                        self._network.notify(cid, msg.data, msg.timestamp)
                    else:
                        self.ignored_frames += 1
                elif self._consumer is not None and cid == 0x700 + self._consumer[0]:
                    self._consumer_last = msg.timestamp
                else:
                    self._refresh_layouts()
                    if self._rpdo is not None and cid == self._rpdo[0]:
                        self._on_rpdo(bytes(msg.data))
            except (struct.error, SdoAbortedError):
                # A real drive ignores frames it cannot parse; so do we (counted for tests).
                self.ignored_frames += 1
            self._power_stage()

    def _power_stage(self) -> None:
        # Out of OPERATION ENABLED the power stage is off at once, SYNC or not.
        if self._applied != 0.0 and self.state is not State402.OPERATION_ENABLED:
            self._apply(0.0)

    def _on_tick(self, now: float) -> None:
        """The drive's own watch on its host, run at least every 2 ms even on a silent bus.

        Times are the frames' bus timestamps (wall clock at sending): a real drive sees each
        frame when it is on the wire, whereas this thread may run late on a busy computer and
        find frames queued. Until the queue is drained, the newest frame taken is "now"."""
        with self._lock:
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

    def _on_nmt(self, data: bytes) -> None:
        if len(data) != 2 or data[1] not in (0, self.node_id):
            self.ignored_frames += 1
            return
        command = data[0]
        nmt = self._node.nmt
        was_operational = nmt._state == NmtState.OPERATIONAL
        if command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            if command == NmtCommand.RESET_NODE:
                self._node.data_store.clear()
            else:
                for index in [i for i in self._node.data_store if 0x1000 <= i <= 0x1FFF]:
                    del self._node.data_store[index]
            self._layouts_dirty = True
            self._consumer = self._consumer_last = None
            nmt.stop_heartbeat()
            self._power_on(keep_drive_state=command == NmtCommand.RESET_COMMUNICATION)
            return
        if command not in (NmtCommand.START, NmtCommand.STOP, NmtCommand.PRE_OPERATIONAL):
            self.ignored_frames += 1
            return
        nmt.on_command(NMT_COB_ID, data, 0.0)
        if nmt._state != NmtState.OPERATIONAL:
            self._rpdo_pending = None
            if was_operational and self.state in (
                State402.OPERATION_ENABLED,
                State402.QUICK_STOP_ACTIVE,
            ):
                # Losing the PDO channel must not leave torque on (CiA 402 0x6007 "disable
                # voltage" reaction).
                self.state = State402.SWITCH_ON_DISABLED
        else:
            self._refresh_layouts()

    def _power_on(self, keep_drive_state: bool = False) -> None:
        nmt = self._node.nmt
        nmt.send_command(NmtCommand.RESET_NODE)  # INITIALISING, sends the boot-up message
        nmt.send_command(NmtCommand.PRE_OPERATIONAL)  # starts heartbeat per 0x1017
        if not keep_drive_state:
            self._controlword = 0
            self._target = 0
            if self.state is not State402.FAULT:
                self.state = State402.SWITCH_ON_DISABLED

    def _on_rpdo(self, data: bytes) -> None:
        if self._node.nmt._state != NmtState.OPERATIONAL or self._rpdo is None:
            return
        layout = self._rpdo[1]
        if len(data) < layout.size:
            # CiA 301: a too-short RPDO is not processed and reported with EMCY 0x8210.
            self._send_emcy(0x8210, 0x11)
            return
        self._rpdo_pending = layout.decode(data)

    def _on_sync(self) -> None:
        self.sync_count += 1
        self._refresh_layouts()
        operational = self._node.nmt._state == NmtState.OPERATIONAL
        if operational and self._rpdo_pending is not None and self._rpdo is not None:
            for obj, value in zip(self._rpdo[1].objects, self._rpdo_pending, strict=True):
                self._write_object(obj.index, obj.subindex, value)
            self._rpdo_pending = None
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
            for cob_id, every, layout in self._tpdos:
                if self.sync_count % every == 0:
                    values = [self._read_object(o.index, o.subindex) for o in layout.objects]
                    self._send(cob_id, layout.encode(values))

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
        self._send(0x80 + self.node_id, emcy_payload(code, register, vendor_data))

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
        if sensor.source == "pdo" and (index, subindex) == (sensor.index, sensor.subindex):
            return self._column
        return None

    def _read_object(self, index: int, subindex: int) -> int:
        value = self._dynamic(index, subindex)
        return self.od_value(index, subindex) if value is None else value

    def _write_object(self, index: int, subindex: int, value: int) -> None:
        if index == CONTROLWORD:
            self._apply_controlword(value)
        elif index == TARGET_TORQUE:
            self._target = value

    def _on_sdo_read(self, index: int, subindex: int, od: ODVariable, **_: object) -> int | None:
        return self._dynamic(index, subindex)

    def _on_sdo_write(
        self, index: int, subindex: int, od: ODVariable, data: bytes, **_: object
    ) -> None:
        value = od.decode_raw(data)
        if index == MODES_OF_OPERATION and value != MODE_CST:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        if 0x1400 <= index <= 0x1BFF:
            self._check_pdo_write(index, subindex, value)
            self._layouts_dirty = True
        if index in (CONTROLWORD, TARGET_TORQUE):
            self._write_object(index, subindex, value)
        if index == CONSUMER_HEARTBEAT and subindex == 1:
            node, ms = (value >> 16) & 0x7F, value & 0xFFFF
            self._consumer = (node, ms / 1000.0) if node and ms else None
            self._consumer_last = None

    def _check_pdo_write(self, index: int, subindex: int, value: int) -> None:
        """The CiA 301 rules drives enforce, so a driver that maps in the wrong order fails
        here as it would on the bench."""
        is_comm = (index & 0xFF00) in (0x1400, 0x1800)
        if is_comm:
            if subindex == 1:
                current = self.od_value(index, 1)
                if (
                    not current & PDO_INVALID
                    and not value & PDO_INVALID
                    and (value & 0x7FF) != (current & 0x7FF)
                ):
                    raise SdoAbortedError(ABORT_VALUE_RANGE)  # COB-ID change while valid
            return
        comm = index - 0x200
        if subindex == 0:
            if value and not self.od_value(comm, 1) & PDO_INVALID:
                raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)
            if value > 8:
                raise SdoAbortedError(ABORT_VALUE_RANGE)
            bits = 0
            for sub in range(1, value + 1):
                bits += self._mapping_target(self.od_value(index, sub)).bits
            if bits > 64:
                raise SdoAbortedError(ABORT_PDO_LENGTH)
            return
        if self.od_value(index, 0) != 0:
            raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)
        self._mapping_target(value)

    def _mapping_target(self, entry: int) -> MappedObject:
        index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        obj = self._od.get_variable(index, subindex)
        if obj is None:
            raise SdoAbortedError(ABORT_NOT_EXIST)
        if not obj.pdo_mappable or _BITS.get(obj.data_type) != bits:
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)
        return MappedObject(index, subindex, bits, obj.data_type in _SIGNED, obj.name)

    def _layout(self, mapping: int) -> PdoLayout:
        count = self.od_value(mapping, 0)
        return PdoLayout(
            [self._mapping_target(self.od_value(mapping, sub)) for sub in range(1, count + 1)]
        )

    def _refresh_layouts(self) -> None:
        if not self._layouts_dirty:
            return
        self._layouts_dirty = False
        self._rpdo = None
        cob = self.od_value(0x1400, 1)
        if not cob & PDO_INVALID:
            self._rpdo = (cob & 0x7FF, self._layout(0x1600))
        self._tpdos = []
        for k in range(4):
            cob = self.od_value(0x1800 + k, 1)
            trans = self.od_value(0x1800 + k, 2)
            if cob & PDO_INVALID or not 1 <= trans <= 240:
                continue  # only synchronous cyclic TPDOs are simulated
            self._tpdos.append((cob & 0x7FF, trans, self._layout(0x1A00 + k)))
