"""The report's driving section: admittance along the road from grip force alone (issue 19).

Per subject, the paper's grip-scheduled LPV model is calibrated on that subject's boundary
tasks (:meth:`analysis.tracking.Calibration.from_records`) and run on each drive from the grip
force alone (``lpv``): that is the estimate the paper's closing sentence asks for, obtained
without a perturbation. Where the drive has the perturbation on, two perturbation-based
trackers run on the same drive and validate it over time: the sliding-window FRF
(``sliding_window_10s``, LTI in each 10-s window, the perturbation as instrument) and
Steerlab's grip-informed Kalman filter (``grip_ekf``). Simulated drives read with their truth
channels are also scored against the truth (RMS of log k_i, bias).

Admittance is summarised as the arm's static compliance 1/k_i + 1/k_c (rad/N·m, the
admittance at 0 Hz); grip is the measured total grip force (N). How road width (the narrow
and wide sections within each drive), speed and friction (the drive conditions) change them:
repeated-measures ANOVA over subjects (:func:`analysis.stats.rm_anova`), one factor at a time,
the other factors averaged within each subject.

Perturbation-based estimates in driving are not the truth either: the driver's steering and
the vehicle's aligning torque respond to the perturbation (through the car), so below about
0.5 Hz the torque the hands feel is no longer independent of the driver. Their agreement with
the LPV estimate is reported, not assumed.
"""

from __future__ import annotations

import html
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from steerlab.analysis.stats import rm_anova
from steerlab.analysis.tracking.base import TRUTH_KEYS, TrackedAdmittance, TrackingTrial
from steerlab.analysis.tracking.calibration import Calibration, CalibrationError
from steerlab.analysis.tracking.kalman import GripInformedEKF
from steerlab.analysis.tracking.metrics import score
from steerlab.analysis.tracking.scheduled import GripScheduledLPV
from steerlab.analysis.tracking.sliding_window import SlidingWindowFRF
from steerlab.hardware.vehicle import DRIVING_CHANNELS
from steerlab.protocols.datafile import SessionFile
from steerlab.protocols.records import TrialRecord

LPV = "lpv"
VALIDATORS = ("sliding_window_10s", "grip_ekf")
SCORE_FROM_S = 15.0  # the sliding window needs its first window; the same span for all
DECIMATE_HZ = 10.0  # the per-drive series kept for the figure and results.json


def _validators() -> list:
    return [SlidingWindowFRF(window_s=10.0), GripInformedEKF()]


def static_compliance(tr: TrackedAdmittance | Mapping[str, np.ndarray]) -> np.ndarray:
    """1/k_i + 1/k_c per sample, rad/(N·m)."""
    p = tr.params if isinstance(tr, TrackedAdmittance) else tr
    return 1.0 / np.asarray(p["k_i"]) + 1.0 / np.asarray(p["k_c"])


@dataclass
class DriveAnalysis:
    """One drive: where it went, what grip and the trackers say along the road."""

    subject: str
    condition: str
    source: str
    speed_mps: float
    friction: float
    perturbation_level: float
    # Per section ("narrow", "wide"): mean grip (N), LPV compliance, true compliance (or nan).
    sections: dict[str, dict[str, float]]
    # Tracker → {"rms_log_k_i", "bias_k_i_percent"} against the truth (simulated drives).
    vs_truth: dict[str, dict[str, float | None]]
    # Validator → {"rms_log_k_i", "bias_k_i_percent"} of the LPV estimate against it.
    lpv_vs_validator: dict[str, dict[str, float]]
    lane_departure_percent: float
    series: dict[str, np.ndarray] = field(default_factory=dict)  # decimated, for the figure

    def to_dict(self) -> dict[str, Any]:
        return {
            "subject": self.subject,
            "condition": self.condition,
            "trial": self.source,
            "speed_mps": self.speed_mps,
            "friction": self.friction,
            "perturbation_level": self.perturbation_level,
            "sections": self.sections,
            "vs_truth": self.vs_truth,
            "lpv_vs_validator": self.lpv_vs_validator,
            "lane_departure_percent": self.lane_departure_percent,
            "series_10Hz": {k: v.tolist() for k, v in self.series.items()},
        }


