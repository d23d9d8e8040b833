"""The CiA 402 servo drive as a drive kind (``[drive] kind = "cia402"``, the default).

:class:`CiA402RigDrive` is :class:`~hardware.can.cia402.CiA402Drive` with what the live path
asks of any rig's drive (:class:`hardware.interfaces.RigDrive`): a reason to stop, a status for
the experimenter, its bus owned and closed with it. The host renders the virtual wheel in its
torque command (the drive has no spring or damper of its own).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import can

from .cia402 import CiA402Drive
from .config import DriveConfig, drive_config_from_dict
from .sim_node import Plant, SimulatedDrive
from .sim_sensor import SharedPlant, SimulatedTorqueSensor
from .transport import open_bus


class CiA402RigDrive(CiA402Drive):
    """A CiA 402 drive on a bus of its own (closed with it)."""

    renders_wheel = False

    def set_wheel(self, stiffness_nm_per_rad: float, damping_nms_per_rad: float) -> None:
        """The host renders the wheel in its command (``hardware.safety.loop_command``)."""

    @property
    def angle_quantum_rad(self) -> float:
        return self.config.angle_quantum_rad

    def problem(self) -> str | None:
        if self.heartbeat_lost:
            return "drive lost: no heartbeat"
        if self.ok:
            return None
        # The first active fault is the cause (an EMCY); later ones follow from it (the drive
        # then leaves OPERATION ENABLED).
        faults = self.active_faults
        if not faults:
            return "drive not ready"
        # The others by kind and code, so that the reason names every fault there was (two can
        # come together: a starved host's heartbeat gap with the drive's own EMCY).
        others = [f"{f.kind} 0x{f.code:04X}" if f.code is not None else f.kind for f in faults[1:]]
        more = f" (and {len(others)} more: {', '.join(others)})" if others else ""
        return f"drive fault: {faults[0]}{more}"

    def status(self) -> dict[str, Any]:
        return {
            "drive_state": getattr(self.state, "name", str(self.state)),
            "drive_ok": bool(self.ok),
            "drive_enabled": bool(self.enabled),
            "heartbeat_age_s": self.heartbeat_age_s(),
            "missed_tpdo": self.missed_tpdo,
            "faults": [str(f) for f in self.faults],
        }

    def drop_bus(self) -> None:
        self._bus.shutdown()

    def close(self) -> None:
        try:
            super().close()
        finally:
            try:
                self._bus.shutdown()
            except Exception:
                pass


class SimulatedCiA402:
    """The simulated CiA 402 drive node, and the torque sensor node if the rig names one
    (``[drive.torque_sensor] source = "node"``): both read the plant through one
    :class:`~hardware.can.sim_sensor.SharedPlant`, which the drive node alone steps."""

    faults = ("stop_heartbeat", "go_silent", "emcy", "mute_pdo")

    def __init__(
        self, config: DriveConfig, plant: Plant, open_bus: Callable[[], can.BusABC]
    ) -> None:
        self._buses = [open_bus()]
        with_sensor = config.torque_sensor.source == "node"
        shared = SharedPlant(plant) if with_sensor else None
        self.node = SimulatedDrive(self._buses[0], config, shared or plant)
        self.sensor_node: SimulatedTorqueSensor | None = None
        if shared is not None:
            self._buses.append(open_bus())
            self.sensor_node = SimulatedTorqueSensor(self._buses[1], config, shared)

    def __getattr__(self, name: str) -> Any:
        # Everything else is the drive node's (tests read its counters and state directly).
        return getattr(self.__dict__["node"], name)

    def start(self) -> None:
        self.node.start()

    def inject(self, fault: str) -> None:
        n = self.node
        if fault == "stop_heartbeat":  # the drive's own heartbeat stops (it still drives)
            n.stop_heartbeat()
        elif fault == "go_silent":  # the link is cut: the drive hears and says nothing
            n.go_silent()
        elif fault == "emcy":  # the drive faults: EMCY 0x2310, power stage off
            n.inject_fault(0x2310)
        elif fault == "mute_pdo":  # SYNCs go unanswered
            n.mute_pdo = True
        else:
            raise ValueError(f"unknown fault {fault!r} (known: {', '.join(self.faults)})")

    def status(self) -> dict[str, Any]:
        n = self.node
        return {
            "t": time.monotonic(),
            "applied_torque_nm": n.applied_torque_nm,
            "zero_torque_since": n.zero_torque_since,
            "state": n.state.value,
            "watching_host": n.watching_host,
            "host_heartbeats_lost": n.host_heartbeats_lost,
            "connection_lost_at": n.connection_lost_at,
            "sync_count": n.sync_count,
            "enabled_syncs": n.enabled_syncs,
            "enabled_cycles": n.enabled_syncs,
            "errors": [repr(e) for e in n.errors],
        }

    def close(self) -> None:
        closers = [self.node.close]
        if self.sensor_node is not None:
            closers.append(self.sensor_node.close)
        closers += [b.shutdown for b in self._buses]
        for closer in closers:
            try:
                closer()
            except Exception:
                pass


class _CiA402Kind:
    name = "cia402"

    def config(self, document: dict[str, Any], source: str) -> DriveConfig:
        return drive_config_from_dict(document, source=source)

    def open(self, config: DriveConfig) -> CiA402RigDrive:
        bus = open_bus(config)
        try:
            return CiA402RigDrive(bus, config)
        except BaseException:
            bus.shutdown()
            raise

    def simulate(
        self,
        config: DriveConfig,
        plant: Plant,
        open_bus: Callable[[], can.BusABC],
        simulation: Any = None,
    ) -> SimulatedCiA402:
        # The drive's guard against a lost host is configured by [drive] (0x1016, 0x6007).
        return SimulatedCiA402(config, plant, open_bus)


KIND = _CiA402Kind()
