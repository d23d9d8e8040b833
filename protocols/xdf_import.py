"""``steerlab import-xdf``: the streams of an XDF recording onto the trials of session files.

A lab records every device on LSL with LabRecorder (or :class:`protocols.xdf_writer.LslRecorder`)
into one XDF file, Steerlab's own streams among them when the session published them
(``protocols/lsl_publisher.py``). This module puts the other streams (EMG, EEG, a force plate,
markers) onto the trials of the session files (``docs/import.md``):

**Reading.** ``pyxdf.load_xdf`` reads the file; each stream's time stamps are put on the
recorder's clock from its ClockOffset chunks (``synchronize_clocks``, with pyxdf's handling of
a clock reset of the stream's computer). Jitter removal is off by default (the time stamps as
recorded; ``dejitter=True`` asks pyxdf to put a regular stream's stamps on a straight line). A
stream without samples is named and left out.

**Matching trials.** A trial's sample i was taken at ``host_time_s[i] + lsl_clock_offset_s`` on
the session computer's LSL clock where the trial records both and its ``lsl_clock_source`` is
``host monotonic`` (exact across a pause of the loop), else at ``lsl_clock_s + time_s[i]``; t0 is
where that time line's 0 is on the recording's clock:

* ``markers``: Steerlab's marker stream in the same file (type ``Markers``, its source_id
  ``steerlab:…:markers``): each ``trial_start`` marker names its trial (``key``, the trial group;
  the subject from the stream's description) and is stamped at the trial's sample 0: t0 is its
  time stamp. Only the trials the recording saw start are matched.
* ``clock``: the trial's LSL times, moved onto the recorder's clock by one straight line fitted
  through the clock offsets of one Steerlab stream of the trial's own subject (none in the file:
  the session ran on the recording's clock, and that is said). Only the trials of the subjects
  the file's Steerlab streams name are placed. A clock reset of the session computer is not
  followed by the line (said when the offsets lie off it); markers are, by pyxdf.
* ``auto`` (default): markers when the file has Steerlab's marker stream, else the clock.

When Steerlab's signal stream is in the file, each matched trial is checked against it: every
trial sample must be there, at its time, with the file's values (:func:`check_steerlab_stream`);
what is not is reported.

**Resampling** (``analysis/alignment.py``): ``linear`` interpolation for a regular numeric stream
at or above the trial's rate, ``hold`` (zero-order hold, the latest sample) for a slower or
irregular one; ``method=`` forces one. The method is recorded on each channel.

**Where it goes** (``protocols/trial_extras.py``): per stream channel a dataset
``xdf_STREAM_LABEL`` (float64, the channel's unit from the stream's description, else
``unknown``) in each matched trial, and the stream's samples within the trial as recorded in
``imported/xdf_STREAM`` (``time_s`` on the trial's time line, ``values`` in the stream's own
type, or ``text`` for a string stream, which gets no channel). Two streams whose names would
give the same channel name both get their stream id in their names.

**Problems** are said, naming the file, the stream and the trial, and the rest goes on: a stream
without samples in a trial is not imported for that trial; a stream whose samples overlap no
trial is named; nothing is written when no stream overlaps any trial.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from steerlab.analysis.alignment import choose_method, max_gap_for, resample
from steerlab.protocols.datafile import (
    DataFileError,
    SessionFile,
    open_for_reading,
    read_channel,
    session_files,
)
from steerlab.protocols.trial_extras import (
    IMPORTED_GROUP,
    SourceGroup,
    TrialAdditions,
    add_to_files,
)

log = logging.getLogger(__name__)

COMMAND = "steerlab import-xdf"
STEERLAB_SIGNAL_TYPE = "Steerlab"
MARKER_TYPE = "Markers"
MATCHES = ("auto", "markers", "clock")
HOST = "host monotonic"  # protocols/lsl_publisher.py's lsl_clock_source of a real-time loop


class XdfImportError(ValueError):
    """An XDF file or a session that cannot be imported; the message names the file/stream."""


# -- reading ---------------------------------------------------------------------------------------
@dataclass
class XdfChannel:
    label: str
    unit: str
    type: str = ""


@dataclass
class XdfStream:
    """One stream of an XDF file, its time stamps on the recorder's clock."""

    stream_id: int
    name: str
    type: str
    source_id: str
    channel_format: str
    nominal_srate: float
    channels: list[XdfChannel]
    time_stamps: np.ndarray
    values: np.ndarray | list  # (n, channels) numbers, or a list of rows of strings
    clock_times: np.ndarray
    clock_values: np.ndarray
    desc: dict
    footer: dict | None = None

    @property
    def n_samples(self) -> int:
        return len(self.time_stamps)

    @property
    def numeric(self) -> bool:
        return self.channel_format != "string"

    @property
    def steerlab(self) -> bool:
        """One of Steerlab's own streams (its signals or its markers)."""
        return (
            self.type == STEERLAB_SIGNAL_TYPE
            or self.source_id.startswith("steerlab:")
            or "steerlab" in self.desc
        )

    @property
    def steerlab_markers(self) -> bool:
        return self.steerlab and not self.numeric and self.type == MARKER_TYPE

    @property
    def subject(self) -> str | None:
        """The subject Steerlab's stream belongs to (its description), if it says."""
        s = self.desc.get("steerlab")
        if isinstance(s, dict) and s.get("subject"):
            return str(s["subject"])
        m = re.fullmatch(r"Steerlab (\S+)(?: markers)?", self.name)
        return m.group(1) if m else None

    def label(self) -> str:
        return f"stream {self.name!r} (id {self.stream_id}, type {self.type or '?'})"

    def span(self) -> str:
        if not self.n_samples:
            return "no samples"
        return f"{self.time_stamps[0]:.3f}–{self.time_stamps[-1]:.3f} s"


