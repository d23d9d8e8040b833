"""The CAN transport: opening the bus the rig file names, and the one receive thread per bus.

Drivers take a ready ``can.BusABC`` so tests and the simulated rig pass a virtual bus and the lab
passes socketcan/pcan/kvaser/vector — the driver code is the same.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import can

from .config import UDP_LOOPBACK, DriveConfig
from .frames import (
    emcy_cob_id,
    heartbeat_cob_id,
    sdo_tx_cob_id,
    tpdo_cob_id,
)

log = logging.getLogger(__name__)


def driver_filters(config: DriveConfig) -> list[can.typechecking.CanFilter]:
    """Acceptance filters for the host: only what the drive sends (EMCY, TPDO1/2, SDO answers,
    heartbeat) and, with a torque sensor node, its frame (and its heartbeat if watched). On
    hardware interfaces the filtering happens in the controller or kernel, which keeps other
    nodes' traffic out of the Python receive thread."""
    n = config.node_id
    ids = [
        emcy_cob_id(n),
        tpdo_cob_id(1, n),
        tpdo_cob_id(2, n),
        sdo_tx_cob_id(n),
        heartbeat_cob_id(n),
    ]
    sensor = config.torque_sensor
    if sensor.source == "node" and sensor.node_id is not None and sensor.frame_cob_id is not None:
        ids.append(sensor.frame_cob_id)
        if sensor.heartbeat_timeout_ms > 0:
            ids.append(heartbeat_cob_id(sensor.node_id))
    return [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids]


def open_bus(config: Any, *, filtered: bool = True, **kwargs: object) -> can.BusABC:
    """Open the bus named by the rig file's ``interface``, ``channel`` and ``bitrate`` (a drive
    config of any kind; ``filtered`` is the CiA 402 driver's filters, a :class:`DriveConfig`'s).

    ``filtered=True`` installs :func:`driver_filters`; pass ``False`` for a bus that must see
    everything (a simulated drive node, a bus monitor). Extra keyword arguments go to
    ``can.Bus`` (backend options such as ``fd`` or ``app_name``).

    :raises can.CanError: the interface cannot be opened (subclasses
        ``CanInterfaceNotImplementedError``, ``CanInitializationError``).
    """
    options: dict[str, Any] = {"bitrate": config.bitrate}
    if config.interface == "virtual":
        # Our own frames must not come back to us as if the drive had sent them.
        options["receive_own_messages"] = False
    if filtered:
        options["can_filters"] = driver_filters(config)
    options.update(kwargs)
    if config.interface == UDP_LOOPBACK:
        from .udp_bus import UdpLoopbackBus

        options.pop("bitrate")
        return UdpLoopbackBus(str(config.channel), **options)
    return can.Bus(interface=config.interface, channel=config.channel, **options)


class BusReader:
    """The single reader of one bus.

    Hands every data frame to ``on_frame`` (error frames to ``on_error_frame``, remote frames
    are dropped), and calls ``on_tick`` at least every ``poll_s`` so watchdogs run even when
    the bus is silent. If ``bus.recv`` or a callback raises, the thread does not die silently:
    it calls ``on_failure`` with the exception and stops. Callbacks run on this thread and must
    be quick; they must not wait for frames this thread would deliver (e.g. an SDO transfer).
    """

    def __init__(
        self,
        bus: can.BusABC,
        on_frame: Callable[[can.Message], None],
        on_failure: Callable[[BaseException], None],
        *,
        name: str,
        on_tick: Callable[[float], None] | None = None,
        on_error_frame: Callable[[can.Message], None] | None = None,
        poll_s: float = 0.01,
    ):
        self._bus = bus
        self._on_frame = on_frame
        self._on_failure = on_failure
        self._on_tick = on_tick
        self._on_error_frame = on_error_frame
        self._poll_s = poll_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.failure: BaseException | None = None

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 1.0) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def thread(self) -> threading.Thread:
        return self._thread

    def _run(self) -> None:
        recv = self._bus.recv
        on_frame = self._on_frame
        next_tick = 0.0
        try:
            while not self._stop.is_set():
                msg = recv(self._poll_s)
                if msg is not None:
                    if msg.is_error_frame:
                        if self._on_error_frame is not None:
                            self._on_error_frame(msg)
                    elif not msg.is_remote_frame:
                        on_frame(msg)
                if self._on_tick is not None:
                    now = time.monotonic()
                    if now >= next_tick:
                        next_tick = now + self._poll_s
                        self._on_tick(now)
        except Exception as exc:
            if self._stop.is_set():
                # Shutting down: the bus was closed under us, which is the normal way out.
                return
            self.failure = exc
            log.error("%s stopped: %r", self._thread.name, exc)
            try:
                self._on_failure(exc)
            except Exception:
                log.exception("%s: failure handler raised", self._thread.name)
