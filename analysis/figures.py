"""The report's figures, drawn from a :class:`analysis.pipeline.StudyResults` (nothing computed here
that the results do not hold, apart from evaluating fitted models on a frequency grid).

Figures are plain :class:`matplotlib.figure.Figure` objects rendered by the Agg canvas: no
pyplot, so no global figure registry, no GUI backend and no state shared between calls (safe
in worker threads and on machines without a display). :func:`png_data_uri` turns one into a
``data:`` URI for a self-contained HTML page.

Conditions keep one colour in every figure, ordered from the widest boundary (RT, dark) to the
narrowest (PT, light).
"""

from __future__ import annotations

import base64
import io
from collections.abc import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import LogFormatterSciNotation

from steerlab.analysis.armfit import arm_admittance
from steerlab.analysis.lpv import admittance_response
from steerlab.analysis.periods import PeriodSelection
from steerlab.analysis.pipeline import PARAMETER_UNITS, StudyResults, leave_one_out_models
from steerlab.analysis.report import in_condition_order, method_name
from steerlab.protocols.records import TrialRecord

DPI = 96
FREE_PARAMETERS = ("b_i", "k_i", "b_c", "k_c")


def new_figure(width_in: float, height_in: float) -> Figure:
    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def png_data_uri(fig: Figure, dpi: int = DPI) -> str:
    """The figure as ``data:image/png;base64,…``."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def condition_colours(conditions: Sequence[str]) -> dict[str, tuple]:
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    n = max(len(conditions) - 1, 1)
    # Stop short of viridis' pale yellow end, which vanishes on white.
    return {c: cmap(0.85 * i / n) for i, c in enumerate(conditions)}


# Log-axis tick labels between these are plain numbers, as the report's tables write them.
PLAIN_RANGE = (1e-4, 1e6)


class PlainLogFormatter(LogFormatterSciNotation):
    """Log-axis tick labels as plain numbers (0.01, 1.2, 50) for ordinary magnitudes, powers of
    ten only outside :data:`PLAIN_RANGE`: never "1.2 × 10⁰". Which ticks carry a label is
    matplotlib's choice (decades, and minor ticks when the axis spans less than one)."""

    def __call__(self, x, pos=None):
        label = super().__call__(x, pos)
        if not label or not PLAIN_RANGE[0] <= abs(x) < PLAIN_RANGE[1]:
            return label
        return f"{x:.6g}"  # six digits drop the float noise of tick positions (0.30000000004)


def log_axes(ax, which: str = "xy") -> None:
    """Log scale on the axes named in ``which``, labelled by :class:`PlainLogFormatter`."""
    for name in which:
        axis = ax.xaxis if name == "x" else ax.yaxis
        (ax.set_xscale if name == "x" else ax.set_yscale)("log")
        axis.set_major_formatter(PlainLogFormatter(labelOnlyBase=False))
        axis.set_minor_formatter(PlainLogFormatter(labelOnlyBase=False))


def symbol(name: str) -> str:
    """A parameter name as mathtext: "k_i" → $k_i$ (subscript, not an underscore)."""
    return f"${name}$" if "_" in name else name


def points_in_condition_order(res: StudyResults) -> list:
    """The operating points in the protocol's condition order (the results keep them by μ),
    so that legends list the conditions as every table does."""
    return in_condition_order(res.points, res.conditions, lambda p: p.condition)


def _fine_grid(f: np.ndarray) -> np.ndarray:
    f = np.asarray(f, dtype=float)
    return np.geomspace(f.min(), f.max(), 300)


# ------------------------------------------------------------------------------------------


