"""A rig file: the drive, the grip source, the safety limits and, for the simulated rig, who sits
at the wheel. ``docs/rig-config.md`` documents every field; ``hardware/rigs/simulated.toml`` is
the example.

Every problem is a :class:`hardware.can.ConfigError` naming the file, the section and the field.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from steerlab.hardware.can.config import ConfigError
from steerlab.hardware.drives import DriveSettings, drive_config
from steerlab.hardware.grip.steerlab_kind import GloveConfig as GloveConfig  # (re-exported)
from steerlab.hardware.grips import SIMULATED_PORT as SIMULATED_PORT
from steerlab.hardware.grips import GripSettings, grip_config
from steerlab.hardware.safety import SafetyLimits

SIMULATED_RIG = "simulated.toml"
KNOWN_TABLES = {"drive", "safety", "glove", "simulation", "rig_check"}
#: [simulation] fields: who holds the wheel, and the simulated wheel's own physics.
SIMULATION_FIELDS = (
    "seed",
    "column_torque_offset_nm",
    "wheel_inertia_kgm2",
    "coulomb_nm",
    "gravity_nm",
    "actuator_lag_s",
    "drive_watchdog_ms",
)
#: [rig_check] fields (steerlab rig-check's verdict) and their defaults.
RIG_CHECK_DEFAULTS = {
    "inertia_rel": 0.10,
    "damping_rel": 0.10,
    "stiffness_rel": 0.10,
    "coulomb_max_nm": 0.10,
    "gravity_max_nm": 0.10,
    "delay_max_s": 0.010,
    "vaf_min_percent": 95.0,
}


@dataclass(frozen=True)
class SimulationConfig:
    seed: int = 0
    column_torque_offset_nm: float = 0.05
    # The simulated wheel's physics (hands-off rig checks measure these).
    wheel_inertia_kgm2: float = 0.3
    coulomb_nm: float = 0.0
    gravity_nm: float = 0.0
    actuator_lag_s: float = 0.0
    # A simulated SensoDrive's own guard against a silent host, ms; 0: none. The real drive's
    # is unknown, so none is the default: the host must not count on one.
    drive_watchdog_ms: float = 0.0

    def world_config(self, fs_hz: float):
        """The simulated world's configuration for this rig."""
        from steerlab.hardware.sim.mechanisms import (
            ActuatorLag,
            CoulombFriction,
            Mechanisms,
            WheelImbalance,
        )
        from steerlab.hardware.sim.world import WorldConfig

        mech = Mechanisms(
            coulomb_friction=CoulombFriction(self.coulomb_nm),
            wheel_imbalance=WheelImbalance(self.gravity_nm),
            actuator_lag=ActuatorLag(self.actuator_lag_s),
        )
        return WorldConfig(fs_hz=fs_hz, wheel_inertia_kgm2=self.wheel_inertia_kgm2, mechanisms=mech)


@dataclass(frozen=True)
class RigConfig:
    source: str
    drive: DriveSettings  # of the kind [drive] kind names (hardware.drives)
    #: the grip source, of the kind [glove] kind names (hardware.grips): a GloveConfig for
    #: Steerlab's own glove unit (the default)
    glove: GripSettings
    safety: SafetyLimits
    simulation: SimulationConfig | None
    rig_check: dict | None = None  # [rig_check] as given (keys of RIG_CHECK_DEFAULTS)

    @property
    def simulated(self) -> bool:
        return self.simulation is not None

    @property
    def loop_rate_hz(self) -> float:
        return self.drive.loop_rate_hz

    def describe(self) -> dict:
        return {
            "source": self.source,
            **self.drive.describe(),
            **self.glove.describe(),
            "loop_rate_hz": self.loop_rate_hz,
            "safety": asdict(self.safety),
            "simulated": self.simulated,
        }


def _read(path: str | Path | None) -> tuple[str, dict[str, Any]]:
    if path is None:
        rigs = resources.files("steerlab.hardware").joinpath("rigs")
        text = rigs.joinpath(SIMULATED_RIG).read_text("utf-8")
        name = str(Path(__file__).parent / "rigs" / SIMULATED_RIG)
    else:
        name = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as e:
            raise ConfigError(name, None, None, f"cannot read rig file ({e.strerror})") from None
    try:
        return name, tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(name, None, None, f"not valid TOML: {e}") from None


def load_rig(path: str | Path | None = None) -> RigConfig:
    """Read a rig file; None gives the simulated rig shipped with Steerlab."""
    src, data = _read(path)
    unknown = set(data) - KNOWN_TABLES
    if unknown:
        raise ConfigError(
            src,
            None,
            sorted(unknown)[0],
            f"unknown table (known: {', '.join(sorted(KNOWN_TABLES))})",
        )
    drive = drive_config(data, src)
    safety = SafetyLimits(**asdict(drive.safety))
    for field, problem in safety.problems():
        raise ConfigError(src, "safety", field, problem)

    glove = grip_config(data, src)

    sim = None
    if "simulation" in data:
        t = data["simulation"]
        if not isinstance(t, dict):
            raise ConfigError(src, "simulation", None, "expected a table")
        for key, value in t.items():
            if key not in SIMULATION_FIELDS:
                raise ConfigError(
                    src,
                    "simulation",
                    key,
                    f"unknown field (known: {', '.join(sorted(SIMULATION_FIELDS))})",
                )
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ConfigError(src, "simulation", key, f"must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ConfigError(src, "simulation", key, f"must be finite, got {value!r}")
            if key == "seed" and (not isinstance(value, int) or value < 0):
                raise ConfigError(
                    src, "simulation", key, f"must be a whole number ≥ 0, got {value!r}"
                )
        if not t.get("wheel_inertia_kgm2", 0.3) > 0:
            raise ConfigError(src, "simulation", "wheel_inertia_kgm2", "must be > 0")
        for key in ("coulomb_nm", "actuator_lag_s", "drive_watchdog_ms"):
            if t.get(key, 0.0) < 0:
                raise ConfigError(src, "simulation", key, "must be ≥ 0")
        sim = SimulationConfig(
            seed=int(t.get("seed", 0)),
            **{k: float(t[k]) for k in SIMULATION_FIELDS[1:] if k in t},
        )
        if drive.interface != "virtual":
            raise ConfigError(
                src,
                "drive",
                "interface",
                'a rig with a [simulation] table runs its drive on the "virtual" bus',
            )
    elif glove.simulated:
        raise ConfigError(
            src, "glove", "port", '"simulated" needs a [simulation] table (who holds the wheel)'
        )
    return RigConfig(src, drive, glove, safety, sim, _rig_check(src, data.get("rig_check")))


def _rig_check(src: str, t) -> dict | None:
    """The [rig_check] tolerances, checked; None when the file has none (defaults apply)."""
    if t is None:
        return None
    if not isinstance(t, dict):
        raise ConfigError(src, "rig_check", None, "expected a table")
    out = {}
    for key, value in t.items():
        if key not in RIG_CHECK_DEFAULTS:
            raise ConfigError(
                src, "rig_check", key, f"unknown field (known: {', '.join(RIG_CHECK_DEFAULTS)})"
            )
        if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
            raise ConfigError(src, "rig_check", key, f"must be a number ≥ 0, got {value!r}")
        out[key] = float(value)
    return out
