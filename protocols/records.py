"""One recorded trial as plain data: what readers hand to the analysis.

Sign conventions (where data leave Steerlab's files):
- ``wheel_angle_rad``: wheel angle, positive counter-clockwise seen by the driver.
- ``driver_torque_Nm``: the torque the wheel exerts on the hands (so that
  S(Tp,θ)/S(Tp,Td) is positive at low frequency).
- ``perturbation_torque_Nm``: the perturbation torque applied to the wheel, positive in the
  direction of positive angle.
- ``grip_force_N``: total grip force, both hands summed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from steerlab.protocols.perturbation import PerturbationDesign

CORE_CHANNELS = (
    "time_s",
    "perturbation_torque_Nm",
    "driver_torque_Nm",
    "wheel_angle_rad",
    "grip_force_N",
)

STATUS_COMPLETE = "complete"
STATUS_ABORTED = "aborted"
STATUS_INCOMPLETE = "incomplete"  # still running, or the writer died mid-trial
STATUS_SUPERSEDED = "superseded"  # a later attempt (redo) of the same trial replaced it
# Set by readers only, never stored: the trial's data or attributes failed their checksums or
# could not be read; ``abort_reason`` says what. The analysis lists it as skipped.
STATUS_DAMAGED = "damaged"


@dataclass
class TrialRecord:
    subject: str
    condition: str
    repetition: int  # 0 for the familiarization trial, 1..n for measured repetitions
    familiarization: bool
    fs_hz: float
    time_s: np.ndarray
    perturbation_torque_Nm: np.ndarray
    driver_torque_Nm: np.ndarray
    wheel_angle_rad: np.ndarray
    grip_force_N: np.ndarray
    trial_index: int | None = None  # 1-based position in the session, when known
    status: str = STATUS_COMPLETE
    abort_reason: str | None = None
    # First sample after the run-in, when the recorder knew it. None: unknown (imported data);
    # the analysis then finds whole periods by itself.
    measured_start: int | None = None
    measured_stop: int | None = None  # one past the last measured sample
    design: PerturbationDesign | None = None
    boundary_deg: float | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    attrs: dict = field(default_factory=dict)
    source: str = ""  # where it came from, for messages: "file.h5:/trials/003_BT12_rep1"
    dtypes: dict[str, str] = field(default_factory=dict)  # storage type per channel, if not f8

    @property
    def n_samples(self) -> int:
        return len(self.time_s)

    @property
    def source_file(self) -> str:
        """The file part of ``source`` (the session file of "file.h5:/trials/…"); "" if none."""
        return self.source.rsplit(":/trials/", 1)[0]

    @property
    def time_varying(self) -> bool:
        """Whether the task changed within the trial (it has a ``schedule``, or it is a driving
        trial: the road changes along the drive)."""
        return bool(self.attrs.get("schedule")) or self.driving

    @property
    def driving(self) -> bool:
        """Whether this is a driving trial (it has a ``driving`` attribute)."""
        return bool(self.attrs.get("driving"))

    @property
    def usable(self) -> bool:
        return self.status == STATUS_COMPLETE and not self.familiarization

    def label(self) -> str:
        rep = "fam" if self.familiarization else f"rep{self.repetition}"
        return f"{self.subject}_{self.condition}_{rep}"
