"""``steerlab rig-check``: a hands-off trial on a rig, and the identification of its wheel.

``--rig RIG.toml --out DIR``: one short perturbation trial with nobody touching the wheel, on
the same engine, loop and safety rules as ``steerlab run`` (the loop in its own process), recorded
in ``DIR/rigcheck.h5`` like any trial (attribute ``hands_off`` true), then identified into
``DIR/rig.json`` and ``DIR/index.html`` (:mod:`analysis.rigcheck`).

``--recording PATH --out DIR``: the identification alone, from a session file or an
interchange-format CSV.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

from steerlab.protocols.engine import SessionEngine, State
from steerlab.protocols.events import TrialStarted
from steerlab.protocols.protocol import Condition, Protocol, TrialTiming, load_protocol
from steerlab.protocols.session import SessionPlan, TrialSetup, TrialSpec, build_plan

SESSION_FILE = "rigcheck.h5"
CONDITION = "HANDS_OFF"
INSTRUCTIONS = "Rig check: let go of the wheel and do not touch it until the trial ends."
SUBJECT = "RIGCHECK"


class RigCheckRunError(ValueError):
    pass


@dataclass(frozen=True)
class HandsOffPlan(SessionPlan):
    """A one-trial session whose trial is hands off."""

    def setup(self, spec: TrialSpec, attempt: int = 1) -> TrialSetup:
        return replace(super().setup(spec, attempt), hands_off=True)

    def attributes(self) -> dict:
        return {**super().attributes(), "rig_check": True}


def hands_off_protocol(protocol: Protocol, periods: int = 3) -> Protocol:
    """The protocol's loop rate and wheel; a rig-check multisine; one hands-off trial."""
    from steerlab.analysis.rigcheck import hands_off_spec

    if periods < 1:
        raise RigCheckRunError(f"--periods must be ≥ 1, got {periods}")
    spec = hands_off_spec(protocol.wheel.stiffness_nm_per_rad)
    timing = TrialTiming(
        periods=periods,
        run_in_s=2.0,
        fade_in_s=1.0,
        fade_out_s=1.0,
        familiarization_trials=0,
        repetitions=1,
        break_between_trials_s=0.0,
        break_between_conditions_s=0.0,
    )
    text = (
        f"# rig check (hands off), derived from protocol {protocol.name!r}\n"
        f'name = "rigcheck"\nloop_rate_hz = {protocol.loop_rate_hz!r}\n'
        f"[trial]\nperiods = {periods}\nrun_in_s = 2.0\nfade_in_s = 1.0\nfade_out_s = 1.0\n"
        f"[perturbation]\n"
        + "".join(f"{k} = {v!r}\n" for k, v in spec.__dict__.items() if k != "crest_iterations")
        + f"[wheel]\ninertia_kgm2 = {protocol.wheel.inertia_kgm2!r}\n"
        f"damping_Nms_per_rad = {protocol.wheel.damping_nms_per_rad!r}\n"
        f"stiffness_Nm_per_rad = {protocol.wheel.stiffness_nm_per_rad!r}\n"
    )
    return replace(
        protocol,
        name="rigcheck",
        conditions=(Condition(CONDITION, math.inf, INSTRUCTIONS),),
        trial=timing,
        perturbation=spec,
        source_text=text,
    )


def hands_off_plan(protocol: Protocol, periods: int = 3) -> HandsOffPlan:
    p = hands_off_protocol(protocol, periods)
    plan = build_plan(p, 1, subject=SUBJECT)
    return HandsOffPlan(**{f: getattr(plan, f) for f in plan.__dataclass_fields__})


def mark_hands_off(writer):
    """The session writer, with the trial attribute ``hands_off`` true on every trial."""

    def on(e):
        if isinstance(e, TrialStarted):
            e = replace(e, attributes={**e.attributes, "hands_off": True})
        writer(e)

    return on


def record_hands_off(
    plan: HandsOffPlan, loop, path: Path, extra: dict, ended: list | None = None
) -> State:
    """Run the plan's trial through the engine into a new session file at ``path``;
    ``ended`` collects the TrialEnded events (status, reason)."""
    from steerlab.protocols.datafile import SessionWriter
    from steerlab.protocols.events import TrialEnded

    engine = SessionEngine(plan, loop)
    writer = SessionWriter(path, extra_attributes=extra)
    engine.subscribe(mark_hands_off(writer))
    if ended is not None:
        engine.subscribe(lambda e: ended.append(e) if isinstance(e, TrialEnded) else None)
    try:
        return engine.run()
    finally:
        writer.close()


def run_rig_check(
    rig_path: str | None,
    out_dir: str | Path,
    *,
    periods: int = 3,
    protocol_path: str | None = None,
    overwrite: bool = False,
    say=print,
):
    """The hands-off trial on the rig (in real time, in the loop's own process), then the fit."""
    import signal

    from steerlab.analysis.rigcheck import identify
    from steerlab.hardware.rig import load_rig
    from steerlab.hardware.trial_loops import rig_loop

    protocol = load_protocol(protocol_path)
    rig = load_rig(rig_path)
    if abs(protocol.loop_rate_hz - rig.loop_rate_hz) > 1e-9:
        raise RigCheckRunError(
            f"the protocol ({protocol.source_path}) runs its loop at {protocol.loop_rate_hz:g} Hz "
            f"but the rig ({rig.source}) at {rig.loop_rate_hz:g} Hz; make them agree"
        )
    out = Path(out_dir)
    path = out / SESSION_FILE
    if path.exists():
        if not overwrite:
            raise RigCheckRunError(f"{path}: exists already; pass --overwrite to replace it")
        from steerlab.analysis.rigcheck import FIGURE, INDEX_HTML, RIG_JSON

        for old in (path, out / RIG_JSON, out / INDEX_HTML, out / FIGURE):
            old.unlink(missing_ok=True)  # no earlier result may pass for this one
    out.mkdir(parents=True, exist_ok=True)
    plan = hands_off_plan(protocol, periods)
    say(f"bringing up the rig ({rig.source}) ...")
    say("RIG CHECK: let go of the wheel; nobody may touch it until the trial ends")
    loop = rig_loop(rig_path, 1)
    extra = {"rig": rig.describe(), "realtime_tuning": loop.realtime, "hands_off_check": True}
    if rig.simulated:
        extra["simulated"] = True
    previous = signal.signal(
        signal.SIGINT, lambda *_: loop.emergency_stop()
    )  # Ctrl-C: the motor stops at once; the trial ends as aborted
    ended: list = []
    try:
        state = record_hands_off(plan, loop, path, extra, ended)
    finally:
        signal.signal(signal.SIGINT, previous)
        loop.close()
    if state is not State.DONE:
        why = ended[-1].reason if ended and ended[-1].reason else f"engine {state.value}"
        raise RigCheckRunError(
            f"{path}: the hands-off trial did not complete: {why}; run again with --overwrite"
        )
    say(f"hands-off trial recorded: {path}")
    return identify(path, out, rig_path=rig_path, protocol_path=protocol_path)
