"""What the simulation gets wrong: measured against simulated, in every view the issue asks for.

All comparisons drive the simulator with the measured perturbation torque (and the measured
grip force) at the data's sample rate; the model's prediction is its deterministic response
(the remnant cannot be reproduced sample by sample, so it stays in the residual).

- Time domain: VAF of the wheel angle and of the driver torque per trial,
  VAF = 100·(1 − Σ(y − ŷ)²/Σy²) over the analysed segment, both mean-free.
- Excited frequencies, per condition (all subjects' trials pooled): Tp→θ, Tp→Td and the
  admittance θ/Td per band of the design, measured with its 95 % interval (from the noise at
  the unexcited bins) and simulated by each model (same estimator on the simulated spectra).
- Unexcited frequencies: power the linear baseline leaves there, split into what repeats from
  one repetition to the other (distortion: the perturbation is identical in every trial, so
  a deterministic response to it repeats) and what does not (noise), and by the kind of line:
  second harmonics of excited bins (even-order distortion), third harmonics (odd-order), and
  the rest (intermodulation and noise).
- Residuals against grip force within a trial, against trial order and repetition, and
  against deflection amplitude.
- FIT% (the paper's, frequency domain) of each trial's measured admittance against the
  model's, over the design's bands: 100·(1 − Σ(1/f)|Ĥ − H_m|² / Σ(1/f)|H_m|²).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from steerlab.analysis.armfit import fit_percent
from steerlab.analysis.diagnosis.data import TrialData
from steerlab.analysis.diagnosis.fit import NoiseModel
from steerlab.analysis.diagnosis.simulate import simulated_segment
from steerlab.analysis.study import _condition_key
from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.hardware.sim.physiology import ArmParams


def vaf(y: np.ndarray, yhat: np.ndarray) -> float:
    y = np.asarray(y) - np.mean(y)
    yhat = np.asarray(yhat) - np.mean(yhat)
    tot = float(np.sum(y * y))
    return 100.0 * (1.0 - float(np.sum((y - yhat) ** 2)) / tot) if tot > 0 else float("nan")


def pooled_vaf(pairs: Sequence[tuple[np.ndarray, np.ndarray]]) -> float:
    err = sum(float(np.sum((y - y.mean() - (h - h.mean())) ** 2)) for y, h in pairs)
    tot = sum(float(np.sum((y - y.mean()) ** 2)) for y, _ in pairs)
    return 100.0 * (1.0 - err / tot) if tot > 0 else float("nan")


@dataclass
class TrialComparison:
    label: str
    condition: str
    subject: str
    repetition: int
    trial_index: int | None
    theta_sim: np.ndarray
    td_sim: np.ndarray

    def vaf_theta(self, t: TrialData) -> float:
        return vaf(t.theta, self.theta_sim)

    def vaf_td(self, t: TrialData) -> float:
        return vaf(t.td, self.td_sim)


DISPLAY_REMNANTS = 2  # remnant realisations for the views and gains of nonlinear models


@contextmanager
def few_remnants(trials: Sequence[TrialData], k: int = DISPLAY_REMNANTS) -> Iterator[None]:
    """Temporarily at most ``k`` remnant realisations per trial: the comparisons need no more
    than the screening used (the retained parameters were fitted with more)."""
    kept = {t.label: t.remnant for t in trials}
    for t in trials:
        t.remnant = t.remnant[:k]
    try:
        yield
    finally:
        for t in trials:
            t.remnant = kept[t.label]


def compare_trials(
    trials: Sequence[TrialData], arms: dict[str, ArmParams], mech: Mechanisms
) -> dict[str, TrialComparison]:
    out = {}
    for t in trials:
        with few_remnants([t]):
            th, td = simulated_segment(t, arms[t.label], mech)
        out[t.label] = TrialComparison(
            t.label, t.condition, t.subject, t.repetition, t.trial_index, th, td
        )
    return out


def vaf_table(
    trials: Sequence[TrialData], sims: dict[str, TrialComparison]
) -> dict[str, dict[str, float]]:
    """Pooled VAF of θ and Td per condition and overall ("all")."""
    groups: dict[str, list[TrialData]] = {}
    for t in trials:
        if t.label in sims:
            groups.setdefault(t.condition, []).append(t)
    out: dict[str, dict[str, float]] = {}
    keys = sorted(groups, key=_condition_key) + ["all"]
    for c in keys:
        ts = [t for t in trials if t.label in sims] if c == "all" else groups[c]
        out[c] = {
            "vaf_theta_percent": pooled_vaf([(t.theta, sims[t.label].theta_sim) for t in ts]),
            "vaf_td_percent": pooled_vaf([(t.td, sims[t.label].td_sim) for t in ts]),
            "n_trials": len(ts),
        }
    return out


# -- excited frequencies --------------------------------------------------------------------------
def _bands_of(t: TrialData) -> tuple[np.ndarray, np.ndarray]:
    """Index into t.bins of the excited bins and their design band."""
    n_per = t.selection.n_periods
    exc = t.excitation
    pos = {int(b): i for i, b in enumerate(t.bins)}
    idx, band = [], []
    for b, j in zip(exc.bins, exc.band_of_bin, strict=True):
        i = pos.get(int(b) * n_per)
        if i is not None:
            idx.append(i)
            band.append(int(j))
    return np.array(idx, dtype=int), np.array(band, dtype=int)


def _noise_cov(t: TrialData, S: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per bin: var(e_θ), var(e_Td), E[e_θ conj e_Td] from the (e_θ, wheel) covariance."""
    zw = t.Zw[idx]
    s11, s21, s22 = S[idx, 0, 0].real, S[idx, 1, 0], S[idx, 1, 1].real
    # e_Td = v2 − Z_w v1
    var_th = s11
    var_td = s22 + np.abs(zw) ** 2 * s11 - 2 * np.real(np.conj(zw) * s21)
    cov = np.conj(s21) - np.conj(zw) * s11  # E[v1 conj(v2 − Z_w v1)]
    return var_th, var_td, cov


