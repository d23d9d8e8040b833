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
from typing import Any, Protocol, runtime_checkable


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
class ColumnTorque(TorqueSensor, Protocol):
    """A drive's driver-torque channel, zeroed from the values of the cycles just run."""

    def clear_recent(self) -> None:
        """Forget earlier values: the next zero() sees only the cycles that follow."""


@runtime_checkable
class RigDrive(WheelDrive, Protocol):
    """A rig's drive of any kind (:mod:`hardware.drives`), as the live path uses it.

    ``renders_wheel``: the drive renders the virtual wheel's spring and damper itself
    (:meth:`set_wheel` puts them in its own fields), so the host's command carries only the
    perturbation and the safety layer's terms; False: the host renders them in its command
    (then :meth:`set_wheel` does nothing)."""

    config: Any
    renders_wheel: bool

    @property
    def torque_sensor(self) -> ColumnTorque:
        """The driver torque (a sensor, or a reconstruction the rig file chose).

        :raises hardware.can.DriveError: the rig file gives no way to obtain it."""
        ...

    @property
    def angle_quantum_rad(self) -> float:
        """The smallest angle step the drive reports (the session file's data-quality check)."""
        ...

    def set_wheel(self, stiffness_nm_per_rad: float, damping_nms_per_rad: float) -> None:
        """The virtual wheel for the next trial; zero when a trial ends (``disable``)."""

    def problem(self) -> str | None:
        """A reason to stop the trial now (drive lost, faulted, unanswered), or None."""

    def status(self) -> dict[str, Any]:
        """The drive's state for the experimenter: at least ``drive_state``, ``drive_ok``,
        ``drive_enabled`` and ``faults`` (a list of words)."""
        ...

    def drop_bus(self) -> None:
        """Fault injection: the host's bus goes away under the driver (a bus-off)."""

    def close(self) -> None:
        """Disable if enabled, stop the driver's threads and close its bus. Never raises."""


@runtime_checkable
class GloveUnit(Protocol):
    def latest(self) -> GripReading | None:
        """Newest calibrated reading, or None before the first frame."""


@runtime_checkable
class GripSource(GloveUnit, Protocol):
    """A rig's grip force of any kind (:mod:`hardware.grips`: Steerlab's glove unit, an LSL
    stream, a text-line device), as the live path uses it. A reader thread of its own keeps
    ``latest()`` current; :class:`hardware.grip.reader.GripReader` implements the rest."""

    def describe(self) -> str:
        """The device in words, for messages ("LSL stream 'GripGlove'")."""
        ...

    def age_s(self) -> float | None:
        """Host seconds since the newest reading arrived; None before the first."""
        ...

    def stream_alive(self, timeout_s: float = 0.1) -> bool: ...

    @property
    def error(self) -> BaseException | None:
        """What stopped the reader, or None."""
        ...

    def check(self) -> None:
        """Raise if the reader failed (the message names the device)."""

    def problem(self, timeout_s: float) -> str | None:
        """A reason to stop the trial now (the reader failed, or no reading for longer than
        ``timeout_s``), naming the device and what went wrong; None while all is well."""
        ...

    def stats(self) -> Any:
        """The source's counters: a dataclass with ``as_dict()`` and at least ``rate_hz``."""
        ...

    def close(self) -> None: ...


@runtime_checkable
class Display(Protocol):
    """The subject's dashboard."""

    def show_condition(self, condition: str, boundary_deg: float) -> None: ...

    def show_angle(self, angle_rad: float) -> None: ...
