"""XDF files written by Steerlab: a writer of the format, and a small LSL recorder on top of it.

XDF (Extensible Data Format, https://github.com/sccn/xdf, "Specifications") is what LabRecorder
writes when a lab records every device on the Lab Streaming Layer. :class:`XdfWriter` writes the
same format, read back by ``pyxdf.load_xdf`` as written; :class:`LslRecorder` records LSL streams
into it, as LabRecorder would (our stand-in for it in tests and in a lab without LabRecorder).

The format, as this module writes it (all numbers little-endian):

* the magic ``XDF:``, then chunks, each ``[NumLengthBytes][Length][Tag][Content]``: the length is
  a variable-length integer (one byte saying 1, 4 or 8, then the number in that many bytes)
  counting the 2-byte tag and the content;
* tag 1 FileHeader: XML ``<info><version>1.0</version>...</info>``;
* tag 2 StreamHeader: a 4-byte stream id, then the stream's XML ``<info>`` (name, type,
  channel_count, nominal_srate, channel_format, source_id, ..., ``<desc>``);
* tag 3 Samples: the stream id, the number of samples (variable-length), then per sample one
  byte ``8`` and its time stamp (float64; this writer always writes it, so time stamps come back
  exactly, never deduced from the rate) and its values: ``channel_count`` numbers of the
  channel format, or for a string stream per channel a variable-length byte count and the UTF-8
  bytes;
* tag 4 ClockOffset: the stream id, the collection time and the offset (two float64): at that
  time of the stream's clock, the recorder's clock was ``offset`` s ahead (pyxdf adds a fit of
  the offsets to the stream's time stamps);
* tag 5 Boundary: a fixed 16-byte signature, so that a reader can resynchronise after damage;
* tag 6 StreamFooter: the stream id and XML with ``first_timestamp``, ``last_timestamp``,
  ``sample_count`` and the ``clock_offsets``.

Channel formats: ``float32``, ``double64``, ``int8``, ``int16``, ``int32``, ``int64``, ``string``.
"""

from __future__ import annotations

import os
import struct
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: Numeric channel formats and their little-endian dtypes.
NUMERIC_FORMATS: dict[str, str] = {
    "float32": "<f4",
    "double64": "<f8",
    "int8": "<i1",
    "int16": "<i2",
    "int32": "<i4",
    "int64": "<i8",
}
CHANNEL_FORMATS = (*NUMERIC_FORMATS, "string")

TAG_FILE_HEADER, TAG_STREAM_HEADER, TAG_SAMPLES, TAG_CLOCK_OFFSET = 1, 2, 3, 4
TAG_BOUNDARY, TAG_STREAM_FOOTER = 5, 6
BOUNDARY_SIGNATURE = bytes.fromhex("43A546DCCBF5410FB30ED5467383CBE4")

#: Clock offsets a recorded stream may fail to give in a row before it is no longer asked.
MAX_OFFSET_FAILURES = 2

#: Samples per Samples chunk when a long block is written at once.
CHUNK_SAMPLES = 4096


class XdfWriteError(ValueError):
    """Data that cannot be written as asked (unknown stream, wrong shape, bad format)."""


def varlen_int(n: int) -> bytes:
    """XDF's variable-length integer: one byte giving the width (1, 4 or 8), then the number."""
    if n < 0:
        raise XdfWriteError(f"negative length {n}")
    if n < 1 << 8:
        return b"\x01" + struct.pack("<B", n)
    if n < 1 << 32:
        return b"\x04" + struct.pack("<I", n)
    return b"\x08" + struct.pack("<Q", n)


def _text(x: float) -> str:
    """A number as XML text that reads back as the same float (repr: shortest exact)."""
    x = float(x)
    return str(int(x)) if x.is_integer() and abs(x) < 1e15 else repr(x)


@dataclass
class ChannelSpec:
    """One channel of a stream as its header's ``desc/channels/channel`` describes it."""

    label: str
    unit: str = ""
    type: str = ""