@dataclass
class ConditionFRF:
    condition: str
    f_hz: np.ndarray
    measured: dict[str, np.ndarray]  # "theta", "td", "adm" → complex per band
    sd: dict[str, np.ndarray]  # standard deviation per band (complex error, |·|)
    simulated: dict[str, dict[str, np.ndarray]]  # model name → channel → complex

    def to_dict(self) -> dict:
        def cx(z: np.ndarray) -> dict:
            return {
                "magnitude": np.abs(z).tolist(),
                "phase_deg": np.degrees(np.unwrap(np.angle(z))).tolist(),
            }

        return {
            "condition": self.condition,
            "frequencies_Hz": self.f_hz.tolist(),
            "measured": {k: {**cx(v), "sd": self.sd[k].tolist()} for k, v in self.measured.items()},
            "simulated": {m: {k: cx(v) for k, v in d.items()} for m, d in self.simulated.items()},
            "units": {"theta": "rad/N·m (Tp→θ)", "td": "1 (Tp→Td)", "adm": "rad/N·m (θ/Td)"},
        }


def condition_frfs(
    trials: Sequence[TrialData],
    noise: NoiseModel,
    models: dict[str, dict[str, np.ndarray]],
) -> list[ConditionFRF]:
    """Per condition: measured and simulated (per model: label → simulated spectra)."""
    out = []
    conds = sorted({t.condition for t in trials}, key=_condition_key)
    for c in conds:
        ts = [t for t in trials if t.condition == c]
        idx0, band0 = _bands_of(ts[0])
        nb = int(band0.max()) + 1
        acc = {k: np.zeros(nb, dtype=complex) for k in ("tt", "td", "pp")}
        sims = {m: {k: np.zeros(nb, dtype=complex) for k in ("tt", "td")} for m in models}
        f_acc = np.zeros(nb)
        cnt = np.zeros(nb)
        per_bin = []
        for t in ts:
            idx, band = _bands_of(t)
            if len(idx) != len(idx0) or not np.array_equal(band, band0):
                continue  # another design: not pooled
            tp = t.Tp[idx]
            acc["tt"] += _bc(band, np.conj(tp) * t.Y[0, idx], nb)
            acc["td"] += _bc(band, np.conj(tp) * t.Y[1, idx], nb)
            acc["pp"] += _bc(band, np.abs(tp) ** 2, nb)
            f_acc += np.bincount(band, t.freqs_hz[idx], nb)
            cnt += np.bincount(band, minlength=nb)
            vt, vd, cv = _noise_cov(t, noise[t.label], idx)
            per_bin.append((band, np.abs(tp) ** 2, vt, vd, cv))
            for m, Ys in models.items():
                Y = Ys[t.label]
                sims[m]["tt"] += _bc(band, np.conj(tp) * Y[0, idx], nb)
                sims[m]["td"] += _bc(band, np.conj(tp) * Y[1, idx], nb)
        pp = acc["pp"].real
        G_th = acc["tt"] / pp
        G_td = acc["td"] / pp
        H = acc["tt"] / acc["td"]
        v_th = np.zeros(nb)
        v_td = np.zeros(nb)
        v_h = np.zeros(nb)
        for band, p2, vt, vd, cv in per_bin:
            v_th += np.bincount(band, p2 * vt, nb)
            v_td += np.bincount(band, p2 * vd, nb)
            Hb = H[band]
            v_h += np.bincount(
                band, p2 * (vt + np.abs(Hb) ** 2 * vd - 2 * np.real(np.conj(Hb) * cv)), nb
            )
        frf = ConditionFRF(
            condition=c,
            f_hz=f_acc / np.maximum(cnt, 1),
            measured={"theta": G_th, "td": G_td, "adm": H},
            sd={
                "theta": np.sqrt(v_th) / pp,
                "td": np.sqrt(v_td) / pp,
                "adm": np.sqrt(np.maximum(v_h, 0)) / np.abs(acc["td"]),
            },
            simulated={
                m: {
                    "theta": d["tt"] / pp,
                    "td": d["td"] / pp,
                    "adm": d["tt"] / d["td"],
                }
                for m, d in sims.items()
            },
        )
        out.append(frf)
    return out


