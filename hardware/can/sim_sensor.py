"""A simulated column torque sensor node (a strain-gauge amplifier with a CANopen interface) on a
python-can bus, for ``[drive.torque_sensor] source = "node"``: the real driver
(:class:`~hardware.can.cia402.CiA402Drive`) hears it as it would hear the amplifier in the lab.

What it speaks: NMT (start, stop, pre-operational, reset node / communication with boot-up), a
heartbeat producer (optional), and on every SYNC in NMT OPERATIONAL its frame (COB-ID
``cob_id``, default 0x180 + node id) with the column torque as a signed little-endian integer
of ``bits`` at ``byte_offset`` (:class:`~hardware.can.frames.SensorFrame`), scaled, signed and
saturated as the rig file says. No SDO server: the host writes nothing to the sensor node.

It shares the plant with the simulated drive through a :class:`SharedPlant`: the drive steps
it, the sensor only reads it. At each SYNC the sensor sends the state after the drive's step
for that SYNC, so its value belongs to the same sample as the drive's TPDOs (in the lab both
latch at the SYNC instant; see :mod:`hardware.can.sim_node`).

Fault injection for tests: :meth:`SimulatedTorqueSensor.go_silent` (the node disappears),
:meth:`~SimulatedTorqueSensor.stop_heartbeat`, ``mute`` (SYNCs go unanswered, heartbeat goes
on).
"""

from __future__ import annotations

import logging
import threading
import time

import can

from .config import DriveConfig
from .frames import (
    NMT_COB_ID,
    SYNC_COB_ID,
    NmtCommand,
    NmtState,
    SensorFrame,
    heartbeat_cob_id,
)
from .scaling import DriveScaling
from .sim_node import Plant
from .transport import BusReader

log = logging.getLogger(__name__)

PlantState = tuple[float, float, float, float]

_NMT_TARGET = {
    NmtCommand.START: NmtState.OPERATIONAL,
    NmtCommand.STOP: NmtState.STOPPED,
    NmtCommand.PRE_OPERATIONAL: NmtState.PRE_OPERATIONAL,
}


class SharedPlant:
    """One plant for several simulated nodes, each on its own receive thread: the simulated
    drive steps it, sensor nodes only read it. It is itself a :class:`~hardware.can.Plant`.

    Each step reads the plant once and keeps that state, so every node sees the same sample
    and no node reads the plant while it steps (the simulated world is not thread-safe, and a
    noisy plant must draw its noise once per sample, not once per reader).
    """

    def __init__(self, plant: Plant):
        self.plant = plant
        self._cond = threading.Condition()
        self._steps = 0
        self._state: PlantState | None = None

    @property
    def steps(self) -> int:
        return self._steps

    def step(self, motor_torque_nm: float) -> None:
        with self._cond:
            self.plant.step(motor_torque_nm)
            self._state = self.plant.read()
            self._steps += 1
            self._cond.notify_all()

    def read(self) -> PlantState:
        """The state after the last step (before the first step: the plant's current one)."""
        with self._cond:
            if self._state is None:
                self._state = self.plant.read()
            return self._state

    def read_next(self, seen: int, timeout_s: float) -> tuple[int, PlantState]:
        """Wait up to ``timeout_s`` for a step after step number ``seen``; return the step
        number and the state (the latest state if no step came)."""
        with self._cond:
            self._cond.wait_for(lambda: self._steps > seen, timeout_s)
            return self._steps, self.read()


