"""An independent wheel simulator for the rig-check tests: the continuous-time model through
``scipy.integrate.solve_ivp``, sampled at jittered instants with gaps, written in the interchange
CSV format. It shares no code with ``hardware/sim`` or ``analysis/rigcheck``.

Model (docs/rig-check.md): the loop commands T_p − b·ω − k·θ, the actuator applies it through a
first-order lag τ, and the wheel has inertia I, dry friction F_c·tanh(ω/ε), an imbalance
G·sin θ and a constant torque T_0; the loop here is continuous (no sample-and-hold).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp


@dataclass(frozen=True)
class Truth:
    inertia: float = 0.32
    damping: float = 2.3
    stiffness: float = 3.9
    coulomb: float = 0.08
    gravity: float = 0.25
    lag: float = 0.004
    eps: float = 0.01
    offset: float = 0.05  # a constant torque on the wheel (a command bias)


@dataclass
class Trajectory:
    t: np.ndarray  # sample instants, s
    tp: np.ndarray  # commanded perturbation torque at those instants, N·m
    angle: np.ndarray  # true angle, rad
    velocity: np.ndarray  # true velocity, rad/s


def jittered_times(rng, t0: float, duration: float, gaps=((8.0, 0.040), (15.5, 0.025))):
    """Steps uniform in 1.5–3 ms, plus a gap of the given length after the given times."""
    steps = rng.uniform(1.5e-3, 3.0e-3, int(duration / 1.5e-3) + 10)
    t = t0 + np.concatenate(([0.0], np.cumsum(steps)))
    for after, length in gaps:
        t[t > t0 + after] += length
    return t[t <= t0 + duration]


def multisine(rng, n: int = 14, sd_nm: float = 2.0):
    f = np.sort(rng.uniform(0.07, 2.5, n))
    ph = rng.uniform(0, 2 * np.pi, n)
    a = np.ones(n)
    a *= sd_nm / np.sqrt(np.sum(a**2) / 2)
    return lambda t: np.sum(
        a[:, None] * np.sin(2 * np.pi * f[:, None] * np.atleast_1d(t) + ph[:, None]), axis=0
    )


def simulate(truth: Truth, t: np.ndarray, tp_of) -> Trajectory:
    I, b, k, fc, g, tau, eps, t0 = (truth.inertia, truth.damping, truth.stiffness, truth.coulomb,
                                    truth.gravity, truth.lag, truth.eps, truth.offset)  # fmt: skip

    def rhs(time, x):
        th, om, T = x
        cmd = tp_of(time)[0] - b * om - k * th
        return [om, (T + t0 - fc * np.tanh(om / eps) - g * np.sin(th)) / I, (cmd - T) / tau]

    th0, om0 = 0.15, -0.3  # arbitrary start: mid-motion, at an arbitrary phase of T_p
    x0 = [th0, om0, tp_of(t[0])[0] - b * om0 - k * th0]
    sol = solve_ivp(rhs, (t[0], t[-1]), x0, method="LSODA", t_eval=t, rtol=1e-10, atol=1e-12)
    assert sol.success, sol.message
    return Trajectory(t, tp_of(t), sol.y[0], sol.y[1])


def write_csv(path, traj: Trajectory, angle: np.ndarray, velocity: np.ndarray | None) -> None:
    cols = {"time_s": traj.t, "perturbation_torque_Nm": traj.tp, "wheel_angle_rad": angle}
    if velocity is not None:
        cols["wheel_velocity_rad_s"] = velocity
    with open(path, "w") as fh:
        fh.write(",".join(cols) + "\n")
        for row in zip(*cols.values(), strict=True):
            fh.write(",".join(f"{v:.12g}" for v in row) + "\n")
