"""A simulated SensoDrive SENSO-Wheel on a python-can bus: the vendor's request/response
protocol (``docs/sensodrive-protocol.md``, :mod:`hardware.can.sensodrive_frames`), with the drive's
own rendering of torque, friction, damping and spring, so a SensoDrive driver (ours or the
public clients through a PCAN-Basic stand-in) runs against it unchanged. Any bus works: the
virtual bus in one process, ``udp_loopback`` (:mod:`hardware.can.udp_bus`) across processes.

What it answers (every request ``0x20n`` with one reply ``0x21n``):

- ``0x200`` (DLC 8): a state command, the end stop and the two torque limits (remembered from
  every frame); the ``0x210`` reply carries the state *after* the command.
- ``0x201`` (DLC 8): torque, friction, damping, stiffness. The host's ``0x201`` is the node's
  clock, as SYNC is a CiA 402 node's: each one advances the plant exactly one step, then the
  ``0x211`` reply carries the new angle, rate and the motor torque of that step. Answered in
  every state (a client reads its initial state before enabling).
- ``0x20A`` (DLC 2): the hand-torque sensor's two voltages (``0x21A``), only when the node has
  one (``hand_sensor_v_per_nm``): by the sensor manual's formula, the torque the hands put on
  the wheel, in the drive's direction.
- ``0x20C`` (DLC 1): pedals (``0x21C``) at rest (throttle raw 1100, brake raw 1), so a client
  that polls them gets an answer.

States and commands (``0x200`` byte 0): OFF ``0x10`` from any state but ERROR; READY ``0x12``
from OFF, READY or ON; ON ``0x14`` only from READY or ON (both public clients pass through
READY; whether a real drive accepts ON from OFF is unknown, so this node refuses it); clear
error ``0x1F`` to OFF from any state; keep ``0x11``. Torque only while ON.

Rendering while ON, in the drive's direction (θ, ω of the wheel; the fields of the last
``0x201``)::

    τ = torque − damping·ω − stiffness·θ − friction·tanh(ω/ω_f) [− K_es·(|θ| − end stop)·sgn θ]

clamped to ±limit % × ``full_scale_torque_nm`` / 100, with the limit between or beyond the end
stops. The friction is Coulomb smoothed over ω_f = :data:`FRICTION_SMOOTHING_RAD_S` (zero at
rest, no chatter); the end stop is a spring of :data:`END_STOP_STIFFNESS_NM_PER_RAD` beyond
±end stop (a negative end stop field counts by its magnitude: lflipse's hard-coded bytes read
as −19 456°). The drive's real internal rate, velocity filter and friction law are unknown.

Directions: the plant works in Steerlab's (positive counter-clockwise seen by the driver); the
drive in its own, value = ``sign`` × Steerlab value (default −1: the clients' evidence points to
clockwise-positive).

Watchdog: ``watchdog_s=None`` means none (the real drive's timeout is unknown: a host must not
count on one). With a value, ON and no ``0x200``/``0x201`` for that long → ERROR, torque 0;
checked on the reader's ticker as well as on frames, so a silent bus trips it too.

Fault injection (:meth:`SimulatedSensoDrive.inject`): ``go_silent`` (hears nothing, sends
nothing; its watchdog still runs), ``error`` (ERROR now, torque 0), ``mute_replies`` (no
``0x211`` any more, while the ``0x201`` it hears still step the plant and set the torque).
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from dataclasses import asdict
from typing import Any

import can

from .frames import FrameError
from .sensodrive_frames import (
    HAND_SENSOR_REQUEST_ID,
    PEDAL_REQUEST_ID,
    STATE_REQUEST_ID,
    WHEEL_COMMAND_ID,
    Command,
    State,
    WheelCommand,
    WheelReply,
    decode_state_command,
    decode_wheel_command,
    encode_hand_sensor_reply,
    encode_state_reply,
    encode_wheel_reply,
    reply_id,
)
from .sim_node import Plant
from .transport import BusReader

log = logging.getLogger(__name__)

#: The spring beyond the end stops (drive-rendered; the real one's stiffness is unknown).
END_STOP_STIFFNESS_NM_PER_RAD = 100.0
#: Velocity over which the Coulomb friction reaches ~76 % of its value (tanh(1)).
FRICTION_SMOOTHING_RAD_S = 0.01
#: Pedals at rest, as JOAN maps them: throttle (raw − 1100)/2460 = 0, brake (raw − 1)/500 = 0.
PEDALS_AT_REST = struct.pack("<HHHH", 0, 1100, 1, 0)
#: Kept entries of :attr:`SimulatedSensoDrive.errors` (a flood of bad frames must not grow it).
MAX_ERRORS = 1000

_REQUEST_DLC = {
    STATE_REQUEST_ID: 8,
    WHEEL_COMMAND_ID: 8,
    HAND_SENSOR_REQUEST_ID: 2,
    PEDAL_REQUEST_ID: 1,
}
_STATE_WORD = {State.OFF: "off", State.READY: "ready", State.ON: "on", State.ERROR: "error"}


def _next_state(state: State, command: Command) -> State:
    if command is Command.CLEAR_ERROR:
        return State.OFF
    if state is State.ERROR or command is Command.KEEP:
        return state
    if command is Command.OFF:
        return State.OFF
    if command is Command.READY:
        return State.READY
    # ON: only from READY (or staying ON)
    return State.ON if state in (State.READY, State.ON) else state


class SimulatedSensoDrive:
    """A SENSO-Wheel on ``bus`` driving ``plant`` (see the module docstring).

    :meth:`start` runs its receive thread until :meth:`close`; replies go out on that thread
    (a host at 1 kHz waits well under a millisecond for them). Nothing the bus brings stops the
    thread: malformed frames (wrong DLC, unknown command) are recorded in ``errors`` and not
    answered; a plant that raises puts the drive in ERROR.
    """

    faults = ("go_silent", "error", "mute_replies")

    def __init__(
        self,
        bus: can.BusABC,
        plant: Plant,
        *,
        sign: int = -1,
        hand_sensor_v_per_nm: float | None = None,
        watchdog_s: float | None = None,
        full_scale_torque_nm: float = 10.0,
        hand_sensor_offset_v: float = 2.5,
        poll_s: float = 0.002,
        owns_bus: bool = False,
    ):
        self._owns_bus = owns_bus  # close() then shuts the bus down too
        if sign not in (1, -1):
            raise ValueError(f"sign must be +1 or -1, not {sign!r}")
        if watchdog_s is not None and not watchdog_s > 0:
            raise ValueError(f"watchdog_s must be positive or None, not {watchdog_s!r}")
        if not full_scale_torque_nm > 0:
            raise ValueError(f"full_scale_torque_nm must be positive, not {full_scale_torque_nm}")
        self.plant = plant
        self.sign = sign
        self.hand_sensor_v_per_nm = hand_sensor_v_per_nm
        self.hand_sensor_offset_v = hand_sensor_offset_v
        self.watchdog_s = watchdog_s
        self.full_scale_torque_nm = full_scale_torque_nm
        self._bus = bus
        self._lock = threading.Lock()

        self.state = State.OFF
        self.command = WheelCommand()
        #: From the last 0x200: end stop (degrees) and limits (percent) between / beyond.
        self.end_stop_deg: int | None = None
        self.torque_limits_percent: tuple[int, int] | None = None
        self._applied_drive = 0.0  # motor torque now, the drive's direction
        #: time.monotonic() since which the applied torque is zero (None while it is not);
        #: CLOCK_MONOTONIC is system-wide, so another process can compare it with its own.
        self.zero_torque_since: float | None = time.monotonic()
        self._last_host: float = time.monotonic()
        self.watchdog_trips = 0
        self.enabled_cycles = 0
        self.requests: dict[str, int] = {}
        self.errors: list[str] = []
        self._silent = False
        self._mute_replies = False
        self._started = False
        self._reader = BusReader(
            bus,
            self._on_frame,
            self._on_reader_failure,
            name="SimulatedSensoDrive rx",
            on_tick=self._on_tick,
            poll_s=poll_s,
        )

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> None:
        """Power on (OFF) and start answering. Calling it again does nothing."""
        if self._started:
            return
        self._started = True
        self._last_host = time.monotonic()
        self._reader.start()

    def close(self) -> None:
        """Stop the receive thread; shut the bus down if it was given to own (``owns_bus``)."""
        self._reader.stop()
        if self._owns_bus:
            try:
                self._bus.shutdown()
            except Exception:
                pass

    def __enter__(self) -> SimulatedSensoDrive:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- fault injection -----------------------------------------------------------------------

    def inject(self, fault: str) -> None:
        """Inject one of :attr:`faults`.

        :raises ValueError: an unknown fault name.
        """
        if fault not in self.faults:
            raise ValueError(f"unknown fault {fault!r}; known: {', '.join(self.faults)}")
        with self._lock:
            if fault == "go_silent":
                self._silent = True
            elif fault == "error":
                self._set_state(State.ERROR)
            else:
                self._mute_replies = True

    # -- what a test or the lab's control socket asks ------------------------------------------

    @property
    def applied_torque_nm(self) -> float:
        """The torque on the wheel now (N·m, Steerlab's direction)."""
        return self.sign * self._applied_drive

    @property
    def watching_host(self) -> bool:
        return self.watchdog_s is not None

    def status(self) -> dict[str, Any]:
        """A snapshot: state word, torque, counters, the last command and settings."""
        with self._lock:
            return {
                "state": _STATE_WORD[self.state],
                "applied_torque_nm": self.applied_torque_nm,
                "zero_torque_since": self.zero_torque_since,
                "enabled_cycles": self.enabled_cycles,
                "requests": dict(self.requests),
                "last_command": asdict(self.command),
                "end_stop_deg": self.end_stop_deg,
                "torque_limits_percent": self.torque_limits_percent,
                "watching_host": self.watching_host,
                "watchdog_trips": self.watchdog_trips,
                "silent": self._silent,
                "mute_replies": self._mute_replies,
                "errors": list(self.errors),
            }

    # -- frames --------------------------------------------------------------------------------

    def _on_frame(self, msg: can.Message) -> None:
        with self._lock:
            if self._silent:
                return
            cid = msg.arbitration_id
            key = f"0x{cid:03X}"
            self.requests[key] = self.requests.get(key, 0) + 1
            dlc = _REQUEST_DLC.get(cid)
            if dlc is None or msg.is_extended_id:
                return  # not ours (a reply, another node's traffic)
            data = bytes(msg.data)
            if len(data) != dlc:
                self._error(f"{key}: DLC {len(data)}, expected {dlc}")
                return
            try:
                if cid == WHEEL_COMMAND_ID:
                    self._last_host = time.monotonic()
                    self._on_wheel_command(data)
                elif cid == STATE_REQUEST_ID:
                    self._last_host = time.monotonic()
                    self._on_state_command(data)
                elif cid == HAND_SENSOR_REQUEST_ID:
                    self._on_hand_sensor()
                else:
                    self._send(reply_id(cid), PEDALS_AT_REST)
            except FrameError as exc:
                self._error(str(exc))
            except can.CanError as exc:
                self._error(f"{key}: reply not sent: {exc}")
            except Exception as exc:  # the plant failed: a firmware error on a real drive
                self._error(f"{key}: {exc!r}")
                log.exception("simulated SensoDrive: %s failed", key)
                self._set_state(State.ERROR)

    def _on_state_command(self, data: bytes) -> None:
        c = decode_state_command(data)
        self.end_stop_deg = c.end_stop_deg
        self.torque_limits_percent = (c.torque_limit_pct, c.torque_limit_beyond_pct)
        self._set_state(_next_state(self.state, c.command))
        self._send(reply_id(STATE_REQUEST_ID), encode_state_reply(self.state))

    def _on_wheel_command(self, data: bytes) -> None:
        self.command = decode_wheel_command(data)
        on = self.state is State.ON
        torque = self._render() if on else 0.0
        self._apply(torque)
        if on:
            self.enabled_cycles += 1
        self.plant.step(self.sign * torque)
        angle, velocity, _, _ = self.plant.read()
        if self._mute_replies:
            return
        s = self.sign
        reply = WheelReply(s * angle, s * velocity, torque)
        self._send(reply_id(WHEEL_COMMAND_ID), encode_wheel_reply(reply))

    def _render(self) -> float:
        """The motor torque of this step (drive direction) from the wheel's state now."""
        angle, velocity, _, _ = self.plant.read()
        theta, omega = self.sign * angle, self.sign * velocity
        c = self.command
        torque = (
            c.torque_nm
            - c.damping_nms_per_rad * omega
            - c.stiffness_nm_per_rad * theta
            - c.friction_nm * math.tanh(omega / FRICTION_SMOOTHING_RAD_S)
        )
        assert self.end_stop_deg is not None and self.torque_limits_percent is not None  # ON
        end = math.radians(abs(self.end_stop_deg))
        between, beyond = self.torque_limits_percent
        limit_pct = between
        if abs(theta) > end:
            torque -= END_STOP_STIFFNESS_NM_PER_RAD * (theta - math.copysign(end, theta))
            limit_pct = beyond
        limit = limit_pct / 100.0 * self.full_scale_torque_nm
        return max(-limit, min(limit, torque))

    def _on_hand_sensor(self) -> None:
        if self.hand_sensor_v_per_nm is None:
            return  # no sensor fitted: no answer
        # The sensor manual's formula gives the torque the hands put on the wheel (the joan
        # client adds the rim's J·θ̈ to it to get the hands' torque): minus the column torque,
        # which is the wheel's on the hands; in the drive's direction.
        column = self.plant.read()[3]
        d = self.hand_sensor_v_per_nm * (self.sign * -column)
        off = self.hand_sensor_offset_v
        self._send(
            reply_id(HAND_SENSOR_REQUEST_ID), encode_hand_sensor_reply(off + d / 2, off - d / 2)
        )

    # -- the drive's own clock -----------------------------------------------------------------

    def _on_tick(self, now: float) -> None:
        if self.watchdog_s is None:
            return
        with self._lock:
            if self.state is State.ON and now - self._last_host > self.watchdog_s:
                self.watchdog_trips += 1
                self._error(f"watchdog: no 0x200/0x201 for {now - self._last_host:.3f} s")
                self._set_state(State.ERROR)

    # -- helpers -------------------------------------------------------------------------------

    def _set_state(self, state: State) -> None:
        self.state = state
        if state is not State.ON:
            self._apply(0.0)  # the power stage is off at once, whatever the next 0x201

    def _apply(self, torque_drive_nm: float) -> None:
        if torque_drive_nm == 0.0:
            if self._applied_drive != 0.0 or self.zero_torque_since is None:
                self.zero_torque_since = time.monotonic()
        else:
            self.zero_torque_since = None
        self._applied_drive = torque_drive_nm

    def _send(self, can_id: int, data: bytes) -> None:
        if self._silent:
            return
        self._bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def _error(self, text: str) -> None:
        self.errors.append(text)
        del self.errors[:-MAX_ERRORS]

    def _on_reader_failure(self, exc: BaseException) -> None:
        self._error(f"reader stopped: {exc!r}")
