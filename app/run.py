"""``steerlab run``: one subject's session on a rig, in real time; ``steerlab stop``: its
emergency stop from another terminal.

Emergency stop, whatever the rig:
- in the terminal running the session: Ctrl-C, or Enter (when the terminal is interactive);
- from another terminal: ``steerlab stop --out DIR [--subject N] [--rig RIG]`` (signals the
  session's process, named in ``DIR/steerlab-run-SUBJECT.pid`` with its start time and command
  line, after checking in /proc that the process is still that session).
Each stops the motor at once (zero torque, drive disabled), ends the trial as aborted with the
reason, and keeps every recorded sample. Run again with ``--resume`` to continue.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

from steerlab.hardware.can.scaling import DriveScaling
from steerlab.hardware.live import ProcessLoop
from steerlab.hardware.realtime import realtime_summary, realtime_warnings
from steerlab.hardware.rig import load_rig
from steerlab.protocols.datafile import (
    SessionFile,
    SessionWriter,
    check_free_space,
    creating_path,
    session_bytes,
)
from steerlab.protocols.engine import SessionEngine, State
from steerlab.protocols.events import StateChanged, TrialEnded, TrialStarted
from steerlab.protocols.names import inside
from steerlab.protocols.protocol import load_protocol
from steerlab.protocols.session import build_plan, subject_id
from steerlab.protocols.writelock import LockedError, WriterLock

PIDFILE_GLOB = "steerlab-run-*.pid"


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
) -> State:
    if subject_number < 1:
        raise RunError(f"--subject must be ≥ 1, got {subject_number}")
    protocol = load_protocol(protocol_path)
    rig = load_rig(rig_path)
    if abs(protocol.loop_rate_hz - rig.loop_rate_hz) > 1e-9:
        raise RunError(
            f"the protocol ({protocol.source_path}) runs its loop at {protocol.loop_rate_hz:g} Hz "
            f"but the rig ({rig.source}) at {rig.loop_rate_hz:g} Hz; make them agree"
        )
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
                last_check,
            )  # fmt: skip
        finally:
            _release(me)
    finally:
        lock.release()


def _run(
    me, rig, rig_path, subject_number, plan, path, attempts, breaks, say, lock, last_check
) -> State:
    # The stop signals act from now on (a stop during the rig's bring-up ends the session before
    # its first trial), not only once the engine runs.
    holder: dict = {}

    def on_signal(signum, _frame):
        reason = f"emergency stop ({signal.Signals(signum).name})"
        engine = holder.get("engine")
        if engine is None:
            holder["stopped"] = reason
        else:
            engine.emergency_stop(reason)

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGUSR1)}
    loop = writer = None
    try:
        say(f"bringing up the rig ({rig.source}) ...")
        loop = ProcessLoop(rig_path, subject_number)
        say(realtime_summary(loop.realtime))
        for w in realtime_warnings(loop.realtime):
            say(f"warning: {w}")
        engine = SessionEngine(plan, loop, attempts=attempts, pace_breaks=breaks)
        extra = {"rig": rig.describe(), "realtime_tuning": loop.realtime}
        if loop.physiology is not None:
            extra.update({"simulated": True, "simulated_subject": loop.physiology})
        if last_check is not None:
            extra["rig_check"] = last_check
        # The drive gives the angle as encoder counts × its scaling: stored as those counts
        # (when exact; docs/data-format.md).
        quanta = {"wheel_angle_rad": abs(DriveScaling(rig.drive).counts_to_angle(1))}
        writer = SessionWriter(path, extra_attributes=extra, lock=lock, quanta=quanta)
        engine.subscribe(writer)
        engine.subscribe(_reporter(say, len(plan.trials)))
        holder["engine"] = engine
        if "stopped" in holder:
            say(f"{holder['stopped']} before the first trial")
            return State.IDLE
        if sys.stdin is not None and sys.stdin.isatty():
            threading.Thread(target=_keyboard, args=(engine,), daemon=True).start()
            say("press Enter (or Ctrl-C) for an emergency stop")
        state = engine.run()
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
    remaining = len(engine.pending())
    if state is State.DONE:
        say(f"session complete: {path}")
    else:
        say(f"session stopped with {remaining} trial(s) to go; continue with --resume: {path}")
    return state


def _keyboard(engine: SessionEngine) -> None:
    for _line in sys.stdin:
        engine.emergency_stop("emergency stop (keyboard)")


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
