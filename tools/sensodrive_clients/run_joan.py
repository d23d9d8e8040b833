"""Run JOAN's SensoDrive client (tud-hri/joan, joansensodrive.py, byte-for-byte as published)
against SimulatedSensoDrive in another process over udp_loopback, through our PCAN-Basic
stand-in (tools/pcanbasic_standin).

Stubs only what is not CAN: PyQt5 (uic, QtWidgets.QDialog), and the JOAN package names the file
imports; its HardwareInputTypes comes from JOAN's own hardwaremanager_inputtypes.py (unmodified).
The client's PCANBasic import is aliased to the stand-in.

usage: run_joan.py [--develop] [--clients DIR] [--out DIR] [run_sim.py options, e.g. --watchdog S]

--develop runs branch develop (J-D: 2022-12..2023-11, adds 0x20A) instead of master (J-M).
Writes into --out: joan[-develop]-run.txt (the report), -run-frames.csv and -run-status.json
(every frame on the bus and the node's status, from run_sim.py) and -reads.json (every Read
the client made: monotonic time, status, id, data).
"""

import argparse
import importlib.util
import json
import multiprocessing as mp
import queue
import sys
import time
import types
import uuid
from types import SimpleNamespace

from common import add_paths, resolve_paths, start_sim, stop_sim, use_standin
from summarise import summarise

INPUTS = "modules.hardwaremanager.hardwaremanager_inputs"


def load(name, path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def stub_imports(pcanbasic):
    """PyQt5 and JOAN's package names; JOAN's PCANBasic module is the stand-in."""
    pyqt5 = types.ModuleType("PyQt5")
    pyqt5.uic = types.ModuleType("PyQt5.uic")
    pyqt5.uic.loadUi = lambda *a, **k: None
    pyqt5.QtWidgets = types.ModuleType("PyQt5.QtWidgets")
    pyqt5.QtWidgets.QDialog = type("QDialog", (), {"__init__": lambda self, parent=None: None})
    sys.modules.update({"PyQt5": pyqt5, "PyQt5.uic": pyqt5.uic, "PyQt5.QtWidgets": pyqt5.QtWidgets})
    for name in ("modules", "modules.hardwaremanager", INPUTS):
        pkg = types.ModuleType(name)
        pkg.__path__ = []
        sys.modules[name] = pkg
    sys.modules[f"{INPUTS}.PCANBasic"] = pcanbasic


def record_reads(pcanbasic, path):
    """Record every Read the client makes (in its own process), without touching the client;
    written at Uninitialize."""
    reads = []
    orig_read = pcanbasic.PCANBasic.Read
    orig_uninit = pcanbasic.PCANBasic.Uninitialize

    def read(self, ch):
        r = orig_read(self, ch)
        reads.append((time.monotonic(), int(r[0]), r[1].ID, bytes(r[1].DATA[:8]).hex()))
        return r

    def uninit(self, ch):
        with open(path, "w") as f:
            json.dump(reads, f)
        return orig_uninit(self, ch)

    pcanbasic.PCANBasic.Read = read
    pcanbasic.PCANBasic.Uninitialize = uninit


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--develop", action="store_true", help="branch develop (J-D), not master")
    add_paths(ap)
    args, sim_args = ap.parse_known_args()
    suffix = "_develop" if args.develop else ""
    name = "joan-develop" if args.develop else "joan"
    files = (f"joan/joansensodrive{suffix}.py", f"joan/hardwaremanager_inputtypes{suffix}.py")
    clients, outdir = resolve_paths(args, *files)
    client, inputtypes = (clients / f for f in files)

    channel = f"joan-{uuid.uuid4().hex[:8]}"
    pcanbasic = use_standin(channel)
    stub_imports(pcanbasic)
    load("modules.hardwaremanager.hardwaremanager_inputtypes", inputtypes)
    (outdir / f"{name}-reads.json").unlink(missing_ok=True)  # none left from an earlier run
    record_reads(pcanbasic, outdir / f"{name}-reads.json")
    jsd = load(f"{INPUTS}.joansensodrive", client)

    mp.set_start_method("fork")  # the child inherits the stubs (JOAN ran on Windows: spawn)
    out = outdir / f"{name}-run"
    sim = start_sim(channel, out, ["--dt", "0.01", *sim_args])

    settings = jsd.SensoDriveSettings("SensoDrive_1")
    settings.events = SimpleNamespace(
        turn_on_event=mp.Event(),
        turn_off_event=mp.Event(),
        close_event=mp.Event(),
        clear_error_event=mp.Event(),
        state_queue=mp.Queue(),
    )
    shared = SimpleNamespace(
        torque=0.0,
        friction=0.0,
        damping=settings.damping,
        auto_center_stiffness=settings.spring_stiffness,
        loha_stiffness=0.0,
    )
    t0 = time.monotonic()
    proc = jsd.JOANSensoDriveProcess(settings, shared)  # starts SensoDriveComm (its CAN loop)
    log, states = [], []

    def state_now():
        try:
            while True:
                s = settings.events.state_queue.get_nowait()
                if not states or states[-1][1] != s:
                    states.append((round(time.monotonic() - t0, 3), s))
        except queue.Empty:
            pass

    raised = []

    def run_for(seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                proc.do()
            except Exception as exc:  # J-D's "turned off" detection raises from do()
                raised.append((round(time.monotonic() - t0, 3), str(exc)))
            state_now()
            log.append(
                (
                    time.monotonic() - t0,
                    shared.steering_angle,
                    shared.steering_rate,
                    shared.measured_torque,
                    shared.throttle,
                    shared.brake,
                    getattr(shared, "torque_sensor", None),
                )
            )
            time.sleep(0.01)

    time.sleep(0.3)
    run_for(0.2)
    settings.events.turn_on_event.set()  # JOAN's "turn on" button: 0x10, 0x12, 0x14
    run_for(1.0)
    shared.torque = 0.5  # 0.5 N·m in JOAN's (drive's) direction
    run_for(1.0)
    shared.torque = 0.0
    run_for(0.5)
    settings.events.turn_off_event.set()  # "turn off": 0x12, 0x10
    run_for(0.5)
    settings.events.close_event.set()
    last = proc.parent_pipe.recv() if proc.parent_pipe.poll(2) else None
    time.sleep(0.3)
    state_now()
    stop_sim(sim)
    report = [
        f"JOAN client states seen (t s, state byte): {[(t, hex(s)) for t, s in states]}",
        f"JOAN shared variables: {len(log)} do() calls",
        f"do() raised {len(raised)} times; first: {raised[:1]}; last: {raised[-1:]}",
    ]
    for t, a, r, tq, th, br, ts in log[::25]:
        report.append(
            f"   t={t:.2f} angle={a:+.4f} rad rate={r:+.3f} rad/s measured_torque={tq:+.3f} N·m "
            f"throttle={th:.2f} brake={br:.2f} torque_sensor={ts}"
        )
    report.append(f"last values over the pipe at close: {last}")
    report.append(summarise(out))
    text = "\n".join(report)
    (outdir / f"{name}-run.txt").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