@dataclass
class XdfRecording:
    path: Path
    streams: list[XdfStream]
    header: dict
    notes: list[str] = field(default_factory=list)  # streams without samples, …


def _first(d: dict, key: str, default=None):
    v = d.get(key)
    if isinstance(v, list):
        v = v[0] if v else default
    return default if v is None else v


def _plain(node) -> object:
    """pyxdf's nested {tag: [values]} as plain dicts/strings (one value: itself)."""
    if isinstance(node, dict):
        return {k: _plain(v[0] if isinstance(v, list) and len(v) == 1 else v)
                for k, v in node.items()}  # fmt: skip
    if isinstance(node, list):
        return [_plain(x) for x in node]
    return node


def _channels(info: dict, n: int) -> list[XdfChannel]:
    out = []
    desc = _first(info, "desc")
    chs: list = []
    if isinstance(desc, dict):
        channels = _first(desc, "channels")
        if isinstance(channels, dict):
            chs = channels.get("channel") or []
    for k in range(n):
        c = chs[k] if k < len(chs) and isinstance(chs[k], dict) else {}
        out.append(
            XdfChannel(
                label=str(_first(c, "label", "") or "").strip() or f"ch{k + 1}",
                unit=str(_first(c, "unit", "") or "").strip() or "unknown",
                type=str(_first(c, "type", "") or "").strip(),
            )
        )
    return out


def read_xdf(
    path: str | Path, *, synchronize_clocks: bool = True, dejitter: bool = False
) -> XdfRecording:
    """Every stream of an XDF file, its time stamps on the recorder's clock (module docstring)."""
    import pyxdf

    path = Path(path)
    if not path.is_file():
        raise XdfImportError(f"{path}: no such file")
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError as e:
        raise XdfImportError(f"{path}: cannot read ({e.strerror or e})") from None
    if magic != b"XDF:":
        raise XdfImportError(f"{path}: not an XDF file (it does not start with 'XDF:')")
    # pyxdf logs what it meets on the way (segments, clock resets) as warnings; what matters
    # here is said by this module, in its own words.
    pyxdf_log = logging.getLogger("pyxdf.pyxdf")
    level = pyxdf_log.level
    pyxdf_log.setLevel(logging.CRITICAL)
    try:
        raw, header = pyxdf.load_xdf(
            str(path),
            synchronize_clocks=synchronize_clocks,
            dejitter_timestamps=dejitter,
        )
    except Exception as e:  # pyxdf raises what its parsing meets
        raise XdfImportError(f"{path}: unreadable XDF ({type(e).__name__}: {e})") from None
    finally:
        pyxdf_log.setLevel(level)
    streams, notes = [], []
    for s in raw:
        info = s["info"]
        n_ch = int(_first(info, "channel_count", "0"))
        fmt = str(_first(info, "channel_format", ""))
        ts = np.asarray(s["time_stamps"], dtype=float)
        values = s["time_series"]
        if fmt != "string":
            values = np.asarray(values)
            if values.ndim == 1:
                values = values.reshape(len(ts), -1)
        desc = _first(info, "desc")
        st = XdfStream(
            stream_id=int(info["stream_id"]),
            name=str(_first(info, "name", "")),
            type=str(_first(info, "type", "")),
            source_id=str(_first(info, "source_id", "") or ""),
            channel_format=fmt,
            nominal_srate=float(_first(info, "nominal_srate", "0") or 0),
            channels=_channels(info, n_ch),
            time_stamps=ts,
            values=values,
            clock_times=np.asarray(s.get("clock_times", []), dtype=float),
            clock_values=np.asarray(s.get("clock_values", []), dtype=float),
            desc=_plain(desc) if isinstance(desc, dict) else {},  # type: ignore[arg-type]
            footer=s.get("footer"),
        )
        if not st.n_samples:
            notes.append(f"{path}: {st.label()}: no samples in the recording; nothing to import")
        elif st.footer is None:
            notes.append(
                f"{path}: {st.label()}: no footer: the recording was cut short (a recorder that"
                f" stopped without closing the file?); its {st.n_samples} samples up to the cut"
                " are read"
            )
        streams.append(st)
    return XdfRecording(path=path, streams=streams, header=header or {}, notes=notes)


