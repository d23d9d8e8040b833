"""The simulated driver in a time-varying trial: behaviour that follows the task sample by sample.

A time-varying trial (``[[conditions]]`` with ``segments``, see ``protocols/protocol.py``) changes
the task within the trial. The simulated driver answers each change by moving every quantity of
its behaviour (arm parameters, grip-force mean and SD, remnant SD) towards the new condition's
values:

- the *target* is the current segment's behaviour; during a protocol ramp it blends from the
  previous segment's, geometrically (log-linear), so stiffness ratios change evenly;
- the *response* is first order in the log of each quantity, time constant ``tau_arm_s`` for the
  arm and the remnant, ``tau_grip_s`` for the grip force (co-contraction: both a few hundred ms).

:class:`ScheduleResponse` produces it in the world's noise blocks, carrying its filter state from
block to block, so the batch and the sample-by-sample paths see the same numbers.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from steerlab.hardware.sim.filters import first_order_lfilter
from steerlab.hardware.sim.physiology import ConditionBehaviour
from steerlab.protocols.session import ConditionSchedule

# Columns of the log-behaviour table.
ARM_COLUMNS = ("b_i", "k_i", "b_c", "k_c")  # the order of the kernel's dpar slots
_COLS = (*ARM_COLUMNS, "grip_mean_n", "grip_sd_n", "remnant_sd_nm")
DEFAULT_TAU_S = 0.2


@dataclass(frozen=True)
class BehaviourSchedule:
    """What the simulated driver does over a time-varying trial (one behaviour per segment)."""

    schedule: ConditionSchedule
    behaviours: tuple[ConditionBehaviour, ...]  # one per segment of ``schedule``
    tau_arm_s: float = DEFAULT_TAU_S
    tau_grip_s: float = DEFAULT_TAU_S

    def __post_init__(self) -> None:
        if len(self.behaviours) != self.schedule.n_segments:
            raise ValueError(
                f"{len(self.behaviours)} behaviours for {self.schedule.n_segments} segments"
            )
        inertias = {b.arm.I_i for b in self.behaviours}
        if len(inertias) > 1:
            # The kernel has no slot for a changing inertia (dpar carries b_i, k_i, b_c, k_c).
            raise ValueError(f"arm inertia must not change within a trial, got {sorted(inertias)}")
        if self.tau_arm_s < 0 or self.tau_grip_s < 0:
            raise ValueError("response time constants must be ≥ 0 s")

    def response(self, fs_hz: float) -> ScheduleResponse:
        return ScheduleResponse(self, fs_hz)


def _log_row(b: ConditionBehaviour) -> list[float]:
    vals = [getattr(b.arm, c) for c in ARM_COLUMNS]
    vals += [b.grip_mean_n, b.grip_sd_n, b.remnant_sd_nm]
    # Zero SD or remnant (noise-free tests) must survive the log: a tiny floor, exp() gives ~0.
    return [float(np.log(max(v, 1e-300))) for v in vals]


def _alpha(tau_s: float, fs_hz: float) -> float:
    return 1.0 if tau_s <= 0 else float(1.0 - np.exp(-1.0 / (tau_s * fs_hz)))


class ScheduleResponse:
    """Stateful: the driver's true behaviour for consecutive blocks of samples."""

    def __init__(self, sched: BehaviourSchedule, fs_hz: float) -> None:
        self.sched = sched
        self.table = np.array([_log_row(b) for b in sched.behaviours])  # (segments, columns)
        self.lag = LogLag(sched.tau_arm_s, sched.tau_grip_s, fs_hz, self.table[0])
        self.k = 0

    def next_block(self, n: int) -> dict[str, np.ndarray]:
        prev, cur, w = self.sched.schedule.blend(self.k, n)
        target = (1.0 - w)[:, None] * self.table[prev] + w[:, None] * self.table[cur]
        self.k += n
        return self.lag.response(target, cur)


class LogLag:
    """First-order lags, in the log domain, from a target behaviour (rows of ``_log_row``
    columns) to the true one: the arm's four parameters and the remnant with ``tau_arm_s``, the
    grip's mean and SD with ``tau_grip_s``. Stateful across blocks; starts settled at ``start``."""

    def __init__(self, tau_arm_s: float, tau_grip_s: float, fs_hz: float, start) -> None:
        a_arm, a_grip = _alpha(tau_arm_s, fs_hz), _alpha(tau_grip_s, fs_hz)
        self.alpha = np.array([a_arm] * 4 + [a_grip, a_grip, a_arm])
        self.state = np.array(start, dtype=float)

    def response(self, target: np.ndarray, segment) -> dict[str, np.ndarray]:
        """The true behaviour for a block of targets (samples × columns, log values)."""
        y = np.empty_like(target)
        for j, a in enumerate(self.alpha):
            # y[k] = y[k−1] + a (target[k] − y[k−1]); zi carries y[k−1] across blocks.
            y[:, j], _ = first_order_lfilter(a, a - 1.0, target[:, j], (1.0 - a) * self.state[j])
        self.state = y[-1].copy()
        v = np.exp(y)
        return {
            "true_arm": v[:, :4],
            "grip_mean_true_N": v[:, 4],
            "grip_sd_N": v[:, 5],
            "remnant_sd_Nm": v[:, 6],
            "segment": segment,
        }


def schedule_for(
    schedule: ConditionSchedule,
    behaviour_of: dict[str, ConditionBehaviour],
    tau_arm_s: float = DEFAULT_TAU_S,
    tau_grip_s: float = DEFAULT_TAU_S,
) -> BehaviourSchedule:
    """A :class:`BehaviourSchedule` from a condition → behaviour map."""
    missing: Sequence[str] = sorted(set(schedule.conditions) - set(behaviour_of))
    if missing:
        raise KeyError(f"no simulated behaviour for condition(s) {list(missing)}")
    return BehaviourSchedule(
        schedule,
        tuple(behaviour_of[c] for c in schedule.conditions),
        tau_arm_s,
        tau_grip_s,
    )
