"""A rig file: the drive, the glove unit, the safety limits and, for the simulated rig, who sits
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

from hardware.can.config import ConfigError, DriveConfig, drive_config_from_dict
from hardware.glove.calibration import CalibrationError, GloveCalibration
from hardware.safety import SafetyLimits

SIMULATED_RIG = "simulated.toml"
SIMULATED_PORT = "simulated"
KNOWN_TABLES = {"drive", "safety", "glove", "simulation"}


@dataclass(frozen=True)
class GloveConfig:
    port: str
    baudrate: int
    calibration: GloveCalibration

    @property
    def simulated(self) -> bool:
        return self.port == SIMULATED_PORT


@dataclass(frozen=True)
class SimulationConfig:
    seed: int = 0
    column_torque_offset_nm: float = 0.05


@dataclass(frozen=True)
class RigConfig:
    source: str
    drive: DriveConfig
    glove: GloveConfig
    safety: SafetyLimits
    simulation: SimulationConfig | None

    @property
    def simulated(self) -> bool:
        return self.simulation is not None

    @property
    def loop_rate_hz(self) -> float:
        return self.drive.loop_rate_hz

    def describe(self) -> dict:
        return {
            "source": self.source,
            "drive_interface": self.drive.interface,
            "drive_channel": str(self.drive.channel),
            "drive_node_id": self.drive.node_id,
            "glove_port": self.glove.port,
            "loop_rate_hz": self.loop_rate_hz,
            "safety": asdict(self.safety),
            "simulated": self.simulated,
        }


def _read(path: str | Path | None) -> tuple[str, dict[str, Any]]:
    if path is None:
        text = resources.files("hardware").joinpath("rigs", SIMULATED_RIG).read_text("utf-8")
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
    drive = drive_config_from_dict(data, source=src)
    safety = SafetyLimits(**asdict(drive.safety))
    for field, problem in safety.problems():
        raise ConfigError(src, "safety", field, problem)

    g = data.get("glove")
    if not isinstance(g, dict):
        raise ConfigError(src, "glove", None, "required table is missing")
    for key in g:
        if key not in ("port", "baudrate", "calibration"):
            raise ConfigError(
                src, "glove", key, "unknown field (known: baudrate, calibration, port)"
            )
    if not isinstance(g.get("port"), str) or not g["port"]:
        raise ConfigError(src, "glove", "port", 'required: a serial device path or "simulated"')
    baud = g.get("baudrate", 115200)
    if isinstance(baud, bool) or not isinstance(baud, int) or baud <= 0:
        raise ConfigError(
            src, "glove", "baudrate", f"must be a positive whole number, got {baud!r}"
        )
    try:
        cal = GloveCalibration.from_config(g.get("calibration"))
    except CalibrationError as e:
        raise ConfigError(src, "glove.calibration", None, str(e)) from None
    glove = GloveConfig(g["port"], baud, cal)

    sim = None
    if "simulation" in data:
        t = data["simulation"]
        if not isinstance(t, dict):
            raise ConfigError(src, "simulation", None, "expected a table")
        for key, value in t.items():
            if key not in ("seed", "column_torque_offset_nm"):
                raise ConfigError(
                    src, "simulation", key, "unknown field (known: column_torque_offset_nm, seed)"
                )
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ConfigError(src, "simulation", key, f"must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ConfigError(src, "simulation", key, f"must be finite, got {value!r}")
            if key == "seed" and (not isinstance(value, int) or value < 0):
                raise ConfigError(
                    src, "simulation", key, f"must be a whole number ≥ 0, got {value!r}"
                )
        sim = SimulationConfig(
            seed=int(t.get("seed", 0)),
            column_torque_offset_nm=float(t.get("column_torque_offset_nm", 0.05)),
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
    return RigConfig(src, drive, glove, safety, sim)
