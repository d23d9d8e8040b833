"""Naming the cause: fit every candidate, keep what predicts held-out data and wins on BIC.

Set-up (:func:`build_setup`)
    1. The wheel's impedance as the world computes it, per trial.
    2. The baseline (the paper's linear arm, plus the mechanisms of a model file when the
       diagnosis starts from one) fitted per trial from the best of several start values
       (the trial's own FRF fit, the subject × condition FRF fit, nominal values).
    3. The noise model from the baseline's residual at the unexcited bins; fixed from then on,
       so every model is judged by the same weights.
    4. Remnant realisations for nonlinear candidates (:mod:`analysis.diagnosis.simulate`).

Greedy forward selection (:func:`select`)
    At each step every remaining candidate is added to the current model and fitted:

    - on all trials: Δ(−2 log L) and ΔBIC = Δ(−2 log L) + Δp·ln n + 2 ln K (n: complex residual
      values; K: the family's forms, its prior shared among them);
    - held out, by repetition: fitted on repetition A (its per-trial arms and the mechanism's
      parameters), then on repetition B the mechanism's parameters stay as A gave them and
      only B's own arm parameters, which every model has, are re-estimated. The held-out gain
      is the drop of B's −2 log L against the current model treated the same way, summed
      over the folds. A mechanism fitted to noise does not carry over and loses there.
      Only a candidate that passes on ΔBIC is tried held out: the others cannot be retained.
      The one with the largest in-sample gain is tried first, and one whose in-sample gain is
      below a quarter of that one's held-out gain (if it can be retained) is not tried either
      (:func:`_held_out_stage`).
    - The linear families (reflex, lag, sensor delay) are fitted first (on a pool: their fits
      go first, beside the others' screening). A family that must be
      simulated gets its best form's full fit only where its forms' screening gained at least
      1/``FULL_FIT_RATIO`` of the best linear family's gain (far from the noise floor only);
      else its screening stands, and it is fitted fully if the held-out stage could still
      choose it.

    A candidate is retained when its ΔBIC < −``MIN_DBIC``, its held-out gain
    > ``MIN_HELD_OUT``, and its parameters stand out from zero by more than ``MIN_ROBUST_Z``
    cluster-robust standard errors (trials as clusters: guards against an improvement that
    rests on a few trials, which the likelihood's noise model would over-count); of several,
    the one with the largest held-out gain. It joins the model
    and the next step starts; the selection stops when no candidate passes, or after
    ``MAX_MECHANISMS``; candidates that improved nothing at the first step are not re-tried,
    and a family whose first step's best form improves nothing at a later step is not
    screened in its other forms.
    Without two repetitions there is no held-out check, and the ΔBIC
    threshold is ``MIN_DBIC_NO_HELD_OUT`` instead.

Drift is judged separately, on the per-trial arm parameters (:mod:`analysis.diagnosis.drift`).
"""

from __future__ import annotations

import concurrent.futures as cf
import heapq
import itertools
import math
import multiprocessing.connection as mp_connection
import time
import uuid
from collections.abc import Callable, Generator, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field, fields, replace
from functools import partial
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from steerlab.analysis.diagnosis.candidates import CANDIDATES, Candidate, candidate
from steerlab.analysis.diagnosis.data import FALLBACK_ARM, PreparedStudy, TrialData, with_inertia
from steerlab.analysis.diagnosis.fit import (
    MAX_ITER,
    RELATIVE_STOP_MIN_LACK,
    SPECTRA_MAP,
    FitResult,
    ModelSpec,
    NoiseModel,
    SpectraJob,
    best_start_arms,
    evaluate_cost,
    fit_model,
    geometric_mean_arm,
    noise_model,
)
from steerlab.analysis.diagnosis.simulate import (
    kernel_wheel_impedance,
    needs_remnant,
    reconstruct_remnant,
    simulated_spectra,
)
from steerlab.analysis.diagnosis.steady_state import is_linear_time_invariant
from steerlab.analysis.executors import (
    pool_cpu_clock,
    share,
    shared_value,
    sharing_pool,
    travels_light,
)
from steerlab.hardware.safety import SafetyLimits
from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.hardware.sim.physiology import NOMINAL, ArmParams

MIN_DBIC = 10.0  # "very strong" evidence on Kass & Raftery's scale
MIN_HELD_OUT = 5.0  # −2 log L units, summed over the folds
MIN_DBIC_NO_HELD_OUT = 30.0
# The likelihood assumes the noise model; a parameter whose improvement rests on a few trials
# passes BIC but not a cluster-robust Wald test (trials as clusters): z must exceed this.
MIN_ROBUST_Z = 3.0
MAX_MECHANISMS = 3
# Two passing candidates whose criterion (held-out −2 log L, or BIC) differs by less than this
# many of its standard errors explain the data equally well: both are named (confusable()).
AMBIGUITY_Z = 2.0
# Iterations of each form's fit when a family has several (the best is then fitted fully).
FORM_SCREEN_ITER = 4
# Forms within this much −2 log L of the best are consistent with the data (the likelihood-ratio
# 95 % set for one parameter, χ²₁): on Steerlab's own world a reflex's delay of 25–60 ms fitted
# within 1.4 units (k_p 6), its activation dynamics 20 units apart.
FORM_CONSISTENT_M2LL = 3.84
# Candidates are re-evaluated at a later step only if they improved −2 log L by more than this
# at the step before (χ²₁ above 6: p ≈ 0.014): masking that strong is not expected.
RETRY_MIN_DELTA_M2LL = 6.0
# A candidate whose in-sample gain (−2 log L) times this is below the held-out gain of
# another of its step, which can be retained, is not tried on held-out data: held-out gains
# were at most 1.8 × the in-sample ones (_held_out_stage).
HELD_OUT_SKIP_RATIO = 4.0
# A family that must be simulated (friction, stiffening, the grip map) gets its best form's
# full fit only where its forms' screening gained at least 1/FULL_FIT_RATIO of what the step's
# best linear family (reflex, lag, sensor delay: fitted first) gained, and only far from the
# noise floor (that fraction at least FULL_FIT_MIN_M2LL); else its screening stands as its
# fit, and it is fitted fully only if the held-out stage could still choose it
# (_held_out_stage). On the independent world's studies a full fit gained at most 2.3 × its
# screening, and held-out gains were 0.54–1.8 × the in-sample ones: below 1/20 of a leader
# that can be retained, such a candidate is not tried on held-out data, fitted fully or not,
# so it cannot be retained. One whose screening gains no more than RETRY_MIN_DELTA_M2LL is
# fitted fully all the same: whether a later step retries it depends on its full gain.
FULL_FIT_RATIO = 20.0
FULL_FIT_MIN_M2LL = 1000.0
K_REMNANT_SELECT = 1  # remnant realisations (± pairs) while screening candidates …
K_REMNANT_FINAL = 8  # … and for the retained model's parameters (see simulate.py)
# Time limit of the candidate stage (s): CPU seconds of the diagnosing process and of its own
# worker processes (``--jobs``; read from /proc, see analysis.executors.pool_cpu_clock),
# wall-clock seconds on a Dask scheduler or where /proc is missing. CPU time, because on a
# shared machine wall time measures the other users, and the verdict should not depend on
# the number of jobs: on the development
# machine a run was stopped for 10 minutes by a colleague's real-time measurement. Long trials
# or a misbehaving candidate could make the stage run away (issue 18: "no answer within
# 300 s"); at the limit the candidates not yet evaluated are left out, and the result says so.
CANDIDATE_TIME_LIMIT_S = 300.0

Progress = Callable[[str], None]
# A recording rig without Steerlab's command limits: every command it computes is applied.
UNLIMITED = SafetyLimits(max_torque_nm=1e9, max_slew_nm_per_s=1e12)
# −2 log L by which "no limits" must explain the data better before Steerlab's are given up.
RIG_LIMITS_MIN_M2LL = 2.0


@dataclass
class Setup:
    trials: list[TrialData]
    fam: list[TrialData]
    noise: NoiseModel
    fs_ref: float
    base_mech: Mechanisms
    base: FitResult
    paper_arms: dict[str, ArmParams]  # the FRF fit per subject × condition (the paper's)
    folds: list[tuple[list[TrialData], list[TrialData]]]  # (train, test) by repetition
    n_remnant: int = K_REMNANT_SELECT
    final_noise: NoiseModel | None = None  # from the retained model's residual
    trial_state: str | None = None  # the TrialState last applied to the trials (its token)

    def spec(self, free: Sequence[Candidate] = ()) -> ModelSpec:
        return ModelSpec(self.base_mech, tuple(free), self.fs_ref)


