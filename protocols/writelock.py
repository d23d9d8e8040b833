"""One writer per session file: an exclusive OS lock (``flock``) on ``NAME.h5.lock`` beside it.

The writer takes the lock before it touches the session file and holds it for the whole session,
breaks included; the kernel drops it when the process ends, however it ends (a SIGKILL leaves no
stale lock). The lock file holds who holds it (pid, command, since when) so that a refused second
writer can say so. Readers never take it; they only ask whether a writer is alive
(:func:`live_writer`), to know whether the file may be mid-write.

The lock file is removed on release. Removing a lock file is racy unless the taker checks,
after locking, that the name still points at the file it locked; :meth:`WriterLock.acquire`
does, and starts again if not.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import shlex
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

LOCK_SUFFIX = ".lock"


class LockedError(ValueError):
    """Another live process writes this session file. The message names it."""


def lock_path(path: str | Path) -> Path:
    p = Path(path)
    return p.with_name(p.name + LOCK_SUFFIX)


def command_line() -> str:
    argv = list(sys.argv) or ["python"]
    prog = os.path.basename(argv[0])
    if prog in ("cli.py", "__main__.py", "steerlab"):
        prog = "steerlab"
    return shlex.join([prog, *argv[1:]])


def _describe(info: dict | None) -> str:
    if not info:
        return "another process (it has not written its name yet)"
    return (
        f"process {info.get('pid')} ({info.get('command')}, on {info.get('host')}) "
        f"since {info.get('since_utc')}"
    )


def _read_info(fd: int) -> dict | None:
    try:
        raw = os.pread(fd, 4096, 0)
        info = json.loads(raw.decode())
        return info if isinstance(info, dict) else None
    except (OSError, ValueError):
        return None


def live_writer(path: str | Path) -> dict | None:
    """Who writes ``path`` now (pid, command, since_utc), or None when no live process does."""
    lp = lock_path(path)
    try:
        fd = os.open(lp, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        return None  # no lock file: nobody writes (or a symlink: not ours)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise
            return _read_info(fd) or {}
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def describe_writer(path: str | Path) -> str | None:
    info = live_writer(path)
    return None if info is None else _describe(info)


class WriterLock:
    """The exclusive writer lock of one session file. A context manager; reentrant release."""

    def __init__(self, path: str | Path, *, command: str | None = None, wait_s: float = 1.0):
        self.path = Path(path)
        self.lock_path = lock_path(self.path)
        self.command = command or command_line()
        self.wait_s = wait_s  # rides over a reader's momentary probe, never over a writer
        self.fd: int | None = None

    @property
    def held(self) -> bool:
        return self.fd is not None

    def acquire(self) -> WriterLock:
        if self.fd is not None:
            return self
        deadline = time.monotonic() + self.wait_s
        while True:
            try:
                fd = os.open(
                    self.lock_path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644
                )
            except OSError as e:
                raise LockedError(
                    f"{self.path}: cannot create the writer lock {self.lock_path.name}: "
                    f"{e.strerror or e}"
                ) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                if e.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                    os.close(fd)
                    raise
                info = _read_info(fd)
                os.close(fd)
                if time.monotonic() < deadline:
                    time.sleep(0.05)
                    continue
                raise LockedError(
                    f"{self.path}: being written by {_describe(info)}; refusing to write it "
                    "too (readers such as report and export may open it)"
                ) from None
            st = os.fstat(fd)
            try:
                now = os.stat(self.lock_path, follow_symlinks=False)
            except FileNotFoundError:
                now = None
            if now is None or (now.st_dev, now.st_ino) != (st.st_dev, st.st_ino):
                os.close(fd)  # the previous holder removed it between our open and lock
                continue
            info = {
                "pid": os.getpid(),
                "command": self.command,
                "host": os.uname().nodename,
                "since_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            }
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(info).encode(), 0)
            self.fd = fd
            return self

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            self.lock_path.unlink(missing_ok=True)  # while still holding it (see module doc)
        finally:
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> WriterLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
