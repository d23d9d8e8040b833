"""A stand-in for PEAK's ``PCANBasic.py`` on python-can: the few PCAN-Basic names the public
SensoDrive clients use, so those clients run unmodified against Steerlab's simulated
SENSO-Wheel (:mod:`hardware.can.sensodrive_sim`) with no PEAK adapter or driver library.

Put this directory first on ``sys.path`` (or alias the client's vendored module name to this
module) and the client's ``from ...PCANBasic import *`` gets these names. Written from the
PCAN-Basic API as the clients call it, not from PEAK's file: the structures have the same
fields, the constants the same values, ``Read`` returns ``(status, TPCANMsg,
TPCANTimestamp)`` from a receive queue that a thread fills from ``Initialize`` on (as the
adapter's driver does) and never blocks, ``Write`` sends one frame.

Which bus a PCAN channel handle opens, from environment variables:

``STEERLAB_PCAN_INTERFACE``
    python-can interface: ``udp_loopback`` (the default: Steerlab's bus shared between
    processes, :mod:`hardware.can.udp_bus`), ``virtual`` (one process), or any python-can
    interface name (``socketcan``, ...).
``STEERLAB_PCAN_CHANNEL``
    the channel for ``PCAN_USBBUS1`` (default ``sensodrive``).
``STEERLAB_PCAN_CHANNEL_USBBUS2`` (``_USBBUS3`` ...)
    the channel for the other handles (default: ``STEERLAB_PCAN_CHANNEL`` + ``-2`` ...).

The bit rate passed to ``Initialize`` is given to interfaces that take one and otherwise
ignored. Like the DLL, one process holds each channel once: ``Initialize`` of a channel already
open returns ``PCAN_ERROR_INITIALIZE``, as do ``Read``/``Write`` on one not open.
"""

from __future__ import annotations

import collections
import os
import threading
import time
from ctypes import Structure, c_char_p, c_ubyte, c_uint, c_ulonglong, c_ushort
from typing import Any

import can

__all__ = [
    "PCANBasic",
    "TPCANBaudrate",
    "TPCANBitrateFD",
    "TPCANHandle",
    "TPCANMessageType",
    "TPCANMsg",
    "TPCANStatus",
    "TPCANTimestamp",
    "TPCANTimestampFD",
    "TPCANType",
    "PCAN_NONEBUS",
    "PCAN_USBBUS1",
    "PCAN_USBBUS2",
    "PCAN_USBBUS3",
    "PCAN_USBBUS4",
    "PCAN_BAUD_1M",
    "PCAN_BAUD_500K",
    "PCAN_BAUD_250K",
    "PCAN_BAUD_125K",
    "PCAN_ERROR_OK",
    "PCAN_ERROR_XMTFULL",
    "PCAN_ERROR_QRCVEMPTY",
    "PCAN_ERROR_ILLPARAMVAL",
    "PCAN_ERROR_INITIALIZE",
    "PCAN_ERROR_ILLOPERATION",
    "PCAN_ERROR_UNKNOWN",
    "PCAN_MESSAGE_STANDARD",
    "PCAN_MESSAGE_RTR",
    "PCAN_MESSAGE_EXTENDED",
    "PCAN_MODE_STANDARD",
]

# -- types (as PCAN-Basic declares them) --------------------------------------------------------

TPCANHandle = c_ushort
TPCANStatus = int
TPCANMessageType = c_ubyte
TPCANType = c_ubyte
TPCANBaudrate = c_ushort
TPCANBitrateFD = c_char_p
TPCANTimestampFD = c_ulonglong


class TPCANMsg(Structure):
    """A CAN frame: identifier, type flags, length, eight data bytes."""

    _fields_ = [
        ("ID", c_uint),
        ("MSGTYPE", TPCANMessageType),
        ("LEN", c_ubyte),
        ("DATA", c_ubyte * 8),
    ]


class TPCANTimestamp(Structure):
    """Receive time: micros + 1000·millis + 2³²·1000·millis_overflow µs."""

    _fields_ = [
        ("millis", c_uint),
        ("millis_overflow", c_ushort),
        ("micros", c_ushort),
    ]


# -- constants (PCAN-Basic's values) ------------------------------------------------------------

PCAN_NONEBUS = TPCANHandle(0x00)
PCAN_USBBUS1 = TPCANHandle(0x51)
PCAN_USBBUS2 = TPCANHandle(0x52)
PCAN_USBBUS3 = TPCANHandle(0x53)
PCAN_USBBUS4 = TPCANHandle(0x54)

PCAN_BAUD_1M = TPCANBaudrate(0x0014)
PCAN_BAUD_500K = TPCANBaudrate(0x001C)
PCAN_BAUD_250K = TPCANBaudrate(0x011C)
PCAN_BAUD_125K = TPCANBaudrate(0x031C)
_BITRATE = {0x0014: 1_000_000, 0x001C: 500_000, 0x011C: 250_000, 0x031C: 125_000}

PCAN_ERROR_OK = TPCANStatus(0x00000)
PCAN_ERROR_XMTFULL = TPCANStatus(0x00001)
PCAN_ERROR_QRCVEMPTY = TPCANStatus(0x00020)
PCAN_ERROR_ILLPARAMVAL = TPCANStatus(0x08000)
PCAN_ERROR_UNKNOWN = TPCANStatus(0x10000)
PCAN_ERROR_INITIALIZE = TPCANStatus(0x4000000)
PCAN_ERROR_ILLOPERATION = TPCANStatus(0x8000000)

