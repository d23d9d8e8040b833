"""Rig check: identify the wheel a rig really renders, from a hands-off recording.

The model (``docs/rig-check.md``): with nobody touching the wheel, the rig's control loop
renders a spring and a damper through its motor, on top of the perturbation torque T_p, and the
wheel's own physics adds inertia, dry friction and the gravity torque of an unbalanced wheel:

    cmd(t)   = T_p(t) − b·ω(t) − k·θ(t)                    (what the loop commands)
    T_m      = the command through a first-order lag τ     (the actuator's torque loop)
    I·ω'     = T_m + T_0 − F_c·tanh(ω/ε) − G·sin θ,   θ' = ω

(T_0: a constant torque on the wheel, e.g. a command or sensor bias; fitted, reported as
``offset_Nm``, not judged.) Angles positive counter-clockwise seen by the driver; torques
positive towards positive angle; SI units. G = m·g·r > 0 means the heavy side hangs below the
axis at θ = 0 (the gravity torque pulls back to centre, like a stiffness k + G at small angles;
only the sin θ curvature tells G from k, so the check needs large angles). ε is fixed
(``EPS_RAD_S``), not fitted.

The loop samples the wheel and holds its command: the model simulates that too (the command is
computed from the state at the start of each hold interval and held over it, the wheel moves
exactly in between). A Steerlab recording is simulated at its own loop rate (one hold per
sample, as the loop did); a recording from elsewhere is simulated on a uniform grid with holds
of at most ``MAX_HOLD_S`` (a near-continuous actuator; the recorded T_p interpolated onto it) and
the model's angle is compared with the recorded one at the recording's own (jittered) time
stamps; a step longer than ``GAP_FACTOR`` × the median is a gap, and each gap-free segment gets
its own initial state. ``delay_s`` is the lag's continuous-time equivalent at low frequency,
τ + h/2 (:func:`lag_equivalent`; the lag acts in continuous time on the held command, the
torque over a hold interval its mean there, as in Steerlab's simulator), which includes the
hold's own half interval.

Estimator: output error. The angle is simulated from the recorded T_p and the parameters
(I, b, k, F_c, G, τ and each gap-free segment's initial angle and velocity) minimise the
squared angle error (``scipy.optimize.least_squares``), started from an equation-error fit.
SEMs come from the Jacobian: (JᵀJ)⁻¹ JᵀΩJ (JᵀJ)⁻¹ with a Newey–West (Bartlett) estimate of the
residual's autocovariance Ω, which reduces to s²(JᵀJ)⁻¹ for a white residual; the plain Fisher
SEM is reported alongside. VAF: of the whole model on every fitted sample.
"""

from __future__ import annotations

import csv
import html
import json
import math
import os
import tempfile
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit
from scipy.ndimage import median_filter
from scipy.optimize import least_squares
from scipy.signal import savgol_filter

from steerlab.hardware.sim.mechanisms import first_order_lag_weights

PARAMS = (
    "inertia_kgm2",
    "damping_Nms_per_rad",
    "stiffness_Nm_per_rad",
    "coulomb_Nm",
    "gravity_Nm",
    "delay_s",
)
UNITS = {
    "inertia_kgm2": "kg·m²",
    "damping_Nms_per_rad": "N·m·s/rad",
    "stiffness_Nm_per_rad": "N·m/rad",
    "coulomb_Nm": "N·m",
    "gravity_Nm": "N·m",
    "delay_s": "s",
}
LABELS = {
    "inertia_kgm2": "inertia I",
    "damping_Nms_per_rad": "damping b",
    "stiffness_Nm_per_rad": "stiffness k",
    "coulomb_Nm": "Coulomb friction F_c",
    "gravity_Nm": "gravity torque m·g·r",
    "delay_s": "actuator lag τ",
}
EPS_RAD_S = 0.01  # the smooth sign: tanh(ω/ε)
NG = 7  # global parameters of the fit: I, b, k, F_c, G, τ, T_0 (then 2 per segment)
MAX_HOLD_S = 0.25e-3  # hold interval for recordings from other rigs (near-continuous actuator)
GAP_FACTOR = 2.5  # a time step longer than this × the median step is a gap
MIN_SEGMENT_S = 1.0  # gap-free stretches shorter than this are not fitted
MIN_TOTAL_S = 5.0  # at least this much gap-free data
MIN_RATE_HZ = 100.0
CLIP_FRACTION = 0.01  # this share of samples flat at the extreme: clipped / saturated
CLIP_RUN = 5  # ... in runs of at least this many samples
RIG_JSON = "rig.json"
INDEX_HTML = "index.html"
FIGURE = "fit.png"
REQUIRED_COLUMNS = ("time_s", "perturbation_torque_Nm", "wheel_angle_rad")
HANDS_COLUMNS = ("driver_torque_Nm", "grip_force_N")  # read when present: hands on the wheel?
# Hands on the wheel. With nobody touching it the column sensor reads its noise alone (the
# simulated rig: 1 % of the perturbation's SD; a held wheel: 60 %) and a glove nobody wears
# reads about 0 N (the simulated one 0.6 N; a light grip is 10 N or more).
HANDS_ON_TORQUE_SHARE = 0.10  # driver torque SD ≥ this × the perturbation's SD
HANDS_ON_GRIP_N = 5.0  # mean grip force ≥ this
FORMAT = "steerlab-rig-check"
FORMAT_VERSION = 1


class RigCheckError(ValueError):
    """A recording or rig-check file that cannot be used; the message names the file and why."""


# -- tolerances (the rig file's [rig_check] table) --------------------------------------------
@dataclass(frozen=True)
class Tolerances:
    """What the lab accepts. Relative tolerances are fractions of the nominal value."""

    inertia_rel: float = 0.10
    damping_rel: float = 0.10
    stiffness_rel: float = 0.10
    coulomb_max_nm: float = 0.10
    gravity_max_nm: float = 0.10
    delay_max_s: float = 0.010
    vaf_min_percent: float = 95.0

    @classmethod
    def from_rig(cls, rig) -> Tolerances:
        return cls(**(getattr(rig, "rig_check", None) or {}))


@dataclass(frozen=True)
class Nominal:
    inertia_kgm2: float = 0.3
    damping_Nms_per_rad: float = 2.0
    stiffness_Nm_per_rad: float = 4.2
    source: str = "Table 1 (Pronker et al. 2017)"

    @classmethod
    def from_wheel(cls, wheel, source: str) -> Nominal:
        w = wheel
        return cls(w.inertia_kgm2, w.damping_nms_per_rad, w.stiffness_nm_per_rad, source)

    def to_dict(self) -> dict:
        return {
            "inertia_kgm2": self.inertia_kgm2,
            "damping_Nms_per_rad": self.damping_Nms_per_rad,
            "stiffness_Nm_per_rad": self.stiffness_Nm_per_rad,
            "coulomb_Nm": 0.0,
            "gravity_Nm": 0.0,
            "delay_s": 0.0,
            "source": self.source,
        }