def stream_header_xml(
    *,
    name: str,
    type: str,
    channel_count: int,
    nominal_srate: float,
    channel_format: str,
    source_id: str = "",
    channels: Sequence[ChannelSpec] | None = None,
    created_at: float | None = None,
    uid: str = "",
    hostname: str = "",
    desc: ET.Element | None = None,
) -> str:
    """The XML of a StreamHeader chunk, in the layout LSL's ``stream_info.as_xml()`` gives."""
    info = ET.Element("info")
    for tag, value in (
        ("name", name),
        ("type", type),
        ("channel_count", str(int(channel_count))),
        ("nominal_srate", _text(nominal_srate)),
        ("channel_format", channel_format),
        ("source_id", source_id),
        ("created_at", _text(created_at if created_at is not None else 0.0)),
        ("uid", uid),
        ("hostname", hostname),
    ):
        ET.SubElement(info, tag).text = value
    d = desc if desc is not None else ET.Element("desc")
    if channels:
        chs = ET.SubElement(d, "channels")
        for c in channels:
            ch = ET.SubElement(chs, "channel")
            ET.SubElement(ch, "label").text = c.label
            if c.unit:
                ET.SubElement(ch, "unit").text = c.unit
            if c.type:
                ET.SubElement(ch, "type").text = c.type
    info.append(d)
    return '<?xml version="1.0"?>' + ET.tostring(info, encoding="unicode")


@dataclass
class _Stream:
    stream_id: int
    channel_count: int
    channel_format: str
    dtype: np.dtype | None
    first: float | None = None
    last: float | None = None
    count: int = 0
    offsets: list[tuple[float, float]] = field(default_factory=list)
    footer_written: bool = False


def _header_fields(xml: str) -> tuple[int, str]:
    try:
        root = ET.fromstring(xml)
    except ET.ParseError as e:
        raise XdfWriteError(f"stream header is not XML: {e}") from None
    try:
        n = int((root.findtext("channel_count") or "").strip())
    except ValueError:
        raise XdfWriteError("stream header has no whole-number channel_count") from None
    fmt = (root.findtext("channel_format") or "").strip()
    if fmt not in CHANNEL_FORMATS:
        raise XdfWriteError(
            f"stream header: channel_format {fmt!r} is not one of {', '.join(CHANNEL_FORMATS)}"
        )
    if n < 1:
        raise XdfWriteError(f"stream header: channel_count must be ≥ 1, got {n}")
    return n, fmt


