"""``steerlab diagnose``: the whole diagnosis of a study directory (see docs/diagnosis.md)."""

from __future__ import annotations

import concurrent.futures as cf
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from steerlab.analysis.diagnosis import compare as C
from steerlab.analysis.diagnosis import engine
from steerlab.analysis.diagnosis.candidates import CANDIDATE_NAMES
from steerlab.analysis.diagnosis.data import (
    DiagnosisError,
    PreparedStudy,
    TrialData,
    prepare_study,
    recorded_rig_limits,
)
from steerlab.analysis.diagnosis.drift import DriftResult, TrialStiffness, analyse_drift
from steerlab.analysis.diagnosis.engine import (
    Selection,
    Setup,
    _limit_threads,
    build_setup,
    plausible_arm,
    refit_noise,
    select,
    set_remnants,
)
from steerlab.analysis.diagnosis.fit import (
    FitResult,
    best_start_arms,
    fit_model,
    noise_model,
    residual_vectors,
    whitened_power,
)
from steerlab.analysis.diagnosis.simulate import remnant_spectrum_fit, simulated_spectra
from steerlab.analysis.diagnosis.wheel import DiagnosisWheel, choose_wheel
from steerlab.analysis.rig_from_data import (
    RigFromData,
    RigFromDataError,
    identify,
    retime,
    stated_convention,
)
from steerlab.analysis.strict_json import json_clean
from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.hardware.sim.model_file import (
    ARM_KEYS,
    baseline_from_model,
    mechanisms_from_model,
    read_model_file,
    world_model_text,
)
from steerlab.hardware.sim.physiology import ArmParams
from steerlab.protocols.datafile import load_study
from steerlab.protocols.records import TrialRecord

ProgressCallback = Callable[[int, int, str], None]

# "Unexplained": what is left after the retained mechanisms, judged against the noise.
UNEXPLAINED_EXCITED_RATIO = 1.5  # whitened power at the excited bins, × the noise level …
UNEXPLAINED_EXCITED_Z = 6.0  # … and this far above it (z-score), in either channel
UNEXPLAINED_REPEAT_RATIO = 0.1  # repeatable share of the unexcited power …
UNEXPLAINED_REPEAT_Z = 6.0  # … and its z-score against zero


@dataclass
class DiagnosisResult:
    """What ``run_diagnosis`` found; ``to_dict()`` is diagnosis.json."""

    cause: str
    causes: list[str]
    candidates: dict[str, dict]
    gain: dict
    comparison: dict
    unexplained: dict | None
    data: dict
    notes: list[str]
    limits: list[str]
    out_dir: Path | None = None
    model_path: Path | None = None
    timing_s: dict = field(default_factory=dict)
    baseline_model: str | None = None
    # The wheel of the simulated world (analysis.diagnosis.wheel): DiagnosisWheel.to_dict(),
    # plus "check": the wheel fitted from the data and how well each wheel fits them.
    wheel: dict = field(default_factory=dict)
    wheel_sentence: str = ""
    # The wheel and the recording's timing identified from the data, and the convention the
    # simulated rig took from them (analysis.rig_from_data.RigFromData.to_dict()).
    rig_from_data: dict = field(default_factory=dict)
    rig_from_data_sentence: str = ""
    # Retained mechanism → the candidates that explain the data as well (engine.confusable).
    equally_good: dict[str, list[dict]] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return json_clean(
            {
                "format": "steerlab-diagnosis",
                "format_version": 1,
                "cause": self.cause,
                "causes": self.causes,
                "equally_good": self.equally_good,
                "baseline_model": self.baseline_model,
                "wheel": self.wheel,
                "rig_from_data": self.rig_from_data,
                "candidates": self.candidates,
                "gain": self.gain,
                "unexplained": self.unexplained,
                "comparison": self.comparison,
                "data": self.data,
                "notes": self.notes,
                "limits": self.limits,
                "model_file": str(self.model_path) if self.model_path else None,
                "timing_s": self.timing_s,
            }
        )

    def summary(self) -> str:
        lines = [f"wheel: {self.wheel_sentence}"] if self.wheel_sentence else []
        if self.rig_from_data_sentence:
            lines.append(f"rig and timing: {self.rig_from_data_sentence}")
        alt = self.equally_good.get(self.cause, [])
        if alt:
            names = " or ".join([self.cause] + [a["name"] for a in alt])
            lines.append(f"cause: {names} (the data cannot tell them apart)")
        else:
            lines.append(f"cause: {self.cause}")
        lines += _equally_good_lines(self.equally_good, self.candidates)
        if len(self.causes) > 1:
            lines.append("all causes (strongest first): " + ", ".join(self.causes))
        for name in self.causes:
            c = self.candidates.get(name, {})
            if c.get("forms_minus2loglik"):
                lines.append(f"  {name}: best-fitting form {form_sentence(c)}")
            for p in c.get("parameters", []):
                lo, hi = p["ci95"]
                lines.append(
                    f"  {name}.{p['parameter']} = {_fmt(p['value'])} {p['unit']} "
                    f"(95 % {_fmt(lo)} … {_fmt(hi)})"
                )
        g = self.gain.get("overall", {})
        signal = [c for c in self.causes if c not in ("drift", "unexplained")]
        if signal and g:
            lines.append(
                "held-out gain: VAF angle {:+.2f} pp, VAF torque {:+.2f} pp, FIT {:+.2f} pp; "
                "ΔBIC {:.1f}".format(
                    g.get("vaf_theta_pp", float("nan")),
                    g.get("vaf_td_pp", float("nan")),
                    g.get("fit_pp", float("nan")),
                    self.gain.get("delta_bic", float("nan")),
                )
            )
        d = self.gain.get("drift")
        if d:
            lines.append(
                "held-out gain of the drift term: VAF angle {:+.2f} pp, VAF torque {:+.2f} pp; "
                "ΔBIC {:.1f}".format(d["vaf_theta_pp"], d["vaf_td_pp"], d["delta_bic"])
            )
        if self.unexplained and self.unexplained.get("description"):
            lines.append("unexplained residual: " + self.unexplained["description"])
        for lim in self.limits:
            lines.append(f"limit: {lim}")
        if self.out_dir is not None:
            lines.append(f"report: {self.out_dir / 'index.html'}")
        if self.model_path is not None:
            lines.append(f"model: {self.model_path}")
        return "\n".join(lines)


