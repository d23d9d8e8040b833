"""Time-varying admittance: every tracker on the same simulated trials, scored against the truth.

Per simulated subject (``protocols/tracking.toml``, the simulated rig through its batch loop,
exactly as ``steerlab simulate`` runs it):

1. the six stationary conditions, one 96-s trial each, calibrate every tracker (per-subject arm
   fits → the grip-scheduled LPV model, and the remnant model);
2. the time-varying trials, SWITCH (the boundary jumps every 10–18 s) and RAMP (it moves over
   5 s), are tracked by every estimator of :func:`analysis.tracking.default_estimators`: the
   LPV model, sliding-window FRF (10 s and 5 s), RLS with forgetting (1.5 s), Morlet wavelets
   (5 and 3 cycles), and ours (grip-informed Kalman filter).

Scores (:mod:`analysis.tracking.metrics`) from 15 s into each trial (past the 5-s run-in and the
first 10-s window) to its end: VAF of the wheel angle (output-error simulation of the tracked
parameters), RMS error and bias of log k_i against the simulated truth, settling time after
each step of SWITCH (within ±15 % of the true k_i for 2 s, for steps of more than 30 %; and the
strict version, within the band until the next step).

Writes ``docs/tracking.png`` (``--figure``) and prints one JSON object (the runner adds it).
The evaluation subjects are seeded apart from the ones used while tuning (``--seed``).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from steerlab.analysis.tracking import (
    Calibration,
    TrackingTrial,
    default_estimators,
    score,
)
from steerlab.analysis.tracking.metrics import StepSettling
from steerlab.benchmarks.machine import machine
from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.rig import SimulatedSubject, simulated_rig
from steerlab.hardware.sim.world import TRUTH_CHANNELS, WorldConfig
from steerlab.protocols.engine import LoopControl
from steerlab.protocols.protocol import Protocol, load_protocol
from steerlab.protocols.records import TrialRecord
from steerlab.protocols.session import ConditionSchedule, build_plan

ROOT = Path(__file__).resolve().parents[1]
PROTOCOL = ROOT / "protocols" / "tracking.toml"
SCORE_FROM_S = 15.0
EVAL_SEED = 2024  # the tuning used seeds 1 and 7: never these subjects


def simulate_subject(
    protocol: Protocol,
    subject_number: int,
    seed: int,
    conditions: Sequence[str] | None = None,
    tau_s: float = 0.2,
) -> list[TrialRecord]:
    """One simulated subject's trials of ``conditions`` (default all), as records."""
    phys = make_population(subject_number, seed=seed)[subject_number - 1]
    rig = simulated_rig(phys, WorldConfig(fs_hz=protocol.loop_rate_hz), protocol.wheel)
    rig.subject = SimulatedSubject(phys, adaptation_tau_s=tau_s, grip_adaptation_tau_s=tau_s)
    plan = build_plan(protocol, subject_number)
    wanted = set(conditions or protocol.condition_names)
    out = []
    for spec in plan.trials:
        if spec.condition not in wanted or spec.familiarization:
            continue
        setup = plan.setup(spec)
        blocks = list(rig.batch_loop().run_trial(setup, LoopControl()))
        d = {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}
        attrs: dict[str, float | str] = {"run_in_s": protocol.trial.run_in_s}
        if setup.schedule is not None:
            attrs["schedule"] = json.dumps(setup.schedule.to_dict())
        out.append(
            TrialRecord(
                subject=plan.subject,
                condition=spec.condition,
                repetition=spec.repetition,
                familiarization=False,
                fs_hz=setup.fs_hz,
                time_s=d["time_s"],
                perturbation_torque_Nm=d["perturbation_torque_Nm"],
                driver_torque_Nm=d["driver_torque_Nm"],
                wheel_angle_rad=d["wheel_angle_rad"],
                grip_force_N=d["grip_force_N"],
                trial_index=spec.trial_index,
                measured_start=setup.measured_start,
                measured_stop=setup.measured_stop,
                design=plan.design,
                boundary_deg=spec.boundary_deg,
                extra={c: d[c] for c in TRUTH_CHANNELS if c in d},
                attrs=attrs,
                source=f"sim:{plan.subject}/{setup.key}",
            )
        )
    return out


def run_subject(protocol: Protocol, number: int, seed: int, estimators=None) -> dict:
    """Calibrate on the stationary trials, track the time-varying ones, score."""
    recs = simulate_subject(protocol, number, seed)
    stationary = [r for r in recs if not r.time_varying]
    varying = [r for r in recs if r.time_varying]
    cal = Calibration.from_records(stationary)
    ests = estimators if estimators is not None else default_estimators()
    for e in ests:
        e.calibrate(cal)
    results = []
    for rec in varying:
        trial = TrackingTrial.from_record(rec)
        tracks = {e.name: e.track(trial) for e in ests}
        scores = {n: score(trial, t, from_s=SCORE_FROM_S) for n, t in tracks.items()}
        # The scored steps are the truth's, the same for every tracker: take any's.
        steps = next(iter(scores.values())).steps
        ok = lpv_ok(trial, cal, steps)
        results.append({"trial": trial, "tracks": tracks, "scores": scores, "lpv_ok": ok})
    return {"calibration": cal, "results": results}


