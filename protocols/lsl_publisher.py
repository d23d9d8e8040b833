"""Steerlab on the lab's clock: a session's signals and events on the Lab Streaming Layer (LSL),
so that LabRecorder records them beside EMG or EEG (``docs/lsl.md``).

Two engine subscribers, neither needing anything of the engine nor of Qt:

- :class:`LabClock` puts each trial's samples on the LSL clock (``pylsl.local_clock()``). The
  session writer asks it for the clock at each trial's first sample (the trial attributes
  ``lsl_clock_s`` and ``lsl_clock_source``, ``docs/data-format.md``), whether or not anything
  is published: a session file and an XDF file then go on one time line.
- :class:`LslPublisher` opens two outlets when the session starts and pushes what happens:

  * a signal stream (type ``Steerlab``, name ``Steerlab SUBJECT``): the channels of
    :data:`SIGNAL_CHANNELS`, labels and units in the stream's description, nominal rate the
    protocol's loop rate, every sample with its own time stamp on the LSL clock;
  * a marker stream (type ``Markers``, name ``Steerlab SUBJECT markers``, one string channel):
    one compact JSON object per event (:data:`MARKER_EVENTS`), e.g.
    ``{"event":"trial_start","key":"01_RT_fam_a1","trial_index":1,"condition":"RT",...}``.

  It hands every event to its clock first: subscribe the publisher *or*, when nothing is
  published, the clock alone, never both; and subscribe it before the session writer, so that
  the clock reads each block's arrival before the file's work on it (publishing takes
  microseconds and never raises).

How a sample gets its time stamp (``lsl_clock_source``):

- ``host monotonic``: a loop that keeps pace with the clock (``steerlab run``, the GUI,
  ``simulate --realtime``). The control loop records, per sample, ``host_time_s``: the host's
  ``time.monotonic()`` at that cycle's read of the sensors (:class:`hardware.loop.DeviceLoop`).
  Sample i is stamped ``host_time_s[i] + offset``, the offset ``local_clock() -
  time.monotonic()`` measured when the clock is made and again as each session starts (the
  two are the same clock on Linux, not on every platform); the trial records it
  (``lsl_clock_offset_s``) beside ``lsl_clock_s`` (sample 0's stamp). How late a block
  reaches the engine (a pipe from a loop in a process of its own, a busy engine thread) and a
  pause inside a trial then change nothing: each sample is where it was read.

  A block without ``host_time_s`` (a loop of another kind) is stamped from its arrival: the
  trial's sample 0 at the block's arrival on the LSL clock less the block's span
  (``time_s``), sample k at that + k / fs, late by what handing the block over took. After a
  pause inside such a trial the timeline is taken again, the same way, from the first block
  after the resume; and when two blocks in a row come more than ``resync_periods`` late (a
  loop in this process that carries on from then, :func:`lab_clock_for`), the timeline
  follows.
- ``synthetic``: a loop faster than real time (``steerlab simulate``'s batch mode, the GUI's
  stepped loop in tests). The timeline starts at the LSL clock when the first block arrives
  and advances by 1 / fs a sample, however fast the samples are computed; each trial starts
  where the previous one ended or at the LSL clock, whichever is later, so trials never
  overlap. Such time stamps run ahead of the wall clock: they order and space the samples,
  they do not say when anything happened.

Nothing here may stop a session. Without a working pylsl (a broken liblsl) the clock records
nothing and says so once; an outlet that cannot be made or fed is given up with a warning, and
the session (and its file) go on as without LSL.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from steerlab.protocols import events as ev
from steerlab.protocols.datafile import UNITS, software_version

log = logging.getLogger(__name__)

#: The signal stream's channels, in this order (the loop's channel names; a block without one
#: sends NaN in its place).
SIGNAL_CHANNELS = (
    "wheel_angle_rad",
    "driver_torque_Nm",
    "perturbation_torque_Nm",
    "grip_force_N",
    "grip_force_left_N",
    "grip_force_right_N",
    "motor_command_Nm",
)
#: The channels' kinds, for the description (the XDF meta-data convention's ``type``).
CHANNEL_TYPES = {
    "wheel_angle_rad": "Angle",
    "driver_torque_Nm": "Torque",
    "perturbation_torque_Nm": "Torque",
    "grip_force_N": "Force",
    "grip_force_left_N": "Force",
    "grip_force_right_N": "Force",
    "motor_command_Nm": "Torque",
}
SIGNAL_TYPE = "Steerlab"
MARKER_TYPE = "Markers"
#: What the marker stream says, in the ``event`` field of each JSON marker.
MARKER_EVENTS = (
    "session_start",  # subject, n_trials, protocol, run (1, 2, … for each run of the engine)
    "trial_start",  # key, trial_index, condition, repetition, familiarization, attempt; at sample 0
    "pause",  # key, sample; at that sample
    "resume",  # key, sample; when the trial goes on
    "abort",  # key, trial_index, reason; at the trial's end (before its trial_stop)
    "trial_stop",  # key, trial_index, condition, status, reason, n_samples; after its last sample
    "superseded",  # key, trial_index, reason: an earlier attempt replaced by a redo
    "engine_broken",  # reason
    "session_stop",  # state, completed, remaining
)

HOST = "host monotonic"
SYNTHETIC = "synthetic"
CLOCK_SOURCES = (HOST, SYNTHETIC)

#: ``STEERLAB_LSL=on|off`` in the environment: whether ``steerlab run``, ``steerlab simulate``
#: and the GUI publish when no ``--lsl``/``--no-lsl`` is given.
LSL_ENV = "STEERLAB_LSL"
_TRUE = {"1", "on", "yes", "true"}
_FALSE = {"0", "off", "no", "false"}


_warned: set[str] = set()


def _warn_once(what: str, warn: Callable[[str], object] | None = None) -> None:
    if what in _warned:
        return
    _warned.add(what)
    (warn or log.warning)(what)


def publish_default(default: bool, environ: dict | None = None, *, strict: bool = True) -> bool:
    """Whether to publish when no flag says: :data:`LSL_ENV` if set, else ``default``.

    :raises ValueError: :data:`LSL_ENV` is set to something else than on/off (not ``strict``:
        a warning, and ``default``)."""
    env = os.environ if environ is None else environ
    raw = env.get(LSL_ENV)
    if raw is None or raw.strip() == "":
        return default
    v = raw.strip().lower()
    if v in _TRUE:
        return True
    if v in _FALSE:
        return False
    problem = f"{LSL_ENV}={raw!r}: say on or off"
    if strict:
        raise ValueError(problem)
    _warn_once(f"{problem}; LSL publishing stays {'on' if default else 'off'}")
    return default


def load_pylsl() -> tuple[Any, str | None]:
    """(the pylsl module, None), or (None, why not): a missing package or a liblsl that does not
    load. Imported here, at first use: ``LSLAPICFG`` must be set before (``docs/lsl.md``)."""
    try:
        import pylsl

        pylsl.local_clock()  # a library that loads but does not answer is no better
        return pylsl, None
    except Exception as e:  # ImportError, RuntimeError (no liblsl), OSError (a broken one)
        return None, f"LSL not available ({type(e).__name__}: {e})"


def measure_offset(local_clock: Callable[[], float], reads: int = 5) -> float:
    """``local_clock() - time.monotonic()``, from the read bracketed most tightly."""
    best = (math.inf, 0.0)
    for _ in range(reads):
        m0 = time.monotonic()
        lc = local_clock()
        m1 = time.monotonic()
        best = min(best, (m1 - m0, lc - (m0 + m1) / 2))
    return best[1]


class LabClock:
    """Each trial's samples on the LSL clock; an engine subscriber (see the module docstring).

    ``source``: :data:`HOST` or :data:`SYNTHETIC`. ``resync_periods`` (host monotonic only):
    when two blocks in a row arrive more than this many sample periods after the timeline says
    their last sample was taken, the timeline is put where the second says (None: never). For
    a loop in this process that carries on from now when its consumer held it up (the simulated
    rig's paced :class:`hardware.loop.DeviceLoop`, :func:`lab_clock_for`); not for a loop in a
    process of its own, whose samples keep to their schedule however late they are handed over.
    ``lsl``: the pylsl module to use (None: import it). ``warn``: where the one warning about a
    missing LSL goes (default: logging).
    """

    def __init__(
        self,
        source: str = HOST,
        *,
        resync_periods: float | None = None,
        lsl: Any = None,
        warn: Callable[[str], object] | None = None,
    ) -> None:
        if source not in CLOCK_SOURCES:
            raise ValueError(f"clock source: {' or '.join(CLOCK_SOURCES)}, not {source!r}")
        self.source = source
        self.resync_periods = resync_periods if source == HOST else None
        self.resyncs = 0  # how often the timeline was put later (a resume, a held-up loop)
        self.problem: str | None = None
        if lsl is None:
            lsl, self.problem = load_pylsl()
        self.lsl = lsl
        self._local_clock: Callable[[], float] | None = None
        self.offset_s: float | None = None  # local_clock() - time.monotonic()
        if lsl is not None:
            self._local_clock = lsl.local_clock
            self.offset_s = measure_offset(lsl.local_clock)
        else:
            _warn_once(
                f"{self.problem}: the session runs, but its trials record no lsl_clock_s and "
                "nothing is published on LSL",
                warn,
            )
        self._fs: dict[str, float] = {}
        self._anchor: dict[str, float] = {}  # trial key → LSL time of its sample 0
        self._host_stamped: set[str] = set()  # trials stamped from their host_time_s
        self._last_stamp: dict[str, tuple[int, float]] = {}  # (sample, stamp) of the newest
        self._resumed: set[str] = set()  # trials whose timeline is taken again at the next block
        self._checked: tuple[str, int] | None = None  # the block last looked at
        self._late: str | None = None  # the trial whose last block came late
        self._floor = -math.inf  # synthetic: where the latest trial's timeline ended

    @property
    def available(self) -> bool:
        return self._local_clock is not None

    def now(self) -> float | None:
        """The LSL clock now (None without LSL)."""
        return self._local_clock() if self._local_clock is not None else None

    # -- the timeline ---------------------------------------------------------------------------
    def __call__(self, event: object) -> None:
        try:
            self._follow(event)
        except Exception as e:  # the clock must never stop the session
            _warn_once(f"LSL clock: {type(e).__name__}: {e}; the time stamps may be off")

    def _follow(self, event: object) -> None:
        match event:
            case ev.SessionStarted() if self._local_clock is not None:
                # The offset as the clock starts (the two clocks may drift apart on a platform
                # where they are not the same one); each trial records the one it was stamped with.
                self.offset_s = measure_offset(self._local_clock)
            case ev.TrialStarted():
                # One trial at a time: what the earlier ones needed is done with.
                self._anchor.clear()
                self._fs.clear()
                self._host_stamped.clear()
                self._last_stamp.clear()
                self._resumed.clear()
                fs = event.attributes.get("fs_hz")
                if fs:
                    self._fs[event.key] = float(fs)
            case ev.SamplesAcquired():
                self.anchor(event)
                host = event.channels.get("host_time_s")
                stamped = event.key in self._host_stamped and self.offset_s is not None
                if stamped and host is not None and event.n:
                    last = float(host[-1]) + (self.offset_s or 0.0)
                    self._last_stamp[event.key] = (event.start + event.n - 1, last)
            case ev.TrialMark(kind="resume") if self.source == HOST:
                if event.key in self._anchor and event.key not in self._host_stamped:
                    # The samples after the resume are taken from then on: the timeline is
                    # taken again from the next block's arrival.
                    self._resumed.add(event.key)
            case ev.TrialEnded():
                end = self.at_sample(event.key, event.n_samples)
                if end is not None:
                    self._floor = max(self._floor, end)

    def _fs_of(self, e: ev.SamplesAcquired) -> float | None:
        fs = self._fs.get(e.key)
        if fs is None:
            t = e.channels.get("time_s")
            if t is not None and len(t) > 1 and t[1] > t[0]:
                fs = self._fs[e.key] = 1.0 / float(t[1] - t[0])
        return fs

    def _times(self, e: ev.SamplesAcquired) -> np.ndarray | None:
        """The block's samples' times in the trial, s (its ``time_s``, or index / fs)."""
        t = e.channels.get("time_s")
        if t is not None:
            return np.asarray(t, dtype=float)
        fs = self._fs_of(e)
        return None if not fs else (e.start + np.arange(e.n)) / fs

    def anchor(self, e: ev.SamplesAcquired) -> float | None:
        """The LSL time of the trial's sample 0 (``time_s`` = 0), fixed at its first block (in
        real time, put later at the first block after a resume, and by ``resync_periods``)."""
        key = e.key
        a = self._anchor.get(key)
        if self._local_clock is None or (a is not None and self._checked == (key, e.start)):
            return a  # asked again about the same block (the writer, the publisher)
        self._checked = (key, e.start)
        t = self._times(e)
        if t is None or not len(t):
            return a
        fs = self._fs_of(e)
        if a is not None:
            if self.source != HOST or key in self._host_stamped:
                return a
            if key not in self._resumed and not self.resync_periods:
                return a
            arrived = self._local_clock() - float(t[-1])  # the block's arrival less its span
            late = fs is not None and (arrived - a) * fs > (self.resync_periods or math.inf)
            # Late twice in a row: the loop carries on later (a loop held up within a block
            # catches up in the next, whose last sample is on time again).
            if key in self._resumed or (late and self._late == key):
                self._resumed.discard(key)
                self.resyncs += 1
                a = self._anchor[key] = arrived
                late = False
            self._late = key if late else None
            return a
        host = e.channels.get("host_time_s")
        if self.source == HOST and host is not None and self.offset_s is not None:
            a = float(host[0]) + self.offset_s - float(t[0])
            self._host_stamped.add(key)
        elif self.source == HOST:
            a = self._local_clock() - float(t[-1])  # the block's arrival less its span
        else:
            a = max(self._local_clock(), self._floor) - float(t[0])
        self._anchor[key] = a
        return a

    def at_sample(self, key: str, sample: int) -> float | None:
        """The LSL time of sample ``sample`` of trial ``key`` (None before its first block). In
        a trial stamped from its ``host_time_s``, a sample after the newest is put that many
        periods after the newest's stamp (a pause shifts the samples, not the nominal line)."""
        a, fs = self._anchor.get(key), self._fs.get(key)
        if a is None or not fs:
            return None
        last = self._last_stamp.get(key)
        if last is not None and sample > last[0]:
            return last[1] + (sample - last[0]) / fs
        return a + sample / fs

    def timestamps(self, e: ev.SamplesAcquired) -> np.ndarray | None:
        """Each sample's LSL time stamp (None without LSL)."""
        a = self.anchor(e)
        if a is None:
            return None
        host = e.channels.get("host_time_s")
        if e.key in self._host_stamped and host is not None and self.offset_s is not None:
            return np.asarray(host, dtype=float) + self.offset_s
        t = self._times(e)
        return None if t is None else a + t

    def first_sample_attributes(self, e: ev.SamplesAcquired) -> dict:
        """For the session writer, at a trial's first block: ``lsl_clock_s`` (the LSL clock at
        the trial's first sample) and ``lsl_clock_source``; and, for a trial stamped from its
        ``host_time_s``, ``lsl_clock_offset_s`` (the ``local_clock() - time.monotonic()`` it
        was stamped with: sample i's stamp is host_time_s[i] + that); {} without LSL."""
        ts = self.timestamps(e)
        if ts is None or not len(ts):
            return {}
        attrs = {"lsl_clock_s": float(ts[0]), "lsl_clock_source": self.source}
        if e.key in self._host_stamped and self.offset_s is not None:
            attrs["lsl_clock_offset_s"] = float(self.offset_s)
        return attrs