def form_sentence(c: dict) -> str:
    """A candidate's best form, and the others as consistent with the data."""
    if c.get("only_first_step_form"):
        return c["form"] + " (the form of the first step; the others not screened at this step)"
    also = [f for f in c.get("forms_consistent_with_data", []) if f != c["form"]]
    return c["form"] + (f" (as consistent with the data: {'; '.join(also)})" if also else "")


def _equally_good_lines(equally_good: dict[str, list[dict]], candidates: dict) -> list[str]:
    """The evidence for each of two (or more) mechanisms that explain the data equally well."""
    lines = []
    for name, alts in equally_good.items():
        own = candidates.get(name, {})
        lines.append(
            f"  {name}: held-out gain {_fmt(own.get('held_out_gain_minus2loglik'))}, "
            f"ΔBIC {_fmt(own.get('delta_bic'))} (retained)"
        )
        for a in alts:
            params = ", ".join(f"{p['parameter']} = {_fmt(p['value'])}" for p in a["parameters"])
            lines.append(
                f"  {a['name']}: held-out gain {_fmt(a['held_out_gain_minus2loglik'])}, "
                f"ΔBIC {_fmt(a['delta_bic'])} ({params}); worse by {_fmt(a['worse_by'])} ± "
                f"{_fmt(a['se'])} on {a['criterion']}: within the noise"
            )
    return lines


def _fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.4g}"


class _Stages:
    """Coarse progress: one tick per stage."""

    STAGES = ("load", "baseline", "candidates", "drift", "compare", "report")

    def __init__(self, cb: ProgressCallback | None) -> None:
        self.cb = cb
        self.i = 0

    def __call__(self, label: str) -> None:
        if self.cb is not None:
            self.cb(min(self.i, len(self.STAGES)), len(self.STAGES), label)

    def next(self, label: str) -> None:
        self.i += 1
        self(label)


def rig_from_data(
    records: list[TrialRecord], wheel: DiagnosisWheel, keep_inertia: bool
) -> RigFromData | None:
    """The wheel and timing of the recording, from its data (analysis.rig_from_data): its
    inertia joins the simulated wheel unless ``keep_inertia`` (an option or a rig check's record
    names the wheel); its timing and rendering always, unless the recording states them. None
    where no trial can be used (the diagnosis then says why, trial by trial)."""
    try:
        stated = stated_convention(records)
    except ValueError as e:
        raise DiagnosisError(str(e)) from None
    try:
        found = identify(
            records,
            wheel.rendered,
            rig_label="the rig check" if wheel.measured else "the nominal wheel",
            stated=stated,
        )
    except RigFromDataError:
        return None
    if keep_inertia:
        c = found.convention
        found = replace(
            found,
            convention=replace(
                c, inertia_kgm2=wheel.rendered.inertia_kgm2, source={**c.source, "inertia": "rig"}
            ),
        )
    return found


def run_diagnosis(
    directory: str | Path,
    out: str | Path | None,
    *,
    jobs: int | None = 1,
    progress: ProgressCallback | None = None,
    model: str | Path | None = None,
    candidates: tuple[str, ...] | None = None,
    rig_model: str | Path | None = None,
    nominal_wheel: bool = False,
    inertia_kgm2: float | None = None,
    executor: cf.Executor | None = None,
) -> DiagnosisResult:
    """Diagnose the session files in ``directory``; write diagnosis.json, index.html and
    model.toml into ``out`` (unless None). ``model``: a model file whose mechanisms become the
    baseline (see docs/diagnosis.md: "diagnosing the extended model"). ``rig_model``: a rig
    check's rig.json, the wheel to simulate; ``nominal_wheel``: the nominal wheel even where
    the session files record a measured one; neither: the measured wheel the files record, if
    any (docs/diagnosis.md: "The wheel"). ``inertia_kgm2``: hold the arm inertia at this value
    (default: one per subject, fitted from the data). ``executor``: where the candidates'
    fits run (any ``concurrent.futures.Executor``: Dask's from ``--scheduler``); without one,
    ``jobs`` local processes."""
    with _limit_threads():
        return _run(
            directory, out, jobs, progress, model, candidates, rig_model, nominal_wheel,
            inertia_kgm2, executor,
        )  # fmt: skip


