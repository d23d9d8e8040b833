"""Stream decoder: bytes in arbitrary chunks -> validated glove frames.

Error policy (also in docs/glove-protocol.md): nothing about the *bytes* makes ``feed()`` raise.
Every defect is counted in ``stats`` and reported as a :class:`DecodeEvent` (kept in
``recent_events`` and passed to the optional ``on_event`` sink). What can escape ``feed()``:

- ``TypeError`` if ``data`` is not bytes-like (a programming error, not a line error);
- whatever the injected ``clock`` or ``on_event`` callables raise, unchanged. ``on_event`` runs
  after the bytes are consumed, so the decoder stays consistent, but the frames completed by
  that call are then lost to the caller.

How a candidate frame is judged, in order:

1. bytes before a sync pattern are skipped (``bytes_discarded``); regaining sync after skipping
   counts one ``resyncs`` when the next good frame is found;
2. version != 1, unknown frame type, or a length field that does not match the type:
   ``bad_headers``; the first sync byte is skipped and the search goes on;
3. CRC mismatch: ``crc_errors``; likewise only one byte is skipped, so a real frame hidden behind
   a false sync (garbage that happens to contain 0xA5 0x5A) is still found;
4. CRC good but a total above FORCE_RAW_MAX: ``out_of_range``; the frame is dropped but its
   sequence number is trusted (the CRC vouches for it), so it does not count as a gap;
5. sequence checks: a forward step of d > 1 adds d - 1 to ``dropped_frames``; d == 0 is a
   ``duplicates`` (dropped); a step back (d >= 2**15 modulo 2**16) is a ``sequence_resets``
   (device restart; the frame is kept).

Counts are of rejected *candidates*: one corrupted frame usually costs one CRC error, but a sync
pattern inside it can add a bad header or a second CRC error.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import StrEnum

from steerlab.hardware.glove import protocol as p

_HALF_SEQUENCE = p.SEQUENCE_MODULUS // 2


@dataclass(frozen=True)
class GloveFrame:
    """One accepted frame: wire content plus when the host received it."""

    sequence: int  # as on the wire, 0..65535
    sequence_ext: int  # never wraps; strictly increasing over the decoder's life
    device_time_us: int  # as on the wire, wraps at 2**32
    left_raw: int
    right_raw: int
    host_time_s: float  # injected clock, read once per feed() call that completed the frame
    cells_left: bytes | None = None  # 349 uint8 cells in FORCE_MAP frames
    cells_right: bytes | None = None


class DecodeEventKind(StrEnum):
    RESYNC = "resync"
    BAD_HEADER = "bad_header"
    CRC_ERROR = "crc_error"
    OUT_OF_RANGE = "out_of_range"
    SEQUENCE_GAP = "sequence_gap"
    DUPLICATE = "duplicate"
    SEQUENCE_RESET = "sequence_reset"


@dataclass(frozen=True)
class DecodeEvent:
    kind: DecodeEventKind
    host_time_s: float
    detail: str
    count: int = 1  # frames lost for SEQUENCE_GAP, bytes skipped for RESYNC, else 1


@dataclass
class DecoderStats:
    bytes_in: int = 0
    bytes_discarded: int = 0
    frames: int = 0  # accepted frames
    resyncs: int = 0
    bad_headers: int = 0
    crc_errors: int = 0
    out_of_range: int = 0
    dropped_frames: int = 0  # missing sequence numbers
    duplicates: int = 0
    sequence_resets: int = 0


class GloveDecoder:
    """Incremental decoder. Not thread-safe: feed it from one thread."""

    def __init__(
        self,
        *,
        clock: Callable[[], float] = time.monotonic,
        on_event: Callable[[DecodeEvent], None] | None = None,
        max_events: int = 256,
    ) -> None:
        self._clock = clock
        self._on_event = on_event
        self._buf = bytearray()
        self._stats = DecoderStats()
        self._last_seq: int | None = None
        self._seq_ext = 0
        self._skipped_since_frame = 0
        self._pending: list[DecodeEvent] = []
        self.recent_events: deque[DecodeEvent] = deque(maxlen=max_events)

    @property
    def stats(self) -> DecoderStats:
        """A copy; the decoder keeps counting in its own."""
        return replace(self._stats)

    @property
    def buffered(self) -> int:
        """Bytes held back waiting for the rest of a frame (always < MAX_FRAME_LEN)."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[GloveFrame]:
        """Add received bytes; return the frames they completed, oldest first."""
        host_time = self._clock()
        self._buf += data
        self._stats.bytes_in += len(data)
        frames: list[GloveFrame] = []
        buf = self._buf
        pos = 0
        while True:
            start = buf.find(p.SYNC, pos)
            if start < 0:
                # A trailing 0xA5 may be the first half of the next sync: keep it.
                keep_from = len(buf) - 1 if buf.endswith(p.SYNC[:1]) else len(buf)
                self._skip(max(keep_from, pos) - pos)
                pos = max(keep_from, pos)
                break
            self._skip(start - pos)
            pos = start
            if len(buf) - pos < p.HEADER_LEN:
                break
            _, version, frame_type, length = p.HEADER.unpack_from(buf, pos)
            if version != p.PROTOCOL_VERSION or p.PAYLOAD_LEN.get(frame_type) != length:
                self._stats.bad_headers += 1
                self._event(
                    DecodeEventKind.BAD_HEADER,
                    host_time,
                    f"version {version}, type 0x{frame_type:02x}, length {length}",
                )
                self._skip(1)
                pos += 1
                continue
            end = pos + p.HEADER_LEN + length + p.CRC_LEN
            if len(buf) < end:
                break
            (crc_rx,) = p.CRC.unpack_from(buf, end - p.CRC_LEN)
            crc = p.crc16_ccitt_false(memoryview(buf)[pos + 2 : end - p.CRC_LEN])
            if crc != crc_rx:
                self._stats.crc_errors += 1
                self._event(
                    DecodeEventKind.CRC_ERROR,
                    host_time,
                    f"received 0x{crc_rx:04x}, computed 0x{crc:04x}",
                )
                self._skip(1)
                pos += 1
                continue
            frame = self._accept(buf, pos, frame_type, host_time)
            pos = end
            if frame is not None:
                frames.append(frame)
        del buf[:pos]
        # Sinks run only once the decoder's state is consistent, so one that raises cannot
        # make the same bytes be counted twice on the next call.
        pending, self._pending = self._pending, []
        if self._on_event is not None:
            for event in pending:
                self._on_event(event)
        return frames

    def _skip(self, n: int) -> None:
        if n > 0:
            self._stats.bytes_discarded += n
            self._skipped_since_frame += n

    def _accept(
        self, buf: bytearray, pos: int, frame_type: int, host_time: float
    ) -> GloveFrame | None:
        """A CRC-checked frame at ``pos``: sequence bookkeeping, range check, build."""
        if self._skipped_since_frame:
            self._stats.resyncs += 1
            self._event(
                DecodeEventKind.RESYNC,
                host_time,
                f"skipped {self._skipped_since_frame} bytes",
                self._skipped_since_frame,
            )
            self._skipped_since_frame = 0

        body_at = pos + p.HEADER_LEN
        seq, t_us, left, right = p.BODY.unpack_from(buf, body_at)
        if not self._track_sequence(seq, host_time):
            return None
        if left > p.FORCE_RAW_MAX or right > p.FORCE_RAW_MAX:
            self._stats.out_of_range += 1
            self._event(
                DecodeEventKind.OUT_OF_RANGE,
                host_time,
                f"seq {seq}: left_raw {left}, right_raw {right} (max {p.FORCE_RAW_MAX})",
            )
            return None

        cells_left = cells_right = None
        if frame_type == p.FRAME_FORCE_MAP:
            at = body_at + p.BODY.size
            cells_left = bytes(buf[at : at + p.CELLS_PER_GLOVE])
            cells_right = bytes(buf[at + p.CELLS_PER_GLOVE : at + 2 * p.CELLS_PER_GLOVE])
        self._stats.frames += 1
        return GloveFrame(
            sequence=seq,
            sequence_ext=self._seq_ext,
            device_time_us=t_us,
            left_raw=left,
            right_raw=right,
            host_time_s=host_time,
            cells_left=cells_left,
            cells_right=cells_right,
        )

    def _track_sequence(self, seq: int, host_time: float) -> bool:
        """Update the sequence state; False if the frame must be dropped (duplicate)."""
        last = self._last_seq
        self._last_seq = seq
        if last is None:
            self._seq_ext = seq
            return True
        step = (seq - last) % p.SEQUENCE_MODULUS
        if step == 0:
            self._stats.duplicates += 1
            self._event(DecodeEventKind.DUPLICATE, host_time, f"seq {seq} repeated")
            return False
        if step >= _HALF_SEQUENCE:
            # Backwards: the device restarted (or over 32767 frames were lost, which the
            # stream-age watchdog of the unit reports long before).
            self._stats.sequence_resets += 1
            self._event(DecodeEventKind.SEQUENCE_RESET, host_time, f"seq {last} -> {seq}")
            self._seq_ext += 1
            return True
        if step > 1:
            self._stats.dropped_frames += step - 1
            self._event(DecodeEventKind.SEQUENCE_GAP, host_time, f"seq {last} -> {seq}", step - 1)
        self._seq_ext += step
        return True

    def _event(self, kind: DecodeEventKind, host_time: float, detail: str, count: int = 1) -> None:
        event = DecodeEvent(kind, host_time, detail, count)
        self.recent_events.append(event)
        self._pending.append(event)
