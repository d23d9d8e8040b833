"""Stream decoder: chunking, resync, CRC, sequence gaps, range checks, fuzzing."""

from __future__ import annotations

import itertools
from dataclasses import asdict

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from steerlab.hardware.glove import protocol as p
from steerlab.hardware.glove.decoder import DecodeEventKind, GloveDecoder, GloveFrame
from steerlab.hardware.glove.protocol import encode_frame


def frames_for(seqs, *, t0_us=0, left=100, right=200):
    return [encode_frame(s, t0_us + 10_000 * i, left + i, right + i) for i, s in enumerate(seqs)]


def content(frame: GloveFrame):
    return (frame.sequence, frame.device_time_us, frame.left_raw, frame.right_raw)


def decode_in_chunks(data: bytes, cuts) -> tuple[list[GloveFrame], GloveDecoder]:
    decoder = GloveDecoder(clock=lambda: 0.0)
    out = []
    bounds = [0, *sorted(cuts), len(data)]
    for a, b in itertools.pairwise(bounds):
        out += decoder.feed(data[a:b])
    return out, decoder


def test_single_frame_fields_and_host_time():
    times = iter([10.0, 20.0])
    decoder = GloveDecoder(clock=lambda: next(times))
    frame_bytes = encode_frame(258, 1_000_000, 1000, 70_000)
    assert decoder.feed(frame_bytes[:10]) == []
    (frame,) = decoder.feed(frame_bytes[10:])
    assert content(frame) == (258, 1_000_000, 1000, 70_000)
    assert frame.host_time_s == 20.0  # the clock reading of the call that completed it
    assert frame.sequence_ext == 258
    assert frame.cells_left is None and frame.cells_right is None
    stats = decoder.stats
    assert (stats.frames, stats.bytes_in, stats.bytes_discarded, stats.resyncs) == (1, 22, 0, 0)


def test_byte_by_byte_equals_one_chunk():
    data = b"".join(frames_for(range(20)))
    whole, _ = decode_in_chunks(data, [])
    single, decoder = decode_in_chunks(data, range(1, len(data)))
    assert [content(f) for f in single] == [content(f) for f in whole]
    assert len(whole) == 20
    assert decoder.buffered == 0


def test_pressure_maps_are_returned():
    left, right = bytes(range(200)) + bytes(149), bytes([9]) * 349
    (frame,) = GloveDecoder().feed(encode_frame(1, 2, 3, 4, left, right))
    assert frame.cells_left == left and frame.cells_right == right


def test_resync_after_garbage():
    good = frames_for(range(3))
    garbage = b"\x00\xa5\xff\xa5\x5a\x13garbage\xa5"
    data = garbage + good[0] + garbage + good[1] + good[2]
    frames, decoder = decode_in_chunks(data, [5, 30, 31, 47])
    assert [f.sequence for f in frames] == [0, 1, 2]
    stats = decoder.stats
    assert stats.resyncs == 2
    assert stats.bytes_discarded == 2 * len(garbage)
    assert stats.bad_headers == 2  # the "A5 5A 13" in the garbage: version 0x13
    assert stats.crc_errors == 0 and stats.dropped_frames == 0


def test_truncated_frame_then_good_frame():
    good = frames_for(range(3))
    data = good[0] + good[1][:15] + good[2]  # frame 1 lost its tail mid-line
    frames, decoder = decode_in_chunks(data, [])
    assert [f.sequence for f in frames] == [0, 2]
    stats = decoder.stats
    # The torn frame claims 22 bytes, so its "CRC" is read out of frame 2: one CRC error.
    assert stats.crc_errors == 1
    assert stats.dropped_frames == 1
    assert stats.resyncs == 1


def test_crc_errors_are_counted_and_reported():
    events = []
    decoder = GloveDecoder(clock=lambda: 5.0, on_event=events.append)
    good = frames_for(range(5))
    bad_crc = bytearray(good[1])
    bad_crc[-1] ^= 0x01
    bad_payload = bytearray(good[3])
    bad_payload[14] ^= 0x80  # a bit of the left total
    frames = decoder.feed(good[0] + bad_crc + good[2] + bad_payload + good[4])
    assert [f.sequence for f in frames] == [0, 2, 4]
    stats = decoder.stats
    assert stats.crc_errors == 2
    assert stats.dropped_frames == 2  # the rejected frames' sequence numbers never arrived
    kinds = [e.kind for e in events]
    assert kinds.count(DecodeEventKind.CRC_ERROR) == 2
    assert kinds.count(DecodeEventKind.SEQUENCE_GAP) == 2
    assert all(e.host_time_s == 5.0 for e in events)
    assert list(decoder.recent_events) == events


