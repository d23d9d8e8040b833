"""Adding channels made from another recording to trials of a session file, safely.

What ``steerlab import-xdf`` and ``steerlab import-tekscan`` add to a trial group
(``docs/import.md``):

* **channels**: 1-D float64 datasets beside the trial's own, one value per trial sample (NaN
  where the other recording says nothing), with ``units``, ``resample_method`` and where they
  came from as attributes. The session reader returns them with the trial's other channels
  (``TrialRecord.extra``).
* **the source samples as recorded**, not resampled, in a group ``imported/NAME`` of the trial:
  nothing the other recording held within the trial is lost to the resampling. The reader does
  not read groups; h5py, R or MATLAB read them as they are.

Every dataset and group added carries ``imported_by`` (the command) and ``imported_utc``.

Safety: the file is changed under its writer lock (a running session, or another import,
holds it: refused, naming the holder), on a copy (``NAME.h5.importing``) that replaces the file
only once every addition is written and synced: a crash leaves the file as it was. The trial's
own datasets and attributes are copied byte for byte and never touched. A name that exists
already is refused (nothing written), unless ``replace``, which replaces only what an import
made (``imported_by``), never a recorded channel. Several files (:func:`add_to_files`): every
lock is taken and every refusal checked for all of them before the first is written; a write
that fails even so (a disk that fills up) is said naming the files written and those not, and
the failed one is as it was.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from steerlab.protocols.datafile import (
    LIBVER,
    DataFileError,
    SessionFile,
    create_channel,
    now_utc,
    set_attrs,
)
from steerlab.protocols.writelock import LockedError, WriterLock

IMPORTED_GROUP = "imported"


class TrialExtrasError(ValueError):
    """The additions cannot be written as asked (names taken, trial missing, file locked)."""


@dataclass
class SourceGroup:
    """Datasets (name → array) and attributes of one ``imported/NAME`` group."""

    datasets: dict[str, np.ndarray]
    attrs: dict = field(default_factory=dict)


@dataclass
class TrialAdditions:
    """What to add to one trial group: channels (name → (values, attrs)) and source groups."""

    key: str
    channels: dict[str, tuple[np.ndarray, dict]] = field(default_factory=dict)
    groups: dict[str, SourceGroup] = field(default_factory=dict)

    def names(self) -> list[str]:
        return [*self.channels, *(f"{IMPORTED_GROUP}/{g}" for g in self.groups)]


def _taken(g: h5py.Group, name: str) -> h5py.HLObject | None:
    return g.get(name)


def _refusals(path: Path, additions: list[TrialAdditions], replace: bool) -> list[str]:
    """Why ``additions`` cannot go into ``path`` as asked (the caller holds its lock)."""
    problems = []
    with h5py.File(path, "r", libver=LIBVER, locking=False) as f:
        trials = f["trials"]
        for a in additions:
            if a.key not in trials:
                problems.append(f"no trial {a.key!r}")
                continue
            g = trials[a.key]
            for name in a.names():
                old = _taken(g, name)
                if old is None:
                    continue
                if not replace:
                    problems.append(
                        f"/trials/{a.key}/{name} exists (imported"
                        f" {old.attrs.get('imported_utc', '?')} by"
                        f" {old.attrs.get('imported_by', 'the recording, not an import')});"
                        " pass --replace to replace what an import made"
                    )
                elif "imported_by" not in old.attrs:
                    problems.append(
                        f"/trials/{a.key}/{name} exists and was not made by an import;"
                        " not replacing a recorded channel"
                    )
    return problems


def _write(path: Path, additions: list[TrialAdditions], command: str, now: str) -> list[str]:
    """Write ``additions`` into a copy of ``path`` that then replaces it (the caller holds its
    lock and has checked the names)."""
    tmp = path.with_name(path.name + ".importing")
    written: list[str] = []
    try:
        tmp.unlink(missing_ok=True)
        shutil.copy2(path, tmp)
        with h5py.File(tmp, "r+", libver=LIBVER, locking=False) as f:
            trials = f["trials"]
            for a in additions:
                g = trials[a.key]
                for name in a.names():
                    if name in g:
                        del g[name]
                for name, (values, attrs) in a.channels.items():
                    d = create_channel(g, name, data=np.asarray(values, dtype=np.float64))
                    set_attrs(d, {**attrs, "imported_by": command, "imported_utc": now})
                    written.append(f"{path}:/trials/{a.key}: {name}")
                if a.groups:
                    parent = g.require_group(IMPORTED_GROUP)
                    for name, src in a.groups.items():
                        sg = parent.create_group(name)
                        for dname, data in src.datasets.items():
                            arr = np.asarray(data)
                            if arr.dtype.kind in "OUS":
                                arr = np.array(
                                    [x.decode("utf-8", "replace") if isinstance(x, bytes)
                                     else str(x) for x in arr.ravel()],
                                    dtype=h5py.string_dtype(),
                                ).reshape(arr.shape)  # fmt: skip
                            if arr.size == 0 or arr.dtype.kind == "O":
                                # Empty, or text: HDF5's filters take neither.
                                sg.create_dataset(dname, data=arr)
                            else:
                                chunks = (max(1, min(len(arr), 65536)), *arr.shape[1:])
                                create_channel(sg, dname, data=arr, chunks=chunks,
                                               maxshape=(None, *arr.shape[1:]))  # fmt: skip
                        set_attrs(sg, {**src.attrs, "imported_by": command, "imported_utc": now})
                        written.append(f"{path}:/trials/{a.key}: {IMPORTED_GROUP}/{name}")
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    try:
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass
    return written


def _why(e: BaseException) -> str:
    if isinstance(e, OSError) and e.strerror:
        return f"{e.strerror}{f': {e.filename}' if e.filename else ''}"
    return f"{type(e).__name__}: {e}"


def add_to_files(
    plan: dict[Path, list[TrialAdditions]], *, command: str, replace: bool = False
) -> list[str]:
    """Write each file's additions, all or nothing: every file's lock is taken and every
    refusal checked before the first file is written. Returns what was written, one line each
    (``FILE:/trials/KEY: NAME``). See the module docstring for the guarantees."""
    todo = {
        Path(p): kept
        for p, adds in plan.items()
        if (kept := [a for a in adds if a.channels or a.groups])
    }
    if not todo:
        return []
    others = len(todo) > 1
    locks: list[WriterLock] = []
    try:
        problems: list[str] = []
        for path in todo:
            try:
                # Readable, and a crashed writer's "open for write" flag cleared (under the
                # lock, which the reader takes for that moment itself).
                SessionFile(path)
                lock = WriterLock(path)
                lock.acquire()
                locks.append(lock)
            except (DataFileError, LockedError) as e:
                problems.append(str(e))
            except OSError as e:  # a lock file that cannot be made (a read-only folder)
                problems.append(f"{path}: cannot take its writer lock ({_why(e)})")
        if not problems:
            for path, additions in todo.items():
                try:
                    found = _refusals(path, additions, replace)
                except (OSError, ValueError, KeyError, RuntimeError) as e:
                    found = [f"unreadable ({_why(e)})"]
                if found:
                    problems.append(f"{path}: nothing written: " + "; ".join(found))
        if problems:
            if others:
                names = ", ".join(str(p) for p in todo)
                problems.append(f"nothing written to any of the session files ({names})")
            elif "nothing written" not in problems[0]:
                problems.append("nothing written")
            raise TrialExtrasError("; ".join(problems))
        now = now_utc()
        written: list[str] = []
        done: list[Path] = []
        for path, additions in todo.items():
            try:
                written += _write(path, additions, command, now)
            except (OSError, ValueError, KeyError, RuntimeError, TypeError) as e:
                msg = f"{path}: writing the imported data failed ({_why(e)}); the file is as it was"
                if others:
                    rest = [str(p) for p in todo if p not in done and p != path]
                    msg += (
                        f"; already written: {', '.join(map(str, done)) or 'none'}"
                        f"; not written: {', '.join([str(path), *rest])}"
                    )
                raise TrialExtrasError(msg) from None
            done.append(path)
        return written
    finally:
        for lock in locks:
            lock.release()


def add_to_trials(
    path: str | Path, additions: list[TrialAdditions], *, command: str, replace: bool = False
) -> list[str]:
    """Write ``additions`` into the session file ``path`` (:func:`add_to_files`)."""
    return add_to_files({Path(path): additions}, command=command, replace=replace)
