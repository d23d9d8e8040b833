"""Each safety rule, against hand-computed values, then in a simulated trial."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from steerlab.hardware.can.config import ConfigError
from steerlab.hardware.rig import load_rig
from steerlab.hardware.safety import SafetyLimits, inputs_finite, loop_command, perturbation_gain
from steerlab.hardware.sim.physiology import NOMINAL
from steerlab.hardware.sim.world import World, WorldConfig
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


# -- no non-finite value reaches the motor -------------------------------------------------------


@pytest.mark.parametrize("where", range(6))
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_input_gives_exactly_zero_torque(where, bad):
    args = [1.0, 0.1, 0.2, 0.3, 4.2, 2.0]  # tp, angle, velocity, previous, k, b
    assert loop_command(*args, S) != 0.0
    args[where] = bad
    assert loop_command(*args, S) == 0.0  # not the slew-limited previous 0.3: cut at once
    assert not inputs_finite(*args)


def test_a_non_finite_intermediate_gives_zero_torque():
    # finite inputs whose virtual wheel overflows to inf − inf = NaN
    assert inputs_finite(0.0, 1e308, -1e308, 0.0, 4.2, 2.0)
    assert loop_command(0.0, 1e308, -1e308, 0.0, 4.2, 2.0, S) == 0.0


def test_the_world_kernel_applies_zero_for_a_non_finite_command():
    w = World(WorldConfig(), safety=LIM)
    w.begin_trial(replace(NOMINAL["RT"], remnant_sd_nm=0.0), 0.5, seed=1)
    tp = np.sin(np.arange(2000) / 100.0)
    tp[1000] = math.nan
    out = w.run(tp)
    assert out["motor_command_Nm"][1000] == 0.0 and out["motor_command_Nm"][999] != 0.0
    assert w.nonfinite_commands == 1
    assert all(np.all(np.isfinite(v)) for v in out.values())
    w.step(math.inf)  # the live path's external command as well
    assert w.nonfinite_commands == 2 and math.isfinite(w.read()["motor_torque_Nm"])


def test_a_non_finite_perturbation_aborts_a_batch_trial(short_protocol, tmp_path):
    from steerlab.hardware.sim.physiology import make_population
    from steerlab.hardware.sim.rig import simulated_rig
    from steerlab.protocols.datafile import SessionFile, SessionWriter
    from steerlab.protocols.engine import SessionEngine
    from steerlab.protocols.session import build_plan

    rig = simulated_rig(make_population(2, seed=1)[1], WorldConfig(fs_hz=1000.0))
    loop = rig.batch_loop()
    run = loop.run_trial

    def poisoned(setup, control):  # the protocol's perturbation turns NaN at 2 s
        tp = setup.perturbation_nm.copy()
        tp[2000:] = math.nan
        return run(replace(setup, perturbation_nm=tp), control)

    loop.run_trial = poisoned
    plan = build_plan(short_protocol, 2)
    eng = SessionEngine(replace(plan, trials=plan.trials[:1]), loop)
    eng.subscribe(SessionWriter(tmp_path / "S02.h5"))
    eng.run()
    (r,) = SessionFile(tmp_path / "S02.h5").records()
    assert r.status == "aborted" and "non-finite" in r.abort_reason
    cmd = r.extra["motor_command_Nm"]
    assert np.all(cmd[2000:] == 0.0) and np.all(np.isfinite(cmd))
    assert r.n_samples >= 2000 and np.any(cmd[:2000] != 0.0)


def _numeric_fields(text: str) -> list[tuple[int, str, str]]:
    """(line number, table, key) of every numeric field of a rig file's text."""
    import re

    out, table = [], None
    for i, line in enumerate(text.splitlines()):
        if m := re.match(r"\[([^\]]+)\]", line):
            table = m.group(1)
        elif m := re.match(r"(\w+) = [-+0-9._xX]+\s*(#.*)?$", line):
            out.append((i, table, m.group(1)))
    return out


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_rig_files_reject_non_finite_numbers_naming_file_and_field(tmp_path, bad):
    base = (ROOT / "hardware" / "rigs" / "simulated.toml").read_text()
    fields = _numeric_fields(base)
    assert len(fields) > 30  # every [drive], [safety], glove calibration and [simulation] number
    for i, table, key in fields:
        lines = base.splitlines()
        lines[i] = f"{key} = {bad}"
        p = tmp_path / f"{table}.{key}.toml"
        p.write_text("\n".join(lines))
        with pytest.raises(ConfigError) as e:
            load_rig(p)
        msg = str(e.value)
        assert str(p) in msg and key in msg, (table, key, msg)
