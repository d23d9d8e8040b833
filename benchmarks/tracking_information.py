"""How fast can the perturbation response alone pin k_i? (an upper bound for issue 7's settling).

On the SWITCH trials of simulated subjects (as ``python -m benchmarks tracking``), Steerlab's
Kalman filter is told the *true* arm at every sample, except that 1 s after each step of the
task the log offset of k_i gets a broad prior (SD 1, i.e. a factor e) and, with ``--others
SD``, the other three parameters' offsets a prior of that SD around their truth. What the
filter then knows of k_i after T seconds comes from the perturbation response only. Printed
per T: the RMS error of log k_i, the filter's own SD, and the fraction of segments within
±15 % (the settling band). A best case: a tracker never knows the other parameters this well.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from steerlab.analysis.tracking import Calibration, TrackingTrial
from steerlab.analysis.tracking.base import TRACKED
from steerlab.analysis.tracking.kalman import X_D, EKFConfig, KalmanCore
from steerlab.benchmarks.machine import machine
from steerlab.benchmarks.tracking import PROTOCOL, simulate_subject, simulated_truth
from steerlab.protocols.protocol import load_protocol

TIMES_S = (0.25, 0.5, 1.0, 2.0, 4.0)
# No random walk, no relaxation, no shrinkage: the offsets are constants to be learnt.
FIXED = EKFConfig(q_delta=(0, 0, 0, 0), p0_delta=1e-10, p_reset=(0, 0, 0, 0), shrink=0.0)


def segments(
    trial: TrackingTrial, cal: Calibration, others_sd: float, k_i_offset: float = 0.0
) -> list[tuple]:
    """(T, error of log k_i, filter SD) for every T after every step of one trial. With
    ``k_i_offset`` the filter's k_i is the truth times e^offset (a wrong start to recover)."""
    core = KalmanCore(cal, trial.fs_hz, FIXED)
    core.coef[:] = 0.0  # the prior is a constant polynomial: the truth, set per sample below
    fs = trial.fs_hz
    schedule, true_params = simulated_truth(trial)
    truth = np.stack([true_params[p] for p in TRACKED], axis=1)
    starts = {int(s + fs) for s in schedule.starts[1:]}
    marks = {s + int(t * fs): t for s in starts for t in TIMES_S}
    rows = []
    for k in range(trial.n):
        core.coef[:, -1] = truth[k]
        core.coef[1, -1] *= math.exp(k_i_offset)
        if k in starts:
            core.x[X_D:] = 0.0
            core.P[X_D:, :] = 0.0
            core.P[:, X_D:] = 0.0
            for i in range(4):
                core.P[X_D + i, X_D + i] = max(others_sd**2, 1e-10)
            core.P[X_D + 1, X_D + 1] = 1.0
        # A constant grip: no change of task is seen, nothing relaxes.
        core.update(trial.perturbation_Nm[k], trial.driver_torque_Nm[k], trial.angle_rad[k], 100.0)
        if k in marks:
            err = core.x[X_D + 1] + k_i_offset
            rows.append((marks[k], err, math.sqrt(core.P[X_D + 1, X_D + 1])))
    return rows


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks tracking_information")
    ap.add_argument("--subjects", type=int, default=4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--others", type=float, default=0.0, help="prior SD of the other offsets")
    a = ap.parse_args(argv)
    protocol = load_protocol(PROTOCOL)
    rows = []
    for number in range(1, a.subjects + 1):
        recs = simulate_subject(protocol, number, a.seed)
        cal = Calibration.from_records([r for r in recs if not r.time_varying])
        for rec in recs:
            trial = TrackingTrial.from_record(rec)
            if trial.schedule is not None and trial.schedule.transition == "step":
                rows += segments(trial, cal, a.others)
    r = np.array(rows)
    out = {}
    for t in TIMES_S:
        m = r[:, 0] == t
        err = r[m, 1]
        out[f"{t:g}s"] = {
            "segments": int(m.sum()),
            "rms_log_k_i": float(np.sqrt(np.mean(err**2))),
            "filter_sd_log_k_i": float(np.mean(r[m, 2])),
            "within_15_percent": float(np.mean(np.abs(err) < math.log(1.15))),
        }
        print(f"T = {t:4.2f} s: {out[f'{t:g}s']}")
    return {"subjects": a.subjects, "seed": a.seed, "others_sd": a.others, "by_time": out,
            "machine": machine()}  # fmt: skip
