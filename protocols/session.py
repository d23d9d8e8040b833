"""A subject's session as plain data: the ordered trials, and what a loop needs to run one."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from protocols.latin_square import condition_order
from protocols.perturbation import PerturbationDesign, design_multisine
from protocols.protocol import Protocol


@dataclass(frozen=True)
class TrialSpec:
    trial_index: int  # 1-based position in the session
    condition: str
    boundary_deg: float
    repetition: int  # 0: familiarization; 1..n: measured repetitions
    familiarization: bool
    instructions: str
    first_of_condition: bool

    @property
    def label(self) -> str:
        return "fam" if self.familiarization else f"rep{self.repetition}"

    def key(self, attempt: int = 1) -> str:
        """Group name in the session file; a redo gets a new attempt, never the same name."""
        return f"{self.trial_index:02d}_{self.condition}_{self.label}_a{attempt}"


@dataclass(frozen=True)
class TrialSetup:
    """Everything a control loop needs to run one trial."""

    spec: TrialSpec
    attempt: int
    fs_hz: float
    perturbation_nm: np.ndarray  # the whole trial, fades included
    measured_start: int  # first sample of the first whole period after the run-in
    measured_stop: int  # one past the last measured sample
    wheel_k: float
    wheel_b: float

    @property
    def n_samples(self) -> int:
        return len(self.perturbation_nm)

    @property
    def key(self) -> str:
        return self.spec.key(self.attempt)


@dataclass(frozen=True)
class SessionPlan:
    protocol: Protocol
    subject: str
    subject_number: int
    latin_square_row: int
    condition_order: tuple[str, ...]
    trials: tuple[TrialSpec, ...]

    @cached_property
    def design(self) -> PerturbationDesign:
        return design_multisine(self.protocol.perturbation)

    @cached_property
    def perturbation_samples(self) -> np.ndarray:
        """The trial's perturbation: run-in (fading in), whole periods, fade-out.

        The run-in plays the end of the period, so the first measured sample is at phase 0
        and every analysed period is a steady-state period.
        """
        p, t = self.protocol, self.protocol.trial
        fs = p.loop_rate_hz
        n_run_in = int(round(t.run_in_s * fs))
        n = p.trial_samples
        time = (np.arange(n) - n_run_in) / fs
        tp = self.design.signal(time)
        env = np.ones(n)
        n_in = int(round(t.fade_in_s * fs))
        if n_in:
            env[:n_in] = 0.5 - 0.5 * np.cos(np.pi * np.arange(n_in) / n_in)
        n_out = int(round(t.fade_out_s * fs))
        if n_out:
            env[n - n_out :] = 0.5 + 0.5 * np.cos(np.pi * (np.arange(n_out) + 1) / n_out)
        tp *= env
        tp.setflags(write=False)
        return tp

    def setup(self, spec: TrialSpec, attempt: int = 1) -> TrialSetup:
        p, t = self.protocol, self.protocol.trial
        fs = p.loop_rate_hz
        start = int(round(t.run_in_s * fs))
        stop = start + int(round(t.periods * p.perturbation.period_s * fs))
        return TrialSetup(
            spec=spec,
            attempt=attempt,
            fs_hz=fs,
            perturbation_nm=self.perturbation_samples,
            measured_start=start,
            measured_stop=stop,
            wheel_k=p.wheel.stiffness_nm_per_rad,
            wheel_b=p.wheel.damping_nms_per_rad,
        )

    def trial(self, trial_index: int) -> TrialSpec:
        for s in self.trials:
            if s.trial_index == trial_index:
                return s
        raise KeyError(f"session of {self.subject} has no trial {trial_index}")

    def attributes(self) -> dict:
        """Session-level metadata, for the file and for subscribers."""
        return {
            "subject": self.subject,
            "subject_number": self.subject_number,
            "latin_square_row": self.latin_square_row,
            "condition_order": list(self.condition_order),
            "protocol_name": self.protocol.name,
        }


def subject_id(number: int) -> str:
    return f"S{number:02d}"


def build_plan(protocol: Protocol, subject_number: int, subject: str | None = None) -> SessionPlan:
    """The session for one subject: Latin-square condition order, then per condition the
    familiarization trial(s) followed by the measured repetitions."""
    row, order = condition_order(subject_number, protocol.condition_names)
    trials = []
    t = protocol.trial
    idx = 1
    for name in order:
        cond = protocol.condition(name)
        reps = [(0, True)] * t.familiarization_trials + [
            (r, False) for r in range(1, t.repetitions + 1)
        ]
        for j, (rep, fam) in enumerate(reps):
            trials.append(
                TrialSpec(
                    trial_index=idx,
                    condition=name,
                    boundary_deg=cond.boundary_deg,
                    repetition=rep,
                    familiarization=fam,
                    instructions=cond.instructions,
                    first_of_condition=j == 0,
                )
            )
            idx += 1
    return SessionPlan(
        protocol=protocol,
        subject=subject or subject_id(subject_number),
        subject_number=subject_number,
        latin_square_row=row,
        condition_order=tuple(order),
        trials=tuple(trials),
    )