# -- the sessions' trials --------------------------------------------------------------------------
@dataclass
class SessionTrial:
    path: Path
    subject: str
    key: str
    trial_index: int | None
    attempt: int
    condition: str
    fs_hz: float
    status: str
    lsl_clock_s: float | None
    time_s: np.ndarray
    #: The session computer's LSL time of each sample (``host_time_s + lsl_clock_offset_s``),
    #: where the trial records them; None: ``lsl_clock_s + time_s``.
    lsl_times: np.ndarray | None = None

    @property
    def where(self) -> str:
        return f"{self.path.name}:/trials/{self.key}"

    @property
    def lsl_ref(self) -> float | None:
        """The LSL time of the trial's time line's 0 (its ``trial_start`` marker's stamp)."""
        if self.lsl_clock_s is not None:
            return self.lsl_clock_s
        if self.lsl_times is not None and len(self.lsl_times):
            return float(self.lsl_times[0] - self.time_s[0])
        return None

    def session_times(self) -> np.ndarray | None:
        """Each sample's time on the session computer's LSL clock (None: not known)."""
        if self.lsl_times is not None:
            return self.lsl_times
        if self.lsl_clock_s is not None:
            return self.lsl_clock_s + self.time_s
        return None


def per_sample_lsl_times(g, attrs: dict) -> np.ndarray | None:
    """``host_time_s + lsl_clock_offset_s`` for a trial whose clock is the host's monotonic
    one and that records both (exact across pauses of the loop); else None."""
    import h5py

    offset = attrs.get("lsl_clock_offset_s")
    d = g.get("host_time_s")
    if offset is None or not isinstance(d, h5py.Dataset) or attrs.get("lsl_clock_source") != HOST:
        return None
    host = read_channel(d).astype(float)
    if len(host) != len(g["time_s"]) or not np.all(np.isfinite(host)):
        return None
    return host + float(offset)


def session_paths(session: str | Path) -> list[Path]:
    p = Path(session)
    if p.is_dir():
        files = session_files(p)
        if not files:
            raise XdfImportError(f"{p}: no session files (*.h5)")
        return files
    if not p.is_file():
        raise XdfImportError(f"{p}: no such session file or folder")
    return [p]


def session_trials(session: str | Path) -> list[SessionTrial]:
    """Every readable trial of the session file(s) at ``session`` (a file or a folder)."""
    out = []
    for path in session_paths(session):
        try:
            sf = SessionFile(path)
            with open_for_reading(path) as f:
                for key in sf.trial_keys:
                    if key in sf.damaged:
                        log.warning("%s:/trials/%s: %s; skipped", path, key, sf.damaged[key])
                        continue
                    a = sf.trial_attrs[key]
                    g = f["trials"][key]
                    if "time_s" not in g:
                        continue  # aborted before its first sample
                    clock = a.get("lsl_clock_s")
                    out.append(
                        SessionTrial(
                            path=path,
                            subject=str(a.get("subject", sf.subject)),
                            key=key,
                            trial_index=int(a["trial_index"])
                            if a.get("trial_index") is not None
                            else None,  # fmt: skip
                            attempt=int(a.get("attempt", 1) or 1),
                            condition=str(a.get("condition", "")),
                            fs_hz=float(a.get("fs_hz") or math.nan),
                            status=str(a.get("status", "")),
                            lsl_clock_s=float(clock) if clock is not None else None,
                            time_s=read_channel(g["time_s"]),
                            lsl_times=per_sample_lsl_times(g, a),
                        )
                    )
        except DataFileError as e:
            raise XdfImportError(str(e)) from None
    return out


