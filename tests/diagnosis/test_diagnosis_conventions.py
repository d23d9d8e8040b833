"""The diagnosis under the recording conventions of other labs' rigs (issue 36).

The team's independent world (``benchmarks/otherworld.py``) records its studies the ways
labs do (``CONVENTIONS``): the angle and torque read at the end of the command interval, a
physical wheel (its damping and spring continuous), a 1 kHz loop averaged to 250 Hz, the torque
channel half a sample off the angle, a low-pass filter on the torque sensor. None of them is a
mechanism: a study with nothing hidden is ``none`` under each, and a hidden mechanism is named
under each. The studies reach the diagnosis only through the interchange files and
``steerlab import``; their truth is deleted first.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from steerlab.analysis import rig_from_data
from steerlab.analysis.diagnosis import run_diagnosis
from steerlab.benchmarks._diagnose_otherworld import FAMILY_NAME
from steerlab.benchmarks.otherworld import CONVENTIONS, HIDDEN, generate_study
from steerlab.benchmarks.outside_worlds import SMALL
from steerlab.protocols.datafile import load_study
from steerlab.protocols.interchange import import_study

# The families a convention could be mistaken for (timing: lags and delays; the wheel:
# friction) and two of the arm's.
FAMILIES = ("reflex", "friction", "stiffening", "actuator_lag", "sensor_delay")


def study(root: Path, convention: str, mechanisms: list[dict], seed: int, **extra) -> Path:
    generate_study(
        root / "csv", seed=seed, mechanisms=mechanisms, **(SMALL | CONVENTIONS[convention] | extra)
    )
    import_study(root / "csv", root / "sessions")
    shutil.rmtree(root / "csv")
    return root / "sessions"


@pytest.mark.parametrize("convention", sorted(CONVENTIONS))
def test_a_null_study_is_none_under_every_recording_convention(tmp_path, convention):
    res = run_diagnosis(study(tmp_path, convention, [], seed=3), None, candidates=CANDIDATES)
    assert res.cause == "none", res.summary()
    assert res.unexplained["within_noise"], res.unexplained


# The families whose names a convention could take (timing: lags and delays; the wheel: friction),
# and an arm-side one; every family under every convention runs in the slow tier.
CANDIDATES = ("reflex_delay", "coulomb_friction", "actuator_lag", "sensor_delay", "drift")


def test_the_end_of_interval_read_and_a_physical_wheel_are_found_and_taken(tmp_path):
    res = run_diagnosis(study(tmp_path, "physical_wheel_end", [], seed=4), None, candidates=())
    conv = res.rig_from_data["convention"]
    assert conv["rendering"] == "continuous" and conv["source"]["rendering"].startswith("data")
    assert conv["theta_offset_samples"] == 1.0 and conv["torque_offset_samples"] == 1.0
    assert conv["source"]["inertia"] == "rig" and conv["source"]["timing"] == "data"


def test_dry_friction_is_measured_and_does_not_hide_the_convention(tmp_path):
    """A wheel with 0.15 N·m of Coulomb friction, physical, read at the end: the friction is
    stated with its SEM (the diagnosis still names it: it is a mechanism, not the rig's
    convention), and the rendering and timing are found through it."""
    s = study(tmp_path, "physical_wheel_end", [HIDDEN["friction"]], seed=11)
    found = rig_from_data.identify(load_study(s))
    c = found.convention
    assert c.rendering == "continuous"
    assert (c.theta_offset_samples, c.torque_offset_samples) == (1.0, 1.0)
    f = found.fits["continuous/free"]
    assert f.values["coulomb_Nm"] == pytest.approx(0.15, rel=0.05)
    assert 0 < f.sem["coulomb_Nm"] < 0.01
    assert "F_c = 0.15" in found.sentence()


def test_a_lag_under_an_end_read_is_read_beside_the_convention(tmp_path):
    """A 12 ms first-order actuator lag under a physical wheel read at the end: neither wheel
    explains the data until a lag is free; with it the rendering and the reads are found, the
    lag is measured (and left to the mechanisms)."""
    s = study(tmp_path, "physical_wheel_end", [HIDDEN["actuator_lag"]], seed=11)
    found = rig_from_data.identify(load_study(s))
    c = found.convention
    assert c.rendering == "continuous"
    assert (c.theta_offset_samples, c.torque_offset_samples) == (1.0, 1.0)
    lag = found.fits["continuous/lag"]
    assert lag.noise_ratio <= rig_from_data.MAX_NOISE_RATIO
    assert lag.values["lag_s"] == pytest.approx(HIDDEN["actuator_lag"]["tau_s"], rel=0.03)
    assert any("actuator lag of 12" in n for n in c.notes), c.notes
    assert "lag = 1" in found.sentence()


def test_a_fast_loop_averaged_to_the_record_rate_is_a_wheel_between_the_renderings(tmp_path):
    """A 1 kHz loop recorded as the mean of four cycles: the two renderings fit alike, and the
    wheel is taken as the one nearest the rig's inertia with the data's inertia, which to first
    order is the 1 kHz rendering's: I − b·h/2 with h = 1 ms."""
    s = study(tmp_path, "1k_averaged_250", [], seed=3)
    found = rig_from_data.identify(load_study(s))
    c = found.convention
    assert not found.rendering_told
    assert c.rendering == "continuous" and c.source["inertia"] == "data"
    assert c.inertia_kgm2 == pytest.approx(0.3 - 2.0 * 1e-3 / 2, abs=2e-4)


def test_a_stated_convention_is_used_as_stated(tmp_path):
    s = study(tmp_path, "end_of_interval", [], seed=4, state_convention=True)
    res = run_diagnosis(s, None, candidates=())
    conv = res.rig_from_data["convention"]
    assert conv["source"]["timing"] == "stated" and conv["source"]["rendering"] == "stated"
    assert conv["theta_offset_samples"] == 1.0 and conv["rendering"] == "sampled"
    assert res.cause == "none", res.summary()


def test_without_the_rig_from_the_data_the_null_study_is_a_false_alarm(tmp_path, monkeypatch):
    """The counterpart: what makes the outside conventions `none` is the identification."""

    steerlab = {"rendering": "sampled", "theta_offset_samples": 0.0, "torque_offset_samples": 0.0}

    def steerlabs_own(records, *a, **k):
        return rig_from_data.identify(records, *a, **(k | {"stated": steerlab}))

    monkeypatch.setattr("steerlab.analysis.diagnosis.run.identify", steerlabs_own)
    s = study(tmp_path, "physical_wheel_end", [], seed=4)
    res = run_diagnosis(s, None, candidates=())
    assert res.cause == "unexplained", res.summary()


# A lag of the actuator is the command arriving late, an end-of-interval read the outputs read
# late: in the wheel's equation they cancel in part, so the rig and timing are read with a lag
# free where neither wheel explains the data (analysis/rig_from_data.py); every family under
# every convention is named.
MATRIX = [
    (family, convention)
    for convention in sorted(set(CONVENTIONS) - {"steerlab"})
    for family in sorted(FAMILIES)
]


@pytest.mark.slow
@pytest.mark.parametrize("family, convention", MATRIX)
def test_a_hidden_mechanism_is_named_under_another_labs_convention(tmp_path, convention, family):
    res = run_diagnosis(study(tmp_path, convention, [HIDDEN[family]], seed=11), None, jobs=2)
    assert FAMILY_NAME[family] in res.causes[:1], res.summary()