def _degenerate(arm: ArmParams) -> bool:
    from steerlab.analysis.armfit import BOUNDS

    return any(
        not (1.05 * BOUNDS[n][0] < getattr(arm, n) < BOUNDS[n][1] / 1.05)
        for n in ("b_i", "k_i", "b_c", "k_c")
    )


def plausible_arm(t: TrialData, model_baseline: dict | None = None) -> ArmParams:
    """The trial's subject × condition FRF fit unless it ran into a bound; else the model
    file's or the simulator's nominal arm for the condition; else a mid-range arm. Whichever
    it is, with the subject's inertia from the data."""
    for arm in (t.arm_cell, t.arm0):
        if not _degenerate(arm):
            return with_inertia(arm, t)
    for source in (model_baseline or {}, NOMINAL):
        if t.condition in source:
            return with_inertia(source[t.condition].arm, t)
    return with_inertia(FALLBACK_ARM, t)


def start_arms(
    setup: Setup,
    trials: Sequence[TrialData],
    spec: ModelSpec,
    noise: NoiseModel,
    x: np.ndarray,
    current: dict[str, ArmParams],
) -> dict[str, ArmParams]:
    """Per trial, the best start among the current model's arms and the plausible ones.

    A misspecified model can drive a trial's arm to its bounds (the baseline on data with a
    10 ms torque-reading delay: k_i = 10⁵ N·m/rad, the contact spring taking the arm's
    compliance); a candidate started there stays stuck in that corner, so such arms are
    replaced by plausible ones, unless the loop is unstable with every plausible arm and
    stable with the one in the corner: on the independent world's reflex study a trial's
    b_i sat at its bound, a plausible arm with the 25 ms reflex diverged, and the final fit,
    started there, stopped at once "converged" at −2 log L 3.6 × 10¹⁶. Every start keeps the
    current model's inertia of the subject (the fit frees one per subject, started from one
    value).
    """
    plausible = {t.label: _plausible_keeping_inertia(t, current) for t in trials}
    return best_start_arms(
        trials, spec, noise, [_unstuck(trials, current), plausible], x=x, last_resort=current
    )


def _plausible_keeping_inertia(t: TrialData, arms: dict[str, ArmParams]) -> ArmParams:
    return replace(plausible_arm(t), I_i=arms[t.label].I_i)


def _unstuck(trials: Sequence[TrialData], arms: dict[str, ArmParams]) -> dict[str, ArmParams]:
    """``arms`` with each arm that ran into a bound replaced by a plausible one (same inertia)."""
    stuck = {t.label for t in trials if _degenerate(arms[t.label])}
    return {
        t.label: _plausible_keeping_inertia(t, arms) if t.label in stuck else arms[t.label]
        for t in trials
    }


def _new_off(spec: ModelSpec, x: np.ndarray) -> np.ndarray:
    """``x`` with the last candidate of ``spec`` (the one being tried) switched off."""
    if not spec.free:
        return np.asarray(x, dtype=float)
    k = len(spec.free[-1].params)
    out = np.array(x, dtype=float, copy=True)
    out[len(out) - k :] = spec.off()[len(out) - k :]
    return out


def fit_nested(
    trials: Sequence[TrialData],
    spec: ModelSpec,
    noise: NoiseModel,
    arms0: dict[str, ArmParams],
    x0: np.ndarray,
    fallback_arms: dict[str, ArmParams],
    fallback_x: np.ndarray,
    fix_mechanisms: bool = False,
    max_iter: int = MAX_ITER,
    relative_stop: bool = False,
) -> FitResult:
    """:func:`fit_model` from ``arms0``; if it ends worse than the model it extends
    (``fallback_arms`` at ``fallback_x``: the candidate switched off), fitted again from there.
    ``relative_stop``: see :func:`fit_model` (a candidate's fits).

    :func:`start_arms` replaces arms that ran into a bound by plausible ones, and a fit from
    those can end far from the current model: on a world with a 35 ms reflex the baseline's
    intrinsic damping went to its bound, and every candidate started from plausible arms ended
    10⁴ units of −2 log L worse than the baseline it contains. A candidate must never look
    worse than the model it extends.
    """
    opts: dict[str, Any] = {
        "fix_mechanisms": fix_mechanisms,
        "max_iter": max_iter,
        "relative_stop": relative_stop,
    }
    fit = fit_model(trials, spec, noise, arms0, x0=x0, **opts)
    ref = 2.0 * sum(evaluate_cost(trials, spec, noise, fallback_arms, fallback_x).values())
    if ref < fit.m2ll:
        alt = fit_model(trials, spec, noise, fallback_arms, x0=fallback_x, **opts)
        if alt.m2ll < fit.m2ll:
            fit = alt
    return _out_of_corners(trials, spec, noise, fit, opts)


def _out_of_corners(
    trials: Sequence[TrialData], spec: ModelSpec, noise: NoiseModel, fit: FitResult, opts: dict
) -> FitResult:
    """``fit`` again for the trials whose arm ended at a bound, from plausible arms or the
    arm the condition's other trials fitted, whichever starts better (:func:`_corner_exits`),
    at the fitted mechanism parameters; the better of the two fits.

    An arm parameter at its bound has no finite-difference slope (the bumped value is clipped
    back), so the fit cannot leave the corner it ran into: on a study with a 5 ms reading
    delay, the delay's fit ended with one trial's contact at k_c = 10⁵ N·m/rad, 13 000 units
    of −2 log L above the optimum the next step's candidates all found from plausible arms,
    and each of them then looked 13 000 units better than the model it extends.
    """
    stuck = [t for t in trials if _degenerate(fit.arms[t.label])]
    if not stuck:
        return fit
    # A corner whose plausible arm makes the loop unstable is kept: from there a fit has no
    # slope to follow and runs its iterations for nothing. (Only the stuck trials' starts are
    # in question: every other trial starts where the fit ended.)
    out = best_start_arms(
        stuck, spec, noise, _corner_exits(trials, stuck, fit.arms), x=fit.x,
        last_resort=fit.arms,
    )  # fmt: skip
    if all(out[t.label] is fit.arms[t.label] for t in stuck):
        return fit
    alt = fit_model(trials, spec, noise, {**fit.arms, **out}, x0=fit.x, **opts)
    return alt if alt.m2ll < fit.m2ll else fit


def _corner_exits(
    trials: Sequence[TrialData], stuck: Sequence[TrialData], arms: dict[str, ArmParams]
) -> list[dict[str, ArmParams]]:
    """Starts for the ``stuck`` trials of a fit on ``trials``: plausible arms; and the arm
    the fit gave the condition's trials that are not stuck (their geometric mean; where there
    are none, the plausible arm again). Each with the fit's inertia of the subject, or the
    data's where every trial of the subject is stuck (its whole fit collapsed, its inertia
    with it).

    On the independent world's 12 ms torque-sensor delay the delay's fit found the delay
    (11.98 ms) and left every trial of one subject in a corner (b_i = 1 000 or k_i = 10⁵,
    I_i a quarter of the data's), −2 log L 7 300–8 100 per trial, where the other subject's
    fitted at 6 300–6 700. That subject's FRF fits had run into bounds, so its plausible arms
    were the simulator's nominal ones: they started at 48 000–255 000 and the fit from them
    ended worse than the corner. From the other subject's arms the fit got out, 7 300 units
    better; without it the next steps' candidates "improved" on the corner by thousands. On
    the 12 ms actuator lag's study a subject collapsed the same way at I_i = 10 kg·m², the
    inertia's upper bound, where no arm fits."""
    stuck_labels = {t.label for t in stuck}
    collapsed = {
        s
        for s in {t.subject for t in stuck}
        if all(t.label in stuck_labels for t in trials if t.subject == s)
    }
    unstuck = _unstuck(stuck, arms)
    keep = {
        t.label: plausible_arm(t) if t.subject in collapsed else unstuck[t.label] for t in stuck
    }
    borrowed = dict(keep)
    for t in stuck:
        others = [
            arms[o.label]
            for o in trials
            if o.condition == t.condition and o.label not in stuck_labels
        ]
        if others:
            like = with_inertia(arms[t.label], t) if t.subject in collapsed else arms[t.label]
            borrowed[t.label] = geometric_mean_arm(others, like=like)
    return [keep, borrowed]


def set_remnants(trials: Sequence[TrialData], arms: dict[str, ArmParams], k: int) -> None:
    for t in trials:
        t.remnant = [reconstruct_remnant(t, arms[t.label], seed=i) for i in range(k)]


