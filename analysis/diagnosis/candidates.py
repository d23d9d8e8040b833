"""The candidate mechanisms: which of each mechanism's parameters are fitted, and how.

Names are the slots of :class:`hardware.sim.mechanisms.Mechanisms`. Each fitted parameter has
a *fitting coordinate* in which its effect on the simulated signals is smooth and close to
linear at the start value, so that Gauss–Newton works from "mechanism off":

- ``actuator_lag``: fitted in τ itself. The simulator's lag acts in continuous time on the
  held command, so the loop's low-frequency delay is τ (plus the hold's h/2), linear from 0.
  (The discrete lag it replaced was fitted in its pole u = e^{−h/τ}, in which that lag's
  effect was linear; under the continuous lag u = 0.02 is already τ ≈ h/4.)
- ``sensor_delay``: fitted as a continuous delay, applied in the frequency domain
  (:mod:`analysis.diagnosis.simulate`); the world rounds it to whole samples.
- all others: in their own units.

Parameters not listed are not fitted: with the perturbation's band they are poorly identified
together with the gains, and the gains are what tells whether the mechanism is there. A
family's *forms* (:class:`Form`) set them instead, and the best-fitting form is chosen
(:func:`analysis.diagnosis.engine.evaluate_candidate`): the reflex's delay (25–80 ms) and
activation dynamics (van der Helm et al. 2002's 2.17 Hz / 0.7, or a fast 6 Hz / 1); friction
Coulomb, Stribeck or viscous plus Coulomb; stiffening cubic, exponential or piecewise; the
actuator's lag first order, second order or a pure delay; the grip map linear or a power law.
A form may fit its own parameters (``Form.params``: the viscous friction's b_v, the
stiffening's relative rise). The laws are :mod:`hardware.sim.mechanisms`'. Drift's forms
(linear, stepwise) are in :mod:`analysis.diagnosis.drift`.

``drift`` is not fitted on the signals: every trial has its own arm parameters, which absorb
any change between trials. It is fitted on those parameters (:mod:`analysis.diagnosis.drift`).
"""

from __future__ import annotations

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

    def to_physical(self, x: float, fs_ref: float) -> float:
        """The parameter's value at fitting coordinate ``x`` (every coordinate is the value
        itself; ``fs_ref``, the data's sample rate, is for coordinates that need it)."""
        return float(x)

    def to_coordinate(self, v: float, fs_ref: float) -> float:
        return float(v)


@dataclass(frozen=True)
class Form:
    """One form of a mechanism family: the slot's settings that are not fitted but chosen
    (the best of the family's forms, by −2 log L on all trials), and, where the form's law has
    other parameters than the family's first form, the parameters it fits."""

    name: str
    fixed: tuple[tuple[str, float | str], ...] = ()  # (field, value) of the mechanism's slot
    params: tuple[ParamSpec, ...] | None = None  # None: the family's


DEFAULT_FORM = Form("default")


@dataclass(frozen=True)
class Candidate:
    name: str  # the family (a slot of Mechanisms)
    params: tuple[ParamSpec, ...]
    signature: str  # what identifies it, for the report
    forms: tuple[Form, ...] = (DEFAULT_FORM,)
    form: Form = DEFAULT_FORM  # the form this candidate is fitted in

    def with_form(self, form: Form) -> Candidate:
        return replace(self, form=form, params=self.params if form.params is None else form.params)

    def form_of(self, mech: Mechanisms) -> Form:
        """The family's form that ``mech``'s slot is in: the first whose fixed settings it has,
        else the slot's settings as they are."""
        slot = getattr(mech, self.name)
        for f in self.forms:
            if all(getattr(slot, k) == v for k, v in f.fixed):
                return f
        return DEFAULT_FORM  # the slot's own settings, the family's parameters

    def apply(self, mech: Mechanisms, coords: list[float], fs_ref: float) -> Mechanisms:
        slot = getattr(mech, self.name)
        values = dict(self.form.fixed)
        values.update(
            {p.field: p.to_physical(x, fs_ref) for p, x in zip(self.params, coords, strict=True)}
        )
        return replace(mech, **{self.name: replace(slot, **values)})

    def current(self, mech: Mechanisms, fs_ref: float) -> list[float]:
        """The fitting coordinates of the mechanism's values in ``mech``."""
        slot = getattr(mech, self.name)
        return [p.to_coordinate(getattr(slot, p.field), fs_ref) for p in self.params]

    def is_on(self, mech: Mechanisms) -> bool:
        return bool(getattr(mech, self.name).active)


# The reflex family (issue 18 item 2): a neural delay of 20–80 ms, and activation dynamics
# from van der Helm et al. (2002: 2.17 Hz, ζ 0.7) to a fast, first-order-like one (6 Hz, ζ 1).
# The gains are fitted in each form; the form is the one with the lowest −2 log L.
REFLEX_DELAYS_S = (0.025, 0.04, 0.06, 0.08)
REFLEX_ACTIVATIONS = (("van der Helm", 2.17, 0.7), ("fast", 6.0, 1.0))
REFLEX_FORMS = tuple(
    Form(
        f"delay {d * 1000:.0f} ms, {label} activation ({hz:g} Hz, ζ {zeta:g})",
        (("delay_s", d), ("activation_hz", hz), ("activation_zeta", zeta)),
    )
    for label, hz, zeta in REFLEX_ACTIVATIONS
    for d in REFLEX_DELAYS_S
)

