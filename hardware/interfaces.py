"""The small device interfaces the engine and the control loop talk to.

A real rig (CAN drive, serial glove unit) and the simulated rig implement the same methods, so
the loop code is the same in the lab and in a simulated run.

Units and signs at this boundary:
- angle in rad, positive counter-clockwise seen by the driver; velocity in rad/s;
- motor torque command in N·m on the wheel axis, positive towards positive angle;
- driver torque in N·m: the torque the wheel exerts on the hands;
- grip force in N per hand.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class DriveReading:
    angle_rad: float
    velocity_rad_s: float
    torque_actual_nm: float


@dataclass(frozen=True)
class GripReading:
    left_n: float
    right_n: float
    host_time_s: float  # host clock when the frame was received
    sequence: int = 0

    @property
    def total_n(self) -> float:
        return self.left_n + self.right_n


@runtime_checkable
class WheelDrive(Protocol):
    def enable(self) -> None: ...

    def disable(self) -> None:
        """Zero torque, then power stage off. Must be safe to call in any state, repeatedly."""

    def quick_stop(self) -> None: ...

    def set_torque(self, torque_nm: float) -> None: ...

    def sync(self) -> None:
        """End of one control cycle: the drive applies the last command and latches new
        actual values (a CANopen SYNC; the simulated drive advances its world one sample)."""

    def read(self) -> DriveReading: ...


@runtime_checkable
class TorqueSensor(Protocol):
    def read(self) -> float:
        """Driver torque, N·m, offset removed."""

    def zero(self) -> None:
        """Measure and store the offset; call with the wheel released."""


@runtime_checkable
class GloveUnit(Protocol):
    def latest(self) -> GripReading | None:
        """Newest calibrated reading, or None before the first frame."""


@runtime_checkable
class Display(Protocol):
    """The subject's dashboard."""

    def show_condition(self, condition: str, boundary_deg: float) -> None: ...

    def show_angle(self, angle_rad: float) -> None: ...