def marker(event: str, **fields: object) -> str:
    """One marker: a compact JSON object, ``event`` first."""
    return json.dumps({"event": event, **fields}, separators=(",", ":"), default=str)


def source_id_for(rig: str, subject: str, session_path: str | Path | None = None) -> str:
    """The signal stream's ``source_id``: the same for a rig, a subject and a session file
    every time (LabRecorder finds a stream again by it after a restart, a resume)."""
    sid = f"steerlab:{rig}:{subject}"
    if session_path is not None:
        digest = hashlib.sha1(str(Path(session_path).resolve()).encode()).hexdigest()[:10]
        sid += f":{digest}"
    return sid


def _loop_rate(protocol_text: str) -> float | None:
    try:
        v = tomllib.loads(protocol_text).get("loop_rate_hz")
        return float(v) if v else None
    except (tomllib.TOMLDecodeError, TypeError, ValueError):
        return None


class LslPublisher:
    """Publishes a session on LSL; an engine subscriber (see the module docstring).

    ``clock``: the :class:`LabClock` whose timeline the samples are stamped on (the one the
    session writer asks; None: a new one, host monotonic). ``rig``: a name for the rig, in the
    streams' description and source_id (e.g. the rig file's name, ``simulated``).
    ``session_path``: the session file, to make the source_id one per session file.
    ``nominal_rate_hz``: the signal stream's rate (None: the protocol's ``loop_rate_hz``, else
    the first trial's fs). ``wait_for_consumers_s``: when the session starts, wait up to this
    long for an inlet on both streams (a test's, a recorder's) before the first trial.
    ``warn``: where warnings go (default: logging).

    ``attach(engine)`` subscribes it; ``close()`` removes the outlets (the streams vanish from
    the network). :attr:`problem` says why it stopped publishing, if it did.
    """

    def __init__(
        self,
        clock: LabClock | None = None,
        *,
        rig: str = "steerlab",
        session_path: str | Path | None = None,
        nominal_rate_hz: float | None = None,
        wait_for_consumers_s: float = 0.0,
        warn: Callable[[str], object] | None = None,
    ) -> None:
        self.clock = clock if clock is not None else LabClock(HOST, warn=warn)
        self.rig = rig
        self.session_path = session_path
        self.nominal_rate_hz = nominal_rate_hz
        self.wait_for_consumers_s = wait_for_consumers_s
        self.warn = warn or log.warning
        self.lsl = self.clock.lsl
        self.problem: str | None = self.clock.problem
        self.signals: Any = None  # the outlets, once the session started
        self.markers: Any = None
        self.name: str | None = None
        self.source_id: str | None = None
        self._runs = 0
        self._trial: ev.TrialStarted | None = None
        self._started: set[str] = set()  # trials whose trial_start is out
        self._last_marker = -math.inf
        self._session: ev.SessionStarted | None = None

    def attach(self, engine) -> LslPublisher:
        engine.subscribe(self)
        return self

    @property
    def publishing(self) -> bool:
        return self.problem is None and self.signals is not None

    def close(self) -> None:
        self.signals = self.markers = None  # pylsl destroys an outlet with its last reference

    # -- events ----------------------------------------------------------------------------------
    def __call__(self, event: object) -> None:
        self.clock(event)
        if self.problem is not None:
            return
        try:
            self._handle(event)
        except Exception as e:  # publishing must never stop the session
            self._give_up(f"{type(e).__name__}: {e}")

    def _give_up(self, why: str) -> None:
        self.problem = why
        self.warn(f"LSL: stopped publishing ({why}); the session and its file go on without it")
        self.close()

    def _handle(self, e: object) -> None:
        match e:
            case ev.SessionStarted():
                self._runs += 1
                if self.markers is None:  # the first run of the engine (a later one: the same)
                    self._open(e)
                    if self.problem is not None:
                        return
                self._mark(
                    marker(
                        "session_start",
                        subject=e.subject,
                        n_trials=e.n_trials,
                        protocol=e.attributes.get("protocol_name"),
                        run=self._runs,
                    ),
                    self.clock.now(),
                )
            case ev.TrialStarted():
                self._trial = e
                if self.signals is None and self.name is not None:
                    self._open_signals(float(e.attributes.get("fs_hz") or 0.0))
            case ev.SamplesAcquired():
                self._samples(e)
            case ev.TrialMark():
                self._trial_start_if_due(e.key)
                at = self.clock.at_sample(e.key, e.sample)
                if e.kind == "resume" and self.clock.source == HOST:
                    at = self.clock.now()  # the loop goes on from now
                fields: dict[str, object] = {"key": e.key, "sample": e.sample}
                if e.detail:
                    fields["detail"] = e.detail
                self._mark(marker(e.kind, **fields), at)
            case ev.TrialEnded():
                self._trial_start_if_due(e.key)
                at = self.clock.at_sample(e.key, e.n_samples)
                t = self._trial if self._trial is not None and self._trial.key == e.key else None
                if e.status == "aborted":
                    self._mark(
                        marker("abort", key=e.key, trial_index=e.trial_index, reason=e.reason), at
                    )
                self._mark(
                    marker(
                        "trial_stop",
                        key=e.key,
                        trial_index=e.trial_index,
                        condition=t.condition if t else None,
                        status=e.status,
                        reason=e.reason,
                        n_samples=e.n_samples,
                    ),
                    at,
                )
            case ev.TrialSuperseded():
                self._mark(
                    marker("superseded", key=e.key, trial_index=e.trial_index, reason=e.reason),
                    self.clock.now(),
                )
            case ev.StateChanged(new="broken"):
                self._mark(marker("engine_broken", reason=e.reason), self.clock.now())
            case ev.SessionEnded():
                self._mark(
                    marker(
                        "session_stop",
                        state=e.state,
                        completed=e.completed,
                        remaining=e.remaining,
                    ),
                    self.clock.now(),
                )

    # -- outlets ---------------------------------------------------------------------------------
    def _open(self, e: ev.SessionStarted) -> None:
        lsl = self.lsl
        self.name = f"Steerlab {e.subject}"
        self.source_id = source_id_for(self.rig, e.subject, self.session_path)
        self._session = e
        try:
            info = lsl.StreamInfo(
                f"{self.name} markers", MARKER_TYPE, 1, lsl.IRREGULAR_RATE, "string",
                f"{self.source_id}:markers",
            )  # fmt: skip
            self._describe(info.desc(), e)
            self.markers = lsl.StreamOutlet(info)
        except Exception as x:
            self._give_up(f"cannot open the marker outlet: {type(x).__name__}: {x}")
            return
        rate = self.nominal_rate_hz or _loop_rate(e.protocol_text)
        if rate:
            self._open_signals(rate)  # else at the first trial, with its fs
        self._wait()

    def _open_signals(self, rate: float) -> None:
        lsl = self.lsl
        try:
            info = lsl.StreamInfo(
                self.name, SIGNAL_TYPE, len(SIGNAL_CHANNELS), rate or lsl.IRREGULAR_RATE,
                "double64", self.source_id,
            )  # fmt: skip
            desc = info.desc()
            channels = desc.append_child("channels")
            for c in SIGNAL_CHANNELS:
                ch = channels.append_child("channel")
                ch.append_child_value("label", c)
                ch.append_child_value("unit", UNITS.get(c, ""))
                ch.append_child_value("type", CHANNEL_TYPES[c])
            if self._session is not None:
                self._describe(desc, self._session)
            self.signals = lsl.StreamOutlet(info)
        except Exception as x:
            self._give_up(f"cannot open the signal outlet: {type(x).__name__}: {x}")

    def _describe(self, desc, e: ev.SessionStarted) -> None:
        acq = desc.append_child("acquisition")
        acq.append_child_value("manufacturer", "Steerlab")
        acq.append_child_value("model", self.rig)
        acq.append_child_value("software_version", software_version())
        s = desc.append_child("steerlab")
        s.append_child_value("subject", e.subject)
        s.append_child_value("rig", self.rig)
        s.append_child_value("protocol_name", str(e.attributes.get("protocol_name", "")))
        s.append_child_value("clock_source", self.clock.source)
        s.append_child_value("session_attributes", json.dumps(e.attributes, default=str))

    def _wait(self) -> None:
        if self.wait_for_consumers_s <= 0:
            return
        end = time.monotonic() + self.wait_for_consumers_s
        for outlet in (self.signals, self.markers):
            if outlet is not None:
                outlet.wait_for_consumers(max(0.0, end - time.monotonic()))

    # -- pushing ---------------------------------------------------------------------------------
    def _mark(self, text: str, at: float | None, *, exact: bool = False) -> None:
        if self.markers is None:
            return
        if at is None:
            at = self.clock.now()
        if at is None:  # no clock: publishing needs one, so never here
            return
        if not exact:  # markers in time order (a trial's start is its first sample's time)
            at = max(at, self._last_marker)
        self._last_marker = max(self._last_marker, at)
        self.markers.push_sample([text], at)

    def _trial_start_if_due(self, key: str) -> None:
        if key in self._started:
            return
        self._started.add(key)
        t = self._trial if self._trial is not None and self._trial.key == key else None
        fields: dict[str, object] = {"key": key}
        if t is not None:
            fields |= {
                "trial_index": t.trial_index,
                "condition": t.condition,
                "repetition": t.attributes.get("repetition"),
                "familiarization": bool(t.attributes.get("familiarization", False)),
                "attempt": t.attempt,
            }
        at = self.clock.at_sample(key, 0)
        self._mark(marker("trial_start", **fields), at, exact=at is not None)

    def _samples(self, e: ev.SamplesAcquired) -> None:
        ts = self.clock.timestamps(e)
        if ts is None:
            return
        self._trial_start_if_due(e.key)
        if self.signals is None:
            return
        n = e.n
        data = np.empty((n, len(SIGNAL_CHANNELS)))
        for j, c in enumerate(SIGNAL_CHANNELS):
            v = e.channels.get(c)
            data[:, j] = np.nan if v is None else v
        self.signals.push_chunk(data, ts.tolist())


