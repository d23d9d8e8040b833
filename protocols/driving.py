"""The driving task as plain data: the vehicle, the road and a driving condition (issue 19).

A protocol may hold driving conditions beside the boundary tasks (``protocols/driving.toml``)::

    [vehicle]                 # single-track (bicycle) model; every key optional
    [road]                    # the seeded road; every key optional
    [[conditions]]
    name = "D15_DRY"
    task = "driving"
    speed_mps = 15.0
    friction = 1.0            # tyre–road friction coefficient μ
    perturbation_level = 1.0  # the protocol's multisine × this; 0: off

Signs (ISO 8855, seen from above, x forward, y left): lateral position positive left of the
lane centre; heading error = car heading − road heading, positive counter-clockwise; road
curvature positive for a left bend; the steering (road wheel) angle δ = θ / steering_ratio,
positive left, so that a positive (counter-clockwise) wheel angle turns the car left. The
aligning torque is a torque on the steering wheel, positive counter-clockwise (the sign of the
wheel angle): it opposes the front tyres' slip, so it pulls the wheel back to centre.

Every problem is a ``ValueError`` naming the file and the field (the protocol reader turns it
into a ``ProtocolError``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

G_MPS2 = 9.81


@dataclass(frozen=True)
class VehicleSpec:
    """A mid-size car (ours: values typical of a 1.5 t saloon, e.g. Rajamani 2012 ch. 2)."""

    mass_kg: float = 1500.0
    yaw_inertia_kgm2: float = 2500.0
    cg_to_front_m: float = 1.2
    cg_to_rear_m: float = 1.5
    front_cornering_N_per_rad: float = 80000.0  # both front tyres together
    rear_cornering_N_per_rad: float = 90000.0
    steering_ratio: float = 15.0  # wheel angle / road-wheel angle
    pneumatic_trail_m: float = 0.03  # at zero slip; shrinks to 0 as the tyre saturates
    mechanical_trail_m: float = 0.01
    # Share of the tyres' aligning moment the wheel renders (the rest is "power assistance").
    feel_gain: float = 0.4
    width_m: float = 1.8

    @property
    def wheelbase_m(self) -> float:
        return self.cg_to_front_m + self.cg_to_rear_m

    @property
    def understeer_gradient_rad_s2_per_m(self) -> float:
        """K = m/L·(b/C_f − a/C_r), rad per m/s² of lateral acceleration (linear tyres)."""
        m, a, b = self.mass_kg, self.cg_to_front_m, self.cg_to_rear_m
        cf, cr = self.front_cornering_N_per_rad, self.rear_cornering_N_per_rad
        return m / self.wheelbase_m * (b / cf - a / cr)

    def steady_yaw_rate_gain(self, speed_mps: float) -> float:
        """Steady-state r/δ = U / (L + K U²) of the linear bicycle model, 1/s."""
        u = speed_mps
        return u / (self.wheelbase_m + self.understeer_gradient_rad_s2_per_m * u * u)

    def kernel_vector(self) -> np.ndarray:
        """The numbers :mod:`hardware.vehicle` takes (friction and speed are added per trial)."""
        m, a, b = self.mass_kg, self.cg_to_front_m, self.cg_to_rear_m
        fzf = m * G_MPS2 * b / (a + b)
        fzr = m * G_MPS2 * a / (a + b)
        return np.array(
            [
                m,
                self.yaw_inertia_kgm2,
                a,
                b,
                self.front_cornering_N_per_rad,
                self.rear_cornering_N_per_rad,
                self.steering_ratio,
                self.pneumatic_trail_m,
                self.mechanical_trail_m,
                self.feel_gain,
                fzf,
                fzr,
            ]
        )


@dataclass(frozen=True)
class RoadSpec:
    """A seeded road: straights and smooth curves; lane width alternating wide and narrow."""

    seed: int = 19
    wide_lane_m: float = 3.6
    narrow_lane_m: float = 2.6
    width_section_min_m: float = 150.0
    width_section_max_m: float = 350.0
    width_taper_m: float = 40.0
    straight_min_m: float = 60.0
    straight_max_m: float = 200.0
    curve_min_m: float = 80.0
    curve_max_m: float = 250.0
    min_radius_m: float = 300.0  # 25 m/s: 2.1 m/s², 43 % of the grip on μ = 0.5
    max_radius_m: float = 800.0
    curvature_taper_m: float = 40.0  # curvature changes smoothly (clothoid-like) over this
    lead_in_m: float = 100.0  # a straight, wide start
    grid_m: float = 0.25

    def generate(self, length_m: float, seed: int | None = None) -> Road:
        return make_road(self, length_m, self.seed if seed is None else seed)


@dataclass(frozen=True)
class DrivingCondition:
    speed_mps: float
    friction: float = 1.0
    perturbation_level: float = 1.0  # × the protocol's multisine; 0: no perturbation

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


@dataclass(frozen=True)
class Road:
    """The centre line and lane width on a uniform arc-length grid (SI units).

    ``x_m, y_m, heading_rad``: the centre line in the road's own frame (start at the origin
    heading along x); ``curvature_1pm`` = d heading / d s, positive left; ``lane_width_m``.
    """

    grid_m: float
    curvature_1pm: np.ndarray
    lane_width_m: np.ndarray
    heading_rad: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    seed: int

    @property
    def length_m(self) -> float:
        return (len(self.curvature_1pm) - 1) * self.grid_m

    def table(self) -> np.ndarray:
        """(5, n) rows: curvature, width, heading, x, y (the vehicle kernel's road)."""
        return np.ascontiguousarray(
            np.vstack([self.curvature_1pm, self.lane_width_m, self.heading_rad, self.x_m, self.y_m])
        )

    def at(self, s_m: np.ndarray | float, row: np.ndarray) -> np.ndarray:
        s = np.asarray(s_m, dtype=float)
        return np.interp(s, np.arange(len(row)) * self.grid_m, row)


def _hann_smooth(x: np.ndarray, width: int) -> np.ndarray:
    if width < 2:
        return x
    w = np.hanning(width + 2)[1:-1]
    w /= w.sum()
    pad = np.concatenate([np.full(width, x[0]), x, np.full(width, x[-1])])
    return np.convolve(pad, w, mode="same")[width:-width]


def make_road(spec: RoadSpec, length_m: float, seed: int) -> Road:
    """Straights and constant-radius curves (alternating sides at random), curvature smoothed
    over ``curvature_taper_m``; width sections alternating wide/narrow, smoothed over
    ``width_taper_m``. Drawn sequentially, so a longer road starts with the same road."""
    rng = np.random.default_rng([seed, 19])
    ds = spec.grid_m
    n = int(math.ceil(length_m / ds)) + 1
    kappa = np.zeros(n)
    width = np.full(n, spec.wide_lane_m)
    k = int(round(spec.lead_in_m / ds))
    straight = False
    while k < n:
        if straight:
            seg = rng.uniform(spec.straight_min_m, spec.straight_max_m)
            value = 0.0
        else:
            seg = rng.uniform(spec.curve_min_m, spec.curve_max_m)
            radius = rng.uniform(spec.min_radius_m, spec.max_radius_m)
            value = rng.choice([-1.0, 1.0]) / radius
        m = int(round(seg / ds))
        kappa[k : k + m] = value
        k += m
        straight = not straight
    k, narrow = int(round(spec.lead_in_m / ds)), True
    while k < n:
        m = int(round(rng.uniform(spec.width_section_min_m, spec.width_section_max_m) / ds))
        width[k : k + m] = spec.narrow_lane_m if narrow else spec.wide_lane_m
        k += m
        narrow = not narrow
    kappa = _hann_smooth(kappa, int(round(spec.curvature_taper_m / ds)))
    width = _hann_smooth(width, int(round(spec.width_taper_m / ds)))
    # Heading and position: trapezoidal integration along the arc.
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * ds)])
    c, s = np.cos(heading), np.sin(heading)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (c[1:] + c[:-1]) * ds)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (s[1:] + s[:-1]) * ds)])
    for a in (kappa, width, heading, x, y):
        a.setflags(write=False)
    return Road(ds, kappa, width, heading, x, y, seed)


