"""The simulated lab devices in a process of their own: the drive node and the grip device,
reached as a lab's host reaches them (a CAN bus shared between processes, ``udp_loopback``, and,
as the rig file's ``[glove] kind`` says, a serial port (a pty) or an LSL stream). The host
(``steerlab run``, :class:`hardware.live.ProcessLoop`) then holds only what it holds in the lab,
and a killed host is a real host kill: the drive goes on and must cut the torque by itself (its
consumer heartbeat 0x1016, abort connection option 0x6007).

Run it as ``python -m hardware.sim.lab --rig RIG.toml --channel NAME`` (the rig file is a
simulated rig's: its ``[drive]``, ``[safety]`` and ``[glove]``). It prints one JSON line
``{"ready": true, "grip": ..., "pty": ..., "channel": ..., "pid": ...}`` (``grip``: where the
host reaches the grip device, :meth:`hardware.grips.GripKind.at`: the pty's path for the glove
unit and a text-line device, which ``pty`` also gives, an LSL stream's source id), then
answers one JSON line per command line on stdin (``{"op": "status"}``,
``{"op": "inject", "fault": NAME}``, ``{"op": "collect"}``: a full garbage collection, timed,
``{"op": "close"}``); end of stdin closes it. :class:`LabProcess` is the parent's handle and
:func:`host_rig_text` writes the host's rig file for it.

The world behind the motor shaft is, by default, a wheel (Table 1's 0.3 kg·m²) held by a relaxed
hand (a spring and a damper, whose torque is the column torque): enough to see torque and motion
at the drive (the fault tests). With ``--subject N`` it is the simulated rig's full world with
subject N of its population (``steerlab run`` on a simulated rig: :class:`hardware.live.ProcessLoop`
starts this process), and a sensor node if the rig names one. The host's loop then tells it
about each trial and the sensor zeroing over a control socket (:class:`LabClient`: the trial's
setup, "the subject lets go", "the subject holds again"), the way an experimenter would tell a
person; nothing of the simulation runs in the loop's process.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import re
import secrets
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from multiprocessing.connection import Client, Listener
from pathlib import Path

from steerlab.hardware.can.config import UDP_LOOPBACK
from steerlab.hardware.can.transport import open_bus
from steerlab.hardware.drives import on_bus
from steerlab.hardware.sim.devices import simulated_devices
from steerlab.protocols.session import TrialSetup

#: Faults of Steerlab's glove unit; the drive's own come from its kind
#: (``SimulatedDriveNode.faults``), another grip kind's from its device (``SimulatedGrip.faults``:
#: ``glove_stop`` and ``glove_hang_up`` for every kind, the LSL outlet destroyed for the latter).
GLOVE_FAULTS = (
    "glove_hang_up",  # the glove's serial port closes
    "glove_stop",  # the glove stream stops
    "crc_storm",  # 200 glove frames with a bad CRC
)


#: Environment variable that carries the control socket's key from parent to lab process.
AUTHKEY_ENV = "STEERLAB_LAB_AUTHKEY"


class SimulatedLab:
    """The simulated drive (of the rig's kind) and grip device (of its ``[glove]`` kind) of a
    simulated rig file, the drive on ``channel`` (udp_loopback); with ``subject``, the rig's
    full simulated world with that subject of its population
    (:func:`hardware.sim.devices.simulated_devices`)."""

    def __init__(self, rig_path: str | None, channel: str, subject: int | None = None) -> None:
        from steerlab.hardware.rig import load_rig

        rig = load_rig(rig_path)
        if subject is not None and rig.simulation is None:
            raise ValueError(f"{rig.source}: --subject needs a simulated rig ([simulation])")
        self.config = on_bus(rig.drive, UDP_LOOPBACK, channel)
        self.devices = simulated_devices(
            rig,
            lambda: open_bus(self.config, filtered=False),
            subject=subject,
            drive_config=self.config,
        )
        self.physiology = self.devices.physiology
        self.world = self.devices.world  # the subject's world, or None
        self.plant = self.devices.plant
        self.node = self.devices.drive
        self.glove = self.devices.glove
        self._listener: Listener | None = None

    @property
    def faults(self) -> tuple[str, ...]:
        return (*self.node.faults, *self.glove.faults)

    # -- the host's loop tells the simulated subject about the trial (control socket) --------
    def serve(self, authkey: bytes) -> str:
        """Listen for :class:`LabClient` connections on a private Unix socket; its address."""
        where = tempfile.mkdtemp(prefix="steerlab-lab-")  # mode 0700: ours alone
        self._listener = Listener(os.path.join(where, "control"), "AF_UNIX", authkey=authkey)
        threading.Thread(target=self._accept, name="lab-control", daemon=True).start()
        return self._listener.address

    def _accept(self) -> None:
        while True:
            listener = self._listener
            if listener is None:
                return
            try:
                conn = listener.accept()
            except Exception:  # closed, or a client with the wrong key
                if self._listener is None:
                    return
                continue
            threading.Thread(target=self._answer, args=(conn,), daemon=True).start()

    def _answer(self, conn) -> None:
        with conn:
            while True:
                try:
                    op, *args = conn.recv()
                except (EOFError, OSError):
                    return
                try:
                    conn.send(("ok", self.control(op, *args)))
                except Exception as e:  # a bad request must not take the devices down
                    conn.send(("error", f"{type(e).__name__}: {e}"))

    def control(self, op: str, *args: object) -> object:
        w = self.world
        if op == "physiology":
            return self.physiology
        if w is None:
            raise ValueError(f"{op!r}: this lab has no simulated subject (start it with --subject)")
        if op == "begin_trial":
            setup = args[0]
            if not isinstance(setup, TrialSetup):
                raise TypeError(f"begin_trial: a TrialSetup, not {type(setup).__name__}")
            w.begin_trial(setup)
        elif op == "release":  # the subject lets go (sensor zeroing)
            w.released = True
        elif op == "hold":
            w.released = False
        else:
            raise ValueError(f"unknown control op {op!r}")
        return None

    def status(self) -> dict:
        # this process's CPU, user + system
        return {"t": time.monotonic(), **self.node.status(), "cpu_s": sum(os.times()[:2])}

    def inject(self, fault: str) -> None:
        if fault in self.glove.faults:
            self.glove.inject(fault)
        elif fault in self.node.faults:
            self.node.inject(fault)
        else:
            raise ValueError(f"unknown fault {fault!r} (known: {', '.join(self.faults)})")

    def close(self) -> None:
        listener, self._listener = self._listener, None
        # Read before the close: a closed Listener has no address (AttributeError).
        address = listener.address if listener is not None else None
        self.devices.close()
        if listener is not None:
            try:
                listener.close()
            except Exception:
                pass
        _remove_control_folder(address)


def _remove_control_folder(address: str | None) -> None:
    """The private folder :meth:`SimulatedLab.serve` made for its socket, once it is closed
    (hundreds of them had gathered in /tmp from test runs)."""
    if not address:
        return
    folder = os.path.dirname(address)
    if os.path.basename(folder).startswith("steerlab-lab-"):
        shutil.rmtree(folder, ignore_errors=True)


class LabClient:
    """The host loop's side of the lab's control socket (:meth:`SimulatedLab.serve`)."""

    def __init__(self, address: str, authkey: bytes) -> None:
        self._conn = Client(address, "AF_UNIX", authkey=authkey)
        self._lock = threading.Lock()

    def call(self, op: str, *args: object) -> object:
        with self._lock:
            self._conn.send((op, *args))
            kind, value = self._conn.recv()
        if kind != "ok":
            raise RuntimeError(f"simulated lab: {op}: {value}")
        return value

    def close(self) -> None:
        try:
            self._conn.close()
        except OSError:
            pass


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m hardware.sim.lab", description=__doc__)
    ap.add_argument("--rig", default=None, help="a simulated rig file (default: the shipped one)")
    ap.add_argument("--channel", required=True, help="udp_loopback channel name")
    ap.add_argument(
        "--subject", type=int, help="simulate subject N of the rig's population (full world)"
    )
    args = ap.parse_args(argv)
    from steerlab.hardware.realtime import tune_process

    lab = SimulatedLab(args.rig, args.channel, args.subject)
    # The drive node answers each SYNC within the host's TPDO timeout (0.8 ms). A full garbage
    # collection walks every object of the process (a subject's world: about 150 000) holding
    # the GIL: 50-80 ms without an answer, and 20 unanswered SYNCs end the host's trial. What is
    # built now lives as long as the process; frozen, collections walk only what comes later.
    gc.collect()
    gc.freeze()
    # Once built (seconds of CPU for a subject's world): the drive node answers each SYNC, so
    # its threads get what the host may have.
    tune_process()
    key = os.environ.pop(AUTHKEY_ENV, "")
    control = lab.serve(bytes.fromhex(key)) if key else None
    out = sys.stdout

    def say(obj: dict) -> None:
        out.write(json.dumps(obj) + "\n")
        out.flush()

    try:
        say(
            {
                "ready": True,
                "grip": lab.glove.address,
                "pty": getattr(lab.glove, "port", None),  # a grip device on a pty
                "channel": args.channel,
                "pid": os.getpid(),
                "control": control,
            }
        )
        for line in sys.stdin:
            try:
                cmd = json.loads(line)
                op = cmd.get("op")
                if op == "status":
                    say(lab.status())
                elif op == "inject":
                    t = time.monotonic()
                    lab.inject(cmd["fault"])
                    say({"t": t, "injected": cmd["fault"]})
                elif op == "collect":
                    t = time.perf_counter()
                    gc.collect()
                    say({"collect_ms": (time.perf_counter() - t) * 1e3})
                elif op == "close":
                    say({"closed": True})
                    break
                else:
                    say({"error": f"unknown op {op!r}"})
            except Exception as e:  # a bad command must not take the devices down
                say({"error": f"{type(e).__name__}: {e}"})
    finally:
        lab.close()
    return 0


class LabProcess:
    """Parent's handle on ``python -m steerlab.hardware.sim.lab`` (see the module docstring)."""

    def __init__(
        self,
        rig_path: str | None = None,
        *,
        subject: int | None = None,
        start_timeout_s: float = 60.0,
    ) -> None:
        self.channel = f"steerlab-lab-{uuid.uuid4().hex[:12]}"
        self.authkey = secrets.token_bytes(16)
        import steerlab

        # The folder that holds the steerlab package (the checkout, or site-packages), so the
        # child imports the same code whether or not it was installed.
        root = Path(steerlab.__file__).resolve().parents[1]
        cmd = [sys.executable, "-m", "steerlab.hardware.sim.lab", "--channel", self.channel]
        if rig_path is not None:
            cmd += ["--rig", str(Path(rig_path).resolve())]
        if subject is not None:
            cmd += ["--subject", str(int(subject))]
        from steerlab.hardware.realtime import SINGLE_THREADED_MATH

        self.proc = subprocess.Popen(
            cmd,
            cwd=root,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            bufsize=1,
            env={**os.environ, **SINGLE_THREADED_MATH, AUTHKEY_ENV: self.authkey.hex()},
        )
        assert self.proc.stdin is not None and self.proc.stdout is not None  # PIPE, PIPE
        self._stdin, self._stdout = self.proc.stdin, self.proc.stdout
        self._lock = threading.Lock()
        ready = self._read(start_timeout_s)
        if not ready.get("ready"):
            self.close()
            raise RuntimeError(f"the simulated lab did not come up: {ready}")
        #: where the host reaches the grip device (hardware.grips.GripKind.at)
        self.grip: str = ready["grip"]
        #: the grip device's pty (the glove unit, a text-line device), or None (an LSL stream)
        self.pty: str | None = ready["pty"]
        self.pid = ready["pid"]
        self.control_address: str | None = ready.get("control")

    def _read(self, timeout_s: float) -> dict:
        result: list[str] = []
        t = threading.Thread(target=lambda: result.append(self._stdout.readline()))
        t.daemon = True
        t.start()
        t.join(timeout_s)
        if not result or not result[0]:
            return {"error": f"no answer within {timeout_s} s (exit {self.proc.poll()})"}
        return json.loads(result[0])

    def ask(self, op: str, timeout_s: float = 10.0, **kw: object) -> dict:
        with self._lock:
            self._stdin.write(json.dumps({"op": op, **kw}) + "\n")
            self._stdin.flush()
            return self._read(timeout_s)

    def status(self) -> dict:
        return self.ask("status")

    def inject(self, fault: str) -> float:
        """Inject ``fault`` in the lab process; returns the time.monotonic() it was done."""
        return self.ask("inject", fault=fault)["t"]

    def wait_zero_torque(self, timeout_s: float = 5.0) -> dict:
        """Poll until the drive applies zero torque (or the timeout); the last status."""
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.status()
            if st.get("applied_torque_nm") == 0.0 or time.monotonic() > deadline:
                return st
            time.sleep(0.01)

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.ask("close", timeout_s=5.0)
            except (OSError, ValueError):
                pass
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        for f in (self._stdin, self._stdout):
            try:
                f.close()
            except OSError:
                pass
        # A lab that was killed left its socket's folder behind.
        _remove_control_folder(getattr(self, "control_address", None))

    def __enter__(self) -> LabProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _set_glove_source_id(text: str, source_id: str) -> tuple[str, int]:
    """``text`` with ``[glove] source_id`` set (replaced where the rig file gives one: a TOML
    key may not appear twice), and how many ``[glove]`` tables there were."""
    line = f'source_id = "{source_id}"'
    table = re.compile(r"(?ms)^(\[glove\][^\n]*\n)(.*?)(?=^\[|\Z)")

    def put(m: re.Match[str]) -> str:
        body, n = re.subn(r"(?m)^source_id\s*=.*$", line, m.group(2))
        return m.group(1) + (body if n else f"{line}\n{body}")

    return table.subn(put, text)


def host_rig_text(lab: LabProcess, simulated_rig_text: str) -> str:
    """The host's rig file for ``lab``: the simulated rig's text with the drive on the lab's
    udp_loopback channel, the grip device where the lab has it (the glove's ``port`` its pty;
    an LSL stream's ``source_id``) and no ``[simulation]`` table (the host sees a lab)."""
    text = simulated_rig_text.split("\n[simulation]")[0]
    text, n1 = re.subn(r'(?m)^interface = "virtual"', f'interface = "{UDP_LOOPBACK}"', text)
    text, n2 = re.subn(r'(?m)^channel = "[^"]*"', f'channel = "{lab.channel}"', text)
    if lab.pty is not None:
        text, n3 = re.subn(r'(?m)^port = "simulated"', f'port = "{lab.pty}"', text)
    else:
        text, n3 = _set_glove_source_id(text, lab.grip)
    if (n1, n2, n3) != (1, 1, 1):
        raise ValueError("not a simulated rig file's text (interface, channel, [glove] port)")
    return text


if __name__ == "__main__":
    sys.exit(main())
