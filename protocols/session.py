"""A subject's session as plain data: the ordered trials, and what a loop needs to run one."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from steerlab.protocols.driving import DrivingSetup, road_length_m
from steerlab.protocols.latin_square import condition_order
from steerlab.protocols.perturbation import PerturbationDesign, design_multisine
from steerlab.protocols.protocol import Condition, Protocol

DISPLAY_RAMP_STEP_S = 0.05  # how often a ramping boundary is redrawn on the subject's display


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
class ConditionSchedule:
    """When the task changes within a time-varying trial, in samples from the trial's start.

    The protocol's segments are cycled until they cover the trial. Segment ``i`` starts at
    ``starts[i]`` with condition ``conditions[i]``; with a "ramp" transition the task blends
    linearly from the previous segment's condition over its first ``transition_samples``
    samples (the boundary lines move; a step to or from "no lines" (inf) happens at once).
    """

    name: str  # the time-varying condition's own name
    conditions: tuple[str, ...]
    boundaries_deg: tuple[float, ...]
    starts: tuple[int, ...]
    transition: str  # "step" | "ramp"
    transition_samples: int
    n_samples: int
    fs_hz: float

    @classmethod
    def build(cls, condition: Condition, protocol: Protocol, n_samples: int) -> ConditionSchedule:
        if not condition.time_varying:
            raise ValueError(f"condition {condition.name!r} has no segments")
        fs = protocol.loop_rate_hz
        conds: list[str] = []
        bounds: list[float] = []
        starts: list[int] = []
        segs = condition.segments
        t, i = 0.0, 0
        while (k := int(round(t * fs))) < n_samples:
            seg = segs[i % len(segs)]
            if starts and k == starts[-1]:  # a segment shorter than a sample never shows
                conds.pop(), bounds.pop(), starts.pop()
            conds.append(seg.condition)
            bounds.append(protocol.condition(seg.condition).boundary_deg)
            starts.append(k)
            t += seg.duration_s
            i += 1
        return cls(
            name=condition.name,
            conditions=tuple(conds),
            boundaries_deg=tuple(bounds),
            starts=tuple(starts),
            transition=condition.transition,
            transition_samples=int(round(condition.transition_s * fs))
            if condition.transition == "ramp"
            else 0,
            n_samples=n_samples,
            fs_hz=fs,
        )

    @property
    def n_segments(self) -> int:
        return len(self.starts)

    def segment_of(self, k: np.ndarray | int) -> np.ndarray:
        """Index of the segment holding sample(s) ``k``."""
        return np.searchsorted(np.asarray(self.starts), k, side="right") - 1

    def blend(self, k0: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per sample k0..k0+n−1: (previous segment, current segment, weight of the current).

        The weight is 1 except while a ramp runs; samples past the trial's end keep the last
        segment (a loop may run a little longer than planned).
        """
        k = np.arange(k0, k0 + n)
        cur = self.segment_of(k)
        prev = np.maximum(cur - 1, 0)
        w = np.ones(n)
        if self.transition_samples > 0:
            since = k - np.asarray(self.starts)[cur]
            ramping = (cur > 0) & (since < self.transition_samples)
            w[ramping] = (since[ramping] + 1) / self.transition_samples
        return prev, cur, w

    def display_changes(self) -> list[tuple[int, str, float]]:
        """(sample, condition, boundary_deg) whenever the subject's display must change,
        the first at sample 0. A ramp is redrawn every DISPLAY_RAMP_STEP_S."""
        out: list[tuple[int, str, float]] = []
        step = max(1, int(round(DISPLAY_RAMP_STEP_S * self.fs_hz)))
        for i, (k0, c, b) in enumerate(
            zip(self.starts, self.conditions, self.boundaries_deg, strict=True)
        ):
            prev = self.boundaries_deg[i - 1] if i else b
            ramp = self.transition_samples
            if i == 0 or ramp == 0 or not (math.isfinite(prev) and math.isfinite(b)) or prev == b:
                out.append((k0, c, b))
                continue
            js = list(range(0, ramp, step))
            if js[-1] != ramp - 1:
                js.append(ramp - 1)  # the last redraw lands exactly on the new boundary
            out += [(k0 + j, c, prev + (b - prev) * (j + 1) / ramp) for j in js]
        return [x for x in out if x[0] < self.n_samples]

    def to_dict(self) -> dict:
        """For the trial's ``schedule`` attribute (JSON; an infinite boundary is null)."""
        return {
            "name": self.name,
            "conditions": list(self.conditions),
            "boundaries_deg": [b if math.isfinite(b) else None for b in self.boundaries_deg],
            "starts": list(self.starts),
            "transition": self.transition,
            "transition_samples": self.transition_samples,
            "n_samples": self.n_samples,
            "fs_hz": self.fs_hz,
        }

    @classmethod
    def from_dict(cls, d: dict) -> ConditionSchedule:
        return cls(
            name=str(d["name"]),
            conditions=tuple(str(c) for c in d["conditions"]),
            boundaries_deg=tuple(math.inf if b is None else float(b) for b in d["boundaries_deg"]),
            starts=tuple(int(k) for k in d["starts"]),
            transition=str(d["transition"]),
            transition_samples=int(d["transition_samples"]),
            n_samples=int(d["n_samples"]),
            fs_hz=float(d["fs_hz"]),
        )


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
    schedule: ConditionSchedule | None = None  # time-varying trials only
    hands_off: bool = False  # a rig check: nobody holds the wheel (analysis/rigcheck.py)
    driving: DrivingSetup | None = None  # driving trials only (protocols/driving.py)

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
        cond = p.condition(spec.condition)
        schedule = None
        if cond.time_varying:
            schedule = ConditionSchedule.build(cond, p, len(self.perturbation_samples))
        tp, driving = self.perturbation_samples, None
        if cond.driving is not None:
            # Every repetition has a road of its own, the same for every subject.
            trial_s = len(tp) / fs
            road = p.road.generate(
                road_length_m(cond.driving, trial_s), seed=p.road.seed + spec.repetition
            )
            driving = DrivingSetup(cond.driving, p.vehicle, road)
            if cond.driving.perturbation_level != 1.0:
                tp = tp * cond.driving.perturbation_level
                tp.setflags(write=False)
        return TrialSetup(
            spec=spec,
            attempt=attempt,
            fs_hz=fs,
            perturbation_nm=tp,
            measured_start=start,
            measured_stop=stop,
            wheel_k=p.wheel.stiffness_nm_per_rad,
            wheel_b=p.wheel.damping_nms_per_rad,
            schedule=schedule,
            driving=driving,
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