def _bc(band: np.ndarray, w: np.ndarray, nb: int) -> np.ndarray:
    w = np.asarray(w)
    if np.iscomplexobj(w):
        return np.bincount(band, w.real, nb) + 1j * np.bincount(band, w.imag, nb)
    return np.bincount(band, w, nb)


def frf_mismatch(frfs: Sequence[ConditionFRF], model: str) -> dict[str, float]:
    """Share of bands where the model lies outside the measurement's 95 % interval."""
    out = {}
    for ch in ("theta", "td", "adm"):
        outside = total = 0
        for c in frfs:
            d = np.abs(c.simulated[model][ch] - c.measured[ch])
            ok = np.isfinite(d) & np.isfinite(c.sd[ch])
            outside += int(np.sum(d[ok] > 1.96 * c.sd[ch][ok]))
            total += int(np.sum(ok))
        out[ch] = outside / total if total else float("nan")
    return out


def trial_fit_percent(t: TrialData, Ysim: np.ndarray) -> float:
    """The paper's FIT% of the trial's admittance per design band against the model's."""
    idx, band = _bands_of(t)
    if len(idx) == 0:
        return float("nan")
    nb = int(band.max()) + 1
    tp = t.Tp[idx]
    num = _bc(band, np.conj(tp) * t.Y[0, idx], nb)
    den = _bc(band, np.conj(tp) * t.Y[1, idx], nb)
    num_s = _bc(band, np.conj(tp) * Ysim[0, idx], nb)
    den_s = _bc(band, np.conj(tp) * Ysim[1, idx], nb)
    f = np.bincount(band, t.freqs_hz[idx], nb) / np.maximum(np.bincount(band, minlength=nb), 1)
    return fit_percent(f, num / den, num_s / den_s)


# -- unexcited frequencies ----------------------------------------------------------------------
LINE_CLASSES = ("harmonic2", "harmonic3", "other")


def line_classes(t: TrialData) -> dict[str, np.ndarray]:
    """Boolean masks over t.bins: unexcited bins at 2× and 3× an excited bin, and the rest."""
    ex = t.bins[t.excited]
    nonex = ~t.excited
    h2 = nonex & np.isin(t.bins, 2 * ex)
    h3 = nonex & np.isin(t.bins, 3 * ex) & ~h2
    return {"harmonic2": h2, "harmonic3": h3, "other": nonex & ~h2 & ~h3}


