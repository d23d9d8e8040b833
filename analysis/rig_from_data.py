"""The wheel the driver felt and the recording's timing, identified from hands-on data.

Whatever the arm does, the wheel obeys its own equation, and all three of its signals are
measured. At the excited frequencies, with s = j2πf, h the sample interval and
G(s) = (1 − e^{−sh})/(sh) the zero-order hold of a command held over one sample:

    G·Tp − Td·e^{−s τ_d h} = [I s² + R(s)·(b s + k)] · Θ·e^{−s τ_θ h}

- Tp is the perturbation command, held over the interval that follows its sample;
- τ_θ and τ_d (in samples) are when the angle and the driver torque were read, relative to
  that command: 0 is Steerlab's loop (read, then command), 1 a system that reads its outputs
  at the end of the interval over which it held the command; a fraction of a sample, a skew
  between the two channels (a torque sensor filtered or averaged differently) lies between;
- R(s) says how the wheel's damping and spring act: rendered by the motor from the angle and
  velocity of the sample and held (R = G, Steerlab's rig), or physical, acting continuously
  (R = 1, a wheel with a real spring and damper, or a drive that renders them inside its own
  fast loop, as a SensoDrive does).

The remnant moves θ and Td together along the wheel's equation, so it cancels there: what is
left is sensor noise, measured per band at the unexcited bins of the same residual. Dry
friction F_c·tanh(ω/ε) and an imbalance's curvature m·g·r·(sin θ − θ) enter through the spectra
of those functions of the measured angle. The fit is weighted least squares on the excited bins
of every trial at once (shared parameters), the noise re-estimated three times; SEMs from the
Jacobian, scaled by the residual's own ratio to its noise where above 1.

Three fits per rendering (``RigFromData.fits``): ``nominal`` (the rig's b and k, I free),
``friction`` (the same with F_c and m·g·r free), ``free`` (I, b, k, F_c, m·g·r free: the data's
wheel, stated only); the two timings are free in all. Where neither rendering's ``friction`` fit
explains the data, a ``lag`` fit per rendering frees a first-order actuator lag as well (the
rendering and timing are then read from it; the lag is left to the mechanisms). What the
simulated rig takes from them
(``convention``; docs/diagnosis.md, "The rig and the timing, from the data"):

- the rendering, where the ``nominal`` fits differ by more than ``RENDERING_MIN_M2LL`` units
  of −2 log L (× the residual's ratio to the noise where above 1); otherwise (to first order in
  h the two are the same wheel with I and b shifted by b·h/2 and k·h/2) the one whose
  ``friction`` fit needs the smaller change of the rig's inertia, and the rig's own where even
  that fit leaves more than ``MAX_NOISE_RATIO`` × the noise;
- from that rendering's ``nominal`` fit where it is within ``MAX_NOISE_RATIO`` × the noise, else
  its ``friction`` fit (:func:`convention_fit`): the inertia, where it departs from the rig's by
  more than 3 SEMs and ``INERTIA_TAKE_REL`` and the fit is within the noise (no mechanism acts as
  an inertia; damping and stiffness stay the rig's: a departure there is friction or an
  unbalanced wheel, which the diagnosis names as mechanisms);
- the angle's timing where it is not before the command (before it is the torque arriving
  late: an actuator lag, a mechanism), and the torque's skew from it within
  ``MAX_CONVENTION_SKEW`` samples (more is a sensor delay, a mechanism): :func:`_timing`.

Computation only: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from steerlab.analysis.periods import find_excitation, select_periods
from steerlab.analysis.rigcheck import EPS_RAD_S as RIGCHECK_EPS_RAD_S
from steerlab.protocols.datafile import DataFileError
from steerlab.protocols.interchange import RENDERINGS, check_rendering, stated_timing
from steerlab.protocols.protocol import VirtualWheel
from steerlab.protocols.records import STATUS_COMPLETE, TrialRecord

NOISE_BAND_BINS = 48  # unexcited bins per noise band
NOISE_ITERATIONS = 3
RENDERING_MIN_M2LL = 10.0
INERTIA_MIN_REL = 0.005
# A wheel between the renderings (rendered in a loop faster than the recording, its outputs
# averaged) is to first order a rendering's wheel with another inertia: a 1 kHz loop averaged to
# 250 Hz is 0.35 % lighter than the continuous wheel, and at 250 Hz the diagnosis sees that
# (4× the noise). Steerlab's own data depart by a few hundredths of a per cent.
INERTIA_TAKE_REL = 0.002
# samples: channels filtered or averaged differently stay within a sample of each other; a
# torque a whole sample or more late is a sensor delay (a mechanism: Steerlab's own world hides
# one of a sample)
MAX_CONVENTION_SKEW = 0.75
WHOLE_SAMPLE_TOL = 0.1  # samples: a timing this close to a whole number, within 3 SEMs, is it
MIN_TIMING_SAMPLES = 0.25  # a smaller departure from reading at the command is not taken
# The wheel's equation explains the data within this × the noise power, or the data do not pin
# the wheel down (a clipping rig, dry friction, a lag): its inertia is then the rig's.
MAX_NOISE_RATIO = 1.5
FRICTION_EPS_RAD_S = RIGCHECK_EPS_RAD_S  # the smooth sign tanh(ω/ε), as the rig check's
FIT_NAMES = (
    "inertia_kgm2",
    "damping_Nms_per_rad",
    "stiffness_Nm_per_rad",
    "theta_offset_samples",
    "torque_offset_samples",
    "coulomb_Nm",
    "gravity_Nm",
    "lag_s",
)
NOMINAL_FREE = ("inertia_kgm2", "coulomb_Nm", "gravity_Nm")
WHEEL_FREE = ("inertia_kgm2", "damping_Nms_per_rad", "stiffness_Nm_per_rad", "coulomb_Nm",
              "gravity_Nm")  # fmt: skip
# A first-order lag of the actuator, free beside the nominal wheel's: a mechanism the diagnosis
# names, but one that bends the wheel's equation, so the rendering and timing are read with it.
LAG_FREE = (*NOMINAL_FREE, "lag_s")
LAG_START_S = 1e-3
# Read offsets a timing fit starts from (samples): Steerlab's and the end-of-interval read.
TIMING_STARTS = ((0.0, 0.0), (1.0, 1.0), (1.0, 0.0), (0.0, 1.0))


class RigFromDataError(ValueError):
    """Data from which the wheel and timing cannot be identified; the message says why."""


@dataclass(frozen=True)
class _Trial:
    label: str
    fs_hz: float
    s: np.ndarray  # j2πf at the bins used
    excited: np.ndarray
    band: np.ndarray
    tp: np.ndarray
    td: np.ndarray
    th: np.ndarray
    friction: np.ndarray  # spectrum of tanh(ω/ε), ω the angle's central difference
    gravity: np.ndarray  # spectrum of sin θ − θ (an imbalance beyond its small-angle spring)
    hold: np.ndarray  # G(s) at the bins

    @property
    def h(self) -> float:
        return 1.0 / self.fs_hz


@dataclass(frozen=True)
class WheelFit:
    """One hypothesis fitted to every trial: a rendering, which of I, b, k are free."""

    rendering: str
    free: tuple[str, ...]
    values: dict[str, float]  # inertia_kgm2, damping_Nms_per_rad, stiffness_Nm_per_rad,
    # theta_offset_samples, torque_offset_samples
    sem: dict[str, float]
    m2ll: float  # −2 log L (up to a constant) of the wheel's equation at the excited bins
    n: int  # complex residuals
    noise_ratio: float  # mean whitened residual power at the excited bins (1: noise)

    def to_dict(self) -> dict[str, Any]:
        return {
            "rendering": self.rendering,
            "free": list(self.free),
            "values": self.values,
            "sem": self.sem,
            "m2ll": self.m2ll,
            "n_bins": self.n,
            "noise_ratio": self.noise_ratio,
        }


@dataclass(frozen=True)
class Convention:
    """What the simulated rig takes from the data (or from what the recording states)."""

    rendering: str  # "sampled" or "continuous"
    inertia_kgm2: float
    theta_offset_samples: float
    torque_offset_samples: float
    source: dict[str, str] = field(default_factory=dict)  # per item: "data", "rig", "stated"
    notes: tuple[str, ...] = ()
    # A torque skew beyond a convention's (samples; 0: none), left to the diagnosis's
    # mechanisms (a sensor delay): not the arm's either, so the report undoes it.
    sensor_skew_samples: float = 0.0

    @property
    def is_steerlab(self) -> bool:
        return (
            self.rendering == "sampled"
            and self.theta_offset_samples == 0.0
            and self.torque_offset_samples == 0.0
        )


@dataclass(frozen=True)
class RigFromData:
    """The study's wheel and timing from its data, and the convention taken from them."""

    rig: VirtualWheel  # the rig's wheel they are compared with (nominal or a rig check's)
    rig_label: str
    fits: dict[str, WheelFit]  # "<rendering>/nominal", "/friction", "/free" (module docstring)
    convention: Convention
    n_trials: int
    rendering_told: bool  # whether the data tell the renderings apart
    fs_hz: float  # the trials' (median) sample rate: a sample in seconds

    def sensor_skew_sentence(self) -> str:
        """The torque skew left to the mechanisms, in words ("" where there is none)."""
        skew = self.convention.sensor_skew_samples
        if skew == 0.0:
            return ""
        return (
            f"the driver torque is recorded {abs(skew):.3g} sample(s) "
            f"({1e3 * abs(skew) / self.fs_hz:.3g} ms) {'later' if skew < 0 else 'earlier'} than "
            f"the angle, more than a recording convention makes (±{MAX_CONVENTION_SKEW:g} "
            "samples): a sensor delay"
        )

    def sentence(self) -> str:
        """One line: the data's wheel and timing beside the rig's."""
        c = self.convention
        f = convention_fit(self.fits, c.rendering)
        v, e = f.values, f.sem
        how = {
            "data": "",
            "stated": " (as the recording states)",
            "rig": " (the data cannot tell; the rig's kept)",
        }.get(
            c.source.get("rendering", ""),
            " (the data cannot tell by the fit; the one nearest the rig's inertia)",
        )
        told = (
            f"rendered {'continuously' if c.rendering == 'continuous' else 'sampled and held'}"
            + how
        )
        timing = (
            f"angle read {_when(v['theta_offset_samples'], e['theta_offset_samples'])}, "
            f"torque {_when(v['torque_offset_samples'], e['torque_offset_samples'])}"
        )
        r = self.rig
        w = self.fits[f"{c.rendering}/free"]
        wv, we = w.values, w.sem
        wheel = (
            f"with b, k, friction and imbalance free: b = "
            f"{_pm(wv['damping_Nms_per_rad'], we['damping_Nms_per_rad'])} N·m·s/rad, k = "
            f"{_pm(wv['stiffness_Nm_per_rad'], we['stiffness_Nm_per_rad'])} N·m/rad, F_c = "
            f"{_pm(wv['coulomb_Nm'], we['coulomb_Nm'])} N·m, m·g·r = "
            f"{_pm(wv['gravity_Nm'], we['gravity_Nm'])} N·m"
        )
        if "lag_s" in w.free:
            wheel = wheel.replace("with b, k,", "with b, k, an actuator lag,") + (
                f", lag = {_pm(1e3 * wv['lag_s'], 1e3 * we['lag_s'])} ms"
            )
        return (
            f"the data: I = {_pm(v['inertia_kgm2'], e['inertia_kgm2'])} kg·m², {told}, "
            f"{timing} ({wheel}); {self.rig_label}: I = {r.inertia_kgm2:.4g} kg·m², "
            f"b = {r.damping_nms_per_rad:.4g} N·m·s/rad, k = {r.stiffness_nm_per_rad:.4g} N·m/rad; "
            f"simulated: {describe(c)}"
        )

    def to_dict(self) -> dict[str, Any]:
        c = self.convention
        return {
            "method": (
                "G·Tp − Td·e^{−sτ_d h} = [I s² + R(s)(b s + k)]·Θ·e^{−sτ_θ h} at the excited "
                "bins, R = G (sampled and held) or 1 (continuous), weighted by the residual's "
                "noise at the unexcited bins; docs/diagnosis.md, 'The rig and the timing'"
            ),
            "n_trials": self.n_trials,
            "rig": {
                "label": self.rig_label,
                "inertia_kgm2": self.rig.inertia_kgm2,
                "damping_Nms_per_rad": self.rig.damping_nms_per_rad,
                "stiffness_Nm_per_rad": self.rig.stiffness_nm_per_rad,
            },
            "fits": {k: f.to_dict() for k, f in self.fits.items()},
            "rendering_told_apart": self.rendering_told,
            "convention": {
                "rendering": c.rendering,
                "inertia_kgm2": c.inertia_kgm2,
                "theta_offset_samples": c.theta_offset_samples,
                "torque_offset_samples": c.torque_offset_samples,
                "source": c.source,
                "sensor_skew_samples": c.sensor_skew_samples,
                "notes": list(c.notes),
                "sentence": describe(c),
            },
        }


