"""SensoDrive SENSO-Wheel driver: the vendor's request/response protocol over any python-can bus.

The SENSO-Wheel does not speak CANopen (``docs/sensodrive-protocol.md``; bytes in
:mod:`hardware.can.sensodrive_frames`). Every request ``0x20n`` is answered by one frame
``0x21n``. One control cycle, as :meth:`SensoDrive.sync` puts it on the bus::

    host  → 0x201  [torque][friction][damping][stiffness]      every cycle
    drive → 0x211  [angle I32, 0.009°][rate I16, rpm][torque I16, mN·m]
    host  → 0x20A  [00 00]                                      with the hand sensor
    drive → 0x21A  [..][U_b][U_a][..]
    host  → 0x200  [0x11 keep][..][end stop][..][limits]        every state_poll_cycles
    drive → 0x210  [state][..][error bytes]                     (read when it comes)

The 0x201 is the drive's clock here as SYNC is a CiA 402 drive's: the host sends one per cycle
and waits up to ``reply_timeout_ms`` for the 0x211 (and 0x21A). The drive renders the virtual
wheel's spring and damper itself from the 0x201's fields (:attr:`SensoDrive.renders_wheel`),
so they see none of the host's latency; the torque field carries the perturbation and the
safety layer's terms.

Replies carry no request number. The driver matches them to requests in order (one answer per
request, in the order sent): a 0x211 that comes after its cycle gave up waiting, but before the
next cycle starts, is counted as late (``late_replies``) instead of being taken for the next
cycle's. A request still unanswered when the next cycle starts is taken as lost (a lost frame
must not shift the matching of every later reply); a reply that comes later still is then taken
for the new cycle's, one cycle stale, as in the CiA 402 driver.

Exceptions that can escape: :meth:`~SensoDrive.enable` raises :class:`DriveEnableError` (the
drive did not reach a state, a frame could not be sent, cancelled by :meth:`disable`), after
disabling again; :meth:`~SensoDrive.set_torque` raises :class:`ValueError` for a NaN or
infinite command (zero is commanded first); :meth:`~SensoDrive.set_wheel` raises
:class:`ValueError` for a spring or damper the drive's fields cannot hold;
:attr:`~SensoDrive.torque_sensor` raises :class:`DriveError` without a way to obtain the driver
torque. Everything else is recorded as a fault, which :meth:`~SensoDrive.problem` reports.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can

from steerlab.hardware.derivatives import LowPassDerivatives
from steerlab.hardware.interfaces import DriveReading

from .errors import DriveEnableError, DriveError
from .fault_log import FaultLog
from .frames import FrameError
from .sensodrive_config import SensoDriveConfig
from .sensodrive_frames import (
    HAND_SENSOR_REPLY_ID,
    HAND_SENSOR_REQUEST,
    HAND_SENSOR_REQUEST_ID,
    STATE_REPLY_ID,
    STATE_REQUEST_ID,
    WHEEL_COMMAND_ID,
    WHEEL_REPLY_ID,
    Command,
    State,
    StateCommand,
    WheelCommand,
    decode_hand_sensor_reply,
    decode_state_reply,
    decode_wheel_command,
    decode_wheel_reply,
    encode_state_command,
    encode_wheel_command,
)
from .transport import BusReader
from .zeroed_torque import ZeroedTorque

log = logging.getLogger(__name__)

__all__ = ["SensoDrive", "DriveError", "DriveEnableError", "LowPassDerivatives"]

#: The velocity :meth:`SensoDrive.read` reports is the angle's derivative through a
#: second-order Butterworth low-pass at this cutoff (the lflipse client differentiates the
#: angle through a 50 Hz filter too): the drive's own rate field has 1 rpm = 0.105 rad/s steps,
#: far too coarse for a damper or an admittance estimate. Capped at 40 % of the loop rate.
VELOCITY_FILTER_HZ = 50.0
#: The smooth sign of Coulomb friction, tanh(ω/ε): the rig check's ε (analysis/rigcheck.py).
COULOMB_EPS_RAD_S = 0.01
#: How often enable() asks for the state while it waits for a transition.
_STATE_POLL_S = 0.002
#: A frame the adapter cannot queue within this long counts as not sent.
_SEND_TIMEOUT_S = 0.01
_HISTORY = 1000  # faults kept
_COLUMN_SAMPLES = 500  # recent driver torque values kept for zeroing
_PENDING_MAX = 64  # requests awaiting their reply (disable() repeated must not grow it)

_RX_WHEEL = 0b01
_RX_HAND = 0b10

_STATE_WORD = {State.OFF: "off", State.READY: "ready", State.ON: "on", State.ERROR: "error"}
_ZERO = WheelCommand()


def _state_name(state: State | int | None) -> str:
    if state is None:
        return "no answer (no 0x210)"
    if isinstance(state, State):
        return f"{state.name} (0x{int(state):02X})"
    return f"unknown (0x{state:02X})"


@dataclass(frozen=True)
class SensoDriveFault:
    """Something went wrong with the drive or the bus; ``message`` is what :meth:`SensoDrive.
    problem` reports."""

    kind: str
    message: str
    time_s: float = 0.0  # time.monotonic()

    def __str__(self) -> str:
        return self.message


def send_off(bus: can.BusABC, config: SensoDriveConfig, repeats: int = 2) -> None:
    """The off sequence on ``bus``, sent blind (no driver, no answer awaited): READY (0x12) and
    OFF (0x10) ``repeats`` times, then zero torque and fields (0x201), should the drive have
    ignored the state commands. For whoever must turn the drive off without its driver: a
    driver whose bus failed, the engine's process when the loop process died. The state
    commands go first: a 0x201 is a control cycle to the drive, and there is none any more.
    :raises can.CanError: a frame could not be sent."""
    zero = can.Message(
        arbitration_id=WHEEL_COMMAND_ID, is_extended_id=False, data=encode_wheel_command(_ZERO)
    )
    states = [
        can.Message(
            arbitration_id=STATE_REQUEST_ID,
            is_extended_id=False,
            data=encode_state_command(
                StateCommand(
                    command,
                    config.end_stop_deg,
                    config.torque_limit_percent,
                    config.torque_limit_beyond_percent,
                )
            ),
        )
        for command in (Command.READY, Command.OFF)
    ]
    for _ in range(repeats):
        for msg in states:
            bus.send(msg, timeout=_SEND_TIMEOUT_S)
    bus.send(zero, timeout=_SEND_TIMEOUT_S)


class _Pending:
    """Requests of one kind awaiting their reply, oldest first. Each carries a tag: a cycle
    number, or None for a request no cycle waits for (enable's and disable's)."""

    def __init__(self) -> None:
        self._q: collections.deque[int | None] = collections.deque(maxlen=_PENDING_MAX)

    def add(self, tag: int | None) -> None:
        self._q.append(tag)

    def drop(self, tag: int | None) -> None:
        """The request was not sent after all."""
        for i in range(len(self._q) - 1, -1, -1):
            if self._q[i] == tag:
                del self._q[i]
                return

    def clear(self) -> None:
        """A new cycle starts: whatever is unanswered is lost."""
        self._q.clear()

    def answer(self) -> tuple[bool, int | None]:
        """Match a reply to the oldest request: (there was one, its tag)."""
        if not self._q:
            return False, None
        return True, self._q.popleft()


class SensoDrive:
    """Implements :class:`hardware.interfaces.RigDrive` for one SENSO-Wheel on ``bus``.

    The driver owns the bus: :meth:`close` shuts it down. A receive thread starts at
    construction. ``set_torque``, ``set_wheel``, ``sync`` and ``read`` belong to the control
    loop's thread; ``disable`` and ``quick_stop`` may be called from any thread at any time.

    Directions: every value crossing this class's interface is Steerlab's (positive
    counter-clockwise seen by the driver); the drive's own is ``config.sign`` × that. The
    drive's damping and stiffness fields do not depend on the direction.
    """

    renders_wheel = True

    def __init__(
        self,
        bus: can.BusABC,
        config: SensoDriveConfig,
        *,
        reopen: Callable[[], can.BusABC] | None = None,
    ):
        self.config = config
        self._bus = bus
        # A bus to send the off sequence on when ours has failed (see :meth:`disable`).
        self._reopen = reopen
        self._sign = config.sign
        self._timeout_s = config.reply_timeout_ms / 1000.0
        self._with_hand = config.has_hand_sensor
        self._rx_full = _RX_WHEEL | (_RX_HAND if self._with_hand else 0)
        self._send_lock = threading.Lock()
        self._cycle_lock = threading.RLock()
        self._rx_lock = threading.Lock()
        self._state_cond = threading.Condition()

        # command image (Steerlab's SI values, already on the fields' steps)
        self._torque_nm = 0.0
        self._stiffness = 0.0
        self._damping = 0.0
        self._enabled = False
        self._cancel = threading.Event()

        # receive side
        self._wheel_pending = _Pending()
        self._hand_pending = _Pending()
        self._awaited: int | None = None
        # a reply that came after its cycle gave up: (cycle, 0x211 values, 0x21A values)
        self._late: tuple[int, Any, Any] | None = None
        self._missed_cycle: tuple[WheelCommand, bool] | None = None  # the last one, if missed
        self._rx_mask = 0
        self._rx_event = threading.Event()
        self._wheel_raw: tuple[float, float, float] | None = None  # this cycle's 0x211
        self._hand_raw: tuple[float, float] | None = None  # this cycle's 0x21A
        self._state: State | int | None = None
        self._error_info = 0
        self._state_count = 0

        # latched values
        dt = config.period_s
        self._velocity_filter = LowPassDerivatives(
            min(VELOCITY_FILTER_HZ, 0.4 * config.loop_rate_hz), dt
        )
        # θ̈ for the rim above the hand sensor: order 4, see LowPassDerivatives
        self._rim_filter: LowPassDerivatives | None = None
        if self._with_hand and config.torque_sensor.rim_inertia_kgm2 > 0:
            self._rim_filter = LowPassDerivatives(self._velocity_filter.cutoff_hz, dt, order=4)
        self._reading = DriveReading(math.nan, math.nan, math.nan)
        self._column_nm = math.nan
        self._column_recent: collections.deque[float] = collections.deque(maxlen=_COLUMN_SAMPLES)
        self._sensor: DriverTorque | None = None
        ts = config.torque_sensor
        self._reconstruct: _Reconstruction | None = None
        if ts.source == "reconstructed":
            self._reconstruct = _Reconstruction(config)
        self._hand_nm_per_v = ts.sign * self._sign / ts.v_per_nm if self._with_hand else 0.0

        self.cycle_count = 0
        self.missed_replies = 0
        self.consecutive_missed = 0
        self.missed_hand_replies = 0
        self.consecutive_missed_hand = 0
        self.late_replies = 0
        self.unsolicited_replies = 0
        self.bad_frames = 0
        self.error_frames = 0

        self._fault_log: FaultLog[SensoDriveFault] = FaultLog(_HISTORY)
        self._closed = False
        self._reader = BusReader(
            bus,
            self._on_frame,
            self._on_reader_failure,
            name="SensoDrive rx",
            on_error_frame=self._on_error_frame,
        )
        self._reader.start()

    # -- RigDrive: set-up ----------------------------------------------------------------------

    @property
    def angle_quantum_rad(self) -> float:
        return self.config.angle_quantum_rad

    def set_wheel(self, stiffness_nm_per_rad: float, damping_nms_per_rad: float) -> None:
        """The spring and damper the drive renders in its own 0x201 fields, from the next
        cycle on while enabled, until :meth:`disable` zeroes them.

        :raises ValueError: a value that is negative, not finite, or too large for its field.
        """
        for name, value in (
            ("stiffness", stiffness_nm_per_rad),
            ("damping", damping_nms_per_rad),
        ):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"SensoDrive: {name} must be finite and ≥ 0, got {value!r}")
        try:
            fields = decode_wheel_command(
                encode_wheel_command(
                    WheelCommand(0.0, 0.0, damping_nms_per_rad, stiffness_nm_per_rad)
                )
            )
        except FrameError as exc:
            raise ValueError(f"SensoDrive: virtual wheel not renderable: {exc}") from None
        with self._cycle_lock:
            self._stiffness = fields.stiffness_nm_per_rad
            self._damping = fields.damping_nms_per_rad

    def enable(self) -> None:
        """Bring the drive to ON: clear its error state (0x1F) if it reports one, send a zero
        0x201 (whatever an earlier host left in the drive's fields goes), then READY (0x12)
        and ON (0x14), each confirmed by the drive's 0x210 within ``state_timeout_s``. Clears
        the recorded faults first: a fault still there shows up again.

        :raises DriveEnableError: a step failed; the message names the state the drive stayed
            in. The drive has been disabled again.
        """
        self._cancel.clear()
        with self._cycle_lock:
            self._enabled = False
            self._torque_nm = 0.0
            self.consecutive_missed = self.consecutive_missed_hand = 0
        self._fault_log.clear()
        step = "state request (0x200/0x11)"
        try:
            state = self._transition(Command.KEEP, None)
            if state is State.ERROR:
                step = "clear error (0x200/0x1F)"
                self._transition(Command.CLEAR_ERROR, State.OFF)
            step = "zero wheel command (0x201)"
            with self._cycle_lock:
                self._cycle(_ZERO, enabled=False, count=False)
            step = "ready (0x200/0x12)"
            self._transition(Command.READY, State.READY)
            step = "on (0x200/0x14)"
            self._transition(Command.ON, State.ON)
            with self._cycle_lock:
                if self._cancel.is_set():
                    raise DriveEnableError("cancelled by disable() or quick_stop()")
                self._enabled = True
        except (can.CanError, DriveEnableError) as exc:
            message = f"SensoDrive: enable failed at {step}: {_describe(exc)}"
            self._record("enable", message, key=None)
            self.disable()
            raise DriveEnableError(message) from exc
        except BaseException:
            self.disable()  # a bug or KeyboardInterrupt half-way must still leave it off
            raise
        log.info("SensoDrive enabled")

    # -- RigDrive: the cycle -------------------------------------------------------------------

    def set_torque(self, torque_nm: float) -> None:
        """The torque (N·m, Steerlab's direction) for the next :meth:`sync`'s 0x201. A value
        its field cannot hold is a fault and commands zero (never a wrapped value).

        :raises ValueError: ``torque_nm`` is NaN or infinite (zero is commanded first).
        """
        if not math.isfinite(torque_nm):
            self._torque_nm = 0.0
            self._record("command", f"SensoDrive: non-finite torque {torque_nm!r}", key="nan")
            raise ValueError(f"torque command must be finite, got {torque_nm!r}")
        try:
            encode_wheel_command(WheelCommand(self._sign * torque_nm))
        except FrameError as exc:
            self._torque_nm = 0.0
            self._record("command", f"SensoDrive: torque not sent: {exc}", key="range")
            return
        self._torque_nm = torque_nm

    def sync(self) -> None:
        """One control cycle: send the 0x201 (with the hand sensor the 0x20A, every
        ``state_poll_cycles`` a 0x200/0x11), wait up to ``reply_timeout_ms`` for the 0x211
        (and 0x21A) and latch them for :meth:`read` and the driver torque. A reply that does
        not come is counted; more than ``max_missed_replies`` in a row is a fault. Never
        raises."""
        with self._cycle_lock:
            enabled = self._enabled
            if enabled:
                command = WheelCommand(
                    self._sign * self._torque_nm,
                    self.config.friction_nm,
                    self._damping,
                    self._stiffness,
                )
            else:
                command = _ZERO
            self._cycle(command, enabled=enabled, count=True)

    def read(self) -> DriveReading:
        """Angle, velocity (the filtered derivative of the angle, see
        :data:`VELOCITY_FILTER_HZ`) and the torque the drive reports, latched by the last
        :meth:`sync` (NaN before the first 0x211). What that torque is on a real drive (the
        command, the motor's output with the rendered spring and damper, a measurement) is
        unknown."""
        return self._reading

    # -- RigDrive: stopping --------------------------------------------------------------------

    def disable(self) -> None:
        """Zero torque and fields (0x201), then READY (0x12) and OFF (0x10); the spring and
        damper of :meth:`set_wheel` are forgotten. Does not wait for the drive's answers;
        safe from any thread, in any state, repeatedly. Never raises."""
        self._cancel.set()
        with self._cycle_lock:
            self._enabled = False
            self._torque_nm = self._stiffness = self._damping = 0.0
            if self._closed:
                return
            sent = [
                self._send_untracked_zero("disable: zero 0x201"),
                self._try_send(self._state_message(Command.READY), "disable: 0x200/0x12"),
                self._try_send(self._state_message(Command.OFF), "disable: 0x200/0x10"),
            ]
        if not all(sent):
            self._off_through_a_new_bus("disable")

    def quick_stop(self) -> None:
        """Zero torque and fields (0x201), then READY and OFF (the clients' way down from ON;
        whether the drive takes OFF straight from ON is unknown), at once, without waiting
        for a cycle in progress: the loop may be stuck in one. A 0x201 that cycle still sends
        reaches a drive that is already on its way off. Never raises."""
        self._cancel.set()
        self._enabled = False
        self._torque_nm = self._stiffness = self._damping = 0.0
        if self._closed:
            return
        sent = [
            self._send_untracked_zero("quick stop: zero 0x201"),
            self._try_send(self._state_message(Command.READY), "quick stop: 0x200/0x12"),
            self._try_send(self._state_message(Command.OFF), "quick stop: 0x200/0x10"),
        ]
        if not all(sent):
            self._off_through_a_new_bus("quick stop")

    def _off_through_a_new_bus(self, what: str) -> None:
        """Our bus failed (bus-off, adapter lost) while the drive may still hold a torque: no
        drive watchdog is known to cut it, so open the bus afresh and send the off sequence
        there. Never raises; what happened is recorded."""
        if self._reopen is None:
            return
        try:
            # Our handle first: an adapter (PCAN-Basic) may not open a channel twice, and a
            # socketcan controller sends again only once it has restarted (restart-ms).
            self._bus.shutdown()
        except Exception:
            pass
        try:
            bus = self._reopen()
        except Exception as exc:
            self._record(
                "bus", f"SensoDrive: {what}: could not reopen the bus: {_describe(exc)}",
                key="reopen",
            )  # fmt: skip
            return
        try:
            send_off(bus, self.config)
            self._record(
                "bus", f"SensoDrive: {what}: off sequence sent on a reopened bus", key="reopened"
            )
        except Exception as exc:
            self._record(
                "bus", f"SensoDrive: {what}: off sequence failed on a reopened bus: "
                f"{_describe(exc)}", key="reopen",
            )  # fmt: skip
        finally:
            try:
                bus.shutdown()
            except Exception:
                pass

    def close(self) -> None:
        """Disable, stop the receive thread and shut the bus down. Never raises."""
        if self._closed:
            return
        try:
            self.disable()
        finally:
            self._closed = True
            self._reader.stop()
            try:
                self._bus.shutdown()
            except Exception:
                log.exception("SensoDrive: bus shutdown failed")

    def drop_bus(self) -> None:
        """Fault injection: shut the bus down under the driver (as a bus-off would)."""
        self._bus.shutdown()

    def __enter__(self) -> SensoDrive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- RigDrive: health ----------------------------------------------------------------------

    @property
    def enabled(self) -> bool:
        return self._enabled

    @property
    def state(self) -> State | int | None:
        """The state of the last 0x210 (None before any)."""
        return self._state

    @property
    def faults(self) -> tuple[SensoDriveFault, ...]:
        """Every fault recorded (most recent last, bounded history)."""
        return self._fault_log.history

    @property
    def active_faults(self) -> tuple[SensoDriveFault, ...]:
        """Faults since the last enable() (one per cause)."""
        return self._fault_log.active

    def problem(self) -> str | None:
        """A reason to stop the trial now (the first fault since enable(), the others
        counted), or None."""
        faults = self.active_faults
        if not faults:
            if not self._reader.alive:
                return "SensoDrive: receive thread is not running"
            return None
        more = f" (and {len(faults) - 1} more)" if len(faults) > 1 else ""
        return f"{faults[0].message}{more}"

    def status(self) -> dict[str, Any]:
        state = self._state
        if isinstance(state, State):
            word = _STATE_WORD[state]
        else:
            word = "unknown" if state is None else f"0x{state:02X}"
        return {
            "drive_state": word,
            "drive_ok": self.problem() is None,
            "drive_enabled": self._enabled,
            "error_info": self._error_info,
            "cycles": self.cycle_count,
            "missed_replies": self.missed_replies,
            "missed_hand_sensor_replies": self.missed_hand_replies,
            "late_replies": self.late_replies,
            "unsolicited_replies": self.unsolicited_replies,
            "bad_frames": self.bad_frames,
            "faults": [str(f) for f in self.faults],
        }

    # -- driver torque -------------------------------------------------------------------------

    @property
    def torque_sensor(self) -> DriverTorque:
        """The driver torque, from the hand sensor or reconstructed from the wheel model, as
        ``[drive.torque_sensor] source`` says (one instance, so its zero offset persists).

        :raises DriveError: ``source = "none"``."""
        if self.config.torque_sensor.source == "none":
            raise DriveError(
                "SensoDrive: no driver torque: [drive.torque_sensor] source is 'none' "
                "(set 'hand_sensor' or 'reconstructed' to run a session)"
            )
        if self._sensor is None:
            self._sensor = DriverTorque(self)
        return self._sensor

    def column_torque_nm(self) -> float:
        """The driver torque latched by the last sync(), offset not removed (NaN if none)."""
        return self._column_nm

    # -- the cycle's internals -----------------------------------------------------------------

    def _cycle(self, command: WheelCommand, *, enabled: bool, count: bool) -> None:
        """Send one 0x201 (+ 0x20A, + the state poll), wait for the replies, latch them.
        Called with the cycle lock held."""
        try:
            data = encode_wheel_command(command)
        except FrameError as exc:  # set_torque and set_wheel check: a bug if it happens
            self._record("command", f"SensoDrive: 0x201 not encodable: {exc}", key="encode")
            data = encode_wheel_command(_ZERO)
            command = _ZERO
        self.cycle_count += 1
        tag = self.cycle_count
        with self._rx_lock:
            late, self._late = self._late, None
            self._wheel_pending.clear()
            self._hand_pending.clear()
            self._awaited = tag
            self._rx_mask = 0
            self._wheel_raw = self._hand_raw = None
            self._rx_event.clear()
            self._wheel_pending.add(tag)
        sent = self._try_send(self._message(WHEEL_COMMAND_ID, data), "0x201")
        if not sent:
            with self._rx_lock:
                self._wheel_pending.drop(tag)
        if self._with_hand and sent:
            with self._rx_lock:
                self._hand_pending.add(tag)
            if not self._try_send(
                self._message(HAND_SENSOR_REQUEST_ID, HAND_SENSOR_REQUEST), "0x20A"
            ):
                with self._rx_lock:
                    self._hand_pending.drop(tag)
        if count and sent and self.cycle_count % self.config.state_poll_cycles == 0:
            self._try_send(self._state_message(Command.KEEP), "0x200/0x11")
        if sent:
            self._rx_event.wait(self._timeout_s)
        with self._rx_lock:
            self._awaited = None
            fresh = self._rx_mask
            wheel, hand = self._wheel_raw, self._hand_raw
        if count:
            self._count(fresh)
        missed = self._missed_cycle
        if missed is not None and late is not None and late[0] == tag - 1 and late[1] is not None:
            # The last cycle's answer came after it gave up: latch it first, so the filters'
            # time base stays whole (the drive did step; only its answer was slow).
            self._latch(late[1], late[2], *missed)
        self._latch(wheel, hand, command, enabled)
        self._missed_cycle = (command, enabled) if wheel is None else None

    def _count(self, fresh: int) -> None:
        limit = self.config.max_missed_replies
        if fresh & _RX_WHEEL:
            self.consecutive_missed = 0
        else:
            self.missed_replies += 1
            self.consecutive_missed += 1
            if self.consecutive_missed > limit:
                self._record(
                    "replies",
                    f"SensoDrive: no answer to 0x201 for {self.consecutive_missed} cycles in a "
                    f"row (timeout {self.config.reply_timeout_ms:g} ms)",
                    key="0x201",
                )
        if not self._with_hand:
            return
        if fresh & _RX_HAND:
            self.consecutive_missed_hand = 0
        else:
            self.missed_hand_replies += 1
            self.consecutive_missed_hand += 1
            if self.consecutive_missed_hand > limit:
                self._record(
                    "replies",
                    f"SensoDrive: no answer to 0x20A (hand sensor) for "
                    f"{self.consecutive_missed_hand} cycles in a row",
                    key="0x20A",
                )

    def _latch(
        self,
        wheel: tuple[float, float, float] | None,
        hand: tuple[float, float] | None,
        command: WheelCommand,
        enabled: bool,
    ) -> None:
        if wheel is None:
            return  # hold the last values; the filters skip the cycle
        s = self._sign
        angle_d, _rate_d, torque_d = wheel
        angle = s * angle_d
        velocity = self._velocity_filter.step(angle)[1]
        self._reading = DriveReading(angle, velocity, s * torque_d)
        accel = self._rim_filter.step(angle)[2] if self._rim_filter is not None else 0.0
        rec = self._reconstruct
        if rec is not None:
            self._column_nm = rec.step(angle, command, enabled)
            self._column_recent.append(self._column_nm)
        elif hand is not None:
            u_a, u_b = hand
            rim = self.config.torque_sensor.rim_inertia_kgm2
            self._column_nm = (u_a - u_b) * self._hand_nm_per_v - rim * accel
            self._column_recent.append(self._column_nm)

    # -- sending -------------------------------------------------------------------------------

    @staticmethod
    def _message(can_id: int, data: bytes) -> can.Message:
        return can.Message(arbitration_id=can_id, is_extended_id=False, data=data)

    def _state_message(self, command: Command) -> can.Message:
        c = self.config
        data = encode_state_command(
            StateCommand(
                command, c.end_stop_deg, c.torque_limit_percent, c.torque_limit_beyond_percent
            )
        )
        return self._message(STATE_REQUEST_ID, data)

    def _send(self, msg: can.Message) -> None:
        with self._send_lock:
            self._bus.send(msg, timeout=_SEND_TIMEOUT_S)

    def _try_send(self, msg: can.Message, what: str) -> bool:
        try:
            self._send(msg)
            return True
        except can.CanError as exc:
            self._record(
                "bus", f"SensoDrive: CAN frame not sent: {what}: {_describe(exc)}", key=what
            )
            return False

    def _send_untracked_zero(self, what: str) -> bool:
        with self._rx_lock:
            self._wheel_pending.add(None)
        if not self._try_send(self._message(WHEEL_COMMAND_ID, encode_wheel_command(_ZERO)), what):
            with self._rx_lock:
                self._wheel_pending.drop(None)
            return False
        return True

    # -- state transitions (enable) ------------------------------------------------------------

    def _transition(self, command: Command, target: State | None) -> State | int | None:
        """Send ``command`` and poll the state until the drive reports ``target`` (None: the
        first answer will do). Returns the state reached.

        :raises DriveEnableError: not within ``state_timeout_s``; cancelled."""
        timeout = self.config.state_timeout_s
        deadline = time.monotonic() + timeout
        msg = self._state_message(command)
        state: State | int | None = None
        while True:
            with self._state_cond:
                seen = self._state_count
            self._send(msg)
            with self._state_cond:

                def answered(seen: int = seen) -> bool:
                    return self._state_count > seen or self._cancel.is_set()

                self._state_cond.wait_for(
                    answered, min(_STATE_POLL_S, max(0.0, deadline - time.monotonic()))
                )
                if self._state_count > seen:
                    state = self._state
            if self._cancel.is_set():
                raise DriveEnableError("cancelled by disable() or quick_stop()")
            if state is not None and (target is None or state == target):
                return state
            if time.monotonic() >= deadline:
                want = "an answer" if target is None else _state_name(target)
                raise DriveEnableError(
                    f"the drive did not reach {want} within {timeout:g} s: it stayed in "
                    f"{_state_name(state)}"
                )
            msg = self._state_message(Command.KEEP)  # the command went; now ask

    # -- receive thread ------------------------------------------------------------------------

    def _on_frame(self, msg: can.Message) -> None:
        cid = msg.arbitration_id
        try:
            if cid == WHEEL_REPLY_ID:
                r = decode_wheel_reply(msg.data)
                self._on_reply(
                    self._wheel_pending, _RX_WHEEL, (r.angle_rad, r.rate_rad_s, r.torque_nm)
                )
            elif cid == HAND_SENSOR_REPLY_ID:
                self._on_reply(self._hand_pending, _RX_HAND, decode_hand_sensor_reply(msg.data))
            elif cid == STATE_REPLY_ID:
                self._on_state(*decode_state_reply(msg.data))
        except FrameError as exc:
            self.bad_frames += 1
            self._record(
                "protocol",
                f"SensoDrive: malformed frame 0x{cid:03X} [{bytes(msg.data).hex()}]: {exc}",
                key=cid,
            )

    def _on_reply(self, pending: _Pending, bit: int, value: Any) -> None:
        with self._rx_lock:
            found, tag = pending.answer()
            if not found:
                self.unsolicited_replies += 1
                return
            if tag is None:
                return  # a request no cycle waits for
            if tag != self._awaited:
                self.late_replies += 1
                late = self._late if self._late is not None and self._late[0] == tag else None
                w, h = (late[1], late[2]) if late is not None else (None, None)
                if bit == _RX_WHEEL:
                    w = value
                else:
                    h = value
                self._late = (tag, w, h)
                return
            if bit == _RX_WHEEL:
                self._wheel_raw = value
            else:
                self._hand_raw = value
            self._rx_mask |= bit
            if self._rx_mask == self._rx_full:
                self._rx_event.set()

    def _on_state(self, state: State | int, info: int) -> None:
        with self._state_cond:
            self._state, self._error_info = state, info
            self._state_count += 1
            self._state_cond.notify_all()
        if not self._enabled:
            return
        if state == State.ERROR:
            self._enabled = False
            self._record(
                "state",
                f"SensoDrive reports its error state (0x18), error bytes 0x{info:04X}",
                key="error",
            )
        elif state != State.ON:
            self._enabled = False
            self._record(
                "state", f"SensoDrive left ON by itself: state {_state_name(state)}", key="left"
            )

    def _on_error_frame(self, msg: can.Message) -> None:
        self.error_frames += 1

    def _on_reader_failure(self, exc: BaseException) -> None:
        self._enabled = False
        self._rx_event.set()
        self._record("thread", f"SensoDrive: receive thread stopped: {_describe(exc)}", key=None)

    # -- faults --------------------------------------------------------------------------------

    def _record(self, kind: str, message: str, *, key: object) -> None:
        fault = SensoDriveFault(kind, message, time.monotonic())
        if not self._fault_log.add(fault, kind, key):
            return
        log.error("%s", message)


class _Reconstruction:
    """The driver torque from the wheel model, without a sensor (Steerlab's directions: the
    torque the wheel exerts on the hands)::

        T_d = T_motor − I·θ̈ − F_c·tanh(θ̇/ε) − G·sin θ,
        T_motor = u − b·θ̇ − k·θ − F_f·tanh(θ̇/ε)

    with u, b, k, F_f the torque, damping, stiffness and friction the host itself sent in the
    0x201 (zero while the drive is not ON), not the 0x211's torque, whose meaning on a real
    drive is unknown; I, F_c, G the wheel model a rig check measures. The friction field's law
    inside the drive is unknown: the Coulomb law here is an assumption.

    Every term goes through the same 4th-order Butterworth low-pass H
    (:class:`LowPassDerivatives` at ``filter_hz``): u itself (held between cycles), and θ, θ̇,
    θ̈ from the angle. So the result is H·T_d, free of the bias that mixing filtered and
    unfiltered terms would leave, but delayed by about 2.6/(2π·filter_hz) (10.4 ms at 40 Hz,
    20.8 ms at 20 Hz; gain 0.998 at half the cutoff, 0.71 at it): an analysis that relates it
    to the angle must pass the angle through the same H (:meth:`DriverTorque.
    frequency_response`). On top comes the angle's 0.009° quantization through I·θ̈: measured
    on the simulated wheel (I = 0.3 kg·m²) 0.16 N·m rms at 40 Hz, 0.035 N·m at 20 Hz (it
    grows as filter_hz^2.5); and the model's own errors: a wrong I adds ΔI·θ̈, unmodelled
    friction or imbalance their torque.
    """

    def __init__(self, config: SensoDriveConfig):
        ts = config.torque_sensor
        self.inertia = config.model_inertia_kgm2
        self.coulomb = ts.coulomb_nm
        self.gravity = ts.gravity_nm
        self.angle_filter = LowPassDerivatives(ts.filter_hz, config.period_s, order=4)
        self.torque_filter = LowPassDerivatives(ts.filter_hz, config.period_s, hold="step", order=4)
        self.sign = config.sign

    def step(self, angle: float, command: WheelCommand, enabled: bool) -> float:
        th, om, acc = self.angle_filter.step(angle)
        if enabled:
            u = self.sign * command.torque_nm  # back to Steerlab's direction
            b, k, ff = (
                command.damping_nms_per_rad,
                command.stiffness_nm_per_rad,
                command.friction_nm,
            )
        else:
            u = b = k = ff = 0.0
        u_f = self.torque_filter.step(u)[0]
        smooth_sign = math.tanh(om / COULOMB_EPS_RAD_S)
        motor = u_f - b * om - k * th - ff * smooth_sign
        return motor - self.inertia * acc - self.coulomb * smooth_sign - self.gravity * math.sin(th)


class DriverTorque(ZeroedTorque):
    """The SensoDrive's driver torque as a :class:`hardware.interfaces.ColumnTorque`: the hand
    sensor's or the reconstruction's value latched by each sync(), minus the offset
    :meth:`zero` measured from the cycles just run (wheel released)."""

    def __init__(self, drive: SensoDrive):
        super().__init__(drive.column_torque_nm, drive._column_recent, "driver torque")
        self._drive = drive

    @property
    def source(self) -> str:
        return self._drive.config.torque_sensor.source

    def frequency_response(self, f_hz: float) -> complex:
        """What the value's path does to the driver torque at ``f_hz``: the reconstruction's
        low-pass (1 for the hand sensor, whose voltages are not filtered)."""
        rec = self._drive._reconstruct
        return 1.0 + 0j if rec is None else rec.angle_filter.response(f_hz)


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"