def choose_rig_limits(
    prep: PreparedStudy, spec: ModelSpec, noise: NoiseModel, fit: FitResult
) -> FitResult:
    """The baseline with the trials' command limits (those the session files record, else
    Steerlab's 8 N·m, 400 N·m/s) or without torque and slew limits, whichever explains the
    study better; ``fit`` is the baseline with the limits. Sets ``safety`` on every trial and
    says in ``prep.notes`` when the limits are dropped.

    The simulated loop clips its command as Steerlab's rig does, but the recording's rig may
    not have. On the independent world's null seed 5001 the multisine peaks at 9.3 N·m and
    that rig applies it in full; clipped at 8 N·m in the stiff conditions (where the wheel's
    spring hardly offsets it), the simulation missed θ and Td by 0.1–0.4 % at every frequency,
    at the excited bins 2–3× the noise, and the study was `unexplained`. Where the limits
    clip nothing the two models are the same, and Steerlab's stay.
    """
    trials = prep.trials
    everything = trials + prep.familiarization
    limited = [t.safety for t in everything]

    def use(limits: Sequence[SafetyLimits]) -> None:
        for t, lim in zip(everything, limits, strict=True):
            t.safety = lim

    # Only the torque and slew limits are dropped: a recorded soft angle limit stays.
    unlimited = [
        replace(lim, max_torque_nm=UNLIMITED.max_torque_nm,
                max_slew_nm_per_s=UNLIMITED.max_slew_nm_per_s)
        for lim in limited
    ]  # fmt: skip
    use(unlimited)
    free_start = 2.0 * sum(evaluate_cost(trials, spec, noise, fit.arms).values())
    free = None
    # Equal costs: nothing was clipped, the two are one model and Steerlab's limits stay.
    if abs(free_start - fit.m2ll) >= 1e-6 * max(fit.m2ll, 1.0):
        free = fit_model(trials, spec, noise, fit.arms)
    if free is None or free.m2ll >= fit.m2ll - RIG_LIMITS_MIN_M2LL:
        use(limited)
        return fit
    lim = limited[0]
    prep.notes.append(
        "the recording's rig applied commands beyond the limits it was first simulated with "
        f"({lim.max_torque_nm:g} N·m, {lim.max_slew_nm_per_s:g} N·m/s): simulated without "
        f"them, which fits by {fit.m2ll - free.m2ll:.0f} units of −2 log L better"
    )
    return free


def build_setup(
    prep: PreparedStudy,
    base_mech: Mechanisms,
    model_baseline: dict | None = None,
    progress: Progress | None = None,
) -> Setup:
    trials = prep.trials
    fs_ref = float(np.median([t.fs_hz for t in trials]))
    spec0 = ModelSpec(base_mech, (), fs_ref)
    if progress:
        progress("wheel impedance")
    # The wheel impedance barely depends on the arm (0.1–0.3 %), but an FRF fit that ran into
    # its bounds (a rigid contact) makes the discretised loop meaningless: start from a
    # plausible arm, and recompute with the fitted one.
    plausible = {t.label: plausible_arm(t, model_baseline) for t in trials + prep.familiarization}
    for t in trials + prep.familiarization:
        t.Zw = kernel_wheel_impedance(t, plausible[t.label], base_mech)
    noise0 = noise_model(
        trials, {t.label: simulated_spectra(t, plausible[t.label], base_mech) for t in trials}
    )
    starts = [{t.label: t.arm0 for t in trials}, {t.label: t.arm_cell for t in trials}]
    for source in (model_baseline or {}, NOMINAL):
        if all(t.condition in source for t in trials):
            starts.append({t.label: with_inertia(source[t.condition].arm, t) for t in trials})
    if progress:
        progress("baseline fit")
    arms = best_start_arms(trials, spec0, noise0, starts)
    first = fit_model(trials, spec0, noise0, arms)
    first = choose_rig_limits(prep, spec0, noise0, first)
    for t in trials:
        t.Zw = kernel_wheel_impedance(t, first.arms[t.label], base_mech)
    noise = noise_model(trials, first.simulated)
    set_remnants(trials, first.arms, K_REMNANT_SELECT)
    base = fit_model(trials, spec0, noise, first.arms)
    reps = sorted({t.repetition for t in trials})
    folds = []
    if len(reps) >= 2:
        for r in reps:
            train = [t for t in trials if t.repetition == r]
            test = [t for t in trials if t.repetition != r]
            if train and test:
                folds.append((train, test))
    return Setup(
        trials=trials,
        fam=prep.familiarization,
        noise=noise,
        fs_ref=fs_ref,
        base_mech=base_mech,
        base=base,
        paper_arms={t.label: t.arm_cell for t in trials},
        folds=folds,
    )


@dataclass
class CandidateResult:
    name: str
    step: int
    fit: FitResult
    delta_m2ll: float  # −2 log L of the current model minus the candidate's (> 0: better)
    delta_bic: float  # candidate − current (< 0: better)
    held_out_gain: float | None  # −2 log L units, summed over folds (> 0: better)
    held_out_folds: list[float] = field(default_factory=list)
    passed: bool = False
    reason: str = ""
    fold_x: list[np.ndarray] = field(default_factory=list, repr=False)
    fold_cost: list[float] = field(default_factory=list, repr=False)
    robust_z: float = float("nan")
    form: str = "default"  # the family's best-fitting form
    form_m2ll: dict[str, float] = field(default_factory=dict)  # −2 log L of every form tried
    forms_consistent: list[str] = field(default_factory=list)  # within FORM_CONSISTENT_M2LL
    held_out_trial_cost: dict[str, float] = field(default_factory=dict, repr=False)
    # Candidates of the same step that explain the data as well as this one (see confusable).
    equally_good: list[dict] = field(default_factory=list)
    # Not tried on held-out data: the held-out gain of another candidate of its step that it
    # could not reach (see _held_out_stage); None when tried, or failed on BIC.
    held_out_skipped: float | None = None
    # A later step's family fitted only in its first step's form (see evaluate_candidate).
    only_first_form: bool = False
    # Passed on BIC, but the time limit came before its held-out check.
    held_out_undone: bool = False
    # Fitted only as far as its forms' screening: its gain was below this, 1/FULL_FIT_RATIO
    # of the step's best linear family's (see evaluate_candidate); None: fitted fully.
    full_fit_skipped: float | None = None

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "step": self.step,
            "form": self.form,
            "forms_minus2loglik": self.form_m2ll,
            "forms_consistent_with_data": self.forms_consistent,
            "parameters": [p for p in self.fit.parameters() if p["mechanism"] == self.name],
            "delta_minus2loglik": self.delta_m2ll,
            "delta_bic": self.delta_bic,
            "held_out_gain_minus2loglik": self.held_out_gain,
            "held_out_folds": self.held_out_folds,
            "robust_z": self.robust_z,
            "passed": self.passed,
            "reason": self.reason,
            "held_out_not_tried_below": self.held_out_skipped,
            "full_fit_not_done_below": self.full_fit_skipped,
            "only_first_step_form": self.only_first_form,
            "equally_good": self.equally_good,
            "iterations": self.fit.iterations,
            "converged": self.fit.converged,
        }


@dataclass
class Current:
    """The model a step adds to: its spec, full fit and held-out fold results."""

    spec: ModelSpec
    fit: FitResult
    fold_x: list[np.ndarray]  # mechanism coordinates fitted on each fold's training trials
    fold_test_cost: list[float]  # −2 log L on each fold's test trials


def _fold_eval(
    setup: Setup,
    spec: ModelSpec,
    arms: dict[str, ArmParams],
    x_starts: Sequence[np.ndarray] | None = None,
    relative_stop: bool | None = None,
) -> tuple[list[np.ndarray], list[float], dict[str, float]]:
    """Per fold: the mechanism coordinates fitted on the training trials (from ``x_starts``,
    never from a fit that saw the test trials), and −2 log L on the test trials with them;
    and −2 log L per test trial (key "fold:label"). ``relative_stop``: see
    :func:`fit_model`; by default for a candidate's folds, not the baseline's."""
    return joined_folds(
        [
            _one_fold(
                setup, spec, arms, i, None if x_starts is None else x_starts[i], relative_stop
            )
            for i in range(len(setup.folds))
        ]
    )


FoldResult = tuple[np.ndarray, float, dict[str, float]]


def _one_fold(
    setup: Setup,
    spec: ModelSpec,
    arms: dict[str, ArmParams],
    i: int,
    x_start: np.ndarray | None,
    relative_stop: bool | None,
) -> FoldResult:
    """Fold ``i`` of :func:`_fold_eval`: its own task on a pool (the folds share nothing)."""
    train, test = setup.folds[i]
    rel = bool(spec.n_free) if relative_stop is None else relative_stop
    if spec.n_free:
        x0 = spec.start() if x_start is None else x_start
        a0 = start_arms(setup, train, spec, setup.noise, x0, arms)
        off = _new_off(spec, x0)
        x = fit_nested(train, spec, setup.noise, a0, x0, arms, off, relative_stop=rel).x
    else:
        x = spec.off()
    a0 = start_arms(setup, test, spec, setup.noise, x, arms)
    te = fit_nested(test, spec, setup.noise, a0, x, arms, x, fix_mechanisms=True, relative_stop=rel)
    return x, te.m2ll, {f"{i}:{lab}": 2.0 * c for lab, c in te.cost_trial.items()}


