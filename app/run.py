"""``steerlab run``: one subject's session on a rig, in real time; ``steerlab stop``: its
emergency stop from another terminal.

Emergency stop, whatever the rig:
- in the terminal running the session: Ctrl-C, or Enter (when the terminal is interactive);
- from another terminal: ``steerlab stop --out DIR`` (signals the process named in
  ``DIR/steerlab-run.pid``).
Each stops the motor at once (zero torque, drive disabled), ends the trial as aborted with the
reason, and keeps every recorded sample. Run again with ``--resume`` to continue.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path

from hardware.live import ProcessLoop
from hardware.rig import load_rig
from protocols.datafile import SessionFile, SessionWriter
from protocols.engine import SessionEngine, State
from protocols.events import StateChanged, TrialEnded, TrialStarted
from protocols.protocol import load_protocol
from protocols.session import build_plan

PIDFILE = "steerlab-run.pid"


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
        from analysis.rigcheck import load_rig_model, rig_check_record

        last_check = rig_check_record(load_rig_model(rig_check))  # before the rig comes up
    plan = build_plan(protocol, subject_number)
    out = Path(out_dir)
    path = out / f"{plan.subject}.h5"
    attempts = None
    if path.exists():
        if not resume:
            raise RunError(f"{path}: exists already; pass --resume to continue this session")
        sf = SessionFile(path)
        if sf.attrs.get("protocol_toml") != protocol.source_text:
            raise RunError(f"{path}: was recorded with a different protocol; cannot resume")
        attempts = sf.attempts()
    out.mkdir(parents=True, exist_ok=True)

    say(f"bringing up the rig ({rig.source}) ...")
    loop = ProcessLoop(rig_path, subject_number)
    engine = SessionEngine(plan, loop, attempts=attempts, pace_breaks=breaks)
    extra = {"rig": rig.describe(), "realtime_tuning": loop.realtime}
    if loop.physiology is not None:
        extra.update({"simulated": True, "simulated_subject": loop.physiology})
    if last_check is not None:
        extra["rig_check"] = last_check
    writer = SessionWriter(path, extra_attributes=extra)
    engine.subscribe(writer)
    engine.subscribe(_reporter(say, len(plan.trials)))

    pidfile = out / PIDFILE
    pidfile.write_text(str(os.getpid()))
    previous = {
        s: signal.signal(
            s,
            lambda signum, _f: engine.emergency_stop(
                f"emergency stop ({signal.Signals(signum).name})"
            ),
        )
        for s in (signal.SIGINT, signal.SIGUSR1)
    }
    if sys.stdin is not None and sys.stdin.isatty():
        threading.Thread(target=_keyboard, args=(engine,), daemon=True).start()
        say("press Enter (or Ctrl-C) for an emergency stop")
    try:
        state = engine.run()
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        loop.close()
        writer.close()
        pidfile.unlink(missing_ok=True)
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


def stop_running(out_dir: str | Path) -> int:
    pidfile = Path(out_dir) / PIDFILE
    try:
        pid = int(pidfile.read_text().strip())
    except (OSError, ValueError):
        raise RunError(f"{pidfile}: no running session found (no readable pid file)") from None
    try:
        os.kill(pid, signal.SIGUSR1)
    except ProcessLookupError:
        pidfile.unlink(missing_ok=True)
        raise RunError(
            f"{pidfile}: process {pid} is not running (stale pid file removed)"
        ) from None
    return pid