@dataclass(frozen=True)
class DrivingSetup:
    """What a loop needs to run one driving trial: the condition, the road, the vehicle."""

    condition: DrivingCondition
    vehicle: VehicleSpec
    road: Road

    def vehicle_vector(self) -> np.ndarray:
        """Kernel parameters: the vehicle's, then speed and friction."""
        return np.concatenate(
            [self.vehicle.kernel_vector(), [self.condition.speed_mps, self.condition.friction]]
        )

    def to_dict(self) -> dict[str, Any]:
        """For the trial's ``driving`` attribute (JSON)."""
        return {
            **self.condition.to_dict(),
            "road_seed": self.road.seed,
            "road_length_m": self.road.length_m,
            "vehicle": asdict(self.vehicle),
        }


# -- reading the TOML --------------------------------------------------------------------------

CONDITION_KEYS = ("task", "speed_mps", "friction", "perturbation_level")
MAX_SPEED_MPS = 60.0


def _number(where: str, key: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValueError(f"{where}.{key}: expected a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise ValueError(f"{where}.{key}: must be a finite number, got {v}")
    return v


def _table(raw: Any, cls: type, where: str) -> Any:
    if raw is None:
        return cls()
    if not isinstance(raw, dict):
        raise ValueError(f"{where}: expected a table, got {raw!r}")
    known = {f.name: f for f in fields(cls)}
    unknown = set(raw) - set(known)
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {sorted(unknown)}; known: {sorted(known)}")
    out: dict[str, Any] = {}
    for k, v in raw.items():
        if known[k].type in ("int", int):
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2**63:
                raise ValueError(f"{where}.{k}: expected a whole number ≥ 0, got {v!r}")
            out[k] = v
        else:
            out[k] = _number(where, k, v)
            if out[k] < 0 or (out[k] == 0 and k not in ("mechanical_trail_m", "feel_gain")):
                raise ValueError(f"{where}.{k}: must be > 0, got {out[k]}")
    return cls(**out)


def parse_vehicle(raw: Any, file: str) -> VehicleSpec:
    v = _table(raw, VehicleSpec, f"{file}: [vehicle]")
    if v.feel_gain > 2.0:
        raise ValueError(f"{file}: [vehicle].feel_gain: at most 2, got {v.feel_gain}")
    return v


def parse_road(raw: Any, file: str) -> RoadSpec:
    r = _table(raw, RoadSpec, f"{file}: [road]")
    w = f"{file}: [road]"
    for lo, hi in (
        ("width_section_min_m", "width_section_max_m"),
        ("straight_min_m", "straight_max_m"),
        ("curve_min_m", "curve_max_m"),
        ("min_radius_m", "max_radius_m"),
    ):
        if getattr(r, lo) > getattr(r, hi):
            raise ValueError(
                f"{w}.{lo}: must not exceed {hi} ({getattr(r, lo)} > {getattr(r, hi)})"
            )
    if not 0.01 <= r.grid_m <= 5.0:
        raise ValueError(f"{w}.grid_m: must be between 0.01 and 5 m, got {r.grid_m}")
    return r


def parse_condition(raw: dict, where: str) -> DrivingCondition:
    """A ``task = "driving"`` condition's own fields (``where`` names the condition)."""
    if raw.get("task") != "driving":
        raise ValueError(f'{where}.task: must be "driving", got {raw.get("task")!r}')
    for key in ("boundary_deg", "segments", "transition", "transition_s"):
        if key in raw:
            raise ValueError(
                f"{where}.{key}: not allowed in a driving condition (the road is the task)"
            )
    if "speed_mps" not in raw:
        raise ValueError(f"{where}.speed_mps: required for a driving condition")
    speed = _number(where, "speed_mps", raw["speed_mps"])
    if not 1.0 <= speed <= MAX_SPEED_MPS:
        raise ValueError(
            f"{where}.speed_mps: must be between 1 and {MAX_SPEED_MPS:g} m/s, got {speed}"
        )
    mu = _number(where, "friction", raw.get("friction", 1.0))
    if not 0.05 <= mu <= 1.5:
        raise ValueError(f"{where}.friction: must be between 0.05 and 1.5, got {mu}")
    level = _number(where, "perturbation_level", raw.get("perturbation_level", 1.0))
    if not 0.0 <= level <= 2.0:
        raise ValueError(f"{where}.perturbation_level: must be between 0 (off) and 2, got {level}")
    return DrivingCondition(speed, mu, level)


ROAD_MARGIN_M = 300.0  # road beyond the trial's end: the driver's preview and a little slack


def road_length_m(condition: DrivingCondition, trial_s: float) -> float:
    return condition.speed_mps * trial_s + ROAD_MARGIN_M