def test_sequence_gap_with_wrap_around():
    seqs = [65533, 65534, 65535, 0, 1, 4, 8]  # gaps 1 -> 4 (2 lost) and 4 -> 8 (3 lost)
    frames, decoder = decode_in_chunks(b"".join(frames_for(seqs)), [])
    assert [f.sequence for f in frames] == [65533, 65534, 65535, 0, 1, 4, 8]
    assert [f.sequence_ext for f in frames] == [65533, 65534, 65535, 65536, 65537, 65540, 65544]
    stats = decoder.stats
    assert stats.dropped_frames == 2 + 3
    assert stats.sequence_resets == 0 and stats.duplicates == 0


def test_gap_across_the_wrap_point():
    frames, decoder = decode_in_chunks(b"".join(frames_for([65530, 5])), [])
    assert decoder.stats.dropped_frames == 10  # 65531..65535 and 0..4
    assert frames[1].sequence_ext == 65536 + 5


def test_duplicate_is_dropped_and_reset_is_kept():
    data = b"".join(frames_for([10, 11, 11, 12, 3, 4]))
    frames, decoder = decode_in_chunks(data, [])
    assert [f.sequence for f in frames] == [10, 11, 12, 3, 4]
    ext = [f.sequence_ext for f in frames]
    assert ext == sorted(ext) and len(set(ext)) == len(ext)
    stats = decoder.stats
    assert (stats.duplicates, stats.sequence_resets, stats.dropped_frames) == (1, 1, 0)


def test_out_of_range_total_is_rejected_but_not_a_gap():
    events = []
    decoder = GloveDecoder(on_event=events.append)
    data = (
        encode_frame(0, 0, 5, 5)
        + encode_frame(1, 10_000, p.FORCE_RAW_MAX + 1, 5, validate=False)
        + encode_frame(2, 20_000, 5, 0xFFFF_FFFF, validate=False)
        + encode_frame(3, 30_000, p.FORCE_RAW_MAX, 0)
    )
    frames = decoder.feed(data)
    assert [f.sequence for f in frames] == [0, 3]
    stats = decoder.stats
    assert stats.out_of_range == 2
    assert stats.dropped_frames == 0 and stats.crc_errors == 0
    assert [e.kind for e in events] == [DecodeEventKind.OUT_OF_RANGE] * 2
    assert "left_raw 16777216" in events[0].detail


def test_bad_version_type_and_length_are_bad_headers():
    good = encode_frame(7, 0, 1, 1)

    def with_header(version, frame_type, length):
        covered = bytes([version, frame_type]) + length.to_bytes(2, "little") + good[6:-2]
        return p.SYNC + covered + p.crc16_ccitt_false(covered).to_bytes(2, "little")

    bad = [with_header(2, 0x10, 14), with_header(1, 0x12, 14), with_header(1, 0x10, 15)]
    frames, decoder = decode_in_chunks(b"".join(bad) + good, [3, 25])
    assert [f.sequence for f in frames] == [7]
    stats = decoder.stats
    assert stats.bad_headers == 3 and stats.crc_errors == 0
    assert stats.bytes_discarded == sum(map(len, bad))


def test_trailing_partial_sync_is_kept():
    decoder = GloveDecoder()
    frame = encode_frame(1, 2, 3, 4)
    assert decoder.feed(b"xyz" + frame[:1]) == []
    assert decoder.buffered == 1
    assert len(decoder.feed(frame[1:])) == 1


# -- fuzzing ------------------------------------------------------------------------------------

raw_total = st.integers(0, p.FORCE_RAW_MAX)
frame_values = st.tuples(st.integers(0, 2**32 - 1), raw_total, raw_total)


# Random bytes rarely contain a sync; these are made of the protocol's own bytes, so false
# headers, false length fields and CRC checks on garbage are exercised too.
protocol_like_bytes = st.lists(
    st.sampled_from([0xA5, 0x5A, 0x01, 0x10, 0x11, 0x0E, 0x00, 0xC8, 0x02, 0xFF]), max_size=3000
).map(bytes)