def describe(c: Convention) -> str:
    """The convention in words."""
    how = "physical (continuous)" if c.rendering == "continuous" else "rendered, sampled and held"
    return (
        f"wheel {c.inertia_kgm2:.4g} kg·m², damping and spring {how}; angle read "
        f"{_when(c.theta_offset_samples, None)}, torque {_when(c.torque_offset_samples, None)}"
    )


def _pm(v: float, e: float | None) -> str:
    """v ± e with e to two significant digits and v to the same decimals."""
    if e is None or not math.isfinite(e) or e <= 0:
        return f"{v:.4g}"
    d = max(0, min(7, 1 - int(math.floor(math.log10(e)))))
    return f"{v:.{d}f} ± {e:.{d}f}"


def _when(v: float, e: float | None) -> str:
    """An offset in samples relative to the command, in words."""
    if v == 0.0:
        return "with the command"
    side = "after" if v > 0 else "before"
    return f"{_pm(abs(v), e)} sample(s) {side} the command"


def zoh(s: np.ndarray, h: float) -> np.ndarray:
    """G(s) = (1 − e^{−sh})/(sh): a command held over one sample, relative to its sample."""
    s = np.asarray(s, dtype=complex)
    out = np.ones_like(s)
    nz = s != 0
    out[nz] = (1.0 - np.exp(-s[nz] * h)) / (s[nz] * h)
    return out