# Friction on the wheel's velocity. The Stribeck form holds one shape (breakaway torque twice
# the sliding one, falling off over 0.05 rad/s; the independent world's default is close to
# it, 2.08 × over 0.05 rad/s): a curve of another shape is fitted by the nearest form.
FRICTION_TORQUE = ParamSpec("torque_nm", "Nm", 0.02, 0.0, 5.0)
FRICTION_FORMS = (
    Form("Coulomb", (("breakaway_ratio", 1.0), ("viscous_nms_per_rad", 0.0))),
    Form(
        "Stribeck (breakaway 2 × F_c, v_s 0.05 rad/s)",
        (("breakaway_ratio", 2.0), ("stribeck_velocity_rad_s", 0.05), ("viscous_nms_per_rad", 0.0)),
    ),
    Form(
        "viscous plus Coulomb",
        (("breakaway_ratio", 1.0),),
        # b_v ≥ 0: friction dissipates. Free to go negative, it took up part of a torque
        # sensor's gain error (tests/diagnosis/test_diagnosis_hidden.py).
        (FRICTION_TORQUE, ParamSpec("viscous_nms_per_rad", "Nms_per_rad", 0.02, 0.0, 5.0)),
    ),
)
# Stiffening: cubic in absolute terms (k3), or relative to each trial's k_i with the
# incremental stiffness (1 + rise) k_i reached at 0.02 rad (exponential) or beyond a break at
# 0.01 rad (piecewise): deflections of the arm in these tasks are of that order.
STIFFENING_FORMS = (
    Form("cubic", (("form", "cubic"),)),
    Form(
        "exponential (stiffness (1 + rise) k_i at 0.02 rad)",
        (("form", "exponential"), ("theta_scale_rad", 0.02)),
        (ParamSpec("rise", "1", 0.05, 0.0, 50.0),),
    ),
    Form(
        "piecewise (slope (1 + rise) k_i beyond 0.01 rad)",
        (("form", "piecewise"), ("theta_scale_rad", 0.01)),
        # rise ≥ 0, as the exponential's: the family is stiffening. Free to go negative, the
        # break's softening (−6 %, z 3.2) passed on two null studies of the independent world.
        (ParamSpec("rise", "1", 0.05, 0.0, 50.0),),
    ),
)
# The actuator: a first-order lag, a second-order one (ω_n = 1/τ, ζ 0.7, a servo drive's
# current and velocity loops), or a pure delay (bus and processing time).
LAG_TAU = ParamSpec("tau_s", "s", 0.001, 0.0, 0.5, start=0.001)
LAG_FORMS = (
    Form("first order", (("form", "first_order"),)),
    Form("second order (ζ 0.7; τ = 1/ω_n)", (("form", "second_order"), ("zeta", 0.7))),
    Form("pure delay", (("form", "delay"),), (ParamSpec("delay_s", "s", 0.001, 0.0, 0.1),)),
)
GRIP_FORMS = (
    Form("linear", (("form", "linear"),)),
    Form("power law (F/F̄)^gain", (("form", "power"),)),
)

CANDIDATES: tuple[Candidate, ...] = (
    Candidate(
        "reflex_delay",
        (
            ParamSpec("k_p", "Nm_per_rad", 0.5, -100.0, 300.0),
            ParamSpec("k_v", "Nms_per_rad", 0.05, -10.0, 30.0),
        ),
        "a change in the admittance's shape between about 1 and 5 Hz (delayed, low-passed "
        "stiffness and damping) that no mass-spring-damper arm reproduces",
        forms=REFLEX_FORMS,
    ),
    Candidate(
        "coulomb_friction",
        (FRICTION_TORQUE,),
        "the wheel's equation (Tp − Td = wheel dynamics × θ) fails by a torque opposing the "
        "velocity; odd-order distortion, relatively larger where the wheel moves little",
        forms=FRICTION_FORMS,
    ),
    Candidate(
        "stiffness_nonlinearity",
        (ParamSpec("k3_nm_per_rad3", "Nm_per_rad3", 20.0, -5000.0, 50000.0),),
        "odd-order distortion of the arm, growing with the deflection faster than linearly",
        forms=STIFFENING_FORMS,
    ),
    Candidate(
        "actuator_lag",
        (LAG_TAU,),
        "the wheel's equation fails by a phase lag of the motor torque that grows with "
        "frequency; the admittance θ/Td is unchanged",
        forms=LAG_FORMS,
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
        forms=GRIP_FORMS,
    ),
)
CANDIDATE_NAMES: tuple[str, ...] = tuple(c.name for c in CANDIDATES) + ("drift",)
ALL_NAMES: tuple[str, ...] = CANDIDATE_NAMES + ("none",)


def candidate(name: str) -> Candidate:
    for c in CANDIDATES:
        if c.name == name:
            return c
    raise KeyError(name)