def joined_folds(
    parts: Sequence[FoldResult],
) -> tuple[list[np.ndarray], list[float], dict[str, float]]:
    """:func:`_fold_eval`'s result from its folds' (:func:`_one_fold`), in fold order."""
    per_trial: dict[str, float] = {}
    for _, _, d in parts:
        per_trial.update(d)
    return [p[0] for p in parts], [p[1] for p in parts], per_trial


FoldEval = Callable[..., tuple[list[np.ndarray], list[float], dict[str, float]]]


def make_current(
    setup: Setup, spec: ModelSpec, fit: FitResult, folds: FoldEval | None = None
) -> Current:
    """The model ``spec`` fitted as ``fit``, with its folds (``folds``: :func:`_fold_eval`
    without its ``setup``, where it runs elsewhere)."""
    xs, costs, _ = (folds or partial(_fold_eval, setup))(spec, fit.arms)
    return Current(spec, fit, xs, costs)


def _fit_form(
    setup: Setup, current: Current, cand: Candidate, max_iter: int = MAX_ITER
) -> FitResult:
    spec = ModelSpec(current.spec.base, current.spec.free + (cand,), current.spec.fs_ref)
    x0 = np.concatenate([current.fit.x, spec.start()[current.spec.n_free :]])
    a0 = start_arms(setup, setup.trials, spec, setup.noise, x0, current.fit.arms)
    off = _new_off(spec, x0)
    return fit_nested(
        setup.trials, spec, setup.noise, a0, x0, current.fit.arms, off, max_iter=max_iter,
        relative_stop=True,
    )  # fmt: skip


def _consistent(form_m2ll: dict[str, float]) -> list[str]:
    """The forms whose −2 log L is within :data:`FORM_CONSISTENT_M2LL` of the best, best first
    (the others were fitted for a few iterations only: an approximate set)."""
    if not form_m2ll:
        return []
    best = min(form_m2ll.values())
    ranked = sorted(form_m2ll, key=form_m2ll.__getitem__)
    return [f for f in ranked if form_m2ll[f] - best <= FORM_CONSISTENT_M2LL]


def is_linear_family(name: str) -> bool:
    """Whether every form of the family ``name`` keeps the loop linear and time-invariant:
    added to a linear model, its fits take the bin route and cost a fraction of a simulated
    family's."""
    family = candidate(name)
    for form in family.forms:
        spec = ModelSpec(Mechanisms(), (family.with_form(form),), 250.0)
        on = spec.clip(spec.start() + [p.step for p in spec.specs()])  # every parameter ≠ 0
        if not is_linear_time_invariant(spec.mechanisms(on)):
            return False
    return True


def evaluate_candidate(
    setup: Setup,
    current: Current,
    name: str,
    step: int,
    first_form: str | None = None,
    full_fit_below: float | None = None,
) -> CandidateResult:
    """The family ``name`` added to the current model: each of its forms fitted on all trials,
    the best by −2 log L as the family's candidate, with its ΔBIC (its held-out folds come
    later, from :func:`add_held_out`, for the candidates that need them). A family the
    baseline already has (a model file's) is re-fitted in the form it has. ``first_form``:
    the form that fitted best at the first step (later steps): screened first, and when it
    improves nothing (less than :data:`RETRY_MIN_DELTA_M2LL`) the other forms are not
    screened. ``full_fit_below``: a family of several forms whose best screening gains less
    than this (and more than :data:`RETRY_MIN_DELTA_M2LL`) is not fitted fully
    (:data:`FULL_FIT_RATIO`; :func:`complete_full_fit` does it where it is needed).

    The fits are :func:`candidate_plan`'s tasks, run here one after the other."""
    plan = candidate_plan(current, name, step, first_form, full_fit_below)
    request: Any = next(plan)
    while True:
        try:
            assert isinstance(request, Fits)  # (never PENDING: the threshold is given)
            request = plan.send([run_task(setup, current, task) for task in request.tasks])
        except StopIteration as stop:
            return stop.value


# A candidate_plan's request for its step's full-fit threshold (known once the linear
# families are evaluated), where it was started without it.
PENDING = "pending"
# A fit of a candidate: ("form", Candidate, max_iter): the candidate (one form) added to the
# current model and fitted (_fit_form); ("full", FitResult): a screening's full fit.
Task = tuple[Any, ...]


@dataclass(frozen=True)
class Fits:
    """A :func:`candidate_plan`'s request: ``tasks``, fits independent of one another (its
    results come back in their order); ``then``: the fits it asks for next unless these
    results say otherwise (a pool may start them early on a worker that would wait)."""

    tasks: list[Task]
    then: list[Task] = field(default_factory=list)


def candidate_plan(
    current: Current,
    name: str,
    step: int,
    first_form: str | None = None,
    full_fit_below: float | str | None = None,
) -> Generator[Fits | str, Any, CandidateResult]:
    """:func:`evaluate_candidate` as a plan: it yields :class:`Fits` and is sent their
    results; with ``full_fit_below`` :data:`PENDING` it yields PENDING when it needs that
    threshold, and is sent it; it returns the candidate. On a pool each request's fits run
    at once: a family's forms had been fitted one after another in one worker while the
    other waited (7.5 of a friction study's 64 s at its second step)."""
    family = candidate(name)
    forms = (
        (family.form_of(current.spec.base),) if family.is_on(current.spec.base) else family.forms
    )
    only_first = False
    skipped = None
    if len(forms) == 1:
        (fit,) = yield Fits([("form", family.with_form(forms[0]), MAX_ITER)])
        return _candidate_result(current, name, step, fit, 1, forms[0].name, {}, False, None)
    # Each form gets a few iterations and the best of them the full fit: fitting every
    # form fully would cost as much as that many candidates.
    order = sorted(forms, key=lambda f: f.name != first_form)
    screens = [("form", family.with_form(f), FORM_SCREEN_ITER) for f in order]
    if order[0].name != first_form:
        fits = list(zip((yield Fits(screens)), order, strict=True))
    else:
        # At a later step a family whose first step's best form now improves nothing is
        # not screened in its others: at the first step, against a baseline far from the
        # data, every family "improved", and its forms were most of a later step's time.
        (first,) = yield Fits(screens[:1], then=screens[1:])
        fits = [(first, order[0])]
        only_first = current.fit.m2ll - first.m2ll < RETRY_MIN_DELTA_M2LL
        if not only_first:
            fits += list(zip((yield Fits(screens[1:])), order[1:], strict=True))
    form_m2ll = {f.name: r.m2ll for r, f in fits}
    fit, form = min(fits, key=lambda pair: pair[0].m2ll)
    gain = current.fit.m2ll - fit.m2ll
    if full_fit_below == PENDING and gain > RETRY_MIN_DELTA_M2LL:
        full_fit_below = yield PENDING
    if full_fit_below is not None and RETRY_MIN_DELTA_M2LL < gain < float(full_fit_below):
        skipped = float(full_fit_below)
    else:
        (fit,) = yield Fits([("full", fit)])
        form_m2ll[form.name] = fit.m2ll
    return _candidate_result(
        current, name, step, fit, len(forms), form.name, form_m2ll, only_first, skipped
    )


@dataclass(eq=False)
class _Fit:
    """A fit of a plan on a pool: "new", "spare" (a fit the plan may ask for next, for a
    worker that would wait), "ready" (asked for), "running", "done" (``result``)."""

    n: str  # the plan's family
    task: Task
    state: str = "new"
    result: Any = None
    error: BaseException | None = None  # what the fit raised, raised if the plan asks for it


def full_fit_threshold(linear: Sequence[CandidateResult]) -> float | None:
    """The ``full_fit_below`` of a step's simulated families, from its linear families'
    candidates (:data:`FULL_FIT_RATIO`)."""
    lead = max((r.delta_m2ll for r in linear), default=0.0) / FULL_FIT_RATIO
    return lead if lead >= FULL_FIT_MIN_M2LL else None


def run_task(setup: Setup, current: Current, task: Task) -> FitResult:
    """One fit of a :func:`candidate_plan`."""
    kind, *args = task
    if kind == "form":
        return _fit_form(setup, current, *args)
    return _full_fit(setup, *args)


