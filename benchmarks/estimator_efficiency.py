"""How good are the per-subject arm estimates and their SEMs? A Monte-Carlo on known parameters.

Each Monte-Carlo *cell* is what the study analyses per subject × condition: two measured
repetitions of one 45-s period (after the protocol's 5-s run-in with its 1-s fade-in),
simulated by Steerlab's own world (``hardware.sim.world.World``: wheel rendering, remnant,
sensor noise and quantisation) with the **same** known arm parameters in both repetitions and in
every cell, only the noise seed changing. The cells go through ``analyze_study`` like real
data. For each parameter:

- ``bias_percent``: mean estimate / truth − 1; ``median_bias_percent`` likewise with the median
  (the estimates of the contact parameters have heavy tails);
- ``sd``: spread of the estimates; ``mean_sem``: mean reported SEM; ``sd_over_mean_sem``: near
  1 when the SEMs describe the real scatter; ``robust_sd_over_median_sem``: the same with
  1.4826·MAD and the median SEM, insensitive to the few wild estimates;
- ``coverage_95_percent``: share of cells whose estimate ± 1.96·SEM contains the truth (95 %
  for honest, normal errors).

Default: 50 cells (100 trials) for each of RT, BT12 and PT at the simulator's nominal values.

``inverse_variance`` (unless ``--no-compare``): the same cells fitted with weights 1/var(Ĥ_k)
(the variance measured at the unexcited bins) instead of the paper's coherence × 1/f. This is
exploratory, to show what the paper's weighting costs; it is done by handing ``fit_arm`` a
coherence of f·median(var)/var, so that its coherence × 1/f weights become ∝ 1/var. Steerlab's
analysis itself keeps the paper's weights.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from analysis.armfit import BOUNDS, fit_arm
from analysis.study import analyze_study
from benchmarks.machine import machine, peak_rss_mb
from hardware.sim.physiology import NOMINAL, ConditionBehaviour
from hardware.sim.world import World, WorldConfig
from protocols.perturbation import design_multisine
from protocols.records import TrialRecord

FREE = ("b_i", "k_i", "b_c", "k_c")
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
            "n_at_bound": at_bound,
        }
    return out


def _inverse_variance_fit(frf):
    v = np.asarray(frf.H_variance, dtype=float)
    coh = frf.frequencies_hz * np.nanmedian(v) / v  # fit_arm weights coh/f, so w ∝ 1/var
    return fit_arm(replace(frf, coherence=coh))


def run_condition(condition: str, cells: int, fs_hz: float, seed: int, compare: bool) -> dict:
    behaviour = NOMINAL[condition]
    design = design_multisine()
    records = []
    for c in range(cells):
        label = f"C{c:03d}"
        for rep in (1, 2):
            rec = simulate_trial(behaviour, design, fs_hz, [seed, c, rep], label, rep)
            rec.condition = condition
            records.append(rec)
    study = analyze_study(records)
    est = np.full((cells, len(FREE)), np.nan)
    sem = np.full((cells, len(FREE)), np.nan)
    est_iv = np.full_like(est, np.nan)
    sem_iv = np.full_like(sem, np.nan)
    failed = 0
    for i, r in enumerate(study.subject_conditions):
        if r.fit is None:
            failed += 1
            continue
        est[i] = [getattr(r.fit.params, n) for n in FREE]
        sem[i] = [r.fit.sems.get(n, np.nan) for n in FREE]
        if compare:
            f = _inverse_variance_fit(r.frf)
            est_iv[i] = [getattr(f.params, n) for n in FREE]
            sem_iv[i] = [f.sems.get(n, np.nan) for n in FREE]
    truth = {n: float(getattr(behaviour.arm, n)) for n in FREE}
    vaf = [r.vaf_percent for r in study.subject_conditions if r.vaf_percent is not None]
    out = {
        "cells": cells,
        "trials": 2 * cells,
        "fits_failed": failed,
        "median_vaf_percent": float(np.median(vaf)) if vaf else None,
        "parameters": summarise(truth, est, sem),
    }
    if compare:
        out["inverse_variance"] = summarise(truth, est_iv, sem_iv)
    return out


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks estimator_efficiency")
    ap.add_argument("--cells", type=int, default=50, help="subject × condition cells per condition")
    ap.add_argument("--conditions", default="RT,BT12,PT", help="comma-separated, from NOMINAL")
    ap.add_argument("--fs", type=float, default=1000.0, help="sample rate, Hz")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--no-compare", action="store_true", help="skip the inverse-variance-weighted fits"
    )
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    conditions = [c.strip() for c in a.conditions.split(",") if c.strip()]
    results = {c: run_condition(c, a.cells, a.fs, a.seed, not a.no_compare) for c in conditions}
    return {
        "cells_per_condition": a.cells,
        "fs_hz": a.fs,
        "seed": a.seed,
        "conditions": results,
        "wall_s": round(time.perf_counter() - t0, 1),
        **peak_rss_mb(),
        "machine": machine(),
    }
