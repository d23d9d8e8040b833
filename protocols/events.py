"""Plain events the engine emits to its subscribers (the file writer, the GUI, a progress bar).

Events carry plain data only (numbers, strings, numpy arrays), so a subscriber needs nothing of
the engine and the engine nothing of its subscribers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class SessionStarted:
    subject: str
    attributes: dict  # session metadata (subject, Latin-square row, condition order, ...)
    protocol_text: str
    design_json: str
    n_trials: int


@dataclass(frozen=True)
class TrialStarted:
    key: str  # unique within the session (trial index, condition, repetition, attempt)
    trial_index: int
    attempt: int
    condition: str
    attributes: dict  # everything a reader needs to interpret the samples
    n_planned: int


@dataclass(frozen=True)
class SamplesAcquired:
    key: str
    start: int  # index of the first sample of this block within the trial
    channels: dict[str, np.ndarray]

    @property
    def n(self) -> int:
        return len(next(iter(self.channels.values())))


@dataclass(frozen=True)
class TrialMark:
    """Something that happened at a sample within a trial (pause, resume, fault, note)."""

    key: str
    sample: int
    kind: str
    detail: str = ""


@dataclass(frozen=True)
class TrialEnded:
    key: str
    trial_index: int
    status: str  # complete | aborted
    reason: str | None
    n_samples: int
    stats: dict = field(default_factory=dict)


@dataclass(frozen=True)
class TrialSuperseded:
    """An earlier attempt was replaced by a redo; its samples stay in the file."""

    key: str
    trial_index: int
    reason: str


@dataclass(frozen=True)
class StateChanged:
    old: str
    new: str
    reason: str = ""


@dataclass(frozen=True)
class SessionEnded:
    subject: str
    state: str
    completed: int
    remaining: int
