"""Another lab's world: a closed-loop steering-wheel + arm simulator that shares no code with
Steerlab (only numpy and scipy; nothing from ``hardware``, ``protocols`` or ``analysis``).

It exists so that Steerlab's analysis (issue 13) and diagnosis (issue 18) can be tried on data
that Steerlab did not generate. Its output is the trial interchange format (``NAME.csv`` +
``NAME.json`` per trial, read by ``steerlab import``) plus a ``truth.json``.

Physics (SI: rad, N·m, s)
    wheel  I_w θ'' = T_a − T_d − T_f(θ')         (T_f: wheel friction, zero unless a mechanism)
    contact  T_d = k_c (θ − θ_h) + b_c (θ' − θ_h')  — the torque the wheel exerts on the hands,
             recorded as ``driver_torque_Nm`` (so S(Tp,θ)/S(Tp,Td) > 0 at low frequency)
    arm    I_i θ_h'' + b_i θ_h' + S(θ_h) + R = T_d + n(t)
             (S(θ) = k_i θ unless stiffening; R: reflex torque, zero unless a mechanism)
    so that without remnant θ/T_d = 1/(b_c s + k_c) + 1/(I_i s² + b_i s + k_i).

The rig renders the virtual wheel (Table 1: 0.3 kg·m², 2 N·m·s/rad, 4.2 N·m/rad) in discrete
time, as a real rig does: at each sample instant t_k it reads the angle (and the velocity: the
drive's estimate, i.e. the true velocity, or a backward difference of the read angles), computes
    u_k = T_p(t_k) − b_sw ω̂_k − k_sw θ̂_k
and holds it (zero-order hold) until t_{k+1}. Without actuator lag T_a = u_k. The wheel's
*physical* inertia ``wheel_inertia`` (default 0.3) is what the rig has; no inertia is rendered.
The recorded angle and torque are the values read at t_k (plus sensor noise), the recorded
perturbation is T_p(t_k) (with its fade-in). By default the rig's loop runs at the record rate;
``control_per_sample`` = m makes it run m times faster, the recorder keeping every m-th cycle,
either the value at that cycle (``record_filter="none"``) or the mean of the angle reads and of
the torque over the m cycles ending there (``"mean"``: a boxcar recorder filter, delay
(m − 1)/2 cycles, on the sensor channels only; T_p is recorded as commanded).

Integration
    - ``"solve_ivp"``: the continuous model between sample instants, one
      ``scipy.integrate.solve_ivp`` (RK45, rtol 1e-7) call per sample interval with the held
      inputs; every mechanism runs here.
    - ``"expm"``: the exact discretisation (matrix exponential of the augmented [A B; 0 0]) of the
      linear model over one interval, for worlds without nonlinear or time-varying mechanisms
      (null, drift across trials, torque-sensor delay). Same model, about 30× faster.
    ``"auto"`` (default) takes ``expm`` where it applies. Tests check that the two agree.

Remnant n(t): unit white noise held over each interval, through a first-order (pole at the
corner) or second-order Butterworth low-pass at ``remnant_corner_hz``, scaled so that its standard
deviation is ``remnant_rel`` × the perturbation's. Injected at the arm (a torque).

Sensor noise: white, ``angle_noise_rad`` and ``torque_noise_Nm`` (standard deviations); optional
quantisation steps ``angle_lsb_rad``/``torque_lsb_Nm``.

Grip force: total grip (N) G(k) = 10 + 230 (1 − exp(−k/200)) of the trial's intrinsic stiffness
(monotone, saturating near 200 N for the stiffest task as in the paper), times (1 + a slow
fluctuation: white noise through a 0.2 Hz first-order low-pass, relative SD ``grip_rel_sd``),
plus white sensor noise ``grip_noise_N``.

Perturbation: this module's own multisine (:class:`Multisine`): 45 s period, 31 double bands,
band starts log-spaced with at least ``min_spacing`` bins from band to band, full power to 0.7 Hz,
power × ``reduced_power_ratio`` above, up to 20 Hz, SD 2.26 N·m, uniformly random phases. A trial
starts at any phase (``phase_offset_s`` in its JSON) with a raised-cosine fade-in over the first
second of the run-in, and lasts run-in + ``n_periods`` periods.

Mechanisms (each a dict ``{"kind": ..., "form": ..., **params}``, see :data:`MECHANISMS`):
    reflex        forms position | velocity | position_velocity: R is the output of a first-order
                  activation (time constant ``tau_act_s``) driven by k_p θ_h(t−τ) + k_v θ_h'(t−τ),
                  delay τ = ``delay_s`` (20–80 ms); delayed states by cubic Hermite interpolation
                  of the stored samples.
    friction      coulomb: F_c tanh(ω/ε); stribeck: (F_c + (F_s − F_c) e^{−(ω/v_s)²}) tanh(ω/ε);
                  viscous_coulomb: F_c tanh(ω/ε) + b_v ω.
    stiffening    the incremental intrinsic stiffness at |θ_h| = ``theta_ref_rad`` is
                  (1 + ``rise``) k_i. cubic: k_i θ + k_3 θ³; exponential: k_i θ_0 sinh(θ/θ_0);
                  piecewise: slope k_i inside ±θ_ref/2, k_i (1 + rise) outside.
    actuator_lag  first_order (``tau_s``), second_order (``f_hz``, ``zeta``), delay (``delay_s``,
                  the held command reaches the wheel that much later).
    sensor_delay  form delay: the recorded torque is T_d(t_k − ``delay_s``).
    grip_stiffness  k_i(t) = k_i M(g(t)/ḡ), g the true grip, M monotone with M(1) = 1: linear
                  1 + α(r − 1); power r^α; exp e^{α(r − 1)} (α = ``alpha``); the grip fluctuation
                  is raised to ``grip_rel_sd``. k_i is held per sample interval.
    drift         across trials: linear (k_i × (1 + ``rate`` (trial_index − 1))) or stepwise
                  (k_i × (1 + ``step``) from trial ``at_trial`` on); the other parameters stay.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.integrate import solve_ivp
from scipy.linalg import expm, solve_discrete_lyapunov
from scipy.signal import lfilter

CONDITIONS = ("RT", "BT18", "BT12", "BT8", "BT5", "PT")
BOUNDARY_DEG = {"RT": math.inf, "BT18": 18.0, "BT12": 12.0, "BT8": 8.0, "BT5": 5.0, "PT": 0.0}
# Median arm parameters per condition (our own choice, following the paper's trends: stiffer and
# a stiffer, more damped contact for narrower boundaries; b_i without a clear trend).
DEFAULT_ARM = {
    "RT": {"k_i": 30.0, "b_i": 1.6, "k_c": 120.0, "b_c": 2.0},
    "BT18": {"k_i": 45.0, "b_i": 1.8, "k_c": 150.0, "b_c": 2.4},
    "BT12": {"k_i": 70.0, "b_i": 2.0, "k_c": 190.0, "b_c": 2.8},
    "BT8": {"k_i": 110.0, "b_i": 2.1, "k_c": 240.0, "b_c": 3.3},
    "BT5": {"k_i": 170.0, "b_i": 2.3, "k_c": 300.0, "b_c": 3.9},
    "PT": {"k_i": 300.0, "b_i": 2.6, "k_c": 400.0, "b_c": 4.8},
}
ARM_KEYS = ("I_i", "b_i", "k_i", "b_c", "k_c")
WHEEL = {"I_sw": 0.3, "b_sw": 2.0, "k_sw": 4.2}  # Table 1, the rendered virtual wheel

MECHANISMS = {
    "reflex": {
        "position": {"delay_s": 0.035, "tau_act_s": 0.03, "k_p": 60.0, "k_v": 0.0},
        "velocity": {"delay_s": 0.035, "tau_act_s": 0.03, "k_p": 0.0, "k_v": 3.0},
        "position_velocity": {"delay_s": 0.035, "tau_act_s": 0.03, "k_p": 60.0, "k_v": 3.0},
    },
    "friction": {
        "coulomb": {"F_c": 0.15, "eps": 0.005},
        "stribeck": {"F_c": 0.12, "F_s": 0.25, "v_s": 0.05, "eps": 0.005},
        "viscous_coulomb": {"F_c": 0.12, "b_v": 0.3, "eps": 0.005},
    },
    "stiffening": {
        "cubic": {"theta_ref_rad": 0.02, "rise": 1.0},
        "exponential": {"theta_ref_rad": 0.02, "rise": 1.0},
        "piecewise": {"theta_ref_rad": 0.02, "rise": 1.0},
    },
    "actuator_lag": {
        "first_order": {"tau_s": 0.012},
        "second_order": {"f_hz": 15.0, "zeta": 0.7},
        "delay": {"delay_s": 0.012},
    },
    "sensor_delay": {"delay": {"delay_s": 0.012}},
    "grip_stiffness": {
        "linear": {"alpha": 1.5, "grip_rel_sd": 0.2},
        "power": {"alpha": 1.5, "grip_rel_sd": 0.2},
        "exp": {"alpha": 1.5, "grip_rel_sd": 0.2},
    },
    "drift": {
        "linear": {"rate": 0.04},
        "stepwise": {"step": 0.3, "at_trial": 4},
    },
}
LINEAR_KINDS = {"drift", "sensor_delay"}  # worlds with only these run on the exact expm path


class OtherworldError(ValueError):
    """A bad world option; the message names it."""


def mechanism(kind: str, form: str, **params) -> dict:
    """A validated mechanism dict with the form's defaults filled in."""
    if kind not in MECHANISMS:
        raise OtherworldError(f"mechanism kind {kind!r}: one of {sorted(MECHANISMS)}")
    forms = MECHANISMS[kind]
    if form not in forms:
        raise OtherworldError(f"mechanism {kind}: form {form!r}: one of {sorted(forms)}")
    unknown = set(params) - set(forms[form])
    if unknown:
        raise OtherworldError(
            f"mechanism {kind}:{form}: unknown parameter(s) {sorted(unknown)}; "
            f"known: {sorted(forms[form])}"
        )
    m: dict[str, Any] = {"kind": kind, "form": form, **forms[form]}
    m.update({k: float(v) for k, v in params.items()})
    if kind == "reflex" and not 0.0 < m["delay_s"]:
        raise OtherworldError(f"mechanism reflex: delay_s must be > 0, got {m['delay_s']}")
    return m