# -- the hands-off trial's perturbation ---------------------------------------------------------
def hands_off_spec(stiffness_nm_per_rad: float, angle_sd_rad: float = 0.5):
    """A multisine for the wheel alone: 10 s period, 12 double bands from 0.1 Hz, full power up
    to 1.5 Hz and a tenth above; torque SD ``angle_sd_rad`` × k (on Table 1's wheel: angle SD
    about 0.25 rad, peaks about 0.6 rad, so that sin θ departs from θ and an imbalance is seen
    apart from the stiffness; the motor command stays near 4 N·m)."""
    from steerlab.protocols.perturbation import PerturbationSpec

    return PerturbationSpec(
        period_s=10.0,
        n_bands=12,
        first_bin=1,
        f_max_hz=5.0,
        full_power_max_hz=1.5,
        reduced_power_ratio=0.1,
        sd_nm=max(0.2, angle_sd_rad * stiffness_nm_per_rad),
        gap_bins=1,
        seed=17,
    )


# -- reading a recording ------------------------------------------------------------------------
@dataclass
class Recording:
    """A hands-off recording as read: raw time stamps and channels."""

    source: str
    time_s: np.ndarray
    perturbation_Nm: np.ndarray
    angle_rad: np.ndarray
    velocity_rad_s: np.ndarray | None = None
    motor_command_Nm: np.ndarray | None = None
    driver_torque_Nm: np.ndarray | None = None  # NaN where a CSV cell is not a number
    grip_force_N: np.ndarray | None = None
    max_torque_nm: float | None = None
    loop_rate_hz: float | None = None  # a Steerlab recording: samples are the loop's cycles
    nominal: Nominal | None = None
    attrs: dict = field(default_factory=dict)
    first_row: int | None = None  # a CSV: the file's row number of sample 0 (for messages)

    def where(self, i: int) -> str:
        return f"sample {i}" + (f" (row {i + self.first_row})" if self.first_row else "")


def read_recording(path: str | Path, trial: str | None = None) -> Recording:
    """A session file (``.h5``: its latest complete hands-off trial, or ``trial``) or an
    interchange-format CSV."""
    p = Path(path)
    if not p.exists():
        raise RigCheckError(f"no such file: {p}")
    if p.suffix.lower() in (".h5", ".hdf5"):
        return _read_session(p, trial)
    return _read_csv(p)