#: :func:`lab_clock_for`: how late (sample periods) a block of an in-process paced loop may
#: come before the timeline follows it. Such a loop runs missed cycles back to back when it
#: is less than two periods late, and carries on from now when later.
RESYNC_PERIODS = 2.0


def lab_clock_for(loop: object, **kw: Any) -> LabClock:
    """The clock for ``loop``: :data:`SYNTHETIC` for a loop that does not keep pace with the
    clock (``realtime`` False: the GUI's stepped loop); host monotonic else, and following the
    loop when it is held up for one that runs in this process and carries on from now
    (``pause_fades_out`` False: the simulated rig's paced loop). A batch loop says nothing of
    its pace: its caller knows (``steerlab simulate``)."""
    realtime = getattr(loop, "realtime", None)
    if realtime is False:
        return LabClock(SYNTHETIC, **kw)
    in_process = realtime is True and getattr(loop, "pause_fades_out", True) is False
    return LabClock(HOST, resync_periods=RESYNC_PERIODS if in_process else None, **kw)


def lab_subscriber(clock: LabClock, publish: bool, **publisher: Any) -> LabClock | LslPublisher:
    """What to subscribe to the engine: a publisher on ``clock``, or the clock alone."""
    if not publish or not clock.available:
        return clock
    return LslPublisher(clock, **publisher)


def close_lab_subscriber(sub: object) -> None:
    if isinstance(sub, LslPublisher):
        with contextlib.suppress(Exception):
            sub.close()
