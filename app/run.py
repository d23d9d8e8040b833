"""``steerlab run``: one subject's session on a rig, in real time; ``steerlab stop``: its
emergency stop from another terminal.

Emergency stop, whatever the rig:
- in the terminal running the session: Ctrl-C, or Enter (when the terminal is interactive);
- from another terminal: ``steerlab stop --out DIR [--subject N] [--rig RIG]`` (signals the
  session's process, named in ``DIR/steerlab-run-SUBJECT.pid`` with its start time and command
  line, after checking in /proc that the process is still that session).
Each stops the motor at once (zero torque, drive disabled), ends the trial as aborted with the
reason, keeps every recorded sample, and ends the session. Run again with ``--resume`` to
continue.

On the lab's clock: unless ``lsl`` is False (``--no-lsl``, or ``STEERLAB_LSL=off``), the session
publishes its signals and events on the Lab Streaming Layer for LabRecorder
(:mod:`protocols.lsl_publisher`, ``docs/lsl.md``); each trial records the LSL clock at its first
sample either way.

A trial aborted by a fault (a stalled loop, a drive fault, the glove stream stopping, ...) does
not end the session by itself: ``on_abort`` (``--on-abort``) says what follows. ``ask`` (the
default when stdin is a terminal) shows the reason and asks "[r]edo the trial, [g]o on to the
next, or [s]top the session?"; ``redo``, ``next`` and ``stop`` answer the same without asking
(``stop`` is the default otherwise: scripts, tests). A redo is a new attempt of the trial; going
on runs the aborted trial again after the others. The aborted attempt stays in the file, marked
aborted, with every sample it recorded. Without a person to ask, :data:`MAX_ABORTS_IN_A_ROW`
aborted trials in a row stop the session: a fault that persists must not abort trial after
trial.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from steerlab.hardware.realtime import realtime_summary, realtime_warnings
from steerlab.hardware.rig import load_rig
from steerlab.hardware.trial_loops import rig_loop
from steerlab.protocols.datafile import (
    SessionFile,
    SessionWriter,
    check_free_space,
    creating_path,
    session_bytes,
)
from steerlab.protocols.engine import SessionEngine, State
from steerlab.protocols.events import StateChanged, TrialEnded, TrialStarted
from steerlab.protocols.lsl_publisher import (
    HOST,
    MARKER_TYPE,
    SIGNAL_TYPE,
    LabClock,
    LslPublisher,
    close_lab_subscriber,
    lab_subscriber,
    publish_default,
)
from steerlab.protocols.names import inside
from steerlab.protocols.protocol import load_protocol
from steerlab.protocols.records import STATUS_ABORTED
from steerlab.protocols.session import build_plan, subject_id
from steerlab.protocols.writelock import LockedError, WriterLock

PIDFILE_GLOB = "steerlab-run-*.pid"
#: Set for the session's child processes: no terminal escape codes from numba (see _run).
NO_NUMBA_HIGHLIGHTING = "NUMBA_DISABLE_ERROR_MESSAGE_HIGHLIGHTING"

#: What follows a trial aborted by a fault: ask the experimenter, or redo, next, stop unasked.
ON_ABORT = ("ask", "redo", "next", "stop")
#: Without a person to ask (``--on-abort redo`` or ``next``), this many aborted trials in a row
#: stop the session.
MAX_ABORTS_IN_A_ROW = 3
ABORT_PROMPT = "[r]edo the trial, [g]o on to the next, or [s]top the session?"
_ANSWERS = {"r": "redo", "redo": "redo", "g": "next", "go": "next", "s": "stop", "stop": "stop"}


def pidfile_path(out_dir: str | Path, subject: str) -> Path:
    return Path(out_dir) / f"steerlab-run-{subject}.pid"


def _proc_start_ticks(pid: int) -> int | None:
    """The process's start time (clock ticks after boot, /proc/PID/stat field 22), or None."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    # the command name (field 2) is in parentheses and may hold spaces or ')'
    return int(stat.rsplit(")", 1)[1].split()[19])


def _proc_cmdline(pid: int) -> list[str] | None:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return None
    return [a.decode(errors="replace") for a in raw.split(b"\0") if a]