def parse_mechanism(text: str) -> dict:
    """``kind:form[:key=value,key=value]`` (the CLI's ``--mechanism``)."""
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise OtherworldError(f"--mechanism {text!r}: expected kind:form[:key=value,...]")
    params = {}
    if len(parts) == 3 and parts[2]:
        for item in parts[2].split(","):
            k, sep, v = item.partition("=")
            try:
                params[k.strip()] = float(v)
            except ValueError:
                raise OtherworldError(f"--mechanism {text!r}: {item!r} is not key=number") from None
            if not sep:
                raise OtherworldError(f"--mechanism {text!r}: {item!r} is not key=number")
    return mechanism(parts[0], parts[1], **params)


# -- perturbation ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Multisine:
    """A sum of sines on the grid k / period_s; value(t) = Σ a_k sin(2π k t / T + φ_k)."""

    period_s: float
    bins: np.ndarray
    amplitudes: np.ndarray
    phases: np.ndarray

    @classmethod
    def design(
        cls,
        seed: int,
        *,
        period_s: float = 45.0,
        n_bands: int = 31,
        first_bin: int = 3,
        f_max_hz: float = 20.0,
        full_power_hz: float = 0.7,
        reduced_power_ratio: float = 0.1,
        sd_Nm: float = 2.26,
        min_spacing: int = 4,
    ) -> Multisine:
        top = int(round(f_max_hz * period_s)) - 1  # first bin of the last band
        starts = [first_bin]
        for j in range(1, n_bands):
            left = n_bands - j
            ratio = (top / starts[-1]) ** (1.0 / left)
            starts.append(max(starts[-1] + min_spacing, int(round(starts[-1] * ratio))))
        if starts[-1] + 1 > round(f_max_hz * period_s):
            raise OtherworldError(
                f"perturbation: {n_bands} bands spaced ≥ {min_spacing} bins from bin "
                f"{first_bin} do not fit below {f_max_hz} Hz"
            )
        bins = np.array([b + i for b in starts for i in (0, 1)], dtype=int)
        f = bins / period_s
        amp = np.where(f <= full_power_hz + 1e-12, 1.0, math.sqrt(reduced_power_ratio))
        amp = amp * sd_Nm / math.sqrt(np.sum(amp**2) / 2.0)
        phases = np.random.default_rng(seed).uniform(0.0, 2 * np.pi, len(bins))
        return cls(float(period_s), bins, amp, phases)

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self.bins / self.period_s

    def value(self, t: np.ndarray) -> np.ndarray:
        tm = np.mod(np.asarray(t, dtype=float), self.period_s)
        w = 2 * np.pi * self.frequencies_hz
        return np.sin(np.outer(tm, w) + self.phases) @ self.amplitudes

    def to_dict(self) -> dict:
        return {
            "period_s": self.period_s,
            "bins": self.bins.tolist(),
            "frequencies_hz": self.frequencies_hz.tolist(),
            "amplitudes_Nm": self.amplitudes.tolist(),
            "phases_rad": self.phases.tolist(),
        }