@dataclass
class DrivingReport:
    drives: list[DriveAnalysis]
    stats: dict[str, dict[str, Any]]  # factor → dv → rm_anova result (dict)
    problems: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "units": {
                "compliance": "rad/(N·m), static: 1/k_i + 1/k_c",
                "grip": "N, total of both hands",
                "k_i": "N·m/rad",
            },
            "drives": [d.to_dict() for d in self.drives],
            "statistics": self.stats,
            "problems": list(self.problems),
            "summary": self.summary(),
        }

    def summary(self) -> dict[str, Any]:
        """Median over drives of each tracker's error against the truth and of the LPV's
        disagreement with each validator."""
        out: dict[str, Any] = {}
        for name in (LPV, *VALIDATORS):
            vals = [d.vs_truth[name] for d in self.drives if name in d.vs_truth]
            rms = [v["rms_log_k_i"] for v in vals if v["rms_log_k_i"] is not None]
            bias = [v["bias_k_i_percent"] for v in vals if v["bias_k_i_percent"] is not None]
            if rms:
                out[f"{name}_vs_truth"] = {
                    "median_rms_log_k_i": float(np.median(rms)),
                    "median_bias_k_i_percent": float(np.median(bias)),
                    "drives": len(rms),
                }
        for name in VALIDATORS:
            pairs = [d.lpv_vs_validator[name] for d in self.drives if name in d.lpv_vs_validator]
            if pairs:
                out[f"lpv_vs_{name}"] = {
                    "median_rms_log_k_i": float(np.median([v["rms_log_k_i"] for v in pairs])),
                    "median_bias_k_i_percent": float(
                        np.median([v["bias_k_i_percent"] for v in pairs])
                    ),
                    "drives": len(pairs),
                }
        return out


def _driving_attrs(rec: TrialRecord) -> dict[str, Any]:
    a = rec.attrs.get("driving")
    return json.loads(a) if isinstance(a, str) else dict(a or {})