# -- matching --------------------------------------------------------------------------------------
@dataclass
class TrialWindow:
    """A trial placed on the recording's clock: its sample i is at ``times[i]``; ``t0`` is
    where its time line's 0 is (``times = t0 + time_s`` unless the loop paused and the trial
    records each sample's host time)."""

    trial: SessionTrial
    t0: float
    matched_by: str
    times: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.times is None:
            self.times = self.t0 + self.trial.time_s

    @property
    def start(self) -> float:
        return float(self.times[0]) if len(self.times) else self.t0

    @property
    def stop(self) -> float:
        return float(self.times[-1]) if len(self.times) else self.t0


def parse_markers(stream: XdfStream) -> list[tuple[float, dict]]:
    """(time stamp, JSON object) of each of Steerlab's markers; other text is skipped."""
    out = []
    for t, row in zip(stream.time_stamps, stream.values, strict=True):
        text = row[0] if row else ""
        try:
            d = json.loads(text)
        except (TypeError, ValueError):
            continue
        if isinstance(d, dict) and "event" in d:
            out.append((float(t), d))
    return out


#: Clock offsets further than this from their fitted line: not one straight clock (a reset?).
CLOCK_FIT_TOLERANCE_S = 0.005


def clock_to_recording(rec: XdfRecording, subject: str | None = None) -> tuple[float, float, str]:
    """(intercept, slope, how): the session computer's LSL time t is at
    ``t + intercept + slope·t`` on the recording's clock, from one straight line fitted through
    the clock offsets of one Steerlab stream of ``subject`` (the one with the most offsets; the
    streams of one session computer share its clock, other subjects' may not)."""
    mine = [
        s
        for s in rec.streams
        if s.steerlab and len(s.clock_times) and (subject is None or s.subject in (None, subject))
    ]
    whose = f"subject {subject}'s Steerlab streams" if subject else "Steerlab's streams"
    if not mine:
        return 0.0, 0.0, f"no clock offsets of {whose} in the file: the session's LSL clock"\
            " taken as the recording's"  # fmt: skip
    by_source: dict[str, XdfStream] = {}
    for s in mine:
        have = by_source.get(s.source_id)
        if have is None or len(s.clock_times) > len(have.clock_times):
            by_source[s.source_id] = s
    s = max(by_source.values(), key=lambda x: len(x.clock_times))
    t, v = s.clock_times, s.clock_values
    if len(t) < 2 or np.ptp(t) == 0:
        return float(np.median(v)), 0.0, f"the clock offset {np.median(v):.6g} s of {s.label()}"
    slope, intercept = np.polyfit(t, v, 1)
    how = f"a line through the {len(t)} clock offsets of {s.label()}"
    worst = float(np.max(np.abs(v - (intercept + slope * t))))
    if worst > CLOCK_FIT_TOLERANCE_S:
        how += (
            f"; they lie up to {worst * 1e3:.1f} ms off that line (a clock reset on the"
            " session computer?): --match markers places trials by the recording's own stamps"
        )
    return float(intercept), float(slope), how


def _marker_window(tr: SessionTrial, t: float, how: str) -> TrialWindow:
    """The trial whose time line's 0 was stamped ``t`` on the recording's clock."""
    if tr.lsl_times is not None and tr.lsl_ref is not None:
        return TrialWindow(tr, t, how, t + (tr.lsl_times - tr.lsl_ref))
    return TrialWindow(tr, t, how)