class XdfWriter:
    """Writes one XDF file. Thread-safe: one lock around every chunk (a recorder's threads).

    The file is written as ``PATH.part`` and renamed to ``PATH`` by :meth:`close`, so a file
    named ``*.xdf`` is always complete (footers written); a recorder killed midway leaves the
    ``.part`` file, which pyxdf reads up to its last whole chunk.
    """

    def __init__(self, path: str | Path, *, overwrite: bool = False, file_info: dict | None = None):
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise XdfWriteError(f"{self.path}: exists; not overwriting it")
        self.part = self.path.with_name(self.path.name + ".part")
        self._lock = threading.Lock()
        self._streams: dict[int, _Stream] = {}
        self._fh = open(self.part, "wb")
        self._fh.write(b"XDF:")
        info = ET.Element("info")
        ET.SubElement(info, "version").text = "1.0"
        for k, v in (file_info or {}).items():
            ET.SubElement(info, k).text = str(v)
        self._chunk(TAG_FILE_HEADER, None, ('<?xml version="1.0"?>' + ET.tostring(
            info, encoding="unicode")).encode())  # fmt: skip
        self.closed = False

    # -- chunks ----------------------------------------------------------------------------------
    def _chunk(self, tag: int, stream_id: int | None, content: bytes) -> None:
        head = struct.pack("<H", tag)
        if stream_id is not None:
            head += struct.pack("<I", stream_id)
        self._fh.write(varlen_int(len(head) + len(content)) + head + content)

    def _stream(self, stream_id: int) -> _Stream:
        s = self._streams.get(stream_id)
        if s is None:
            raise XdfWriteError(f"{self.path}: no stream with id {stream_id}")
        return s

    # -- public API ------------------------------------------------------------------------------
    def add_stream(self, header_xml: str, stream_id: int | None = None) -> int:
        """Write a StreamHeader chunk (``header_xml``: an ``<info>`` document such as
        :func:`stream_header_xml` or LSL's ``stream_info.as_xml()`` gives). Returns the id."""
        n, fmt = _header_fields(header_xml)
        with self._lock:
            if stream_id is None:
                stream_id = max(self._streams, default=0) + 1
            if stream_id in self._streams:
                raise XdfWriteError(f"{self.path}: stream id {stream_id} is taken")
            if not 0 <= stream_id < 1 << 32:
                raise XdfWriteError(f"stream id must fit in 32 bits, got {stream_id}")
            dtype = np.dtype(NUMERIC_FORMATS[fmt]) if fmt != "string" else None
            self._streams[stream_id] = _Stream(stream_id, n, fmt, dtype)
            self._chunk(TAG_STREAM_HEADER, stream_id, header_xml.encode("utf-8"))
        return stream_id

    def write_samples(self, stream_id: int, timestamps, values) -> None:
        """Write samples: ``timestamps`` (n,) in s; ``values`` (n, channel_count), numbers of
        any type that casts exactly to the stream's format, or for a string stream str/bytes."""
        s = self._stream(stream_id)
        ts = np.asarray(timestamps, dtype=np.float64).reshape(-1)
        n = len(ts)
        if n == 0:
            return
        if not np.all(np.isfinite(ts)):
            raise XdfWriteError(f"{self.path}: stream {stream_id}: a time stamp is not finite")
        if s.dtype is not None:
            v = np.asarray(values)
            if v.ndim == 1 and s.channel_count == 1:
                v = v.reshape(-1, 1)
            if v.shape != (n, s.channel_count):
                raise XdfWriteError(
                    f"{self.path}: stream {stream_id}: values of shape {v.shape}, expected"
                    f" ({n}, {s.channel_count})"
                )
            cast = v.astype(s.dtype)
            if v.dtype.kind == "f" and s.dtype.kind == "i" and not np.array_equal(cast, v):
                raise XdfWriteError(
                    f"{self.path}: stream {stream_id}: values are not whole numbers for"
                    f" {s.channel_format}"
                )
            rows: list = [cast[i : i + CHUNK_SAMPLES] for i in range(0, n, CHUNK_SAMPLES)]
        else:
            text = [list(row) if not isinstance(row, str | bytes) else [row] for row in values]
            if len(text) != n or any(len(r) != s.channel_count for r in text):
                raise XdfWriteError(
                    f"{self.path}: stream {stream_id}: expected {n} samples of"
                    f" {s.channel_count} strings"
                )
            rows = [text[i : i + CHUNK_SAMPLES] for i in range(0, n, CHUNK_SAMPLES)]
        with self._lock:
            if s.footer_written:
                raise XdfWriteError(f"{self.path}: stream {stream_id} is closed (footer written)")
            for k, block in enumerate(rows):
                t = ts[k * CHUNK_SAMPLES : k * CHUNK_SAMPLES + len(block)]
                self._chunk(TAG_SAMPLES, stream_id, self._samples_content(s, t, block))
            s.first = float(ts[0]) if s.first is None else s.first
            s.last = float(ts[-1])
            s.count += n

    @staticmethod
    def _samples_content(s: _Stream, ts: np.ndarray, block) -> bytes:
        n = len(ts)
        parts = [varlen_int(n)]
        if s.dtype is not None:
            # One record per sample: [8][float64 stamp][values], built with a structured array.
            rec = np.empty(n, dtype=[("b", "u1"), ("t", "<f8"), ("v", s.dtype, (s.channel_count,))])
            rec["b"], rec["t"], rec["v"] = 8, ts, block
            parts.append(rec.tobytes())
        else:
            stamp = struct.Struct("<Bd")
            for t, row in zip(ts, block, strict=True):
                parts.append(stamp.pack(8, float(t)))
                for value in row:
                    raw = value if isinstance(value, bytes) else str(value).encode("utf-8")
                    parts.append(varlen_int(len(raw)) + raw)
        return b"".join(parts)

    def write_clock_offset(self, stream_id: int, collection_time: float, offset: float) -> None:
        """A ClockOffset chunk: at ``collection_time`` (the stream's clock) the recorder's clock
        read ``collection_time + offset``."""
        s = self._stream(stream_id)
        with self._lock:
            self._chunk(TAG_CLOCK_OFFSET, stream_id, struct.pack("<dd", collection_time, offset))
            s.offsets.append((float(collection_time), float(offset)))

    def write_boundary(self) -> None:
        with self._lock:
            self._chunk(TAG_BOUNDARY, None, BOUNDARY_SIGNATURE)

    def write_footer(self, stream_id: int) -> None:
        """The stream's StreamFooter (its first and last stamps, count, clock offsets)."""
        s = self._stream(stream_id)
        info = ET.Element("info")
        ET.SubElement(info, "first_timestamp").text = _text(s.first or 0.0)
        ET.SubElement(info, "last_timestamp").text = _text(s.last or 0.0)
        ET.SubElement(info, "sample_count").text = str(s.count)
        offsets = ET.SubElement(info, "clock_offsets")
        for t, v in s.offsets:
            o = ET.SubElement(offsets, "offset")
            ET.SubElement(o, "time").text = _text(t)
            ET.SubElement(o, "value").text = _text(v)
        xml = '<?xml version="1.0"?>' + ET.tostring(info, encoding="unicode")
        with self._lock:
            if s.footer_written:
                return
            self._chunk(TAG_STREAM_FOOTER, stream_id, xml.encode())
            s.footer_written = True

    def flush(self) -> None:
        with self._lock:
            self._fh.flush()

    def close(self) -> Path:
        """Write the footers not yet written, sync, and give the file its name."""
        if self.closed:
            return self.path
        for sid in list(self._streams):
            self.write_footer(sid)
        with self._lock:
            self._fh.flush()
            os.fsync(self._fh.fileno())
            self._fh.close()
            os.replace(self.part, self.path)
            self.closed = True
        return self.path

    def abort(self) -> None:
        """Close without renaming (the ``.part`` file stays, as it is)."""
        if not self.closed:
            with self._lock:
                self._fh.close()
                self.closed = True

    def __enter__(self) -> XdfWriter:
        return self

    def __exit__(self, exc_type, *rest) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