def _log_error(est: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    e = np.log(est) - np.log(ref)
    return {
        "rms_log_k_i": float(np.sqrt(np.mean(e**2))),
        "bias_k_i_percent": float(100.0 * (math.exp(np.mean(e)) - 1.0)),
    }


def analyse_drive(rec: TrialRecord, cal: Calibration, keep_series: bool = True) -> DriveAnalysis:
    """One drive: the LPV estimate from grip, the validators where the perturbation is on."""
    d = _driving_attrs(rec)
    trial = TrackingTrial.from_record(rec)
    fs = trial.fs_hz
    k0 = max(trial.start, int(round(SCORE_FROM_S * fs)))
    lpv = GripScheduledLPV()
    lpv.calibrate(cal)
    tracks = {LPV: lpv.track(trial)}
    level = float(d.get("perturbation_level", 1.0))
    if level > 0:
        for name, est in zip(VALIDATORS, _validators(), strict=True):
            est.calibrate(cal)
            tracks[name] = est.track(trial)
    vs_truth: dict[str, dict[str, float | None]] = {}
    if trial.truth is not None:
        for name, tr in tracks.items():
            s = score(trial, tr, from_s=k0 / fs)
            vs_truth[name] = {"rms_log_k_i": s.rms_log_k_i, "bias_k_i_percent": s.bias_k_i_percent}
    agree = {}
    k_lpv = tracks[LPV].params["k_i"]
    for name in VALIDATORS:
        if name in tracks:
            ok = tracks[name].valid.copy()
            ok[:k0] = False
            if ok.any():
                agree[name] = _log_error(k_lpv[ok], tracks[name].params["k_i"][ok])
    width = np.asarray(rec.extra["lane_width_m"], dtype=float)
    y = np.asarray(rec.extra["lateral_position_m"], dtype=float)
    car_w = float(d.get("vehicle", {}).get("width_m", 1.8))
    departed = np.abs(y) > (width - car_w) / 2
    span = slice(k0, trial.n)
    mid = 0.5 * (width.min() + width.max())
    narrow = np.zeros(trial.n, dtype=bool)
    wide = np.zeros(trial.n, dtype=bool)
    if width.max() - width.min() > 0.05:  # sections only where the width does change
        narrow[span] = width[span] < mid - 0.05 * (width.max() - width.min())
        wide[span] = width[span] > mid + 0.05 * (width.max() - width.min())
    c_lpv = static_compliance(tracks[LPV])
    c_true = static_compliance(trial.truth) if trial.truth is not None else None
    sections = {}
    for label, mask in (("narrow", narrow), ("wide", wide)):
        if mask.sum() < fs:  # less than a second: no section
            continue
        sections[label] = {
            "grip_N": float(np.mean(trial.grip_N[mask])),
            "lpv_compliance": float(np.mean(c_lpv[mask])),
            "true_compliance": float(np.mean(c_true[mask])) if c_true is not None else math.nan,
            "seconds": float(mask.sum() / fs),
        }
    sections["all"] = {
        "grip_N": float(np.mean(trial.grip_N[span])),
        "lpv_compliance": float(np.mean(c_lpv[span])),
        "true_compliance": float(np.mean(c_true[span])) if c_true is not None else math.nan,
        "seconds": float((trial.n - k0) / fs),
    }
    series: dict[str, np.ndarray] = {}
    if keep_series:
        step = max(1, int(round(fs / DECIMATE_HZ)))
        series = {
            "road_distance_m": np.asarray(rec.extra["road_distance_m"])[::step],
            "lane_width_m": width[::step],
            "grip_N": trial.grip_N[::step],
        }
        for name, tr in tracks.items():
            series[f"{name}_k_i"] = tr.params["k_i"][::step]
        if trial.truth is not None:
            series["true_k_i"] = trial.truth["k_i"][::step]
    return DriveAnalysis(
        subject=rec.subject,
        condition=rec.condition,
        source=rec.source or rec.label(),
        speed_mps=float(d.get("speed_mps", math.nan)),
        friction=float(d.get("friction", math.nan)),
        perturbation_level=level,
        sections=sections,
        vs_truth=vs_truth,
        lpv_vs_validator=agree,
        lane_departure_percent=float(100.0 * departed[span].mean()),
        series=series,
    )


def _factor_tables(drives: Sequence[DriveAnalysis]) -> dict[str, list[tuple[str, str, dict]]]:
    """factor → rows (subject, level, section means) with the other factors averaged."""
    out: dict[str, list[tuple[str, str, dict]]] = {"width": [], "speed": [], "friction": []}
    for d in drives:
        for sec in ("narrow", "wide"):
            if sec in d.sections:
                out["width"].append((d.subject, sec, d.sections[sec]))
        out["speed"].append((d.subject, f"{d.speed_mps:g} m/s", d.sections["all"]))
        out["friction"].append((d.subject, f"μ {d.friction:g}", d.sections["all"]))
    return out


def driving_statistics(drives: Sequence[DriveAnalysis]) -> tuple[dict[str, dict], list[str]]:
    """Repeated-measures ANOVA over subjects for grip and compliance, per factor."""
    import pandas as pd

    stats: dict[str, dict] = {}
    problems = []
    for factor, rows in _factor_tables(drives).items():
        levels = sorted({lv for _, lv, _ in rows})
        subjects = sorted({s for s, _, _ in rows})
        if len(levels) < 2:
            continue
        if len(subjects) < 3:
            problems.append(
                f"{factor}: {len(subjects)} subject(s); repeated-measures statistics need 3 or more"
            )
            continue
        stats[factor] = {}
        for dv in ("grip_N", "lpv_compliance", "true_compliance"):
            df = pd.DataFrame(
                [{"subject": s, "level": lv, "value": v[dv]} for s, lv, v in rows]
            ).dropna()
            if df.empty:
                continue
            try:
                r = rm_anova(df, dv="value", within="level", subject="subject")
            except ValueError as e:
                problems.append(f"{factor} / {dv}: {e}")
                continue
            doc = r.to_dict()
            doc["dv"] = dv
            stats[factor][dv] = doc
    return stats, problems


#: The channels a drive's analysis reads beyond the core five.
DRIVE_CHANNELS = (*DRIVING_CHANNELS, *TRUTH_KEYS.values(), "true_grip_mean_N")


def with_drive_channels(records: Sequence[TrialRecord]) -> list[TrialRecord]:
    """The records, each drive read again with its road and truth channels when they were
    dropped (the report reads only the core channels, ``analysis.pipeline.load_directory``)."""
    out = list(records)
    missing = [i for i, r in enumerate(out) if r.driving and "lane_width_m" not in r.extra]
    by_file: dict[str, list[int]] = {}
    for i in missing:
        path = out[i].source_file
        if path:
            by_file.setdefault(path, []).append(i)
    for path, idx in by_file.items():
        full = {r.source: r for r in SessionFile(path).records(extra_channels=DRIVE_CHANNELS)}
        for i in idx:
            if out[i].source in full:
                out[i] = full[out[i].source]
    return out


def analyse_driving(records: Sequence[TrialRecord]) -> DrivingReport | None:
    """None when no record is a complete, measured driving trial."""
    if not any(r.driving and r.usable for r in records):
        return None
    records = with_drive_channels(records)
    drives_recs = [r for r in records if r.driving and r.usable]
    stationary = [r for r in records if not r.time_varying and r.usable]
    out = DrivingReport([], {})
    first = True
    for subject in sorted({r.subject for r in drives_recs}):
        own = [r for r in stationary if r.subject == subject]
        try:
            cal = Calibration.from_records(own, source=f"{subject}'s boundary tasks")
        except (CalibrationError, ValueError) as e:
            out.problems.append(f"{subject}: drives not analysed: {e}")
            continue
        for rec in (r for r in drives_recs if r.subject == subject):
            try:
                out.drives.append(analyse_drive(rec, cal, keep_series=first))
                first = False
            except (KeyError, ValueError) as e:
                out.problems.append(f"{rec.source or rec.label()}: not analysed: {e}")
    out.stats, problems = driving_statistics(out.drives)
    out.problems += problems
    return out


def figure(rep: DrivingReport):
    """The first drive along the road: lane width, grip, k_i from grip (LPV), the validators
    and the truth."""
    if not rep.drives or not rep.drives[0].series:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = rep.drives[0]
    s = d.series
    x = s["road_distance_m"]
    fig, axes = plt.subplots(3, 1, figsize=(10, 6.4), sharex=True)
    axes[0].plot(x, s["lane_width_m"], color="0.3")
    axes[0].set_ylabel("lane width (m)")
    axes[1].plot(x, s["grip_N"], color="#2ca02c", lw=0.8)
    axes[1].set_ylabel("grip force (N)")
    if "true_k_i" in s:
        axes[2].plot(x, s["true_k_i"], color="k", lw=2, label="truth (simulated)")
    colours = {LPV: "#1f77b4", "sliding_window_10s": "#ff7f0e", "grip_ekf": "#d62728"}
    for name, c in colours.items():
        if f"{name}_k_i" in s:
            label = "lpv (grip only)" if name == LPV else name
            axes[2].plot(x, s[f"{name}_k_i"], color=c, lw=1.1, label=label)
    axes[2].set_yscale("log")
    axes[2].set_ylabel("k_i (N·m/rad)")
    axes[2].set_xlabel("distance along the road (m)")
    axes[2].legend(fontsize=8, ncol=4)
    axes[0].set_title(
        f"{d.source}: {d.speed_mps:g} m/s, μ {d.friction:g}, "
        f"perturbation ×{d.perturbation_level:g}",
        fontsize=9,
    )
    fig.tight_layout()
    return fig


def html_section(rep: DrivingReport, image_uri: str | None) -> str:
    def num(v: float | None, fmt: str) -> str:
        return "–" if v is None or not np.isfinite(v) else format(v, fmt)

    rows = []
    for d in rep.drives:
        t = d.vs_truth.get(LPV, {})
        cells = [
            ("l", html.escape(d.source)),
            ("", f"{d.speed_mps:g}"),
            ("", f"{d.friction:g}"),
            ("", f"{d.perturbation_level:g}"),
            ("", num(d.lane_departure_percent, ".1f")),
        ]
        for sec in ("narrow", "wide"):
            v = d.sections.get(sec, {})
            cells.append(("", num(v.get("grip_N"), ".0f")))
            cells.append(("", num(v.get("lpv_compliance"), ".4f")))
        cells.append(("", num(t.get("rms_log_k_i"), ".3f")))
        for name in VALIDATORS:
            a = d.lpv_vs_validator.get(name)
            cells.append(("", num(a["rms_log_k_i"], ".3f") if a else "–"))
            vt = d.vs_truth.get(name, {})
            cells.append(("", num(vt.get("rms_log_k_i"), ".3f")))
        rows.append("<tr>" + "".join(f'<td class="{c}">{v}</td>' for c, v in cells) + "</tr>")
    heads = ["drive", "speed (m/s)", "μ", "pert. ×", "out of lane %"]
    heads += ["grip narrow (N)", "C narrow (rad/N·m)", "grip wide (N)", "C wide (rad/N·m)"]
    heads += ["lpv vs truth (RMS log k_i)"]
    for name in VALIDATORS:
        heads += [f"lpv vs {name}", f"{name} vs truth"]
    head = "".join(f'<th class="{"l" if i == 0 else ""}">{h}</th>' for i, h in enumerate(heads))
    stat_rows = []
    for factor, by_dv in rep.stats.items():
        for dv, r in by_dv.items():
            means = ", ".join(
                f"{html.escape(str(c))}: {m:.4g}" for c, m in r["condition_means"].items()
            )
            stat_rows.append(
                f'<tr><td class="l">{factor}</td><td class="l">{dv}</td><td class="l">{means}</td>'
                f"<td>{r['F']:.2f}</td><td>{r['df1']}, {r['df2']}</td><td>{num(r['p'], '.3g')}</td>"
                f"<td>{r['n_subjects']}</td></tr>"
            )
    stats_table = (
        "<table><thead><tr><th class='l'>factor</th><th class='l'>measure</th>"
        "<th class='l'>means</th><th>F</th><th>df</th><th>p</th><th>subjects</th></tr></thead>"
        f"<tbody>{''.join(stat_rows)}</tbody></table>"
        if stat_rows
        else ""
    )
    summary = rep.summary()
    summ = "".join(
        f"<li>{html.escape(k)}: median RMS log k_i {v['median_rms_log_k_i']:.3f}, median bias "
        f"{v['median_bias_k_i_percent']:+.1f} % over {v['drives']} drive(s)</li>"
        for k, v in summary.items()
    )
    fig = (
        f'<figure><img alt="driving" src="{image_uri}"><figcaption>The first drive along the '
        "road: lane width, grip force, and the intrinsic stiffness k_i estimated from grip "
        "alone (lpv), by the perturbation-based trackers, and the truth (simulation)."
        "</figcaption></figure>"
        if image_uri
        else ""
    )
    problems = "".join(f"<li>{html.escape(p)}</li>" for p in rep.problems)
    return (
        '<h2 id="driving">Driving: admittance along the road without perturbation</h2>'
        "<p>Per subject, the grip-scheduled LPV model is calibrated on that subject's boundary "
        "tasks and estimates the admittance along each drive from the grip force alone "
        "(<b>lpv</b>). Where the perturbation was on, the sliding-window FRF and Steerlab's "
        "grip-informed Kalman filter validate it over time (RMS of the log ratio of k_i, "
        f"from {SCORE_FROM_S:g} s on). C is the static compliance 1/k_i + 1/k_c. In driving the "
        "driver's steering and the car's aligning torque respond to the perturbation, so the "
        "perturbation-based trackers are a check, not the truth; simulated drives are also "
        "scored against the truth. Statistics: repeated-measures ANOVA over subjects, one "
        "factor at a time (the others averaged within each subject).</p>"
        + fig
        + (f"<ul>{summ}</ul>" if summ else "")
        + f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"
        + stats_table
        + (f"<ul>{problems}</ul>" if problems else "")
    )


def report_section(records: Sequence[TrialRecord], figures: bool = True):
    """(results.json entry, HTML section) for the report, or None without driving trials."""
    rep = analyse_driving(records)
    if rep is None:
        return None
    uri = None
    if figures:
        fig = figure(rep)
        if fig is not None:
            import matplotlib.pyplot as plt

            from steerlab.analysis import figures as F

            uri = F.png_data_uri(fig)
            plt.close(fig)
    return rep.to_dict(), html_section(rep, uri)
