"""How good are the per-subject arm estimates and their SEMs? A Monte-Carlo on known parameters.

Each Monte-Carlo *replicate* is one simulated subject as the study analyses it: every condition
(default all six) with two measured repetitions of one 45-s period each (after the protocol's
5-s run-in with its 1-s fade-in), simulated by Steerlab's own world (``hardware.sim.world.World``:
wheel rendering, remnant, sensor noise and quantisation) with the **same** known arm parameters
in every replicate, only the noise seed changing. The trials go through ``analyze_study`` with
the default options (inverse-variance maximum-likelihood weights, one I_i per subject shared by
its conditions), exactly as a report fits them. For each condition and parameter (I_i included):

- ``bias_percent``: mean estimate / truth − 1; ``median_bias_percent`` likewise with the median;
- ``sd``: spread of the estimates; ``mean_sem``: mean reported SEM; ``sd_over_mean_sem``: near
  1 when the SEMs describe the real scatter; ``robust_sd_over_median_sem``: the same with
  1.4826·MAD and the median SEM, insensitive to the few wild estimates;
- ``coverage_95_percent``: share of replicates whose estimate ± 1.96·SEM contains the truth
  (95 % for honest, normal errors); ``coverage_binomial_p``: the two-sided binomial test of that
  count against 95 %. With 80 replicates a coverage is known to ±2.4 points, and honest SEMs
  put about 5 of the 25 distinct cells outside 92–98 % by chance (docs/benchmarks.md,
  2026-11-26); a small p, not a miss of the band, is what says a cell's SEMs are off.

Goal (issue 13): ``sd_over_mean_sem`` within 0.8–1.25 and coverage within 92–98 % for every
parameter and condition. ``paper`` (unless ``--no-compare``): the same replicates fitted with the
paper's coherence × 1/f weights (``fit_compare``, same joint inertia), to show what they cost.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import stats

from steerlab.analysis.armfit import BOUNDS
from steerlab.analysis.study import AnalysisOptions, analyze_study
from steerlab.benchmarks.machine import machine, peak_rss_mb
from steerlab.hardware.sim.physiology import NOMINAL, ConditionBehaviour
from steerlab.hardware.sim.world import World, WorldConfig
from steerlab.protocols.perturbation import design_multisine
from steerlab.protocols.records import TrialRecord

FREE = ("I_i", "b_i", "k_i", "b_c", "k_c")
RUN_IN_S, FADE_IN_S, FADE_OUT_S = 5.0, 1.0, 1.0  # the paper protocol's trial timing


def simulate_trial(
    behaviour: ConditionBehaviour, design, fs_hz: float, seed: list[int], label: str, rep: int
) -> TrialRecord:
    """One trial as the engine records it: run-in (fading in), one period, fade-out."""
    n_run = int(round(RUN_IN_S * fs_hz))
    n_per = int(round(design.period_s * fs_hz))
    n_out = int(round(FADE_OUT_S * fs_hz))
    n = n_run + n_per + n_out
    t = (np.arange(n) - n_run) / fs_hz  # the first measured sample is at phase 0
    tp = design.signal(t)
    k_in = int(round(FADE_IN_S * fs_hz))
    tp[:k_in] *= 0.5 - 0.5 * np.cos(np.pi * np.arange(k_in) / k_in)
    tp[n - n_out :] *= 0.5 + 0.5 * np.cos(np.pi * (np.arange(n_out) + 1) / n_out)
    world = World(WorldConfig(fs_hz=fs_hz))
    world.begin_trial(behaviour, 0.5, seed)
    out = world.run(tp)
    return TrialRecord(
        subject=label,
        condition="MC",
        repetition=rep,
        familiarization=False,
        fs_hz=fs_hz,
        time_s=np.arange(n) / fs_hz,
        perturbation_torque_Nm=tp,
        driver_torque_Nm=out["driver_torque_Nm"],
        wheel_angle_rad=out["wheel_angle_rad"],
        grip_force_N=out["grip_force_left_N"] + out["grip_force_right_N"],
        trial_index=rep,
        measured_start=n_run,
        measured_stop=n_run + n_per,
        design=design,
        source=f"montecarlo:{label}_rep{rep}",
    )


def summarise(truth: dict[str, float], est: np.ndarray, sem: np.ndarray) -> dict:
    out = {}
    for j, name in enumerate(FREE):
        x, s, tv = est[:, j], sem[:, j], truth[name]
        ok = np.isfinite(x) & np.isfinite(s)
        x, s = x[ok], s[ok]
        if x.size < 2:
            out[name] = {"truth": tv, "n": int(x.size)}
            continue
        lo, hi = BOUNDS[name]
        at_bound = int(np.sum((x <= lo * 1.01) | (x >= hi / 1.01)))
        mad = 1.4826 * np.median(np.abs(x - np.median(x)))
        sd = float(np.std(x, ddof=1))
        out[name] = {
            "truth": tv,
            "n": int(x.size),
            "mean": float(np.mean(x)),
            "median": float(np.median(x)),
            "bias_percent": float(100 * (np.mean(x) / tv - 1)),
            "median_bias_percent": float(100 * (np.median(x) / tv - 1)),
            "sd": sd,
            "sd_percent_of_truth": float(100 * sd / tv),
            "mean_sem": float(np.mean(s)),
            "median_sem": float(np.median(s)),
            "sd_over_mean_sem": float(sd / np.mean(s)),
            "robust_sd_over_median_sem": float(mad / np.median(s)),
            "coverage_95_percent": float(100 * np.mean(np.abs(x - tv) <= 1.96 * s)),
            "coverage_binomial_p": float(
                stats.binomtest(int(np.sum(np.abs(x - tv) <= 1.96 * s)), x.size, 0.95).pvalue
            ),
            "n_at_bound": at_bound,
        }
    return out


def _goal_met(summary: dict) -> bool:
    ratio = summary.get("sd_over_mean_sem", float("nan"))
    cover = summary.get("coverage_95_percent", float("nan"))
    return bool(0.8 <= ratio <= 1.25 and 92.0 <= cover <= 98.0)


def run_study(
    conditions: list[str],
    cells: int,
    fs_hz: float,
    seed: int,
    compare: bool,
    executor=None,
    jobs: int = 1,
) -> dict:
    design = design_multisine()
    records = []
    for c in range(cells):
        label = f"C{c:03d}"
        for k, cond in enumerate(conditions):
            for rep in (1, 2):
                rec = simulate_trial(NOMINAL[cond], design, fs_hz, [seed, c, k, rep], label, rep)
                rec.condition = cond
                records.append(rec)
    study = analyze_study(
        records, executor=executor, jobs=jobs, options=AnalysisOptions(compare_weightings=compare)
    )
    out = {}
    for cond in conditions:
        rs = [r for r in study.subject_conditions if r.condition == cond]
        est = np.full((cells, len(FREE)), np.nan)
        sem = np.full((cells, len(FREE)), np.nan)
        est_p = np.full_like(est, np.nan)
        sem_p = np.full_like(sem, np.nan)
        failed = cells - sum(r.fit is not None for r in rs)
        for i, r in enumerate(rs):
            if r.fit is not None:
                est[i] = [getattr(r.fit.params, n) for n in FREE]
                sem[i] = [r.fit.sems.get(n, np.nan) for n in FREE]
            if r.fit_compare is not None:
                est_p[i] = [getattr(r.fit_compare.params, n) for n in FREE]
                sem_p[i] = [r.fit_compare.sems.get(n, np.nan) for n in FREE]
        truth = {n: float(getattr(NOMINAL[cond].arm, n)) for n in FREE}
        vaf = [r.vaf_percent for r in rs if r.vaf_percent is not None]
        params = summarise(truth, est, sem)
        out[cond] = {
            "cells": cells,
            "trials": 2 * cells,
            "fits_failed": failed,
            "median_vaf_percent": float(np.median(vaf)) if vaf else None,
            "parameters": params,
            "goal_met": {n: _goal_met(v) for n, v in params.items()},
        }
        if compare:
            out[cond]["paper"] = summarise(truth, est_p, sem_p)
    return out


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks estimator_efficiency")
    ap.add_argument("--cells", type=int, default=50, help="simulated subjects (replicates)")
    ap.add_argument(
        "--conditions", default="RT,BT18,BT12,BT8,BT5,PT", help="comma-separated, from NOMINAL"
    )
    ap.add_argument("--fs", type=float, default=1000.0, help="sample rate, Hz")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-compare", action="store_true", help="skip the paper-weighted fits")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes for the analysis")
    ap.add_argument("--scheduler", help="Dask scheduler address, or local[:N]")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    conditions = [c.strip() for c in a.conditions.split(",") if c.strip()]
    from steerlab.analysis.executors import executor_for

    with executor_for(a.scheduler, a.jobs) as ex:
        results = run_study(
            conditions, a.cells, a.fs, a.seed, not a.no_compare, executor=ex, jobs=a.jobs
        )
    return {
        "all_goals_met": all(all(r["goal_met"].values()) for r in results.values()),
        "cells_per_condition": a.cells,
        "fs_hz": a.fs,
        "seed": a.seed,
        "conditions": results,
        "wall_s": round(time.perf_counter() - t0, 1),
        **peak_rss_mb(),
        "machine": machine(),
    }