# -- recording LSL streams ------------------------------------------------------------------------
class RecorderError(ValueError):
    """The recorder cannot start as asked (no stream found, a bad query)."""


def _pull(inlet, max_samples: int) -> tuple[list, np.ndarray]:
    """The samples available now (at most ``max_samples``): rows of values, and stamps.

    Sample by sample (``pull_sample``), not ``pull_chunk``: with ``recover=True`` an inlet whose
    outlet has gone (a session that ended) still hands over what it had received, one sample at
    a time (measured: ~2 µs a sample), where ``pull_chunk`` was seen to block; and with
    ``recover=False`` liblsl drops the whole buffer at the loss (a LostError at once)."""
    rows, stamps = [], []
    for _ in range(max_samples):
        values, stamp = inlet.pull_sample(timeout=0.0)
        if stamp is None:
            break
        rows.append(values)
        stamps.append(stamp)
    return rows, np.asarray(stamps, dtype=np.float64)


@dataclass
class RecordedStream:
    """One stream the recorder writes: its LSL info and its id in the file."""

    name: str
    type: str
    source_id: str
    stream_id: int
    inlet: Any = field(repr=False)
    samples: int = 0
    silent: bool = False  # its clock offset could not be measured (its outlet has gone)
    offset_failures: int = 0