def _run(
    directory: str | Path,
    out: str | Path | None,
    jobs: int | None,
    progress: ProgressCallback | None,
    model: str | Path | None,
    candidates: tuple[str, ...] | None,
    rig_model: str | Path | None = None,
    nominal_wheel: bool = False,
    inertia_kgm2: float | None = None,
    executor: cf.Executor | None = None,
) -> DiagnosisResult:
    t0 = time.perf_counter()
    timing: dict[str, float] = {}
    stages = _Stages(progress)
    stages("load")
    choice = choose_wheel(directory, rig_model=rig_model, nominal=nominal_wheel)
    records = load_study(directory)
    # The actuator lag becomes the simulated loop's lag at the data's rate (τ = delay − h/2).
    wheel = choice.wheel(float(np.median([r.fs_hz for r in records])) if records else 1000.0)
    rig_wheel = wheel
    rig_data = rig_from_data(records, wheel, keep_inertia=wheel.measured or nominal_wheel)
    conv = rig_data.convention if rig_data is not None else None
    if conv is not None:
        records = [
            retime(r, conv.theta_offset_samples, conv.torque_offset_samples) for r in records
        ]
        if conv.inertia_kgm2 != wheel.rendered.inertia_kgm2:
            wheel = replace(wheel, rendered=replace(wheel.rendered, inertia_kgm2=conv.inertia_kgm2))
    rig_limits, limit_notes = recorded_rig_limits(directory)
    prep = prepare_study(
        records, wheel, inertia_kgm2, rig_limits,
        wheel_rendering=conv.rendering if conv is not None else "sampled",
        rig_wheel=rig_wheel,
    )  # fmt: skip
    prep.notes.extend(limit_notes)
    if conv is not None:
        prep.notes.extend(conv.notes)
        if rig_data is not None and conv.sensor_skew_samples:
            prep.notes.append(rig_data.sensor_skew_sentence() + ": left to the mechanisms")
    base_mech = Mechanisms()
    model_baseline = None
    base_drift = 0.0
    if model is not None:
        data = read_model_file(model)
        base_mech = mechanisms_from_model(data, str(model))
        model_baseline = baseline_from_model(data, str(model))
        base_drift = base_mech.drift.rate_per_trial
    base_mech, replaced = wheel.apply(base_mech)
    prep.notes.extend(choice.notes + replaced)
    names = tuple(candidates) if candidates is not None else CANDIDATE_NAMES
    unknown = set(names) - set(CANDIDATE_NAMES)
    if unknown:
        raise DiagnosisError(f"unknown candidate(s) {sorted(unknown)}; known: {CANDIDATE_NAMES}")
    timing["load"] = time.perf_counter() - t0

    stages.next("baseline")
    t1 = time.perf_counter()
    setup = build_setup(prep, base_mech, model_baseline)
    timing["baseline"] = time.perf_counter() - t1

    stages.next("candidates")
    t1 = time.perf_counter()
    signal_names = [n for n in names if n != "drift"]
    sel = select(setup, signal_names, jobs=max(1, jobs or 1), executor=executor)
    timing["candidates"] = time.perf_counter() - t1
    for what in sel.undone:
        prep.limits.append(
            f"time limit of the candidate stage ({engine.CANDIDATE_TIME_LIMIT_S:g} s of CPU "
            f"time, workers included; wall time on a scheduler) reached: {what}"
        )

    stages.next("drift")
    t1 = time.perf_counter()
    fam_arms = _fit_familiarization(setup, sel)
    drift = None
    if "drift" in names:
        drift = analyse_drift(_stiffness_rows(setup, sel.final, fam_arms), r0=base_drift)
    timing["drift"] = time.perf_counter() - t1

    stages.next("compare")
    t1 = time.perf_counter()
    result = _assemble(prep, setup, sel, drift, fam_arms, base_mech, model)
    # The rig's wheel; what the simulation took from the data beside it is in rig_from_data.
    result.wheel = {**rig_wheel.to_dict(), "check": prep.wheel_check}
    result.wheel_sentence = rig_wheel.sentence()
    if rig_data is not None:
        result.rig_from_data = rig_data.to_dict()
        result.rig_from_data_sentence = rig_data.sentence()
    timing["compare"] = time.perf_counter() - t1

    if out is not None:
        stages.next("report")
        t1 = time.perf_counter()
        out_dir = Path(out)
        out_dir.mkdir(parents=True, exist_ok=True)
        result.out_dir = out_dir
        result.model_path = out_dir / "model.toml"
        result.model_path.write_text(_model_text(prep, setup, sel, drift, result), "utf-8")
        from steerlab.analysis.diagnosis.report import write_html

        # The page shows the analysis' time; diagnosis.json gets the report's too.
        _close_timing(timing, t0, prep)
        result.timing_s = timing
        write_html(out_dir / "index.html", result, prep, setup, sel, drift)
        timing["report"] = time.perf_counter() - t1
        _close_timing(timing, t0, prep)
        (out_dir / "diagnosis.json").write_text(json.dumps(result.to_dict(), indent=1), "utf-8")
    else:
        _close_timing(timing, t0, prep)
        result.timing_s = timing
    stages.next("done")
    return result


