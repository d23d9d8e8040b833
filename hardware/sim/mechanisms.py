"""Physical mechanisms that can be added to the baseline simulated world.

Each mechanism is a small frozen dataclass with its own parameters (SI units) that fills its
slot in the world's kernel: the baseline kernel then needs no change to gain a mechanism.
All are off by default: the baseline is the paper's linear contact + intrinsic arm.
Names match the diagnosis vocabulary (``steerlab diagnose``).
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


@dataclass(frozen=True)
class CoulombFriction:
    """Dry friction in the wheel/column: T = −F_c tanh(ω/ω_ε)."""

    torque_nm: float = 0.0
    velocity_eps_rad_s: float = 0.01

    @property
    def active(self) -> bool:
        return self.torque_nm != 0.0


@dataclass(frozen=True)
class WheelImbalance:
    """An unbalanced wheel: gravity torque T = −m g r sin θ (m g r > 0: the heavy side hangs
    below the axis at θ = 0, so the torque pulls the wheel back to centre)."""

    torque_nm: float = 0.0  # m g r, N·m

    @property
    def active(self) -> bool:
        return self.torque_nm != 0.0


@dataclass(frozen=True)
class StiffnessNonlinearity:
    """Intrinsic stiffness that rises with deflection: extra torque −k3 θ_h³."""

    k3_nm_per_rad3: float = 0.0

    @property
    def active(self) -> bool:
        return self.k3_nm_per_rad3 != 0.0


@dataclass(frozen=True)
class ActuatorLag:
    """The applied motor torque lags the command: first order, time constant τ."""

    tau_s: float = 0.0

    @property
    def active(self) -> bool:
        return self.tau_s > 0.0


@dataclass(frozen=True)
class SensorDelay:
    """The driver-torque measurement is delayed relative to the angle."""

    delay_s: float = 0.0

    @property
    def active(self) -> bool:
        return self.delay_s > 0.0


@dataclass(frozen=True)
class GripScheduledStiffness:
    """Within a trial, k_i follows grip force: k_i(t) = k_i (1 + g (F(t) − F̄)/F̄)."""

    gain: float = 0.0

    @property
    def active(self) -> bool:
        return self.gain != 0.0


@dataclass(frozen=True)
class Drift:
    """Parameters change over the session: k_i and k_c scale by (1 + rate·(trial_index − 1))."""

    rate_per_trial: float = 0.0

    @property
    def active(self) -> bool:
        return self.rate_per_trial != 0.0

    def factor(self, trial_index: int) -> float:
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
        p[w.P_K3] = self.stiffness_nonlinearity.k3_nm_per_rad3
        p[w.P_COUL] = self.coulomb_friction.torque_nm
        p[w.P_COUL_EPS] = self.coulomb_friction.velocity_eps_rad_s
        p[w.P_GRAV] = self.wheel_imbalance.torque_nm
        tau = self.actuator_lag.tau_s
        # Exact discrete first-order lag; alpha = 1 is no lag.
        p[w.P_ACT_ALPHA] = 1.0 - np.exp(-dt / tau) if tau > 0 else 1.0
        r = self.reflex_delay
        p[w.P_RKP], p[w.P_RKV] = r.k_p, r.k_v
        p[w.P_RW], p[w.P_RZ] = 2 * np.pi * r.activation_hz, r.activation_zeta

    def reflex_delay_samples(self, fs_hz: float) -> int:
        r = self.reflex_delay
        return int(round(r.delay_s * fs_hz)) if r.active else 0

    def sensor_delay_samples(self, fs_hz: float) -> int:
        return int(round(self.sensor_delay.delay_s * fs_hz))

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
        d[:, 1] = k_i * g.gain * (block["grip_true_N"] - mean) / mean
        return d