# -- one trial -------------------------------------------------------------------------------------
@dataclass
class World:
    """Everything one trial needs besides the perturbation and the random stream."""

    arm: dict  # I_i, b_i, k_i, b_c, k_c
    fs_hz: float = 250.0
    wheel_inertia: float = WHEEL["I_sw"]  # the rig's physical inertia
    render_b: float = WHEEL["b_sw"]
    render_k: float = WHEEL["k_sw"]
    velocity_source: str = "state"  # "state" (drive's estimate) | "difference"
    remnant_rel: float = 0.25
    remnant_corner_hz: float = 0.6
    remnant_order: int = 1
    angle_noise_rad: float = 2e-5
    torque_noise_Nm: float = 0.02
    angle_lsb_rad: float = 0.0
    torque_lsb_Nm: float = 0.0
    grip_rel_sd: float = 0.05
    grip_noise_N: float = 1.0
    mechanisms: list = field(default_factory=list)
    integrator: str = "auto"
    control_per_sample: int = 1  # the rig renders this many times per recorded sample
    record_filter: str = "none"  # "none" | "mean": the recorder's filter on angle and torque
    # Recording conventions a lab's rig may have (CONVENTIONS):
    wheel_rendering: str = "sampled"  # "continuous": a physical spring and damper
    # "end": angle and torque read at the end of the command interval (one control cycle on,
    # which is one recorded sample only where the loop runs at the record's rate)
    sample_timing: str = "start"
    torque_skew_s: float = 0.0  # the torque channel samples this much earlier than the angle
    torque_lowpass_hz: float = 0.0  # first-order low-pass of the torque sensor (0: none)

    @property
    def control_hz(self) -> float:
        return self.fs_hz * self.control_per_sample

    def validate(self) -> None:
        for k in ARM_KEYS:
            v = self.arm.get(k)
            if v is None or not v > 0 or not math.isfinite(v):
                raise OtherworldError(f"world arm parameter {k}: must be a number > 0, got {v!r}")
        if not 100.0 <= self.fs_hz <= 5000.0:
            raise OtherworldError(f"world fs_hz: 100–5000 Hz, got {self.fs_hz}")
        if not (isinstance(self.control_per_sample, int) and 1 <= self.control_per_sample <= 20):
            raise OtherworldError(
                f"world control_per_sample: a whole number 1–20, got {self.control_per_sample!r}"
            )
        if self.record_filter not in ("none", "mean"):
            raise OtherworldError(
                f"world record_filter: 'none' or 'mean', got {self.record_filter!r}"
            )
        if self.wheel_rendering not in ("sampled", "continuous"):
            raise OtherworldError(
                f"world wheel_rendering: 'sampled' or 'continuous', got {self.wheel_rendering!r}"
            )
        if self.sample_timing not in ("start", "end"):
            raise OtherworldError(
                f"world sample_timing: 'start' or 'end', got {self.sample_timing!r}"
            )
        if not (0.0 <= self.torque_skew_s < 0.05 and 0.0 <= self.torque_lowpass_hz < 1e4):
            raise OtherworldError(
                "world torque_skew_s (0–0.05 s) and torque_lowpass_hz (≥ 0) out of range: "
                f"{self.torque_skew_s!r}, {self.torque_lowpass_hz!r}"
            )
        if self.velocity_source not in ("state", "difference"):
            raise OtherworldError(
                f"world velocity_source: 'state' or 'difference', got {self.velocity_source!r}"
            )
        if self.remnant_order not in (1, 2):
            raise OtherworldError(f"world remnant_order: 1 or 2, got {self.remnant_order}")
        if self.integrator not in ("auto", "expm", "solve_ivp"):
            raise OtherworldError(f"world integrator: auto|expm|solve_ivp, got {self.integrator!r}")
        kinds = [m["kind"] for m in self.mechanisms]
        if len(set(kinds)) != len(kinds):
            raise OtherworldError(f"world mechanisms: at most one of each kind, got {kinds}")
        for m in self.mechanisms:
            mechanism(
                m["kind"], m["form"], **{k: v for k, v in m.items() if k not in ("kind", "form")}
            )
            if m["kind"] == "reflex" and m["delay_s"] < 1.0 / self.control_hz:
                raise OtherworldError(
                    f"mechanism reflex: delay_s {m['delay_s']} s is shorter than a control "
                    f"cycle ({1 / self.control_hz:g} s)"
                )
        if self.integrator == "expm" and not self.is_linear():
            raise OtherworldError(
                f"world integrator 'expm': only for worlds whose mechanisms are in "
                f"{sorted(LINEAR_KINDS)}; got {kinds}"
            )

    def mech(self, kind: str) -> dict | None:
        for m in self.mechanisms:
            if m["kind"] == kind:
                return m
        return None

    def is_linear(self) -> bool:
        return all(m["kind"] in LINEAR_KINDS for m in self.mechanisms)

    @property
    def physical_wheel(self) -> tuple[float, float]:
        """The wheel's physical damping and spring (b, k); zero where the rig renders them."""
        if self.wheel_rendering == "continuous":
            return self.render_b, self.render_k
        return 0.0, 0.0

    @property
    def rendered(self) -> tuple[float, float]:
        """The damping and spring the rig's loop renders (b, k)."""
        if self.wheel_rendering == "continuous":
            return 0.0, 0.0
        return self.render_b, self.render_k


def grip_of_stiffness(k_i: float) -> float:
    """Mean total grip force (N) for an intrinsic stiffness (N·m/rad): monotone, saturating."""
    return 10.0 + 230.0 * (1.0 - math.exp(-k_i / 200.0))


class _Layout:
    """State vector: θ, ω, θ_h, ω_h, remnant filter (1–2), reflex activation, actuator lag."""

    def __init__(self, world: World):
        i = 4
        self.rem = list(range(i, i + world.remnant_order))
        i += world.remnant_order
        self.reflex = None
        if world.mech("reflex"):
            self.reflex = i
            i += 1
        self.lag = []
        lag = world.mech("actuator_lag")
        if lag and lag["form"] == "first_order":
            self.lag = [i]
        elif lag and lag["form"] == "second_order":
            self.lag = [i, i + 1]
        i += len(self.lag)
        self.n = i


def _linear_matrices(world: World, lay: _Layout, g: float, wc: float):
    """Continuous A, B (inputs: held command u, held unit white noise w) of the linear world."""
    a = world.arm
    Iw = world.wheel_inertia
    A = np.zeros((lay.n, lay.n))
    B = np.zeros((lay.n, 2))
    A[0, 1] = 1.0
    A[2, 3] = 1.0
    # wheel: Iw ω' = u − k_c(θ − θh) − b_c(ω − ωh)
    b_w, k_w = world.physical_wheel
    A[1, :4] = np.array([-a["k_c"] - k_w, -a["b_c"] - b_w, a["k_c"], a["b_c"]]) / Iw
    B[1, 0] = 1.0 / Iw
    # arm: I ωh' = k_c(θ − θh) + b_c(ω − ωh) − b_i ωh − k_i θh + n
    A[3, :4] = np.array([a["k_c"], a["b_c"], -a["k_c"] - a["k_i"], -a["b_c"] - a["b_i"]]) / a["I_i"]
    A[3, lay.rem[0]] = 1.0 / a["I_i"]
    if len(lay.rem) == 1:
        A[lay.rem[0], lay.rem[0]] = -wc
        B[lay.rem[0], 1] = wc * g
    else:  # Butterworth: n'' = wc²(g w − n) − √2 wc n'
        r0, r1 = lay.rem
        A[r0, r1] = 1.0
        A[r1, r0] = -(wc**2)
        A[r1, r1] = -math.sqrt(2.0) * wc
        B[r1, 1] = wc**2 * g
    return A, B


def _discretise(A: np.ndarray, B: np.ndarray, h: float):
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n] = A
    M[:n, n:] = B
    E = expm(M * h)
    return E[:n, :n], E[:n, n:]