class LslRecorder:
    """Records LSL streams into an XDF file until :meth:`stop`: our stand-in for LabRecorder.

    ``types`` / ``names``: record every stream whose type or name is listed (both empty: every
    stream found); ``source_ids``: only streams whose source_id starts with one of these.
    Streams are resolved once at :meth:`start` (``resolve_s`` long, waiting for at least
    ``expect`` streams), their inlets opened and their headers written before :meth:`start`
    returns, so that every sample pushed after that is recorded. A thread then pulls every
    ``poll_s`` and writes a Boundary chunk every ``boundary_interval_s``; another writes a
    ClockOffset chunk per stream every ``offset_interval_s`` (LSL's ``time_correction``).
    :meth:`stop` pulls for ``drain_s`` more (what is on its way), writes the footers and
    closes the file.

    A stream whose outlet goes away (the end of a session) is not an error: the inlets are
    made with ``recover=True``, so what they had received is still pulled, and the stream's
    clock offsets stop (:attr:`notes` says when). :attr:`errors` holds what went wrong.

    Time stamps are written as LSL gives them (the sender's clock, no post-processing), with
    the clock offsets beside them, as LabRecorder does; ``pyxdf.load_xdf`` maps them onto the
    recorder's clock.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        types: Iterable[str] = (),
        names: Iterable[str] = (),
        source_ids: Iterable[str] = (),
        expect: int = 1,
        resolve_s: float = 5.0,
        poll_s: float = 0.02,
        offset_interval_s: float = 5.0,
        boundary_interval_s: float = 10.0,
        drain_s: float = 0.5,
        overwrite: bool = False,
        on_error: Callable[[str], None] | None = None,
    ) -> None:
        self.path = Path(path)
        self.types = tuple(types)
        self.names = tuple(names)
        self.source_ids = tuple(source_ids)
        self.expect = expect
        self.resolve_s = resolve_s
        self.poll_s = poll_s
        self.offset_interval_s = offset_interval_s
        self.boundary_interval_s = boundary_interval_s
        self.drain_s = drain_s
        self.overwrite = overwrite
        self.on_error = on_error
        self.streams: list[RecordedStream] = []
        self.errors: list[str] = []
        self.notes: list[str] = []  # what is worth knowing but lost nothing
        self._writer: XdfWriter | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._offset_thread: threading.Thread | None = None

    def _wanted(self, info) -> bool:
        if self.source_ids and not info.source_id().startswith(self.source_ids):
            return False
        if not self.types and not self.names:
            return True
        return info.type() in self.types or info.name() in self.names

    def _predicate(self) -> str:
        """An XPath predicate for LSL's resolver that matches what is wanted (a superset:
        :meth:`_wanted` decides)."""

        def lit(x: str) -> str | None:
            return f"'{x}'" if "'" not in x else None

        parts = []
        ids = [lit(x) for x in self.source_ids]
        if ids and None not in ids:
            parts.append("(" + " or ".join(f"starts-with(source_id,{x})" for x in ids) + ")")
        props = [("type", lit(t)) for t in self.types] + [("name", lit(n)) for n in self.names]
        if props and all(v is not None for _, v in props):
            parts.append("(" + " or ".join(f"{k}={v}" for k, v in props) + ")")
        return " and ".join(parts) or "channel_count>0"

    def _resolve(self) -> list:
        """The wanted streams: LSL's resolver asked until ``expect`` of them answer (it returns
        as soon as they do) or ``resolve_s`` passes."""
        import pylsl

        deadline = time.monotonic() + self.resolve_s
        found: dict[str, object] = {}
        predicate = self._predicate()
        while True:
            left = max(0.1, deadline - time.monotonic())
            for info in pylsl.resolve_bypred(predicate, minimum=self.expect, timeout=left):
                if self._wanted(info) and info.uid() not in found:
                    found[info.uid()] = info
            if len(found) >= self.expect or time.monotonic() >= deadline:
                break
        return list(found.values())

    def start(self) -> list[RecordedStream]:
        import pylsl

        infos = self._resolve()
        asked = [f"type {t!r}" for t in self.types] + [f"name {n!r}" for n in self.names]
        wanted = ", ".join(asked) or "any"
        if len(infos) < self.expect:
            raise RecorderError(
                f"found {len(infos)} LSL stream(s) matching {wanted} in {self.resolve_s:g} s,"
                f" expected at least {self.expect}"
            )
        self._writer = XdfWriter(
            self.path, overwrite=self.overwrite, file_info={"recorder": "steerlab LslRecorder"}
        )
        try:
            for info in sorted(infos, key=lambda i: (i.type(), i.name(), i.uid())):
                inlet = pylsl.StreamInlet(info, max_buflen=360, recover=True)
                inlet.open_stream(timeout=self.resolve_s)
                full = inlet.info(timeout=self.resolve_s)
                sid = self._writer.add_stream(full.as_xml())
                self.streams.append(
                    RecordedStream(full.name(), full.type(), full.source_id(), sid, inlet)
                )
            self._writer.flush()
        except Exception:
            self._writer.abort()
            raise
        self._thread = threading.Thread(target=self._run, name="xdf-recorder", daemon=True)
        self._offset_thread = threading.Thread(
            target=self._run_offsets, name="xdf-recorder-offsets", daemon=True
        )
        self._thread.start()
        self._offset_thread.start()
        return list(self.streams)

    @staticmethod
    def _now_text() -> str:
        return time.strftime("%H:%M:%S")

    def _error(self, what: str) -> None:
        self.errors.append(what)
        if self.on_error is not None:
            self.on_error(what)

    def _pull_all(self) -> int:
        assert self._writer is not None
        got = 0
        for s in self.streams:
            while True:
                try:
                    values, stamps = _pull(s.inlet, 4096)
                except Exception as e:  # a lost stream: recorded up to here, said
                    self._error(f"stream {s.name!r} ({s.type}): {type(e).__name__}: {e}")
                    break
                if len(stamps) == 0:
                    break
                self._writer.write_samples(s.stream_id, stamps, values)
                s.samples += len(stamps)
                got += len(stamps)
        return got

    def _offsets(self, timeout_s: float = 2.0) -> None:
        """One ClockOffset chunk per stream (LSL's ``time_correction``). A stream that gives
        none ``MAX_OFFSET_FAILURES`` times in a row (its outlet has gone: a session that ended)
        is not asked again; what it sent is recorded all the same."""
        import pylsl

        assert self._writer is not None
        for s in self.streams:
            if s.silent or s.inlet is None:
                continue
            try:
                offset = s.inlet.time_correction(timeout=timeout_s)
            except Exception as e:
                s.offset_failures += 1
                if s.offset_failures >= MAX_OFFSET_FAILURES:
                    s.silent = True
                    self.notes.append(
                        f"stream {s.name!r}: no clock offset from {self._now_text()} on"
                        f" ({type(e).__name__}); its outlet has probably gone"
                    )
                continue
            s.offset_failures = 0
            now = pylsl.local_clock()
            self._writer.write_clock_offset(s.stream_id, now - offset, offset)

    def _run_offsets(self) -> None:
        """Clock offsets on a thread of their own: a slow ``time_correction`` never holds up
        the pulling."""
        try:
            while True:
                self._offsets()
                if self._stop.wait(self.offset_interval_s):
                    return
        except Exception as e:
            if not self._stop.is_set():  # else: the file closed while it measured
                self._error(f"clock offsets stopped: {type(e).__name__}: {e}")

    def _run(self) -> None:
        next_boundary = time.monotonic() + self.boundary_interval_s
        try:
            while not self._stop.is_set():
                self._pull_all()
                now = time.monotonic()
                if now >= next_boundary:
                    self._writer.write_boundary()  # type: ignore[union-attr]
                    next_boundary = now + self.boundary_interval_s
                self._stop.wait(self.poll_s)
        except Exception as e:
            self._error(f"recorder stopped: {type(e).__name__}: {e}")

    def stop(self) -> Path:
        """Pull for ``drain_s`` more (samples on their way), write the footers and close;
        returns the file's path."""
        if self._writer is None:
            raise RecorderError("the recorder was not started")
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self._offset_thread is not None:
            # It may be waiting on a stream whose outlet has gone: not waited for.
            self._offset_thread.join(0.2)
        end = time.monotonic() + self.drain_s
        while True:
            self._pull_all()
            if time.monotonic() >= end:
                break
            time.sleep(self.poll_s)
        for s in self.streams:
            s.inlet = None  # pylsl closes an inlet with its last reference
        return self._writer.close()

    def __enter__(self) -> LslRecorder:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._writer is not None and not self._writer.closed:
            self.stop()