@dataclass(frozen=True)
class SessionProcess:
    """What a running session's pid file says: enough to tell that a pid is still that session
    (pids are reused) and which session it is."""

    pid: int
    start_ticks: int
    cmdline: list[str]
    subject: str
    rig: str
    out: str
    path: Path

    @classmethod
    def mine(cls, path: Path, subject: str, rig: str, out: Path) -> SessionProcess:
        pid = os.getpid()
        return cls(
            pid, _proc_start_ticks(pid) or 0, _proc_cmdline(pid) or [], subject, rig, str(out), path
        )

    @classmethod
    def read(cls, path: Path) -> SessionProcess:
        """:raises ValueError: not a pid file of ours (unreadable, not JSON, fields missing)."""
        try:
            d = json.loads(path.read_text())
            return cls(
                int(d["pid"]),
                int(d["start_ticks"]),
                [str(a) for a in d["cmdline"]],
                str(d["subject"]),
                str(d["rig"]),
                str(d["out"]),
                path,
            )
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ValueError(f"{path}: not a readable Steerlab pid file ({e})") from None

    def write_exclusive(self) -> None:
        """Create the pid file; :raises FileExistsError: one exists."""
        data = {
            "pid": self.pid,
            "start_ticks": self.start_ticks,
            "cmdline": self.cmdline,
            "subject": self.subject,
            "rig": self.rig,
            "out": self.out,
        }
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        with os.fdopen(fd, "w") as f:
            json.dump(data, f)

    def why_not_alive(self) -> str | None:
        """None if the pid is still this session's process, else why not."""
        ticks = _proc_start_ticks(self.pid)
        if ticks is None:
            return f"process {self.pid} is not running"
        if ticks != self.start_ticks:
            return f"process {self.pid} is another process now (started at another time)"
        cmdline = _proc_cmdline(self.pid)
        if cmdline != self.cmdline:
            return f"process {self.pid} is another program now ({' '.join(cmdline or [])!r})"
        return None

    def describe(self) -> str:
        return f"{self.subject} (process {self.pid}, rig {self.rig})"


class RunError(ValueError):
    pass


def wheel_notes(rig, protocol) -> list[str]:
    """What the rig's drive renders of the protocol's wheel, said where it differs: a drive
    without an inertia field (a SENSO-Wheel) leaves the subject the wheel's own."""
    own = getattr(rig.drive, "wheel_inertia_kgm2", None)
    if own is None:
        return []
    asked = protocol.wheel.inertia_kgm2
    note = (
        f"the {rig.drive.kind} drive renders no inertia: the subject feels the wheel's own "
        f"{own:g} kg·m² ([drive] wheel_inertia_kgm2)"
    )
    if abs(own - asked) > 0.05 * asked:
        note += (
            f", not the protocol's {asked:g} kg·m²; the report and the diagnosis take the wheel "
            "a rig check measured (docs/sensodrive.md)"
        )
    else:
        note += f", as the protocol's {asked:g} kg·m² asks"
    return [note]