def _full_fit(setup: Setup, screened: FitResult, relative_stop: bool = True) -> FitResult:
    """The full fit of a family's best screened form, from its screening (or of any fit, on
    from where it ended). ``relative_stop``: see :func:`fit_model`."""
    opts = {"relative_stop": relative_stop}
    fit = fit_model(setup.trials, screened.spec, setup.noise, screened.arms, x0=screened.x, **opts)
    # The full fit can walk into a corner its screening did not reach: the independent
    # world's second-order lag ended with three trials' arms at bounds, 1 000 units of
    # −2 log L above the fit from plausible arms, and every candidate of the next step,
    # started from those, "improved" on it by as much (and went to its held-out folds).
    return _out_of_corners(setup.trials, screened.spec, setup.noise, fit, opts)


def _candidate_result(
    current: Current,
    name: str,
    step: int,
    fit: FitResult,
    n_forms: int,
    form: str,
    form_m2ll: dict[str, float],
    only_first: bool,
    full_fit_skipped: float | None,
) -> CandidateResult:
    d_m2ll = current.fit.m2ll - fit.m2ll
    # The family's prior is shared among its K forms (as drift's): 2 ln K on the −2 log L
    # scale, the price of choosing the best of K shapes on the same data.
    d_bic = fit.bic - current.fit.bic + 2.0 * math.log(n_forms)
    return CandidateResult(
        name, step, fit, float(d_m2ll), float(d_bic), None, form=form,
        form_m2ll=form_m2ll, forms_consistent=[] if only_first else _consistent(form_m2ll),
        only_first_form=only_first, full_fit_skipped=full_fit_skipped,
    )  # fmt: skip


def complete_full_fit(setup: Setup, current: Current, r: CandidateResult) -> CandidateResult:
    """``r`` (fitted only as far as its forms' screening) with its best form's full fit: the
    candidate :func:`evaluate_candidate` gives without ``full_fit_below``."""
    if r.full_fit_skipped is None:
        return r
    fit = _full_fit(setup, r.fit)
    form_m2ll = {**r.form_m2ll, r.form: fit.m2ll}
    n_forms = len(candidate(r.name).forms)
    return _candidate_result(
        current, r.name, r.step, fit, n_forms, r.form, form_m2ll, r.only_first_form, None
    )


def needs_held_out(setup: Setup, r: CandidateResult) -> bool:
    """The held-out folds only decide between candidates that pass on BIC: one that does not
    cannot be retained, and its folds (half the stage's time) would change nothing."""
    return bool(setup.folds) and r.delta_bic < -MIN_DBIC


def held_out_fold(setup: Setup, current: Current, r: CandidateResult, i: int) -> FoldResult:
    """Fold ``i`` of :func:`_fold_eval` for the candidate ``r`` fitted at this step."""
    new = r.fit.spec.start()[current.spec.n_free :]
    start = np.concatenate([current.fold_x[i], new])
    return _one_fold(setup, r.fit.spec, current.fit.arms, i, start, None)


def add_held_out(
    current: Current,
    r: CandidateResult,
    folds: tuple[list[np.ndarray], list[float], dict[str, float]],
) -> None:
    """Fill in ``r``'s held-out gain from its folds (:func:`held_out_fold`, joined)."""
    xs, costs, per_trial = folds
    r.held_out_folds = [c0 - c1 for c0, c1 in zip(current.fold_test_cost, costs, strict=True)]
    r.held_out_gain = float(sum(r.held_out_folds))
    r.fold_x, r.fold_cost, r.held_out_trial_cost = xs, costs, per_trial


def robust_z(r: CandidateResult) -> float:
    """How far the candidate's parameters are from "as before" (0, or the model file's value),
    in cluster-robust standard errors (the largest over its parameters)."""
    return parameter_z(r.fit, r.name)


def parameter_z(fit: FitResult, name: str) -> float:
    """How far ``fit``'s parameters of mechanism ``name`` are from the baseline's (0, or the
    model file's or measured wheel's value), in standard errors (the largest)."""
    spec = fit.spec
    off = spec.physical(spec.off(), None)
    z = 0.0
    for p, o in zip(fit.parameters(), off, strict=True):
        if p["mechanism"] != name:
            continue
        se = p["se"]
        if se and np.isfinite(se) and se > 0:
            z = max(z, abs(p["value"] - o["value"]) / se)
    return float(z)


def confusable(
    best: CandidateResult, others: Sequence[CandidateResult], held_out: bool
) -> list[dict]:
    """The passing candidates that explain the data as well as ``best``, within the noise of
    the criterion, with the evidence for each (issue 18 item 4).

    The criterion is what chose ``best``: the held-out −2 log L (or, without a held-out check,
    BIC). Its difference between two candidates is a sum over trials of per-trial differences
    (held out: over the test trials of every fold), and the trials are independent, so its
    standard error is √n × their standard deviation. Within ``AMBIGUITY_Z`` standard errors the
    data cannot tell the two apart.
    """
    out = []
    for r in others:
        if r is best or not r.passed:
            continue
        if held_out:
            keys = sorted(best.held_out_trial_cost.keys() & r.held_out_trial_cost.keys())
            d = np.array([r.held_out_trial_cost[k] - best.held_out_trial_cost[k] for k in keys])
            diff = float(d.sum())
        else:
            keys = sorted(best.fit.cost_trial.keys() & r.fit.cost_trial.keys())
            d = np.array([2.0 * (r.fit.cost_trial[k] - best.fit.cost_trial[k]) for k in keys])
            # Both are fitted on every trial against the same current model: their BIC
            # difference, with the prices of parameters and forms as ΔBIC has them.
            diff = float(r.delta_bic - best.delta_bic)
        if len(d) < 2:
            continue
        se = float(math.sqrt(len(d)) * d.std(ddof=1))
        if diff <= AMBIGUITY_Z * se:
            out.append(
                {
                    "name": r.name,
                    "form": r.form,
                    "criterion": "held-out −2 log L" if held_out else "BIC",
                    "worse_by": diff,  # the criterion's difference, alternative − best
                    "se": se,
                    "held_out_gain_minus2loglik": r.held_out_gain,
                    "delta_bic": r.delta_bic,
                    "robust_z": r.robust_z,
                    "parameters": [p for p in r.fit.parameters() if p["mechanism"] == r.name],
                }
            )
    return out


def judge(results: Sequence[CandidateResult], held_out: bool) -> None:
    for r in results:
        r.robust_z = robust_z(r)
        ok_z = r.robust_z > MIN_ROBUST_Z
        if held_out:
            ok_bic = r.delta_bic < -MIN_DBIC
            ok_ho = r.held_out_gain is not None and r.held_out_gain > MIN_HELD_OUT
            r.passed = ok_bic and ok_ho and ok_z
            if r.passed:
                r.reason = "better on BIC and on held-out data"
            elif ok_bic and ok_ho:
                r.reason = (
                    "better on BIC and held out, but its parameter does not stand out from "
                    f"the trial-to-trial scatter (robust z = {r.robust_z:.1f})"
                )
            elif ok_bic and r.held_out_undone:
                r.reason = "better on BIC, but the time limit came before its held-out check"
            elif ok_bic and r.held_out_skipped is not None:
                r.reason = (
                    f"better on BIC, but its gain (−2 log L {r.delta_m2ll:.4g}) is far below "
                    f"another candidate's held-out gain ({r.held_out_skipped:.4g}): not tried "
                    "on held-out data"
                )
            elif ok_bic:
                r.reason = "better on BIC, but does not predict the other repetition"
            elif r.held_out_gain is None and r.full_fit_skipped is not None:
                r.reason = "not better on BIC at its screening (so not tried on held-out data)"
            elif r.held_out_gain is None:
                r.reason = "not better on BIC (so not tried on held-out data)"
            else:
                r.reason = "no better than the model without it"
            if r.full_fit_skipped is not None:
                r.reason += (
                    f" (fitted only as far as its forms' screening: its gain is below "
                    f"{r.full_fit_skipped:.4g}, 1/{FULL_FIT_RATIO:g} of the best linear "
                    "candidate's)"
                )
        else:
            r.passed = r.delta_bic < -MIN_DBIC_NO_HELD_OUT and ok_z
            r.reason = (
                "better on BIC (no held-out check possible)" if r.passed else "not better on BIC"
            )


# -- parallel evaluation ------------------------------------------------------------------------
def _limit_threads() -> AbstractContextManager:
    """One BLAS thread while in effect (as a context manager; called bare, for good).

    Tiny matrices everywhere (the world's 7×7 matrix exponential per trial): BLAS threads only
    add overhead, 70× for expm on a loaded 2-core machine. threadpoolctl is a dependency, not
    an option: without it (an install without the test extras, as the README's first command
    made) the independent world's studies took 4 × the CPU seconds.
    """
    return threadpool_limits(1)


def in_worker(fn: Callable[..., Any], setup: object, *args: Any) -> Any:
    """``fn(set-up, *args)`` as a task: ``setup`` is the handle of :mod:`analysis.executors`
    that brings the set-up once per worker (a Dask worker has no initializer to install it)."""
    with _limit_threads():
        return fn(shared_value(setup), *args)


