"""Run lflipse's Experiment/SensoDrive/SensoDriveTest.py (the 2021-05-18 version, 06daaad =
99c4424^, byte-for-byte; deleted later) against SimulatedSensoDrive over udp_loopback via our
PCAN-Basic stand-in (tools/pcanbasic_standin): importing it runs it: its last lines build the
tester and call do() (1000 cycles at 100 Hz). Its `from PCANBasic import *` finds the stand-in
first on sys.path.

usage: run_lflipse_test.py [--clients DIR] [--out DIR]

Writes into --out: lflipse-test-run.txt (the report), lflipse-test-run-frames.csv and
lflipse-test-run-status.json (every frame on the bus and the node's status, from run_sim.py).
"""

import argparse
import contextlib
import importlib.util
import io
import time
import uuid
from collections import Counter

from common import add_paths, resolve_paths, start_sim, stop_sim, use_standin
from summarise import summarise


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    add_paths(ap)
    clients, outdir = resolve_paths(ap.parse_args(), "lflipse/SensoDriveTest_LT.py")
    client = clients / "lflipse" / "SensoDriveTest_LT.py"

    channel = f"lt-{uuid.uuid4().hex[:8]}"
    use_standin(channel)  # its `from PCANBasic import *`
    out = outdir / "lflipse-test-run"
    sim = start_sim(channel, out, ["--dt", "0.01"])
    spec = importlib.util.spec_from_file_location("SensoDriveTest", client)
    mod = importlib.util.module_from_spec(spec)
    buf = io.StringIO()
    t0 = time.monotonic()
    with contextlib.redirect_stdout(buf):
        spec.loader.exec_module(mod)
    dur = time.monotonic() - t0
    stop_sim(sim)
    lines = buf.getvalue().splitlines()
    report = [
        f"do() took {dur:.2f} s; client printed {len(lines)} lines; first 12: {lines[:12]}",
        f"ids the client printed per cycle: {Counter(x for x in lines if x.isdigit())}",
        summarise(out),
    ]
    text = "\n".join(report)
    (outdir / "lflipse-test-run.txt").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
