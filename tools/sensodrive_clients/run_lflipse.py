"""Run lflipse's SensoDrive client (gt-state-feedback-observer,
Controller_Design/SensoDrive/SensoDriveMultiprocessing.py, byte-for-byte as published, with its
own Lowpassfilter_Biquad.py) against SimulatedSensoDrive in another process over udp_loopback,
through our PCAN-Basic stand-in (tools/pcanbasic_standin). Stubbed: the package names it imports
from, and its controller (an object with compute_control_input returning a torque step).

usage: run_lflipse.py [--clients DIR] [--out DIR] [--numpy1 DIR | --system-numpy]
                      [run_sim.py options, e.g. --watchdog S]

The client was written for NumPy 1.x (with NumPy 2 it stops in its own map_si_to_sensodrive:
"only 0-dimensional arrays can be converted"). When the running NumPy is 2.x, this script
re-runs itself with --numpy1 (default CLIENTS/np1, installed there by fetch.sh) first on
PYTHONPATH, as `PYTHONPATH=CLIENTS/np1 python run_lflipse.py` would; the simulated drive keeps
Steerlab's NumPy. --system-numpy skips that (to see the NumPy 2 failure).

Writes into --out: lflipse-run.txt (the report), lflipse-run-frames.csv and
lflipse-run-status.json (every frame on the bus and the node's status, from run_sim.py) and
lflipse-reads.json (every successful Read of the client: monotonic time, id, data).
"""

import argparse
import importlib.util
import json
import multiprocessing as mp
import os
import sys
import time
import types
import uuid
from pathlib import Path

import numpy as np
from common import add_paths, resolve_paths, start_sim, stop_sim, use_standin
from summarise import summarise

PKG = "Controller_Design.SensoDrive"


def load(name, path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def with_numpy1(np1):
    """Re-run this script with np1 first on PYTHONPATH (once: not if it is there already)."""
    path = os.environ.get("PYTHONPATH", "")
    if path.split(os.pathsep)[0] == str(np1):
        return
    if not (np1 / "numpy").is_dir():
        print(
            f"warning: NumPy {np.__version__} and no NumPy 1.x in {np1} (fetch.sh installs it): "
            "the client is expected to fail",
            flush=True,
        )
        return
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(np1), path) if p))
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)


def record_reads(pcanbasic, path):
    """Record every successful Read the client makes (in its own process), without touching
    the client; written at Uninitialize."""
    reads = []
    orig_read = pcanbasic.PCANBasic.Read
    orig_uninit = pcanbasic.PCANBasic.Uninitialize

    def read(self, ch):
        r = orig_read(self, ch)
        if r[0] == 0:
            reads.append((time.monotonic(), r[1].ID, bytes(r[1].DATA[:8]).hex()))
        return r

    def uninit(self, ch):
        with open(path, "w") as f:
            json.dump(reads, f)
        return orig_uninit(self, ch)

    pcanbasic.PCANBasic.Read = read
    pcanbasic.PCANBasic.Uninitialize = uninit


class StepController:
    """0.5 N·m (the client's direction) from 1.0 s to 2.0 s after its first call."""

    def __init__(self):
        self.t0 = None

    def compute_control_input(self, states, condition):
        now = time.monotonic()
        self.t0 = self.t0 or now
        tau = 0.5 if 1.0 <= now - self.t0 < 2.0 else 0.0
        return {"output_torque": tau, "real_torque": tau, "robot_gain": np.array([[0.0, 0.0]])}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    add_paths(ap)
    ap.add_argument("--numpy1", type=Path, default=None, help="NumPy 1.x (default CLIENTS/np1)")
    ap.add_argument("--system-numpy", action="store_true", help="run with the venv's NumPy")
    args, sim_args = ap.parse_known_args()
    files = ("lflipse/SensoDriveMultiprocessing.py", "lflipse/Lowpassfilter_Biquad.py")
    clients, outdir = resolve_paths(args, *files)
    if not args.system_numpy and int(np.__version__.split(".")[0]) >= 2:
        with_numpy1((args.numpy1 or clients / "np1").resolve())
    client, biquad = (clients / f for f in files)

    channel = f"lfl-{uuid.uuid4().hex[:8]}"
    pcanbasic = use_standin(channel)
    for name in ("Controller_Design", PKG):
        pkg = types.ModuleType(name)
        pkg.__path__ = []
        sys.modules[name] = pkg
    sys.modules[f"{PKG}.PCANBasic"] = pcanbasic
    (outdir / "lflipse-reads.json").unlink(missing_ok=True)  # none left from an earlier run
    record_reads(pcanbasic, outdir / "lflipse-reads.json")
    load(f"{PKG}.Lowpassfilter_Biquad", biquad)
    sdm = load(f"{PKG}.SensoDriveMultiprocessing", client)

    mp.set_start_method("fork")
    out = outdir / "lflipse-run"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # the sim: Steerlab's numpy
    sim = start_sim(channel, out, sim_args, env=env)
    parent, child = mp.Pipe(duplex=True)
    senso_dict = {
        "parent_conn": parent,
        "child_conn": child,
        "controller": StepController(),
        "controller_type": "Manual",
        "damping": 2.0,
        "stiffness": 4.2,
        "beta": 1.0,
        "alpha_1": 1.0,
        "alpha_2": 1.0,
        "initial_human": np.array([0, 0]),
    }
    module = sdm.SensoDriveModule(senso_dict)
    t0 = time.monotonic()
    module.start()
    msg = {
        "ref": np.array([0.0, 0.0]),
        "factor": 1,
        "manual": False,
        "condition": 0,
        "experiment": False,
        "exit": False,
        "reset": False,
        "virtual_human_gain": np.array([0.0, 0.0]),
        "sharing_rule": np.zeros((2, 2)),
        "robot_cost": np.zeros((2, 2)),
    }
    log = []
    while time.monotonic() - t0 < 3.5:
        parent.send(msg)
        if parent.poll(2.0):
            s = parent.recv()
            log.append(
                (
                    time.monotonic() - t0,
                    s["steering_angle"],
                    s["steering_rate"],
                    float(np.ravel(s["torque"])[0]),
                )
            )
        time.sleep(0.01)
    parent.send(dict(msg, exit=True))
    if parent.poll(2.0):
        parent.recv()
    module.join(10)
    exitcode = module.exitcode
    time.sleep(0.3)
    stop_sim(sim)
    reads_file = outdir / "lflipse-reads.json"
    reads = json.loads(reads_file.read_text()) if reads_file.is_file() else []
    report = [
        f"numpy in the client process: {np.__version__}",
        f"client process exit code {exitcode}; {len(reads)} successful Reads, "
        f"ids {sorted({hex(r[1]) for r in reads})}",
        f"client states over the pipe: {len(log)} samples",
    ]
    for t, a, r, tq in log[::30]:
        report.append(
            f"   t={t:.2f} steering_angle={a:+.4f} rad steering_rate(filtered)={r:+.3f} rad/s "
            f"torque cmd={tq:+.3f} N·m"
        )
    report.append(summarise(out))
    text = "\n".join(report)
    (outdir / "lflipse-run.txt").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