def _spectra(x: np.ndarray, start: int, stop: int, bins: np.ndarray) -> np.ndarray:
    # The diagnosis' own spectra (ramp removed); imported here, not at the top: the diagnosis
    # package imports this module.
    from steerlab.analysis.diagnosis.data import channel_spectra

    return channel_spectra(x, start, stop, bins)[0]


def _prepare(rec: TrialRecord) -> _Trial | None:
    if rec.status != STATUS_COMPLETE or rec.familiarization:
        return None
    try:
        sel = select_periods(rec)
        exc = find_excitation(rec, sel)
    except ValueError:
        return None
    from steerlab.analysis.diagnosis.data import analysis_bins  # the diagnosis' own bin grid

    fs = float(rec.fs_hz)
    P = sel.n_samples
    bins, excited, _ = analysis_bins(fs, sel, exc)
    K = len(bins)
    if not excited.any():
        return None
    start, stop = sel.start, sel.stop
    chans = (rec.perturbation_torque_Nm, rec.driver_torque_Nm, rec.wheel_angle_rad)
    if not all(
        np.all(np.isfinite(np.asarray(c)[start : min(stop + 1, rec.n_samples)])) for c in chans
    ):
        return None
    tp = np.fft.rfft(np.asarray(rec.perturbation_torque_Nm, float)[start:stop])[bins] * (2.0 / P)
    td = _spectra(np.asarray(rec.driver_torque_Nm, float), start, stop, bins)
    theta = np.asarray(rec.wheel_angle_rad, float)
    th = _spectra(theta, start, stop, bins)
    omega = np.gradient(theta, 1.0 / fs)
    friction = _spectra(np.tanh(omega / FRICTION_EPS_RAD_S), start, stop, bins)
    gravity = _spectra(np.sin(theta) - theta, start, stop, bins)
    s = 2j * np.pi * bins * fs / P
    band = (np.arange(K) // NOISE_BAND_BINS).astype(int)
    if band[-1] > 0 and np.count_nonzero(band == band[-1]) < NOISE_BAND_BINS // 2:
        band[band == band[-1]] -= 1
    return _Trial(
        rec.label(), fs, s, excited, band, tp, td, th, friction, gravity, zoh(s, 1.0 / fs)
    )


def _residual(t: _Trial, x: np.ndarray, rendering: str) -> np.ndarray:
    """G·Tp − Td·e^{−sτ_d h} − ([I s² + R (b s + k)]·Θ + F_c·F + m·g·r·S)·e^{−sτ_θ h} at every
    bin of ``t`` (F, S: the spectra of tanh(ω/ε) and sin θ − θ, read with the angle); with a
    lag τ_a of the actuator, what the motor renders (G·Tp, and R (b s + k)·Θ where sampled)
    passes through 1/(1 + s τ_a) first."""
    I, b, k, tth, ttd, fc, grav, lag = x
    h = t.h
    G = t.hold
    shift = np.exp(-t.s * tth * h)
    td = t.td * np.exp(-t.s * ttd * h)
    motor = G * t.tp
    wheel = I * t.s**2 * t.th
    rendered = (b * t.s + k) * t.th
    if rendering == "sampled":
        motor = motor - G * rendered * shift
    else:
        wheel = wheel + rendered
    if lag != 0.0:
        motor = motor / (1.0 + t.s * lag)
    if fc != 0.0 or grav != 0.0:
        wheel = wheel + fc * t.friction + grav * t.gravity
    return motor - td - wheel * shift


def _noise_weights(t: _Trial, x: np.ndarray, rendering: str) -> np.ndarray:
    """1/σ per excited bin: σ² the mean |residual|² at the unexcited bins of its band."""
    r = _residual(t, x, rendering)
    var = np.full(len(r), np.nan)
    for b in np.unique(t.band):
        m = t.band == b
        u = m & ~t.excited
        if u.any():
            var[m] = np.mean(np.abs(r[u]) ** 2)
    if not np.isfinite(var).any():
        var[:] = 1.0
    var[~np.isfinite(var)] = np.nanmax(var)
    var = np.maximum(var, np.finfo(float).tiny)
    return 1.0 / np.sqrt(var[t.excited])


def _fit(
    trials: Sequence[_Trial],
    rig: VirtualWheel,
    rendering: str,
    free: tuple[str, ...],
    start: WheelFit | None = None,
) -> WheelFit:
    """One hypothesis fitted to every trial; ``start``: a fit of the same rendering to start
    from (its timings: no search over TIMING_STARTS)."""
    names = FIT_NAMES
    base = np.array(
        [rig.inertia_kgm2, rig.damping_nms_per_rad, rig.stiffness_nm_per_rad]
        + [0.0] * (len(names) - 3)
    )
    if "lag_s" in free:
        base[names.index("lag_s")] = LAG_START_S
    idx = [i for i, n in enumerate(names) if n in free or n.endswith("offset_samples")]
    # A lag is ≥ 0 (a negative one is a command that arrives before it is sent).
    lower = np.array([0.0 if names[i] == "lag_s" else -np.inf for i in idx])

    def full(z: np.ndarray) -> np.ndarray:
        x = base.copy()
        x[idx] = z
        return x

    x = base.copy()
    weights = [np.ones(int(t.excited.sum())) for t in trials]
    first = 0
    if start is not None:
        x[[3, 4]] = start.values["theta_offset_samples"], start.values["torque_offset_samples"]
        x[0] = start.values["inertia_kgm2"]
        first = 1
    best = None
    for it in range(first, NOISE_ITERATIONS + 1):
        if it > 0:
            weights = [_noise_weights(t, x, rendering) for t in trials]

        def fun(z: np.ndarray, weights=weights) -> np.ndarray:
            xx = full(z)
            parts = [
                _residual(t, xx, rendering)[t.excited] * w
                for t, w in zip(trials, weights, strict=True)
            ]
            r = np.concatenate(parts)
            return np.concatenate([r.real, r.imag])

        starts = TIMING_STARTS if it == 0 else ((x[3], x[4]),)
        best = None
        for a, d in starts:
            z0 = x[idx].copy() if it > 0 else base[idx].copy()
            z0[[j for j, i in enumerate(idx) if i == 3]] = a
            z0[[j for j, i in enumerate(idx) if i == 4]] = d
            r = least_squares(fun, np.maximum(z0, lower), x_scale="jac", bounds=(lower, np.inf))
            if best is None or r.cost < best.cost:
                best = r
        assert best is not None
        x = full(best.x)
    assert best is not None
    n = len(best.fun) // 2
    ratio = float(2.0 * best.cost / n)  # mean |r|²/σ² per complex bin
    J = best.jac
    try:
        cov = np.linalg.pinv(J.T @ J) * max(ratio / 2.0, 0.5)
        sem_v = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        sem_v = np.full(len(idx), np.nan)
    values = {n_: float(v) for n_, v in zip(names, x, strict=True)}
    sem = {names[i]: float(e) for i, e in zip(idx, sem_v, strict=True)}
    return WheelFit(rendering, tuple(free), values, sem, float(4.0 * best.cost), n, ratio)


def convention_fit(fits: dict[str, WheelFit], rendering: str) -> WheelFit:
    """The fit the convention reads its inertia and timing from: the rig's b and k with only the
    inertia free where that explains the data within noise (the timings are sharpest there); else,
    where one was fitted and explains them, the one with an actuator lag free; else the one with
    dry friction and an imbalance free as well."""
    plain = fits[f"{rendering}/nominal"]
    if plain.noise_ratio <= MAX_NOISE_RATIO:
        return plain
    lag = fits.get(f"{rendering}/lag")  # fitted only where neither wheel explains the data
    if lag is not None and lag.noise_ratio <= MAX_NOISE_RATIO:
        return lag
    return fits[f"{rendering}/friction"]


def _timing(v: float, e: float, pinned: bool, snap: bool = False) -> float:
    """A fitted timing as the convention takes it: a whole sample where the data allow (within
    3 SEMs, or with ``snap`` within WHOLE_SAMPLE_TOL: a read offset is a convention of whole
    samples, start or end, where a skew is what a filter makes), and none (0) where it is
    within 3 SEMs of none. Where the wheel's equation leaves more than
    noise (not ``pinned``: a lag, friction, clipping bend the fit) only a whole number of
    samples, at least MIN_TIMING_SAMPLES from none, is taken."""
    r = round(v)
    whole = abs(v - r) <= WHOLE_SAMPLE_TOL
    if whole and (abs(v - r) <= 3 * e or snap or not pinned):
        v = float(r)
    if abs(v) <= 3 * e or (not pinned and (abs(v) < MIN_TIMING_SAMPLES or not whole)):
        return 0.0
    return float(v)


def identify(
    records: Sequence[TrialRecord],
    rig: VirtualWheel | None = None,
    rig_label: str = "the rig (nominal)",
    rig_rendering: str = "sampled",
    stated: dict[str, Any] | None = None,
    max_trials: int | None = None,
) -> RigFromData:
    """Identify the wheel and timing from the measured trials of ``records`` (at most
    ``max_trials`` of the usable ones, taken evenly across the study).

    ``rig``: the wheel the rig is meant to have (nominal by default); ``rig_rendering``: how
    that rig renders its damping and spring, kept where the data cannot tell; ``stated``: what
    the recording says of itself (``rendering``, ``theta_offset_samples``,
    ``torque_offset_samples``), used as stated. Raises :class:`RigFromDataError` when no trial
    can be used."""
    rig = rig or VirtualWheel()
    stated = dict(stated or {})
    trials = [t for t in (_prepare(r) for r in records) if t is not None]
    if max_trials is not None and len(trials) > max_trials:
        pick = np.linspace(0, len(trials) - 1, max_trials).round().astype(int)
        trials = [trials[i] for i in sorted(set(pick.tolist()))]
    if not trials:
        raise RigFromDataError(
            "no complete measured trial with a perturbation to identify the wheel from"
        )
    fits: dict[str, WheelFit] = {}
    for rendering in RENDERINGS:
        # The rendering is told apart with the rig's b and k and nothing else free (a free
        # friction absorbs the damping the wrong rendering needs); the inertia and the timing
        # are read with dry friction and an imbalance free (left out, they bend both: a friction
        # study's read offset came out 1.2 samples for 1).
        plain = fits[f"{rendering}/nominal"] = _fit(trials, rig, rendering, ("inertia_kgm2",))
        fits[f"{rendering}/friction"] = _fit(trials, rig, rendering, NOMINAL_FREE, plain)
        fits[f"{rendering}/free"] = _fit(trials, rig, rendering, WHEEL_FREE, plain)
    notes: list[str] = []
    # Neither wheel explains the data, even with friction: an actuator lag bends the equation
    # (under an end-of-interval read it and the read partly cancel, and the timing read without
    # it is wrong). The rendering and timing are then read with a lag free.
    basis, near = "nominal", "friction"
    if min(fits[f"{r}/friction"].noise_ratio for r in RENDERINGS) > MAX_NOISE_RATIO:
        for rendering in RENDERINGS:
            fits[f"{rendering}/lag"] = _fit(trials, rig, rendering, LAG_FREE)
        if min(fits[f"{r}/lag"].noise_ratio for r in RENDERINGS) <= MAX_NOISE_RATIO:
            basis = near = "lag"
            for rendering in RENDERINGS:  # the data's wheel, stated: with the lag free too
                fits[f"{rendering}/free"] = _fit(
                    trials, rig, rendering, (*WHEEL_FREE, "lag_s"), fits[f"{rendering}/lag"]
                )
    source: dict[str, str] = {}
    d = fits[f"sampled/{basis}"].m2ll - fits[f"continuous/{basis}"].m2ll
    misfit = min(fits[f"sampled/{basis}"].noise_ratio, fits[f"continuous/{basis}"].noise_ratio)
    # Where the equation leaves more than noise, the difference must stand above that misfit.
    told = abs(d) > RENDERING_MIN_M2LL * max(1.0, misfit)
    if "rendering" in stated:
        rendering = str(stated["rendering"])
        source["rendering"] = "stated"
    elif told:
        rendering = "continuous" if d > 0 else "sampled"
        source["rendering"] = "data"
    elif min(fits[f"{r}/{near}"].noise_ratio for r in RENDERINGS) > MAX_NOISE_RATIO:
        rendering = rig_rendering
        source["rendering"] = "rig"
    else:
        # Both fit as well: the one that needs the smaller change of the rig's inertia (on
        # equal terms, the rig's own), read with friction and imbalance free.
        def change(r: str) -> float:
            return abs(fits[f"{r}/{near}"].values["inertia_kgm2"] - rig.inertia_kgm2)

        rendering = min(RENDERINGS, key=lambda r: (change(r), r != rig_rendering))
        if change(rendering) > INERTIA_MIN_REL * rig.inertia_kgm2:
            rendering = rig_rendering  # neither gives the rig's wheel: a mechanism bends both
        source["rendering"] = "rig" if rendering == rig_rendering else "data (closest inertia)"
    f = convention_fit(fits, rendering)
    if f is fits.get(f"{rendering}/lag"):
        notes.append(
            f"an actuator lag of {1e3 * f.values['lag_s']:.3g} ms bends the wheel's equation: "
            "the rendering and the timing are read with it free (the lag is left to the "
            "mechanisms)"
        )
    # Pinned down: the rig's own wheel explains the data within noise. Where it does only with
    # friction free, that friction's form may not be ours (Stribeck): fractions are not taken.
    pinned = fits[f"{rendering}/nominal"].noise_ratio <= MAX_NOISE_RATIO
    v, e = f.values, f.sem
    inertia = rig.inertia_kgm2
    source["inertia"] = "rig"
    dI = v["inertia_kgm2"] - rig.inertia_kgm2
    if abs(dI) > 3 * e["inertia_kgm2"] and abs(dI) > INERTIA_TAKE_REL * rig.inertia_kgm2:
        if pinned:
            inertia = v["inertia_kgm2"]
            source["inertia"] = "data"
        else:
            notes.append(
                f"the data's wheel inertia ({v['inertia_kgm2']:.4g} kg·m²) is not taken: the "
                f"wheel's equation leaves {f.noise_ratio:.2g}× the noise power (clipping, dry "
                "friction or a lag), so the data do not pin the wheel down"
            )
    sensor_skew = 0.0
    # Each channel as stated, else from the data (the torque: the angle's plus the data's skew).
    if "theta_offset_samples" in stated:
        th_off = float(stated["theta_offset_samples"])
    else:
        th_off = _timing(v["theta_offset_samples"], e["theta_offset_samples"], pinned, snap=True)
        if th_off < 0:
            notes.append(
                f"the angle responds {-th_off:.2g} sample(s) later than a rig reading at the "
                "command would see it: no reading convention does that, so it is left to the "
                "mechanisms (an actuator lag or delay)"
            )
            th_off = 0.0
    if "torque_offset_samples" in stated:
        td_off = float(stated["torque_offset_samples"])
    else:
        skew = v["torque_offset_samples"] - v["theta_offset_samples"]
        skew_e = math.hypot(e["torque_offset_samples"], e["theta_offset_samples"])
        if abs(skew) <= MAX_CONVENTION_SKEW:
            td_off = th_off + _timing(skew, skew_e, pinned)
        else:
            td_off = th_off
            sensor_skew = _timing(skew, skew_e, pinned)
    said = [k for k in ("theta_offset_samples", "torque_offset_samples") if k in stated]
    source["timing"] = "stated" if len(said) == 2 else ("stated in part" if said else "data")
    conv = Convention(
        rendering, float(inertia), float(th_off), float(td_off), source, tuple(notes), sensor_skew
    )
    fs = float(np.median([t.fs_hz for t in trials]))
    return RigFromData(rig, rig_label, fits, conv, len(trials), told, fs)


def retime(rec: TrialRecord, theta_offset: float, torque_offset: float) -> TrialRecord:
    """``rec`` with the angle and driver torque moved to the instant of the command (Steerlab's
    reading: offsets 0). A whole-sample offset moves the samples; a fraction is interpolated by
    a windowed sinc (exact in phase well below Nyquist; the first and last samples of the record
    repeat its ends)."""
    if theta_offset == 0.0 and torque_offset == 0.0:
        return rec
    return replace(
        rec,
        wheel_angle_rad=_delay(np.asarray(rec.wheel_angle_rad, float), theta_offset),
        driver_torque_Nm=_delay(np.asarray(rec.driver_torque_Nm, float), torque_offset),
    )


SINC_HALF_TAPS = 16


def _delay(x: np.ndarray, d: float) -> np.ndarray:
    """y[i] = x(i − d), d in samples (a non-finite sample spreads over the sinc's 32 taps)."""
    if d == 0.0 or len(x) == 0:
        return x.copy()
    n = int(math.floor(d))
    if abs(n) + 1 >= len(x):  # nothing of the record is left at the command's instants
        return np.full(len(x), np.nan)
    frac = d - n
    y = x
    if frac != 0.0:
        m = SINC_HALF_TAPS
        k = np.arange(-m + 1, m + 1)  # taps at x[i − k]
        w = np.sinc(k - frac) * np.kaiser(2 * m, 6.0)
        w /= w.sum()
        pad = np.concatenate([np.full(m, x[0]), x, np.full(m, x[-1])])
        y = np.zeros(len(x))
        for kk, ww in zip(k, w, strict=True):
            y += ww * pad[m - kk : m - kk + len(x)]
    if n > 0:
        y = np.concatenate([np.full(n, y[0]), y[:-n]])
    elif n < 0:
        y = np.concatenate([y[-n:], np.full(-n, y[-1])])
    return y


def stated_convention(records: Sequence[TrialRecord]) -> dict[str, Any]:
    """What the recordings say of their timing and rendering (trial attributes
    ``sample_timing``, ``torque_timing``, ``wheel_rendering``), where every trial that says
    anything says the same; ``ValueError`` naming two trials that disagree."""
    out: dict[str, Any] = {}
    first: dict[str, str] = {}
    for r in records:
        a = r.attrs or {}
        where = r.source or r.label()
        said: dict[str, Any] = {}
        if "sample_timing" in a:
            said["theta_offset_samples"] = stated_timing(a["sample_timing"], where)
            said["torque_offset_samples"] = said["theta_offset_samples"]
        if "torque_timing" in a:
            said["torque_offset_samples"] = stated_timing(
                a["torque_timing"], where, "torque_timing"
            )
        if "wheel_rendering" in a:
            said["rendering"] = check_rendering(a["wheel_rendering"], where)
        for k, v in said.items():
            if k in out and out[k] != v:
                raise ValueError(
                    f"{where} and {first[k]} state different {k.replace('_', ' ')} "
                    f"({v!r} and {out[k]!r}): one study is recorded one way"
                )
            out.setdefault(k, v)
            first.setdefault(k, where)
    return out


#: Trials the report identifies the timing from: enough for SEMs of a few thousandths of a
#: sample, spread over subjects and conditions, and a few seconds on a large study.
REPORT_TRIALS = 12


def align_to_command(
    records: Sequence[TrialRecord], max_trials: int | None = REPORT_TRIALS
) -> tuple[list[TrialRecord], dict[str, Any]]:
    """The records with the angle and the driver torque moved to the command's instant, as the
    recording states or its data show (the convention's timing; its rendering and inertia are
    the diagnosis's concern), and what was done (``results.json``'s ``recording_timing``).

    ``max_trials``: identify from at most this many measured trials, taken evenly across the
    study (None: all). Records are returned unchanged where nothing can be identified."""
    records = list(records)
    try:
        stated = stated_convention(records)
    except ValueError as e:  # two trials that state different conventions: bad input
        raise DataFileError(str(e)) from None
    try:
        found = identify(records, stated=stated, max_trials=max_trials)
    except RigFromDataError as err:
        return records, {"applied": False, "reason": str(err)}
    c = found.convention
    th, td = c.theta_offset_samples, c.torque_offset_samples
    notes = list(c.notes)
    if c.sensor_skew_samples != 0.0:
        # The admittance is the arm's whatever delays the torque channel: a skew beyond what a
        # convention makes (a sensor delay, which the diagnosis names) is undone here too.
        td = th + c.sensor_skew_samples
        notes.append(found.sensor_skew_sentence() + ": undone here")
    moved = [retime(r, th, td) for r in records]
    return moved, {
        "applied": not (th == 0.0 and td == 0.0),
        "theta_offset_samples": th,
        "torque_offset_samples": td,
        "source": c.source.get("timing", "data"),
        "n_trials_identified": found.n_trials,
        "sentence": found.sentence(),
        "notes": notes,
    }
