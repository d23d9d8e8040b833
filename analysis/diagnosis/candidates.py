"""The candidate mechanisms: which of each mechanism's parameters are fitted, and how.

Names are the slots of :class:`hardware.sim.mechanisms.Mechanisms`. Each fitted parameter has
a *fitting coordinate* in which its effect on the simulated signals is smooth and close to
linear at the start value, so that Gauss–Newton works from "mechanism off":

- ``actuator_lag``: the discrete first-order lag y_k = (1 − u) x_k + u y_{k−1}, fitted in u
  (0: no lag); τ = −1/(f_ref ln u) with f_ref the data's sample rate. In τ the effect has a
  kink at zero (nothing happens until τ is a fraction of a sample).
- ``sensor_delay``: fitted as a continuous delay, applied in the frequency domain
  (:mod:`analysis.diagnosis.simulate`); the world rounds it to whole samples.
- all others: in their own units.

Parameters not listed are held at their defaults (reflex delay 40 ms and activation dynamics
2.17 Hz / 0.7 from van der Helm et al. 2002; friction velocity scale 0.01 rad/s): with the
perturbation's band they are poorly identified together with the gains, and the gains are
what tells whether the mechanism is there.

``drift`` is not fitted on the signals: every trial has its own arm parameters, which absorb
any change between trials. It is fitted on those parameters (:mod:`analysis.diagnosis.drift`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from steerlab.hardware.sim.mechanisms import Mechanisms


@dataclass(frozen=True)
class ParamSpec:
    field: str  # field of the mechanism's dataclass
    unit: str
    step: float  # finite-difference step, fitting coordinate
    lower: float  # bounds, fitting coordinate
    upper: float
    start: float = 0.0  # fitting coordinate when the mechanism is switched on from "off"
    transform: str = "identity"  # or "lag": u ↔ τ (see the module docstring)

    def to_physical(self, x: float, fs_ref: float) -> float:
        if self.transform == "lag":
            if x <= 0.0:
                return 0.0
            x = min(x, 0.999999)
            return -1.0 / (fs_ref * math.log(x))
        return float(x)

    def to_coordinate(self, v: float, fs_ref: float) -> float:
        if self.transform == "lag":
            return math.exp(-1.0 / (fs_ref * v)) if v > 0 else 0.0
        return float(v)

    def derivative(self, x: float, fs_ref: float) -> float:
        """d physical / d coordinate, for the delta method."""
        if self.transform == "lag":
            if x <= 0.0:
                return float("nan")
            lx = math.log(min(x, 0.999999))
            return 1.0 / (fs_ref * x * lx * lx)
        return 1.0


@dataclass(frozen=True)
class Candidate:
    name: str
    params: tuple[ParamSpec, ...]
    signature: str  # what identifies it, for the report

    def apply(self, mech: Mechanisms, coords: list[float], fs_ref: float) -> Mechanisms:
        slot = getattr(mech, self.name)
        values = {
            p.field: p.to_physical(x, fs_ref) for p, x in zip(self.params, coords, strict=True)
        }
        return replace(mech, **{self.name: replace(slot, **values)})

    def current(self, mech: Mechanisms, fs_ref: float) -> list[float]:
        """The fitting coordinates of the mechanism's values in ``mech``."""
        slot = getattr(mech, self.name)
        return [p.to_coordinate(getattr(slot, p.field), fs_ref) for p in self.params]

    def is_on(self, mech: Mechanisms) -> bool:
        return bool(getattr(mech, self.name).active)


CANDIDATES: tuple[Candidate, ...] = (
    Candidate(
        "reflex_delay",
        (
            ParamSpec("k_p", "Nm_per_rad", 0.5, -100.0, 300.0),
            ParamSpec("k_v", "Nms_per_rad", 0.05, -10.0, 30.0),
        ),
        "a change in the admittance's shape between about 1 and 5 Hz (delayed, low-passed "
        "stiffness and damping) that no mass-spring-damper arm reproduces",
    ),
    Candidate(
        "coulomb_friction",
        (ParamSpec("torque_nm", "Nm", 0.02, 0.0, 5.0),),
        "the wheel's equation (Tp − Td = wheel dynamics × θ) fails by a torque opposing the "
        "velocity; odd-order distortion, relatively larger where the wheel moves little",
    ),
    Candidate(
        "stiffness_nonlinearity",
        (ParamSpec("k3_nm_per_rad3", "Nm_per_rad3", 20.0, -5000.0, 50000.0),),
        "odd-order distortion of the arm, growing with the cube of the deflection",
    ),
    Candidate(
        "actuator_lag",
        (ParamSpec("tau_s", "s", 0.02, 0.0, 0.995, start=0.02, transform="lag"),),
        "the wheel's equation fails by a phase lag of the motor torque that grows with "
        "frequency; the admittance θ/Td is unchanged",
    ),
    Candidate(
        "sensor_delay",
        (ParamSpec("delay_s", "s", 0.001, 0.0, 0.1),),
        "the measured driver torque lags the angle: a phase lead of θ/Td that grows linearly "
        "with frequency, and the wheel's equation fails at high frequency",
    ),
    Candidate(
        "grip_scheduled_stiffness",
        (ParamSpec("gain", "1", 0.1, -10.0, 10.0),),
        "sidebands around the excited lines that follow the slow grip-force fluctuation "
        "within a trial",
    ),
)
CANDIDATE_NAMES: tuple[str, ...] = tuple(c.name for c in CANDIDATES) + ("drift",)
ALL_NAMES: tuple[str, ...] = CANDIDATE_NAMES + ("none",)


def candidate(name: str) -> Candidate:
    for c in CANDIDATES:
        if c.name == name:
            return c
    raise KeyError(name)