# -- helpers --------------------------------------------------------------------------------------
def _close_timing(timing: dict[str, float], t0: float, prep: PreparedStudy) -> None:
    timing["total"] = time.perf_counter() - t0
    timing["per_subject"] = timing["total"] / max(len(prep.subjects), 1)


def _fit_familiarization(setup: Setup, sel: Selection) -> dict[str, ArmParams]:
    """Per-trial arms of the familiarization trials (drift axis only), fitted exactly as the
    measured trials' (same start values, two-stage noise model, as many remnant realisations
    for a nonlinear model), with the retained mechanisms fixed. A different treatment would
    bias the first trial of every condition, which the drift test would read as a trend."""
    fam = setup.fam
    if not fam:
        return {}
    spec = sel.final_spec
    mech = spec.mechanisms(sel.final.x)
    x = sel.final.x
    for t in fam:
        t.remnant = []
    # A subject's inertia is the one its measured trials gave (one familiarization trial per
    # condition would determine it poorly, and a different inertia would show as drift).
    inertia = sel.final.inertia

    def held(arm: ArmParams, t: TrialData) -> ArmParams:
        return replace(arm, I_i=inertia[t.subject]) if t.subject in inertia else arm

    start = {t.label: held(plausible_arm(t), t) for t in fam}
    noise = noise_model(fam, {t.label: simulated_spectra(t, start[t.label], mech) for t in fam})
    own = {t.label: held(t.arm0, t) for t in fam}
    arms = best_start_arms(fam, spec, noise, [start, own], x=x)
    first = fit_model(fam, spec, noise, arms, x0=x, fix_mechanisms=True, fit_inertia=False)
    set_remnants(fam, first.arms, setup.n_remnant)
    noise = noise_model(fam, first.simulated)
    return fit_model(
        fam, spec, noise, first.arms, x0=x, fix_mechanisms=True, fit_inertia=False
    ).arms


def _stiffness_rows(
    setup: Setup, final: FitResult, fam_arms: dict[str, ArmParams]
) -> list[TrialStiffness]:
    rows = []
    for t in setup.trials + setup.fam:
        arm = final.arms.get(t.label) or fam_arms.get(t.label)
        if arm is None or t.trial_index is None:
            continue
        rows.append(
            TrialStiffness(t.label, t.cell, int(t.trial_index), t.repetition, arm.k_i, arm.k_c)
        )
    return rows