class SimulatedTorqueSensor:
    """Torque sensor node ``config.torque_sensor.node_id`` on ``bus``, reading ``plant``.

    ``bus`` must be a bus of its own (a second reader on the drive node's bus would take
    frames from it). ``heartbeat_ms``: the period of the node's heartbeat; by default a third
    of ``[drive.torque_sensor] heartbeat_timeout_ms``, and none when that is 0. Runs its own
    receive thread from :meth:`start` (called by the constructor unless ``autostart=False``)
    until :meth:`close`; exceptions in it (a plant value that cannot be encoded, a bus that
    fails) are kept in :attr:`errors`.

    :raises ValueError: the config's torque sensor is not ``source = "node"``.
    """

    def __init__(
        self,
        bus: can.BusABC,
        config: DriveConfig,
        plant: SharedPlant,
        *,
        heartbeat_ms: int | None = None,
        autostart: bool = True,
    ):
        sensor = config.torque_sensor
        if sensor.source != "node" or sensor.node_id is None:
            raise ValueError(
                f"{config.source}: [drive.torque_sensor] is not a sensor node "
                f"(source = {sensor.source!r})"
            )
        self.config = config
        self.plant = plant
        cob_id = sensor.frame_cob_id
        if sensor.node_id is None or cob_id is None:
            raise ValueError(f"{config.source}: [drive.torque_sensor] needs node_id")
        self.node_id: int = sensor.node_id
        self.cob_id: int = cob_id
        self.frame = SensorFrame(sensor.byte_offset, sensor.bits)
        if heartbeat_ms is None:
            timeout = sensor.heartbeat_timeout_ms
            heartbeat_ms = max(1, timeout // 3) if timeout > 0 else 0
        self.heartbeat_ms = heartbeat_ms
        self._bus = bus
        self._scaling = DriveScaling(config)
        self._hb_id = heartbeat_cob_id(self.node_id)
        # How long a SYNC waits for the drive's step before sending the state it has: short
        # enough that the frame still arrives within the host's wait when the drive is late.
        self._step_wait_s = config.tpdo_timeout_ms / 1000.0 / 2
        self._seen = plant.steps
        self._next_heartbeat = 0.0

        self.nmt_state = NmtState.BOOTUP
        self.mute = False
        self._silent = False
        self.sync_count = 0
        self.sent_frames = 0
        self.ignored_frames = 0
        self.errors: list[BaseException] = []
        self._reader = BusReader(
            bus,
            self._on_frame,
            self._on_reader_failure,
            name=f"SimulatedTorqueSensor node {self.node_id} rx",
            on_tick=self._on_tick,
            poll_s=0.005,
        )
        self._started = False
        if autostart:
            self.start()

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> None:
        """Power on: boot-up message, then NMT PRE-OPERATIONAL (no values until NMT start)."""
        self._boot()
        if not self._started:
            self._started = True
            self._reader.start()

    def close(self) -> None:
        """Stop the receive thread (and with it the heartbeat). The bus stays open."""
        self._reader.stop()

    def __enter__(self) -> SimulatedTorqueSensor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- fault injection -----------------------------------------------------------------------

    def go_silent(self) -> None:
        """The node disappears: no heartbeat, no frames, no reaction to anything."""
        self._silent = True

    def stop_heartbeat(self) -> None:
        self.heartbeat_ms = 0

    # -- frames --------------------------------------------------------------------------------

    def _boot(self) -> None:
        self.nmt_state = NmtState.BOOTUP
        self._send(self._hb_id, bytes([NmtState.BOOTUP]))
        self.nmt_state = NmtState.PRE_OPERATIONAL
        self._next_heartbeat = time.monotonic() + self.heartbeat_ms / 1000.0

    def _on_frame(self, msg: can.Message) -> None:
        if self._silent:
            return
        cid = msg.arbitration_id
        if cid == SYNC_COB_ID and len(msg.data) <= 1:
            self._on_sync()
        elif cid == NMT_COB_ID:
            self._on_nmt(bytes(msg.data))

    def _on_nmt(self, data: bytes) -> None:
        if len(data) != 2 or data[1] not in (0, self.node_id):
            self.ignored_frames += 1
            return
        command = data[0]
        if command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            self._boot()
        elif command in _NMT_TARGET:
            self.nmt_state = _NMT_TARGET[NmtCommand(command)]
        else:
            self.ignored_frames += 1

    def _on_sync(self) -> None:
        self.sync_count += 1
        # Track the drive's steps in every NMT state, so the first value after NMT start is
        # already the one of its own SYNC.
        self._seen, state = self.plant.read_next(self._seen, self._step_wait_s)
        if self.nmt_state != NmtState.OPERATIONAL or self.mute:
            return
        try:
            data = self.frame.encode(self._scaling.torque_to_sensor(state[3]))
        except (ValueError, OverflowError) as exc:
            # A NaN or infinite value: an amplifier would send nothing usable either.
            self.errors.append(exc)
            log.error("simulated torque sensor node %d: cannot encode %r", self.node_id, state[3])
            return
        self._send(self.cob_id, data)
        self.sent_frames += 1

    def _on_tick(self, now: float) -> None:
        if self._silent or self.heartbeat_ms <= 0 or now < self._next_heartbeat:
            return
        self._next_heartbeat = now + self.heartbeat_ms / 1000.0
        self._send(self._hb_id, bytes([self.nmt_state]))

    def _send(self, cob_id: int, data: bytes) -> None:
        self._bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def _on_reader_failure(self, exc: BaseException) -> None:
        self.errors.append(exc)
