"""The drift test's false alarms and power on simulated per-trial stiffnesses.

The diagnosis judges drift on each trial's fitted k_i and k_c (``analysis/diagnosis/drift.py``).
This draws such stiffnesses without and with drift and counts how often drift is retained, at
thresholds around the default (``drift.MIN_DBIC``): the figures behind the threshold's choice
in docs/diagnosis.md ("Drift"), reproducible.

Designs: 1 or 2 subjects × 2 conditions (BT12, PT: 4 or 8 trials) or × 3 (RT, BT12, PT: 6 or
12 trials; with one subject ν = 2 or 3, below ``drift.MIN_DOF``: not judged), two
repetitions back to back, conditions in a random order per subject, no familiarization trial
(as the independent world's studies); log-normal scatter of one SD for every condition, or
1, 2 and 4 % by condition (stiff conditions scatter more). Effects: none; k_i × 1.3 from trial
4 on (k_c unchanged; the step shows inside one condition per subject); k_i and k_c × (1 + 0.04
(i − 1)).

Usage: ``python -m benchmarks drift_calibration [--sessions N] [--thresholds 6 8 10]
[--likelihood restricted|profiled]``. ``profiled`` is the likelihood with n in place of the
residual degrees of freedom (the one used before 2026-11-26), for comparison. About 3 CPU
minutes at the defaults (200 sessions).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from steerlab.benchmarks.machine import machine

K0 = {"RT": (30.0, 120.0), "BT12": (70.0, 190.0), "PT": (300.0, 400.0)}  # k_i, k_c (N·m/rad)
# name → (conditions, subjects)
DESIGNS = {
    "4 trials (1 subject)": (("BT12", "PT"), 1),
    "6 trials (1 subject)": (("RT", "BT12", "PT"), 1),
    "8 trials": (("BT12", "PT"), 2),
    "12 trials": (("RT", "BT12", "PT"), 2),
}
SCATTERS = {"2 %": {c: 0.02 for c in K0}, "1/2/4 % by condition": {"RT": 0.01, "BT12": 0.02,
                                                                   "PT": 0.04}}  # fmt: skip
EFFECTS = {
    "none": (lambda i: 1.0, False),
    "k_i x 1.3 from trial 4": (lambda i: 1.3 if i >= 4 else 1.0, True),
    "linear 4 %/trial": (lambda i: 1.0 + 0.04 * (i - 1), False),
}


def stiffness_rows(factor, seed: int, conditions, sds: dict, ki_alone: bool, subjects: int = 2):
    from steerlab.analysis.diagnosis.drift import TrialStiffness

    rng = np.random.default_rng(seed)
    rows = []
    for s in range(subjects):
        ti = 0
        for c in rng.permutation(list(conditions)):
            for rep in (1, 2):
                ti += 1
                f = factor(ti)
                ki = K0[c][0] * f * np.exp(sds[c] * rng.standard_normal())
                kc = K0[c][1] * (1.0 if ki_alone else f) * np.exp(sds[c] * rng.standard_normal())
                rows.append(TrialStiffness(f"S{s}_{ti}", (f"S{s}", str(c)), ti, rep, ki, kc))
    return rows


def main(argv: list[str]) -> dict:
    from steerlab.analysis.diagnosis import drift

    ap = argparse.ArgumentParser(prog="python -m benchmarks drift_calibration")
    ap.add_argument("--sessions", type=int, default=200, help="sessions per line")
    ap.add_argument("--thresholds", type=float, nargs="*", default=[6.0, 8.0, 10.0])
    ap.add_argument("--likelihood", choices=("restricted", "profiled"), default="restricted")
    a = ap.parse_args(argv)
    profiled = a.likelihood == "profiled"  # as before 2026-11-26: no MIN_DOF either
    if profiled:
        # n in place of ν = n − cells: the likelihood profiled over the cell means.
        setattr(drift, "_dof", len)  # noqa: B010 (a module's function, swapped for a benchmark)
    t0 = time.process_time()
    lines = []
    for dname, (conds, subjects) in DESIGNS.items():
        for sname, sds in SCATTERS.items():
            for ename, (factor, ki_alone) in EFFECTS.items():
                res = [
                    drift.analyse_drift(
                        stiffness_rows(factor, s, conds, sds, ki_alone, subjects=subjects)
                    )
                    for s in range(a.sessions)
                ]
                # Retained at threshold T: ΔBIC < −T and a positive leave-one-out gain (the
                # default's rule with MIN_DBIC = T).
                passed = {
                    f"{t:g}": sum(
                        1
                        for r in res
                        if r is not None
                        and r.delta_bic < -t
                        and (r.held_out_gain or 0) > 0
                        and (profiled or r.n_trials - r.n_cells >= drift.MIN_DOF)
                    )
                    for t in a.thresholds
                }
                lines.append(
                    {"design": dname, "scatter": sname, "effect": ename, "retained": passed}
                )
                print(dname, "|", sname, "|", ename, "|", passed, flush=True)
    return {
        "likelihood": a.likelihood,
        "sessions_per_line": a.sessions,
        "default_threshold": drift.MIN_DBIC,
        "lines": lines,
        "cpu_s": time.process_time() - t0,
        "machine": machine(),
    }