def _remnant_gain(world: World, sd: float) -> float:
    """Gain on unit held white noise that gives the remnant filter output SD ``sd``."""
    if sd == 0:
        return 0.0
    wc = 2 * np.pi * world.remnant_corner_hz
    o = world.remnant_order
    A = np.array([[-wc]]) if o == 1 else np.array([[0.0, 1.0], [-(wc**2), -math.sqrt(2) * wc]])
    B = np.array([[wc]]) if o == 1 else np.array([[0.0], [wc**2]])
    Ad, Bd = _discretise(A, B, 1.0 / world.control_hz)
    P = solve_discrete_lyapunov(Ad, Bd @ Bd.T)
    return sd / math.sqrt(P[0, 0])


def _hermite(t, t0, h, x0, x1, d0, d1):
    s = (t - t0) / h
    h00 = 2 * s**3 - 3 * s**2 + 1
    h10 = s**3 - 2 * s**2 + s
    h01 = -2 * s**3 + 3 * s**2
    h11 = s**3 - s**2
    return h00 * x0 + h10 * h * d0 + h01 * x1 + h11 * h * d1


class _History:
    """States and their derivatives at the ends of each finished interval: x(t) for any past t."""

    def __init__(self, n_samples: int, n_states: int, h: float):
        self.h = h
        self.x = np.zeros((n_samples, n_states))
        self.d0 = np.zeros((n_samples, n_states))  # derivative at the start of interval k
        self.d1 = np.zeros((n_samples, n_states))  # … at its end (same held inputs)

    def reflex_drive(self, t: float, k_p: float, k_v: float) -> float:
        """k_p θ_h(t) + k_v θ_h'(t) by cubic Hermite (θ_h, ω_h are states 2, 3), in floats."""
        if t <= 0.0:
            return 0.0
        k = int(t / self.h)
        s = (t - k * self.h) / self.h
        h = self.h
        s2, s3 = s * s, s * s * s
        h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
        x0, x1, d0, d1 = self.x[k], self.x[k + 1], self.d0[k], self.d1[k]
        th = h00 * x0[2] + h10 * h * d0[2] + h01 * x1[2] + h11 * h * d1[2]
        om = h00 * x0[3] + h10 * h * d0[3] + h01 * x1[3] + h11 * h * d1[3]
        return k_p * th + k_v * om

    def at(self, t: float, idx) -> np.ndarray:
        if t <= 0.0:
            return self.x[0, idx]
        k = int(t / self.h)
        t0 = k * self.h
        return _hermite(
            t, t0, self.h, self.x[k, idx], self.x[k + 1, idx], self.d0[k, idx], self.d1[k, idx]
        )


def _spring(m: dict | None, theta: float, k_i: float) -> float:
    if m is None:
        return k_i * theta
    ref, rise = m["theta_ref_rad"], m["rise"]
    if m["form"] == "cubic":
        return k_i * theta + rise * k_i / (3 * ref**2) * theta**3
    if m["form"] == "exponential":
        th0 = ref / math.acosh(1.0 + rise)
        return k_i * th0 * math.sinh(theta / th0)
    brk = ref / 2.0  # piecewise
    if abs(theta) <= brk:
        return k_i * theta
    return math.copysign(k_i * brk + k_i * (1.0 + rise) * (abs(theta) - brk), theta)


def _friction(m: dict | None, w: float) -> float:
    if m is None:
        return 0.0
    s = math.tanh(w / m["eps"])
    if m["form"] == "coulomb":
        return m["F_c"] * s
    if m["form"] == "stribeck":
        return (m["F_c"] + (m["F_s"] - m["F_c"]) * math.exp(-((w / m["v_s"]) ** 2))) * s
    return m["F_c"] * s + m["b_v"] * w