def run_session(
    rig_path: str | None,
    subject_number: int,
    out_dir: str | Path,
    *,
    resume: bool = False,
    protocol_path: str | None = None,
    breaks: bool = True,
    say=print,
    rig_check: str | None = None,
    on_abort: str | None = None,
    lsl: bool | None = None,
) -> State:
    """Run the session; its final state (DONE when every trial is complete).

    ``on_abort``: one of :data:`ON_ABORT` (the module docstring); None: ``ask`` when stdin is a
    terminal, else ``stop``. ``lsl``: publish on LSL (None: yes, unless ``STEERLAB_LSL=off``)."""
    if subject_number < 1:
        raise RunError(f"--subject must be ≥ 1, got {subject_number}")
    try:
        publish = publish_default(True) if lsl is None else bool(lsl)
    except ValueError as e:
        raise RunError(str(e)) from None
    interactive = sys.stdin is not None and sys.stdin.isatty()
    if on_abort is None:
        on_abort = "ask" if interactive else "stop"
    if on_abort not in ON_ABORT:
        raise RunError(f"--on-abort must be one of {', '.join(ON_ABORT)}, not {on_abort!r}")
    if on_abort == "ask" and not interactive:
        raise RunError("--on-abort ask needs a terminal on stdin to ask in; use redo, next or stop")
    protocol = load_protocol(protocol_path)
    rig = load_rig(rig_path)
    if abs(protocol.loop_rate_hz - rig.loop_rate_hz) > 1e-9:
        raise RunError(
            f"the protocol ({protocol.source_path}) runs its loop at {protocol.loop_rate_hz:g} Hz "
            f"but the rig ({rig.source}) at {rig.loop_rate_hz:g} Hz; make them agree"
        )
    if rig.drive.torque_sensor.source == "none":
        raise RunError(
            f'{rig.source}: [drive.torque_sensor] source = "none": this rig gives no driver '
            "torque, which the admittance estimate needs; name a sensor or (SensoDrive) "
            '"reconstructed" (docs/rig-config.md). A hands-off steerlab rig-check can run'
        )
    for note in wheel_notes(rig, protocol):
        say(f"note: {note}")
    last_check = None
    if rig_check is not None:
        from steerlab.analysis.rigcheck import load_rig_model, rig_check_record

        last_check = rig_check_record(load_rig_model(rig_check))  # before the rig comes up
    plan = build_plan(protocol, subject_number)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = inside(out, out / f"{plan.subject}.h5")
    lock = WriterLock(path)
    try:
        lock.acquire()  # before anything is checked or written: one writer per session file
    except LockedError as e:
        raise RunError(str(e)) from None
    try:
        attempts = None
        creating_path(path).unlink(missing_ok=True)  # left by a kill while the file was created
        if path.exists():
            if not resume:
                raise RunError(f"{path}: exists already; pass --resume to continue this session")
            sf = SessionFile(path)
            if sf.attrs.get("protocol_toml") != protocol.source_text:
                raise RunError(f"{path}: was recorded with a different protocol; cannot resume")
            attempts = sf.attempts()
        check_free_space(out, session_bytes(plan))
        me = SessionProcess.mine(
            pidfile_path(out, plan.subject),
            plan.subject,
            str(Path(rig.source).resolve()),
            out.resolve(),
        )
        _claim(me, say)
        try:
            return _run(
                me, rig, rig_path, subject_number, plan, path, attempts, breaks, say, lock,
                last_check, on_abort, publish,
            )  # fmt: skip
        finally:
            _release(me)
    finally:
        lock.release()


def _run(
    me, rig, rig_path, subject_number, plan, path, attempts, breaks, say, lock, last_check,
    on_abort, publish,
) -> State:  # fmt: skip
    # The stop signals act from now on (a stop during the rig's bring-up ends the session before
    # its first trial), not only once the engine runs.
    holder: dict = {}

    def emergency_stop(reason: str) -> None:
        # Whenever it comes (a trial, a break, the question after an abort): the session ends.
        holder["stopped"] = reason
        engine = holder.get("engine")
        if engine is not None:
            engine.emergency_stop(reason)

    def on_signal(signum, _frame):
        emergency_stop(f"emergency stop ({signal.Signals(signum).name})")

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGUSR1)}
    loop = writer = lab = None
    # numba's error highlighting (colorama) registers a reset at exit in every process that
    # formats a typing message while compiling; the loop's and the simulated lab's processes
    # do, and on a terminal each then wrote a stray "\x1b[0m" as it ended. The processes
    # inherit this when they start; their messages are plain text either way.
    os.environ.setdefault(NO_NUMBA_HIGHLIGHTING, "1")
    try:
        say(f"bringing up the rig ({rig.source}) ...")
        loop = rig_loop(rig_path, subject_number)
        say(realtime_summary(loop.realtime))
        for w in realtime_warnings(loop.realtime):
            say(f"warning: {w}")
        engine = SessionEngine(plan, loop, attempts=attempts, pace_breaks=breaks)
        extra = {"rig": rig.describe(), "realtime_tuning": loop.realtime}
        if loop.physiology is not None:
            extra.update({"simulated": True, "simulated_subject": loop.physiology})
        if last_check is not None:
            extra["rig_check"] = last_check
        # The drive gives the angle as counts × its step: stored as those counts (when exact;
        # docs/data-format.md).
        quanta = {"wheel_angle_rad": rig.drive.angle_quantum_rad}
        # The LSL clock at each trial's first sample goes into the file, published or not.
        clock = LabClock(HOST, warn=lambda m: say(f"warning: {m}"))
        writer = SessionWriter(
            path,
            extra_attributes=extra,
            lock=lock,
            quanta=quanta,
            first_sample_attributes=clock.first_sample_attributes,
        )
        lab = lab_subscriber(
            clock,
            publish,
            rig=Path(rig.source).stem,
            session_path=path,
            nominal_rate_hz=rig.loop_rate_hz,
            warn=lambda m: say(f"warning: {m}"),
        )
        # Before the writer: the clock reads each block's arrival before the file's work on it
        # (microseconds to publish; it never raises).
        engine.subscribe(lab)
        engine.subscribe(writer)
        if isinstance(lab, LslPublisher):
            say(
                f"publishing on LSL: 'Steerlab {plan.subject}' (type {SIGNAL_TYPE}) and "
                f"'Steerlab {plan.subject} markers' (type {MARKER_TYPE}); --no-lsl turns it off"
            )
        engine.subscribe(_reporter(say, len(plan.trials)))
        holder["engine"] = engine
        if "stopped" in holder:
            say(f"{holder['stopped']} before the first trial")
            return State.IDLE
        terminal = None
        if sys.stdin is not None and sys.stdin.isatty():
            terminal = Terminal(sys.stdin, lambda: emergency_stop("emergency stop (keyboard)"))
            terminal.start()
            say("press Enter (or Ctrl-C) for an emergency stop")
        state = _walk(engine, on_abort, terminal, lambda: holder.get("stopped"), say)
    finally:
        # The pid file goes before the stop signals stop being ours: a `steerlab stop` that
        # finds it must not kill this process with SIGUSR1's default action.
        _release(me)
        for s, h in previous.items():
            signal.signal(s, h)
        if loop is not None:
            loop.close()
        if writer is not None:
            writer.close()
        close_lab_subscriber(lab)
    remaining = len(engine.pending())
    if state is State.DONE:
        say(f"session complete: {path}")
    else:
        say(f"session stopped with {remaining} trial(s) to go; continue with --resume: {path}")
    return state


