"""What the grip source kinds share: their ``[glove]`` fields' checks, the force scale (a value
in newtons, or raw with a gain and an offset per hand), and opening a serial port.

Every problem in a rig file is a :class:`hardware.can.ConfigError` naming the file, the table
and the field; unknown fields are errors, so a typo cannot silently leave a default in place.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from steerlab.hardware.can.config import ConfigError
from steerlab.hardware.grip.reader import GripSourceError

HANDS = ("left", "right")
#: ``unit`` values: the device sends newtons, or raw values that ``[glove.calibration]`` scales
UNITS = ("N", "raw")
_HAND_FIELDS = ("gain", "offset")


def is_number(value: object) -> bool:
    # bool is an int, but `gain = true` in a rig file is a mistake, not a gain of 1.
    return isinstance(value, int | float) and not isinstance(value, bool)


class Fields:
    """Checks one table of a rig file: unknown fields on construction, then each field."""

    def __init__(
        self, table: dict[str, Any], source: str, section: str, known: tuple[str, ...]
    ) -> None:
        self.table, self.source, self.section = table, source, section
        for key in table:
            if key not in known:
                raise self.fail(key, f"unknown field (known: {', '.join(sorted(known))})")

    def fail(self, name: str | None, problem: str) -> ConfigError:
        return ConfigError(self.source, self.section, name, problem)

    def required(self, name: str, what: str) -> Any:
        if name not in self.table:
            raise self.fail(name, f"required: {what}")
        return self.table[name]

    def text(self, name: str, what: str, default: str | None = None) -> str | None:
        """A non-empty string (``what`` says which); ``default`` when absent."""
        if name not in self.table:
            return default
        value = self.table[name]
        if not isinstance(value, str) or not value:
            raise self.fail(name, f"must be {what}, got {value!r}")
        return value

    def whole(self, name: str, *, lo: int, default: int | None = None) -> int:
        """A whole number ≥ ``lo``."""
        value = self.table.get(name, default)
        if value is None:
            raise self.fail(name, "required field is missing")
        if not isinstance(value, int) or isinstance(value, bool) or value < lo:
            raise self.fail(name, f"must be a whole number ≥ {lo}, got {value!r}")
        return value

    def positive(self, name: str, default: float) -> float:
        """A finite number > 0."""
        value = self.table.get(name, default)
        if not is_number(value) or not math.isfinite(value) or value <= 0:
            raise self.fail(name, f"must be a finite number > 0, got {value!r}")
        return float(value)

    def choice(self, name: str, options: tuple[str, ...], what: str) -> str:
        value = self.required(name, f"{what} ({' or '.join(repr(o) for o in options)})")
        if value not in options:
            raise self.fail(
                name, f"must be {' or '.join(repr(o) for o in options)} ({what}), got {value!r}"
            )
        return value

    def subtable(self, name: str, required: bool = True) -> dict[str, Any] | None:
        value = self.table.get(name)
        if value is None:
            if required:
                raise ConfigError(
                    self.source, f"{self.section}.{name}", None, "required table is missing"
                )
            return None
        if not isinstance(value, dict):
            raise self.fail(name, f"expected a table [{self.section}.{name}], got {value!r}")
        return value


@dataclass(frozen=True)
class HandScale:
    """N = gain · (value − offset)."""

    gain: float = 1.0
    offset: float = 0.0

    def to_newtons(self, value: float) -> float:
        return self.gain * (value - self.offset)

    def from_newtons(self, newtons: float) -> float:
        return newtons / self.gain + self.offset


@dataclass(frozen=True)
class ForceScale:
    """What a device's values are: newtons (``unit = "N"``), or raw values with a linear
    calibration per hand (``unit = "raw"`` and ``[glove.calibration.left/right]``)."""

    unit: str = "N"
    left: HandScale = HandScale()
    right: HandScale = HandScale()

    def to_newtons(self, left: float, right: float) -> tuple[float, float]:
        return self.left.to_newtons(left), self.right.to_newtons(right)

    def from_newtons(self, left_n: float, right_n: float) -> tuple[float, float]:
        """The values the device would send for these forces (a simulated device)."""
        return self.left.from_newtons(left_n), self.right.from_newtons(right_n)

    def describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {"glove_unit": self.unit}
        if self.unit == "raw":
            for hand in HANDS:
                scale = getattr(self, hand)
                out[f"glove_{hand}_gain"] = scale.gain
                out[f"glove_{hand}_offset"] = scale.offset
        return out


def force_scale(fields: Fields) -> ForceScale:
    """``unit`` and, for raw values, ``[glove.calibration]`` of a ``[glove]`` table."""
    unit = fields.choice("unit", UNITS, "what the device sends: newtons, or raw values")
    table = fields.subtable("calibration", required=unit == "raw")
    if unit == "N":
        if table is not None:
            raise fields.fail(
                "calibration",
                'the device sends newtons (unit = "N"): give a calibration only with unit = "raw"',
            )
        return ForceScale()
    assert table is not None
    section = f"{fields.section}.calibration"
    Fields(table, fields.source, section, HANDS)
    hands = {}
    for hand in HANDS:
        entry = table.get(hand)
        if not isinstance(entry, dict):
            raise ConfigError(
                fields.source,
                section,
                hand,
                f"required: a table [{section}.{hand}] with gain and offset "
                "(N = gain · (value − offset))",
            )
        f = Fields(entry, fields.source, f"{section}.{hand}", _HAND_FIELDS)
        gain = f.required("gain", "newtons per unit of the device's value, > 0")
        if not is_number(gain) or not math.isfinite(gain) or gain <= 0:
            raise f.fail("gain", f"must be a finite number > 0 (N per unit), got {gain!r}")
        offset = f.required("offset", "the device's value with the hand off the sensor")
        if not is_number(offset) or not math.isfinite(offset):
            raise f.fail("offset", f"must be a finite number, got {offset!r}")
        hands[hand] = HandScale(float(gain), float(offset))
    return ForceScale("raw", **hands)


def open_serial(port: str, baudrate: int, what: str, timeout_s: float = 0.05):
    """``serial.Serial(port, baudrate)`` with a read timeout; :class:`GripSourceError` naming
    ``what`` and the port if it cannot be opened."""
    import serial

    try:
        return serial.Serial(port, baudrate, timeout=timeout_s)
    except (serial.SerialException, OSError) as e:
        raise GripSourceError(f"{what}: cannot open serial port {port!r}: {e}") from None