def _unexplained(setup: Setup, fit: FitResult) -> dict | None:
    """Is a clear residual left? Judged with the noise re-estimated from ``fit``'s residual."""
    noise = refit_noise(setup, fit)
    exc = np.zeros(2)
    n_exc = 0
    by_cond: dict[str, list[float]] = {}
    by_freq: dict[str, list[float]] = {}
    for t in setup.trials:
        p = whitened_power(t, noise[t.label], fit.simulated[t.label])
        exc += p[:, t.excited].sum(axis=1)
        n_exc += int(np.count_nonzero(t.excited))
        by_cond.setdefault(t.condition, []).append(float(p[:, t.excited].mean()))
        f = t.freqs_hz[t.excited]
        pe = p[:, t.excited].mean(axis=0)
        for lo, hi in zip(C.FREQ_EDGES_HZ[:-1], C.FREQ_EDGES_HZ[1:], strict=True):
            m = (f >= lo) & (f < hi)
            if m.any():
                by_freq.setdefault(f"{lo:g}–{hi:g} Hz", []).append(float(pe[m].mean()))
    ratio = exc / max(n_exc, 1)
    # Σ|z|² over n complex values: mean n, SD √n (exponential terms).
    z_exc = (exc - n_exc) / math.sqrt(max(n_exc, 1))
    resid = {t.label: residual_vectors(t, fit.simulated[t.label]) for t in setup.trials}
    dist = C.distortion_table(setup.trials, resid, noise)
    rep_x = rep_n = 0.0
    rep_worst = None
    for r in dist["rows"]:
        if r["repeatable_vs_noise"] is None:
            continue
        nb = r["n_bins"]
        rep_x += r["repeatable_vs_noise"] * nb
        rep_n += nb
        if rep_worst is None or (r["repeatable_z"] or 0) > (rep_worst["repeatable_z"] or 0):
            rep_worst = r
    rep_ratio = rep_x / rep_n if rep_n else 0.0
    rep_z = rep_x / math.sqrt(rep_n / 2.0) if rep_n else 0.0
    flags = []
    channels = ("the wheel angle", "the wheel's equation (Tp − Td − wheel dynamics × θ)")
    for ch in range(2):
        if ratio[ch] > UNEXPLAINED_EXCITED_RATIO and z_exc[ch] > UNEXPLAINED_EXCITED_Z:
            worst_c = max(by_cond, key=lambda c: np.mean(by_cond[c]))
            worst_f = max(by_freq, key=lambda k: np.mean(by_freq[k]))
            flags.append(
                f"at the excited frequencies {channels[ch]} differs from the model by "
                f"{ratio[ch]:.1f}× the noise power (worst in {worst_c}, at {worst_f})"
            )
    if rep_ratio > UNEXPLAINED_REPEAT_RATIO and rep_z > UNEXPLAINED_REPEAT_Z and rep_worst:
        kind = {
            "harmonic2": "even-order (second-harmonic lines)",
            "harmonic3": "odd-order (third-harmonic lines)",
            "other": "intermodulation lines",
        }[rep_worst["lines"]]
        flags.append(
            "at unexcited frequencies a residual repeats from one repetition to the other "
            f"({100 * rep_ratio:.0f} % of the noise power; strongest: {kind}, "
            f"{rep_worst['channel']}, {rep_worst['f_lo_Hz']:g}–{rep_worst['f_hi_Hz']:g} Hz, "
            f"{rep_worst['condition']}): a deterministic response to the perturbation that the "
            "model does not produce"
        )
    stats = {
        "excited_power_vs_noise": {"angle": ratio[0], "wheel_equation": ratio[1]},
        "excited_z": {"angle": z_exc[0], "wheel_equation": z_exc[1]},
        "excited_power_vs_noise_by_condition": {c: float(np.mean(v)) for c, v in by_cond.items()},
        "excited_power_vs_noise_by_frequency": {k: float(np.mean(v)) for k, v in by_freq.items()},
        "repeatable_unexcited_vs_noise": rep_ratio,
        "repeatable_unexcited_z": rep_z,
        "within_noise": not flags,
        # What the residual would still gain if explained: the excess −2 log L over noise at
        # the excited bins of the flagged channels, and of the repeatable unexcited power.
        "excess_minus2loglik": float(
            2.0 * sum(exc[ch] - n_exc for ch in range(2) if ratio[ch] > UNEXPLAINED_EXCITED_RATIO)
            + (2.0 * rep_x if rep_ratio > UNEXPLAINED_REPEAT_RATIO else 0.0)
        ),
    }
    if not flags:
        return {"description": None, **stats}
    return {"description": "; ".join(flags), **stats}


def _sim_spectra(trials, arms, mech) -> dict[str, np.ndarray]:
    return {t.label: simulated_spectra(t, arms[t.label], mech) for t in trials}


def _candidate_table(sel: Selection, drift: DriftResult | None) -> dict[str, dict]:
    """Per candidate: its evaluation at the first step (against the baseline), and where it
    was retained, the step that retained it."""
    out: dict[str, dict] = {}
    for step in sel.steps:
        for r in step:
            d = r.to_dict()
            if r.name not in out:
                out[r.name] = {**d, "later_steps": []}
            else:
                out[r.name]["later_steps"].append(d)
    for r in sel.retained:
        out[r.name]["retained"] = True
        out[r.name]["retained_at_step"] = r.step
        # The form retained (the family's best at that step) and those as consistent with it.
        out[r.name]["form"] = r.form
        out[r.name]["forms_minus2loglik"] = r.form_m2ll
        out[r.name]["forms_consistent_with_data"] = r.forms_consistent
        out[r.name]["only_first_step_form"] = r.only_first_form
        # The retained model's parameters (all its data; nonlinear ones refined at the end).
        out[r.name]["parameters"] = [p for p in sel.final.parameters() if p["mechanism"] == r.name]
    for d in out.values():
        d.setdefault("retained", False)
    if drift is not None:
        out["drift"] = {**drift.to_dict(), "retained": drift.passed}
    return out


