"""Fixtures of the grip-source tests.

``grip_session`` runs one short trial of a simulated rig through the real control loop
(:class:`hardware.live.RigDevices`, the engine, the session file), as tests/live does.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest


def lenient_text(rig_file: Path, **limits: str) -> str:
    """The rig file's text with the behaviour tests' lenient limits (tests.helpers: a glove
    timeout of 2 s, say) and ``limits``."""
    from tests.helpers import lenient_rig_text

    return lenient_rig_text(rig_file.read_text(), **limits)


def lenient(rig_file: Path, **limits: str):
    """:func:`lenient_text` of the rig file, loaded (a RigConfig)."""
    import tempfile

    from steerlab.hardware.rig import load_rig

    with tempfile.TemporaryDirectory() as where:
        p = Path(where) / rig_file.name
        p.write_text(lenient_text(rig_file, **limits))
        return load_rig(p)


@pytest.fixture
def world_grip(monkeypatch) -> list[float]:
    """Every grip (left + right, N) the simulated subject's world gave the simulated grip
    device, from now on (WorldPlant.grip, recorded)."""
    from steerlab.hardware.sim.devices import WorldPlant

    sums: list[float] = []
    original = WorldPlant.grip

    def grip(self, t):
        g = original(self, t)
        sums.append(g[0] + g[1])
        return g

    monkeypatch.setattr(WorldPlant, "grip", grip)
    return sums


def nearest_gap(values: np.ndarray, produced: list[float]) -> np.ndarray:
    """How far each of ``values`` is from the nearest of ``produced``."""
    p = np.unique(np.asarray(produced, dtype=float))
    i = np.searchsorted(p, values).clip(1, max(len(p) - 1, 1))
    return np.minimum(np.abs(values - p[i - 1]), np.abs(values - p[np.minimum(i, len(p) - 1)]))


@pytest.fixture
def grip_session(tmp_path):
    """``run(rig, inject=None, at_s=1.0)``: one short trial (tests/live's SHORT_PROTOCOL, 4 s)
    of ``rig`` (a RigConfig) for subject 2, with ``inject(devices)`` called once ``at_s`` of
    samples are in; (state, records, the SamplesAcquired events, the RigDevices). Run again
    (up to 3 times) while the trial was aborted only because the test process was starved of
    the CPU (tests.live.conftest.starved). The devices are closed at the test's end."""
    from steerlab.hardware.live import RigDevices
    from steerlab.protocols import events as ev
    from steerlab.protocols.datafile import SessionFile, SessionWriter
    from steerlab.protocols.engine import SessionEngine
    from steerlab.protocols.protocol import parse_protocol
    from steerlab.protocols.session import build_plan
    from tests.live.conftest import SHORT_PROTOCOL, starved

    opened: list[RigDevices] = []
    protocol = parse_protocol(SHORT_PROTOCOL, "short.toml")

    def once(rig, inject: Callable | None, at_s: float, attempt: int):
        devices = RigDevices(rig, subject_number=2)
        opened.append(devices)
        plan = build_plan(protocol, 2)
        eng = SessionEngine(replace(plan, trials=plan.trials[:1]), devices.device_loop())
        path = tmp_path / f"attempt{attempt}" / "S02.h5"
        path.parent.mkdir()
        eng.subscribe(SessionWriter(path))
        seen: list = []
        fired = threading.Event()

        def on(e):
            if not isinstance(e, ev.SamplesAcquired):
                return
            seen.append(e)
            if inject is not None and e.start >= at_s * 1000 and not fired.is_set():
                fired.set()
                threading.Thread(target=inject, args=(devices,), daemon=True).start()

        eng.subscribe(on)
        state = eng.run()
        return state, SessionFile(path).records(), seen, devices

    def run(rig, inject: Callable | None = None, at_s: float = 1.0):
        for attempt in range(3):
            result = once(rig, inject, at_s, attempt)
            if not starved(result[1]):
                break
            result[3].close()
        return result

    yield run
    for devices in opened:
        devices.close()


@pytest.fixture
def lab_session(tmp_path):
    """``run(rig_file, trials=1, between=None)``: the first ``trials`` trials of the short
    protocol for subject 2 as ``steerlab run`` has them on a simulated rig: the simulated
    devices in a lab process of their own, the loop in another (:class:`ProcessLoop`), the rig
    file with :func:`lenient_text`'s limits. ``between(loop)`` runs once, after the first
    trial. Returns (the records, the lab's grip address, its pty); run again (up to 3 times)
    while a trial was aborted only because the machine starved the processes of the CPU."""
    from steerlab.hardware.live import ProcessLoop
    from steerlab.protocols import events as ev
    from steerlab.protocols.datafile import SessionFile, SessionWriter
    from steerlab.protocols.engine import SessionEngine
    from steerlab.protocols.protocol import parse_protocol
    from steerlab.protocols.session import build_plan
    from tests.live.conftest import SHORT_PROTOCOL, starved

    plan = build_plan(parse_protocol(SHORT_PROTOCOL, "short.toml"), 2)

    def run(rig_file: Path, trials: int = 1, between: Callable | None = None):
        for attempt in range(3):
            where = tmp_path / f"lab{attempt}"
            where.mkdir()
            rig = where / rig_file.name
            rig.write_text(lenient_text(rig_file))
            loop = ProcessLoop(str(rig), 2)
            try:
                assert loop.lab is not None
                address, pty = loop.lab.grip, loop.lab.pty
                eng = SessionEngine(replace(plan, trials=plan.trials[:trials]), loop)
                eng.subscribe(SessionWriter(where / "S02.h5"))
                done = threading.Event()

                def on(e, loop=loop, done=done):
                    if isinstance(e, ev.TrialEnded) and between and not done.is_set():
                        done.set()
                        between(loop)

                eng.subscribe(on)
                eng.run()
            finally:
                loop.close()
            records = SessionFile(where / "S02.h5").records()
            if not starved(records[:1]):
                break
        return records, address, pty

    return run