def _walk(
    engine: SessionEngine,
    on_abort: str,
    terminal: Terminal | None,
    stopped: Callable[[], str | None],
    say: Callable[[str], object],
) -> State:
    """Run the engine's trials; after a trial aborted by a fault, redo it, go on or stop, as
    ``on_abort`` says (``ask``: as the experimenter answers on ``terminal``)."""
    ends: list[TrialEnded] = []
    engine.subscribe(lambda e: ends.append(e) if isinstance(e, TrialEnded) else None)
    in_a_row = 0
    while True:
        ends.clear()
        state = engine.run()
        if state is not State.IDLE or stopped() is not None or not ends:
            return state  # done, broken, or stopped by a person
        last = ends[-1]
        if last.status != STATUS_ABORTED:
            return state
        in_a_row = 0 if any(e.status != STATUS_ABORTED for e in ends) else in_a_row
        in_a_row += 1
        if on_abort == "ask":
            assert terminal is not None  # run_session refuses ask without a terminal
            say(f"trial {last.trial_index} ({last.key}) was aborted: {last.reason}")
            choice = terminal.ask(ABORT_PROMPT, say, stopped)
        elif on_abort != "stop" and in_a_row >= MAX_ABORTS_IN_A_ROW:
            say(f"{in_a_row} trials aborted in a row: stopping the session (--on-abort {on_abort})")
            choice = "stop"
        else:
            choice = on_abort
        if choice == "stop" or stopped() is not None:
            return state
        if choice == "redo":
            engine.redo(last.trial_index, "redo after an aborted trial")
            say(f"redoing trial {last.trial_index} (a new attempt; the aborted one stays)")
        else:
            engine.defer(last.trial_index)
            say(f"going on; trial {last.trial_index} is run again after the others")


class Terminal:
    """The session's one reader of its terminal. While trials run (breaks included) a line is
    an emergency stop; while the experimenter is asked what to do after an aborted trial, lines
    are answers. One reader for both: an answer is never taken for an emergency stop, and the
    reader of one never eats the other."""

    def __init__(self, stream: IO[str], on_stop: Callable[[], None]) -> None:
        self.stream = stream
        self.on_stop = on_stop
        self._asking = threading.Event()
        self._answers: queue.Queue[str] = queue.Queue()
        self._closed = threading.Event()

    def start(self) -> None:
        threading.Thread(target=self._read, name="steerlab-terminal", daemon=True).start()

    def _read(self) -> None:
        try:
            for line in self.stream:
                if self._asking.is_set():
                    self._answers.put(line.strip().lower())
                else:
                    self.on_stop()
        except (OSError, ValueError):  # the terminal went away
            pass
        finally:
            self._closed.set()

    def ask(
        self, prompt: str, say: Callable[[str], object], stopped: Callable[[], str | None]
    ) -> str:
        """``redo``, ``next`` or ``stop``, as answered; asked again until the answer is one
        (an empty line, Enter as for an emergency stop, is not). ``stop`` when ``stopped()``
        says a person stopped the session meanwhile, or when the terminal is gone."""
        while not self._answers.empty():  # typed before the question: not an answer to it
            self._answers.get_nowait()
        self._asking.set()
        try:
            while True:
                say(prompt)
                while True:
                    if stopped() is not None:
                        return "stop"
                    try:
                        answer = self._answers.get(timeout=0.1)
                        break
                    except queue.Empty:
                        if self._closed.is_set():
                            say("no terminal to answer on: stopping the session")
                            return "stop"
                choice = _ANSWERS.get(answer)
                if choice is not None:
                    return choice
                say(f"{answer!r}: please answer r, g or s")
        finally:
            self._asking.clear()