def simulate_trial(
    world: World,
    design: Multisine,
    *,
    n_periods: int = 2,
    run_in_s: float = 5.0,
    phase_offset_s: float = 0.0,
    seed: int = 0,
    fade_in_s: float = 1.0,
) -> dict:
    """One trial. Returns the recorded channels and what the world really did.

    Keys: ``time_s``, ``perturbation_torque_Nm``, ``driver_torque_Nm``, ``wheel_angle_rad``,
    ``grip_force_N`` (recorded, noisy), ``true`` (a dict of the noise-free signals at the sample
    instants: theta, omega, theta_h, omega_h, Td, remnant, u (held command), applied (torque
    reaching the wheel at the start of each interval), k_i (per interval), grip) and ``integrator``.
    """
    world.validate()
    mc = world.control_per_sample
    fs = world.control_hz  # everything below runs at the control rate; recorded at the end
    h = 1.0 / fs
    n_rec = int(round((run_in_s + n_periods * design.period_s) * world.fs_hz))
    # A recorder that reads at the end of the interval needs the instant after the last one.
    late = 1 if world.sample_timing == "end" else 0
    n = n_rec * mc + late
    rng = np.random.default_rng(seed)
    t = np.arange(n) * h
    tp = design.value(t + phase_offset_s)
    fade = np.ones(n)
    nf = int(round(fade_in_s * fs))
    if nf > 0:
        fade[:nf] = 0.5 - 0.5 * np.cos(np.pi * np.arange(nf) / nf)
    tp = tp * fade
    sd_tp = float(np.sqrt(np.sum(design.amplitudes**2) / 2.0))
    lay = _Layout(world)
    g = _remnant_gain(world, world.remnant_rel * sd_tp)
    wc = 2 * np.pi * world.remnant_corner_hz
    white = rng.standard_normal(n)
    a = world.arm

    # grip: the true (noise-free) grip of this trial and the stiffness it schedules
    grip_m = world.mech("grip_stiffness")
    rel_sd = grip_m["grip_rel_sd"] if grip_m else world.grip_rel_sd
    gc = 2 * np.pi * 0.2
    phi = math.exp(-gc * h)
    e = rng.standard_normal(n) * math.sqrt(1 - phi**2)
    e[0] = rng.standard_normal()  # start in the stationary distribution (unit variance)
    fl = lfilter([1.0], [1.0, -phi], e)  # AR(1): fl[k] = φ fl[k−1] + e[k]
    grip_mean = grip_of_stiffness(a["k_i"])
    grip_true = grip_mean * (1.0 + rel_sd * fl)
    if grip_m:
        r = np.maximum(grip_true / grip_mean, 0.05)
        al = grip_m["alpha"]
        M = {
            "linear": np.maximum(1.0 + al * (r - 1.0), 0.05),
            "power": r**al,
            "exp": np.exp(al * (r - 1.0)),
        }[grip_m["form"]]
        k_series = a["k_i"] * M
    else:
        k_series = np.full(n, a["k_i"])

    integ = world.integrator
    if integ == "auto":
        integ = "expm" if world.is_linear() else "solve_ivp"

    hist = _History(n, lay.n, h)
    u = np.zeros(n)
    applied = np.zeros(n)
    theta_read = np.zeros(n)
    omega_read = np.zeros(n)
    a_noise = world.angle_noise_rad * rng.standard_normal(n)
    lag = world.mech("actuator_lag")
    delay_steps, delay_frac = 0, 0.0
    if lag and lag["form"] == "delay":
        q = lag["delay_s"] / h
        delay_steps = int(math.floor(q + 1e-9))
        delay_frac = (q - delay_steps) * h  # switch time inside the interval

    rb, rk = world.rendered
    b_w, k_w = world.physical_wheel

    def read(k, x):
        th = x[0] + a_noise[k]
        if world.angle_lsb_rad > 0:
            th = np.round(th / world.angle_lsb_rad) * world.angle_lsb_rad
        theta_read[k] = th
        if world.velocity_source == "state":
            omega_read[k] = x[1]
        else:
            omega_read[k] = (th - theta_read[k - 1]) * fs if k > 0 else 0.0
        u[k] = tp[k] - rb * omega_read[k] - rk * th

    def held(j):
        return u[j] if j >= 0 else 0.0

    if integ == "expm":
        A, B = _linear_matrices(world, lay, g, wc)
        Phi, Gam = _discretise(A, B, h)
        x = np.zeros(lay.n)
        for k in range(n - 1):
            hist.x[k] = x
            read(k, x)
            inp = np.array([u[k], white[k]])
            applied[k] = u[k]
            hist.d0[k] = A @ x + B @ inp
            x = Phi @ x + Gam @ inp
            hist.d1[k] = A @ x + B @ inp
        hist.x[n - 1] = x
        read(n - 1, x)
        applied[n - 1] = u[n - 1]
    else:
        refl = world.mech("reflex")
        fric = world.mech("friction")
        stiff = world.mech("stiffening")
        I_i, Iw = a["I_i"], world.wheel_inertia
        lagi = lay.lag
        if lag and lag["form"] == "second_order":
            wn2 = (2 * np.pi * lag["f_hz"]) ** 2
            z2wn = 2 * lag["zeta"] * 2 * np.pi * lag["f_hz"]

        def rhs(tt, x, uk, wk, kk):
            th, om, thh, omh = x[0], x[1], x[2], x[3]
            td = a["k_c"] * (th - thh) + a["b_c"] * (om - omh)
            d = np.zeros_like(x)
            d[0] = om
            d[2] = omh
            if lagi:
                ta = x[lagi[0]]
            else:
                ta = uk
            d[1] = (ta - td - _friction(fric, om) - b_w * om - k_w * th) / Iw
            rem = x[lay.rem[0]]
            refl_t = x[lay.reflex] if lay.reflex is not None else 0.0
            d[3] = (td + rem - a["b_i"] * omh - _spring(stiff, thh, kk) - refl_t) / I_i
            if len(lay.rem) == 1:
                d[lay.rem[0]] = wc * (g * wk - rem)
            else:
                d[lay.rem[0]] = x[lay.rem[1]]
                d[lay.rem[1]] = wc**2 * (g * wk - rem) - math.sqrt(2) * wc * x[lay.rem[1]]
            if lay.reflex is not None:
                drive = hist.reflex_drive(tt - refl["delay_s"], refl["k_p"], refl["k_v"])
                d[lay.reflex] = (drive - refl_t) / refl["tau_act_s"]
            if len(lagi) == 1:
                d[lagi[0]] = (uk - x[lagi[0]]) / lag["tau_s"]
            elif len(lagi) == 2:
                d[lagi[0]] = x[lagi[1]]
                d[lagi[1]] = wn2 * (uk - x[lagi[0]]) - z2wn * x[lagi[1]]
            return d

        x = np.zeros(lay.n)

        def step(t0, t1, x, uk, wk, kk):
            sol = solve_ivp(
                rhs,
                (t0, t1),
                x,
                args=(uk, wk, kk),
                rtol=1e-7,
                atol=1e-11,
                first_step=0.999 * (t1 - t0),
            )
            if sol.status != 0:
                raise RuntimeError(f"otherworld: solve_ivp failed at t={t0:.4f} s: {sol.message}")
            return sol.y[:, -1]

        for k in range(n - 1):
            hist.x[k] = x
            read(k, x)
            t0, t1 = k * h, (k + 1) * h
            kk = k_series[k]
            if lag and lag["form"] == "delay":
                u_before, u_after = held(k - delay_steps - 1), held(k - delay_steps)
                applied[k] = u_before if delay_frac > 0 else u_after
                hist.d0[k] = rhs(t0, x, applied[k], white[k], kk)
                if delay_frac > 1e-12:
                    x = step(t0, t0 + delay_frac, x, u_before, white[k], kk)
                x = step(t0 + delay_frac, t1, x, u_after, white[k], kk)
                hist.x[k + 1] = x
                hist.d1[k] = rhs(t1, x, u_after, white[k], kk)
            else:
                applied[k] = u[k] if not lagi else x[lagi[0]]
                hist.d0[k] = rhs(t0, x, u[k], white[k], kk)
                x = step(t0, t1, x, u[k], white[k], kk)
                hist.x[k + 1] = x  # needed by the reflex's delayed read of this interval
                hist.d1[k] = rhs(t1, x, u[k], white[k], kk)
        hist.x[n - 1] = x
        read(n - 1, x)
        applied[n - 1] = u[n - 1]

    X = hist.x
    td_true = a["k_c"] * (X[:, 0] - X[:, 2]) + a["b_c"] * (X[:, 1] - X[:, 3])
    sd = world.mech("sensor_delay")
    skew = (sd["delay_s"] if sd else 0.0) + world.torque_skew_s
    if skew > 0.0:
        ts = t - skew
        th_d = np.array([hist.at(tt, [0, 1, 2, 3]) for tt in ts])
        td_sensed = a["k_c"] * (th_d[:, 0] - th_d[:, 2]) + a["b_c"] * (th_d[:, 1] - th_d[:, 3])
    else:
        td_sensed = td_true
    if world.torque_lowpass_hz > 0.0:
        pole = math.exp(-2 * math.pi * world.torque_lowpass_hz * h)
        td_sensed = lfilter([1.0 - pole], [1.0, -pole], td_sensed, zi=[pole * td_sensed[0]])[0]

    # The recorder: one sample per `mc` control cycles, at a control instant. "mean" averages the
    # angle reads and the torque over the mc cycles ending there; T_p is the command's value.
    rec_idx = np.arange(n_rec) * mc
    read_idx = rec_idx + late  # "end": the sensors' values one control cycle later

    def record(x):
        if world.record_filter == "none" or mc == 1:
            return x[read_idx]
        c = np.concatenate(([0.0], np.cumsum(x)))
        lo = np.maximum(read_idx - mc + 1, 0)
        return (c[read_idx + 1] - c[lo]) / (read_idx + 1 - lo)

    td_meas = record(td_sensed) + world.torque_noise_Nm * rng.standard_normal(n_rec)
    if world.torque_lsb_Nm > 0:
        td_meas = np.round(td_meas / world.torque_lsb_Nm) * world.torque_lsb_Nm
    grip_meas = grip_true[rec_idx] + world.grip_noise_N * rng.standard_normal(n_rec)
    return {
        "time_s": np.arange(n_rec) / world.fs_hz,
        "perturbation_torque_Nm": tp[rec_idx],
        "driver_torque_Nm": td_meas,
        "wheel_angle_rad": record(theta_read),
        "grip_force_N": grip_meas,
        "integrator": integ,
        "true": {  # at the record instants
            "theta": X[rec_idx, 0],
            "omega": X[rec_idx, 1],
            "theta_h": X[rec_idx, 2],
            "omega_h": X[rec_idx, 3],
            "Td": td_true[rec_idx],
            "remnant": X[rec_idx, lay.rem[0]],
            "reflex": X[rec_idx, lay.reflex] if lay.reflex is not None else np.zeros(n_rec),
            "u": u[rec_idx],
            "applied": applied[rec_idx],
            "k_i": k_series[rec_idx],
            "grip": grip_true[rec_idx],
        },
    }