def match_trials(
    rec: XdfRecording, trials: list[SessionTrial], *, match: str = "auto"
) -> tuple[list[TrialWindow], list[str]]:
    """Place the trials on the recording's clock (module docstring); (windows, notes)."""
    if match not in MATCHES:
        raise XdfImportError(f"--match must be one of {', '.join(MATCHES)}, not {match!r}")
    marker_streams = [s for s in rec.streams if s.steerlab_markers and s.n_samples]
    notes: list[str] = []
    if match == "markers" and not marker_streams:
        raise XdfImportError(f"{rec.path}: no Steerlab marker stream with samples in the file")
    if match == "markers" or (match == "auto" and marker_streams):
        windows: list[TrialWindow] = []
        seen: set[tuple[Path, str]] = set()
        for ms in marker_streams:
            subject = ms.subject
            for t, d in parse_markers(ms):
                if d.get("event") != "trial_start":
                    continue
                key = d.get("key")
                found = [
                    tr
                    for tr in trials
                    if tr.key == key and (subject is None or tr.subject == subject)
                ]
                if not found:
                    notes.append(
                        f"{rec.path}: marker trial_start of {key!r}"
                        f"{' (subject ' + subject + ')' if subject else ''} at {t:.3f} s:"
                        " no such trial in the session file(s)"
                    )
                    continue
                if len(found) > 1:
                    where = ", ".join(tr.where for tr in found)
                    notes.append(
                        f"{rec.path}: marker trial_start of {key!r} matches {where}; give one"
                        " session file (--session FILE)"
                    )
                    continue
                tr = found[0]
                if (tr.path, tr.key) in seen:
                    notes.append(f"{rec.path}: a second trial_start of {tr.where}; the first kept")
                    continue
                seen.add((tr.path, tr.key))
                windows.append(_marker_window(tr, t, f"marker trial_start of {ms.label()}"))
        return windows, notes
    # As markers do: where the file names the subjects of its Steerlab streams, only their
    # trials are placed (another subject's session ran on another clock, or not in this one).
    subjects = {s.subject for s in rec.streams if s.steerlab and s.subject}
    if subjects:
        others = [tr for tr in trials if tr.subject not in subjects]
        if others:
            notes.append(
                f"{rec.path}: {len(others)} trial(s) of subject(s)"
                f" {', '.join(sorted({tr.subject for tr in others}))} not placed: the file's"
                f" Steerlab streams are of {', '.join(sorted(subjects))}"
            )
        trials = [tr for tr in trials if tr.subject in subjects]
    windows = []
    missing = [tr.where for tr in trials if tr.session_times() is None]
    if missing:
        notes.append(
            f"{len(missing)} trial(s) record no lsl_clock_s and cannot be placed by the clock:"
            f" {', '.join(missing[:5])}{' …' if len(missing) > 5 else ''}"
        )
    fits: dict[str, tuple[float, float, str]] = {}
    how = ""
    for tr in trials:
        lsl = tr.session_times()
        ref = tr.lsl_ref
        if lsl is None or ref is None:
            continue
        if tr.subject not in fits:
            fits[tr.subject] = clock_to_recording(rec, tr.subject if subjects else None)
        intercept, slope, how = fits[tr.subject]
        per_sample = " and its samples' host_time_s" if tr.lsl_times is not None else ""
        windows.append(
            TrialWindow(
                tr,
                ref + intercept + slope * ref,
                f"lsl_clock_s{per_sample} ({how})",
                lsl + intercept + slope * lsl,
            )
        )
    if not windows:
        raise XdfImportError(
            "no trial can be placed on the recording's clock: the file has no Steerlab marker"
            " stream and no trial records lsl_clock_s"
        )
    # A folder holds other sessions too (other subjects, other days): only the trials the
    # recording spans are matched.
    stamps = [s.time_stamps for s in rec.streams if s.n_samples]
    if stamps:
        lo = min(float(t.min()) for t in stamps)
        hi = max(float(t.max()) for t in stamps)
        inside = [w for w in windows if w.stop >= lo and w.start <= hi]
        if not inside:
            raise XdfImportError(
                f"{rec.path}: no trial lies within the recording ({lo:.3f}–{hi:.3f} s on its"
                f" clock): by their lsl_clock_s ({how}) the {len(windows)} trial(s) span"
                f" {min(w.start for w in windows):.3f}–{max(w.stop for w in windows):.3f} s;"
                " nothing imported"
            )
        if len(inside) < len(windows):
            notes.append(
                f"{rec.path}: {len(windows) - len(inside)} trial(s) lie outside the recording"
                f" ({lo:.3f}–{hi:.3f} s on its clock) and are not matched"
            )
        windows = inside
    return windows, notes


# -- resampling onto trials ------------------------------------------------------------------------
def safe_part(text: str) -> str:
    s = re.sub(r"[^A-Za-z0-9_.+-]+", "_", text).strip("_.")
    return s or "x"


def _names_of(prefix: str, stream: XdfStream) -> list[str]:
    return channel_names(prefix, stream) if stream.numeric else []


def _clashes(streams: list[XdfStream], prefixes: dict[int, str]) -> dict[str, list[XdfStream]]:
    """Names two streams would both write: a channel (``xdf_EMG`` + ``a_b`` and ``xdf_EMG_a``
    + ``b``), or a source group."""
    owners: dict[str, list[XdfStream]] = {}
    for s in streams:
        for name in {
            *_names_of(prefixes[s.stream_id], s),
            f"{IMPORTED_GROUP}/{prefixes[s.stream_id]}",
        }:
            owners.setdefault(name, []).append(s)
    return {n: ss for n, ss in owners.items() if len(ss) > 1}


