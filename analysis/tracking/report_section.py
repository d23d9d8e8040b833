"""The report's tracking section: only for studies with time-varying trials.

Per subject, the trackers are calibrated on that subject's stationary trials
(:meth:`Calibration.from_records`) and run on each of the subject's time-varying trials. The
report runs the two trackers the live panel can use, the paper's LPV model and ours
(``REPORT_TRACKERS``); the full comparison with the perturbation-based rivals is
``python -m benchmarks tracking``. With no truth in measured data, the score is the VAF of the
wheel angle (the tracked parameters driven by the measured torque); simulated sessions read
with their truth channels also get the RMS error of log k_i.

``results.json`` gets a ``tracking`` key (docs/results.md): a group calibration for the live
tracker (:meth:`analysis.tracking.online.OnlineTracker.from_results` reads it) and one entry
per trial.
"""

from __future__ import annotations

import html
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from steerlab.analysis.tracking.base import (
    TrackedAdmittance,
    TrackingEstimator,
    TrackingTrial,
    is_time_varying,
)
from steerlab.analysis.tracking.calibration import Calibration, CalibrationError, Disturbance
from steerlab.analysis.tracking.kalman import GripInformedEKF
from steerlab.analysis.tracking.metrics import TrackingScore, score
from steerlab.analysis.tracking.scheduled import GripScheduledLPV
from steerlab.protocols.records import TrialRecord

REPORT_TRACKERS = ("lpv", "grip_ekf")
SCORE_FROM_S = 15.0


@dataclass
class TrialTracking:
    subject: str
    source: str
    schedule: dict[str, Any]
    trial: TrackingTrial
    tracks: dict[str, TrackedAdmittance]
    scores: dict[str, TrackingScore]

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "subject": self.subject,
            "trial": self.source,
            "schedule": self.schedule,
            "trackers": {},
        }
        for n, s in self.scores.items():
            k = self.tracks[n].params["k_i"]
            med, frac = s.settling_summary()
            out["trackers"][n] = {
                "vaf_percent": s.vaf_percent,
                "k_i_median_Nm_per_rad": float(np.median(k)),
                "k_i_range_Nm_per_rad": [float(np.percentile(k, 5)), float(np.percentile(k, 95))],
                "rms_log_k_i": s.rms_log_k_i,
                "bias_k_i_percent": s.bias_k_i_percent,
                "settling_median_s": med,
                "settled_fraction": frac,
            }
        return out


@dataclass
class TrackingReport:
    trials: list[TrialTracking]
    calibrations: dict[str, Calibration]
    problems: list[str] = field(default_factory=list)

    def group_disturbance(self) -> Disturbance:
        ds = [c.disturbance for c in self.calibrations.values()]
        if not ds:
            return Disturbance()
        m = np.median([list(vars(d).values()) for d in ds], axis=0)
        return Disturbance(*(float(v) for v in m))

    def to_dict(self) -> dict[str, Any]:
        return {
            "trackers": list(REPORT_TRACKERS),
            "score_from_s": SCORE_FROM_S,
            "calibration": {"disturbance": self.group_disturbance().to_dict()},
            "subject_calibrations": {s: c.to_dict() for s, c in self.calibrations.items()},
            "trials": [t.to_dict() for t in self.trials],
            "problems": list(self.problems),
        }


def analyse_tracking(records: Sequence[TrialRecord]) -> TrackingReport | None:
    """None when no record is a (complete, measured) time-varying trial."""
    # Driving trials vary too, but have a section of their own (analysis.driving_report).
    varying = [r for r in records if is_time_varying(r) and r.usable and not r.driving]
    if not varying:
        return None
    stationary = [r for r in records if not is_time_varying(r) and r.usable]
    out = TrackingReport([], {})
    for subject in sorted({r.subject for r in varying}):
        own = [r for r in stationary if r.subject == subject]
        try:
            cal = Calibration.from_records(own, source=f"{subject}'s stationary trials")
        except (CalibrationError, ValueError) as e:
            out.problems.append(f"{subject}: not tracked: {e}")
            continue
        out.calibrations[subject] = cal
        trackers: list[TrackingEstimator] = [GripScheduledLPV(), GripInformedEKF()]
        for t in trackers:
            t.calibrate(cal)
        for rec in (r for r in varying if r.subject == subject):
            trial = TrackingTrial.from_record(rec)
            tracks = {t.name: t.track(trial) for t in trackers}
            out.trials.append(
                TrialTracking(
                    subject,
                    rec.source or rec.label(),
                    trial.schedule.to_dict() if trial.schedule else {},
                    trial,
                    tracks,
                    {n: score(trial, tr, from_s=SCORE_FROM_S) for n, tr in tracks.items()},
                )
            )
    return out