@dataclass
class Selection:
    steps: list[list[CandidateResult]]
    retained: list[CandidateResult]
    final: FitResult
    final_spec: ModelSpec
    base: FitResult
    final_fold_x: list[np.ndarray]  # the final model's mechanisms fitted on each fold
    # The retained model as selected: fitted with the same noise model as the baseline and
    # every candidate, so its −2 log L and BIC compare with theirs (``final`` is re-fitted
    # with the noise re-estimated from its own residual, for its parameters).
    final_as_selected: FitResult | None = None
    # What the time limit left undone (empty when the selection ran to its end).
    undone: list[str] = field(default_factory=list)


def select(
    setup: Setup,
    names: Sequence[str] | None = None,
    jobs: int = 1,
    progress: Progress | None = None,
    time_limit_s: float | None = None,
    executor: cf.Executor | None = None,
) -> Selection:
    """Greedy forward selection (module docstring). ``time_limit_s``: the candidate stage's
    limit (default :data:`CANDIDATE_TIME_LIMIT_S`, read at call time; ``math.inf``: none).
    ``executor``: where the candidates are evaluated (any ``concurrent.futures.Executor``,
    Dask's included); else ``jobs`` processes of our own, or this process."""
    pool = [c.name for c in CANDIDATES] if names is None else list(names)
    if time_limit_s is None:
        time_limit_s = CANDIDATE_TIME_LIMIT_S
    own_pool = executor is None and jobs > 1
    shared: object = None
    if own_pool:
        executor, shared = sharing_pool(jobs, setup)
    elif executor is not None:
        shared = share(executor, setup)
    try:
        # CPU seconds: this process's, and our own workers' where they can be read (then the
        # limit does not come sooner on a loaded machine or with more jobs); else (an
        # executor we were given) wall-clock seconds.
        clock: Callable[[], float] = time.process_time
        per_wall = 1  # CPU seconds the clock can advance per wall second
        if own_pool:
            clock = pool_cpu_clock(executor) or time.monotonic
            per_wall = jobs + 1 if clock is not time.monotonic else 1
        elif executor is not None:
            clock = time.monotonic
        deadline = clock() + time_limit_s
        undone: list[str] = []

        def late() -> bool:
            return clock() > deadline

        def evaluate(
            current: Current,
            batch: list[str],
            step: int,
            first_forms: dict[str, str],
            below: float | None,
        ) -> list[CandidateResult]:
            """The candidates ``batch`` here, one after another (``below``: see
            :func:`evaluate_candidate`); what the time limit leaves unevaluated goes to
            ``undone``."""
            results: list[CandidateResult] = []
            for i, n in enumerate(batch):
                if late():
                    undone.append(f"step {step}: {', '.join(batch[i:])} not evaluated")
                    break
                if progress:
                    progress(f"step {step}: {n}")
                results.append(
                    evaluate_candidate(setup, current, n, step, first_forms.get(n), below)
                )
            return results

        def evaluate_pooled(
            current: Current,
            linear: list[str],
            simulated: list[str],
            step: int,
            first_forms: dict[str, str],
        ) -> list[CandidateResult]:
            """:func:`evaluate`'s candidates, linear and simulated, on the executor: every
            fit of their plans (:func:`candidate_plan`) as its own task, submitted as soon
            as the plan asks for it; the simulated families' threshold as soon as the
            linear ones are evaluated. The same fits as :func:`evaluate`'s, with the same
            results; only the order of their running differs, and on our own pool a worker
            with nothing to do starts a fit a plan may ask for next (:class:`Fits`)."""
            nonlocal executor
            assert executor is not None
            pool = executor
            plans = {
                n: candidate_plan(
                    current, n, step, first_forms.get(n), None if n in linear else PENDING
                )
                for n in linear + simulated
            }
            done_: dict[str, CandidateResult] = {}
            asked: dict[str, list[_Fit]] = {}  # each plan's request, being fitted
            early: dict[str, list[_Fit]] = {}  # fits a plan may ask for next
            futs: dict[cf.Future, _Fit] = {}
            ready: list[tuple] = []  # asked for, not yet submitted (a heap)
            spare: list[_Fit] = []  # fits for a worker that would wait
            order = itertools.count()
            # On our own pool, no more fits queued than it has workers, so that a fit asked
            # for later can still go first; an executor we were given has its own order.
            in_flight = jobs if own_pool else math.inf
            waiting: list[str] = []  # plans that asked for the threshold
            threshold: list[float | None] = []  # once known

            def advance(n: str, value: Any) -> None:
                try:
                    request = plans[n].send(value)
                except StopIteration as stop:
                    done_[n] = stop.value
                    for fit in early.pop(n, []):
                        if fit.state == "spare":
                            spare.remove(fit)
                    release()
                    return
                if not isinstance(request, Fits):  # PENDING
                    if threshold:
                        advance(n, threshold[0])
                    else:
                        waiting.append(n)
                    return
                fits = []
                offered = early.pop(n, [])
                for task in request.tasks:
                    match = [f for f in offered if f.task == task]
                    fit = match[0] if match else _Fit(n, task)
                    if match:
                        offered.remove(fit)
                    if fit.state in ("new", "spare"):
                        if fit.state == "spare":
                            spare.remove(fit)
                        key = (n not in linear, task[0] != "full", next(order))
                        heapq.heappush(ready, (*key, fit))
                        fit.state = "ready"
                    fits.append(fit)
                for fit in offered:  # not asked for after all
                    if fit.state == "spare":
                        spare.remove(fit)
                asked[n] = fits
                if own_pool:
                    early[n] = [_Fit(n, task, state="spare") for task in request.then]
                    spare.extend(early[n])
                answer(n)

            def answer(n: str) -> None:
                """Send plan ``n`` its request's results once they are all in."""
                if n in asked and all(f.state == "done" for f in asked[n]):
                    fits = asked.pop(n)
                    for fit in fits:
                        if fit.error is not None:
                            raise fit.error
                    advance(n, [f.result for f in fits])
                pump()

            def pump() -> None:
                """Submit fits while fewer than ``in_flight`` run (on our own pool: while a
                worker is free): those asked for, the linear families' first (their gains
                set the threshold the simulated families' full fits wait for) and of each
                kind the full fits first (the longest: started last, one had run alone at
                the end of a step); else a spare."""
                while started and len(futs) < in_flight and (ready or spare):
                    fit = heapq.heappop(ready)[-1] if ready else spare.pop(0)
                    fit.state = "running"
                    futs[pool.submit(in_worker, run_task, shared, current, fit.task)] = fit

            def release() -> None:
                if threshold or not all(n in done_ for n in linear):
                    return
                threshold.append(full_fit_threshold([done_[n] for n in linear]))
                for n in list(waiting):
                    waiting.remove(n)
                    advance(n, threshold[0])

            started = False  # (every plan's first request in before any fit is submitted)
            for n in plans:
                advance(n, None)
            started = True
            release()  # (no linear family at all)
            pump()
            while len(done_) < len(plans):
                # (Every plan not done has a fit asked for, or waits for the linear ones.)
                assert futs, "candidate plans left without a fit to wait for"
                finished = wait_any(set(futs))
                if finished is None:
                    ready.clear()
                    spare.clear()
                    _drop(set(futs), pool, own_pool)
                    executor = None
                    left = [n for n in plans if n not in done_]
                    undone.append(f"step {step}: {', '.join(left)} not evaluated")
                    break
                for f in finished:
                    fit = futs.pop(f)
                    # (A spare's failure is its plan's only if the plan asks for that fit.)
                    fit.error = f.exception()
                    fit.result = None if fit.error else f.result()
                    fit.state = "done"
                    answer(fit.n)
            # (A spare fit still running is left to end: its result is not wanted.)
            return [done_[n] for n in plans if n in done_]

        def wait_any(futs: set) -> set | None:
            """The futures of ``futs`` done, once one is; None at the time limit."""
            while True:
                left = deadline - clock() if math.isfinite(deadline) else None
                if left is not None and left <= 0:
                    return None
                timeout = None if left is None else max(left / per_wall, 0.05)
                d, _ = cf.wait(futs, timeout, return_when=cf.FIRST_COMPLETED)
                if d:
                    return d

        def wait(futs: dict) -> tuple[set, set]:
            """cf.wait for ``futs`` until done or the time limit (done, pending)."""
            done: set = set()
            pending = set(futs)
            while pending:
                left = deadline - clock() if math.isfinite(deadline) else None
                if left is not None and left <= 0:
                    break
                d, pending = cf.wait(pending, None if left is None else max(left / per_wall, 0.05))
                done |= d
            return done, pending

        def fold_eval(
            spec: ModelSpec,
            arms: dict[str, ArmParams],
            x_starts: Sequence[np.ndarray] | None = None,
            relative_stop: bool | None = None,
        ) -> tuple[list[np.ndarray], list[float], dict[str, float]]:
            """:func:`_fold_eval` of a model the main process holds: each fold a task on
            the executor where there is one (the baseline's took 3.5 s of a sensor-delay
            study's wall time while the workers waited)."""
            if executor is None:
                return _fold_eval(setup, spec, arms, x_starts, relative_stop)
            starts = [None] * len(setup.folds) if x_starts is None else list(x_starts)
            futs = [
                executor.submit(in_worker, _one_fold, shared, spec, arms, i, x0, relative_stop)
                for i, x0 in enumerate(starts)
            ]
            return joined_folds([f.result() for f in futs])

        current = make_current(setup, setup.spec(), setup.base, fold_eval)
        steps: list[list[CandidateResult]] = []
        retained: list[CandidateResult] = []
        for step in range(1, MAX_MECHANISMS + 1):
            remaining = retried([n for n in pool if n not in current.spec.names], steps)
            first_forms = {r.name: r.form for r in steps[0]} if steps else {}
            if not remaining:
                break
            if late():
                undone.append(f"step {step} not started ({', '.join(remaining)} not tried)")
                break
            if progress:
                progress(f"step {step}: {len(remaining)} candidates")
            # The linear families first: the best of their gains decides which simulated
            # family is worth its full fit (FULL_FIT_RATIO; only with a held-out check, which
            # is what makes a candidate far below the leader one that cannot be chosen).
            linear = [n for n in remaining if not setup.folds or is_linear_family(n)]
            simulated = [n for n in remaining if n not in linear]
            if executor is not None:
                results = evaluate_pooled(current, linear, simulated, step, first_forms)
            else:
                results = evaluate(current, linear, step, first_forms, None)
                if simulated and undone:
                    undone.append(f"step {step}: {', '.join(simulated)} not evaluated")
                elif simulated:
                    below = full_fit_threshold(results)
                    results += evaluate(current, simulated, step, first_forms, below)
            results.sort(key=lambda r: remaining.index(r.name))
            if undone:
                # Cut before their held-out stage: say so rather than "does not predict".
                for r in results:
                    r.held_out_undone = needs_held_out(setup, r)
            else:
                executor = _held_out_stage(
                    setup, current, results, step, executor, shared, own_pool, late, wait,
                    undone,
                )  # fmt: skip
            judge(results, held_out=bool(setup.folds))
            steps.append(results)
            passing = [r for r in results if r.passed]
            if not passing or undone:
                break
            key = (lambda r: r.held_out_gain) if setup.folds else (lambda r: -r.delta_bic)
            best = max(passing, key=key)
            best.equally_good = confusable(best, passing, held_out=bool(setup.folds))
            retained.append(best)
            with simulations_on(executor, shared, None, jobs):
                current = current_after(setup, best, fold_eval)
        final_spec = current.spec
        final = current.fit
        if final_spec.n_free and late():
            undone.append(
                "the retained model's final re-fit (own noise model, more remnant "
                "realisations) not done: its parameters are those of the selection"
            )
        elif final_spec.n_free:
            if progress:
                progress("final fit")
            final = _final_fit(setup, final_spec, final, executor, shared, jobs)
            _confirm_refits(setup, retained, final)
    finally:
        if own_pool and executor is not None:
            executor.shutdown()
    return Selection(
        steps, retained, final, final_spec, setup.base, current.fold_x, current.fit, undone
    )