def simulated_truth(trial: TrackingTrial) -> tuple[ConditionSchedule, Mapping[str, np.ndarray]]:
    """(schedule, true parameters) of a simulated time-varying trial."""
    if trial.schedule is None or trial.truth is None:
        raise ValueError(f"trial {trial.label!r}: no schedule or truth (not simulated here?)")
    return trial.schedule, trial.truth


def lpv_ok(
    trial: TrackingTrial, cal: Calibration, steps: list[StepSettling], tol: float = 0.15
) -> list[bool]:
    """Per scored step (:func:`analysis.tracking.score`'s): is the calibrated LPV model right
    about the new task (its k_i at the true grip mean within ±tol of the true k_i at the
    segment's end)? Where it is not, no grip-based tracker can be right at once; the
    perturbation must correct it."""
    grip = trial.truth_grip
    if grip is None:
        raise ValueError(f"trial {trial.label!r}: no true grip mean (not simulated here?)")
    out = []
    for st in steps:
        end = int(round((st.time_s + st.segment_s) * trial.fs_hz)) - 1
        mu = grip[end]
        out.append(abs(math.log(cal.prior(mu)[1] / st.k_i_to)) <= math.log(1 + tol))
    return out


def summarise(all_scores: list[dict], names: list[str], ok: list[list[bool]]) -> dict:
    """Per estimator over all trials: mean VAF, RMS log k_i, bias, settling (SWITCH steps)."""
    out = {}
    for n in names:
        sc = [s[n] for s in all_scores]
        steps = [st for s in sc for st in s.steps]
        vals = [st.settling_or_segment_s for st in steps]
        settled = [st.settling_s for st in steps if st.settling_s is not None]
        strict = [
            st.strict_settling_s if st.strict_settling_s is not None else st.segment_s
            for st in steps
        ]
        out[n] = {
            "causal": sc[0].causal,
            "vaf_percent_mean": float(np.mean([s.vaf_percent for s in sc])),
            "vaf_percent_min": float(np.min([s.vaf_percent for s in sc])),
            "rms_log_k_i_mean": float(np.mean([s.rms_log_k_i for s in sc])),
            "rms_log_k_c_mean": float(np.mean([s.rms_log["k_c"] for s in sc])),
            "bias_k_i_percent_mean": float(np.mean([s.bias_k_i_percent for s in sc])),
            "settling_median_s": float(np.median(vals)) if vals else None,
            "settling_p90_s": float(np.percentile(vals, 90)) if vals else None,
            "settled_fraction": len(settled) / len(steps) if steps else None,
            "strict_settling_median_s": float(np.median(strict)) if strict else None,
            # Split by whether the calibrated LPV model was right about the new task.
            "settling_median_s_lpv_right": _median_where(sc, ok, True),
            "settling_median_s_lpv_wrong": _median_where(sc, ok, False),
            "within_0_5_s_fraction": (sum(v <= 0.5 for v in vals) / len(vals) if vals else None),
            "within_0_5_s_fraction_lpv_right": _fraction_where(sc, ok, True, 0.5),
            "n_steps": len(steps),
            "compute_s_per_trial": float(np.mean([s.compute_s for s in sc])),
        }
    return out


def _median_where(scores: list, ok: list[list[bool]], want: bool) -> float | None:
    vals = [
        st.settling_or_segment_s
        for s, flags in zip(scores, ok, strict=True)
        for st, f in zip(s.steps, flags, strict=True)
        if f == want
    ]
    return float(np.median(vals)) if vals else None


def _fraction_where(scores: list, ok: list[list[bool]], want: bool, limit: float) -> float | None:
    vals = [
        st.settling_s is not None and st.settling_s <= limit
        for s, flags in zip(scores, ok, strict=True)
        for st, f in zip(s.steps, flags, strict=True)
        if f == want
    ]
    return sum(vals) / len(vals) if vals else None


