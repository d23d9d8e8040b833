"""A CAN bus shared between processes of one machine: UDP multicast on the loopback interface.

python-can's ``virtual`` bus connects buses in one process only, so a host that is killed takes
the simulated drive with it. With ``interface = "udp_loopback"`` the simulated drive can run in a
process of its own (:mod:`hardware.sim.lab`), and killing the host is a real host kill: the
drive keeps running and must cut the torque by itself. (python-can's ``udp_multicast`` interface
does the same but needs msgpack; socketcan ``vcan`` needs a kernel module this machine may not
have.)

Every bus on one ``channel`` (a name: it picks the UDP port) receives every frame the others
send, in order per sender. One datagram per frame: 8 bytes sender id, then CAN id (u32),
flags (u8: 1 extended, 2 remote, 4 error frame), DLC (u8), 8 data bytes and the send time
(time.time(), f64: the frame's timestamp, as python-can's virtual bus gives it). Nothing leaves the
machine (multicast TTL 0, loopback interface).
"""

from __future__ import annotations

import os
import select
import socket
import struct
import time
import zlib

import can

GROUP = "239.74.163.2"
_FRAME = struct.Struct("<IBB8sd")
_EXT, _RTR, _ERR = 1, 2, 4


def channel_port(channel: str) -> int:
    """The UDP port of a channel name (40000..59999)."""
    return 40000 + zlib.crc32(str(channel).encode()) % 20000


class UdpLoopbackBus(can.BusABC):
    """python-can bus over UDP multicast on 127.0.0.1 (see the module docstring)."""

    def __init__(
        self,
        channel: str,
        *,
        can_filters: can.typechecking.CanFilters | None = None,
        receive_own_messages: bool = False,
        **kwargs: object,
    ):
        self.channel = str(channel)
        self._port = channel_port(self.channel)
        self._id = os.urandom(8)
        self._own = receive_own_messages
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            s.bind(("", self._port))
            lo = socket.inet_aton("127.0.0.1")
            s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(GROUP) + lo)
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, lo)
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        except OSError as e:
            s.close()
            raise can.CanInitializationError(f"udp_loopback {channel!r}: {e}") from e
        self._sock: socket.socket | None = s
        self.channel_info = f"udp_loopback {GROUP}:{self._port} ({self.channel})"
        super().__init__(channel=self.channel, can_filters=can_filters, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        sock = self._sock
        if sock is None:
            raise can.CanOperationError("Cannot operate on a closed bus")
        flags = (
            (_EXT if msg.is_extended_id else 0)
            | (_RTR if msg.is_remote_frame else 0)
            | (_ERR if msg.is_error_frame else 0)
        )
        data = bytes(msg.data)
        payload = self._id + _FRAME.pack(msg.arbitration_id, flags, len(data), data, time.time())
        try:
            sock.sendto(payload, (GROUP, self._port))
        except OSError as e:
            raise can.CanOperationError(f"{self.channel_info}: {e}") from e

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        sock = self._sock
        if sock is None:
            raise can.CanOperationError("Cannot operate on a closed bus")
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            # Our own frames come back from the group: skipped here, not returned as "nothing",
            # so that a poll (timeout 0) still finds the frames queued behind one of them.
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                ready, _, _ = select.select([sock], [], [], wait)
                if not ready:
                    return None, False
                payload = sock.recv(64)
            except (OSError, ValueError) as e:  # closed by shutdown() meanwhile
                raise can.CanOperationError(f"{self.channel_info}: {e}") from e
            if len(payload) == 8 + _FRAME.size and (payload[:8] != self._id or self._own):
                break
        cid, flags, dlc, data, sent = _FRAME.unpack_from(payload, 8)
        msg = can.Message(
            timestamp=sent,
            arbitration_id=cid,
            is_extended_id=bool(flags & _EXT),
            is_remote_frame=bool(flags & _RTR),
            is_error_frame=bool(flags & _ERR),
            dlc=dlc,
            data=data[:dlc],
            channel=self.channel,
        )
        return msg, False

    def shutdown(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
        super().shutdown()