FREQ_EDGES_HZ = (0.0, 0.7, 2.0, 6.0, 25.0)


def distortion_table(
    trials: Sequence[TrialData], residual: dict[str, np.ndarray], noise: NoiseModel
) -> dict:
    """Whitened power left at unexcited bins, split into repeatable (distortion) and not.

    ``residual``: label → (2, n_bins) residual vectors (angle, wheel equation). For each
    condition, frequency range and line class: mean whitened power (1 = noise level), and
    the part that repeats between repetitions of the same subject × condition, estimated by
    the cross-power Re(z₁ z₂*) of their whitened residuals (zero mean for independent noise);
    ``z`` is its z-score against zero.
    """
    from steerlab.analysis.diagnosis.fit import whitener

    cells: dict[tuple[str, str], list[TrialData]] = {}
    for t in trials:
        cells.setdefault(t.cell, []).append(t)
    acc: dict[tuple[str, str, str, int], list[float]] = {}
    for items in cells.values():
        zs = []
        for t in items:
            z = whitener(t, noise[t.label])(residual[t.label])
            n = len(t.bins)
            zc = np.array([z[:n] + 1j * z[n : 2 * n], z[2 * n : 3 * n] + 1j * z[3 * n :]])
            zs.append((t, zc))
        for t, zc in zs:
            classes = line_classes(t)
            f = t.freqs_hz
            for cls, mask in classes.items():
                for r, (lo, hi) in enumerate(
                    zip(FREQ_EDGES_HZ[:-1], FREQ_EDGES_HZ[1:], strict=True)
                ):
                    m = mask & (f >= lo) & (f < hi)
                    for ch, name in enumerate(("angle", "wheel")):
                        a = acc.setdefault((t.condition, cls, name, r), [0.0, 0.0, 0.0, 0.0])
                        a[0] += float(np.sum(np.abs(zc[ch, m]) ** 2))
                        a[1] += float(np.count_nonzero(m))
        # Cross-power between two repetitions of the same cell.
        if len(zs) >= 2 and len(zs[0][0].bins) == len(zs[1][0].bins):
            (t1, z1), (_, z2) = zs[0], zs[1]
            classes = line_classes(t1)
            f = t1.freqs_hz
            for cls, mask in classes.items():
                for r, (lo, hi) in enumerate(
                    zip(FREQ_EDGES_HZ[:-1], FREQ_EDGES_HZ[1:], strict=True)
                ):
                    m = mask & (f >= lo) & (f < hi)
                    for ch, name in enumerate(("angle", "wheel")):
                        a = acc[(t1.condition, cls, name, r)]
                        a[2] += float(np.sum(np.real(z1[ch, m] * np.conj(z2[ch, m]))))
                        a[3] += float(np.count_nonzero(m))
    rows = []
    for (cond, cls, channel, band), (power, n_bins, cross, n_cross) in sorted(
        acc.items(), key=lambda kv: (_condition_key(kv[0][0]), kv[0][1:])
    ):
        if n_bins == 0:
            continue
        rows.append(
            {
                "condition": cond,
                "lines": cls,
                "channel": channel,
                "f_lo_Hz": FREQ_EDGES_HZ[band],
                "f_hi_Hz": FREQ_EDGES_HZ[band + 1],
                "n_bins": int(n_bins),
                "power_vs_noise": power / n_bins,
                "repeatable_vs_noise": cross / n_cross if n_cross else None,
                "repeatable_z": cross / np.sqrt(n_cross / 2.0) if n_cross else None,
            }
        )
    return {"rows": rows, "classes": list(LINE_CLASSES), "freq_edges_Hz": list(FREQ_EDGES_HZ)}


