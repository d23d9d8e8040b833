"""Synthetic trials with known truth, for the analysis tests.

The closed loop is the physical one (as in Steerlab's simulated world, written out again here
so the tests do not depend on it):

    I_w θ''   = T_p − b_w θ' − k_w θ − T_d          wheel (paper, Table 1)
    T_d       = k_c (θ − θ_h) + b_c (θ' − θ_h')      torque the wheel exerts on the hands
    I_i θ_h'' = T_d − b_i θ_h' − k_i θ_h + N         arm, remnant torque N on the hands

so θ/T_d is the paper's admittance. The response to the multisine is the exact periodic steady
state (the continuous-time frequency response evaluated at each sine), so noise-free data have
no discretisation error; the remnant's response is simulated with scipy.signal.lsim from rest.
With ``transient=True`` the multisine response is simulated from rest too (start-up included).
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from steerlab.protocols.perturbation import PerturbationDesign, design_multisine
from steerlab.protocols.records import TrialRecord

WHEEL = {"I": 0.3, "b": 2.0, "k": 4.2}
ARM = {"I_i": 0.1, "b_i": 1.0, "k_i": 13.0, "b_c": 2.6, "k_c": 100.0}  # a BT12-like arm

_DESIGN: PerturbationDesign | None = None


def default_design() -> PerturbationDesign:
    global _DESIGN
    if _DESIGN is None:
        _DESIGN = design_multisine()
    return _DESIGN


def admittance(arm: dict, f_hz: np.ndarray) -> np.ndarray:
    """The truth the analysis must recover: θ/T_d of the arm."""
    s = 2j * np.pi * np.asarray(f_hz, dtype=float)
    return 1 / (arm["b_c"] * s + arm["k_c"]) + 1 / (arm["I_i"] * s**2 + arm["b_i"] * s + arm["k_i"])


def closed_loop(arm: dict, wheel: dict = WHEEL) -> signal.StateSpace:
    """Inputs [T_p, N], outputs [θ, T_d]; states [θ, θ', θ_h, θ_h']."""
    I, b, k = wheel["I"], wheel["b"], wheel["k"]
    Ii, bi, ki, bc, kc = arm["I_i"], arm["b_i"], arm["k_i"], arm["b_c"], arm["k_c"]
    A = np.array(
        [
            [0, 1, 0, 0],
            [-(k + kc) / I, -(b + bc) / I, kc / I, bc / I],
            [0, 0, 0, 1],
            [kc / Ii, bc / Ii, -(ki + kc) / Ii, -(bi + bc) / Ii],
        ]
    )
    B = np.array([[0, 0], [1 / I, 0], [0, 0], [0, 1 / Ii]])
    C = np.array([[1, 0, 0, 0], [kc, bc, -kc, -bc]])
    return signal.StateSpace(A, B, C, np.zeros((2, 2)))


def _steady_state(sys: signal.StateSpace, design: PerturbationDesign, t: np.ndarray):
    """Exact periodic response of [θ, T_d] to the multisine at times t (perturbation time)."""
    w = 2 * np.pi * design.frequencies_hz
    n = sys.A.shape[0]
    out = np.zeros((2, len(t)))
    tm = np.mod(t, design.period_s)
    for a, wk, ph in zip(design.amplitudes_nm, w, design.phases_rad, strict=True):
        g = sys.C @ np.linalg.solve(1j * wk * np.eye(n) - sys.A, sys.B[:, 0])
        out += a * np.imag(g[:, None] * np.exp(1j * (wk * tm + ph))[None, :])
    return out[0], out[1]


def make_trial(
    arm: dict | None = None,
    *,
    design: PerturbationDesign | None = None,
    fs_hz: float = 1000.0,
    n_periods: int = 1,
    run_in_s: float = 5.0,
    phase_s: float = 0.0,
    tail_s: float = 0.0,
    remnant_sd: float = 0.0,
    remnant_corner_hz: float = 0.4,
    theta_noise_sd: float = 0.0,
    td_noise_sd: float = 0.0,
    transient: bool = False,
    seed: int = 0,
    known_start: bool = True,
    with_design: bool = True,
    subject: str = "S01",
    condition: str = "BT12",
    repetition: int = 1,
    grip_mean: float = 60.0,
    grip_sd: float = 5.0,
    **record_kw,
) -> TrialRecord:
    """A trial: ``run_in_s`` + ``n_periods`` periods + ``tail_s``; the perturbation starts at
    ``phase_s`` into its period. ``known_start``: set measured_start/stop like the recorder."""
    arm = dict(ARM if arm is None else arm)
    design = design or default_design()
    rng = np.random.default_rng(seed)
    P = int(round(design.period_s * fs_hz))
    n_run = int(round(run_in_s * fs_hz))
    n = n_run + n_periods * P + int(round(tail_s * fs_hz))
    t = np.arange(n) / fs_hz
    sys = closed_loop(arm)
    tp = design.signal(t + phase_s)
    if transient:
        _, y, _ = signal.lsim(sys, np.column_stack([tp, np.zeros(n)]), t)
        theta, td = y[:, 0], y[:, 1]
    else:
        theta, td = _steady_state(sys, design, t + phase_s)
    if remnant_sd > 0:
        a = np.exp(-2 * np.pi * remnant_corner_hz / fs_hz)
        nr = signal.lfilter([1 - a], [1, -a], rng.standard_normal(n))
        nr *= remnant_sd / nr.std()
        _, y, _ = signal.lsim(sys, np.column_stack([np.zeros(n), nr]), t)
        theta = theta + y[:, 0]
        td = td + y[:, 1]
    theta = theta + theta_noise_sd * rng.standard_normal(n)
    td = td + td_noise_sd * rng.standard_normal(n)
    grip = grip_mean + grip_sd * rng.standard_normal(n)
    kw = dict(
        subject=subject,
        condition=condition,
        repetition=repetition,
        familiarization=repetition == 0,
        fs_hz=fs_hz,
        time_s=t,
        perturbation_torque_Nm=tp,
        driver_torque_Nm=td,
        wheel_angle_rad=theta,
        grip_force_N=grip,
        measured_start=n_run if known_start else None,
        measured_stop=n_run + n_periods * P if known_start else None,
        design=design if with_design else None,
        source=f"synthetic:{subject}_{condition}_rep{repetition}_seed{seed}",
    )
    kw.update(record_kw)
    return TrialRecord(**kw)


def load_example(path: str) -> TrialRecord:
    """The shared interchange example, read with numpy as an importer would."""
    import json
    from pathlib import Path

    p = Path(path)
    meta = json.loads(p.with_suffix(".json").read_text())
    with open(p) as fh:
        header = fh.readline().strip().split(",")
    data = np.loadtxt(p, delimiter=",", skiprows=1)
    col = {name: data[:, i] for i, name in enumerate(header)}
    return TrialRecord(
        subject=meta["subject"],
        condition=meta["condition"],
        repetition=int(meta["repetition"]),
        familiarization=bool(meta["familiarization"]),
        fs_hz=float(meta["fs_hz"]),
        time_s=col["time_s"],
        perturbation_torque_Nm=col["perturbation_torque_Nm"],
        driver_torque_Nm=col["driver_torque_Nm"],
        wheel_angle_rad=col["wheel_angle_rad"],
        grip_force_N=col["grip_force_N"],
        trial_index=meta.get("trial_index"),
        source=str(p),
    )


def find_example() -> str | None:
    """The shared interchange example, if this checkout can see it.

    Looked for in $STEERLAB_EXAMPLES, then beside the repository (the team's shared folder).
    """
    import os
    from pathlib import Path

    name = "example_BT12_rep1.csv"
    here = Path(__file__).resolve()
    candidates = []
    if os.environ.get("STEERLAB_EXAMPLES"):
        candidates.append(Path(os.environ["STEERLAB_EXAMPLES"]) / name)
    candidates += [
        here.parents[2] / "docs" / "examples" / "interchange" / name,
        here.parents[3] / "shared" / "examples" / "interchange" / name,
    ]
    for c in candidates:
        if c.is_file():
            return str(c)
    return None