PCAN_MESSAGE_STANDARD = TPCANMessageType(0x00)
PCAN_MESSAGE_RTR = TPCANMessageType(0x01)
PCAN_MESSAGE_EXTENDED = TPCANMessageType(0x02)
PCAN_MODE_STANDARD = PCAN_MESSAGE_STANDARD

# -- the channels this process holds ------------------------------------------------------------


class _Channel:
    """An open bus and its receive queue, filled by a thread of its own as the PCAN driver
    fills the adapter's queue: ``Read`` only pops. (Polling the bus from ``Read`` instead
    would lose time on frames the bus discards, e.g. ``udp_loopback``'s echo of our own
    frames, and let replies pile up behind a client that reads once per write.)"""

    def __init__(self, bus: can.BusABC):
        self.bus = bus
        self.queue: collections.deque[can.Message] = collections.deque()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="PCANBasic stand-in rx", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                frame = self.bus.recv(0.05)
            except can.CanError:
                return
            if frame is not None and not frame.is_error_frame:
                self.queue.append(frame)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.bus.shutdown()


_open: dict[int, _Channel] = {}


def _handle(channel: Any) -> int:
    return int(getattr(channel, "value", channel))


def _channel_name(handle: int) -> str:
    base = os.environ.get("STEERLAB_PCAN_CHANNEL", "sensodrive")
    if handle == 0x51:
        return base
    n = handle - 0x50
    return os.environ.get(f"STEERLAB_PCAN_CHANNEL_USBBUS{n}", f"{base}-{n}")


def _open_bus(handle: int, bitrate: int | None) -> can.BusABC:
    interface = os.environ.get("STEERLAB_PCAN_INTERFACE", "udp_loopback")
    channel = _channel_name(handle)
    if interface == "udp_loopback":
        from steerlab.hardware.can.udp_bus import UdpLoopbackBus

        return UdpLoopbackBus(channel)
    options: dict[str, Any] = {"receive_own_messages": False}
    if bitrate is not None and interface != "virtual":
        options["bitrate"] = bitrate
    return can.Bus(interface=interface, channel=channel, **options)


class PCANBasic:
    """The PCAN-Basic calls the SensoDrive clients make, on python-can buses."""

    def Initialize(
        self, Channel: Any, Btr0Btr1: Any, HwType: Any = 0, IOPort: Any = 0, Interrupt: Any = 0
    ) -> int:
        handle = _handle(Channel)
        if handle in _open:
            return PCAN_ERROR_INITIALIZE
        try:
            _open[handle] = _Channel(_open_bus(handle, _BITRATE.get(_handle(Btr0Btr1))))
        except (can.CanError, OSError, ValueError):
            return PCAN_ERROR_ILLOPERATION
        return PCAN_ERROR_OK

    def Uninitialize(self, Channel: Any) -> int:
        channel = _open.pop(_handle(Channel), None)
        if channel is None:
            return PCAN_ERROR_INITIALIZE
        channel.close()
        return PCAN_ERROR_OK

    def Reset(self, Channel: Any) -> int:
        """Empty the receive queue."""
        channel = _open.get(_handle(Channel))
        if channel is None:
            return PCAN_ERROR_INITIALIZE
        channel.queue.clear()
        return PCAN_ERROR_OK

    def GetStatus(self, Channel: Any) -> int:
        return PCAN_ERROR_OK if _handle(Channel) in _open else PCAN_ERROR_INITIALIZE

    def Read(self, Channel: Any) -> tuple[int, TPCANMsg, TPCANTimestamp]:
        """The oldest received frame, or ``PCAN_ERROR_QRCVEMPTY`` at once (never waits)."""
        msg, stamp = TPCANMsg(), TPCANTimestamp()
        channel = _open.get(_handle(Channel))
        if channel is None:
            return PCAN_ERROR_INITIALIZE, msg, stamp
        try:
            frame = channel.queue.popleft()
        except IndexError:
            return PCAN_ERROR_QRCVEMPTY, msg, stamp
        msg.ID = frame.arbitration_id
        msg.MSGTYPE = (0x02 if frame.is_extended_id else 0) | (0x01 if frame.is_remote_frame else 0)
        msg.LEN = frame.dlc
        for i, b in enumerate(bytes(frame.data)[:8]):
            msg.DATA[i] = b
        us = int((frame.timestamp or time.time()) * 1e6)
        ms = us // 1000
        stamp.micros = us % 1000
        stamp.millis = ms & 0xFFFF_FFFF
        stamp.millis_overflow = (ms >> 32) & 0xFFFF
        return PCAN_ERROR_OK, msg, stamp

    def Write(self, Channel: Any, MessageBuffer: TPCANMsg) -> int:
        channel = _open.get(_handle(Channel))
        if channel is None:
            return PCAN_ERROR_INITIALIZE
        length = int(MessageBuffer.LEN)
        if length > 8:
            return PCAN_ERROR_ILLPARAMVAL
        kind = int(MessageBuffer.MSGTYPE)
        frame = can.Message(
            arbitration_id=int(MessageBuffer.ID),
            is_extended_id=bool(kind & 0x02),
            is_remote_frame=bool(kind & 0x01),
            dlc=length,
            data=b"" if kind & 0x01 else bytes(MessageBuffer.DATA[:length]),
        )
        try:
            channel.bus.send(frame)
        except can.CanError:
            return PCAN_ERROR_XMTFULL
        return PCAN_ERROR_OK

    def GetErrorText(self, Error: int, Language: int = 0) -> tuple[int, bytes]:
        return PCAN_ERROR_OK, f"PCAN status 0x{int(Error):X} (stand-in)".encode()