def _final_fit(
    setup: Setup,
    spec: ModelSpec,
    fit: FitResult,
    executor: cf.Executor | None,
    shared: object,
    jobs: int,
) -> FitResult:
    """The retained model's parameters: with the noise re-estimated from its own residual
    (the baseline's residual holds the distortion the mechanism explains, which
    under-weights the unexcited bins), and for a nonlinear mechanism from more remnant
    realisations (one biases its parameters towards zero by a few per cent).

    Its simulations run on the selection's pool where there is one: this fit was a sixth to
    a fifth of a friction study's wall time, in one process while the workers waited."""
    mech = spec.mechanisms(fit.x)
    more = needs_remnant(mech) and K_REMNANT_FINAL > setup.n_remnant
    state = TrialState(
        uuid.uuid4().hex,
        fit.arms if more else None,
        K_REMNANT_FINAL if more else setup.n_remnant,
        mech.sensor_delay.active,
    )
    state.apply(setup)  # here; each worker applies it to its own copy
    setup.final_noise = noise_model(setup.trials, fit.simulated)
    with simulations_on(executor, shared, state, jobs):
        a0 = start_arms(setup, setup.trials, spec, setup.final_noise, fit.x, fit.arms)
        final = fit_model(setup.trials, spec, setup.final_noise, a0, x0=fit.x)
        return _out_of_corners(setup.trials, spec, setup.final_noise, final, {})


@contextmanager
def simulations_on(
    executor: cf.Executor | None, shared: object, state: TrialState | None, jobs: int
) -> Iterator[None]:
    """The fits of the main process within run their simulations on ``executor`` (none:
    here; here too where a task's handle carries the set-up, an executor we were given that
    is not Dask's: :func:`~analysis.executors.travels_light`); ``state``: what the workers'
    trials need applied (None: nothing)."""
    if executor is None or not travels_light(shared):
        yield
        return
    state = state or TrialState("", None, 0, False)
    token = SPECTRA_MAP.set(_pool_spectra(executor, shared, state, max(jobs, 2)))
    try:
        yield
    finally:
        SPECTRA_MAP.reset(token)


@dataclass(frozen=True)
class TrialState:
    """What the main process changed on the set-up's trials for the final fit, after the
    pool's workers got their copy: each worker applies it to its own once (``token``)."""

    token: str
    remnant_arms: dict[str, ArmParams] | None  # the arms the remnants are reconstructed for
    n_remnant: int
    undo_reading_delay: bool

    def apply(self, setup: Setup) -> None:
        if not self.token or setup.trial_state == self.token:
            return
        if self.remnant_arms is not None:
            set_remnants(setup.trials, self.remnant_arms, self.n_remnant)
            setup.n_remnant = self.n_remnant
        if self.undo_reading_delay:
            for t in setup.trials + setup.fam:
                t.undo_reading_delay = True
        setup.trial_state = self.token