# -- residual against grip, order, amplitude ------------------------------------------------------
def residual_vs_grip(
    trials: Sequence[TrialData], sims: dict[str, TrialComparison], n_bins: int = 5
) -> dict:
    """Per condition and grip quintile (of the trial's low-passed grip force around its mean):
    the residual driver torque regressed on the simulated angle, an "unmodelled stiffness"
    (N·m/rad). A stiffness that follows grip force rises from the low to the high quintile."""
    out: dict[str, list] = {}
    for c in sorted({t.condition for t in trials}, key=_condition_key):
        num = np.zeros(n_bins)
        den = np.zeros(n_bins)
        g_sum = np.zeros(n_bins)
        g_n = np.zeros(n_bins)
        for t in (t for t in trials if t.condition == c and t.label in sims):
            g = t.grip[t.start : t.stop]
            dg = (g - g.mean()) / max(g.mean(), 1e-9)
            edges = np.quantile(dg, np.linspace(0, 1, n_bins + 1))
            q = np.clip(np.searchsorted(edges, dg, side="right") - 1, 0, n_bins - 1)
            e = t.td - sims[t.label].td_sim
            th = sims[t.label].theta_sim
            num += np.bincount(q, e * th, n_bins)
            den += np.bincount(q, th * th, n_bins)
            g_sum += np.bincount(q, dg, n_bins)
            g_n += np.bincount(q, minlength=n_bins)
        out[c] = [
            {
                "grip_rel_mean": float(g_sum[i] / g_n[i]) if g_n[i] else None,
                "unmodelled_stiffness_Nm_per_rad": float(num[i] / den[i]) if den[i] else None,
            }
            for i in range(n_bins)
        ]
    return out


def residual_vs_amplitude(
    trials: Sequence[TrialData], sims: dict[str, TrialComparison], n_bins: int = 5
) -> dict:
    """Per condition and quintile of the simulated deflection |θ|: RMS of the residual angle and
    driver torque there, relative to the trial's overall residual RMS (1 everywhere for a
    residual that does not depend on amplitude)."""
    out: dict[str, list] = {}
    for c in sorted({t.condition for t in trials}, key=_condition_key):
        acc = np.zeros((2, n_bins))
        cnt = np.zeros(n_bins)
        amp = np.zeros(n_bins)
        for t in (t for t in trials if t.condition == c and t.label in sims):
            th = sims[t.label].theta_sim
            a = np.abs(th)
            edges = np.quantile(a, np.linspace(0, 1, n_bins + 1))
            q = np.clip(np.searchsorted(edges, a, side="right") - 1, 0, n_bins - 1)
            for ch, (y, ys) in enumerate(
                ((t.theta, sims[t.label].theta_sim), (t.td, sims[t.label].td_sim))
            ):
                e = y - ys
                acc[ch] += np.bincount(q, e * e, n_bins) / max(np.mean(e * e), 1e-300)
            cnt += np.bincount(q, minlength=n_bins)
            amp += np.bincount(q, a, n_bins)
        out[c] = [
            {
                "deflection_mean_rad": float(amp[i] / cnt[i]) if cnt[i] else None,
                "rel_rms_theta": float(np.sqrt(acc[0, i] / cnt[i])) if cnt[i] else None,
                "rel_rms_td": float(np.sqrt(acc[1, i] / cnt[i])) if cnt[i] else None,
            }
            for i in range(n_bins)
        ]
    return out


def residual_vs_order(
    trials: Sequence[TrialData],
    arms: dict[str, ArmParams],
    sims: dict[str, TrialComparison],
) -> list[dict]:
    """Per trial: its position, repetition, VAFs, and its fitted k_i and k_c relative to the
    mean of its subject × condition (log ratio): a trend with trial order is drift."""
    cells: dict[tuple[str, str], list[TrialData]] = {}
    for t in trials:
        if t.label in arms:
            cells.setdefault(t.cell, []).append(t)
    rows = []
    for items in cells.values():
        lk_i = np.log([arms[t.label].k_i for t in items])
        lk_c = np.log([arms[t.label].k_c for t in items])
        for i, t in enumerate(items):
            rows.append(
                {
                    "trial": t.label,
                    "subject": t.subject,
                    "condition": t.condition,
                    "trial_index": t.trial_index,
                    "repetition": t.repetition,
                    "familiarization": t.familiarization,
                    "log_k_i_vs_cell": float(lk_i[i] - lk_i.mean()),
                    "log_k_c_vs_cell": float(lk_c[i] - lk_c.mean()),
                    "vaf_theta_percent": sims[t.label].vaf_theta(t) if t.label in sims else None,
                    "vaf_td_percent": sims[t.label].vaf_td(t) if t.label in sims else None,
                }
            )
    rows.sort(key=lambda r: (r["subject"], r["trial_index"] or 0))
    return rows