# Pieces of real frames (whole or cut, any values including out-of-range totals, with or
# without maps) mixed with random bytes: reaches the CRC, range and sequence paths.
wire_total = st.integers(0, 2**32 - 1)
frame_piece = st.builds(
    lambda seq, t, left, right, maps, a, b: encode_frame(
        seq, t, left, right, *(maps or (None, None)), validate=False
    )[min(a, b) : max(a, b)],
    st.integers(0, 65535),
    st.integers(0, 2**32 - 1),
    wire_total,
    wire_total,
    st.none() | st.just((bytes(349), bytes(range(256)) + bytes(93))),
    st.integers(0, 720) | st.just(0),
    st.integers(0, 720) | st.just(720),
)
spliced_frames = st.lists(frame_piece | st.binary(max_size=16), max_size=30).map(b"".join)


@st.composite
def cuts_for(draw, data):
    n = draw(st.integers(0, min(len(data), 40)))
    return draw(st.lists(st.integers(0, len(data)), min_size=n, max_size=n))


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_fuzz_random_bytes_never_raise_and_split_does_not_matter(data):
    blob = data.draw(st.binary(max_size=3000) | protocol_like_bytes | spliced_frames)
    cuts = data.draw(cuts_for(blob))
    frames, decoder = decode_in_chunks(blob, cuts)
    whole, reference = decode_in_chunks(blob, [])
    assert [content(f) for f in frames] == [content(f) for f in whole]
    assert asdict(decoder.stats) == asdict(reference.stats)
    stats = decoder.stats
    assert stats.bytes_in == len(blob)
    assert stats.bytes_discarded + decoder.buffered <= len(blob)
    assert decoder.buffered < p.MAX_FRAME_LEN
    assert all(f.left_raw <= p.FORCE_RAW_MAX and f.right_raw <= p.FORCE_RAW_MAX for f in frames)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_fuzz_corrupted_stream_keeps_every_intact_frame(data):
    start_seq = data.draw(st.integers(0, 65535), label="start_seq")
    values = data.draw(st.lists(frame_values, min_size=1, max_size=40), label="values")
    sent = [
        (((start_seq + i) % 65536), t, left, right) for i, (t, left, right) in enumerate(values)
    ]
    stream = bytearray()
    intact = []
    for fields in sent:
        stream += data.draw(st.binary(max_size=30), label="garbage before")
        frame = bytearray(encode_frame(*fields))
        # At most one damaged byte per frame: CRC-16 is then guaranteed to catch it, so the
        # expected output is exact.
        if data.draw(st.booleans(), label="corrupt"):
            at = data.draw(st.integers(0, len(frame) - 1), label="at")
            frame[at] ^= data.draw(st.integers(1, 255), label="xor")
        else:
            intact.append(fields)
        stream += frame
    # Zero padding completes any false frame candidate still waiting for bytes; a live stream
    # does the same by flowing on.
    stream += bytes(p.MAX_FRAME_LEN)
    cuts = data.draw(cuts_for(bytes(stream)), label="cuts")
    frames, decoder = decode_in_chunks(bytes(stream), cuts)
    assert [content(f) for f in frames] == intact
    stats = decoder.stats
    assert stats.frames == len(intact)
    assert stats.duplicates == 0 and stats.out_of_range == 0
    if intact:
        first, last = frames[0].sequence_ext, frames[-1].sequence_ext
        assert stats.frames + stats.dropped_frames == last - first + 1


def test_documented_exceptions_only():
    decoder = GloveDecoder()
    with pytest.raises(TypeError):
        decoder.feed("A55A")  # text is a programming error, not line noise
    assert decoder.stats.bytes_in == 0


def test_a_raising_event_sink_leaves_the_decoder_consistent():
    calls = []

    def sink(event):
        calls.append(event)
        if len(calls) == 1:
            raise RuntimeError("sink bug")

    decoder = GloveDecoder(on_event=sink)
    bad = bytearray(encode_frame(0, 0, 1, 1))
    bad[-1] ^= 1
    with pytest.raises(RuntimeError, match="sink bug"):
        decoder.feed(bytes(bad))
    assert decoder.stats.crc_errors == 1
    assert [f.sequence for f in decoder.feed(encode_frame(1, 0, 1, 1))] == [1]
    assert decoder.stats.crc_errors == 1  # the bad bytes were not judged twice
