"""The SensoDrive SENSO-Wheel as a drive kind (``[drive] kind = "sensodrive"``).

The driver is :class:`~hardware.can.sensodrive.SensoDrive`; the simulated drive
:class:`~hardware.can.sensodrive_sim.SimulatedSensoDrive`, imported only when a simulated rig
asks for it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import can

from .sensodrive import SensoDrive, send_off
from .sensodrive_config import SensoDriveConfig, sensodrive_config
from .sensodrive_frames import (
    HAND_SENSOR_REPLY_ID,
    PEDAL_REQUEST_ID,
    STATE_REPLY_ID,
    WHEEL_REPLY_ID,
)
from .sensodrive_frames import reply_id as _reply_id
from .transport import open_bus

if TYPE_CHECKING:
    from .sensodrive_sim import SimulatedSensoDrive
    from .sim_node import Plant

#: What the host needs to hear: the drive's replies (the pedals' too, should a rig want them).
REPLY_IDS = (STATE_REPLY_ID, WHEEL_REPLY_ID, HAND_SENSOR_REPLY_ID, _reply_id(PEDAL_REQUEST_ID))


class _SensoDriveKind:
    name = "sensodrive"

    def config(self, document: dict[str, Any], source: str) -> SensoDriveConfig:
        return sensodrive_config(document, source)

    def open(self, config: SensoDriveConfig) -> SensoDrive:
        filters = [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in REPLY_IDS]
        bus = open_bus(config, filtered=False, can_filters=filters)
        try:
            drive = SensoDrive(bus, config, reopen=lambda: open_bus(config, filtered=False))
        except BaseException:
            bus.shutdown()
            raise
        # A wheel an earlier host left ON (it crashed, the drive's own guard being unknown)
        # keeps its torque and fields until told: told now, not at the first trial's enable.
        drive.disable()
        return drive

    def emergency_off(self, config: SensoDriveConfig) -> None:
        """Turn the drive off from a process other than the loop's (the loop process died):
        the SENSO-Wheel's own guard against a silent host is unknown, so the host assumes it
        has none. On hardware this needs a second handle on the adapter (socketcan allows it;
        PCAN-Basic on Windows releases a dead process's handle first)."""
        bus = open_bus(config, filtered=False)
        try:
            send_off(bus, config)
        finally:
            bus.shutdown()

    def simulate(
        self,
        config: SensoDriveConfig,
        plant: Plant,
        open_bus: Callable[[], can.BusABC],
        simulation: Any = None,
    ) -> SimulatedSensoDrive:
        from .sensodrive_sim import SimulatedSensoDrive

        watchdog_ms = getattr(simulation, "drive_watchdog_ms", 0.0)
        return SimulatedSensoDrive(
            open_bus(),
            plant,
            sign=config.sign,
            hand_sensor_v_per_nm=config.hand_sensor_v_per_nm if config.has_hand_sensor else None,
            full_scale_torque_nm=config.full_scale_torque_nm,
            watchdog_s=watchdog_ms / 1000.0 if watchdog_ms > 0 else None,
            owns_bus=True,
        )


KIND = _SensoDriveKind()
