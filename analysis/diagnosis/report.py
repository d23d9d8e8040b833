"""index.html of a diagnosis: one self-contained page (figures embedded as PNG data URIs).

Figures are plain :class:`matplotlib.figure.Figure` objects on the Agg canvas (no pyplot, no
global state), drawn from what the diagnosis computed; nothing is re-fitted here.
"""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from steerlab.analysis.diagnosis.candidates import CANDIDATES
from steerlab.analysis.diagnosis.run import form_sentence
from steerlab.analysis.study import _condition_key

DPI = 90
MODEL_STYLE = {
    "paper": {"color": "#999999", "ls": ":", "label": "paper's fit (FRF, per subject × condition)"},
    "baseline": {"color": "#d62728", "ls": "--", "label": "baseline (before)"},
    "extended": {"color": "#1f77b4", "ls": "-", "label": "extended model (after)"},
}


def _fig(w: float, h: float) -> Figure:
    fig = Figure(figsize=(w, h), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _uri(fig: Figure) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _e(x: Any) -> str:
    return html.escape(str(x))


def _n(v: Any, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, int | np.integer):
        return str(int(v))
    return f"{float(v):.{digits}g}"


def _pp(v: Any) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{float(v):+.2f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    h = "".join(f"<th>{_e(c)}</th>" for c in header)
    b = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{b}</tbody></table>"


# -- figures ---------------------------------------------------------------------------------------
def fig_candidates(result) -> Figure:
    names = [c.name for c in CANDIDATES] + ["drift"]
    cand = result.candidates
    names = [n for n in names if n in cand]
    fig = _fig(9.5, 3.2)
    ax1, ax2 = fig.subplots(1, 2)
    y = np.arange(len(names))
    # Clipped for display: a diverged candidate can score −10¹⁶.
    dbic = np.clip([cand[n].get("delta_bic") or 0.0 for n in names], -1e7, 1e7)
    # None: not tried on held-out data (it failed on BIC); no bar, marked "not tried".
    ho_raw = [cand[n].get("held_out_gain_minus2loglik") for n in names]
    ho = np.clip([0.0 if v is None else v for v in ho_raw], -1e7, 1e7)
    colours = ["#1f77b4" if cand[n].get("retained") else "#bbbbbb" for n in names]
    ax1.barh(y, dbic, color=colours)
    ax1.axvline(-10, color="k", lw=0.8, ls=":")
    ax1.set_xscale("symlog", linthresh=10)
    ax1.set_xlim(min(dbic.min() * 2, -30), max(dbic.max() * 2, 30))
    ax1.set_yticks(y, names)
    ax1.invert_yaxis()
    ax1.set_xlabel("ΔBIC vs baseline (dotted: −10; drift's: −8)")
    tried = np.array([v is not None for v in ho_raw])
    ax2.barh(y[tried], ho[tried], color=[c for c, t in zip(colours, tried, strict=True) if t])
    ax2.axvline(0, color="k", lw=0.8)
    ax2.set_xscale("symlog", linthresh=10)
    ax2.set_xlim(min(ho.min() * 2, -30), max(ho.max() * 2, 30))
    for yi in y[~tried]:
        # Not tried because it failed on BIC, or its gain was far below another candidate's
        # held-out gain; or the study has no held-out data.
        c = cand[names[yi]]
        if c.get("held_out_not_tried_below") is not None:
            why = "not tried (gain ≪ another's)"
        elif "not tried" in c.get("reason", ""):
            why = "not tried (ΔBIC)"
        else:
            why = "none"
        ax2.text(0, yi, f" {why}", va="center", ha="left", fontsize=7, color="#777777")
    ax2.set_yticks(y, [""] * len(names))
    ax2.invert_yaxis()
    ax2.set_xlabel("held-out gain, −2 log L (> 0: better)")
    fig.suptitle("Candidates at the first step (blue: retained)", fontsize=10)
    return fig


def fig_time(trial, sims: dict, window_s: float = 10.0) -> Figure:
    fs = trial.fs_hz
    n = min(len(trial.theta), int(window_s * fs))
    i0 = max(0, len(trial.theta) // 2 - n // 2)
    t = np.arange(i0, i0 + n) / fs
    fig = _fig(9.5, 4.6)
    axes = fig.subplots(2, 2, sharex=True)
    for row, (key, y, unit) in enumerate(
        (
            ("theta_sim", trial.theta, "wheel angle (rad)"),
            ("td_sim", trial.td, "driver torque (N·m)"),
        )
    ):
        ax = axes[row, 0]
        ax.plot(t, y[i0 : i0 + n], color="k", lw=1.0, label="measured")
        for m in ("baseline", "extended"):
            st = MODEL_STYLE[m]
            ax.plot(t, getattr(sims[m], key)[i0 : i0 + n], color=st["color"], ls=st["ls"],
                    lw=1.0, label=st["label"])  # fmt: skip
        ax.set_ylabel(unit)
        axr = axes[row, 1]
        for m in ("baseline", "extended"):
            st = MODEL_STYLE[m]
            axr.plot(t, (y - getattr(sims[m], key))[i0 : i0 + n], color=st["color"],
                     ls=st["ls"], lw=0.9)  # fmt: skip
        axr.set_ylabel("measured − simulated")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[1, 0].set_xlabel("time in the analysed period (s)")
    axes[1, 1].set_xlabel("time in the analysed period (s)")
    fig.suptitle(f"{trial.label}: simulation driven by the measured perturbation", fontsize=10)
    return fig


def fig_frf(frfs: list[dict]) -> Figure:
    nc = len(frfs)
    fig = _fig(2.4 * max(nc, 2) + 1, 8.0)
    axes = np.atleast_2d(fig.subplots(4, nc, sharex=True, squeeze=False))
    rows = (
        ("theta", "mag", "|Tp→θ| (rad/N·m)"),
        ("td", "mag", "|Tp→Td| (–)"),
        ("adm", "mag", "|θ/Td| (rad/N·m)"),
        ("adm", "phase", "∠θ/Td (deg)"),
    )
    for j, c in enumerate(frfs):
        f = np.asarray(c["frequencies_Hz"])
        for i, (ch, kind, label) in enumerate(rows):
            ax = axes[i, j]
            meas = c["measured"][ch]
            mag = np.asarray(meas["magnitude"], dtype=float)
            sd = np.asarray(meas["sd"], dtype=float)
            if kind == "mag":
                lo = np.maximum(mag - 1.96 * sd, mag * 1e-3)
                ax.fill_between(f, lo, mag + 1.96 * sd, color="k", alpha=0.15, lw=0)
                ax.plot(f, mag, "k.", ms=3, label="measured ± 95 %")
                for m, d in c["simulated"].items():
                    st = MODEL_STYLE[m]
                    ax.plot(f, d[ch]["magnitude"], color=st["color"], ls=st["ls"], lw=1.0)
                ax.set_yscale("log")
            else:
                ph = np.asarray(meas["phase_deg"], dtype=float)
                dph = np.degrees(1.96 * sd / np.maximum(mag, 1e-30))
                ax.fill_between(f, ph - dph, ph + dph, color="k", alpha=0.15, lw=0)
                ax.plot(f, ph, "k.", ms=3)
                for m, d in c["simulated"].items():
                    st = MODEL_STYLE[m]
                    ax.plot(f, d[ch]["phase_deg"], color=st["color"], ls=st["ls"], lw=1.0)
            ax.set_xscale("log")
            if j == 0:
                ax.set_ylabel(label, fontsize=8)
            if i == 0:
                ax.set_title(c["condition"], fontsize=9)
            if i == 3:
                ax.set_xlabel("frequency (Hz)")
            ax.tick_params(labelsize=7)
    handles = [
        axes[0, 0].lines[0],
        *[
            axes[0, 0].plot(
                [],
                [],
                color=MODEL_STYLE[m]["color"],
                ls=MODEL_STYLE[m]["ls"],
                label=MODEL_STYLE[m]["label"],
            )[0]  # fmt: skip
            for m in ("paper", "baseline", "extended")
        ],
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=4, fontsize=8)
    return fig


def fig_unexcited(tables: dict) -> Figure:
    classes = ("harmonic2", "harmonic3", "other")
    titles = {
        "harmonic2": "2nd-harmonic lines (even order)",
        "harmonic3": "3rd-harmonic lines (odd order)",
        "other": "other unexcited lines",
    }
    fig = _fig(9.5, 5.2)
    axes = fig.subplots(2, 3, sharey="row")
    for col, cls in enumerate(classes):
        for row, (key, label) in enumerate(
            (("power_vs_noise", "power / noise"), ("repeatable_vs_noise", "repeatable / noise"))
        ):
            ax = axes[row, col]
            for k, (m, tab) in enumerate(tables.items()):
                rows = [r for r in tab["rows"] if r["lines"] == cls and r[key] is not None]
                labels = sorted({f"{r['f_lo_Hz']:g}–{r['f_hi_Hz']:g}" for r in rows},
                                key=lambda s: float(s.split("–")[0]))  # fmt: skip
                vals = []
                for lab in labels:
                    sel = [r for r in rows if f"{r['f_lo_Hz']:g}–{r['f_hi_Hz']:g}" == lab]
                    w = np.array([r["n_bins"] for r in sel], dtype=float)
                    v = np.array([r[key] for r in sel], dtype=float)
                    vals.append(float(np.sum(w * v) / np.sum(w)) if w.sum() else np.nan)
                x = np.arange(len(labels))
                st = MODEL_STYLE[m]
                ax.bar(x + (k - 0.5) * 0.38, vals, width=0.38, color=st["color"], label=st["label"])
                ax.set_xticks(x, labels, fontsize=7)
            ax.axhline(1.0 if row == 0 else 0.0, color="k", lw=0.7, ls=":")
            if col == 0:
                ax.set_ylabel(label)
            if row == 0:
                ax.set_title(titles[cls], fontsize=9)
            if row == 1:
                ax.set_xlabel("Hz")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(
        "Unexcited frequencies: what a linear model cannot produce (1 = noise; repeatable = "
        "the same in both repetitions, i.e. distortion)",
        fontsize=9,
    )
    return fig


def fig_residual_views(comp: dict, drift_rate: float | None) -> Figure:
    fig = _fig(9.5, 7.0)
    (a1, a2), (a3, a4) = fig.subplots(2, 2)
    conds = sorted(comp["residual_vs_grip"]["baseline"], key=_condition_key)
    cmap = {c: f"C{i}" for i, c in enumerate(conds)}
    for m in ("baseline", "extended"):
        st = MODEL_STYLE[m]
        for c in conds:
            rows = comp["residual_vs_grip"][m][c]
            x = [r["grip_rel_mean"] for r in rows]
            y = [r["unmodelled_stiffness_Nm_per_rad"] for r in rows]
            a1.plot(np.array(x, dtype=float) * 100, y, color=cmap[c], ls=st["ls"], marker=".",
                    lw=1.0)  # fmt: skip
    a1.set_xlabel("grip force relative to the trial's mean (%, quintiles)")
    a1.set_ylabel("unmodelled stiffness (N·m/rad)")
    a1.set_title("Residual against grip force within a trial", fontsize=9)
    for m in ("baseline", "extended"):
        st = MODEL_STYLE[m]
        for c in conds:
            rows = comp["residual_vs_amplitude"][m][c]
            x = [r["deflection_mean_rad"] for r in rows]
            y = [r["rel_rms_td"] for r in rows]
            a2.plot(np.degrees(np.array(x, dtype=float)), y, color=cmap[c], ls=st["ls"],
                    marker=".", lw=1.0)  # fmt: skip
    a2.axhline(1.0, color="k", lw=0.6, ls=":")
    a2.set_xlabel("simulated deflection |θ| (deg, quintiles)")
    a2.set_ylabel("residual torque RMS / trial's RMS")
    a2.set_title("Residual against deflection amplitude", fontsize=9)
    rows = comp["residual_vs_order"]
    for key, ax, lab in (
        ("log_k_i_vs_cell", a3, "k_i"),
        ("log_k_c_vs_cell", a3, "k_c"),
    ):
        for c in conds:
            pts = [r for r in rows if r["condition"] == c and r["trial_index"] is not None]
            ax.plot([r["trial_index"] for r in pts], [100 * r[key] for r in pts],
                    marker="o" if lab == "k_i" else "s", ls="none", color=cmap[c], ms=4,
                    mfc="none" if lab == "k_c" else cmap[c])  # fmt: skip
    if drift_rate is not None:
        idx = np.array([r["trial_index"] for r in rows if r["trial_index"] is not None])
        if idx.size:
            xs = np.linspace(idx.min(), idx.max(), 50)
            a3.plot(xs, 100 * drift_rate * (xs - xs.mean()), color="k", lw=1, label="drift fitted")
            a3.legend(fontsize=7)
    a3.set_xlabel("trial index in the session (● k_i, □ k_c; colour: condition)")
    a3.set_ylabel("stiffness vs its condition's mean (%)")
    a3.set_title("Arm stiffness against trial order", fontsize=9)
    for c in conds:
        pts = [r for r in rows if r["condition"] == c and r["vaf_td_percent"] is not None]
        a4.plot([r["trial_index"] for r in pts], [r["vaf_td_percent"] for r in pts],
                marker="o", ls="none", color=cmap[c], ms=4, label=c)  # fmt: skip
        a4.plot([r["trial_index"] for r in pts], [r["vaf_theta_percent"] for r in pts],
                marker="^", ls="none", color=cmap[c], ms=4, mfc="none")  # fmt: skip
    a4.set_xlabel("trial index (● torque, △ angle)")
    a4.set_ylabel("VAF of the extended model (%)")
    a4.set_title("Fit against trial order and repetition", fontsize=9)
    a4.legend(fontsize=7, ncol=2)
    fig.suptitle("dashed: baseline (before); solid: extended model (after); colour: condition",
                 fontsize=9)  # fmt: skip
    return fig


# -- page ----------------------------------------------------------------------------------------
CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1100px;
margin:2em auto;padding:0 1em;color:#222;line-height:1.45}
h1{font-size:1.6em}h2{font-size:1.25em;margin-top:2em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}
td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f4f4f4}td:first-child,th:first-child{text-align:left}
.verdict{background:#eef5fb;border-left:5px solid #1f77b4;padding:.8em 1.2em}
.warn{background:#fff6e5;border-left:5px solid #e69500;padding:.6em 1.2em}
figure{margin:1em 0}figcaption{font-size:.9em;color:#444}img{max-width:100%}
code{background:#f4f4f4;padding:0 .2em}
"""


def _verdict(result) -> str:
    c = result.cause
    parts = []
    if c == "none":
        parts.append(
            "<p><b>Cause: none.</b> The baseline simulation reproduces the measurements within "
            "their noise; no candidate mechanism improves the prediction of held-out data "
            "enough to be retained.</p>"
        )
    elif c == "unexplained":
        parts.append(
            "<p><b>Cause: unexplained.</b> A clear residual remains that none of the candidate "
            f"mechanisms explains: {_e(result.unexplained['description'])}.</p>"
        )
        partial = [n for n in result.causes if n != "unexplained"]
        if partial:
            parts.append(
                "<p>Retained, but explaining far less than what is left (partial "
                f"explanations, possibly standing in for the real cause): {_e(', '.join(partial))}"
                ".</p>"
            )
    else:
        parts.append(f"<p><b>Cause: {_e(c)}.</b> Retained (strongest first): "
                     f"{_e(', '.join(result.causes))}.</p>")  # fmt: skip
    for name, alts in result.equally_good.items():
        others = ", ".join(a["name"] for a in alts)
        rows_eq = [[_e(a["name"]), _e(a["form"]), _n(a["held_out_gain_minus2loglik"], 4),
                    _n(a["delta_bic"], 4), f"{_n(a['worse_by'], 3)} ± {_n(a['se'], 2)}"]
                   for a in alts]  # fmt: skip
        parts.append(
            f"<p><b>The data cannot tell {_e(name)} from {_e(others)}</b>: they explain the "
            "data equally well (the criterion differs by less than two of its standard "
            "errors). Both are possible; the evidence for each alternative:</p>"
            + _table(["alternative", "form", "held-out gain", "ΔBIC", "worse by"], rows_eq)
        )
    rows = []
    for name in result.causes:
        for p in result.candidates.get(name, {}).get("parameters", []):
            ci = f"{_n(p['ci95'][0], 4)} … {_n(p['ci95'][1], 4)}"
            rows.append([_e(name), _e(p["parameter"]), _n(p["value"], 4), _e(p["unit"]),
                         _n(p["se"], 2), ci])  # fmt: skip
    if rows:
        parts.append(
            _table(["mechanism", "parameter", "value", "unit", "SE", "95 % interval"], rows)
        )
    g = result.gain
    if g.get("held_out") and result.causes and result.cause not in ("none", "unexplained"):
        o = g["overall"]
        parts.append(
            "<p>Held-out gain (each repetition predicted from the other): VAF of the wheel "
            f"angle {_pp(o['vaf_theta_pp'])} pp ({_n(o['vaf_theta_before'], 4)} → "
            f"{_n(o['vaf_theta_after'], 4)} %), of the driver torque {_pp(o['vaf_td_pp'])} pp "
            f"({_n(o['vaf_td_before'], 4)} → {_n(o['vaf_td_after'], 4)} %), FIT "
            f"{_pp(o['fit_pp'])} pp; ΔBIC {_n(g['delta_bic'], 4)}.</p>"
        )
    if result.unexplained and result.unexplained.get("description") and c != "unexplained":
        parts.append(f"<p>Still unexplained: {_e(result.unexplained['description'])}.</p>")
    return '<div class="verdict">' + "".join(parts) + "</div>"


def _gain_table(result) -> str:
    g = result.gain
    if not g.get("held_out"):
        return "<p>No held-out comparison: the data have a single repetition per condition.</p>"
    rows = []
    for c, d in list(g["per_condition"].items()) + [("all", g["overall"])]:
        rows.append([
            _e(c), _n(d["vaf_theta_before"], 4), _n(d["vaf_theta_after"], 4),
            _pp(d["vaf_theta_pp"]), _n(d["vaf_td_before"], 4), _n(d["vaf_td_after"], 4),
            _pp(d["vaf_td_pp"]), _n(d["fit_before"], 4), _n(d["fit_after"], 4),
            _pp(d["fit_pp"]), _n(d.get("delta_bic"), 4),
        ])  # fmt: skip
    t = _table(
        ["condition", "VAF θ before", "after", "Δ pp", "VAF Td before", "after", "Δ pp",
         "FIT before", "after", "Δ pp", "ΔBIC"],
        rows,
    )  # fmt: skip
    extra = ""
    if "drift" in g and g["drift"]:
        d = g["drift"]
        extra = (
            f"<p>Drift, held out (each trial simulated with the other repetition's arm, scaled "
            f"by the fitted drift): VAF θ {_pp(d['vaf_theta_pp'])} pp, VAF Td "
            f"{_pp(d['vaf_td_pp'])} pp.</p>"
        )
    return t + extra


def _candidate_table(result) -> str:
    rows = []
    for name, d in result.candidates.items():
        params = "; ".join(
            f"{p['parameter']} = {_n(p['value'], 3)} ± {_n(p['se'], 2)} {p['unit']}"
            for p in d.get("parameters", [])
        )
        if d.get("forms_minus2loglik"):
            params = f"form: {form_sentence(d)}; {params}"
        rows.append([
            _e(name), params, _n(d.get("delta_bic"), 4),
            _n(d.get("held_out_gain_minus2loglik"), 4),
            "yes" if d.get("retained") else "no", _e(d.get("reason", "")),
        ])  # fmt: skip
    return _table(["candidate", "fitted parameters (first step)", "ΔBIC", "held-out gain",
                   "retained", "why"], rows)  # fmt: skip


def _vaf_table(result) -> str:
    v = result.comparison["vaf"]
    conds = [c for c in v["baseline"] if c != "all"] + ["all"]
    rows = []
    for c in conds:
        rows.append([_e(c)] + [
            f"{_n(v[m][c]['vaf_theta_percent'], 4)} / {_n(v[m][c]['vaf_td_percent'], 4)}"
            for m in ("paper", "baseline", "extended")
        ])  # fmt: skip
    return _table(["condition", "paper's FRF fit", "baseline", "extended"], rows)


def _wheel_paragraph(result) -> str:
    """Which wheel the simulated world has, and how well it and the nominal one fit the data."""
    if not result.wheel_sentence:
        return ""
    check = result.wheel.get("check") or {}
    fit = check.get("fitted_from_data")
    extra = ""
    if fit:
        extra = (
            f" Fitted from the data (Tp − Td = (I s² + b s + k) θ below 2 Hz): "
            f"I = {fit['I_kgm2']:.3g} kg·m², b = {fit['b_Nms_per_rad']:.3g} N·m·s/rad, "
            f"k = {fit['k_Nm_per_rad']:.3g} N·m/rad; relative misfit there of the simulated "
            f"wheel {check['misfit_percent']:.1f} %, of the nominal wheel "
            f"{check['misfit_nominal_percent']:.1f} %."
        )
    return f"<p><b>Wheel</b>: {_e(result.wheel_sentence)}.{_e(extra)}</p>"


FIT_LABELS = {
    "nominal": "I free",
    "friction": "I, F_c, m·g·r free",
    "free": "I, b, k, F_c, m·g·r free",
    "lag": "I, F_c, m·g·r, τ_a free",
}
_PARAM_LABELS = {
    "inertia_kgm2": ("I", "kg·m²"),
    "damping_Nms_per_rad": ("b", "N·m·s/rad"),
    "stiffness_Nm_per_rad": ("k", "N·m/rad"),
    "theta_offset_samples": ("angle read after the command", "samples"),
    "torque_offset_samples": ("torque read after the command", "samples"),
    "coulomb_Nm": ("dry friction F_c", "N·m"),
    "gravity_Nm": ("imbalance m·g·r", "N·m"),
    "lag_s": ("actuator lag τ_a", "s"),
}


def _rig_from_data_section(result) -> str:
    """The wheel and the recording's timing identified from the data, beside the rig's, and
    what the simulation took from them (analysis.rig_from_data)."""
    d = result.rig_from_data
    if not d:
        return ""
    rows = []
    for key, f in d["fits"].items():
        rendering, which = key.split("/")
        label = FIT_LABELS.get(which, which)
        if which == "free" and "lag_s" in f["free"]:
            label = label.replace(" free", ", τ_a free")
        cells = []
        for p in _PARAM_LABELS:
            v, e = f["values"].get(p, 0.0), f["sem"].get(p)
            fixed = "none" if p == "lag_s" else f"{_n(v, 4)} (rig's)"
            cells.append(f"{_n(v, 4)} ± {_n(e, 1)}" if e else fixed)
        rows.append(
            [_e(f"{rendering}, {label}")] + cells + [_n(f["m2ll"], 5), _n(f["noise_ratio"], 3)]
        )
    header = ["damping and spring"] + [f"{a} ({u})" for a, u in _PARAM_LABELS.values()]
    header += ["−2 log L", "residual / noise"]
    conv = d["convention"]
    told = ""
    if conv["source"].get("rendering") in ("rig", "data (closest inertia)"):
        told = (
            " The fits with the rig's damping and stiffness do not tell the two renderings apart"
            " (to first order in the sample interval they are the same wheel with I and b"
            " shifted); the one nearest the rig's inertia is simulated, the rig's own where the"
            " data fit neither within the noise."
        )
    notes = "".join(f"<li>{_e(n)}</li>" for n in conv.get("notes", []))
    return (
        "<h3>The rig and the timing, from the data</h3>"
        f"<p>{_e(result.rig_from_data_sentence)}.{_e(told)} Where each item of the simulation "
        f"came from: {_e(', '.join(f'{k}: {v}' for k, v in conv['source'].items()))}.</p>"
        + (f"<ul>{notes}</ul>" if notes else "")
        + _table(header, rows)
        + f"<p class='small'>{_e(d['method'])}</p>"
    )


def write_html(path: Path, result, prep, setup, sel, drift) -> None:
    comp = result.comparison
    from steerlab.analysis.diagnosis import compare as C

    # The example trial: where the extension changed the torque's VAF most. Only it is
    # simulated again for the figure (each trial's simulation is its own, and deterministic).
    vt = comp["vaf_per_trial"]
    example = max(
        setup.trials,
        key=lambda t: abs(
            (vt[t.label]["extended"]["td"] or 0) - (vt[t.label]["baseline"]["td"] or 0)
        ),
    )
    sims = {
        "baseline": C.compare_trials([example], sel.base.arms, setup.base_mech),
        "extended": C.compare_trials(
            [example], sel.final.arms, sel.final_spec.mechanisms(sel.final.x)
        ),
    }
    figs = {
        "candidates": _uri(fig_candidates(result)),
        "time": _uri(fig_time(example, {m: sims[m][example.label] for m in sims})),
        "frf": _uri(fig_frf(comp["frf"])),
        "unexcited": _uri(fig_unexcited(comp["unexcited"])),
        "residuals": _uri(
            fig_residual_views(
                comp,
                drift.rate
                if drift is not None and drift.passed and drift.form.at_trial is None
                else None,
            )
        ),
    }
    limits = "".join(f"<li>{_e(x)}</li>" for x in result.limits)
    notes = "".join(f"<li>{_e(x)}</li>" for x in result.notes)
    skipped = "".join(
        f"<li>{_e(s['trial'])}: {_e(s['reason'])}</li>" for s in result.data["skipped"]
    )
    mis = comp["frf_outside_ci95"]
    mis_rows = [[_e(m)] + [f"{100 * (mis[m][k] or 0):.0f} %" for k in ("theta", "td", "adm")]
                for m in mis]  # fmt: skip
    d = result.data
    page = f"""<!doctype html><html lang="en"><head><meta charset="utf-8">
<title>Steerlab diagnosis</title><style>{CSS}</style></head><body>
<h1>What the simulation gets wrong, and why</h1>
<p>Data: {len(d["subjects"])} subject(s) ({_e(", ".join(d["subjects"]))}), conditions
{_e(", ".join(d["conditions"]))}, {d["n_trials"]} measured trials
(+ {d["n_familiarization_trials"]} familiarization trials, used only for the trial-order
check), sampled at {_e(", ".join(f"{x:g}" for x in d["sample_rates_Hz"]))} Hz.
{("Baseline: model file " + _e(result.baseline_model) + ".") if result.baseline_model else ""}</p>
{_wheel_paragraph(result)}
{_rig_from_data_section(result)}
{_verdict(result)}
{('<div class="warn"><b>Limits of these data</b><ul>' + limits + "</ul></div>") if limits else ""}

<h2>How to read this page</h2>
<p>The simulator (the same world as <code>steerlab simulate</code>) is driven by the
<em>measured</em> perturbation torque, at the data's sample rate, and its wheel angle θ and driver
torque Td are compared with the measured ones. The <b>baseline</b> is the paper's arm model
(contact spring-damper in series with the arm's mass-spring-damper), fitted to every trial. The
driver's own torque noise (remnant) cannot be reproduced sample by sample: it is the residual
the best model still leaves, estimated at the frequencies the perturbation does not excite.
Each candidate mechanism is added to the model and fitted; it is <b>retained</b> only if it
improves BIC (ΔBIC &lt; −10, where a mechanism that comes in K forms pays 2 ln K for the
choice of its best form) <em>and</em> predicts the other repetition better than the model
without it (held-out gain &gt; 5). Drift is judged on the trials' fitted stiffnesses instead
(ΔBIC &lt; −8 on their restricted likelihood, a leave-one-trial-out gain, and at least 4
differences between trials of the same subject and condition). The <b>extended model</b> is
the baseline plus what was retained; it is written to <code>model.toml</code>.
VAF = 100·(1 − Σ(measured − simulated)² / Σ measured²); FIT% is the paper's frequency-domain
fit of the admittance θ/Td.</p>

<h2>1. What the simulation gets wrong</h2>
<h3>Time domain</h3>
<p>VAF (%) of the wheel angle / the driver torque, simulated against measured, in-sample:</p>
{_vaf_table(result)}
<figure><img src="{figs["time"]}" alt="time traces"><figcaption>Measured and simulated signals
of one trial (the one where the extension changes the driver torque's VAF most), and the
residuals.</figcaption></figure>
<h3>Excited frequencies</h3>
<figure><img src="{figs["frf"]}" alt="frequency responses"><figcaption>Per condition (all
subjects pooled): perturbation → wheel angle, perturbation → driver torque, and the admittance
θ/Td, measured (dots, grey band: 95 % interval from the noise at the unexcited neighbours) and
simulated by each model (same estimator on the simulated signals).</figcaption></figure>
<p>Share of bands where the simulated response lies outside the measurement's 95 % interval
(Tp→θ, Tp→Td, θ/Td):</p>
{_table(["model", "Tp→θ", "Tp→Td", "θ/Td"], mis_rows)}
<h3>Unexcited frequencies</h3>
<figure><img src="{figs["unexcited"]}" alt="unexcited"><figcaption>Power left at the frequencies
the perturbation does not excite, relative to the noise there (top), and the part of it that
repeats between the two repetitions (bottom: the perturbation is identical in every trial, so a
deterministic nonlinear response repeats, while remnant and sensor noise do not). "Angle" and
"wheel" channels are pooled; second-harmonic lines reveal even-order, third-harmonic lines
odd-order distortion.</figcaption></figure>
<h3>Residuals against grip force, trial order and amplitude</h3>
<figure><img src="{figs["residuals"]}" alt="residual views"><figcaption>Top left: the residual
driver torque per unit simulated angle ("unmodelled stiffness") in each quintile of the trial's
grip force; a stiffness that follows grip force rises to the right. Top right: residual torque
RMS in each quintile of the deflection; a stiffness nonlinearity grows at large deflections.
Bottom left: each trial's fitted stiffnesses against its position in the session (drift is a
trend). Bottom right: the extended model's VAF per trial.</figcaption></figure>

<h2>2. Naming the cause</h2>
<figure><img src="{figs["candidates"]}" alt="candidates"></figure>
{_candidate_table(result)}
<p>Each candidate's parameters are fitted together with every trial's arm by weighted least
squares on the spectra (see <code>docs/diagnosis.md</code>). Held out: fitted on one
repetition, the mechanism's parameters are kept for the other, where only that trial's arm is
re-fitted. Drift is judged on the trials' fitted stiffnesses against trial order.</p>

<h2>3. The extended model</h2>
<p>Written to <code>model.toml</code> beside this page: the typical subject per condition
(arm, grip force, remnant) and the retained mechanisms with their fitted parameters and
uncertainties. <code>steerlab simulate --model model.toml</code> simulates with it.</p>

<h2>4. What it gains</h2>
{_gain_table(result)}
<p>Overall ΔBIC (extended − baseline, all data; the 2 ln K for a choice among forms is
not in it): {_n(result.gain.get("delta_bic"), 5)}.</p>

<h2>Data and notes</h2>
<ul>{notes}</ul>
{("<p>Left out:</p><ul>" + skipped + "</ul>") if skipped else ""}
<p>Run time: {_n(result.timing_s.get("total"), 3)} s
({_n(result.timing_s.get("per_subject"), 3)} s per subject session).</p>
</body></html>
"""
    Path(path).write_text(page, encoding="utf-8")
