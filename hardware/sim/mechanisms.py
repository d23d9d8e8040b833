"""Physical mechanisms that can be added to the baseline simulated world.

Each mechanism is a small frozen dataclass with its own parameters (SI units) that fills its
slot in the world's kernel: the baseline kernel then needs no change to gain a mechanism.
All are off by default: the baseline is the paper's linear contact + intrinsic arm.
Names match the diagnosis vocabulary (``steerlab diagnose``).

A mechanism is a *family* (issue 18 item 2): where a real lab meets several laws, ``form``
chooses the law (the default form is the law the mechanism had before it had forms, with the
same parameters, so existing models and studies simulate exactly as before).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

import numpy as np


@dataclass(frozen=True)
class ReflexDelay:
    """Reflexive position/velocity feedback with a neural delay and activation dynamics
    (van der Helm et al. 2002): T = −H_act(s) e^{−sτ} (k_p θ_h + k_v θ_h')."""

    k_p: float = 0.0  # N·m/rad
    k_v: float = 0.0  # N·m·s/rad
    delay_s: float = 0.04
    activation_hz: float = 2.17
    activation_zeta: float = 0.7

    @property
    def active(self) -> bool:
        return self.k_p != 0.0 or self.k_v != 0.0


def _check_form(kind: str, form: str, forms: tuple[str, ...]) -> None:
    if form not in forms:
        raise ValueError(f"{kind}: form {form!r}: one of {list(forms)}")


@dataclass(frozen=True)
class CoulombFriction:
    """Friction in the wheel/column, on the wheel's velocity ω:

    T = −(F_c + (F_s − F_c) e^{−(ω/v_s)²}) tanh(ω/ω_ε) − b_v ω,  F_s = ``breakaway_ratio`` · F_c.

    Coulomb (the default): ratio 1, b_v 0. Stribeck: ratio > 1 (the breakaway torque F_s at
    rest falls to F_c above ~v_s). Viscous plus Coulomb: b_v > 0. The form is given by the
    parameters, the law is one.
    """

    torque_nm: float = 0.0  # F_c
    velocity_eps_rad_s: float = 0.01
    breakaway_ratio: float = 1.0  # F_s / F_c
    stribeck_velocity_rad_s: float = 0.05  # v_s
    viscous_nms_per_rad: float = 0.0  # b_v

    @property
    def active(self) -> bool:
        return self.torque_nm != 0.0 or self.viscous_nms_per_rad != 0.0


@dataclass(frozen=True)
class WheelImbalance:
    """An unbalanced wheel: gravity torque T = −m g r sin θ (m g r > 0: the heavy side hangs
    below the axis at θ = 0, so the torque pulls the wheel back to centre)."""

    torque_nm: float = 0.0  # m g r, N·m

    @property
    def active(self) -> bool:
        return self.torque_nm != 0.0


STIFFENING_FORMS = ("cubic", "exponential", "piecewise")


@dataclass(frozen=True)
class StiffnessNonlinearity:
    """Intrinsic stiffness that rises with deflection θ_h: a torque on the arm beyond k_i θ_h.

    - ``cubic`` (default): −k3 θ_h³ (k3 in N·m/rad³, the same in every condition);
    - ``exponential``: −k_i (θ_0 sinh(θ_h/θ_0) − θ_h), θ_0 = θ_s / arccosh(1 + rise): the
      spring k_i θ_0 sinh(θ_h/θ_0), whose incremental stiffness is (1 + rise) k_i at |θ_h| = θ_s;
    - ``piecewise``: −k_i · rise · sign(θ_h) (|θ_h| − θ_s) beyond |θ_h| = θ_s: slope k_i inside
      ±θ_s, (1 + rise) k_i outside.

    k_i is the trial's intrinsic stiffness (the exponential and piecewise laws scale with it);
    θ_s is ``theta_scale_rad``. ``rise`` ≥ 0 for the exponential form.
    """

    k3_nm_per_rad3: float = 0.0
    form: str = "cubic"
    rise: float = 0.0
    theta_scale_rad: float = 0.02

    def __post_init__(self) -> None:
        _check_form("stiffness_nonlinearity", self.form, STIFFENING_FORMS)

    @property
    def active(self) -> bool:
        if self.form == "cubic":
            return self.k3_nm_per_rad3 != 0.0
        return self.rise != 0.0


LAG_FORMS = ("first_order", "second_order", "delay")


@dataclass(frozen=True)
class ActuatorLag:
    """The applied motor torque lags the command.

    - ``first_order`` (default): time constant τ = ``tau_s`` (its state updated exactly);
    - ``second_order``: ω_n = 1/``tau_s``, damping ratio ``zeta`` (exact zero-order-hold
      discretisation of T'' = ω_n² (cmd − T) − 2ζω_n T');
    - ``delay``: the command reaches the motor ``delay_s`` later (a fraction of a sample by
      linear interpolation between the two held commands it falls between).

    The lag acts in continuous time on the held command, and the torque the arm and wheel get
    over a sample is the lag's mean over it (the delay form's interpolation is that mean too).
    Applying the lag's value at the sample's end instead made a 12 ms lag, simulated in
    continuous time at 250 Hz (benchmarks/otherworld.py), fit as 13.8 ms (half a sample
    more) and leave a misfit a reflex then "explained".
    """

    tau_s: float = 0.0
    form: str = "first_order"
    zeta: float = 0.7
    delay_s: float = 0.0

    def __post_init__(self) -> None:
        _check_form("actuator_lag", self.form, LAG_FORMS)

    @property
    def active(self) -> bool:
        if self.form == "delay":
            return self.delay_s > 0.0
        return self.tau_s > 0.0

    def delay_samples(self, fs_hz: float) -> tuple[int, float]:
        """(whole samples, fraction of the next) of the delay form; (0, 0) otherwise."""
        if self.form != "delay" or not self.delay_s > 0.0:
            return 0, 0.0
        q = self.delay_s * fs_hz
        n = int(np.floor(q + 1e-9))
        return n, max(q - n, 0.0)


@dataclass(frozen=True)
class SensorDelay:
    """The driver-torque measurement is delayed relative to the angle."""

    delay_s: float = 0.0

    @property
    def active(self) -> bool:
        return self.delay_s > 0.0


GRIP_FORMS = ("linear", "power", "exponential")
# A grip ratio F/F̄ below this is taken as this (the glove can read ~0 N; a power law of 0 with
# a negative exponent is infinite).
GRIP_RATIO_FLOOR = 0.05


@dataclass(frozen=True)
class GripScheduledStiffness:
    """Within a trial, k_i follows grip force through a monotone map M of r = F(t)/F̄, M(1) = 1:
    k_i(t) = k_i M(r), with gain g:

    - ``linear`` (default): M = 1 + g (r − 1);
    - ``power``: M = r^g (r at least :data:`GRIP_RATIO_FLOOR`);
    - ``exponential``: M = e^{g (r − 1)}.

    All three agree to first order in r − 1.
    """

    gain: float = 0.0
    form: str = "linear"

    def __post_init__(self) -> None:
        _check_form("grip_scheduled_stiffness", self.form, GRIP_FORMS)

    @property
    def active(self) -> bool:
        return self.gain != 0.0

    def relative_change(self, ratio: np.ndarray) -> np.ndarray:
        """M(r) − 1 for grip ratios r = F/F̄."""
        g = self.gain
        if self.form == "linear":
            return g * (ratio - 1.0)
        if self.form == "power":
            return np.maximum(ratio, GRIP_RATIO_FLOOR) ** g - 1.0
        return np.expm1(g * (ratio - 1.0))


DRIFT_FORMS = ("linear", "stepwise")
DRIFT_STIFFNESSES = ("k_i,k_c", "k_i")


@dataclass(frozen=True)
class Drift:
    """Parameters change over the session: the stiffnesses ``stiffnesses`` (k_i and k_c, the
    default, or k_i alone) scale by a factor of the trial index,

    - ``linear`` (default): 1 + rate·(trial_index − 1);
    - ``stepwise``: 1 before trial ``at_trial``, 1 + ``step`` from it on.
    """

    rate_per_trial: float = 0.0
    form: str = "linear"
    step: float = 0.0
    at_trial: int = 2
    stiffnesses: str = "k_i,k_c"

    def __post_init__(self) -> None:
        _check_form("drift", self.form, DRIFT_FORMS)
        _check_form("drift stiffnesses", self.stiffnesses, DRIFT_STIFFNESSES)
        # A model file's numbers are read as floats; the trial index is whole.
        object.__setattr__(self, "at_trial", int(self.at_trial))

    @property
    def active(self) -> bool:
        if self.form == "stepwise":
            return self.step != 0.0
        return self.rate_per_trial != 0.0

    def factor(self, trial_index: int) -> float:
        if self.form == "stepwise":
            return 1.0 + self.step if trial_index >= self.at_trial else 1.0
        return 1.0 + self.rate_per_trial * (trial_index - 1)


@dataclass(frozen=True)
class Mechanisms:
    reflex_delay: ReflexDelay = field(default_factory=ReflexDelay)
    coulomb_friction: CoulombFriction = field(default_factory=CoulombFriction)
    stiffness_nonlinearity: StiffnessNonlinearity = field(default_factory=StiffnessNonlinearity)
    actuator_lag: ActuatorLag = field(default_factory=ActuatorLag)
    sensor_delay: SensorDelay = field(default_factory=SensorDelay)
    grip_scheduled_stiffness: GripScheduledStiffness = field(default_factory=GripScheduledStiffness)
    drift: Drift = field(default_factory=Drift)
    wheel_imbalance: WheelImbalance = field(default_factory=WheelImbalance)

    def active(self) -> list[str]:
        return [f.name for f in fields(self) if getattr(self, f.name).active]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Mechanisms:
        defaults = cls()
        kinds = {f.name: type(getattr(defaults, f.name)) for f in fields(cls)}
        unknown = set(d) - set(kinds)
        if unknown:
            raise ValueError(f"unknown mechanism(s) {sorted(unknown)}; known: {sorted(kinds)}")
        return cls(**{k: kinds[k](**v) for k, v in d.items()})

    # -- kernel slots (see hardware.sim.world) ---------------------------------------------
    def configure(self, p: np.ndarray, behaviour, fs_hz: float) -> None:
        from steerlab.hardware.sim import world as w

        dt = 1.0 / fs_hz
        sn = self.stiffness_nonlinearity
        if sn.form == "cubic":
            p[w.P_K3] = sn.k3_nm_per_rad3
        elif sn.rise != 0.0:
            p[w.P_STIFF_FORM] = 1.0 if sn.form == "exponential" else 2.0
            p[w.P_RISE] = sn.rise
            if sn.form == "exponential":
                if sn.rise <= 0.0:
                    raise ValueError("stiffness_nonlinearity: exponential form needs rise > 0")
                # arccosh(1 + r), accurate for the tiny r a fit starting at 0 tries
                rise = sn.rise
                p[w.P_THETA_S] = sn.theta_scale_rad / np.log1p(rise + np.sqrt(rise * (2.0 + rise)))
            else:
                p[w.P_THETA_S] = sn.theta_scale_rad
        p[w.P_KI] = behaviour.arm.k_i
        cf = self.coulomb_friction
        p[w.P_COUL] = cf.torque_nm
        p[w.P_COUL_EPS] = cf.velocity_eps_rad_s
        p[w.P_STRIB] = cf.torque_nm * (cf.breakaway_ratio - 1.0)
        p[w.P_STRIB_V] = cf.stribeck_velocity_rad_s
        p[w.P_VISC] = cf.viscous_nms_per_rad
        p[w.P_GRAV] = self.wheel_imbalance.torque_nm
        lag = self.actuator_lag
        tau = lag.tau_s
        # Exact discrete first-order lag; alpha = 1 is no lag. The torque applied over a
        # sample is the lag's mean over it (the class docstring).
        first = lag.form == "first_order"
        p[w.P_ACT_ALPHA], p[w.P_LAG_MEAN] = first_order_lag_weights(tau if first else 0.0, dt)
        if lag.form == "second_order" and tau > 0:
            p[w.P_LAG_FORM] = 1.0
            p[w.P_LAG2 : w.P_LAG2 + 6] = _second_order_zoh(1.0 / tau, lag.zeta, dt)
            p[w.P_LAG_MEAN : w.P_LAG_MEAN + 3] = _second_order_mean(1.0 / tau, lag.zeta, dt)
        elif lag.form == "delay" and lag.active:
            p[w.P_LAG_FORM] = 2.0
            n, frac = lag.delay_samples(fs_hz)
            p[w.P_LAG_N], p[w.P_LAG_FRAC] = n, frac
        r = self.reflex_delay
        p[w.P_RKP], p[w.P_RKV] = r.k_p, r.k_v
        p[w.P_RW], p[w.P_RZ] = 2 * np.pi * r.activation_hz, r.activation_zeta

    def reflex_delay_samples(self, fs_hz: float) -> int:
        r = self.reflex_delay
        return int(round(r.delay_s * fs_hz)) if r.active else 0

    def sensor_delay_samples(self, fs_hz: float) -> int:
        return int(round(self.sensor_delay.delay_s * fs_hz))

    def command_ring_samples(self, fs_hz: float) -> int:
        """Length of the ring of past commands the actuator's delay form reads (0: none)."""
        if self.actuator_lag.form != "delay" or not self.actuator_lag.active:
            return 0
        return self.actuator_lag.delay_samples(fs_hz)[0] + 2

    def parameter_deltas(self, block: dict[str, np.ndarray], behaviour) -> np.ndarray | None:
        """Per-sample changes (Δb_i, Δk_i, Δb_c, Δk_c) for one noise block, or None."""
        g = self.grip_scheduled_stiffness
        if not g.active:
            return None
        # In a time-varying trial the grip's mean and k_i move with the task (per sample):
        # the mechanism then scales around those, not around the trial's base behaviour.
        mean = np.maximum(block.get("grip_mean_true_N", behaviour.grip_mean_n), 1e-9)
        k_i = block["true_arm"][:, 1] if "true_arm" in block else behaviour.arm.k_i
        d = np.zeros((len(block["grip_true_N"]), 4))
        if g.form == "linear":  # as before forms, operation for operation
            d[:, 1] = k_i * g.gain * (block["grip_true_N"] - mean) / mean
        else:
            d[:, 1] = k_i * g.relative_change(block["grip_true_N"] / mean)
        return d


def first_order_lag_weights(tau: float, dt: float) -> tuple[float, float]:
    """(alpha, m) of a first-order lag τ on a command held for ``dt``: its exact update
    T ← T + alpha (cmd − T), and the torque over the sample, its mean there,
    cmd + m (T − cmd) from T at the sample's start. (1, 0) for τ ≤ 0: no lag."""
    if tau <= 0:
        return 1.0, 0.0
    alpha = float(-np.expm1(-dt / tau))
    return alpha, alpha * tau / dt


def _second_order_matrix(wn: float, zeta: float) -> np.ndarray:
    """[T, T', cmd]' of T'' = ω_n² (cmd − T) − 2ζω_n T' with cmd held."""
    M = np.zeros((3, 3))
    M[0, 1] = 1.0
    M[1, 0] = -wn * wn
    M[1, 1] = -2.0 * zeta * wn
    M[1, 2] = wn * wn
    return M


def _second_order_zoh(wn: float, zeta: float, dt: float) -> np.ndarray:
    """(Φ00, Φ01, Φ10, Φ11, Γ0, Γ1): exact zero-order-hold discretisation of
    [T, T']' = [[0, 1], [−ω_n², −2ζω_n]] [T, T'] + [0, ω_n²] cmd."""
    from scipy.linalg import expm

    E = expm(_second_order_matrix(wn, zeta) * dt)
    return np.array([E[0, 0], E[0, 1], E[1, 0], E[1, 1], E[0, 2], E[1, 2]])


def _second_order_mean(wn: float, zeta: float, dt: float) -> np.ndarray:
    """(m0, m1, m2): T's mean over a sample, m0 T + m1 T' + m2 cmd from the state at its start
    and the held command (the integral of exp(M t) over the sample, from the 6 × 6
    exponential of [[M, I], [0, 0]] dt)."""
    from scipy.linalg import expm

    big = np.zeros((6, 6))
    big[:3, :3] = _second_order_matrix(wn, zeta) * dt
    big[:3, 3:] = np.eye(3) * dt
    return expm(big)[0, 3:] / dt