def _assemble(
    prep: PreparedStudy,
    setup: Setup,
    sel: Selection,
    drift: DriftResult | None,
    fam_arms: dict[str, ArmParams],
    base_mech: Mechanisms,
    model: str | Path | None,
) -> DiagnosisResult:
    trials = setup.trials
    base, final = sel.base, sel.final
    as_sel = sel.final_as_selected or final
    final_mech = sel.final_spec.mechanisms(final.x)
    # Strongest first, by how much −2 log L each explains (a mechanism: its drop when it was
    # retained; "unexplained": the excess it leaves). A residual far larger than what the
    # retained mechanisms explain makes them partial explanations and the cause unexplained.
    strength = {r.name: r.delta_m2ll for r in sel.retained}
    if drift is not None and drift.passed:
        strength["drift"] = drift.delta_m2ll
    unexplained = _unexplained(setup, final)
    if unexplained and unexplained["description"]:
        strength["unexplained"] = unexplained["excess_minus2loglik"]
    causes = sorted(strength, key=lambda n: -strength[n])
    cause = causes[0] if causes else "none"

    sims = {
        "paper": C.compare_trials(trials, setup.paper_arms, base_mech),
        "baseline": C.compare_trials(trials, base.arms, base_mech),
        "extended": C.compare_trials(trials, final.arms, final_mech),
    }
    spectra = {
        "paper": _sim_spectra(trials, setup.paper_arms, base_mech),
        "baseline": base.simulated,
        "extended": final.simulated,
    }
    frfs = C.condition_frfs(trials, setup.noise, spectra)
    resid = {
        m: {t.label: residual_vectors(t, spectra[m][t.label]) for t in trials}
        for m in ("baseline", "extended")
    }
    all_arms = {**final.arms, **fam_arms}
    fam_sims = C.compare_trials(setup.fam, fam_arms, final_mech) if fam_arms else {}
    comparison = {
        "vaf": {m: C.vaf_table(trials, s) for m, s in sims.items()},
        "vaf_per_trial": {
            t.label: {
                m: {"theta": s[t.label].vaf_theta(t), "td": s[t.label].vaf_td(t)}
                for m, s in sims.items()
            }  # fmt: skip
            for t in trials
        },
        "fit_percent_per_trial": {
            t.label: {m: C.trial_fit_percent(t, spectra[m][t.label]) for m in spectra}
            for t in trials
        },
        "frf_outside_ci95": {m: C.frf_mismatch(frfs, m) for m in spectra},
        "frf": [f.to_dict() for f in frfs],
        "unexcited": {m: C.distortion_table(trials, resid[m], setup.noise) for m in resid},
        "residual_vs_grip": {
            m: C.residual_vs_grip(trials, sims[m]) for m in ("baseline", "extended")
        },
        "residual_vs_amplitude": {
            m: C.residual_vs_amplitude(trials, sims[m]) for m in ("baseline", "extended")
        },
        "residual_vs_order": C.residual_vs_order(
            trials + setup.fam, all_arms, {**sims["extended"], **fam_sims}
        ),
        "fit_quality": {
            "baseline": {
                "lack_of_fit": base.lack_of_fit,
                "minus2loglik": base.m2ll,
                "bic": base.bic,
                "n_params": base.n_params,
                "n_obs": base.n_obs,
            },
            "extended": {
                "lack_of_fit": as_sel.lack_of_fit,
                "minus2loglik": as_sel.m2ll,
                "bic": as_sel.bic,
                "n_params": as_sel.n_params,
                "n_obs": as_sel.n_obs,
            },
        },  # fmt: skip
    }
    gain = _gain(setup, sel, drift, frfs)
    cand = _candidate_table(sel, drift)
    data = {
        "subjects": prep.subjects,
        "conditions": prep.conditions,
        "n_trials": len(trials),
        "n_familiarization_trials": len(setup.fam),
        "sample_rates_Hz": sorted({t.fs_hz for t in trials}),
        "skipped": [{"trial": a, "reason": b} for a, b in prep.skipped],
        "held_out_folds": [
            {"train": sorted({t.repetition for t in a}), "test": sorted({t.repetition for t in b})}
            for a, b in setup.folds
        ],
        "arms": {lab: a.__dict__ for lab, a in final.arms.items()},
        # One per subject, fitted with each model (baseline, retained model): a mechanism
        # that looks like inertia in part moves it (docs/diagnosis.md).
        "arm_inertia_kgm2": {"baseline": base.inertia, "extended": final.inertia},
        "remnant": _remnant_table(setup, final),
    }
    notes = list(prep.notes)
    if model is not None:
        notes.append(
            f"baseline: the model file {Path(model).name} (its mechanisms, with their "
            "parameters as given, are part of the baseline; a candidate of the same name "
            "re-fits them)"
        )
    return DiagnosisResult(
        cause=cause,
        causes=causes,
        candidates=cand,
        gain=gain,
        comparison=comparison,
        unexplained=unexplained,
        data=data,
        notes=notes,
        limits=list(prep.limits),
        baseline_model=str(model) if model is not None else None,
        equally_good={r.name: r.equally_good for r in sel.retained if r.equally_good},
    )