def time_signals(record: TrialRecord, selection: PeriodSelection | None = None) -> Figure:
    """Perturbation, driver torque, wheel angle and grip force of one trial; the analysed
    periods shaded."""
    fig = new_figure(10, 7)
    axes = fig.subplots(4, 1, sharex=True)
    t = np.asarray(record.time_s, dtype=float)
    t = t - t[0] if t.size else t
    rows = [
        (record.perturbation_torque_Nm, "perturbation\ntorque T_p (N·m)"),
        (record.driver_torque_Nm, "driver torque\nT_d (N·m)"),
        (np.degrees(record.wheel_angle_rad), "wheel angle\nθ (deg)"),
        (record.grip_force_N, "total grip\nforce (N)"),
    ]
    for ax, (y, label) in zip(axes, rows, strict=True):
        ax.plot(t, y, lw=0.4, color="0.15")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if selection is not None and t.size:
            ax.axvspan(
                t[selection.start],
                t[min(selection.stop, t.size) - 1],
                color="tab:blue",
                alpha=0.08,
                lw=0,
            )
    axes[-1].set_xlabel("time in trial (s)")
    rep = "familiarization" if record.familiarization else f"repetition {record.repetition}"
    title = f"Subject {record.subject}, {record.condition}, {rep}"
    if selection is not None:
        n = selection.n_periods
        title += f" (shaded: the analysed period{'s' if n != 1 else ''})"
    fig.suptitle(title)
    return fig


def grip_boxplots(res: StudyResults) -> Figure:
    """Per-subject mean and SD of the total grip force, per condition."""
    conds = list(res.conditions)
    colours = condition_colours(conds)
    fig = new_figure(10, 4.2)
    axes = fig.subplots(1, 2)
    cells = {(r.subject, r.condition): r for r in res.study.subject_conditions}
    for ax, attr, label in (
        (axes[0], "grip_mean_N", "mean total grip force (N)"),
        (axes[1], "grip_sd_N", "grip-force SD within a condition (N)"),
    ):
        data = [[getattr(r, attr) for (s, c), r in cells.items() if c == cond] for cond in conds]
        _boxes(ax, data, conds, colours)
        for s in res.subjects:  # one faint line per subject: the within-subject pattern
            y = [getattr(cells[(s, c)], attr) if (s, c) in cells else np.nan for c in conds]
            ax.plot(range(1, len(conds) + 1), y, color="0.6", lw=0.5, alpha=0.6, zorder=1)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    mu = {c.condition: c.grip_median_of_means_N for c in res.study.conditions}
    axes[0].scatter(
        range(1, len(conds) + 1),
        [mu[c] for c in conds],
        marker="D",
        s=28,
        color="black",
        zorder=4,
        label="μ: median of subject means",
    )
    axes[0].legend(loc="upper left", fontsize=8)
    fig.suptitle("Grip force per condition (lines join one subject's values)")
    return fig


def _boxes(ax, data: list[list[float]], conds: list[str], colours: dict) -> None:
    clean = [[v for v in d if v is not None and np.isfinite(v)] for d in data]
    bp = ax.boxplot(clean, patch_artist=True, widths=0.55, showfliers=False)
    ax.set_xticks(range(1, len(conds) + 1), conds)
    for patch, c in zip(bp["boxes"], conds, strict=True):
        patch.set_facecolor(colours[c])
        patch.set_alpha(0.35)
    rng = np.random.default_rng(0)  # fixed jitter: the same figure every run
    for i, (vals, c) in enumerate(zip(clean, conds, strict=True), 1):
        x = i + rng.uniform(-0.12, 0.12, len(vals))
        ax.scatter(x, vals, s=12, color=colours[c], edgecolor="black", lw=0.3, zorder=3)


