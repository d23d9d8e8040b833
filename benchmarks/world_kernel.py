"""The simulated world's compiled kernel (``hardware.sim.world._advance``): CPU time of one
trial's ``World.run`` per simulated sample, for the mechanisms the diagnosis simulates most.

Each run is one trial in the way the diagnosis runs its simulations
(``analysis.diagnosis.simulate``): a noiseless world at the trial's rate, given its exogenous
signals as one block by the diagnosis's ``ReplayBlocks`` (here a seeded remnant-like torque
and a constant grip), run over
``--seconds`` of a multisine perturbation (from rest, with the default wheel and limits; the
diagnosis starts from the periodic steady state, which changes nothing per sample). Timed:
``World.run`` of ``--runs`` worlds made and started beforehand, the least CPU time
(``time.process_time``, one BLAS thread) of ``--repeats`` tries. ``World.run`` is the kernel
plus its block handling (output arrays allocated and filled); making and starting a world
(``ms_setup_per_run``: the matrix exponential, the noise source) is reported apart.

Last line: one JSON object with, per case and rate, ``ns_per_sample`` and ``ms_per_run`` of
``World.run`` and ``ms_setup_per_run``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.signal import lfilter
from threadpoolctl import threadpool_limits

from steerlab.analysis.diagnosis.simulate import ReplayBlocks
from steerlab.benchmarks.machine import machine
from steerlab.hardware.sim.mechanisms import (
    ActuatorLag,
    CoulombFriction,
    Mechanisms,
    ReflexDelay,
    SensorDelay,
    StiffnessNonlinearity,
)
from steerlab.hardware.sim.physiology import NOMINAL
from steerlab.hardware.sim.world import NOISELESS_SENSORS, World, WorldConfig
from steerlab.protocols.perturbation import design_multisine

CASES = {
    "linear": Mechanisms(),
    "reflex_40ms": Mechanisms(reflex_delay=ReflexDelay(k_p=6.0, k_v=0.5, delay_s=0.04)),
    "coulomb": Mechanisms(coulomb_friction=CoulombFriction(torque_nm=0.15)),
    "stribeck": Mechanisms(coulomb_friction=CoulombFriction(torque_nm=0.15, breakaway_ratio=2.0)),
    "cubic": Mechanisms(stiffness_nonlinearity=StiffnessNonlinearity(k3_nm_per_rad3=200.0)),
    "sensor_delay": Mechanisms(sensor_delay=SensorDelay(delay_s=0.012)),
    "lag_2nd_order": Mechanisms(actuator_lag=ActuatorLag(tau_s=0.012, form="second_order")),
}


def _ready(mech: Mechanisms, fs: float, remnant: np.ndarray) -> World:
    """A world made, started and given its signals: what is left is ``run``."""
    behaviour = NOMINAL["BT12"]
    w = World(WorldConfig(fs_hz=fs, sensors=NOISELESS_SENSORS, mechanisms=mech))
    w.begin_trial(behaviour, 0.5, seed=0)
    w.noise = ReplayBlocks(fs, np.full(len(remnant), behaviour.grip_mean_n), remnant, len(remnant))
    return w


def main(argv: list[str]) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks world_kernel")
    ap.add_argument("--rates", default="250,1000", help="sample rates, Hz (comma-separated)")
    ap.add_argument("--seconds", type=float, default=95.0, help="trial length, s")
    ap.add_argument("--runs", type=int, default=20, help="runs per timing")
    ap.add_argument("--repeats", type=int, default=7, help="timings; the least is reported")
    ap.add_argument("--only", nargs="*", choices=list(CASES), help="cases (default: all)")
    a = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    out: dict[str, dict] = {}
    samples: dict[str, int] = {}
    with threadpool_limits(1):
        for fs in (float(r) for r in a.rates.split(",")):
            n = int(round(a.seconds * fs))
            samples[f"{fs:g} Hz"] = n
            tp = design_multisine().signal(np.arange(n) / fs)
            # A remnant of the simulator's size and bandwidth (AR(1), SD 0.2 N·m, corner 0.6 Hz).
            alpha = np.exp(-2 * np.pi * 0.6 / fs)
            remnant = lfilter([0.2 * np.sqrt(1 - alpha**2)], [1.0, -alpha], rng.standard_normal(n))
            for name in a.only or list(CASES):
                mech = CASES[name]
                _ready(mech, fs, remnant).run(tp)  # compiled and warm
                best, setup = np.inf, np.inf
                for _ in range(a.repeats):
                    c0 = time.process_time()
                    worlds = [_ready(mech, fs, remnant) for _ in range(a.runs)]
                    c1 = time.process_time()
                    for w in worlds:
                        w.run(tp)
                    c2 = time.process_time()
                    setup = min(setup, (c1 - c0) / a.runs)
                    best = min(best, (c2 - c1) / a.runs)
                out.setdefault(name, {})[f"{fs:g} Hz"] = {
                    "ms_per_run": round(best * 1e3, 3),
                    "ns_per_sample": round(best / n * 1e9, 1),
                    "ms_setup_per_run": round(setup * 1e3, 3),
                }
    return {"samples_per_run": samples, "cases": out, "machine": machine()}
