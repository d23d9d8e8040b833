from __future__ import annotations

import math

import pytest

from steerlab.protocols.protocol import ProtocolError, load_protocol, parse_protocol
from tests.helpers import fast_protocol_text


def test_default_protocol_is_the_papers(default_protocol):
    p = default_protocol
    assert p.condition_names == ["RT", "BT18", "BT12", "BT8", "BT5", "PT"]
    assert math.isinf(p.condition("RT").boundary_deg) and p.condition("PT").boundary_deg == 0
    assert [p.condition(c).boundary_deg for c in ("BT18", "BT12", "BT8", "BT5")] == [18, 12, 8, 5]
    assert p.trial.familiarization_trials == 1 and p.trial.repetitions == 2
    assert p.perturbation.period_s == 45 and p.perturbation.n_bands == 31
    assert p.perturbation.sd_nm == 2.26 and p.perturbation.full_power_max_hz == 0.7
    assert (p.wheel.inertia_kgm2, p.wheel.damping_nms_per_rad, p.wheel.stiffness_nm_per_rad) == (
        0.3,
        2.0,
        4.2,
    )
    assert "[[conditions]]" in p.source_text


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace("run_in_s = 5.0", "run_in_s = -5.0"), r"\[trial\]\.run_in_s.*≥ 0"),
        (lambda t: t.replace("periods = 1 ", "periods = 0 "), r"\[trial\]\.periods"),
        (
            lambda t: t.replace("periods = 1 ", "periods = 1.5 "),
            r"\[trial\]\.periods.*whole number",
        ),
        (lambda t: t.replace("sd_nm = 2.26", 'sd_nm = "big"'), r"\[perturbation\]\.sd_nm.*number"),
        (lambda t: t.replace('name = "BT8"', 'name = "BT12"'), r"duplicate condition.*BT12"),
        (lambda t: t.replace("boundary_deg = 5.0", "boundary_deg = -5.0"), r"BT5\)\.boundary_deg"),
        (lambda t: t.replace("[trial]", "[trial]\nperiod = 3"), r"unknown field.*period"),
        (lambda t: t.replace("[wheel]", "[wheel\n"), r"not valid TOML"),
        (
            lambda t: t.replace("fade_in_s = 1.0", "fade_in_s = 9.0"),
            r"fade_in_s.*inside the run-in",
        ),
    ],
)
def test_bad_protocol_names_file_and_field(tmp_path, edit, message):
    text = edit(fast_protocol_text(1000.0, 5.0))
    path = tmp_path / "study.toml"
    path.write_text(text)
    with pytest.raises(ProtocolError, match=message) as e:
        load_protocol(path)
    assert str(path) in str(e.value)


def test_unknown_condition_and_missing_file(default_protocol, tmp_path):
    with pytest.raises(ProtocolError, match="unknown condition 'XX'"):
        default_protocol.condition("XX")
    with pytest.raises(ProtocolError, match="cannot read protocol file"):
        load_protocol(tmp_path / "nope.toml")


def test_period_must_be_whole_samples():
    text = fast_protocol_text(1000.0).replace("period_s = 45.0", "period_s = 45.0001")
    with pytest.raises(ProtocolError, match="period_s"):
        parse_protocol(text, "p.toml")
