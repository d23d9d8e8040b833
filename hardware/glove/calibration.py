"""Raw glove totals (ADC counts) to newtons, one linear law per hand.

    force_N = gain_n_per_count * (counts - offset_counts)

``offset_counts`` is the unloaded reading (measure it with the hands off the wheel), so the gain
is the only number that comes from a load calibration. Forces below the offset come out
negative and are kept: clipping noise at zero would bias the mean grip force upward.

Configuration, e.g. from the rig's TOML::

    [glove.calibration.left]
    gain_n_per_count = 0.0025
    offset_counts = 1200

    [glove.calibration.right]
    gain_n_per_count = 0.0024
    offset_counts = 1150
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, TypeGuard

from steerlab.hardware.glove.protocol import FORCE_RAW_MAX

HANDS = ("left", "right")
_HAND_FIELDS = ("gain_n_per_count", "offset_counts")


class CalibrationError(ValueError):
    """A calibration value or config entry is invalid; the message names the field."""


@dataclass(frozen=True)
class HandCalibration:
    gain_n_per_count: float
    offset_counts: float = 0.0

    def __post_init__(self) -> None:
        _check_hand(self.gain_n_per_count, self.offset_counts, "HandCalibration")

    def to_newtons(self, counts: float) -> float:
        return self.gain_n_per_count * (counts - self.offset_counts)

    def to_counts(self, newtons: float) -> int:
        """The raw total the unit would send for this force: rounded, and clipped to the
        converter's range as a saturating ADC would."""
        if not math.isfinite(newtons):
            raise ValueError(f"force must be finite, got {newtons!r}")
        counts = round(newtons / self.gain_n_per_count + self.offset_counts)
        return min(max(counts, 0), FORCE_RAW_MAX)


@dataclass(frozen=True)
class GloveCalibration:
    left: HandCalibration
    right: HandCalibration

    @classmethod
    def from_config(cls, config: Mapping[str, Any] | None) -> GloveCalibration:
        """Build from ``{"left": {...}, "right": {...}}``; every field is required and unknown
        keys are refused, so a typo cannot silently leave a default in place."""
        if not isinstance(config, Mapping):
            raise CalibrationError(
                f"glove calibration: expected a table with 'left' and 'right', "
                f"got {type(config).__name__}"
            )
        _check_keys(config, HANDS, "glove calibration")
        hands = {}
        for hand in HANDS:
            entry = config[hand]
            if not isinstance(entry, Mapping):
                raise CalibrationError(
                    f"glove calibration: '{hand}' must be a table with {', '.join(_HAND_FIELDS)}"
                    f", got {type(entry).__name__}"
                )
            _check_keys(entry, _HAND_FIELDS, f"glove calibration '{hand}'")
            gain, offset = entry["gain_n_per_count"], entry["offset_counts"]
            _check_hand(gain, offset, hand)
            hands[hand] = HandCalibration(float(gain), float(offset))
        return cls(**hands)

    def to_config(self) -> dict[str, dict[str, float]]:
        """The inverse of from_config; plain data for session metadata."""
        return {
            hand: {
                "gain_n_per_count": getattr(self, hand).gain_n_per_count,
                "offset_counts": getattr(self, hand).offset_counts,
            }
            for hand in HANDS
        }

    def to_newtons(self, left_raw: float, right_raw: float) -> tuple[float, float]:
        return self.left.to_newtons(left_raw), self.right.to_newtons(right_raw)

    def to_counts(self, left_n: float, right_n: float) -> tuple[int, int]:
        return self.left.to_counts(left_n), self.right.to_counts(right_n)


def _check_keys(table: Mapping[str, Any], required: tuple[str, ...], where: str) -> None:
    missing = [k for k in required if k not in table]
    if missing:
        raise CalibrationError(f"{where}: missing {', '.join(repr(k) for k in missing)}")
    unknown = sorted(str(k) for k in table if k not in required)
    if unknown:
        raise CalibrationError(
            f"{where}: unknown {', '.join(repr(k) for k in unknown)} "
            f"(expected {', '.join(required)})"
        )


def _check_hand(gain: object, offset: object, hand: str) -> None:
    if not _is_number(gain) or not math.isfinite(gain) or gain <= 0:
        raise CalibrationError(
            f"glove calibration: {hand}.gain_n_per_count must be a finite number > 0 "
            f"(N per count), got {gain!r}"
        )
    if not _is_number(offset) or not 0 <= offset <= FORCE_RAW_MAX:
        raise CalibrationError(
            f"glove calibration: {hand}.offset_counts must be a number in 0..{FORCE_RAW_MAX} "
            f"(raw counts), got {offset!r}"
        )


def _is_number(value: object) -> TypeGuard[int | float]:
    # bool is an int, but `gain = true` in a config file is a mistake, not a gain of 1.
    return isinstance(value, int | float) and not isinstance(value, bool)