# -- a study ---------------------------------------------------------------------------------------
@dataclass
class StudyOptions:
    """World options common to every trial of a study (see :class:`World`)."""

    fs_hz: float = 250.0
    arm_inertia: float = 0.07
    inertia_rel_sd: float = 0.0  # subject-to-subject spread of I_i (lognormal)
    between_rel_sd: float = 0.2  # subject factor on b_i, k_i, b_c, k_c (lognormal)
    within_rel_sd: float = 0.08  # subject × condition jitter
    remnant_rel: float = 0.25
    remnant_corner_hz: float = 0.6
    remnant_order: int = 1
    angle_noise_rad: float = 2e-5
    torque_noise_Nm: float = 0.02
    angle_lsb_rad: float = 0.0
    torque_lsb_Nm: float = 0.0
    velocity_source: str = "state"
    wheel_inertia: float = WHEEL["I_sw"]
    n_periods: int = 2
    run_in_s: tuple = (3.0, 8.0)  # uniform range
    random_phase: bool = True
    mechanisms: list = field(default_factory=list)
    integrator: str = "auto"
    control_per_sample: int = 1
    record_filter: str = "none"
    wheel_rendering: str = "sampled"
    sample_timing: str = "start"
    torque_skew_s: float = 0.0
    torque_lowpass_hz: float = 0.0
    state_convention: bool = False  # write sample_timing and wheel_rendering into each JSON
    perturbation_seed: int | None = None  # default: from the study seed
    period_s: float = 45.0  # the perturbation's period (shorter only for fast tests)


# Worlds a real lab varies and Steerlab cannot know (issue 13's robustness list), as StudyOptions.
WORLDS: dict[str, dict[str, Any]] = {
    "null": {},
    "inertia_0.05": {"arm_inertia": 0.05},
    "inertia_0.15": {"arm_inertia": 0.15},
    "inertia_spread": {"inertia_rel_sd": 0.25},
    "remnant_x0.5_1Hz": {"remnant_rel": 0.125, "remnant_corner_hz": 1.0},
    "remnant_x3_0.05Hz": {"remnant_rel": 0.75, "remnant_corner_hz": 0.05},
    "paper_coherence": {"remnant_rel": 2.0, "remnant_corner_hz": 0.05, "remnant_order": 2},
    "noisy_sensors": {
        "angle_noise_rad": 1e-4,
        "torque_noise_Nm": 0.1,
        "angle_lsb_rad": 2 * math.pi / 2**14,
    },
    "fs_100": {"fs_hz": 100.0},
    "fs_2000": {"fs_hz": 2000.0},
    "rig_1k_recorder_250_mean": {"control_per_sample": 4, "record_filter": "mean"},
    "velocity_difference": {"velocity_source": "difference"},
    "heavy_rig": {"wheel_inertia": 0.36},
}
# Recording conventions of other labs' rigs (issue 36), as StudyOptions: none of them is a
# mechanism, so a study with nothing hidden must be diagnosed `none` under each.
CONVENTIONS: dict[str, dict[str, Any]] = {
    "steerlab": {},
    "end_of_interval": {"sample_timing": "end"},
    "physical_wheel": {"wheel_rendering": "continuous"},
    "physical_wheel_end": {"wheel_rendering": "continuous", "sample_timing": "end"},
    "1k_averaged_250": {"control_per_sample": 4, "record_filter": "mean"},
    "torque_skew_half": {"torque_skew_s": 0.002},
    "torque_lowpass_100hz": {"torque_lowpass_hz": 100.0},
}
# One moderate hidden mechanism per family (issue 18's table), for diagnosis studies.
HIDDEN = {
    "reflex": mechanism("reflex", "position_velocity", delay_s=0.035),
    "friction": mechanism("friction", "coulomb"),
    "stiffening": mechanism("stiffening", "cubic"),
    "actuator_lag": mechanism("actuator_lag", "first_order", tau_s=0.012),
    "sensor_delay": mechanism("sensor_delay", "delay", delay_s=0.012),
    "grip_stiffness": mechanism("grip_stiffness", "power"),
    "drift": mechanism("drift", "linear", rate=0.04),
}


def _subject_arms(rng, conditions, opts: StudyOptions) -> tuple[float, dict]:
    I_i = opts.arm_inertia * math.exp(opts.inertia_rel_sd * rng.standard_normal())
    factor = {k: math.exp(opts.between_rel_sd * rng.standard_normal()) for k in DEFAULT_ARM["RT"]}
    arms = {}
    for c in conditions:
        base = DEFAULT_ARM[c]
        arms[c] = {"I_i": I_i} | {
            k: base[k] * factor[k] * math.exp(opts.within_rel_sd * rng.standard_normal())
            for k in base
        }
    return I_i, arms


def _drifted(arm: dict, m: dict | None, trial_index: int) -> dict:
    if m is None:
        return dict(arm)
    if m["form"] == "linear":
        f = 1.0 + m["rate"] * (trial_index - 1)
    else:
        f = 1.0 + (m["step"] if trial_index >= m["at_trial"] else 0.0)
    return arm | {"k_i": arm["k_i"] * f}


def _fmt(x: np.ndarray, digits: int) -> list[str]:
    return [f"%.{digits}g" % v for v in x]


def write_trial(out: Path, name: str, rec: dict, meta: dict) -> None:
    cols = (
        "time_s",
        "perturbation_torque_Nm",
        "driver_torque_Nm",
        "wheel_angle_rad",
        "grip_force_N",
    )
    digits = {"time_s": 12}
    text = [_fmt(rec[c], digits.get(c, 9)) for c in cols]
    with open(out / f"{name}.csv", "w", newline="") as fh:
        fh.write(",".join(cols) + "\n")
        fh.writelines(",".join(row) + "\n" for row in zip(*text, strict=True))
    (out / f"{name}.json").write_text(json.dumps(meta, indent=1))