def stream_prefixes(streams: Iterable[XdfStream]) -> tuple[dict[int, str], list[str]]:
    """``xdf_NAME`` per stream id, and what was said about it: ``xdf_NAME_ID`` where two
    streams share a name, or where their names would give the same channel name."""
    streams = list(streams)
    names = [safe_part(s.name) for s in streams]
    out = {}
    for s, n in zip(streams, names, strict=True):
        out[s.stream_id] = f"xdf_{n}" if names.count(n) == 1 else f"xdf_{n}_{s.stream_id}"
    notes: list[str] = []
    clashes = _clashes(streams, out)
    if clashes:
        moved: dict[int, XdfStream] = {}
        for name, owners in clashes.items():
            for s in owners:
                if s.stream_id not in moved:
                    moved[s.stream_id] = s
                    out[s.stream_id] = f"xdf_{safe_part(s.name)}_{s.stream_id}"
            notes.append(f"{name} would be written by {' and by '.join(s.label() for s in owners)}")
        left = _clashes(streams, out)
        if left:
            raise XdfImportError(
                "streams whose channels would get the same name: "
                + "; ".join(f"{n}: {', '.join(s.label() for s in ss)}" for n, ss in left.items())
                + "; import one of them (--stream NAME)"
            )
        notes = [
            "; ".join(notes)
            + ": their names carry the stream id ("
            + ", ".join(f"{s.name!r} → {out[i]}" for i, s in moved.items())
            + ")"
        ]
    return out, notes


def channel_names(prefix: str, stream: XdfStream) -> list[str]:
    labels = [safe_part(c.label) for c in stream.channels]
    return [
        f"{prefix}_{lab}" if labels.count(lab) == 1 else f"{prefix}_{lab}_{k + 1}"
        for k, lab in enumerate(labels)
    ]


@dataclass
class XdfImport:
    """What an import did (or would do): lines written, problems met, checks of Steerlab's
    own stream."""

    xdf: Path
    windows: list[TrialWindow]
    written: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    checks: list[TrialCheck] = field(default_factory=list)
    additions: dict[Path, list[TrialAdditions]] = field(default_factory=dict)
    imported_streams: list[str] = field(default_factory=list)

    def summary(self) -> str:
        lines = [f"{self.xdf}: {len(self.windows)} trial(s) matched"]
        lines += [f"  {w.trial.where}: t0 = {w.t0:.6f} s ({w.matched_by})" for w in self.windows]
        lines += [f"  {c.summary()}" for c in self.checks]
        lines += [f"  wrote {w}" for w in self.written]
        return "\n".join(lines)


def _inside(ts: np.ndarray, w: TrialWindow) -> np.ndarray:
    half = 0.5 / w.trial.fs_hz if w.trial.fs_hz > 0 else 0.0
    return (ts >= w.start - half) & (ts <= w.stop + half)