def admittance(res: StudyResults) -> Figure:
    """Group admittance per condition: magnitude and phase with 95 % intervals, the group fit,
    and coherence."""
    conds = list(res.conditions)
    colours = condition_colours(conds)
    fig = new_figure(10, 9)
    ax_m, ax_p, ax_c = fig.subplots(3, 1, sharex=True, height_ratios=[3, 2, 1.3])
    n_low = res.study.options.fit.n_exclude_low
    for c in res.study.conditions:
        g, col = c.group_frf, colours[c.condition]
        f = g.frequencies_hz
        low = np.argsort(f)[:n_low]
        used = np.setdiff1d(np.arange(f.size), low)
        ax_m.fill_between(f, *g.magnitude_ci, color=col, alpha=0.18, lw=0)
        ax_m.plot(f[used], g.magnitude[used], "o", ms=3.5, color=col, label=c.condition)
        ax_m.plot(f[low], g.magnitude[low], "o", ms=3.5, mfc="none", color=col)
        ax_p.fill_between(f, *g.phase_ci_deg, color=col, alpha=0.18, lw=0)
        ax_p.plot(f, g.phase_deg, "o", ms=3, color=col)
        ax_c.plot(f, g.coherence, "-o", ms=2.5, lw=1, color=col)
        if c.fit is not None:
            ff = _fine_grid(f)
            h = arm_admittance(c.fit.params, ff)
            ax_m.plot(ff, np.abs(h), "-", lw=1.2, color=col)
            ax_p.plot(ff, np.degrees(np.unwrap(np.angle(h))), "-", lw=1.2, color=col)
    log_axes(ax_m)
    ax_m.set_ylabel("|H| (rad/N·m)")
    ax_m.legend(ncol=len(conds), fontsize=8, loc="lower left")
    ax_p.set_ylabel("phase (deg)")
    ax_c.set_ylabel("coherence")
    ax_c.set_ylim(min(0.5, ax_c.get_ylim()[0]), 1.02)
    ax_c.set_xlabel("frequency (Hz)")
    for ax in (ax_m, ax_p, ax_c):
        ax.grid(which="both", alpha=0.25)
    pct = round(100 * res.study.options.confidence)
    fig.suptitle(
        f"Admittance θ/T_d: subject mean (dots), {pct} % interval (band), group fit (line)"
    )
    return fig


def parameter_boxplots(res: StudyResults) -> Figure:
    """Per-subject estimates with their SEMs, and the group fit ± SEM, per condition; I_i per
    subject. Estimates the data do not determine (``ArmFit.unidentified``) stay out of the
    boxes and the axis range, drawn as red × at the edge, so one wild value cannot squash the
    rest (they are also left out of the statistics)."""
    conds = list(res.conditions)
    colours = condition_colours(conds)
    fig = new_figure(12, 7.5)
    axes = fig.subplots(2, 3).ravel()
    group = {c.condition: c.fit for c in res.study.conditions}
    rng = np.random.default_rng(1)
    for ax, name in zip(axes, FREE_PARAMETERS, strict=False):
        data, sems, wild = [], [], []
        for cond in conds:
            fits = [
                r.fit
                for r in res.study.subject_conditions
                if r.condition == cond and r.fit is not None
            ]
            ok = [f for f in fits if name not in f.unidentified()]
            data.append([getattr(f.params, name) for f in ok])
            sems.append([f.sems.get(name, np.nan) for f in ok])
            wild.append(len(fits) - len(ok))
        _boxes_plain(ax, data, conds, colours)
        for i, (vals, ss) in enumerate(zip(data, sems, strict=True), 1):
            v, s = np.asarray(vals, float), np.asarray(ss, float)
            x = i - 0.3 + rng.uniform(-0.05, 0.05, v.size)
            lo = np.clip(v - s, v * 0.05, None)  # a log axis cannot show a bar through zero
            ax.errorbar(
                x, v, yerr=[v - lo, s], fmt="o", ms=2.5, lw=0.6, color="0.35", alpha=0.7, zorder=3
            )
        gx, gy, gs = [], [], []
        for i, cond in enumerate(conds, 1):
            fit = group.get(cond)
            if fit is not None and name not in fit.unidentified():
                gx.append(i + 0.3)
                gy.append(getattr(fit.params, name))
                gs.append(fit.sems.get(name, np.nan))
        gy_a, gs_a = np.asarray(gy), np.asarray(gs)
        ax.errorbar(
            gx,
            gy_a,
            yerr=[gy_a - np.clip(gy_a - gs_a, gy_a * 0.05, None), gs_a],
            fmt="D",
            ms=5,
            color="black",
            capsize=3,
            zorder=4,
            label="group fit ± SEM",
        )
        log_axes(ax, "y")
        top = ax.get_ylim()[1]
        for i, n in enumerate(wild, 1):
            if n:
                ax.plot([i], [top], "x", color="red", ms=7, clip_on=False, zorder=5)
                ax.annotate(f"{n}", (i, top), xytext=(4, -10), textcoords="offset points",
                            color="red", fontsize=7)  # fmt: skip
        ax.set_title(f"{symbol(name)} ({PARAMETER_UNITS[name]})")
        ax.grid(axis="y", which="both", alpha=0.25)
    axes[0].legend(fontsize=8, loc="upper left")
    _inertia_panel(axes[len(FREE_PARAMETERS)], res)
    for ax in axes[len(FREE_PARAMETERS) + 1 :]:
        ax.set_visible(False)
    fig.suptitle(
        "Arm parameters: subjects (boxes; grey: estimate ± SEM), group fit ± SEM; "
        "red ×: estimates the data do not determine (count), left out"
    )
    return fig