def generate_study(
    out_dir: str | Path,
    *,
    subjects: int = 2,
    conditions: tuple[str, ...] | list[str] = ("BT18", "BT8", "PT"),
    seed: int = 0,
    overwrite: bool = False,
    **world_options,
) -> dict:
    """Write one study in the interchange format plus ``truth.json``; returns the truth.

    ``world_options`` are the fields of :class:`StudyOptions`. Each subject does every condition
    twice (repetitions 1 and 2, one after the other) in a random order of conditions;
    ``trial_index`` counts that subject's trials from 1.
    """
    unknown = set(world_options) - set(StudyOptions.__dataclass_fields__)
    if unknown:
        raise OtherworldError(
            f"generate_study: unknown option(s) {sorted(unknown)}; "
            f"known: {sorted(StudyOptions.__dataclass_fields__)}"
        )
    opts = StudyOptions(**world_options)
    bad = [c for c in conditions if c not in DEFAULT_ARM]
    if bad:
        raise OtherworldError(f"generate_study: unknown condition(s) {bad}; known: {CONDITIONS}")
    if subjects < 1:
        raise OtherworldError(f"generate_study: subjects must be ≥ 1, got {subjects}")
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise OtherworldError(f"{out}: not empty; pass overwrite=True (--overwrite)")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    ss = np.random.SeedSequence(seed)
    pert_seed = opts.perturbation_seed
    if pert_seed is None:
        pert_seed = int(ss.generate_state(1)[0])
    design = Multisine.design(pert_seed, period_s=opts.period_s)
    drift = next((m for m in opts.mechanisms if m["kind"] == "drift"), None)
    truth: dict[str, Any] = {
        "world": "steerlab.benchmarks.otherworld",
        "seed": seed,
        "options": asdict(opts),
        "wheel_rendered": WHEEL,
        "perturbation": design.to_dict(),
        "mechanisms": opts.mechanisms,
        "subjects": {},
        "trials": {},
    }
    t_start = time.perf_counter()
    n_trials = 0
    for si, child in enumerate(ss.spawn(subjects)):
        subj = f"S{si + 1:02d}"
        rng = np.random.default_rng(child)
        I_i, arms = _subject_arms(rng, conditions, opts)
        order = list(rng.permutation(list(conditions)))
        truth["subjects"][subj] = {
            "I_i": I_i,
            "condition_order": order,
            "conditions": {
                c: arms[c] | {"grip_mean_N": grip_of_stiffness(arms[c]["k_i"])} for c in conditions
            },
        }
        ti = 0
        for c in order:
            for rep in (1, 2):
                ti += 1
                arm = _drifted(arms[c], drift, ti)
                world = World(
                    arm=arm,
                    fs_hz=opts.fs_hz,
                    wheel_inertia=opts.wheel_inertia,
                    velocity_source=opts.velocity_source,
                    remnant_rel=opts.remnant_rel,
                    remnant_corner_hz=opts.remnant_corner_hz,
                    remnant_order=opts.remnant_order,
                    angle_noise_rad=opts.angle_noise_rad,
                    torque_noise_Nm=opts.torque_noise_Nm,
                    angle_lsb_rad=opts.angle_lsb_rad,
                    torque_lsb_Nm=opts.torque_lsb_Nm,
                    mechanisms=[dict(m) for m in opts.mechanisms],
                    integrator=opts.integrator,
                    control_per_sample=opts.control_per_sample,
                    record_filter=opts.record_filter,
                    wheel_rendering=opts.wheel_rendering,
                    sample_timing=opts.sample_timing,
                    torque_skew_s=opts.torque_skew_s,
                    torque_lowpass_hz=opts.torque_lowpass_hz,
                )
                lo, hi = opts.run_in_s
                run_in = float(rng.uniform(lo, hi))
                # whole samples, so the record is an exact number of samples
                run_in = round(run_in * opts.fs_hz) / opts.fs_hz
                offset = float(rng.uniform(0, design.period_s)) if opts.random_phase else 0.0
                tseed = int(rng.integers(2**63))
                rec = simulate_trial(
                    world,
                    design,
                    n_periods=opts.n_periods,
                    run_in_s=run_in,
                    phase_offset_s=offset,
                    seed=tseed,
                )
                name = f"{subj}_T{ti:02d}_{c}_rep{rep}"
                bd = BOUNDARY_DEG[c]
                meta = {
                    "subject": subj,
                    "condition": c,
                    "repetition": rep,
                    "fs_hz": opts.fs_hz,
                    "familiarization": False,
                    "trial_index": ti,
                    "boundary_deg": "inf" if math.isinf(bd) else bd,
                    "lab": "otherworld",
                }
                if opts.state_convention:
                    meta["sample_timing"] = opts.sample_timing
                    meta["wheel_rendering"] = opts.wheel_rendering
                    if opts.torque_skew_s:  # a filter's lag has no one timing: not stated
                        read = 1.0 if opts.sample_timing == "end" else 0.0
                        meta["torque_timing"] = read - opts.torque_skew_s * opts.fs_hz
                write_trial(out, name, rec, meta)
                n_trials += 1
                truth["trials"][name] = {
                    "subject": subj,
                    "condition": c,
                    "repetition": rep,
                    "trial_index": ti,
                    "arm": arm,
                    "phase_offset_s": offset,
                    "run_in_s": run_in,
                    "seed": tseed,
                    "integrator": rec["integrator"],
                    "grip_mean_N": grip_of_stiffness(arm["k_i"]),
                }
    truth["generation_s"] = time.perf_counter() - t_start
    truth["n_trials"] = n_trials
    (out / "truth.json").write_text(json.dumps(truth, indent=1, default=_json_default))
    return truth


def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(f"not JSON: {type(o)}")