def plan_stream(
    stream: XdfStream,
    windows: list[TrialWindow],
    *,
    prefix: str,
    method: str = "auto",
    xdf_path: Path,
) -> tuple[dict[tuple[Path, str], TrialAdditions], list[str]]:
    """The additions one stream makes to the trials it overlaps, and its problems."""
    out: dict[tuple[Path, str], TrialAdditions] = {}
    problems: list[str] = []
    where = f"{xdf_path}: {stream.label()}"
    if not stream.n_samples:
        return out, problems  # said by read_xdf
    ts = stream.time_stamps
    order = np.argsort(ts, kind="stable")
    if np.any(np.diff(ts) < 0):
        problems.append(f"{where}: time stamps go back in time; sorted before resampling")
    hits = [(w, _inside(ts, w)) for w in windows]
    names = channel_names(prefix, stream) if stream.numeric else []
    empty: list[str] = []  # trials without anything from the stream
    for w, m in hits:
        tr = w.trial
        res, m_used, gap = None, "", math.inf
        if stream.numeric:
            values = np.asarray(stream.values)
            m_used = method if method != "auto" else choose_method(stream.nominal_srate, tr.fs_hz)
            gap = max_gap_for(stream.nominal_srate)
            # The samples around the trial too: interpolation (and the hold) at its first and
            # last sample.
            lo = max(0, int(np.searchsorted(ts[order], w.start, "left")) - 1)
            hi = int(np.searchsorted(ts[order], w.stop, "right")) + 1
            sel = order[lo:hi]
            res = resample(ts[sel], values[sel].astype(float), w.times, method=m_used,
                           max_gap_s=gap)  # fmt: skip
        # A slow stream held across a trial has no sample inside it and still says something.
        if not m.any() and (res is None or np.isnan(res).all()):
            empty.append(
                f"{where}: no samples in trial {tr.where} ({w.start:.3f}–{w.stop:.3f} s on the"
                f" recording's clock; the stream has {stream.span()}); not imported for that"
                " trial"
            )
            continue
        add = out.setdefault((tr.path, tr.key), TrialAdditions(tr.key))
        idx = np.flatnonzero(m)
        common = {
            "source_file": str(xdf_path),
            "stream_name": stream.name,
            "stream_type": stream.type,
            "stream_id": stream.stream_id,
            "stream_source_id": stream.source_id,
            "channel_format": stream.channel_format,
            "nominal_srate_hz": stream.nominal_srate,
            "matched_by": w.matched_by,
            "trial_t0_s": w.t0,
            "n_source_samples": int(len(idx)),
        }
        if res is not None:
            for k, (name, ch) in enumerate(zip(names, stream.channels, strict=True)):
                col = res[:, k]
                add.channels[name] = (
                    col,
                    {
                        **common,
                        "units": ch.unit,
                        "channel_label": ch.label,
                        "channel_index": k,
                        "resample_method": m_used,
                        "max_gap_s": gap if math.isfinite(gap) else -1.0,
                        "n_nan": int(np.isnan(col).sum()),
                    },
                )
            add.groups[prefix] = SourceGroup(
                {"time_s": ts[idx] - w.t0, "values": values[idx]},
                {
                    **common,
                    "channel_labels": [c.label for c in stream.channels],
                    "channel_units": [c.unit for c in stream.channels],
                    "channels": names,
                },
            )
        else:
            text = np.array([[str(x) for x in stream.values[i]] for i in idx], dtype=object)
            add.groups[prefix] = SourceGroup(
                {"time_s": ts[idx] - w.t0, "text": text},
                {**common, "channel_labels": [c.label for c in stream.channels]},
            )
    if out:
        problems += empty
    else:
        first = min(w.start for w in windows)
        last = max(w.stop for w in windows)
        problems.append(
            f"{where}: its samples ({stream.span()} on the recording's clock) overlap no trial"
            f" (the trials span {first:.3f}–{last:.3f} s); nothing imported from it"
        )
    return out, problems


# -- checking Steerlab's own stream ----------------------------------------------------------------
@dataclass
class TrialCheck:
    """Steerlab's signal stream against a trial of the session file."""

    where: str
    stream: str
    n_trial: int  # samples of the trial
    n_found: int  # trial samples the stream has a sample for
    n_equal: int  # of those, with every compared channel equal to the file's value
    n_extra: int  # stream samples in the window that fall on no trial sample or twice on one
    channels: list[str]
    max_time_error_s: float

    @property
    def all_in_place(self) -> bool:
        return self.n_found == self.n_trial == self.n_equal and self.n_extra == 0

    def summary(self) -> str:
        if self.all_in_place:
            return (
                f"{self.where}: every one of its {self.n_trial} samples is in {self.stream} at its"
                f" time, with the file's values ({len(self.channels)} channels)"
            )
        return (
            f"{self.where}: {self.stream} has {self.n_found} of its {self.n_trial} samples,"
            f" {self.n_equal} with the file's values, {self.n_extra} others in its span"
        )