def table(summary: dict) -> str:
    """The summary as a Markdown table (docs/benchmarks.md)."""
    rows = [
        "| estimator | causal | VAF % (mean / min) | RMS log k_i | bias k_i | RMS log k_c "
        "| settling median / p90 (s) | settled | settled ≤ 0.5 s (all / LPV right) "
        "| settling median, LPV right / wrong (s) | strict settling median (s) "
        "| compute s/trial |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for n, v in summary.items():
        rows.append(
            f"| {n} | {'yes' if v['causal'] else 'no'} "
            f"| {v['vaf_percent_mean']:.1f} / {v['vaf_percent_min']:.1f} "
            f"| {v['rms_log_k_i_mean']:.3f} | {v['bias_k_i_percent_mean']:+.1f} % "
            f"| {v['rms_log_k_c_mean']:.3f} "
            f"| {v['settling_median_s']:.2f} / {v['settling_p90_s']:.2f} "
            f"| {100 * v['settled_fraction']:.0f} % "
            f"| {100 * v['within_0_5_s_fraction']:.0f} / "
            f"{100 * v['within_0_5_s_fraction_lpv_right']:.0f} % "
            f"| {_f(v['settling_median_s_lpv_right'])} / {_f(v['settling_median_s_lpv_wrong'])} "
            f"| {v['strict_settling_median_s']:.2f} "
            f"| {v['compute_s_per_trial']:.2f} |"
        )
    return "\n".join(rows)


def _f(v: float | None) -> str:
    return "–" if v is None else f"{v:.2f}"


def figure(result: dict, path: Path) -> None:
    """k_i over time for every tracker on one SWITCH and one RAMP trial, with the truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = result["results"]
    fig, axes = plt.subplots(len(res), 1, figsize=(13, 3.6 * len(res)), squeeze=False)
    styles = {
        "lpv": ("#1f77b4", "-"),
        "sliding_window_10s": ("#ff7f0e", "-"),
        "sliding_window_5s": ("#ff7f0e", ":"),
        "rls_1.5s": ("#2ca02c", "-"),
        "wavelet_5cyc": ("#9467bd", "-"),
        "wavelet_3cyc": ("#9467bd", ":"),
        "grip_ekf": ("#d62728", "-"),
    }
    for ax, r in zip(axes[:, 0], res, strict=True):
        tr: TrackingTrial = r["trial"]
        sch, truth = simulated_truth(tr)
        t = tr.time_s
        ax.plot(t, truth["k_i"], color="k", lw=2.2, label="truth")
        for n, trk in r["tracks"].items():
            k = np.where(trk.valid, trk.params["k_i"], np.nan)
            sc = r["scores"][n]
            colour, ls = styles.get(n, ("0.5", "-"))
            ax.plot(
                t, k, lw=1.6 if n == "grip_ekf" else 0.9, color=colour, ls=ls,
                label=f"{n} (VAF {sc.vaf_percent:.1f} %, RMS log k_i {sc.rms_log_k_i:.2f})",
            )  # fmt: skip
        ax.set_yscale("log")
        ax.set_xlim(SCORE_FROM_S - 5, t[-1])
        ax.set_ylabel("k_i (N·m/rad)")
        ax.set_title(f"{tr.label}: {sch.name} ({sch.transition})", fontsize=10)
        lo = SCORE_FROM_S - 5
        for k0, c in zip(sch.starts, sch.conditions, strict=True):
            x = max(k0 / tr.fs_hz, lo)
            ax.axvline(x, color="0.8", lw=0.8)
            ax.text(x + 0.3, ax.get_ylim()[1] * 0.8, c, fontsize=7, color="0.4")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[-1, 0].set_xlabel("time in trial (s)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks tracking")
    ap.add_argument("--subjects", type=int, default=6)
    ap.add_argument("--seed", type=int, default=EVAL_SEED)
    ap.add_argument("--protocol", default=str(PROTOCOL))
    ap.add_argument("--figure", default=str(ROOT / "docs" / "tracking.png"))
    ap.add_argument("--no-figure", action="store_true")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    protocol = load_protocol(a.protocol)
    all_scores, per_trial, oks, first = [], [], [], None
    for number in range(1, a.subjects + 1):
        res = run_subject(protocol, number, a.seed)
        first = first or res
        for r in res["results"]:
            all_scores.append(r["scores"])
            oks.append(r["lpv_ok"])
            per_trial.append({n: s.to_dict() for n, s in r["scores"].items()})
    names = list(all_scores[0])
    if not a.no_figure and first is not None:
        figure(first, Path(a.figure))
    summary = summarise(all_scores, names, oks)
    print(table(summary))
    return {
        "subjects": a.subjects,
        "seed": a.seed,
        "trials": len(all_scores),
        "score_from_s": SCORE_FROM_S,
        "summary": summary,
        "per_trial": per_trial,
        "steps_lpv_right": sum(sum(o) for o in oks),
        "steps_lpv_wrong": sum(len(o) - sum(o) for o in oks),
        "wall_s": round(time.perf_counter() - t0, 1),
        "machine": machine(),
    }
