"""``steerlab run`` after a trial a fault aborted: ask the experimenter (a terminal), or redo,
go on or stop without asking (``--on-abort``). The aborted attempt stays in the file with its
samples; a redo is a new attempt. Faults are injected into the real loop process
(``ProcessLoop.inject``: the perturbation turns NaN, which aborts the trial at once)."""

from __future__ import annotations

import os
import pty
import select
import sys
import time
from dataclasses import dataclass

import pytest

import steerlab.app.run as run_module
from steerlab.app.run import ABORT_PROMPT, MAX_ABORTS_IN_A_ROW, RunError, run_session
from steerlab.hardware.live import ProcessLoop
from steerlab.protocols.datafile import SessionFile
from steerlab.protocols.engine import SessionEngine, State
from steerlab.protocols.protocol import parse_protocol
from steerlab.protocols.session import build_plan
from tests.helpers import ROOT
from tests.session_helpers import SHORT_TRIALS_KW, THREE_CONDITIONS, short_protocol

from .conftest import STARVED

# Three short trials (1.75 s each at 1 kHz), no breaks.
ABORT_PROTOCOL = short_protocol("abort-test", **SHORT_TRIALS_KW, conditions=THREE_CONDITIONS)
INJECTED = "non-finite motor command input"


@pytest.fixture
def protocol_file(tmp_path):
    p = tmp_path / "abort.toml"
    p.write_text(ABORT_PROTOCOL)
    return p


@dataclass
class Outcome:
    state: State
    started: list[str]  # trial keys in the order the loop ran them
    said: list[str]
    attempts: dict[int, list[tuple[int, str]]]
    reasons: dict[tuple[int, int], str | None]  # (trial, attempt) → why it was aborted
    samples: dict[tuple[int, int], int]

    def starved(self) -> bool:
        """A trial aborted because the (loaded, shared) test machine starved the loop."""
        return any(r and any(s in r for s in STARVED) for r in self.reasons.values())


def _faulty_loop(started: list[str], faulty: set[int]) -> type[ProcessLoop]:
    class FaultyLoop(ProcessLoop):
        def run_trial(self, setup, control):
            started.append(setup.key)
            inject = len(started) in faulty
            for i, block in enumerate(super().run_trial(setup, control)):
                if inject and i == 1:
                    self.inject("nan")
                yield block

    return FaultyLoop


def _session(monkeypatch, tmp_path, protocol_file, lenient_rig, faulty: set[int], **kw):
    """Run the session with ``steerlab run``'s code in this process; the loop's ``n``-th trial
    (from 1) gets the NaN fault for each ``n`` in ``faulty``. A session the machine starved is
    run again in a fresh folder."""
    for attempt in range(3):
        started: list[str] = []
        monkeypatch.setattr(run_module, "rig_loop", _faulty_loop(started, faulty))
        said: list[str] = []
        say = kw.pop("say", None)
        out = tmp_path / f"try{attempt}"
        state = run_session(
            str(lenient_rig), 1, out, protocol_path=str(protocol_file), breaks=False,
            say=say or said.append, **kw,
        )  # fmt: skip
        sf = SessionFile(out / "S01.h5")
        recs = sf.records()
        o = Outcome(
            state,
            started,
            said,
            sf.attempts(),
            {(r.trial_index, int(r.attrs["attempt"])): r.abort_reason for r in recs},
            {(r.trial_index, int(r.attrs["attempt"])): len(r.time_s) for r in recs},
        )
        if not o.starved():
            return o
        if say is not None:
            kw["say"] = say
    return o


def _check_recorded(o: Outcome) -> None:
    """Every attempt the loop ran is in the file, once; the injected ones aborted, with the
    samples they took before the fault."""
    assert sorted(o.reasons) == sorted(
        (int(k[:2]), int(k.rsplit("_a", 1)[1])) for k in o.started
    ), (o.started, o.attempts)
    for key, reason in o.reasons.items():
        if reason is not None:
            assert INJECTED in reason, (key, reason)
            assert o.samples[key] > 0


def test_redo_runs_the_aborted_trial_again_at_once(
    monkeypatch, tmp_path, protocol_file, lenient_rig
):
    o = _session(monkeypatch, tmp_path, protocol_file, lenient_rig, {1}, on_abort="redo")
    assert o.state is State.DONE
    assert [k[:2] for k in o.started] == ["01", "01", "02", "03"]
    assert o.attempts[1] == [(1, "aborted"), (2, "complete")]
    assert o.attempts[2] == [(1, "complete")] and o.attempts[3] == [(1, "complete")]
    _check_recorded(o)
    assert not any(ABORT_PROMPT in s for s in o.said)  # not asked


def test_next_goes_on_and_runs_the_aborted_trial_after_the_others(
    monkeypatch, tmp_path, protocol_file, lenient_rig
):
    o = _session(monkeypatch, tmp_path, protocol_file, lenient_rig, {1}, on_abort="next")
    assert o.state is State.DONE
    assert [k[:2] for k in o.started] == ["01", "02", "03", "01"]
    assert o.attempts[1] == [(1, "aborted"), (2, "complete")]
    _check_recorded(o)
    assert any("trial 1 is run again after the others" in s for s in o.said)


def test_without_a_terminal_an_abort_stops_the_session_by_default(
    monkeypatch, tmp_path, protocol_file, lenient_rig
):
    assert not sys.stdin.isatty()  # pytest's stdin; run_session then defaults to stop
    o = _session(monkeypatch, tmp_path, protocol_file, lenient_rig, {2})
    assert o.state is State.IDLE
    assert [k[:2] for k in o.started] == ["01", "02"]
    assert o.attempts == {1: [(1, "complete")], 2: [(1, "aborted")]}
    _check_recorded(o)
    assert "2 trial(s) to go" in o.said[-1]