def _pool_spectra(
    executor: cf.Executor, shared: object, state: TrialState, n_tasks: int
) -> Callable[[list[SpectraJob]], list[np.ndarray]]:
    """A :data:`~analysis.diagnosis.fit.SPECTRA_MAP` that splits the jobs into ``n_tasks``
    runs of consecutive jobs, one task each (the trials travel as their labels)."""

    def run(jobs: list[SpectraJob]) -> list[np.ndarray]:
        labelled = [(t.label, arm, mech) for t, arm, mech in jobs]
        size = -(-len(labelled) // n_tasks)
        futs = [
            executor.submit(in_worker, _spectra_here, shared, state, labelled[i : i + size])
            for i in range(0, len(labelled), size)
        ]
        return [ys for f in futs for ys in f.result()]

    return run


def _spectra_here(
    setup: Setup, state: TrialState, jobs: list[tuple[str, ArmParams, Mechanisms]]
) -> list[np.ndarray]:
    """A task of :func:`_pool_spectra`: each job's spectra, on this worker's trials with
    ``state`` applied."""
    state.apply(setup)
    trials = {t.label: t for t in setup.trials}
    return [simulated_spectra(trials[label], arm, mech) for label, arm, mech in jobs]


def retried(names: Sequence[str], steps: Sequence[Sequence[CandidateResult]]) -> list[str]:
    """Of ``names``, those the next step tries: at the first step all; later, those that
    improved −2 log L by more than :data:`RETRY_MIN_DELTA_M2LL` at the step before (and so at
    every step before).

    A mechanism that improved nothing is not tried again: after a nonlinear mechanism every
    evaluation costs several simulations. On the independent world's Coulomb friction the
    third step re-fitted a reflex and a lag that had each improved the second step's model
    by less than 0.1 unit (11 of the study's 117 CPU s), because each had improved the
    first step's, a baseline far from the data, by hundreds."""
    if not steps:
        return list(names)
    # (A candidate fitted only as far as its screening gained more than the threshold there,
    # and its full fit at least as much: retried either way.)
    before = {r.name: r.delta_m2ll for r in steps[-1]}
    return [n for n in names if before.get(n, -math.inf) > RETRY_MIN_DELTA_M2LL]


def current_after(setup: Setup, best: CandidateResult, folds: FoldEval | None = None) -> Current:
    """The model the next step adds to: the retained candidate ``best`` as judged; or, where
    it was retained far from the noise floor (a lack of fit above
    :data:`~analysis.diagnosis.fit.RELATIVE_STOP_MIN_LACK`, where its fits may have stopped at
    the tolerance relative to the misfit), fitted on to the absolute tolerance, its folds
    too. Else the next step's candidates, started from its arms, would collect the descent
    it left (up to hundreds of units an iteration at a lack just above 3 on a full study) and
    pass on it."""
    if best.fit.lack_of_fit <= RELATIVE_STOP_MIN_LACK:
        return Current(best.fit.spec, best.fit, best.fold_x, best.fold_cost)
    spec = best.fit.spec
    fit = _full_fit(setup, best.fit, relative_stop=False)
    fold_x, fold_cost = best.fold_x, best.fold_cost
    if fold_x:
        folds = folds or partial(_fold_eval, setup)
        fold_x, fold_cost, _ = folds(spec, fit.arms, fold_x, relative_stop=False)
    return Current(spec, fit, fold_x, fold_cost)


def _held_out_stage(
    setup: Setup,
    current: Current,
    results: list[CandidateResult],
    step: int,
    executor: cf.Executor | None,
    shared: object,
    own_pool: bool,
    late: Callable[[], bool],
    wait: Callable[[dict], tuple[set, set]],
    undone: list[str],
) -> cf.Executor | None:
    """The held-out folds of the step's candidates that pass on BIC and could still be
    chosen; returns the executor (None once abandoned at the time limit).

    The candidate with the largest in-sample gain is tried first. The candidate chosen is the
    one with the largest held-out gain, and a candidate's held-out gain was at most 1.8 × its
    in-sample gain on the independent world's studies (docs/diagnosis.md, "Speed"): one whose
    in-sample gain is below 1/:data:`HELD_OUT_SKIP_RATIO` of that first candidate's held-out
    gain (when it can be retained) is not tried on held-out data, and its reason says so. On
    a baseline far from the data every candidate passes on BIC, and these folds were more
    than half of the step's time. The others are then tried together (with any number of jobs
    the same ones: the rule looks at the first candidate only). A candidate fitted only as far
    as its screening (:data:`FULL_FIT_RATIO`) that the rule leaves in gets its full fit first
    (its full gain is at least its screening's), and is tried if that passes on BIC.
    """
    # A candidate fitted short is in question even where its screening fails on BIC: its
    # full fit might pass (it is fitted fully only if the rule below leaves it in).
    todo = sorted(
        (r for r in results if needs_held_out(setup, r) or r.full_fit_skipped is not None),
        key=lambda r: -r.delta_m2ll,
    )
    best = -math.inf

    def cut(left: list[CandidateResult]) -> None:
        left = list({id(r): r for r in left}.values())  # a candidate's folds: named once
        if not left:
            return
        for r in left:
            r.held_out_undone = True
        names = ", ".join(r.name for r in left)
        undone.append(f"step {step}: held-out check of {names} not done")

    def each(
        batch: list[tuple[CandidateResult, tuple]],
        fn: Callable[..., Any],
        take: Callable[..., None],
    ) -> bool:
        """``fn(setup, current, r, *args)`` for each ``(r, args)`` of the batch (on the
        executor where there is one), its result given to ``take(r, *args, result)``; False
        when the time limit left some undone (their candidates are cut)."""
        nonlocal executor
        if executor is None:
            for i, (r, args) in enumerate(batch):
                if late():
                    cut([b[0] for b in batch[i:]])
                    return False
                take(r, *args, fn(setup, current, r, *args))
            return True
        futs = {
            executor.submit(in_worker, fn, shared, current, r, *args): (r, args)
            for r, args in batch
        }
        done, pending = wait(futs)
        for f, (r, args) in futs.items():
            if f in done:
                take(r, *args, f.result())
        if pending:
            _drop(pending, executor, own_pool)
            executor = None
            cut([futs[f][0] for f in futs if f in pending])
            return False
        return True

    def complete(batch: list[CandidateResult]) -> bool:
        """The full fits of the batch's candidates fitted as far as their screening only,
        in place."""
        short = [(r, ()) for r in batch if r.full_fit_skipped is not None]
        return each(short, complete_full_fit, _take)

    def run(batch: list[CandidateResult]) -> bool:
        """The batch's folds, each fold its own task (a candidate's two folds share nothing:
        on two workers the first candidate's folds had run alone, one worker idle)."""
        parts: dict[int, dict[int, FoldResult]] = {id(r): {} for r in batch}
        n = len(setup.folds)
        ok = each(
            [(r, (i,)) for r in batch for i in range(n)],
            held_out_fold,
            lambda r, i, part: parts[id(r)].__setitem__(i, part),
        )
        for r in batch:
            if len(parts[id(r)]) == n and not r.held_out_undone:
                folds = joined_folds([parts[id(r)][i] for i in range(n)])
                add_held_out(current, r, folds)
        return ok

    if not todo:
        return executor
    # (The first is never one fitted short where the threshold came from a linear family that
    # passes on BIC, see select; completed anyway, for any other way in.)
    if not complete(todo[:1]) or not run([r for r in todo[:1] if needs_held_out(setup, r)]):
        if todo[1:]:
            cut(todo[1:])
        return executor
    first = todo[0]
    first.robust_z = robust_z(first)
    gain = first.held_out_gain
    if gain is not None and gain > MIN_HELD_OUT and first.robust_z > MIN_ROBUST_Z:
        best = gain
    rest = []
    for r in todo[1:]:
        if HELD_OUT_SKIP_RATIO * r.delta_m2ll < best:
            r.held_out_skipped = best
        else:
            rest.append(r)
    if not complete(rest):
        cut([r for r in rest if r.full_fit_skipped is None and needs_held_out(setup, r)])
        return executor
    # The simulated families' folds first: the longest (a friction's 12 s fold had started
    # last and run alone).
    rest = sorted(
        (r for r in rest if needs_held_out(setup, r)), key=lambda r: is_linear_family(r.name)
    )
    if rest:
        run(rest)
    return executor


def _take(r: CandidateResult, new: CandidateResult) -> None:
    """``r`` becomes ``new`` in place (the step's list holds ``r``)."""
    for f in fields(CandidateResult):
        setattr(r, f.name, getattr(new, f.name))


def _drop(pending: set, executor: cf.Executor, own_pool: bool) -> None:
    """Work left at the time limit: not started, cancelled; already running on an executor we
    were given, left to finish, unwanted (only our own pool's workers are ours to stop)."""
    for f in pending:
        f.cancel()
    if own_pool:
        _abandon(executor)


ABANDON_GRACE_S = 5.0


def _abandon(executor: cf.Executor, grace_s: float = ABANDON_GRACE_S) -> None:
    """Stop a pool whose work is no longer wanted: queued work is cancelled and the workers
    still busy are terminated (shutdown alone would wait for them), then killed if they have
    not ended within ``grace_s``."""
    # Read before shutdown: it sets the pool's process table to None.
    procs = list((getattr(executor, "_processes", None) or {}).values())
    executor.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        proc.terminate()
    # Wait on the sentinels, never join: the pool's own thread reaps these processes too, and
    # a second waitpid on a reaped child reports "no such child", which reads as "alive".
    waiting = {proc.sentinel: proc for proc in procs}
    deadline = time.monotonic() + grace_s
    while waiting and (left := deadline - time.monotonic()) > 0:
        for ended in mp_connection.wait(list(waiting), left):
            del waiting[ended]
    for proc in waiting.values():
        proc.kill()


def _confirm_refits(setup: Setup, retained: list[CandidateResult], final: FitResult) -> None:
    """Un-retain re-fits of a baseline mechanism that the final fit puts back where they were.

    A mechanism the baseline already has (a model file's; the measured wheel's friction and
    lag) is screened with one remnant realisation, against a baseline simulated with one too:
    for a nonlinear mechanism the approximation's bias, not the data, can then move it (a
    measured 0.15 N·m friction, exactly the simulated study's, was re-fitted at screening,
    passed, and came back to 0.1498 ± 0.003 N·m with eight realisations). Screening the
    baseline with eight is the other way, about 5× slower.
    """
    for r in list(retained):
        if not candidate(r.name).is_on(setup.base_mech):
            continue
        z = parameter_z(final, r.name)
        if z <= MIN_ROBUST_Z:
            r.passed = False
            r.reason = (
                f"passed at screening, but re-fitted with {setup.n_remnant} remnant "
                f"realisations its value is the baseline's (robust z = {z:.1f})"
            )
            retained.remove(r)


def refit_noise(setup: Setup, fit: FitResult) -> NoiseModel:
    """The noise model re-estimated from a fitted model's residual (for the final checks)."""
    return noise_model(setup.trials, fit.simulated)
