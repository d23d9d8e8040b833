"""Steerlab's own glove unit as a grip source kind (``[glove] kind = "steerlab"``, the default).

The unit speaks Steerlab's framed protocol on a serial port (``docs/glove-protocol.md``); its
reader is :class:`hardware.glove.unit.SerialGloveUnit` and its simulation
:class:`hardware.glove.simulated.SimulatedGloveUnit`, which writes the same frames into a pty.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

from steerlab.hardware.can.config import ConfigError
from steerlab.hardware.glove.calibration import CalibrationError, GloveCalibration
from steerlab.hardware.grip.common import Fields, open_serial
from steerlab.hardware.grips import SIMULATED_PORT, GripFunction

FIELDS = ("kind", "port", "baudrate", "calibration")


@dataclass(frozen=True)
class GloveConfig:
    port: str
    baudrate: int
    calibration: GloveCalibration
    source: str = ""
    kind: ClassVar[str] = "steerlab"

    @property
    def simulated(self) -> bool:
        return self.port == SIMULATED_PORT

    def describe(self) -> dict[str, Any]:
        return {"glove_kind": self.kind, "glove_port": self.port}


class _SteerlabKind:
    name = "steerlab"

    def config(self, table: dict[str, Any], source: str) -> GloveConfig:
        f = Fields(table, source, "glove", FIELDS)
        port = table.get("port")
        if not isinstance(port, str) or not port:
            raise f.fail("port", f'required: a serial device path or "{SIMULATED_PORT}"')
        baud = f.whole("baudrate", lo=1, default=115200)
        try:
            cal = GloveCalibration.from_config(table.get("calibration"))
        except CalibrationError as e:
            raise ConfigError(source, "glove.calibration", None, str(e)) from None
        return GloveConfig(port, baud, cal, source)

    def open(self, config: GloveConfig):
        from steerlab.hardware.glove.unit import SerialGloveUnit

        port = open_serial(config.port, config.baudrate, "glove unit")
        return SerialGloveUnit(port, config.calibration).start()

    def simulate(self, config: GloveConfig, grip: GripFunction):
        from steerlab.hardware.glove.simulated import SimulatedGloveUnit

        return SimulatedGloveUnit(grip, config.calibration)

    def at(self, config: GloveConfig, address: str) -> GloveConfig:
        return replace(config, port=address)


KIND = _SteerlabKind()