def test_unattended_aborts_in_a_row_stop_the_session(
    monkeypatch, tmp_path, protocol_file, lenient_rig
):
    faulty = set(range(1, 10))  # the fault persists
    o = _session(monkeypatch, tmp_path, protocol_file, lenient_rig, faulty, on_abort="next")
    assert o.state is State.IDLE
    assert [k[:2] for k in o.started] == ["01", "02", "03"][:MAX_ABORTS_IN_A_ROW]
    _check_recorded(o)
    assert any(f"{MAX_ABORTS_IN_A_ROW} trials aborted in a row" in s for s in o.said)


def test_the_experimenter_is_asked_at_the_terminal(
    monkeypatch, tmp_path, protocol_file, lenient_rig
):
    """stdin is a pseudo-terminal: the reason, then the question; Enter (the emergency stop's
    key during a trial) and a wrong answer are asked again, not taken; r redoes, g goes on."""
    master, slave = pty.openpty()
    stdin = open(slave, encoding="utf-8")  # noqa: SIM115 (closed below)
    monkeypatch.setattr(sys, "stdin", stdin)
    answers = ["\n", "maybe\n", "r\n", "g\n"]
    said: list[str] = []

    def say(line: str) -> None:
        if line.startswith("bringing up the rig"):  # a session (again, if the first starved)
            said.clear()
        said.append(line)
        if line == ABORT_PROMPT:
            os.write(master, answers[sum(s == ABORT_PROMPT for s in said) - 1].encode())

    try:
        o = _session(monkeypatch, tmp_path, protocol_file, lenient_rig, {1, 2}, say=say)
    finally:
        os.close(master)
        stdin.close()
    assert o.state is State.DONE
    assert [k[:2] for k in o.started] == ["01", "01", "02", "03", "01"]
    assert o.attempts[1] == [(1, "aborted"), (2, "aborted"), (3, "complete")]
    _check_recorded(o)
    asked = [i for i, s in enumerate(said) if s == ABORT_PROMPT]
    assert len(asked) == 4
    reason = said[asked[0] - 1]
    assert "trial 1 (01_BT12_rep1_a1) was aborted" in reason and INJECTED in reason
    assert "'': please answer r, g or s" in said and "'maybe': please answer r, g or s" in said


def test_ask_needs_a_terminal(tmp_path, protocol_file):
    with pytest.raises(RunError, match="needs a terminal"):
        run_session(None, 1, tmp_path, protocol_path=str(protocol_file), on_abort="ask")
    assert not (tmp_path / "S01.h5").exists()


def test_a_deferred_trial_runs_after_the_others_and_a_redo_brings_it_back():
    plan = build_plan(parse_protocol(ABORT_PROTOCOL, "abort.toml"), 1)
    engine = SessionEngine(plan, loop=None)  # type: ignore[arg-type]  # no trial is run
    engine.defer(1)
    assert [t.trial_index for t in engine.pending()] == [2, 3, 1]
    engine.defer(2)
    assert [t.trial_index for t in engine.pending()] == [3, 1, 2]
    engine.redo(1)
    assert [t.trial_index for t in engine.pending()] == [1, 3, 2]


def _run_on_a_terminal(args: list[str], press_enter_at: bytes, limit_s: float = 120.0):
    """``python -m steerlab ARGS`` with a pseudo-terminal as its stdin and stdout (what a
    person sees); Enter is pressed once ``press_enter_at`` has been printed. (output, exit code)"""
    pid, fd = pty.fork()
    if pid == 0:  # the child: nothing of pytest's may run here
        try:
            os.chdir(ROOT)
            os.execv(sys.executable, [sys.executable, "-m", "steerlab", *args])
        finally:
            os._exit(127)
    out, pressed, end = b"", False, time.monotonic() + limit_s
    try:
        while time.monotonic() < end:
            if select.select([fd], [], [], 0.2)[0]:
                try:
                    data = os.read(fd, 4096)
                except OSError:  # the child closed the terminal: it has ended
                    break
                if not data:
                    break
                out += data
            if not pressed and press_enter_at in out:
                os.write(fd, b"\n")
                pressed = True
    finally:
        os.close(fd)
        if time.monotonic() >= end:
            os.kill(pid, 9)
        _, status = os.waitpid(pid, 0)
    return out.decode(errors="replace"), os.waitstatus_to_exitcode(status)


def test_a_stopped_session_on_a_terminal_prints_no_escape_codes_and_exits_with_3(
    tmp_path, protocol_file, lenient_rig
):
    """Enter during the second trial: an emergency stop ends the session, exit code 3 (the
    run subcommand's help lists it); nothing on the terminal but text."""
    out, code = _run_on_a_terminal(
        ["run", "--rig", str(lenient_rig), "--subject", "1", "--out", str(tmp_path / "d"),
         "--protocol", str(protocol_file), "--no-breaks", "--on-abort", "stop"],
        press_enter_at=b"trial 2/3",
    )  # fmt: skip
    assert "session stopped with" in out, out
    assert code == 3, out
    assert "\x1b" not in out, repr(out)


def test_the_run_help_lists_the_exit_codes(capsys):
    from steerlab.app.cli import main

    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = capsys.readouterr().out
    codes = text.split("exit codes:", 1)[1]
    for code, words in (("0", "complete"), ("2", "bad input"), ("3", "stopped before its end"),
                        ("130", "Ctrl-C")):  # fmt: skip
        assert f"  {code} " in codes and words in codes, text