def _gain(setup: Setup, sel: Selection, drift: DriftResult | None, frfs: list) -> dict:
    """Held-out VAF and FIT% before (baseline) and after (retained model), per condition."""
    base, final = sel.base, sel.final
    spec = sel.final_spec
    as_sel = sel.final_as_selected or final
    d_bic = as_sel.bic - base.bic
    out: dict[str, Any] = {
        "method": (
            "each repetition predicted by the model fitted on the other: the retained "
            "mechanisms' parameters come from the other repetition; every trial's own arm "
            "parameters (which every model has, the baseline included) are fitted on it"
        ),
        "delta_bic": d_bic,
        "delta_minus2loglik": base.m2ll - as_sel.m2ll,
    }
    per_cond: dict[str, dict[str, Any]] = {}
    if not setup.folds:
        out["held_out"] = False
        out["overall"] = {}
        out["per_condition"] = {}
        return out
    before: dict[str, C.TrialComparison] = {}
    after: dict[str, C.TrialComparison] = {}
    fit_b: dict[str, float] = {}
    fit_a: dict[str, float] = {}
    base_mech = setup.base_mech
    for (_train, test), x in zip(setup.folds, sel.final_fold_x, strict=True):
        if spec.n_free:
            with C.few_remnants(test):
                te = fit_model(test, spec, setup.noise, final.arms, x0=x, fix_mechanisms=True)
            arms_after, mech_after = te.arms, spec.mechanisms(x)
            Y_after = te.simulated
        else:
            arms_after, mech_after = base.arms, base_mech
            Y_after = {t.label: base.simulated[t.label] for t in test}
        before.update(C.compare_trials(test, base.arms, base_mech))
        after.update(C.compare_trials(test, arms_after, mech_after))
        for t in test:
            fit_b[t.label] = C.trial_fit_percent(t, base.simulated[t.label])
            fit_a[t.label] = C.trial_fit_percent(t, Y_after[t.label])
    tested = [t for t in setup.trials if t.label in before]
    vb, va = C.vaf_table(tested, before), C.vaf_table(tested, after)
    for c in vb:
        ts = tested if c == "all" else [t for t in tested if t.condition == c]
        fb = float(np.nanmean([fit_b[t.label] for t in ts]))
        fa = float(np.nanmean([fit_a[t.label] for t in ts]))
        m2_b = 2.0 * sum(base.cost_trial[t.label] for t in ts)
        m2_a = 2.0 * sum(as_sel.cost_trial[t.label] for t in ts)
        n_obs = 2 * sum(len(t.bins) for t in ts)
        per_cond[c] = {
            "vaf_theta_before": vb[c]["vaf_theta_percent"],
            "vaf_theta_after": va[c]["vaf_theta_percent"],
            "vaf_theta_pp": va[c]["vaf_theta_percent"] - vb[c]["vaf_theta_percent"],
            "vaf_td_before": vb[c]["vaf_td_percent"],
            "vaf_td_after": va[c]["vaf_td_percent"],
            "vaf_td_pp": va[c]["vaf_td_percent"] - vb[c]["vaf_td_percent"],
            "fit_before": fb,
            "fit_after": fa,
            "fit_pp": fa - fb,
            # In-sample, on all trials of the condition; shared mechanism parameters are
            # counted in full for each condition, as if fitted to it alone.
            "delta_minus2loglik": m2_b - m2_a,
            "delta_bic": -(m2_b - m2_a) + spec.n_free * math.log(max(n_obs, 2)),
            "n_trials": vb[c]["n_trials"],
        }
    out["held_out"] = True
    out["overall"] = per_cond.pop("all")
    out["per_condition"] = per_cond
    if drift is not None and drift.passed:
        out["drift"] = _drift_gain(setup, sel, drift)
    return out


def _drift_gain(setup: Setup, sel: Selection, drift: DriftResult) -> dict:
    """Held-out gain of the drift term: each repetition's arm predicted from the other
    repetition's, scaled by the drift between their trial indices, against unscaled."""
    final = sel.final
    mech = sel.final_spec.mechanisms(final.x)
    cells: dict[tuple[str, str], list[TrialData]] = {}
    for t in setup.trials:
        cells.setdefault(t.cell, []).append(t)
    pairs_b, pairs_a = [], []
    for items in cells.values():
        for t in items:
            other = [o for o in items if o is not t and o.trial_index is not None]
            if not other or t.trial_index is None:
                continue
            o = other[0]
            o_index = o.trial_index
            assert o_index is not None  # (filtered above)
            arm = final.arms[o.label]
            f = drift.factor(t.trial_index) / drift.factor(o_index)
            f_c = f if "k_c" in drift.form.stiffnesses else 1.0
            with C.few_remnants([t]):
                th_b, td_b = C.simulated_segment(t, arm, mech)
                th_a, td_a = C.simulated_segment(
                    t, replace(arm, k_i=arm.k_i * f, k_c=arm.k_c * f_c), mech
                )
            pairs_b.append((t, th_b, td_b))
            pairs_a.append((t, th_a, td_a))
    if not pairs_b:
        return {}
    vb_th = C.pooled_vaf([(t.theta, th) for t, th, _ in pairs_b])
    va_th = C.pooled_vaf([(t.theta, th) for t, th, _ in pairs_a])
    vb_td = C.pooled_vaf([(t.td, td) for t, _, td in pairs_b])
    va_td = C.pooled_vaf([(t.td, td) for t, _, td in pairs_a])
    return {
        "method": "each trial simulated with the arm fitted on the other repetition of its "
        "condition, with and without the drift between their positions",
        "vaf_theta_before": vb_th,
        "vaf_theta_after": va_th,
        "vaf_theta_pp": va_th - vb_th,
        "vaf_td_before": vb_td,
        "vaf_td_after": va_td,
        "vaf_td_pp": va_td - vb_td,
        "delta_bic": drift.delta_bic,
    }


