"""CAN drive stack: a CiA 402 servo drive over CANopen (python-can + canopen), its rig
configuration, and a simulated drive node that answers the same protocol on a virtual bus (plus
a simulated column torque sensor node for ``[drive.torque_sensor] source = "node"``).

Typical use::

    config = load_drive_config("hardware/rigs/simulated.toml")
    bus = open_bus(config)
    drive = CiA402Drive(bus, config)
    drive.enable()
    ...  # each cycle: drive.set_torque(u); drive.sync(); y = drive.read()
    drive.disable(); drive.close(); bus.shutdown()
"""

from .cia402 import (
    CiA402Drive,
    DriveColumnTorque,
    DriveEnableError,
    DriveError,
    DriveFault,
    DriveFaultError,
    SdoWrite,
    startup_writes,
)
from .config import (
    ConfigError,
    DriveConfig,
    SafetyConfig,
    TorqueSensorConfig,
    drive_config_from_dict,
    load_drive_config,
)
from .frames import Emcy, FrameError, NmtState, SensorFrame, State402
from .scaling import DriveScaling
from .sim_node import Plant, SimulatedDrive, build_object_dictionary
from .sim_sensor import SharedPlant, SimulatedTorqueSensor
from .transport import BusReader, driver_filters, open_bus

__all__ = [
    "BusReader",
    "CiA402Drive",
    "ConfigError",
    "DriveColumnTorque",
    "DriveConfig",
    "DriveEnableError",
    "DriveError",
    "DriveFault",
    "DriveFaultError",
    "DriveScaling",
    "Emcy",
    "FrameError",
    "NmtState",
    "Plant",
    "SafetyConfig",
    "SdoWrite",
    "SensorFrame",
    "SharedPlant",
    "SimulatedDrive",
    "SimulatedTorqueSensor",
    "State402",
    "TorqueSensorConfig",
    "build_object_dictionary",
    "drive_config_from_dict",
    "driver_filters",
    "load_drive_config",
    "open_bus",
    "startup_writes",
]