def _read_csv(p: Path) -> Recording:
    try:
        with open(p, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as e:
        raise RigCheckError(f"{p}: cannot read ({e})") from None
    rows = [r for r in rows if r and not r[0].startswith("#")]
    if not rows:
        raise RigCheckError(f"{p}: empty file (no header)")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise RigCheckError(
            f"{p}: missing column(s) {', '.join(missing)} (need {', '.join(REQUIRED_COLUMNS)}; "
            "wheel_velocity_rad_s optional)"
        )
    want = list(REQUIRED_COLUMNS) + [c for c in ("wheel_velocity_rad_s",) if c in header]
    idx = {c: header.index(c) for c in want}
    data = {c: np.empty(len(rows) - 1) for c in want}
    for i, row in enumerate(rows[1:]):
        for c, j in idx.items():
            try:
                v = float(row[j])
            except (IndexError, ValueError):
                cell = row[j] if j < len(row) else "(missing)"
                raise RigCheckError(
                    f"{p}: row {i + 2}, column {c}: not a number: {cell!r}"
                ) from None
            if not math.isfinite(v):
                raise RigCheckError(f"{p}: row {i + 2}, column {c}: not finite: {row[j]!r}")
            data[c][i] = v
    # Not needed by the fit, only to tell whether hands were on the wheel: read leniently.
    hands = {}
    for c in HANDS_COLUMNS:
        if c in header:
            j = header.index(c)
            hands[c] = np.array(
                [_number_or_nan(row[j] if j < len(row) else "") for row in rows[1:]]
            )
    return Recording(
        source=str(p),
        time_s=data["time_s"],
        perturbation_Nm=data["perturbation_torque_Nm"],
        angle_rad=data["wheel_angle_rad"],
        velocity_rad_s=data.get("wheel_velocity_rad_s"),
        driver_torque_Nm=hands.get("driver_torque_Nm"),
        grip_force_N=hands.get("grip_force_N"),
        first_row=2,
    )


def _number_or_nan(cell: str) -> float:
    try:
        return float(cell)
    except ValueError:
        return math.nan


def _read_session(p: Path, trial: str | None) -> Recording:
    import h5py

    from steerlab.protocols.datafile import read_channel

    try:
        f = h5py.File(p, "r", swmr=True)
    except OSError as e:
        raise RigCheckError(f"{p}: not a readable session file ({e})") from None
    with f:
        trials = f.get("trials")
        if trials is None:
            raise RigCheckError(f"{p}: no /trials group: not a Steerlab session file")
        if trial is not None:
            if trial not in trials:
                raise RigCheckError(f"{p}: no trial {trial!r} (has: {', '.join(trials)})")
            key = trial
        else:
            keys = [
                k
                for k in trials
                if bool(trials[k].attrs.get("hands_off", False))
                and str(trials[k].attrs.get("status", "")) == "complete"
            ]
            if not keys:
                raise RigCheckError(
                    f"{p}: no complete hands-off trial (attribute hands_off true); record one "
                    "with `steerlab rig-check --rig RIG.toml --out DIR`"
                )
            key = sorted(keys, key=lambda k: str(trials[k].attrs.get("started_utc", "")))[-1]
        g = trials[key]
        src = f"{p}:/trials/{key}"
        for c in REQUIRED_COLUMNS:
            if c not in g:
                raise RigCheckError(f"{src}: missing channel {c}")

        def opt(name):
            return read_channel(g[name]) if name in g else None

        rig = json.loads(f.attrs["rig"]) if "rig" in f.attrs else {}
        max_t = (rig.get("safety") or {}).get("max_torque_nm")
        nominal = None
        if "protocol_toml" in f.attrs:
            try:
                w = tomllib.loads(str(f.attrs["protocol_toml"])).get("wheel", {})
                nominal = Nominal(
                    float(w.get("inertia_kgm2", 0.3)),
                    float(w.get("damping_Nms_per_rad", 2.0)),
                    float(w.get("stiffness_Nm_per_rad", 4.2)),
                    f"the protocol recorded in {p.name}",
                )
            except (tomllib.TOMLDecodeError, TypeError, ValueError):
                nominal = None
        fs = g.attrs.get("fs_hz")
        return Recording(
            source=src,
            time_s=read_channel(g["time_s"]),
            perturbation_Nm=read_channel(g["perturbation_torque_Nm"]),
            angle_rad=read_channel(g["wheel_angle_rad"]),  # counts × scale_factor, if counts
            velocity_rad_s=opt("wheel_velocity_rad_s"),
            motor_command_Nm=opt("motor_command_Nm"),
            driver_torque_Nm=opt("driver_torque_Nm"),
            grip_force_N=opt("grip_force_N"),
            max_torque_nm=float(max_t) if max_t else None,
            loop_rate_hz=float(fs) if fs else None,
            nominal=nominal,
            attrs={k: _plain(v) for k, v in g.attrs.items()},
        )


def _plain(v):
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


# -- checks, resampling and gaps ----------------------------------------------------------------
@dataclass
class Prepared:
    """A checked recording: its raw samples, the gap-free segments that are fitted, and the
    simulation grid (hold interval ``hold_s``) the model runs on."""

    source: str
    time_s: np.ndarray  # raw time stamps
    perturbation_Nm: np.ndarray
    angle_rad: np.ndarray
    velocity_rad_s: np.ndarray | None
    segments: list[tuple[int, int]]  # [start, stop) raw sample indices, gap-free, fitted
    dt: float  # the recording's (median) sample step, s
    hold_s: float  # the model's hold interval, s
    loop: bool  # True: a Steerlab loop recording, one hold per sample (zero-order hold)
    notes: list[str]
    warnings: list[str] = field(default_factory=list)  # the recording may not be hands off

    @property
    def mask(self) -> np.ndarray:
        m = np.zeros(len(self.time_s), bool)
        for a, b in self.segments:
            m[a:b] = True
        return m

    @property
    def n_fitted(self) -> int:
        return int(sum(b - a for a, b in self.segments))


def _flat_extreme_fraction(x: np.ndarray) -> tuple[float, float]:
    """Share of samples sitting flat at the signal's maximum or minimum, in runs ≥ CLIP_RUN; and
    that extreme value."""
    worst, where = 0.0, 0.0
    span = float(np.max(x) - np.min(x))
    for ext in (np.max(x), np.min(x)):
        at = np.abs(x - ext) <= 1e-6 * max(abs(ext), span, 1e-12)
        d = np.diff(np.concatenate(([0], at.astype(np.int8), [0])))
        lengths = np.flatnonzero(d == -1) - np.flatnonzero(d == 1)
        frac = int(np.sum(lengths[lengths >= CLIP_RUN])) / len(x)
        if frac > worst:
            worst, where = frac, float(ext)
    return worst, where


def prepare(rec: Recording) -> Prepared:
    """Check a recording, find its gaps and choose the model's simulation grid.

    Raises :class:`RigCheckError` (naming the file) when the recording is too short, not
    excited, saturated or clipped, or has unusable time stamps.
    """
    src = rec.source
    t = np.asarray(rec.time_s, float)
    n = len(t)
    for name, x in (
        ("perturbation_torque_Nm", rec.perturbation_Nm),
        ("wheel_angle_rad", rec.angle_rad),
        ("wheel_velocity_rad_s", rec.velocity_rad_s),
    ):
        if x is None:
            continue
        if len(x) != n:
            raise RigCheckError(f"{src}: {name} has {len(x)} samples but time_s has {n}")
        bad = np.flatnonzero(~np.isfinite(x))
        if len(bad):
            raise RigCheckError(f"{src}: {name} is not finite at {rec.where(bad[0])}")
    if n < 10:
        raise RigCheckError(f"{src}: too short: {n} samples")
    if not np.all(np.isfinite(t)):
        bad = np.flatnonzero(~np.isfinite(t))[0]
        raise RigCheckError(f"{src}: time_s is not finite at {rec.where(bad)}")
    dts = np.diff(t)
    back = np.flatnonzero(dts <= 0)
    if len(back):
        raise RigCheckError(
            f"{src}: time_s does not increase at {rec.where(back[0] + 1)} "
            f"({t[back[0]]:.6g} s then {t[back[0] + 1]:.6g} s); cannot order the samples"
        )
    notes: list[str] = []
    dt = 1.0 / rec.loop_rate_hz if rec.loop_rate_hz else float(np.median(dts))
    if 1.0 / dt < MIN_RATE_HZ:
        raise RigCheckError(
            f"{src}: sampled at {1 / dt:.3g} Hz (median step {dt * 1e3:.3g} ms); "
            f"the rig check needs ≥ {MIN_RATE_HZ:g} Hz"
        )
    gap_s = GAP_FACTOR * dt
    gaps = np.flatnonzero(dts > gap_s)
    uniform = bool(np.max(np.abs(dts - dt)) <= 1e-6 * dt)
    loop = bool(rec.loop_rate_hz) and uniform
    if not uniform:
        jit = np.percentile(dts, [1, 99]) * 1e3
        notes.append(
            f"time stamps not uniform (steps {jit[0]:.2f}–{jit[1]:.2f} ms, 1st–99th percentile, "
            f"median {dt * 1e3:.3g} ms): the torque is resampled on the model's uniform grid, "
            "the model compared with the angle at its own time stamps"
        )
    if len(gaps):
        notes.append(
            f"{len(gaps)} gap(s) in the time stamps (steps longer than {gap_s * 1e3:.3g} ms; the "
            f"longest {np.max(dts[gaps]) * 1e3:.3g} ms): fitted across gap-free segments only, "
            "each with its own initial state"
        )
    edges = np.concatenate(([0], gaps + 1, [n]))
    segs = [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    short = [s for s in segs if t[s[1] - 1] - t[s[0]] < MIN_SEGMENT_S]
    segs = [s for s in segs if t[s[1] - 1] - t[s[0]] >= MIN_SEGMENT_S]
    if short:
        notes.append(f"{len(short)} gap-free stretch(es) shorter than {MIN_SEGMENT_S:g} s left out")
    total = sum(t[b - 1] - t[a] for a, b in segs)
    if total < MIN_TOTAL_S:
        raise RigCheckError(
            f"{src}: too short: {total:.2f} s of gap-free data (duration {t[-1] - t[0]:.2f} s, "
            f"{len(gaps)} gap(s)); the rig check needs ≥ {MIN_TOTAL_S:g} s"
        )
    m = np.zeros(n, bool)
    for a, b in segs:
        m[a:b] = True
    tp, th = np.asarray(rec.perturbation_Nm, float), np.asarray(rec.angle_rad, float)
    sd_tp = float(np.std(tp[m]))
    if sd_tp < 0.01:
        raise RigCheckError(
            f"{src}: no excitation: perturbation_torque_Nm varies by {sd_tp:.3g} N·m (SD); the "
            "rig check needs a perturbation (≥ 0.01 N·m SD)"
        )
    sd_th = float(np.std(th[m]))
    if sd_th < 1e-3:
        raise RigCheckError(
            f"{src}: no excitation: wheel_angle_rad varies by {sd_th:.3g} rad (SD): the wheel did "
            "not move (locked, or the motor disabled?)"
        )
    frac, at = _flat_extreme_fraction(tp)
    if frac >= CLIP_FRACTION:
        raise RigCheckError(
            f"{src}: perturbation_torque_Nm saturated: flat at {at:+.4g} N·m for {frac:.1%} of "
            "the samples; lower the perturbation, the fit cannot use a clipped torque"
        )
    if rec.motor_command_Nm is not None and rec.max_torque_nm:
        sat = np.abs(rec.motor_command_Nm) >= rec.max_torque_nm * (1 - 1e-4)
        if np.mean(sat) >= CLIP_FRACTION / 10:
            raise RigCheckError(
                f"{src}: motor_command_Nm saturated at the rig's limit ±{rec.max_torque_nm:g} N·m "
                f"for {np.mean(sat):.1%} of the samples; lower the perturbation"
            )
    frac, at = _flat_extreme_fraction(th)
    if frac >= CLIP_FRACTION:
        raise RigCheckError(
            f"{src}: wheel_angle_rad clipped: flat at {at:+.4g} rad for {frac:.1%} of the "
            "samples (an end stop or the sensor's range); the fit cannot use it"
        )
    hold = dt if loop else dt / max(1, math.ceil(dt / MAX_HOLD_S - 1e-9))
    om = None if rec.velocity_rad_s is None else np.asarray(rec.velocity_rad_s, float)
    warnings = hands_on_evidence(rec, m, sd_tp)
    return Prepared(src, t, tp, th, om, segs, dt, hold, loop, notes, warnings)


def hands_on_evidence(rec: Recording, mask: np.ndarray, sd_tp: float) -> list[str]:
    """Why the recording may not be hands off (empty: no sign of hands). The model has no arm:
    fitted to a held wheel, its values are the wheel and the arm together, not the rig's."""
    out = []
    if rec.attrs and not bool(rec.attrs.get("hands_off", False)):  # a session file's trial
        out.append(
            f"hands on the wheel? the trial is not a hands-off trial (condition "
            f"{rec.attrs.get('condition', '?')!s}; its attribute hands_off is not true)"
        )
    td = _finite(rec.driver_torque_Nm, mask)
    if td is not None and len(td) > 1 and sd_tp > 0:
        share = float(np.std(td)) / sd_tp
        if share >= HANDS_ON_TORQUE_SHARE:
            out.append(
                f"hands on the wheel? driver_torque_Nm varies by {np.std(td):.3g} N·m (SD), "
                f"{share:.0%} of the perturbation's {sd_tp:.3g} N·m; with nobody touching the "
                f"wheel it reads its noise alone (below {HANDS_ON_TORQUE_SHARE:.0%})"
            )
    grip = _finite(rec.grip_force_N, mask)
    if grip is not None and len(grip) and float(np.mean(grip)) >= HANDS_ON_GRIP_N:
        out.append(
            f"hands on the wheel? grip_force_N averages {np.mean(grip):.3g} N; a glove that holds "
            f"nothing reads about 0 (below {HANDS_ON_GRIP_N:g} N)"
        )
    if out:
        out.append(
            "the model has no arm in it: fitted to a held wheel, its values are those of the "
            "wheel and the arm together, not the rig's; record again with the hands off"
        )
    return out


def _finite(x: np.ndarray | None, mask: np.ndarray) -> np.ndarray | None:
    if x is None or len(x) != len(mask):
        return None
    x = np.asarray(x, float)[mask]
    return x[np.isfinite(x)]


# -- the model ------------------------------------------------------------------------------
@njit(cache=True)
def _simulate(u, th0, om0, I, b, k, fc, eps, g, t0, alpha, m, h, out):
    """θ at the start of each hold interval (len(u) + 1 values into ``out``): the command is
    computed from the state at the interval's start and held; the lag acts on it in
    continuous time, and the torque over the interval is the lag's mean over it (``m``: the
    weight of the lag's torque at the interval's start; ``alpha``: its exact update), as in
    Steerlab's simulator; the wheel moves exactly under the held torques; ``t0`` is a
    constant torque on the wheel."""
    th, om = th0, om0
    T = u[0] - b * om - k * th
    for j in range(len(u)):
        out[j] = th
        cmd = u[j] - b * om - k * th
        applied = cmd + m * (T - cmd)
        T += alpha * (cmd - T)
        acc = (applied + t0 - fc * np.tanh(om / eps) - g * np.sin(th)) / I
        th += om * h + 0.5 * acc * h * h
        om += acc * h
    out[len(u)] = th


def lag_equivalent(tau: float, h: float) -> tuple[float, float]:
    """The model's lag (time constant ``tau`` on a command held for ``h``) as a delay at low
    frequency: τ + h/2 (the lag's own part plus the hold's half interval); and its derivative
    with respect to τ."""
    return max(tau, 0.0) + 0.5 * h, 1.0


def lag_time_constant(delay_s: float, h: float) -> float:
    """The inverse of :func:`lag_equivalent`: the lag τ (the model's and the simulator's,
    :class:`hardware.sim.mechanisms.ActuatorLag`) at hold ``h`` whose continuous-time
    equivalent is ``delay_s`` (0 when ``delay_s`` ≤ h/2: the hold alone is that slow)."""
    return max(delay_s - 0.5 * h, 0.0)


@dataclass
class _Segment:
    u: np.ndarray  # the torque held over each hold interval
    idx: np.ndarray  # for each raw sample: the hold interval it falls in
    w: np.ndarray  # ... and how far into it (0..1)
    y: np.ndarray  # measured angle at the raw samples


@dataclass
class _Problem:
    prep: Prepared
    eps: float
    segs: list[_Segment]

    @classmethod
    def build(cls, prep: Prepared, eps: float) -> _Problem:
        h = prep.hold_s
        out = []
        for a, b in prep.segments:
            t = prep.time_s[a:b] - prep.time_s[a]
            tp = prep.perturbation_Nm[a:b]
            if prep.loop:
                u = np.ascontiguousarray(tp[:-1])  # the loop's own zero-order hold
                idx, w = np.arange(len(t)), np.zeros(len(t))
            else:
                n_h = int(math.ceil(t[-1] / h - 1e-9))
                # Sampled at each interval's start, like the feedback: one command, held.
                u = np.interp(np.arange(n_h) * h, t, tp)
                pos = t / h
                idx = np.minimum(np.floor(pos).astype(int), n_h - 1)
                w = pos - idx
            out.append(_Segment(np.ascontiguousarray(u), idx, w, prep.angle_rad[a:b]))
        return cls(prep, eps, out)

    def simulate(self, x: np.ndarray) -> list[np.ndarray]:
        """The model's angle at every raw sample of every segment."""
        I, b, k, fc, g, tau, t0 = x[:NG]
        h = self.prep.hold_s
        alpha, m = first_order_lag_weights(tau, h)
        res = []
        for s, seg in enumerate(self.segs):
            th = np.empty(len(seg.u) + 1)
            th0, om0 = x[NG + 2 * s], x[NG + 1 + 2 * s]
            _simulate(seg.u, th0, om0, I, b, k, fc, self.eps, g, t0, alpha, m, h, th)
            idx1 = np.minimum(seg.idx + 1, len(th) - 1)
            res.append(th[seg.idx] * (1.0 - seg.w) + th[idx1] * seg.w)
        return res

    def residual(self, x: np.ndarray) -> np.ndarray:
        sims = self.simulate(x)
        r = np.concatenate([seg.y - o for seg, o in zip(self.segs, sims, strict=True)])
        if not np.all(np.isfinite(r)) or np.max(np.abs(r)) > 1e3:
            return np.full(len(r), 1e3)
        return r


def _equation_error_start(prep: Prepared, eps: float, nominal: Nominal) -> np.ndarray:
    """I, b, k, F_c, T_0 from T_p + T_0 = I θ'' + b θ' + k θ + F_c tanh(θ'/ε), on derivatives of
    the angle smoothed over 50 ms (a starting point for the output-error fit)."""
    rows, rhs = [], []
    for a, b in prep.segments:
        t, th = prep.time_s[a:b], prep.angle_rad[a:b]
        grid = np.arange(t[0], t[-1], prep.dt)
        win = max(7, int(round(0.05 / prep.dt)) | 1)
        if len(grid) <= 3 * win:
            continue
        thg = np.interp(grid, t, th)
        d1 = savgol_filter(thg, win, 3, deriv=1, delta=prep.dt)
        d2 = savgol_filter(thg, win, 3, deriv=2, delta=prep.dt)
        cut = slice(win, len(grid) - win)
        ones = np.ones(len(thg))
        rows.append(np.column_stack([d2, d1, thg, np.tanh(d1 / eps), ones])[cut])
        rhs.append(np.interp(grid, t, prep.perturbation_Nm[a:b])[cut])
    x = np.array([nominal.inertia_kgm2, nominal.damping_Nms_per_rad,
                  nominal.stiffness_Nm_per_rad, 0.0, 0.0])  # fmt: skip
    if rows:
        sol, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
        if np.all(np.isfinite(sol)) and sol[0] > 0 and sol[2] > 0:
            x = sol
            x[4] = -x[4]  # T_p + T_0 = ...: the constant column's coefficient is −T_0
    return x


def _jacobian(fun, x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Central differences (one-sided at a bound)."""
    r0 = fun(x)
    J = np.empty((len(r0), len(x)))
    for i in range(len(x)):
        step = 1e-6 * max(abs(x[i]), 1e-3)
        xp, xm = x.copy(), x.copy()
        xp[i] = min(x[i] + step, hi[i])
        xm[i] = max(x[i] - step, lo[i])
        J[:, i] = (fun(xp) - fun(xm)) / (xp[i] - xm[i])
    return J


def _newey_west(J: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, int]:
    """Covariance of the estimate with a Bartlett-weighted residual autocovariance; the lag
    window ends where the residual's autocorrelation first falls below 0.05 (isolated spikes,
    such as a missed cycle's stale reading, removed first by a 5-point median: white spikes
    would otherwise hide a slow correlation and cut the window short)."""
    n = len(r)
    rm = median_filter(r, size=5, mode="nearest")
    rc = rm - rm.mean()
    f = np.fft.rfft(rc, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[:n]
    ac = ac / ac[0] if ac[0] > 0 else ac
    below = np.flatnonzero(np.abs(ac) < 0.05)
    L = int(min(below[0] if len(below) else n // 5, n // 5))
    g = J * r[:, None]
    G = np.fft.rfft(g, 2 * n, axis=0)
    cross = np.fft.irfft(G[:, :, None] * np.conj(G[:, None, :]), axis=0)[: L + 1]
    omega = cross[0].copy()
    for lag in range(1, L + 1):
        w = 1.0 - lag / (L + 1)
        omega += w * (cross[lag] + cross[lag].T)
    A = np.linalg.inv(J.T @ J)
    return A @ omega @ A, L


@dataclass
class RigFit:
    source: str
    values: dict[str, float]
    sem: dict[str, float | None]  # None: the fit left this parameter on a bound
    sem_fisher: dict[str, float | None]
    vaf_percent: float
    prep: Prepared
    model_angle: np.ndarray  # at the raw samples; NaN outside the fitted segments
    eps: float
    hold_s: float
    hac_lags: int
    at_bound: list[str]
    initial_states: list[tuple[float, float]]
    nominal: Nominal
    cost_evals: int
    lag_time_constant_s: float  # the model's lag τ at hold_s
    offset_nm: float = 0.0  # constant torque on the wheel (bias, cogging mean), not judged
    offset_sem: float | None = None

    def to_dict(self) -> dict:
        d: dict[str, Any] = {p: {"value": self.values[p], "sem": self.sem[p]} for p in PARAMS}
        d["offset_Nm"] = {"value": self.offset_nm, "sem": self.offset_sem}
        d.update(
            {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "vaf_percent": self.vaf_percent,
                "nominal": self.nominal.to_dict(),
                "recording": self.source,
                "model": {
                    "equation": "I·ω' = lag_τ(T_p − b·ω − k·θ) + T_0 − F_c·tanh(ω/ε) − G·sin θ",
                    "friction_eps_rad_s": self.eps,
                    "hold_s": self.hold_s,
                    "lag_time_constant_s": self.lag_time_constant_s,
                    "delay_s_is": "the continuous-time equivalent of the actuator's lag, "
                    "including the hold's half interval: τ + h/2",
                },
                "sem_method": "Jacobian sandwich with Newey–West residual autocovariance "
                f"({self.hac_lags} lags)",
                "sem_fisher": self.sem_fisher,
                "at_bound": self.at_bound,
                "fit": {
                    "samples": self.prep.n_fitted,
                    "segments_s": [
                        [float(self.prep.time_s[a]), float(self.prep.time_s[b - 1])]
                        for a, b in self.prep.segments
                    ],
                    "sample_step_s": self.prep.dt,
                    "notes": self.prep.notes,
                },
            }
        )
        return d


def fit_rig(prep: Prepared, *, nominal: Nominal | None = None, eps: float = EPS_RAD_S) -> RigFit:
    """The output-error fit of the rig model to a prepared recording."""
    nominal = nominal or Nominal()
    prob = _Problem.build(prep, eps)
    I0, b0, k0, fc0, off0 = _equation_error_start(prep, eps, nominal)
    start = [I0, b0, k0, max(fc0, 0.0), 0.0, 2e-3, off0]
    lower = [1e-4, -50.0, -50.0, -20.0, -100.0, 0.0, -50.0]
    upper = [100.0, 500.0, 5000.0, 20.0, 100.0, 0.2, 50.0]
    for (a, b), seg in zip(prep.segments, prob.segs, strict=True):
        y, t = seg.y, prep.time_s[a:b]
        if prep.velocity_rad_s is not None:
            w0 = float(prep.velocity_rad_s[a])
        else:
            j = min(5, len(y) - 1)
            w0 = float((y[j] - y[0]) / (t[j] - t[0]))
        start += [float(y[0]), w0]
        lower += [-20.0, -200.0]
        upper += [20.0, 200.0]
    lo, hi = np.array(lower), np.array(upper)
    x0 = np.clip(np.array(start), lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    res = least_squares(
        prob.residual, x0, bounds=(lo, hi), x_scale="jac", method="trf",
        xtol=1e-12, ftol=1e-12, gtol=1e-10, max_nfev=400,
    )  # fmt: skip
    x = res.x
    r = prob.residual(x)
    J = _jacobian(prob.residual, x, lo, hi)
    # A parameter the fit left on a bound is held there: the SEMs are those of the others,
    # given it (its own SEM is not defined: None in rig.json).
    held = (res.active_mask != 0) | (x <= lo) | (x >= hi)
    scaled = np.linalg.norm(J, axis=0) * np.maximum(np.abs(x), 1e-3)
    held |= scaled <= 1e-9 * np.max(scaled)  # no effect on the residual at all
    free = np.flatnonzero(~held)
    Jf = J[:, free]
    s2 = float(r @ r) / max(1, len(r) - len(free))
    try:
        cov_f = s2 * np.linalg.inv(Jf.T @ Jf)
        cov_h, L = _newey_west(Jf, r)
    except np.linalg.LinAlgError:
        raise RigCheckError(
            f"{prep.source}: the rig model is not identifiable from this recording (singular "
            "Jacobian): is the wheel excited over a range of angles and speeds?"
        ) from None
    sem_f = np.full(len(x), np.nan)
    sem_h = np.full(len(x), np.nan)
    sem_f[free] = np.sqrt(np.maximum(np.diag(cov_f), 0.0))
    sem_h[free] = np.sqrt(np.maximum(np.diag(cov_h), 0.0))
    off_sem = None if not np.isfinite(sem_h[6]) else float(sem_h[6])
    sem_f, sem_h = sem_f[:6], sem_h[:6]
    delay, ddelay = lag_equivalent(float(x[5]), prep.hold_s)
    vals = [*x[:5], delay]
    sem_h[5] *= ddelay
    sem_f[5] *= ddelay

    def clean(v):
        return None if not np.isfinite(v) else float(v)

    values = {p: float(v) for p, v in zip(PARAMS, vals, strict=True)}
    sem = {p: clean(v) for p, v in zip(PARAMS, sem_h, strict=True)}
    sem_fisher = {p: clean(v) for p, v in zip(PARAMS, sem_f, strict=True)}
    at_bound = [PARAMS[i] for i in range(6) if held[i]] + (["offset_Nm"] if held[6] else [])
    y = np.concatenate([seg.y for seg in prob.segs])
    vaf = float(100.0 * (1.0 - np.var(r) / np.var(y)))
    model = np.full(len(prep.time_s), np.nan)
    for (a, b), o in zip(prep.segments, prob.simulate(x), strict=True):
        model[a:b] = o
    inits = [(float(x[NG + 2 * s]), float(x[NG + 1 + 2 * s])) for s in range(len(prep.segments))]
    return RigFit(prep.source, values, sem, sem_fisher, vaf, prep, model, eps, prep.hold_s,
                  L, at_bound, inits, nominal, int(res.nfev), float(x[5]),
                  float(x[6]), off_sem)  # fmt: skip


# -- verdict -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Check:
    name: str
    value: float
    nominal: float
    limit: float  # the largest acceptable |value − nominal| (or minimum, for VAF)
    passed: bool
    rule: str


def verdict(fit: RigFit, tol: Tolerances) -> list[Check]:
    v, n = fit.values, fit.nominal
    out = []
    for p, nom, rel in (
        ("inertia_kgm2", n.inertia_kgm2, tol.inertia_rel),
        ("damping_Nms_per_rad", n.damping_Nms_per_rad, tol.damping_rel),
        ("stiffness_Nm_per_rad", n.stiffness_Nm_per_rad, tol.stiffness_rel),
    ):
        lim = rel * abs(nom)
        out.append(Check(p, v[p], nom, lim, abs(v[p] - nom) <= lim, f"within {rel:.0%} of nominal"))
    for p, lim in (
        ("coulomb_Nm", tol.coulomb_max_nm),
        ("gravity_Nm", tol.gravity_max_nm),
        ("delay_s", tol.delay_max_s),
    ):
        out.append(Check(p, v[p], 0.0, lim, abs(v[p]) <= lim, f"|value| ≤ {lim:g} {UNITS[p]}"))
    out.append(
        Check("vaf_percent", fit.vaf_percent, 100.0, tol.vaf_min_percent,
              fit.vaf_percent >= tol.vaf_min_percent, f"≥ {tol.vaf_min_percent:g} %")
    )  # fmt: skip
    return out


NOT_VALID = "NOT VALID (hands on the wheel)"


def hands_on(fit: RigFit) -> bool:
    """Whether the recording shows hands on the wheel (:func:`hands_on_evidence`)."""
    return bool(fit.prep.warnings)


def verdict_status(fit: RigFit, checks: list[Check]) -> str:
    """The verdict: "PASS", "FAIL" or "NOT VALID". A held wheel's values are those of the wheel and
    the arm together: judging them against the rig's tolerances would pass or fail the arm,
    so such a recording gets no pass or fail at all."""
    if hands_on(fit):
        return "NOT VALID"
    return "PASS" if all(c.passed for c in checks) else "FAIL"


def verdict_line(fit: RigFit, checks: list[Check]) -> str:
    """The verdict in words, as printed and as the page's headline: "PASS", "FAIL (names of
    the failed checks)" or :data:`NOT_VALID`."""
    status = verdict_status(fit, checks)
    if status == "NOT VALID":
        return NOT_VALID
    if status == "FAIL":
        return "FAIL (" + ", ".join(c.name for c in checks if not c.passed) + ")"
    return status


def format_vaf(v: float) -> str:
    """The VAF as every output writes it (terminal, page, figure): two decimals."""
    return f"{v:.2f} %"


def fit_warnings(fit: RigFit, checks: list[Check]) -> list[str]:
    """What makes the result unfit for use: signs of hands on the wheel, and values the
    recording does not determine (an SEM larger than the value itself and than the tolerance
    it is judged against: a value near zero may carry an SEM up to its tolerance, as a clear
    "no friction" does)."""
    out = list(fit.prep.warnings)
    for c in checks:
        sem = fit.sem.get(c.name)
        if sem is None:
            continue
        if sem > abs(c.value) and sem > c.limit:
            unit = UNITS[c.name]
            out.append(
                f"{LABELS[c.name]}: its SEM ({_g(sem, 2)} {unit}) exceeds the value itself "
                f"({_g(c.value, 3)} {unit}) and the tolerance ({_g(c.limit, 3)} {unit}): the "
                "recording does not determine it, and its verdict means nothing"
            )
    return out


# -- output --------------------------------------------------------------------------------------
def _figure(fit: RigFit, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = fit.prep
    fig, ax = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True)
    ax[0].plot(p.time_s, p.perturbation_Nm, lw=0.6, color="0.3")
    ax[0].set_ylabel("T_p (N·m)")
    ax[1].plot(p.time_s, np.where(p.mask, p.angle_rad, np.nan), lw=0.8, label="measured")
    ax[1].plot(p.time_s, fit.model_angle, lw=0.8, ls="--", label="model")
    ax[1].set_ylabel("θ (rad)")
    ax[1].legend(loc="upper right", fontsize=8)
    ax[2].plot(p.time_s, (p.angle_rad - fit.model_angle) * 1e3, lw=0.6, color="C3")
    ax[2].set_ylabel("residual (mrad)")
    ax[2].set_xlabel("time (s)")
    out = np.flatnonzero(np.diff(np.concatenate(([0], (~p.mask).astype(np.int8), [0]))))
    for a, b in zip(out[::2], out[1::2], strict=True):  # stretches left out of the fit
        for x in ax:
            x.axvspan(p.time_s[a], p.time_s[min(b, len(p.time_s) - 1)], color="0.9", lw=0)
    ax[0].set_title(f"rig check: VAF {format_vaf(fit.vaf_percent)} (grey: left out, gaps)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _g(v: float, digits: int) -> str:
    """``digits`` significant digits, as ``:g`` but in plain notation for ordinary magnitudes
    (130, 0.00018), as the report writes numbers; a power of ten only outside 1e-4…1e6."""
    if not math.isfinite(v) or v == 0:
        return f"{v:g}"
    r = float(f"{v:.{digits}g}")
    if 1e-4 <= abs(r) < 1e6:
        return np.format_float_positional(r, trim="-")
    return f"{v:.{digits}g}"


def _fmt(v: float) -> str:
    return _g(v, 4)


def format_pm(v: float, sem: float | None) -> str:
    """A value with its SEM, the value to the SEM's second significant digit."""
    if sem is None or not sem > 0:
        return f"{_g(v, 4)} (at a bound)" if sem is None else _g(v, 4)
    decimals = max(0, 1 - math.floor(math.log10(sem)))
    if decimals > 8:
        return f"{_g(v, 6)} ± {_g(sem, 2)}"
    return f"{v:.{decimals}f} ± {_g(sem, 2)}"


def _html(fit: RigFit, checks: list[Check], tol_source: str) -> str:
    status = verdict_status(fit, checks)
    judged = status != "NOT VALID"
    rows = []
    for c in checks:
        if c.name in fit.sem:
            val = f"{format_pm(c.value, fit.sem[c.name])} {UNITS.get(c.name, '%')}"
        elif c.name == "vaf_percent":
            val = format_vaf(c.value)
        else:
            val = f"{_fmt(c.value)} {UNITS.get(c.name, '%')}"
        label = LABELS.get(c.name, "VAF")
        if not judged:
            cell = "<td>not judged</td>"
        else:
            cell = f"<td class={'ok' if c.passed else 'bad'}>{'pass' if c.passed else 'FAIL'}</td>"
        rows.append(
            f"<tr><td>{html.escape(label)}</td><td>{val}</td><td>{_fmt(c.nominal)}</td>"
            f"<td>{html.escape(c.rule)}</td>{cell}</tr>"
        )
    headline = html.escape(NOT_VALID if not judged else status)
    not_valid = (
        "<p class=bad>The recording shows hands on the wheel (warnings below): the values are "
        "those of the wheel and the arm together, not the rig's, so they are not judged "
        "against the tolerances. Record again with the hands off.</p>"
        if not judged
        else ""
    )
    warned = fit_warnings(fit, checks)
    notes = (
        "".join(
            [f"<li class=bad>warning: {html.escape(s)}</li>" for s in warned]
            + [f"<li>{html.escape(s)}</li>" for s in fit.prep.notes]
        )
        or "<li>none</li>"
    )
    warning_box = (
        "<h2 class=bad>Warnings</h2><ul>"
        + "".join(f"<li>{html.escape(s)}</li>" for s in warned)
        + "</ul>"
        if warned
        else ""
    )
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>Rig check</title>
<style>body{{font-family:sans-serif;max-width:62em;margin:2em auto}}td,th{{padding:.2em .7em;
text-align:left}}.ok{{color:#070}}.bad{{color:#b00;font-weight:bold}}</style></head><body>
<h1>Rig check: <span class={"ok" if status == "PASS" else "bad"}>{headline}</span></h1>
{not_valid}{warning_box}
<p>Recording: <code>{html.escape(fit.source)}</code>.
Nominal wheel: {html.escape(fit.nominal.source)}. Tolerances: {html.escape(tol_source)}.</p>
<p>Model: I·ω' = lag<sub>τ</sub>(T<sub>p</sub> − b·ω − k·θ) + T<sub>0</sub>
− F<sub>c</sub>·tanh(ω/ε) − m·g·r·sin θ,
T<sub>0</sub> = {html.escape(format_pm(fit.offset_nm, fit.offset_sem))} N·m (not judged),
ε = {fit.eps:g} rad/s; values ± SEM (Jacobian sandwich, Newey–West, {fit.hac_lags} lags).
The lag is reported as its continuous-time equivalent, h/(e<sup>h/τ</sup> − 1) + h/2 (hold h =
{fit.hold_s * 1e3:.3g} ms).</p>
<table><tr><th>quantity</th><th>measured</th><th>nominal</th><th>tolerance</th><th>verdict</th></tr>
{"".join(rows)}</table>
<p>At a bound of the fit (SEM not meaningful): {", ".join(fit.at_bound) or "none"}.</p>
<h2>Fit and residual</h2><img src="{FIGURE}" alt="The perturbation torque, the measured and
the model's wheel angle, and their difference against time" style="max-width:100%">
<h2>Notes on the recording</h2><ul>{notes}</ul>
<p>Use the result: <code>steerlab simulate --rig-model {RIG_JSON}</code>; <code>steerlab run
--rig-check {RIG_JSON}</code> records it in the session file.</p></body></html>
"""


def write_outputs(
    fit: RigFit, out_dir: str | Path, tol: Tolerances, tol_source: str
) -> list[Check]:
    """``rig.json``, ``fit.png`` and ``index.html`` in ``out_dir`` (written to a temporary file
    each and renamed, so a reader never sees half a file)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    checks = verdict(fit, tol)
    d = fit.to_dict()
    status = verdict_status(fit, checks)
    d["verdict"] = {
        "passed": status == "PASS",
        "status": status,
        "not_valid_reason": "hands on the wheel" if status == "NOT VALID" else None,
        "tolerances": tol.__dict__,
        "tolerances_source": tol_source,
        "checks": [c.__dict__ for c in checks],
    }
    d["warnings"] = fit_warnings(fit, checks)
    _atomic(out / RIG_JSON, json.dumps(d, indent=2, allow_nan=False, default=_plain))
    fig_tmp = out / f".{FIGURE}.tmp.png"
    _figure(fit, fig_tmp)
    os.replace(fig_tmp, out / FIGURE)
    _atomic(out / INDEX_HTML, _html(fit, checks, tol_source))
    return checks


def _atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write(text)
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def identify(
    recording: str | Path,
    out_dir: str | Path,
    *,
    rig_path: str | Path | None = None,
    protocol_path: str | Path | None = None,
    trial: str | None = None,
) -> tuple[RigFit, list[Check]]:
    """Read, check, fit and write: the whole of ``steerlab rig-check --recording``."""
    from steerlab.hardware.rig import load_rig
    from steerlab.protocols.protocol import load_protocol

    rig = load_rig(rig_path)
    tol = Tolerances.from_rig(rig)
    tol_source = f"[rig_check] of {rig.source}" if getattr(rig, "rig_check", None) else "defaults"
    rec = read_recording(recording, trial)
    nominal = rec.nominal
    if nominal is None or protocol_path is not None:
        proto = load_protocol(protocol_path)
        nominal = Nominal.from_wheel(proto.wheel, f"the protocol {proto.source_path or proto.name}")
    prep = prepare(rec)
    fit = fit_rig(prep, nominal=nominal)
    checks = write_outputs(fit, out_dir, tol, tol_source)
    return fit, checks


# -- using a result ----------------------------------------------------------------------------
def load_rig_model(path: str | Path) -> dict:
    """A ``rig.json`` as a dict (values checked); raises :class:`RigCheckError` naming the key."""
    p = Path(path)
    if p.is_dir():
        p = p / RIG_JSON
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except OSError as e:
        raise RigCheckError(f"{p}: cannot read ({e.strerror})") from None
    except json.JSONDecodeError as e:
        raise RigCheckError(f"{p}: not valid JSON ({e})") from None
    return checked_rig_model(d, str(p))


def checked_rig_model(d: Any, where: str) -> dict:
    """``d`` (a rig.json's content, or a session file's record of one) with its values checked,
    and ``_path`` set to ``where``; :class:`RigCheckError` names ``where`` and the key."""
    if not isinstance(d, dict):
        raise RigCheckError(f"{where}: not a rig-check result (expected an object)")
    for key in PARAMS:
        v = d.get(key)
        if not isinstance(v, dict) or not _is_number(v.get("value")):
            raise RigCheckError(f"{where}: {key}: missing, or without a numeric 'value'")
        if not math.isfinite(v["value"]):
            raise RigCheckError(f"{where}: {key}.value: not finite")
    if d["inertia_kgm2"]["value"] <= 0:
        raise RigCheckError(f"{where}: inertia_kgm2.value: must be > 0")
    if d["delay_s"]["value"] < 0:
        raise RigCheckError(f"{where}: delay_s.value: must be ≥ 0")
    model = d.get("model")
    if model is not None and not isinstance(model, dict):
        raise RigCheckError(f"{where}: model: expected an object")
    eps = (model or {}).get("friction_eps_rad_s", EPS_RAD_S)
    # measured_world divides by it: a bad value would fail later, far from the file.
    if not _is_number(eps) or not math.isfinite(eps) or eps <= 0:
        raise RigCheckError(f"{where}: model.friction_eps_rad_s: must be a number > 0")
    return {**d, "_path": where}


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def recorded_rig_model(attrs: Mapping[str, Any], where: str) -> dict | None:
    """The measured wheel a session file records, as a checked rig model: its ``wheel_used``
    when that is "measured" (``simulate --rig-model``), else its ``rig_check`` (``run
    --rig-check``); None when it records neither, or a nominal wheel. ``_path`` is the rig.json
    the record names (it need not exist any more: the values are in the record),
    ``_recorded_in`` is ``where``."""
    for key in ("wheel_used", "rig_check"):
        raw = attrs.get(key)
        if raw is None:
            continue
        try:
            d = raw if isinstance(raw, dict) else json.loads(raw)
        except (TypeError, ValueError):
            raise RigCheckError(f"{where}: attribute {key}: not valid JSON") from None
        if not isinstance(d, dict):
            raise RigCheckError(f"{where}: attribute {key}: expected an object")
        if key == "wheel_used":
            if d.get("source") != "measured":
                return None
            # simulate records the values plain, a rig check as {"value", "sem"}.
            d = {**d, **{k: {"value": d.get(k)} for k in PARAMS}}
        model = checked_rig_model(d, f"{where}: attribute {key}")
        origin = d.get("detail") if key == "wheel_used" else d.get("path")
        model["_path"] = str(origin) if origin else f"{where} ({key})"
        model["_recorded_in"] = where
        return model
    return None


def measured_world(rig_model: dict, world, wheel, fs_hz: float):
    """(WorldConfig, VirtualWheel) for the simulator with the measured wheel: inertia, rendered
    damping and stiffness, friction, imbalance, and the actuator lag as the simulated loop's
    lag with the same continuous-time equivalent (:func:`lag_time_constant`)."""
    from steerlab.hardware.sim.mechanisms import ActuatorLag, CoulombFriction, WheelImbalance

    v = {k: float(rig_model[k]["value"]) for k in PARAMS}
    eps = float((rig_model.get("model") or {}).get("friction_eps_rad_s", EPS_RAD_S))
    mech = replace(
        world.mechanisms,
        coulomb_friction=CoulombFriction(v["coulomb_Nm"], eps),
        wheel_imbalance=WheelImbalance(v["gravity_Nm"]),
        actuator_lag=ActuatorLag(lag_time_constant(v["delay_s"], 1.0 / fs_hz)),
    )
    new_world = replace(world, wheel_inertia_kgm2=v["inertia_kgm2"], mechanisms=mech)
    new_wheel = replace(
        wheel,
        inertia_kgm2=v["inertia_kgm2"],
        damping_nms_per_rad=v["damping_Nms_per_rad"],
        stiffness_nm_per_rad=v["stiffness_Nm_per_rad"],
    )
    return new_world, new_wheel


def summary(fit: RigFit, checks: list[Check]) -> str:
    lines = []
    for p in PARAMS:
        lines.append(f"  {LABELS[p]:<22} {format_pm(fit.values[p], fit.sem[p])} {UNITS[p]}")
    off = format_pm(fit.offset_nm, fit.offset_sem)
    lines.append(f"  {'torque offset T_0':<22} {off} N·m (not judged)")
    lines.append(f"  {'VAF':<22} {format_vaf(fit.vaf_percent)}")
    lines.append("verdict: " + verdict_line(fit, checks))
    if hands_on(fit):
        lines.append(
            "  the values are the wheel's and the arm's together, not the rig's: not judged "
            "against the tolerances"
        )
    lines += [f"warning: {w}" for w in fit_warnings(fit, checks)]
    return "\n".join(lines)


def rig_check_record(rig_model: dict) -> dict:
    """What a session file records of the rig's last check (attribute ``rig_check``)."""
    verdict_ = rig_model.get("verdict") or {}
    return {
        "path": rig_model["_path"],
        "recording": rig_model.get("recording"),
        "passed": verdict_.get("passed"),
        "vaf_percent": rig_model.get("vaf_percent"),
        **{k: rig_model[k] for k in PARAMS},
    }