def _remnant_table(setup: Setup, fit: FitResult) -> dict[str, dict]:
    out = {}
    for t in setup.trials:
        sd, fc = remnant_spectrum_fit(t, fit.arms[t.label])
        out[t.label] = {"remnant_sd_Nm": sd, "remnant_corner_Hz": fc}
    return out


def _gmean(x: list[float]) -> float:
    x = [v for v in x if v is not None and np.isfinite(v) and v > 0]
    return float(np.exp(np.mean(np.log(x)))) if x else float("nan")


def _model_text(
    prep: PreparedStudy,
    setup: Setup,
    sel: Selection,
    drift: DriftResult | None,
    result: DiagnosisResult,
) -> str:
    final = sel.final
    mech = sel.final_spec.mechanisms(final.x)
    fitted: dict[str, list[dict]] = {}
    for p in final.parameters():
        fitted.setdefault(p["mechanism"], []).append(p)
    if drift is not None and drift.passed:
        mech = replace(mech, drift=drift.mechanism())
        fitted["drift"] = drift.to_dict()["parameters"]
    baseline: dict[str, dict[str, Any]] = {}
    rem = result.data["remnant"]
    for cond in prep.conditions:
        ts = [t for t in setup.trials if t.condition == cond]
        subjects = sorted({t.subject for t in ts})
        vals: dict[str, Any] = {}
        per_subj: dict[str, dict[str, list[float]]] = {s: {} for s in subjects}
        for t in ts:
            arm = final.arms[t.label]
            d = per_subj[t.subject]
            for a in ARM_KEYS:
                d.setdefault(a, []).append(getattr(arm, a))
            g = t.grip[t.start : t.stop]
            d.setdefault("grip_mean", []).append(float(np.mean(g)))
            d.setdefault("grip_sd", []).append(float(np.std(g)))
            d.setdefault("rem_sd", []).append(rem[t.label]["remnant_sd_Nm"])
            d.setdefault("rem_fc", []).append(rem[t.label]["remnant_corner_Hz"])
        subj_means = {s: {k: _gmean(v) for k, v in d.items()} for s, d in per_subj.items()}
        for a, key in ARM_KEYS.items():
            vals[key] = _gmean([m[a] for m in subj_means.values()])
        vals["grip_mean_N"] = _gmean([m["grip_mean"] for m in subj_means.values()])
        vals["grip_sd_N"] = _gmean([m["grip_sd"] for m in subj_means.values()])
        vals["remnant_sd_Nm"] = _gmean([m["rem_sd"] for m in subj_means.values()])
        vals["remnant_corner_Hz"] = _gmean([m["rem_fc"] for m in subj_means.values()])
        vals["n_subjects"] = len(subjects)
        if len(subjects) > 1:
            for a in ("k_i", "k_c", "b_i", "b_c"):
                lv = np.log([m[a] for m in subj_means.values()])
                vals[f"{a}_between_subject_cv"] = float(np.std(lv, ddof=1))
        baseline[cond] = vals
    header = {
        "fs_hz": float(np.median([t.fs_hz for t in setup.trials])),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "cause": result.cause,
        "causes": result.causes,
        "wheel": result.wheel.get("source", "nominal"),
    }
    comments = [
        "Steerlab world model, written by `steerlab diagnose` (docs/diagnosis.md).",
        "Simulate with it: steerlab simulate --model model.toml --subjects N --out DIR",
        "[baseline.*]: the typical subject per condition (geometric mean over subjects); "
        "[mechanisms.*]: the retained mechanisms, fitted parameters with se and ci95.",
    ]
    # What the diagnosis simulated, for the record: replays (simulate --model) clip at
    # Steerlab's limits all the same (a model file must not lift or set a safety limit).
    limits = sorted({(t.safety.max_torque_nm, t.safety.max_slew_nm_per_s) for t in setup.trials})
    if all(torque >= engine.UNLIMITED.max_torque_nm for torque, _ in limits):
        header["rig_command_limits"] = "none"
        comments.append(
            "The recording's rig applied commands beyond Steerlab's limits: the diagnosis "
            "simulated it without them (rig_command_limits)"
        )
    else:
        tables = [{"max_torque_nm": a, "max_slew_nm_per_s": b} for a, b in limits]
        header["rig_command_limits"] = tables[0] if len(tables) == 1 else tables
        comments.append(
            "rig_command_limits: the recording's limits the diagnosis simulated (not applied "
            "by simulate --model, which clips at the simulated rig's own)"
        )
    rig_json = result.wheel.get("rig_json")
    if rig_json:
        # The measured wheel's friction, imbalance and lag are among [mechanisms.*]; its
        # inertia, damping and stiffness are not, so the model needs the rig check with it.
        header["rig_model"] = str(rig_json)
        comments.append(
            f"Diagnosed with the wheel measured by a rig check ({rig_json}): simulate with "
            f"--rig-model {rig_json} as well"
        )
    return world_model_text(baseline, mech, fitted, header, comments)
