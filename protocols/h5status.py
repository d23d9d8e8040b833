"""The HDF5 superblock's file-consistency flags: read them, and clear them as ``h5clear -s`` does.

A file opened for writing with ``libver="latest"`` (superblock version 2 or 3) carries, in its
superblock, a byte that says "open for write" (bit 0) and "open for SWMR write" (bit 2). The
library sets it on open and clears it on close. A writer killed with the file open leaves it set,
and the library then refuses every later open (``file is already open for write (may use
<h5clear file> to clear file consistency flags)``), although the data are intact.

:func:`clear_status_flags` does what ``h5clear -s`` does: it sets that byte to 0 and rewrites the
superblock checksum, touching nothing else. It first checks the stored checksum against the one it
computes, so a damaged superblock is reported, never "repaired". Callers must make sure no live
writer has the file open (Steerlab: the writer lock, :mod:`protocols.writelock`).

Superblock v2/v3 layout (HDF5 File Format Specification, "Superblock"): signature (8 bytes),
version, size of offsets, size of lengths, file consistency flags (1 byte each), base address,
superblock extension address, end-of-file address, root group object header address (one
"size of offsets" each), checksum (Jenkins lookup3 of everything before it, 4 bytes LE).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

SIGNATURE = b"\x89HDF\r\n\x1a\n"
FLAGS_OFFSET = 11  # from the superblock's start
WRITE_ACCESS = 0x01
SWMR_WRITE_ACCESS = 0x04
_M = 0xFFFFFFFF


class SuperblockError(ValueError):
    pass


def _rot(x: int, k: int) -> int:
    return ((x << k) | (x >> (32 - k))) & _M


def lookup3(data: bytes, initval: int = 0) -> int:
    """Bob Jenkins' lookup3 ``hashlittle`` (byte-wise), as HDF5's ``H5_checksum_lookup3``."""
    length = len(data)
    a = b = c = (0xDEADBEEF + length + initval) & _M
    i = 0
    while length > 12:
        a = (a + int.from_bytes(data[i : i + 4], "little")) & _M
        b = (b + int.from_bytes(data[i + 4 : i + 8], "little")) & _M
        c = (c + int.from_bytes(data[i + 8 : i + 12], "little")) & _M
        a = (a - c) & _M
        a ^= _rot(c, 4)
        c = (c + b) & _M  # noqa: E702
        b = (b - a) & _M
        b ^= _rot(a, 6)
        a = (a + c) & _M  # noqa: E702
        c = (c - b) & _M
        c ^= _rot(b, 8)
        b = (b + a) & _M  # noqa: E702
        a = (a - c) & _M
        a ^= _rot(c, 16)
        c = (c + b) & _M  # noqa: E702
        b = (b - a) & _M
        b ^= _rot(a, 19)
        a = (a + c) & _M  # noqa: E702
        c = (c - b) & _M
        c ^= _rot(b, 4)
        b = (b + a) & _M  # noqa: E702
        length -= 12
        i += 12
    if length == 0:
        return c
    tail = data[i:] + bytes(12 - length)  # the missing bytes add nothing
    a = (a + int.from_bytes(tail[0:4], "little")) & _M
    b = (b + int.from_bytes(tail[4:8], "little")) & _M
    c = (c + int.from_bytes(tail[8:12], "little")) & _M
    c ^= b
    c = (c - _rot(b, 14)) & _M  # noqa: E702
    a ^= c
    a = (a - _rot(c, 11)) & _M  # noqa: E702
    b ^= a
    b = (b - _rot(a, 25)) & _M  # noqa: E702
    c ^= b
    c = (c - _rot(b, 16)) & _M  # noqa: E702
    a ^= c
    a = (a - _rot(c, 4)) & _M  # noqa: E702
    b ^= a
    b = (b - _rot(a, 14)) & _M  # noqa: E702
    c ^= b
    c = (c - _rot(b, 24)) & _M  # noqa: E702
    return c


def _find_superblock(fh) -> int:
    # At 0, or (after a user block) at 512, 1024, 2048, ... bytes.
    size = os.fstat(fh.fileno()).st_size
    pos = 0
    while pos + 8 <= size:
        fh.seek(pos)
        if fh.read(8) == SIGNATURE:
            return pos
        pos = 512 if pos == 0 else pos * 2
    raise SuperblockError("no HDF5 signature (not an HDF5 file, or its start is damaged)")


def _read(fh) -> tuple[int, bytes, int]:
    """(superblock offset, the bytes the checksum covers, the stored checksum)."""
    pos = _find_superblock(fh)
    fh.seek(pos)
    head = fh.read(12)
    if len(head) < 12:
        raise SuperblockError("superblock cut short")
    version, size_of_offsets = head[8], head[9]
    if version < 2:
        raise SuperblockError(f"superblock version {version} has no status flags to clear")
    if size_of_offsets not in (2, 4, 8, 16):
        raise SuperblockError(f"superblock damaged (size of offsets {size_of_offsets})")
    body = head + fh.read(4 * size_of_offsets)
    raw = fh.read(4)
    if len(body) < 12 + 4 * size_of_offsets or len(raw) < 4:
        raise SuperblockError("superblock cut short")
    (stored,) = struct.unpack("<I", raw)
    return pos, body, stored


def status_flags(path: str | Path) -> int:
    """The superblock's file-consistency flags (0: closed cleanly, or never opened for write)."""
    with open(path, "rb") as fh:
        _pos, body, stored = _read(fh)
    if lookup3(body) != stored:
        raise SuperblockError("superblock checksum does not match (damaged superblock)")
    return body[FLAGS_OFFSET]


def clear_status_flags(path: str | Path) -> int:
    """Set the flags to 0 and rewrite the checksum (``h5clear -s``). Returns the old flags.

    Only the flags byte and the 4 checksum bytes are written; nothing when the flags are 0.
    """
    with open(path, "r+b") as fh:
        pos, body, stored = _read(fh)
        if lookup3(body) != stored:
            raise SuperblockError("superblock checksum does not match (damaged superblock)")
        old = body[FLAGS_OFFSET]
        if old == 0:
            return 0
        new = body[:FLAGS_OFFSET] + b"\x00" + body[FLAGS_OFFSET + 1 :]
        fh.seek(pos + FLAGS_OFFSET)
        fh.write(b"\x00")
        fh.seek(pos + len(body))
        fh.write(struct.pack("<I", lookup3(new)))
        fh.flush()
        os.fsync(fh.fileno())
    return old
