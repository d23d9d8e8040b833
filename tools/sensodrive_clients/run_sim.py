"""SimulatedSensoDrive in its own process on a udp_loopback channel, plus a bus monitor that
logs every frame (host requests and the node's replies). Runs until stdin closes; then writes
<out>-frames.csv and <out>-status.json.

The drive: sign -1 (its direction is minus Steerlab's), hand sensor fitted, no watchdog unless
--watchdog; the wheel: J = 0.3 kg·m² held by a relaxed hand (k = 5 N·m/rad, b = 1 N·m·s/rad),
stepped by --dt per 0x201 request (the node's clock is the host's requests).

usage: run_sim.py CHANNEL OUT [--watchdog S] [--dt S]
"""

import argparse
import csv
import json
import sys
import threading
import time

from steerlab.hardware.can.sensodrive_sim import SimulatedSensoDrive
from steerlab.hardware.can.udp_bus import UdpLoopbackBus


class HeldWheel:
    """J = 0.3 kg·m², relaxed hand k = 5 N·m/rad, b = 1 N·m·s/rad (Steerlab direction)."""

    def __init__(self, dt):
        self.dt = dt
        self.angle = self.velocity = self.motor = 0.0

    def hand(self):
        return -(5.0 * self.angle + 1.0 * self.velocity)

    def step(self, tau):
        self.motor = tau
        self.velocity += (tau + self.hand()) / 0.3 * self.dt
        self.angle += self.velocity * self.dt

    def read(self):
        return self.angle, self.velocity, self.motor, -self.hand()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("channel")
    ap.add_argument("out", help="output prefix: writes OUT-frames.csv and OUT-status.json")
    ap.add_argument("--watchdog", type=float, default=None)
    ap.add_argument("--dt", type=float, default=1e-3, help="plant step per 0x201 (s)")
    a = ap.parse_args()

    node_bus = UdpLoopbackBus(a.channel)
    mon_bus = UdpLoopbackBus(a.channel)
    frames = []
    stop = threading.Event()

    def monitor():
        while not stop.is_set():
            m = mon_bus.recv(0.05)
            if m is not None:
                frames.append((time.time(), m.arbitration_id, m.dlc, bytes(m.data).hex()))

    t = threading.Thread(target=monitor, daemon=True)
    t.start()
    node = SimulatedSensoDrive(
        node_bus,
        HeldWheel(a.dt),
        sign=-1,
        watchdog_s=a.watchdog,
        hand_sensor_v_per_nm=-(1 / 14.696 + 1 / 14.832),
    )
    node.start()
    print("ready", flush=True)
    sys.stdin.read()
    time.sleep(0.2)
    stop.set()
    t.join()
    node.close()
    status = node.status()
    status["errors"] = status["errors"][:50]
    with open(a.out + "-status.json", "w") as f:
        json.dump(status, f, indent=1, default=str)
    with open(a.out + "-frames.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "id", "dlc", "data"])
        w.writerows(frames)
    node_bus.shutdown()
    mon_bus.shutdown()
    print("done", len(frames), flush=True)


if __name__ == "__main__":
    main()
