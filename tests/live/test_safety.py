"""Each safety rule, against hand-computed values, then in a simulated trial."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hardware.can.config import ConfigError
from hardware.rig import load_rig
from hardware.safety import SafetyLimits, loop_command, perturbation_gain
from hardware.sim.physiology import NOMINAL
from hardware.sim.world import World, WorldConfig
from tests.helpers import ROOT

LIM = SafetyLimits(
    max_torque_nm=8.0,
    max_slew_nm_per_s=400.0,
    soft_angle_limit_deg=90.0,
    fade_zone_deg=15.0,
    brake_damping_nms_per_rad=5.0,
)
S = LIM.kernel_vector(1000.0)


def test_renders_the_virtual_wheel_inside_the_limits():
    # tp − b·ω − k·θ, nothing clipped.
    assert loop_command(1.0, 0.1, 0.2, 0.2, 4.2, 2.0, S) == pytest.approx(1.0 - 0.4 - 0.42)


def test_saturation():
    big = loop_command(50.0, 0.0, 0.0, 7.9, 4.2, 2.0, S)
    assert big == pytest.approx(8.0)
    assert loop_command(-50.0, 0.0, 0.0, -7.9, 4.2, 2.0, S) == pytest.approx(-8.0)


def test_slew_limit_per_cycle():
    # From 0 to a 5 N·m request: at most 400 N·m/s × 1 ms = 0.4 N·m per cycle.
    assert loop_command(5.0, 0.0, 0.0, 0.0, 4.2, 2.0, S) == pytest.approx(0.4)
    assert loop_command(-5.0, 0.0, 0.0, 1.0, 4.2, 2.0, S) == pytest.approx(0.6)


def test_soft_angle_limit_fades_perturbation_and_brakes():
    lim, zone = math.radians(90), math.radians(15)
    assert perturbation_gain(math.radians(70), lim, zone) == 1.0
    assert perturbation_gain(math.radians(82.5), lim, zone) == pytest.approx(0.5)
    assert perturbation_gain(math.radians(-82.5), lim, zone) == pytest.approx(0.5)
    assert perturbation_gain(math.radians(95), lim, zone) == 0.0
    th = math.radians(95)
    # Beyond the limit moving outward: no perturbation, spring + damper + brake.
    # (previous commands near the result, so that the slew limit does not bind)
    # (no virtual spring here, so that neither saturation nor slew binds)
    out = loop_command(3.0, th, 0.5, -3.4, 0.0, 2.0, S)
    assert out == pytest.approx(-2.0 * 0.5 - 5.0 * 0.5)
    # Moving back inward: no brake.
    back = loop_command(3.0, th, -1.0, 1.9, 0.0, 2.0, S)
    assert back == pytest.approx(2.0)


def test_limits_hold_in_a_simulated_trial_with_an_excessive_perturbation():
    """A perturbation 10× too strong on a relaxed arm: every rule engages, none is broken."""
    w = World(WorldConfig(), safety=LIM)
    w.begin_trial(replace(NOMINAL["RT"], remnant_sd_nm=0.0), 0.5, seed=1)
    t = np.arange(20000) / 1000.0
    tp = 40.0 * np.sin(2 * np.pi * 0.1 * t) * np.minimum(1.0, t)  # slow and huge
    out = w.run(tp)
    cmd = out["motor_command_Nm"]
    assert np.max(np.abs(cmd)) <= 8.0 + 1e-12
    assert np.max(np.abs(np.diff(cmd))) <= 0.4 + 1e-12
    assert np.max(np.abs(cmd)) == pytest.approx(8.0)  # saturation did engage
    ang = np.degrees(np.abs(out["wheel_angle_rad"]))
    assert ang.max() < 120  # braked: the wheel does not run away past the soft limit


def test_rig_file_errors_name_file_section_and_field(tmp_path):
    base = (ROOT / "hardware" / "rigs" / "simulated.toml").read_text()
    cases = {
        "glove port": (base.replace('port = "simulated"', "port = 3"), r"\[glove\] port"),
        "calibration": (
            base.replace(
                "gain_n_per_count = 0.01\noffset_counts = 0\n[glove.calibration.right]",
                "offset_counts = 0\n[glove.calibration.right]",
            ),
            r"\[glove.calibration\].*gain_n_per_count",
        ),
        "safety": (base.replace("max_torque_nm = 8.0", "max_torque_nm = -1"), r"\[safety\]"),
        "stall": (base.replace("loop_stall_s = 0.02", "loop_stall_s = 0"), r"loop_stall_s"),
        "unknown table": (base + "\n[displayy]\nx = 1\n", r"displayy.*unknown table"),
        "simulation": (base.replace("seed = 0  ", "seedd = 0  "), r"\[simulation\] seedd"),
        "drive field": (base.replace("node_id = 1 ", "node_idd = 1 "), r"\[drive\] node_idd"),
    }
    for name, (text, pattern) in cases.items():
        p = tmp_path / f"{name.replace(' ', '_')}.toml"
        p.write_text(text)
        assert text != base, name
        with pytest.raises(ConfigError, match=pattern) as e:
            load_rig(p)
        assert str(p) in str(e.value), name


def test_the_shipped_rig_file_loads():
    rig = load_rig()
    assert rig.simulated and rig.glove.simulated and rig.loop_rate_hz == 1000
    assert rig.safety.max_torque_nm == 8.0 and rig.safety.soft_angle_limit_deg == 90.0