def _reporter(say, n_trials: int):
    def on(e):
        if isinstance(e, TrialStarted):
            say(f"trial {e.trial_index}/{n_trials} {e.condition} (attempt {e.attempt}) ...")
        elif isinstance(e, TrialEnded):
            timing = e.stats
            t = (
                (
                    f", p99 period error {timing['period_error_p99_ms']:.3f} ms, "
                    f"{timing['late_cycles']} late cycles"
                )
                if "period_error_p99_ms" in timing
                else ""
            )
            why = f": {e.reason}" if e.reason else ""
            say(f"  {e.status}{why} ({e.n_samples} samples{t})")
        elif isinstance(e, StateChanged) and e.new == "broken":
            say(f"engine broken: {e.reason}")

    return on


def _claim(me: SessionProcess, say) -> None:
    """Write our pid file; a stale one is removed with a message, a live one refuses."""
    for _ in range(2):
        try:
            me.write_exclusive()
            return
        except FileExistsError:
            try:
                other = SessionProcess.read(me.path)
                why = other.why_not_alive()
            except ValueError as e:
                why = str(e)
            if why is None:
                raise RunError(
                    f"{me.path}: a session for {me.subject} is already running in {me.out} "
                    f"({other.describe()}); stop it first (steerlab stop --out {me.out} "
                    f"--subject {int(me.subject[1:])})"
                ) from None
            me.path.unlink(missing_ok=True)
            say(f"removed a stale pid file {me.path}: {why}")
    raise RunError(f"{me.path}: cannot create the pid file")


def _release(me: SessionProcess) -> None:
    try:
        if SessionProcess.read(me.path).pid == me.pid:
            me.path.unlink(missing_ok=True)
    except ValueError:
        pass


def running_sessions(out_dir: str | Path, say=print) -> list[SessionProcess]:
    """The sessions running in ``out_dir``, each checked against /proc; stale pid files are
    removed, with a message through ``say``."""
    live = []
    for path in sorted(Path(out_dir).glob(PIDFILE_GLOB)):
        try:
            sp = SessionProcess.read(path)
            why = sp.why_not_alive()
        except ValueError as e:
            sp, why = None, str(e)
        if why is not None:
            path.unlink(missing_ok=True)
            say(f"removed a stale pid file {path}: {why}")
            continue
        assert sp is not None  # read, since why_not_alive answered
        live.append(sp)
    return live


def stop_running(
    out_dir: str | Path, *, subject: int | None = None, rig: str | None = None, say=print
) -> SessionProcess:
    """Emergency stop (SIGUSR1) of the session running in ``out_dir`` for ``subject`` (and
    ``rig``); without ``subject`` there must be exactly one. Returns the session signalled.

    :raises RunError: no such session, or several and no way to tell which.
    """
    out = Path(out_dir)
    sessions = running_sessions(out, say)
    if subject is not None:
        sessions = [s for s in sessions if s.subject == subject_id(subject)]
    if rig is not None:
        sessions = [s for s in sessions if s.rig == str(Path(rig).resolve())]
    which = " ".join(
        w for w in (subject and f"for subject {subject_id(subject)}", rig and f"on rig {rig}") if w
    )
    if not sessions:
        raise RunError(f"{out}: no running session{' ' + which if which else ''}")
    if len(sessions) > 1:
        listed = "; ".join(s.describe() for s in sessions)
        raise RunError(
            f"{out}: {len(sessions)} sessions are running{' ' + which if which else ''}: "
            f"{listed}; say which with --subject (and --rig)"
        )
    (target,) = sessions
    why = target.why_not_alive()  # once more, just before the signal
    if why is not None:
        target.path.unlink(missing_ok=True)
        raise RunError(f"{target.path}: {why} (stale pid file removed)")
    os.kill(target.pid, signal.SIGUSR1)
    return target
