"""The udp_loopback bus between buses of one machine."""

import time
import uuid

import can

from steerlab.hardware.can.udp_bus import UdpLoopbackBus


def _frame(i: int) -> can.Message:
    return can.Message(arbitration_id=i, data=bytes([i]), is_extended_id=False)


def test_a_poll_finds_a_frame_queued_behind_our_own():
    # A driver that polls (recv(0), as PCAN-Basic's Read does) must not see "nothing" while
    # another node's answer waits behind the echo of its own request.
    channel = f"udp-test-{uuid.uuid4().hex[:8]}"
    host, drive = UdpLoopbackBus(channel), UdpLoopbackBus(channel)
    try:
        host.send(_frame(1))
        drive.send(_frame(2))
        time.sleep(0.05)
        got = host.recv(0)
        assert got is not None and got.arbitration_id == 2
        assert host.recv(0) is None
        got = drive.recv(0)
        assert got is not None and got.arbitration_id == 1
    finally:
        host.shutdown()
        drive.shutdown()
