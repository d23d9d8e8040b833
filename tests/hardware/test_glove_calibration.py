from __future__ import annotations

import math

import pytest

from steerlab.hardware.glove.calibration import CalibrationError, GloveCalibration, HandCalibration
from steerlab.hardware.glove.protocol import FORCE_RAW_MAX

CONFIG = {
    "left": {"gain_n_per_count": 0.0025, "offset_counts": 1200},
    "right": {"gain_n_per_count": 0.004, "offset_counts": 0},
}


def test_from_config_and_conversion():
    cal = GloveCalibration.from_config(CONFIG)
    assert cal.to_newtons(1200 + 4000, 5000) == pytest.approx((10.0, 20.0))
    assert cal.to_newtons(1000, 0) == pytest.approx((-0.5, 0.0))  # below offset: kept negative
    assert cal.to_counts(10.0, 20.0) == (5200, 5000)
    assert GloveCalibration.from_config(cal.to_config()) == cal


def test_to_counts_rounds_and_saturates_like_an_adc():
    hand = HandCalibration(gain_n_per_count=0.01, offset_counts=100)
    assert hand.to_counts(0.014) == 101
    assert hand.to_counts(-5.0) == 0
    assert hand.to_counts(1e9) == FORCE_RAW_MAX
    with pytest.raises(ValueError, match="finite"):
        hand.to_counts(math.nan)


def _with(hand: str, field: str, value: object) -> dict:
    config = {h: dict(v) for h, v in CONFIG.items()}
    config[hand][field] = value
    return config


@pytest.mark.parametrize(
    "config, message",
    [
        ([], "expected a table with 'left' and 'right'"),
        ({"left": CONFIG["left"]}, "missing 'right'"),
        ({**CONFIG, "centre": {}}, "unknown 'centre'"),
        ({**CONFIG, "right": 3.0}, "'right' must be a table"),
        (_with("left", "gain", 1.0), r"glove calibration 'left': unknown 'gain'"),
        ({**CONFIG, "right": {"gain_n_per_count": 1.0}}, "'right': missing 'offset_counts'"),
        (_with("left", "gain_n_per_count", 0), "left.gain_n_per_count must be"),
        (_with("right", "gain_n_per_count", -0.1), "right.gain_n_per_count must be"),
        (_with("right", "gain_n_per_count", math.inf), "right.gain_n_per_count"),
        (_with("left", "gain_n_per_count", True), "left.gain_n_per_count"),
        (_with("left", "gain_n_per_count", "0.1"), "left.gain_n_per_count"),
        (_with("right", "offset_counts", -1), "right.offset_counts must be a number in 0.."),
        (_with("right", "offset_counts", FORCE_RAW_MAX + 1), "right.offset_counts"),
        (_with("left", "offset_counts", math.nan), "left.offset_counts"),
    ],
)
def test_invalid_config_names_the_field(config, message):
    with pytest.raises(CalibrationError, match=message):
        GloveCalibration.from_config(config)


def test_direct_construction_is_validated_too():
    with pytest.raises(CalibrationError, match="gain_n_per_count"):
        HandCalibration(gain_n_per_count=-1.0)
    assert issubclass(CalibrationError, ValueError)