def figure(rep: TrackingReport):
    """k_i over time in the first tracked trial: both trackers, the truth if known."""
    if not rep.trials:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = rep.trials[0]
    fig, ax = plt.subplots(figsize=(10, 3.4))
    time = t.trial.time_s
    if t.trial.truth is not None:
        ax.plot(time, t.trial.truth["k_i"], color="k", lw=2, label="truth (simulated)")
    for n, colour in zip(REPORT_TRACKERS, ("#1f77b4", "#d62728"), strict=True):
        ax.plot(time, t.tracks[n].params["k_i"], color=colour, lw=1.2, label=n)
    if t.trial.schedule is not None:
        sch = t.trial.schedule
        for k0, c in zip(sch.starts, sch.conditions, strict=True):
            ax.axvline(k0 / t.trial.fs_hz, color="0.85", lw=0.8)
            ax.text(k0 / t.trial.fs_hz + 0.3, 0.92, c, fontsize=7, color="0.4",
                    transform=ax.get_xaxis_transform())  # fmt: skip
    ax.set_yscale("log")
    ax.set_xlabel("time in trial (s)")
    ax.set_ylabel("k_i (N·m/rad)")
    ax.set_title(f"{t.source}", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def html_section(rep: TrackingReport, image_uri: str | None) -> str:
    """The section for index.html (cells escaped here)."""

    def num(v: float | None, fmt: str) -> str:
        return "–" if v is None or not np.isfinite(v) else format(v, fmt)

    rows = []
    for t in rep.trials:
        for n in REPORT_TRACKERS:
            s = t.scores[n]
            med, _ = s.settling_summary()
            k = t.tracks[n].params["k_i"]
            rows.append(
                "<tr>"
                + "".join(
                    f'<td class="{c}">{v}</td>'
                    for c, v in (
                        ("l", html.escape(t.source)),
                        ("l", html.escape(n)),
                        ("", num(s.vaf_percent, ".1f")),
                        ("", f"{np.percentile(k, 5):.1f}–{np.percentile(k, 95):.1f}"),
                        ("", num(s.rms_log_k_i, ".3f")),
                        ("", num(s.bias_k_i_percent, "+.1f")),
                        ("", num(med, ".2f")),
                    )
                )
                + "</tr>"
            )
    head = "".join(
        f'<th class="{c}">{h}</th>'
        for c, h in (
            ("l", "trial"),
            ("l", "tracker"),
            ("", "VAF %"),
            ("", "k_i 5–95 % (N·m/rad)"),
            ("", "RMS log k_i"),
            ("", "bias k_i %"),
            ("", "settling median (s)"),
        )
    )
    fig = (
        f'<figure><img alt="tracking" src="{image_uri}"><figcaption>Intrinsic stiffness k_i '
        "over the first time-varying trial; grey lines: the task changes.</figcaption></figure>"
        if image_uri
        else ""
    )
    problems = "".join(f"<li>{html.escape(p)}</li>" for p in rep.problems)
    return (
        '<h2 id="tracking">Time-varying trials: tracked admittance</h2>'
        "<p>Trials whose task changed within the trial are not in the stationary analysis "
        "above. Per subject, the trackers are calibrated on that subject's stationary trials: "
        "<b>lpv</b> is the paper's grip-scheduled LPV model; <b>grip_ekf</b> is Steerlab's "
        "tracker, the LPV prediction corrected by the perturbation response (a Kalman filter "
        "on the arm model; see analysis/tracking). VAF: the tracked parameters driven by the "
        f"measured driver torque against the measured angle, from {SCORE_FROM_S:g} s into "
        "the trial. RMS error, bias and settling need the truth (simulated trials read with "
        "their truth channels) and are blank otherwise. Every rival tracker is compared in "
        "<code>python -m benchmarks tracking</code> (docs/benchmarks.md).</p>"
        + fig
        + f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"
        + (f"<ul>{problems}</ul>" if problems else "")
    )