# -- command line ----------------------------------------------------------------------------------
def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.otherworld",
        description="Write a study from an independent simulator (interchange CSV + JSON).",
    )
    p.add_argument("--out", required=True)
    p.add_argument("--subjects", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--conditions", default="BT18,BT8,PT", help="comma-separated")
    p.add_argument("--fs", type=float, default=250.0, help="sample rate, Hz (100–2000)")
    p.add_argument("--inertia", type=float, default=0.07, help="arm inertia I_i, kg·m²")
    p.add_argument("--remnant-rel", type=float, default=0.25)
    p.add_argument("--remnant-corner", type=float, default=0.6, help="Hz")
    p.add_argument("--remnant-order", type=int, default=1)
    p.add_argument("--angle-noise", type=float, default=2e-5, help="rad")
    p.add_argument("--torque-noise", type=float, default=0.02, help="N·m")
    p.add_argument("--velocity", choices=("state", "difference"), default="state")
    p.add_argument("--inertia-sd", type=float, default=0.0, help="subject spread of I_i (rel.)")
    p.add_argument("--wheel-inertia", type=float, default=WHEEL["I_sw"], help="physical, kg·m²")
    p.add_argument(
        "--control-per-sample", type=int, default=1, help="rig loop cycles per recorded sample"
    )
    p.add_argument("--record-filter", choices=("none", "mean"), default="none")
    p.add_argument("--angle-lsb", type=float, default=0.0, help="quantisation step, rad")
    p.add_argument("--torque-lsb", type=float, default=0.0, help="quantisation step, N·m")
    p.add_argument("--periods", type=int, default=2)
    p.add_argument("--integrator", choices=("auto", "expm", "solve_ivp"), default="auto")
    p.add_argument(
        "--mechanism",
        action="append",
        default=[],
        help="kind:form[:key=value,...], e.g. reflex:position:delay_s=0.035 (repeatable)",
    )
    p.add_argument("--overwrite", action="store_true")
    p.add_argument(
        "--world",
        choices=sorted(WORLDS),
        help="a named world (WORLDS); its options replace the flags above for those options",
    )
    p.add_argument(
        "--timing", action="store_true", help="only time one trial per integrator (no study)"
    )
    p.add_argument(
        "--report",
        action="store_true",
        help="then run `steerlab import` and `steerlab report` (default options) on the study "
        "(into OUT/sessions, OUT/report; the trials go to OUT/csv) and compare with the truth",
    )
    return p


def time_trials(fs_hz: float = 250.0, n_periods: int = 2, run_in_s: float = 5.0) -> dict:
    """Wall and CPU seconds for one trial (BT12 arm, I_i 0.07) per integrator and with a
    nonlinear mechanism; the CSV writing of a study comes on top."""
    d = Multisine.design(1)
    arm = {"I_i": 0.07} | DEFAULT_ARM["BT12"]
    cases = {
        "expm_null": World(arm=arm, fs_hz=fs_hz, integrator="expm"),
        "solve_ivp_null": World(arm=arm, fs_hz=fs_hz, integrator="solve_ivp"),
        "solve_ivp_reflex": World(
            arm=arm, fs_hz=fs_hz, mechanisms=[mechanism("reflex", "position_velocity")]
        ),
        "solve_ivp_friction": World(
            arm=arm, fs_hz=fs_hz, mechanisms=[mechanism("friction", "stribeck")]
        ),
    }
    out: dict[str, Any] = {"trial_s": run_in_s + n_periods * d.period_s, "fs_hz": fs_hz}
    for name, w in cases.items():
        w0, c0 = time.perf_counter(), time.process_time()
        simulate_trial(w, d, n_periods=n_periods, run_in_s=run_in_s, seed=1)
        out[name] = {
            "wall_s": round(time.perf_counter() - w0, 2),
            "cpu_s": round(time.process_time() - c0, 2),
        }
    return out


def report_recovery(study_dir: str | Path, csv_dir: str | Path, truth: dict) -> dict:
    """Run Steerlab on the study, as a user would (its CLI, default options), and compare.

    This is the consumer side: it imports Steerlab's CLI; the world above does not."""
    from steerlab.app.cli import main as steerlab

    root = Path(study_dir)
    t0 = time.perf_counter()
    for argv in (
        ["import", str(csv_dir), "--out", str(root / "sessions"), "--overwrite"],
        ["report", str(root / "sessions"), "--out", str(root / "report")],
    ):
        rc = steerlab(argv)
        if rc != 0:
            raise OtherworldError(f"steerlab {' '.join(argv)} exited with {rc}")
    rec = recovery(truth, root / "report" / "per_subject.csv")
    return {
        "steerlab_s": round(time.perf_counter() - t0, 1),
        "median_error": {k: v["median_error"] for k, v in rec["parameters"].items()},
        "median_abs_error": {k: v["median_abs_error"] for k, v in rec["parameters"].items()},
    }


def main(argv: list[str]) -> dict:
    """``python -m benchmarks otherworld ...``: generate a study; returns timing figures."""
    a = _parser().parse_args(argv)
    if a.timing:
        return time_trials(a.fs, a.periods)
    conds = tuple(c.strip() for c in a.conditions.split(",") if c.strip())
    mechs = [parse_mechanism(m) for m in a.mechanism]
    csv_dir = Path(a.out) / "csv" if a.report else Path(a.out)
    if a.report and Path(a.out).exists() and a.overwrite:
        shutil.rmtree(a.out)
    options: dict[str, Any] = dict(
        fs_hz=a.fs,
        arm_inertia=a.inertia,
        remnant_rel=a.remnant_rel,
        remnant_corner_hz=a.remnant_corner,
        remnant_order=a.remnant_order,
        angle_noise_rad=a.angle_noise,
        torque_noise_Nm=a.torque_noise,
        velocity_source=a.velocity,
        inertia_rel_sd=a.inertia_sd,
        wheel_inertia=a.wheel_inertia,
        control_per_sample=a.control_per_sample,
        record_filter=a.record_filter,
        angle_lsb_rad=a.angle_lsb,
        torque_lsb_Nm=a.torque_lsb,
        n_periods=a.periods,
        integrator=a.integrator,
        mechanisms=mechs,
    ) | (WORLDS[a.world] if a.world else {})
    truth = generate_study(
        csv_dir,
        subjects=a.subjects,
        conditions=conds,
        seed=a.seed,
        overwrite=a.overwrite,
        **options,
    )
    result = {
        "out": str(a.out),
        "trials": truth["n_trials"],
        "seconds": round(truth["generation_s"], 2),
        "seconds_per_trial": round(truth["generation_s"] / truth["n_trials"], 3),
        "integrators": sorted({t["integrator"] for t in truth["trials"].values()}),
    }
    if a.report:
        result |= report_recovery(a.out, csv_dir, truth)
    return result


def cli(argv: list[str] | None = None) -> int:
    try:
        print(json.dumps(main(sys.argv[1:] if argv is None else argv)))
    except OtherworldError as e:
        print(f"otherworld: {e}", file=sys.stderr)
        return 2
    return 0


# -- recovery: Steerlab's estimates against this world's truth ------------------------------------
def recovery(truth: dict | str | Path, per_subject_csv: str | Path) -> dict:
    """Relative error (estimate / truth − 1) of each arm parameter in a ``per_subject.csv``
    written by ``steerlab report``, against ``truth.json``. Only the CSV's columns are read
    (subject, condition, quantity, value). Returns per-cell errors and medians per parameter.
    """
    import csv

    truth_doc: dict = truth if isinstance(truth, dict) else json.loads(Path(truth).read_text())
    est: dict[tuple[str, str], dict[str, float]] = {}
    with open(per_subject_csv, newline="") as fh:
        for row in csv.DictReader(fh):
            if row["quantity"] in ARM_KEYS:
                try:
                    v = float(row["value"])
                except ValueError:
                    v = math.nan
                est.setdefault((row["subject"], row["condition"]), {})[row["quantity"]] = v
    cells = []
    for subj, s in truth_doc["subjects"].items():
        for cond, arm in s["conditions"].items():
            e = est.get((subj, cond), {})
            cells.append(
                {
                    "subject": subj,
                    "condition": cond,
                    **{k: (e.get(k, math.nan) / arm[k] - 1.0) for k in ARM_KEYS},
                }
            )
    med = {}
    for k in ARM_KEYS:
        errs = np.array([c[k] for c in cells], dtype=float)
        med[k] = {
            "median_error": float(np.nanmedian(errs)) if np.any(np.isfinite(errs)) else math.nan,
            "median_abs_error": float(np.nanmedian(np.abs(errs)))
            if np.any(np.isfinite(errs))
            else math.nan,
            "n": int(np.sum(np.isfinite(errs))),
        }
    return {"cells": cells, "parameters": med}


if __name__ == "__main__":
    sys.exit(cli())