def _inertia_panel(ax, res: StudyResults) -> None:
    fits = {k: v for k, v in res.study.inertia.items() if k != "group"}
    opt = res.study.options.fit
    if not fits:
        held = f"held at {opt.I_i:g} kg·m²" if opt.inertia == "fixed" else "fitted per cell"
        ax.text(0.5, 0.5, f"I_i {held}", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
        return
    names = sorted(fits)
    v = np.array([fits[n].I_i for n in names])
    s = np.array([fits[n].I_i_sem if fits[n].I_i_sem is not None else np.nan for n in names])
    x = np.arange(1, len(names) + 1)
    ax.errorbar(x, v, yerr=s, fmt="o", ms=4, color="0.2", capsize=2)
    # The group fits hold the subjects' median (a free group I_i where none is determined).
    g = res.study.inertia.get("group")
    group_held = [c.fit.params.I_i for c in res.study.conditions if c.fit is not None]
    if g is not None:
        ax.axhline(g.I_i, color="black", lw=1, ls="--", label=f"group fit {g.I_i:.3g}")
    elif group_held:
        v0 = group_held[0]
        ax.axhline(v0, color="black", lw=1, ls="--", label=f"group fits hold {v0:.3g}")
    if g is not None or group_held:
        ax.legend(fontsize=8, loc="upper left")
    ax.set_xticks(x, names, rotation=90, fontsize=7)
    ax.set_title(f"{symbol('I_i')} (kg·m²), one per subject ± SEM")
    ax.grid(axis="y", alpha=0.25)


def subject_admittance(res: StudyResults) -> Figure | None:
    """Each subject's admittance magnitude per condition (dots: Ĥ; lines: the subject's fit)."""
    subjects = list(res.subjects)
    if not subjects:
        return None
    conds = list(res.conditions)
    colours = condition_colours(conds)
    ncol = min(6, len(subjects))
    nrow = int(np.ceil(len(subjects) / ncol))
    # A few subjects' panels are narrower than the title and legend: the figure keeps a
    # minimum width and the title breaks into two lines.
    fig = new_figure(max(2.1 * ncol + 0.6, 6.0), 1.9 * nrow + 0.9)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, sharex=True, sharey=True)).ravel()
    n_low = res.study.options.fit.n_exclude_low
    for ax, subj in zip(axes, subjects, strict=False):
        for r in res.study.subject_conditions:
            if r.subject != subj:
                continue
            col = colours[r.condition]
            f = r.frf.frequencies_hz
            low = np.argsort(f)[:n_low]
            ax.plot(f, r.frf.magnitude, "o", ms=1.8, color=col)
            ax.plot(f[low], r.frf.magnitude[low], "o", ms=1.8, mfc="none", color=col)
            if r.fit is not None:
                ff = _fine_grid(f)
                ax.plot(ff, np.abs(arm_admittance(r.fit.params, ff)), "-", lw=0.9, color=col)
        log_axes(ax)
        ax.set_title(subj, fontsize=8)
        ax.tick_params(labelsize=6)
        ax.grid(which="both", alpha=0.2)
    for ax in axes[len(subjects) :]:
        ax.set_visible(False)
    handles = [axes[0].plot([], [], "-o", ms=3, color=colours[c], label=c)[0] for c in conds]
    sep = ":\n" if ncol < 4 else ": "
    fig.suptitle(
        f"Admittance per subject{sep}Ĥ (dots; hollow: left out of the fit) and fit (lines)"
    )
    for ax in axes[max(0, len(subjects) - ncol) : len(subjects)]:
        ax.set_xlabel("frequency (Hz)", fontsize=7)
    fig.supylabel("|H| (rad/N·m)", fontsize=8)
    fig.legend(
        handles=handles, ncol=len(conds), fontsize=8, loc="outside lower center", frameon=False
    )
    return fig


