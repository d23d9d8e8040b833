"""The live path: a rig's devices, and the 1 kHz control loop in a process of its own.

:class:`RigDevices` opens what a rig file names: the drive of its kind on its CAN bus and the
grip source of its kind (the glove unit on its serial port, an LSL stream, a text-line device).
For the simulated rig, the same drivers talk to a simulated drive node (hosting the simulated
world) and to a simulated grip device of the same kind (a pseudo-terminal fed by the simulated
glove unit, an LSL outlet, ...): every byte and frame is the lab's. :class:`ProcessLoop` runs
those simulated devices in a process of their own (``hardware.sim.lab``, over the
``udp_loopback`` bus), so that the loop's process holds only what it holds in the lab;
``RigDevices`` built directly on a simulated rig file hosts them in its own process
(python-can's virtual bus), for tests.

:class:`ProcessLoop` is the engine's :class:`protocols.engine.TrialLoop` for a real-time rig. The
control loop runs in a separate process, so the session file writer and the GUI, which run in
the engine's process, never hold it up (Python runs one thread at a time per process). Blocks of
samples come back through a pipe that the loop process's death cannot leave half-read
(:mod:`hardware.messages`); pause, abort and the emergency stop go the other way, the
emergency stop through a shared event that the loop checks every cycle.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import queue
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import TYPE_CHECKING

import can
import numpy as np

from steerlab.hardware.can.errors import DriveError
from steerlab.hardware.drives import drive_kind, on_bus
from steerlab.hardware.grip.reader import GripSourceError
from steerlab.hardware.grips import grip_kind
from steerlab.hardware.interfaces import ColumnTorque, GripSource, RigDrive
from steerlab.hardware.loop import BLOCK_CHANNELS, DEFAULT_BLOCK_S, SPIN_S, DeviceLoop
from steerlab.hardware.messages import Outbox, WriterGone, message_pipe
from steerlab.hardware.rig import RigConfig, load_rig
from steerlab.protocols.engine import LoopControl, TrialFault
from steerlab.protocols.session import TrialSetup

if TYPE_CHECKING:
    from steerlab.hardware.sim.devices import SimulatedDevices

ZEROING_S = 0.3


class RigError(RuntimeError):
    """The rig could not be brought up; the message says which device and why."""


class RigDevices:
    """Everything a rig file names, opened and ready; ``close()`` releases it all.

    The drive is of the kind the rig file names (:mod:`hardware.drives`); for a simulated rig
    file, the simulated devices (:func:`hardware.sim.devices.simulated_devices`) are built here
    too, on python-can's virtual bus and a pty, and the same drivers talk to them.

    ``lab``: the control socket of a simulated lab process (``hardware.sim.lab.LabClient``) whose
    devices ``rig`` (a lab's rig: udp_loopback channel, pty) reaches; the trial's setup and the
    sensor zeroing's "let go" are passed on to its simulated subject."""

    # Set once opened: a RigDevices that exists has both (close() also sees a partial one).
    drive: RigDrive
    glove: GripSource  # of the rig's [glove] kind (hardware.grips)

    def __init__(self, rig: RigConfig, *, subject_number: int = 1, lab=None) -> None:
        self.rig = rig
        self.lab = lab
        self.simulated: SimulatedDevices | None = None
        self.physiology: dict | None = None
        self.hands_off = False  # the current trial is a rig check's: no gloves needed
        drive_cfg = rig.drive
        glove_cfg = rig.glove
        grips = grip_kind(glove_cfg.kind)
        try:
            if rig.simulated:
                from steerlab.hardware.sim.devices import simulated_devices

                # A channel of its own: two simulated rigs in one process must not cross-talk.
                drive_cfg = on_bus(
                    drive_cfg, "virtual", f"{drive_cfg.channel}-{uuid.uuid4().hex[:8]}"
                )
                channel = drive_cfg.channel
                self.simulated = simulated_devices(
                    rig,
                    lambda: can.Bus(
                        interface="virtual", channel=channel, receive_own_messages=False
                    ),
                    subject=subject_number,
                    drive_config=drive_cfg,
                )
                self.physiology = self.simulated.physiology
                glove_cfg = grips.at(glove_cfg, self.simulated.glove.address)
            if lab is not None:
                self.physiology = lab.call("physiology")
            self.drive_config = drive_cfg
            self.glove_config = glove_cfg
            self.drive = drive_kind(drive_cfg.kind).open(drive_cfg)
            try:
                self.glove = grips.open(glove_cfg)
            except GripSourceError as e:  # it names the device and what is wrong
                raise RigError(str(e)) from None
        except BaseException:
            self.close()
            raise

    @property
    def plant(self):
        """The simulated world behind a simulated rig's drive (None for a lab's devices)."""
        return self.simulated.plant if self.simulated is not None else None

    @property
    def node(self):
        """The simulated drive of a simulated rig (None for a lab's devices)."""
        return self.simulated.drive if self.simulated is not None else None

    @property
    def glove_sim(self):
        """The simulated grip device of a simulated rig, of its [glove] kind (None for a lab's
        devices)."""
        return self.simulated.glove if self.simulated is not None else None

    @property
    def sensor_node(self):
        """A simulated rig's own torque sensor node, if its kind has one (None otherwise)."""
        return getattr(self.node, "sensor_node", None)

    @property
    def torque_sensor(self) -> ColumnTorque:
        return self.drive.torque_sensor

    def begin_trial(self, setup: TrialSetup) -> None:
        # A hands-off trial (rig check) needs no gloves: their watchdog is off for it.
        self.hands_off = setup.hands_off
        if self.plant is not None:
            self.plant.begin_trial(setup)
        if self.lab is not None:
            self.lab.call("begin_trial", setup)

    def _release(self, released: bool) -> None:
        """The simulated subject lets go of the wheel (or holds it again)."""
        if self.plant is not None:
            self.plant.released = released
        if self.lab is not None:
            self.lab.call("release" if released else "hold")

    def zero_torque_sensor(self) -> None:
        """With the wheel released, average the column torque and take it as the offset."""
        self._release(True)
        self._driver_torque().clear_recent()
        try:
            period = 1.0 / self.rig.loop_rate_hz
            t0 = time.perf_counter()
            for i in range(int(ZEROING_S * self.rig.loop_rate_hz)):
                # Sleep most of the wait, as the loop does: a busy wait under SCHED_FIFO would
                # starve the process's other threads (the host heartbeat the drive watches).
                due = t0 + i * period
                wait = due - time.perf_counter()
                if wait > SPIN_S + 1e-4:
                    time.sleep(wait - SPIN_S)
                while time.perf_counter() < due:
                    pass
                self.drive.set_torque(0.0)
                self.drive.sync()
            self._driver_torque().zero()
        finally:
            self._release(False)

    def health(self) -> str | None:
        """A reason to stop the trial now, or None."""
        problem = self.drive.problem()
        if problem is not None or self.hands_off:
            return problem
        # The grip source of any kind: its reader failed, or its stream stopped (naming the
        # device, and what it saw go wrong on the line: bad CRCs, malformed lines).
        return self.glove.problem(self.rig.safety.glove_timeout_s)

    def status(self) -> dict:
        d, g = getattr(self, "drive", None), getattr(self, "glove", None)
        st = g.stats().as_dict() if g is not None else {}
        drive = (
            d.status()
            if d is not None
            else {"drive_state": "none", "drive_ok": False, "drive_enabled": False, "faults": []}
        )
        return {
            **drive,
            "glove_source": g.describe() if g else None,
            "glove_rate_hz": st.get("rate_hz"),
            # Each only for the kinds that have them (None otherwise): the glove unit's CRCs
            # and sequence gaps, a text-line device's malformed lines, an LSL stream's
            # non-numeric samples.
            "glove_crc_errors": st.get("crc_errors"),
            "glove_dropped_frames": st.get("dropped_frames"),
            "glove_bad_samples": st.get("bad_lines", st.get("bad_samples")),
            "glove_age_s": g.age_s() if g else None,
        }

    def _driver_torque(self) -> ColumnTorque:
        try:
            return self.drive.torque_sensor
        except DriveError:  # the rig file gives none: hands-off trials only
            return _NoDriverTorque(self)

    def device_loop(
        self, *, estop=None, realtime: bool = True, block_s: float = DEFAULT_BLOCK_S
    ) -> DeviceLoop:
        """The control loop over these devices. Its consumer must keep pulling blocks: the
        loop only cycles while it is asked for samples. The engine therefore drives a real-time
        rig through :class:`ProcessLoop`, never this loop directly (an engine pause would
        suspend the loop and leave the drive holding its last command)."""
        return DeviceLoop(
            self.drive,
            self._driver_torque(),
            self.glove,
            realtime=realtime,
            trial_hooks=[self.begin_trial],
            pre_trial=self.zero_torque_sensor,
            health=self.health,
            estop=estop,
            pause_fades_out=True,
            safety=self.rig.safety,
            block_s=block_s,
        )

    def close(self) -> None:
        drive = getattr(self, "drive", None)  # a failed __init__ may not have got so far
        closers: list[Callable[[], object]] = [drive.disable, drive.close] if drive else []
        for device in (getattr(self, "glove", None), self.simulated, self.lab):
            if device is not None:
                closers.append(device.close)
        for closer in closers:
            try:
                closer()
            except Exception:
                pass


class _NoDriverTorque:
    """A rig without a driver torque (``[drive.torque_sensor] source = "none"``): recorded as
    NaN in a hands-off trial (a rig check needs none); any other trial is refused at its start
    (``steerlab run`` refuses the session before that)."""

    def __init__(self, devices: RigDevices) -> None:
        self._devices = devices

    def read(self) -> float:
        if not self._devices.hands_off:
            raise TrialFault(
                'this rig gives no driver torque ([drive.torque_sensor] source = "none"): '
                "only a hands-off trial (rig check) can run on it"
            )
        return math.nan

    def zero(self) -> None:
        pass

    def clear_recent(self) -> None:
        pass


# -- the loop's own process ----------------------------------------------------------------------
#: How often the loop process reports the devices' status between blocks, s.
STATUS_PERIOD_S = 1.0


#: Samples the shared ring holds (s at 1 kHz): what the engine recovers of a killed loop process.
RING_SAMPLES = 2048


class SampleRing:
    """The loop's newest samples in shared memory, written as each is complete, so that those a
    killed loop process had not yet handed over (its block in progress, blocks still in its
    queue's buffer) can still reach the file."""

    def __init__(self, ctx) -> None:
        n = len(BLOCK_CHANNELS)
        self.data = ctx.RawArray("d", RING_SAMPLES * n)
        self.count = ctx.RawValue("q", 0)  # samples of this trial written

    def sink(self):
        ring = np.frombuffer(self.data, dtype=float).reshape(RING_SAMPLES, -1)
        count = self.count
        channels = BLOCK_CHANNELS

        def put(index: int, buf: dict, row: int) -> None:
            r = ring[index % RING_SAMPLES]
            for c, name in enumerate(channels):
                r[c] = buf[name][row]
            count.value = index + 1

        return put

    def since(self, first: int) -> dict | None:
        """Samples ``first`` … newest as a block, if the ring still holds them all."""
        last = self.count.value
        if last <= first or last - first > RING_SAMPLES:
            return None
        ring = np.frombuffer(self.data, dtype=float).reshape(RING_SAMPLES, -1)
        rows = ring[np.arange(first, last) % RING_SAMPLES]
        return {name: rows[:, c].copy() for c, name in enumerate(BLOCK_CHANNELS)}


def _terminated(signum, frame) -> None:
    # SIGTERM (multiprocessing's terminate(), the engine's process ending): leave through the
    # finalizers, which disable the drive, instead of dying where it stands.
    raise SystemExit(128 + signum)


def _worker(
    rig, subject_number: int, conn, out_end, estop, block_s: float, ring=None, lab=None
) -> None:
    import signal

    signal.signal(signal.SIGTERM, _terminated)
    out = Outbox(out_end)
    try:
        _serve(rig, subject_number, conn, out, estop, block_s, ring, lab)
    finally:
        out.close()  # what is queued reaches the engine before the process ends


def _serve(rig, subject_number: int, conn, out: Outbox, estop, block_s: float, ring, lab) -> None:
    from steerlab.hardware.realtime import tune_process
    from steerlab.hardware.safety import warm_up

    # The heavy start-up first (imports above, compiling the loop's kernel), so that this
    # process does not hold a CPU at real-time priority for seconds (it starved a running
    # session's processes); then the priority, before the rig's threads start, so that they
    # inherit it (the CAN reader that latches each SYNC's answer is one of them).
    warm_up()
    tuning = tune_process()
    try:
        if not isinstance(rig, RigConfig):
            rig = load_rig(rig)
        client = None
        if lab is not None:
            from steerlab.hardware.sim.lab import LabClient

            client = LabClient(*lab)
        devices = RigDevices(rig, subject_number=subject_number, lab=client)
    except Exception as e:
        out.put(("error", f"{type(e).__name__}: {e}"))
        return
    try:
        loop = devices.device_loop(estop=estop, block_s=block_s)
        loop.trace = bool(os.environ.get("STEERLAB_LOOP_TRACE"))  # benchmarks/live_loop --trace
        if ring is not None:
            loop.sample_sink = ring.sink()
        status_every = max(1, round(STATUS_PERIOD_S / loop.block_s))
        out.put(
            (
                "ready",
                {"status": devices.status(), "physiology": devices.physiology, "realtime": tuning},
            )
        )
        while True:
            msg = conn.recv()
            if msg[0] == "close":
                break
            if msg[0] != "trial":
                continue
            control = LoopControl()
            fault = None
            closing = False
            # A writable perturbation, so that an injected fault ("nan") can reach it.
            setup = replace(msg[1], perturbation_nm=np.array(msg[1].perturbation_nm))
            profile_to = os.environ.get("STEERLAB_LOOP_PROFILE")  # benchmarks/live_loop --profile
            if profile_to:
                import cProfile

                profiler = cProfile.Profile()
                profiler.enable()
            try:
                for i, block in enumerate(loop.run_trial(setup, control)):
                    out.put(("block", block))
                    if i % status_every == 0:
                        out.put(("status", devices.status()))
                    while conn.poll():
                        m = conn.recv()
                        if m[0] == "abort":
                            control.abort_reason = m[1]
                        elif m[0] == "pause":
                            control.paused.set()
                        elif m[0] == "close":
                            control.abort_reason, closing = "the session was closed", True
                        elif m[0] == "inject":
                            out.put(("injected", (m[1], _inject(m[1], devices, setup))))
            except TrialFault as f:
                fault = str(f)
            except Exception as e:
                fault = f"internal error in the live loop: {type(e).__name__}: {e}"
            finally:
                if profile_to:
                    profiler.disable()
                    profiler.dump_stats(profile_to)
            cpu = os.times()
            loop._stats["loop_process_cpu_s"] = cpu.user + cpu.system
            out.put(
                ("end", {"stats": loop.trial_stats(), "fault": fault, "status": devices.status()})
            )
            if closing:
                break
    finally:
        devices.close()


#: Faults :meth:`ProcessLoop.inject` can put into the loop process's running trial (tests and
#: ``python -m benchmarks faults``): the host's CAN bus goes bus-off, the loop thread hangs for
#: 0.2 s, the perturbation turns NaN.
HOST_FAULTS = ("bus_off", "hang", "nan")


def _inject(fault: str, devices: RigDevices, setup: TrialSetup) -> float:
    """Inject ``fault`` now, on the loop's thread, between two blocks; its time.monotonic()."""
    t = time.monotonic()
    if fault == "bus_off":
        devices.drive.drop_bus()
    elif fault == "hang":
        time.sleep(0.2)
    elif fault == "nan":
        setup.perturbation_nm[:] = np.nan
    return t


class ProcessLoop:
    """A real-time rig's control loop, run in its own process (see the module docstring).

    For a simulated rig file the simulated devices get a process of their own
    (:class:`hardware.sim.lab.LabProcess`, :attr:`lab`) unless ``simulated_devices="in_loop"``
    (the loop's process then hosts them, on python-can's virtual bus, as before issue 14)."""

    def __init__(
        self,
        rig_path: str | None,
        subject_number: int,
        *,
        start_timeout_s: float = 60.0,
        block_s: float = DEFAULT_BLOCK_S,
        simulated_devices: str = "process",
    ):
        if simulated_devices not in ("process", "in_loop"):
            raise ValueError(
                f"simulated_devices: 'process' or 'in_loop', not {simulated_devices!r}"
            )
        self.lab = None
        rig: RigConfig | str | None = rig_path
        lab_control = None
        #: The drive as the engine's process reaches it when the loop process dies (None: the
        #: drive is in the loop's own process, a simulated rig's ``"in_loop"``).
        self._guarded: RigConfig | None = None
        #: What the guard did when the loop process died: {"t", "sent"} or {"t", "error"}.
        self.guard_report: dict | None = None
        self._closing = False
        try:
            loaded = load_rig(rig_path)
        except Exception as e:  # the same message as from the loop process
            raise RigError(f"the rig could not be brought up: {type(e).__name__}: {e}") from e
        if not loaded.simulated:
            self._guarded = loaded
        if simulated_devices == "process":
            if loaded.simulated:
                from steerlab.hardware.can.config import UDP_LOOPBACK
                from steerlab.hardware.sim.lab import LabProcess

                try:
                    self.lab = LabProcess(rig_path, subject=subject_number)
                except Exception as e:
                    raise RigError(f"the simulated devices did not come up: {e}") from e
                # The host sees a lab: the drive on the lab's bus, the grip where the lab says
                # (the glove unit's pty, an LSL stream's source id).
                grips = grip_kind(loaded.glove.kind)
                rig = replace(
                    loaded,
                    drive=on_bus(loaded.drive, UDP_LOOPBACK, self.lab.channel),
                    glove=grips.at(loaded.glove, self.lab.grip),
                    simulation=None,
                )
                lab_control = (self.lab.control_address, self.lab.authkey)
                self._guarded = rig
        try:
            self._start(rig, subject_number, start_timeout_s, block_s, lab_control)
        except BaseException:
            if self.lab is not None:
                self.lab.close()
            raise

    def _start(self, rig, subject_number, start_timeout_s, block_s, lab_control) -> None:
        ctx = mp.get_context("spawn")
        self._estop = ctx.Event()
        self._ring = SampleRing(ctx)
        self._conn, child = ctx.Pipe()
        self._inbox, out_end = message_pipe(ctx)
        self._stats: dict = {}
        self._delivered = 0
        self._unhanded: list[dict] = []
        self.status: dict = {}
        self.injected: dict[str, float] = {}
        self.physiology: dict | None = None
        self._lock = threading.Lock()
        self._proc = ctx.Process(
            target=_worker,
            args=(
                rig,
                subject_number,
                child,
                out_end,
                self._estop,
                block_s,
                self._ring,
                lab_control,
            ),
            name="steerlab-loop",
            daemon=True,
        )
        from steerlab.hardware.realtime import single_threaded_math_for_children

        try:
            with single_threaded_math_for_children():
                self._proc.start()
        except BaseException:
            self._inbox.close()
            raise
        self._inbox.started()
        try:
            kind, payload = self._inbox.get(timeout=start_timeout_s)
        except queue.Empty:
            self.close()
            raise RigError(f"the rig did not come up within {start_timeout_s:.0f} s") from None
        except WriterGone:
            self.close()
            raise RigError(
                f"the loop process ended before the rig came up (exit code {self._proc.exitcode})"
            ) from None
        if kind == "error":
            self._proc.join(5)
            raise RigError(f"the rig could not be brought up: {payload}")
        self.status = payload["status"]
        self.physiology = payload["physiology"]
        self.realtime = payload["realtime"]
        guard_off = None
        if self._guarded is not None:
            guard_off = getattr(drive_kind(self._guarded.drive.kind), "emergency_off", None)
        if guard_off is not None:
            threading.Thread(
                target=self._guard, args=(guard_off,), name="steerlab-drive-guard", daemon=True
            ).start()

    def _guard(self, emergency_off) -> None:
        """The loop process died (killed, crashed): from this process, turn the drive off.

        For a drive whose own guard against a silent host is unknown (its kind has an
        ``emergency_off``), the host assumes there is none: the loop's torque command would
        stay on the wheel. A CiA 402 drive watches the host's heartbeat itself."""
        from multiprocessing.connection import wait

        wait([self._proc.sentinel])
        # The sentinel is ready as the process closes its files, a moment before its exit
        # status can be read (and close() may be reaping it on another thread meanwhile).
        deadline = time.monotonic() + 1.0
        while self._proc.exitcode is None and time.monotonic() < deadline:
            time.sleep(0.002)
        if self._closing and self._proc.exitcode == 0:
            return  # closed as asked: it disabled the drive itself
        # Killed or crashed (a negative exit code is a signal: close()'s own terminate or kill
        # of a loop process that would not end is one): its finalizers did not run.
        assert self._guarded is not None  # only started with a guarded drive
        why = {"exitcode": self._proc.exitcode, "closing": self._closing}
        try:
            emergency_off(self._guarded.drive)
            self.guard_report = {"t": time.monotonic(), "sent": True, **why}
        except Exception as e:  # nothing more this process can do; say so in the report
            self.guard_report = {"t": time.monotonic(), "error": f"{type(e).__name__}: {e}", **why}

    def emergency_stop(self) -> None:
        self._estop.set()

    def inject(self, fault: str) -> None:
        """Fault injection for tests and benchmarks (:data:`HOST_FAULTS`): done by the loop
        process between two blocks of the running trial; the time it was done
        (time.monotonic()) then appears in :attr:`injected`."""
        if fault not in HOST_FAULTS:
            raise ValueError(f"unknown fault {fault!r} (known: {', '.join(HOST_FAULTS)})")
        with self._lock:
            self._conn.send(("inject", fault))

    def trial_stats(self) -> dict:
        return dict(self._stats)

    @property
    def samples_completed(self) -> int:
        """Samples of this trial the loop completed, as its shared ring counts them (read even
        after the loop process died)."""
        return int(self._ring.count.value)

    def run_trial(self, setup: TrialSetup, control: LoopControl) -> Iterator[dict]:
        self._estop.clear()
        self._stats = {}
        self._ring.count.value = 0
        self._delivered = 0
        self._unhanded = []
        with self._lock:
            self._conn.send(("trial", setup))
        done = threading.Event()
        forwarder = threading.Thread(target=self._forward, args=(control, done), daemon=True)
        forwarder.start()
        ended = False
        try:
            dead_since = None
            while True:
                try:
                    kind, payload = self._inbox.get(timeout=0.1)
                except (queue.Empty, WriterGone) as e:
                    if isinstance(e, queue.Empty):
                        if self._proc.is_alive():
                            continue
                        # Dead: what it sent whole is still being read (a starved reading
                        # thread); its end of file says when that is done.
                        dead_since = dead_since or time.monotonic()
                        if time.monotonic() - dead_since < 1.0:
                            continue
                    self._proc.join(1.0)  # its pipe ends a moment before it is reaped
                    rest = self._undelivered()
                    if rest is not None:
                        yield rest
                    raise TrialFault(
                        f"the live loop process died (exit code {self._proc.exitcode})"
                    ) from None
                if kind == "block":
                    self._delivered += len(payload["time_s"])
                    yield payload
                elif kind == "status":
                    self.status = payload
                elif kind == "injected":
                    self.injected[payload[0]] = payload[1]
                elif kind == "end":
                    ended = True
                    self._stats = payload["stats"]
                    self.status = payload["status"]
                    if payload["fault"]:
                        raise TrialFault(payload["fault"])
                    return
        finally:
            done.set()
            forwarder.join(1.0)
            if not ended and self._proc.is_alive():
                # The engine let go of the trial (its writer failed, it was cut off, …): the
                # loop must not go on applying the perturbation. Zero torque at its next cycle.
                self._stop_trial()

    def _stop_trial(self, timeout_s: float = 5.0) -> None:
        self._estop.set()
        try:
            with self._lock:
                self._conn.send(("abort", "the engine stopped the trial"))
        except (OSError, BrokenPipeError):
            return
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:  # its remaining blocks, then its end
            try:
                kind, payload = self._inbox.get(timeout=0.1)
            except (queue.Empty, WriterGone) as e:
                if isinstance(e, WriterGone) or not self._proc.is_alive():
                    rest = self._undelivered()
                    if rest is not None:
                        self._unhanded.append(rest)
                    return
                continue
            if kind == "block":
                # Recorded before the loop stopped: kept for take_unhanded(), not dropped.
                self._unhanded.append(payload)
                self._delivered += len(payload["time_s"])
            elif kind == "end":
                self._stats = payload["stats"]
                self.status = payload["status"]
                return

    def _undelivered(self) -> dict | None:
        """What a dead loop took but never handed over (the shared ring's samples after the
        last delivered), counted as delivered from now on: handed over once."""
        rest = self._ring.since(self._delivered)
        if rest is not None:
            self._delivered += len(rest["time_s"])
        return rest

    def take_unhanded(self) -> list[dict]:
        """The blocks the loop recorded after the engine let go of the trial (it stops at its
        next cycle): the engine hands them on to its subscribers like the others."""
        out, self._unhanded = self._unhanded, []
        return out

    def _forward(self, control: LoopControl, done: threading.Event) -> None:
        """Pass pause and abort on to the loop process, even while the engine is not pulling."""
        sent_abort = sent_pause = False
        while not done.wait(0.02):
            with self._lock:
                if control.abort_reason is not None and not sent_abort:
                    self._conn.send(("abort", control.abort_reason))
                    sent_abort = True
                if control.paused.is_set() and not sent_pause:
                    self._conn.send(("pause",))
                    sent_pause = True

    def close(self) -> None:
        self._closing = True
        try:
            with self._lock:
                self._conn.send(("close",))
        except (OSError, BrokenPipeError):
            pass
        self._proc.join(10)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(5)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5)
        self._inbox.close()
        if self.lab is not None:
            self.lab.close()