def check_steerlab_stream(rec: XdfRecording, windows: list[TrialWindow]) -> list[TrialCheck]:
    """For each window, Steerlab's signal stream (of its subject) against the trial's samples:
    the stream sample nearest each trial sample's time (within a quarter sample), compared with
    the stored value (cast to the stored float32 where the file stores float32)."""
    import h5py

    signals = [s for s in rec.streams if s.type == STEERLAB_SIGNAL_TYPE and s.n_samples]
    out: list[TrialCheck] = []
    for w in windows:
        tr = w.trial
        mine = [s for s in signals if s.subject in (None, tr.subject)]
        if not mine or not tr.fs_hz > 0:
            continue
        s = mine[0]
        m = _inside(s.time_stamps, w)
        ts = s.time_stamps[m]
        vals = np.asarray(s.values)[m]
        # The trial sample nearest each stream sample (the trial's times need not be regular:
        # a paused loop).
        if len(w.times) == 0:
            continue
        j = np.clip(np.searchsorted(w.times, ts), 1, max(1, len(w.times) - 1))
        before = np.clip(j - 1, 0, len(w.times) - 1)
        after = np.clip(j, 0, len(w.times) - 1)
        near_before = np.abs(ts - w.times[before]) <= np.abs(ts - w.times[after])
        i = np.where(near_before, before, after).astype(np.int64)
        err = np.abs(ts - w.times[i])
        ok = err <= 0.25 / tr.fs_hz
        uniq, counts = np.unique(i[ok], return_counts=True)
        single = uniq[counts == 1]
        n_extra = int((~ok).sum() + (counts[counts > 1] - 1).sum() + (counts > 1).sum())
        equal = np.zeros(len(tr.time_s), dtype=bool)
        equal[single] = True
        compared = []
        with open_for_reading(tr.path) as f:
            g = f["trials"][tr.key]
            for k, ch in enumerate(s.channels):
                d = g.get(ch.label)
                if not isinstance(d, h5py.Dataset):
                    continue
                compared.append(ch.label)
                stored = read_channel(d)
                col = np.full(len(tr.time_s), np.nan)
                sel = ok.copy()
                col[i[sel]] = vals[sel, k]
                if d.dtype == np.float32:
                    same = col.astype(np.float32) == d[()]
                else:
                    same = col == stored
                same |= np.isnan(col) & np.isnan(stored)
                equal &= same
        out.append(
            TrialCheck(
                where=tr.where,
                stream=s.label(),
                n_trial=len(tr.time_s),
                n_found=int(len(single)),
                n_equal=int(equal.sum()),
                n_extra=n_extra,
                channels=compared,
                max_time_error_s=float(err[ok].max()) if ok.any() else math.nan,
            )
        )
    return out


# -- the whole import ------------------------------------------------------------------------------
def import_xdf(
    xdf: str | Path,
    session: str | Path,
    *,
    match: str = "auto",
    method: str = "auto",
    streams: Iterable[str] | None = None,
    dejitter: bool = False,
    replace: bool = False,
    dry_run: bool = False,
) -> XdfImport:
    """Import the streams of ``xdf`` (all but Steerlab's own; ``streams``: only those names or
    types) into the matching trials of the session file(s) at ``session``."""
    if method not in ("auto", "linear", "hold"):
        raise XdfImportError(f"--method must be auto, linear or hold, not {method!r}")
    rec = read_xdf(xdf, dejitter=dejitter)
    trials = session_trials(session)
    if not trials:
        raise XdfImportError(f"{session}: no trials with samples")
    windows, notes = match_trials(rec, trials, match=match)
    result = XdfImport(xdf=rec.path, windows=windows, problems=[*rec.notes, *notes])
    if not windows:
        raise XdfImportError(
            f"{rec.path}: no trial of {session} matched"
            + (": " + "; ".join(notes) if notes else "")  # fmt: skip
        )
    result.checks = check_steerlab_stream(rec, windows)
    for c in result.checks:
        if not c.all_in_place:
            result.problems.append(
                f"{rec.path}: Steerlab's own stream does not match the session file: " + c.summary()
            )
    wanted = set(streams or ())
    chosen = [
        s
        for s in rec.streams
        if not s.steerlab and (not wanted or s.name in wanted or s.type in wanted)
    ]
    if wanted and not chosen:
        names = ", ".join(repr(s.name) for s in rec.streams if not s.steerlab) or "none"
        raise XdfImportError(
            f"{rec.path}: no stream named or typed {sorted(wanted)}; it has {names}"
        )
    prefixes, named = stream_prefixes(chosen)
    result.problems += [f"{rec.path}: {n}" for n in named]
    per_file: dict[Path, dict[str, TrialAdditions]] = {}
    for s in chosen:
        adds, problems = plan_stream(s, windows, prefix=prefixes[s.stream_id], method=method,
                                     xdf_path=rec.path)  # fmt: skip
        result.problems += problems
        if adds:
            result.imported_streams.append(s.name)
        for (path, key), a in adds.items():
            mine = per_file.setdefault(path, {}).setdefault(key, TrialAdditions(key))
            both = (set(mine.channels) & set(a.channels)) | (set(mine.groups) & set(a.groups))
            if both:  # stream_prefixes keeps names apart; never overwrite one silently
                raise XdfImportError(
                    f"{rec.path}: two streams give {sorted(both)}; nothing written"
                )
            mine.channels.update(a.channels)
            mine.groups.update(a.groups)
    result.additions = {p: list(d.values()) for p, d in per_file.items()}
    if not result.additions:
        raise XdfImportError(
            f"{rec.path}: nothing to import into {session}: " + "; ".join(result.problems)
            if result.problems
            else f"{rec.path}: no stream to import besides Steerlab's own"
        )
    if not dry_run:
        # Every file's lock and every refusal before the first file is written.
        result.written += add_to_files(result.additions, command=COMMAND, replace=replace)
    return result
