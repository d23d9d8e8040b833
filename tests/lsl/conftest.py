"""Helpers for the LSL tests: a short protocol, and an inlet on each of a publisher's streams."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from steerlab.protocols.protocol import parse_protocol
from tests.helpers import short_protocol_text as _short_protocol_text


def short_protocol_text(loop_rate_hz: float = 200.0) -> str:
    """The shared short protocol (4.75 s trials, 950 samples at 200 Hz), without breaks."""
    return _short_protocol_text(loop_rate_hz, no_breaks=True)


@pytest.fixture
def short_protocol():
    return parse_protocol(short_protocol_text(), "short.toml")


@pytest.fixture
def short_protocol_file(tmp_path):
    p = tmp_path / "short.toml"
    p.write_text(short_protocol_text())
    return p


class Receiver:
    """An inlet on a publisher's signal stream and one on its marker stream (found by the
    signal stream's ``source_id``), pulled on a thread until :meth:`stop`.

    Start it before the session: the inlets connect as soon as the outlets appear (a publisher
    made with ``wait_for_consumers_s`` waits for them before its first marker)."""

    def __init__(self, source_id: str, timeout_s: float = 30.0) -> None:
        self.source_id = source_id
        self.timeout_s = timeout_s
        self.samples: list[list[float]] = []
        self.stamps: list[float] = []
        self.markers: list[tuple[dict, float]] = []
        self.info = None
        self.marker_info = None
        self.error: BaseException | None = None
        self.connected = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="lsl-test-inlet", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import pylsl

        try:
            sig = pylsl.resolve_byprop("source_id", self.source_id, 1, self.timeout_s)
            mk = pylsl.resolve_byprop("source_id", f"{self.source_id}:markers", 1, self.timeout_s)
            if not sig or not mk:
                raise TimeoutError(f"no LSL stream {self.source_id!r} within {self.timeout_s} s")
            si = pylsl.StreamInlet(sig[0], max_buflen=360)
            mi = pylsl.StreamInlet(mk[0], max_buflen=360)
            si.open_stream(self.timeout_s)
            mi.open_stream(self.timeout_s)
            self.info, self.marker_info = si.info(), mi.info()
            self.connected.set()
            quiet_since = None
            while True:
                x, t = si.pull_chunk(timeout=0.05, max_samples=100_000)
                y, u = mi.pull_chunk(timeout=0.0)
                if x:
                    self.samples.extend(x)
                    self.stamps.extend(t)
                for (text,), ts in zip(y, u, strict=True):
                    self.markers.append((json.loads(text), ts))
                if self._stop.is_set():
                    if x or y:
                        quiet_since = None
                    elif quiet_since is None:
                        quiet_since = time.monotonic()
                    elif time.monotonic() - quiet_since > 0.5:
                        break
            si.close_stream()
            mi.close_stream()
            del si, mi
        except BaseException as e:  # reported by stop()
            self.error = e
            self.connected.set()

    def stop(self) -> Receiver:
        """Pull what is still on its way (until 0.5 s without any), then close the inlets."""
        self._stop.set()
        self._thread.join(60)
        assert not self._thread.is_alive(), "the test inlet did not stop"
        if self.error is not None:
            raise self.error
        return self

    @property
    def data(self) -> np.ndarray:
        return np.asarray(self.samples, dtype=float).reshape(-1, 7)

    def events(self) -> list[str]:
        return [m["event"] for m, _ in self.markers]


class OutletCount:
    """Counts the LSL outlets made (pylsl.StreamOutlet, wrapped)."""

    def __init__(self, monkeypatch) -> None:
        import pylsl

        self.made: list[str] = []
        real = pylsl.StreamOutlet

        def counting(info, *a, **kw):
            self.made.append(info.name())
            return real(info, *a, **kw)

        monkeypatch.setattr(pylsl, "StreamOutlet", counting)


@pytest.fixture
def outlets(monkeypatch):
    return OutletCount(monkeypatch)