def _boxes_plain(ax, data: list[list[float]], conds: list[str], colours: dict) -> None:
    clean = [[v for v in d if np.isfinite(v)] for d in data]
    bp = ax.boxplot(
        clean, patch_artist=True, widths=0.35, showfliers=True, flierprops={"markersize": 3}
    )
    ax.set_xticks(range(1, len(conds) + 1), conds)
    for patch, c in zip(bp["boxes"], conds, strict=True):
        patch.set_facecolor(colours[c])
        patch.set_alpha(0.45)


def lpv_parameters(res: StudyResults) -> Figure | None:
    """Local (group) parameters against μ, and the physical-parameter LPV polynomials."""
    if res.lpv is None or "physical" not in res.lpv.models:
        return None
    model = res.lpv.models["physical"]
    colours = condition_colours(list(res.conditions))
    fits = {c.condition: c.fit for c in res.study.conditions}
    lo, hi = model.mu_range
    mu = np.linspace(lo, hi, 200)
    fig = new_figure(10, 6.5)
    axes = fig.subplots(2, 2).ravel()
    for ax, name in zip(axes, FREE_PARAMETERS, strict=True):
        ax.plot(
            mu,
            [model.parameters(m)[name] for m in mu],
            "-",
            color="0.3",
            label=f"physical LPV, order {res.lpv.table.order}",
        )
        for p in points_in_condition_order(res):
            fit = fits.get(p.condition)
            sem = fit.sems.get(name, np.nan) if fit is not None else np.nan
            included = p.condition not in res.lpv.excluded
            ax.errorbar(
                [p.mu_N],
                [p.parameters[name]],
                yerr=[[sem], [sem]],
                fmt="o",
                ms=6,
                capsize=3,
                color=colours[p.condition],
                mfc=colours[p.condition] if included else "none",
                label=p.condition + ("" if included else " (not in LPV)"),
            )
        ax.set_title(f"{symbol(name)} ({PARAMETER_UNITS[name]})")
        ax.set_xlabel("μ: median of subjects' mean grip force (N)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=2)
    fig.suptitle("LPV scheduling: group-fit parameters (± SEM) against grip force μ")
    return fig


def lpv_responses(res: StudyResults) -> Figure | None:
    """Measured group FRF at each included operating point against both LPV models at μ."""
    if res.lpv is None:
        return None
    colours = condition_colours(list(res.conditions))
    fig = new_figure(10, 6.5)
    ax_m, ax_p = fig.subplots(2, 1, sharex=True, height_ratios=[3, 2])
    styles = {"physical": "-", "de_caigny": "--"}
    for p in points_in_condition_order(res):
        if p.condition in res.lpv.excluded or p.frf is None:
            continue
        col = colours[p.condition]
        f, h = p.frf.frequencies_hz, p.frf.response
        ax_m.plot(f, np.abs(h), "o", ms=3.5, color=col, label=f"{p.condition} measured")
        ax_p.plot(f, np.degrees(np.unwrap(np.angle(h))), "o", ms=3, color=col)
        ff = _fine_grid(f)
        for m, model in res.lpv.models.items():
            hm = model.frequency_response(p.mu_N, ff)
            ax_m.plot(ff, np.abs(hm), styles.get(m, ":"), lw=1.1, color=col)
            ax_p.plot(
                ff, np.degrees(np.unwrap(np.angle(hm))), styles.get(m, ":"), lw=1.1, color=col
            )
    ax_m.plot([], [], "-", color="0.3", label="physical LPV")
    ax_m.plot([], [], "--", color="0.3", label="de Caigny LPV")
    log_axes(ax_m)
    ax_m.set_ylabel("|H| (rad/N·m)")
    ax_p.set_ylabel("phase (deg)")
    ax_p.set_xlabel("frequency (Hz)")
    ax_m.legend(fontsize=7, ncol=3)
    for ax in (ax_m, ax_p):
        ax.grid(which="both", alpha=0.25)
    fig.suptitle("LPV models at each operating point's μ against the measured group FRF")
    return fig


def leave_one_out(res: StudyResults) -> Figure | None:
    """Each intermediate operating point predicted by the LPV models rebuilt without it."""
    if res.lpv is None or res.lpv.leave_one_out is None:
        return None
    folds = leave_one_out_models(res.lpv, res.points, order=res.lpv.table.order)
    left_out = in_condition_order(dict.fromkeys(p.condition for p, _, _ in folds), res.conditions)
    if not left_out:
        return None
    loo = res.lpv.leave_one_out
    vaf = {(v.method, v.condition): v.median_vaf_percent for v in res.loo_vaf}
    fig = new_figure(max(4.0 * len(left_out), 8), 6.5)
    axes = np.atleast_2d(fig.subplots(2, len(left_out), sharex=True, squeeze=False))
    styles = {"physical": ("-", "tab:red"), "de_caigny": ("--", "tab:blue")}
    for j, cond in enumerate(left_out):
        ax_m, ax_p = axes[0, j], axes[1, j]
        p = next(q for q, _, _ in folds if q.condition == cond)
        if p.frf is not None:
            f, h = p.frf.frequencies_hz, p.frf.response
            ax_m.plot(f, np.abs(h), "o", ms=3, color="0.2", label="measured (group)")
            ax_p.plot(f, np.degrees(np.unwrap(np.angle(h))), "o", ms=3, color="0.2")
            ff = _fine_grid(f)
        else:
            ff = np.geomspace(0.05, 20, 300)
        hl = admittance_response(p.parameters, ff)
        ax_m.plot(ff, np.abs(hl), "-", lw=3, color="0.8", label="local LTI", zorder=0)
        ax_p.plot(ff, np.degrees(np.unwrap(np.angle(hl))), "-", lw=3, color="0.8", zorder=0)
        lines = []
        for q, m, model in folds:
            if q.condition != cond:
                continue
            ls, col = styles.get(m, (":", "k"))
            hm = model.frequency_response(p.mu_N, ff)
            ax_m.plot(
                ff, np.abs(hm), ls, lw=1.3, color=col, label=f"{method_name(m)}, {cond} left out"
            )
            ax_p.plot(ff, np.degrees(np.unwrap(np.angle(hm))), ls, lw=1.3, color=col)
            r = loo.get(m, cond)
            fit = r.fit_vs_measured_percent
            v = vaf.get((m, cond))
            lines.append(f"{method_name(m)}: FIT {_fmt(fit, 1)} %, VAF {_fmt(v, 1)} %")
        ax_m.set_title(f"{cond} left out (μ = {p.mu_N:.0f} N)\n" + "\n".join(lines), fontsize=9)
        log_axes(ax_m)
        ax_p.set_xlabel("frequency (Hz)")
        for ax in (ax_m, ax_p):
            ax.grid(which="both", alpha=0.25)
    axes[0, 0].set_ylabel("|H| (rad/N·m)")
    axes[1, 0].set_ylabel("phase (deg)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Leave-one-out: each point predicted by the models rebuilt without it")
    return fig


def _fmt(v: float | None, digits: int) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"
