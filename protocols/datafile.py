"""Session files: one HDF5 file per subject session. Layout in ``docs/data-format.md``.

:class:`SessionWriter` is an engine subscriber. While a trial runs the file is in SWMR mode
(single writer, multiple readers): another process can read it, and a writer killed at any
moment leaves a readable file holding every sample up to the last flush, with the trial still
marked ``incomplete``. Samples are flushed at least every ``flush_interval_s`` of wall time.
Nothing is ever overwritten: a redo is a new group; the old one is only marked superseded.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Iterable
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path

import h5py
import numpy as np

from steerlab.protocols import events as ev
from steerlab.protocols.engine import TrialFault
from steerlab.protocols.h5status import SuperblockError, clear_status_flags
from steerlab.protocols.names import UnsafeNameError, check_name
from steerlab.protocols.perturbation import PerturbationDesign
from steerlab.protocols.records import (
    CORE_CHANNELS,
    STATUS_ABORTED,
    STATUS_COMPLETE,
    STATUS_DAMAGED,
    STATUS_INCOMPLETE,
    STATUS_SUPERSEDED,
    TrialRecord,
)
from steerlab.protocols.writelock import LockedError, WriterLock, live_writer

log = logging.getLogger(__name__)

FORMAT = "steerlab-session"
FORMAT_VERSION = 2  # 2: compressed, counts channels, native attributes (docs/data-format.md)

UNITS = {
    "time_s": "s",
    "host_time_s": "s",
    "perturbation_torque_Nm": "N·m",
    "driver_torque_Nm": "N·m",
    "wheel_angle_rad": "rad",
    "wheel_velocity_rad_s": "rad/s",
    "motor_command_Nm": "N·m",
    "motor_torque_Nm": "N·m",
    "grip_force_N": "N",
    "grip_force_left_N": "N",
    "grip_force_right_N": "N",
    # Simulated time-varying trials only: the driver's true parameters (hardware.sim.world).
    "true_b_i_Nms_per_rad": "N·m·s/rad",
    "true_k_i_Nm_per_rad": "N·m/rad",
    "true_b_c_Nms_per_rad": "N·m·s/rad",
    "true_k_c_Nm_per_rad": "N·m/rad",
    "true_grip_mean_N": "N",
    # Driving trials (hardware.vehicle.DRIVING_CHANNELS, docs/driving.md).
    "road_distance_m": "m",
    "lateral_position_m": "m",
    "heading_error_rad": "rad",
    "road_curvature_1pm": "1/m",
    "lane_width_m": "m",
    "aligning_torque_Nm": "N·m",
}
SIGN_CONVENTIONS = (
    "wheel_angle_rad: positive counter-clockwise seen by the driver; "
    "perturbation_torque_Nm and motor_*_Nm: torque on the wheel, positive towards positive angle; "
    "driver_torque_Nm: the torque the wheel exerts on the hands (S(Tp,θ)/S(Tp,Td) > 0 at low "
    "frequency); grip_force_N: total of both hands."
)
#: HDF5 format bounds of every object Steerlab writes. SWMR needs the 1.10 format; capping it
#: there keeps the files readable by HDF5 1.10–1.14 libraries (R's hdf5r, Octave, MATLAB,
#: HDFView): "latest" with the HDF5 2.0 that h5py bundles writes objects HDF5 1.10 cannot open.
LIBVER = ("v110", "v110")

#: Suffix of a counts dataset moved aside while it is rewritten as float64 (see
#: ``SessionWriter._counts_to_float``).
COUNTS_ASIDE = "~counts"
MARK_DTYPE = np.dtype([("sample", "<i8"), ("kind", "S16"), ("detail", "S240")])


class DataFileError(ValueError):
    """A session file that cannot be read or written as asked; the message names the file."""


def software_version() -> str:
    try:
        from importlib.metadata import version

        return version("steerlab")
    except Exception:
        return "0+unknown"


def now_utc() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def native_attr(v: object) -> object:
    """An attribute value in a type MATLAB, R and HDFView read as it is (``docs/data-format.md``).

    Booleans become ``uint8`` 0/1 (h5py would write an HDF5 enum, which MATLAB and R read
    awkwardly); a list of strings becomes an array of variable-length UTF-8 strings and a list
    of numbers a numeric array; only a structure (a mapping, or a list holding one) is JSON.
    """
    if isinstance(v, bool | np.bool_):
        return np.uint8(bool(v))
    if isinstance(v, dict):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        if v and all(isinstance(x, str) for x in v):
            return np.array(v, dtype=h5py.string_dtype())
        if v and all(isinstance(x, int | float) and not isinstance(x, bool) for x in v):
            return np.asarray(v)
        return json.dumps(v)
    if isinstance(v, np.ndarray):
        if v.dtype == np.bool_:
            return v.astype(np.uint8)
        if v.dtype.kind in "OU":  # str items (an imported session's arrays come back as these)
            return np.array([str(x) for x in v.ravel()], dtype=h5py.string_dtype()).reshape(v.shape)
    return v


def set_attrs(obj, attrs: dict) -> None:
    for k, v in attrs.items():
        if v is None:
            continue
        obj.attrs[k] = native_attr(v)


#: Free space the writer keeps in hand: it stops writing samples (a fault that ends the trial)
#: before the disk is this full, so that the last samples, the trial's end and the file's
#: metadata still fit and the file stays readable. HDF5 itself, once a write fails for lack of
#: space, leaves a file no reader can open (and the writing process may crash).
RESERVE_BYTES = 4 * 1024 * 1024


class WriterFailure(TrialFault):
    """The session writer cannot go on (disk full, I/O error, file removed): a fault that ends
    the trial. The message names the file and the cause."""


#: Where the samples a failed writer could not put into the session file go when the session
#: file's folder cannot take them either: a memory-backed folder (RAM, not the full disk).
def _fallback_dirs() -> list[Path]:
    out = [Path(d) for d in (os.environ.get("XDG_RUNTIME_DIR"), "/dev/shm") if d]
    import tempfile

    out.append(Path(tempfile.gettempdir()))
    return [d for d in out if d.is_dir()]


def unsaved_path(session_path: str | Path, key: str) -> Path:
    """The file next to ``session_path`` that holds trial ``key``'s samples its writer could not
    write (``SessionWriter``, after a failure): a NumPy ``.npz`` (one array per channel, plus
    ``first_sample``, the trial sample index of its first row, ``session_file`` and
    ``trial_key``)."""
    p = Path(session_path)
    return p.with_name(f"{p.name}.{key.replace('/', '_')}.unsaved.npz")


def load_unsaved(path: str | Path) -> tuple[int, dict[str, np.ndarray]]:
    """(first sample index, channels) of an unsaved-samples file (:func:`unsaved_path`)."""
    with np.load(path, allow_pickle=False) as z:
        first = int(z["first_sample"])
        return first, {k: z[k] for k in z.files if k not in _UNSAVED_META}


_UNSAVED_META = ("first_sample", "session_file", "trial_key")


#: Channels every trial logs (time, host time, perturbation, driver torque, angle, velocity,
#: motor command and torque, grip total and per hand), the simulated truth of a time-varying or
#: driving trial, and a driving trial's own (hardware.vehicle.DRIVING_CHANNELS).
BASE_CHANNELS, TRUTH_CHANNEL_COUNT, DRIVING_CHANNEL_COUNT = 11, 5, 6


def trial_channels(setup) -> int:
    """How many channels the trial of ``setup`` (protocols.session.TrialSetup) logs at most."""
    n = BASE_CHANNELS
    if setup.schedule is not None or setup.driving is not None:
        n += TRUTH_CHANNEL_COUNT
    if setup.driving is not None:
        n += DRIVING_CHANNEL_COUNT
    return n


def session_bytes(
    plan, channels: int | None = None, chunk_samples: int = 8192, dtype_bytes: int = 4
) -> int:
    """Bytes the session file of ``plan`` takes at most (uncompressed, whole chunks: HDF5
    allocates them); ``channels`` per trial, or by default what each trial logs
    (:func:`trial_channels`)."""
    total = 256 * 1024  # file metadata, protocol text, attributes
    for spec in plan.trials:
        setup = plan.setup(spec, 1)
        n_channels = trial_channels(setup) if channels is None else channels
        # time_s and host_time_s f8, the rest dtype
        per_sample = 16 + max(0, n_channels - 2) * dtype_bytes
        chunks = -(-setup.n_samples // chunk_samples)
        total += chunks * chunk_samples * per_sample + 64 * 1024
    return total


def check_free_space(directory: str | Path, needed_bytes: int, *, margin: float = 1.5) -> int:
    """Refuse (:class:`DataFileError`) when ``directory`` has less free space than
    ``needed_bytes`` × ``margin`` + :data:`RESERVE_BYTES`; returns the free bytes."""
    free = shutil.disk_usage(directory).free
    want = int(needed_bytes * margin) + RESERVE_BYTES
    if free < want:
        raise DataFileError(
            f"{directory}: not enough free space for the session: {_mb(free)} free, the session "
            f"needs {_mb(needed_bytes)} ({_mb(want)} with margin and reserve)"
        )
    return free


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


#: The compression of every dataset: HDF5's byte shuffle, then deflate (gzip) at this level.
#: Both are built into HDF5 (no plugin: MATLAB, R, HDFView and h5py read them as they are), and
#: lossless. Level 1: level 4 gained under 2 % on simulated sessions and cost more time.
GZIP_LEVEL = 1


def create_channel(group: h5py.Group, name: str, **kwargs) -> h5py.Dataset:
    """Every dataset of a session file is made here: chunked, compressed losslessly (shuffle +
    gzip, :data:`GZIP_LEVEL`), with HDF5's Fletcher-32 checksum on each stored chunk, so a
    damaged chunk is an error when read, never silently wrong numbers. SWMR works with all
    three (appending writes whole chunks)."""
    if "data" in kwargs and "chunks" not in kwargs:
        n = len(kwargs["data"])
        kwargs["chunks"] = (max(1, min(n, 65536)),)
        kwargs.setdefault("maxshape", (None,))
    return group.create_dataset(
        name,
        fletcher32=True,
        shuffle=True,
        compression="gzip",
        compression_opts=GZIP_LEVEL,
        **kwargs,
    )


#: Attribute of a dataset stored as integer counts: the value of one count, in the dataset's
#: ``units`` (CF convention: value = stored × scale_factor).
SCALE_ATTR = "scale_factor"


def read_channel(d: h5py.Dataset) -> np.ndarray:
    """A channel's values in its units, as float64: integer counts times their
    ``scale_factor`` (plus ``add_offset``, if any), other datasets as stored."""
    raw = d[()]
    if SCALE_ATTR not in d.attrs and "add_offset" not in d.attrs:
        return np.asarray(raw, dtype=float)
    scale = float(d.attrs.get(SCALE_ATTR, 1.0))
    offset = float(d.attrs.get("add_offset", 0.0))
    return np.asarray(raw, dtype=float) * scale + offset


def on_grid(values: np.ndarray, quantum: float) -> np.ndarray | None:
    """``values`` as int32 counts of ``quantum`` when that is exact (counts × quantum gives back
    every value bit for bit, as a drive's counts × its scaling do), else None."""
    v = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(v)):
        return None
    counts = np.rint(v / quantum)
    if np.any(np.abs(counts) > np.iinfo(np.int32).max) or not np.array_equal(counts * quantum, v):
        return None
    return counts.astype(np.int32)


def creating_path(path: Path) -> Path:
    """Where a new session file is built before it takes its name (never matches ``*.h5``)."""
    return path.with_name(path.name + ".creating")


class SessionWriter:
    """Writes the engine's events into one session file.

    Any failure while a trial is recorded (disk full, I/O error, the file removed or replaced)
    raises :class:`WriterFailure` from the engine's event, which ends the trial as aborted (the
    loop's finalizer leaves zero torque). The writer then keeps what it can: samples already
    written stay, the trial is marked aborted, the file is closed; later events are ignored
    (:attr:`failure` says why). Before the disk is full (:data:`RESERVE_BYTES` left) it stops
    on its own, so that the file stays readable with every sample it was given.

    Crash safety (``docs/data-format.md``, "After a crash"):
    - The writer holds the session file's writer lock (:mod:`protocols.writelock`) from its
      construction to :meth:`close`; a second writer is refused, naming this one.
    - A new file is built as ``NAME.h5.creating`` and renamed into place once its session
      attributes are written: a kill while creating leaves no half-made ``NAME.h5``.
    - The file is open only while a trial runs (in SWMR mode, flushed every
      ``flush_interval_s``) and for the moments it takes to write a trial's attributes; it is
      closed during breaks and between subjects, so a kill there leaves a cleanly closed file.
    - A kill while it is open leaves the superblock's "open for write" flag set; the next writer
      or reader, holding the lock, clears it (as ``h5clear -s``): every flushed sample is kept.

    ``quanta``: channel → the value of one count of the sensor that gives it (the encoder's
    rad per count, the torque sensor's N·m per count). Such a channel is stored as int32 counts
    with a ``scale_factor`` attribute when its first block is exactly counts × quantum; if a
    later block is not, the channel is rewritten as float64 (nothing is rounded).

    ``first_sample_attributes``: called with each trial's first block of samples; what it
    returns is written as attributes of the trial (the LSL clock at the trial's first sample,
    :meth:`protocols.lsl_publisher.LabClock.first_sample_attributes`). A failure there is
    logged and the trial goes on without them.

    ``lock``: True takes the lock now and holds it to the end of the session (or :meth:`close`);
    a held :class:`WriterLock` is used and left to the caller to release (``run``, the GUI, which
    hold it across several runs of the engine); False means the caller holds it for this file in
    another process (simulate's workers).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        dtype: str = "f4",
        flush_interval_s: float = 0.5,
        chunk_samples: int = 8192,
        extra_attributes: dict | None = None,
        clock=time.monotonic,
        lock: WriterLock | bool = True,
        quanta: dict[str, float] | None = None,
        first_sample_attributes: Callable[[ev.SamplesAcquired], dict] | None = None,
    ) -> None:
        self.path = Path(path)
        self.first_sample_attributes = first_sample_attributes
        # channel → the value of one count of the sensor behind it (e.g. the encoder's rad per
        # count): such a channel is stored as int32 counts with a scale_factor, when exact.
        self.quanta = {k: float(q) for k, q in (quanta or {}).items() if q and q > 0}
        self._counts: dict[str, float] = {}  # this trial's channels stored as counts
        self.dtype = dtype
        self.flush_interval_s = flush_interval_s
        self.chunk_samples = chunk_samples
        self.extra_attributes = extra_attributes or {}
        self.clock = clock
        self.f: h5py.File | None = None
        self.recovered_flags = 0  # the status flags a crashed writer had left, if any
        self._own_lock: WriterLock | None = None
        if lock is True:
            self._own_lock = WriterLock(self.path)
            try:
                self._own_lock.acquire()
            except LockedError as e:
                raise DataFileError(str(e)) from None
        self._key: str | None = None
        self._buf: dict[str, list[np.ndarray]] = {}
        self._marks: list[tuple] = []
        self._buffered = 0
        self._created = False
        self._chunk = chunk_samples
        self._written = 0
        self._last_flush = clock()
        self.reserve_bytes = RESERVE_BYTES
        self.failure: str | None = None
        self._identity: tuple[int, int] | None = None  # (st_dev, st_ino) of the open file

    # -- file handling --------------------------------------------------------------------------
    def _open(self) -> h5py.File:
        if self.f is None:
            if self._own_lock is not None and not self._own_lock.held:
                try:
                    self._own_lock.acquire()
                except LockedError as e:
                    raise DataFileError(str(e)) from None
            try:
                self.f = h5py.File(self.path, "a", libver=LIBVER, locking=False)
            except OSError as e:
                if "already open for write" not in str(e) or not self.path.exists():
                    raise DataFileError(f"{self.path}: cannot open for writing: {e}") from None
                # A writer died with the file open (we hold the lock: it is not alive).
                self.recovered_flags = _clear_crash_flags(self.path)
                self.f = h5py.File(self.path, "a", libver=LIBVER, locking=False)
                self.f.attrs["recovered_utc"] = now_utc()
            st = os.stat(self.path)
            self._identity = (st.st_dev, st.st_ino)
        return self.f

    def _file(self) -> h5py.File:
        """The file, open (while a trial is written)."""
        if self.f is None:
            raise DataFileError(f"{self.path}: the session writer has no open file")
        return self.f

    def _reopen_plain(self) -> h5py.File:
        # Attributes and new groups cannot be written in SWMR mode: close and reopen.
        if self.f is not None and self.f.swmr_mode:
            self.f.close()
            self.f = None
        return self._open()

    def _close_file(self) -> None:
        if self.f is not None:
            self.f.close()
            self.f = None

    def close(self) -> None:
        """Close the file and release the writer lock (when this writer took it)."""
        if self._salvage is not None:  # failed, and the trial's end never came
            self._finish_failure()
        self._close_file()
        if self._own_lock is not None:
            self._own_lock.release()

    # -- events -----------------------------------------------------------------------------------
    def __call__(self, event: object) -> None:
        if self.failure is not None:
            # Failed (and reported). The failed trial's samples that still come (the loop's
            # last blocks, taken before it stopped) are kept; its end closes the file.
            self._after_failure(event)
            return
        in_trial = self._key is not None
        try:
            self._dispatch(event)
        except WriterFailure as e:
            raise self._fail(str(e), space_left=True, event=event) from None
        except DataFileError:
            raise
        except Exception as e:  # h5py: OSError, RuntimeError, …
            if not in_trial and not isinstance(event, ev.SamplesAcquired):
                raise
            raise self._fail(
                f"{self.path}: {type(e).__name__}: {e}", space_left=False, event=event
            ) from e

    def _fail(self, what: str, *, space_left: bool, event: object = None) -> WriterFailure:
        """Return the fault to raise at once (the engine stops the loop: zero torque first);
        what can be kept is kept when the trial has ended (:meth:`_finish_failure`).

        Samples given to the writer are never dropped: the block that arrived with the failure
        and the loop's last blocks, taken before it stopped, join the buffer; at the trial's end
        the buffer goes into the file when the failure left room for it (the disk-full reserve),
        else to :func:`unsaved_path` next to the file or, if that folder cannot take them, to a
        memory-backed folder (:attr:`unsaved_file`; the fault's message names it)."""
        self.failure = what
        key = self._key
        if key is None:
            self._close_quietly()
            return WriterFailure(f"session writer failed: {what}")
        self._salvage = space_left
        self._keep_failed(event)  # the block it failed on, if the buffer does not have it
        where = ""
        if not space_left and self._buffered:
            self.unsaved_file = self._unsaved_target(key)
            where = f"; the samples it could not write go to {self.unsaved_file}"
        return WriterFailure(f"session writer failed: {what}{where}")

    #: After a failure, until the trial's end: True/False (whether the buffer may still go into
    #: the file); None: nothing pending.
    _salvage: bool | None = None
    #: Samples of the failed trial that are not in the session file but in :attr:`unsaved_file`.
    unsaved_samples = 0
    #: Where they are (None: nothing unsaved, or no folder could take them; then logged).
    unsaved_file: Path | None = None
    _unsaved: dict | None = None

    def _keep_failed(self, event: object) -> None:
        """A failed trial's samples that still come (in order) join the buffer."""
        if not isinstance(event, ev.SamplesAcquired) or event.key != self._key:
            return
        expected = self._written + self._buffered
        if event.start < expected:
            return  # the buffer has it already
        if event.start > expected:
            log.error(
                "%s: trial %s: samples from %d, expected %d; kept as they come",
                self.path, event.key, event.start, expected,
            )  # fmt: skip
        if not self._buf:
            self._buf = {k: [] for k in event.channels}
        for k, v in event.channels.items():
            self._buf.setdefault(k, []).append(np.array(v))
        self._buffered += event.n

    def _after_failure(self, event: object) -> None:
        if self._salvage is None:
            return
        if isinstance(event, ev.SamplesAcquired):
            self._keep_failed(event)
        elif isinstance(event, ev.TrialEnded | ev.SessionEnded):
            self._finish_failure()

    def _finish_failure(self) -> None:
        """Keep what can be kept (the loop has stopped): the buffer into the file if there is
        room, the trial marked aborted, the file closed; what the file did not take into the
        unsaved-samples file."""
        space_left, self._salvage = self._salvage, None
        key = self._key
        try:
            if self.f is not None and self._still_ours():
                if space_left:
                    try:
                        self._write_out()  # the reserve is for this
                    except Exception as e:
                        log.error("%s: buffered samples not written: %r", self.path, e)
                g = self._reopen_plain()["trials"][key]
                set_attrs(
                    g,
                    {
                        "status": STATUS_ABORTED,
                        "abort_reason": f"session writer failed: {self.failure}",
                        "n_samples": self._written,
                        "ended_utc": now_utc(),
                    },
                )
                self._file().flush()
        except Exception as e:  # the file takes no more; what was flushed stays
            log.error("%s: could not record the writer's failure: %r", self.path, e)
        finally:
            self._close_quietly()
        if self._buffered:
            self._unsaved = {
                "key": key,
                "first": self._written,
                "parts": {k: list(v) for k, v in self._buf.items()},
                "n": self._buffered,
            }
            if self.unsaved_file is None:
                self.unsaved_file = self._unsaved_target(key or "trial")
                log.error(
                    "%s: %d samples the file did not take go to %s",
                    self.path, self._buffered, self.unsaved_file,
                )  # fmt: skip
            self._dump_unsaved()
        self._buf, self._buffered, self._key = {}, 0, None

    def _close_quietly(self) -> None:
        try:
            self._close_file()
        except Exception as e:
            log.error("%s: could not close after the writer's failure: %r", self.path, e)
            self.f = None
        if self._own_lock is not None:
            self._own_lock.release()

    def _unsaved_target(self, key: str) -> Path:
        """Next to the session file if its folder has room for the samples (generously: the
        trial's samples so far, again, a minute more, and the reserve), else a memory-backed
        folder."""
        first = unsaved_path(self.path, key)
        n = self._written + self._buffered + 60_000
        need = RESERVE_BYTES + 16 * n * max(1, len(self._buf))
        for d in [first.parent, *_fallback_dirs()]:
            try:
                if shutil.disk_usage(d).free > need:
                    return first if d == first.parent else d / f"steerlab-{first.name}"
            except OSError:
                continue
        return first

    def _dump_unsaved(self) -> None:
        """Write the unsaved samples (all of them, again: the file is replaced as it grows)."""
        u = self._unsaved
        if u is None or not u["n"] or u.get("dumped") == u["n"]:
            return
        arrays = {k: np.concatenate(v) for k, v in u["parts"].items() if v}
        meta = {
            "first_sample": np.int64(u["first"]),
            "session_file": np.str_(str(self.path)),
            "trial_key": np.str_(u["key"]),
        }
        first = unsaved_path(self.path, u["key"])
        where = [self.unsaved_file or first]
        where += [d / f"steerlab-{first.name}" for d in _fallback_dirs()]
        for target in where:
            tmp = target.with_name(target.name + ".part")
            try:
                with open(tmp, "wb") as fh:
                    np.savez(fh, **arrays, **meta)  # type: ignore[arg-type]
                    fh.flush()
                    os.fsync(fh.fileno())
                os.replace(tmp, target)
            except OSError as e:
                log.error("%s: unsaved samples not written to %s: %r", self.path, target, e)
                try:
                    tmp.unlink(missing_ok=True)
                except OSError:
                    pass
                continue
            if self.unsaved_file is not None and target != self.unsaved_file:
                log.error(
                    "%s: unsaved samples moved from %s to %s", self.path, self.unsaved_file, target
                )
            self.unsaved_file, self.unsaved_samples = target, u["n"]
            u["dumped"] = u["n"]
            return
        log.error("%s: %d unsaved samples could not be written anywhere", self.path, u["n"])

    def _still_ours(self) -> bool:
        try:
            st = os.stat(self.path)
        except OSError:
            return False
        return (st.st_dev, st.st_ino) == self._identity

    def _dispatch(self, event: object) -> None:
        match event:
            case ev.SessionStarted():
                self._session_started(event)
            case ev.TrialStarted():
                self._trial_started(event)
            case ev.SamplesAcquired():
                self._samples(event)
            case ev.TrialMark():
                self._marks.append(
                    (event.sample, event.kind.encode()[:16], event.detail.encode()[:240])
                )
            case ev.TrialEnded():
                self._trial_ended(event)
            case ev.TrialSuperseded():
                self._superseded(event)
            case ev.SessionEnded():
                # The lock this writer took itself ends with the session (a later run of the
                # engine takes it again); a lock its caller passed stays the caller's.
                self.close()

    def _session_attributes(self, e: ev.SessionStarted) -> dict:
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "software_version": software_version(),
            "created_utc": now_utc(),
            **e.attributes,
            "protocol_toml": e.protocol_text,
            "perturbation_design": e.design_json,
            "units": UNITS,
            "sign_conventions": SIGN_CONVENTIONS,
            **self.extra_attributes,
        }

    def _session_started(self, e: ev.SessionStarted) -> None:
        self._close_file()
        if not self.path.exists():
            # Built under another name and renamed: the name appears complete or not at all.
            tmp = creating_path(self.path)
            tmp.unlink(missing_ok=True)
            with h5py.File(tmp, "w", libver=LIBVER) as f:
                set_attrs(f, self._session_attributes(e))
                f.create_group("trials")
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, self.path)
            return
        f = self._open()
        if f.attrs.get("format") is None:
            set_attrs(f, self._session_attributes(e))
        else:
            if str(f.attrs.get("subject")) != e.subject:
                raise DataFileError(
                    f"{self.path}: holds subject {f.attrs.get('subject')!r}, not {e.subject!r}"
                )
            if str(f.attrs.get("protocol_toml", "")) != e.protocol_text:
                raise DataFileError(
                    f"{self.path}: was recorded with a different protocol; resume with the same "
                    "protocol file, or start a new session file"
                )
            f.attrs["resumed_utc"] = now_utc()
        f.require_group("trials")
        self._close_file()

    def _trial_started(self, e: ev.TrialStarted) -> None:
        f = self._reopen_plain()
        trials = f.require_group("trials")
        if e.key in trials:
            raise DataFileError(
                f"{self.path}: trial group {e.key!r} exists already; not overwriting"
            )
        g = trials.create_group(e.key)
        design = f.attrs.get("perturbation_design")
        set_attrs(
            g,
            {
                **e.attributes,
                "status": STATUS_INCOMPLETE,
                "n_planned": e.n_planned,
                "started_utc": now_utc(),
                "perturbation_design": design,
                "units": UNITS,
                "sign_conventions": SIGN_CONVENTIONS,
                "software_version": software_version(),
            },
        )
        f.flush()
        self._key = e.key
        self._buf, self._marks, self._buffered, self._written = {}, [], 0, 0
        self._created = False  # this trial's datasets (made at its first write)
        self._last_flush = self.clock()

    def _chunk_for_pace(self) -> int:
        """Samples per chunk for this trial, from how fast its samples came.

        Compressed chunks are written once when whole (a simulation at full speed fills
        ``chunk_samples`` long before ``flush_interval_s``). When a trial is paced in real
        time, every flush writes the last chunk part-full; each rewrite of a compressed chunk
        leaves its earlier version's bytes unused in the file (HDF5 does not reuse them in SWMR
        mode), so the chunk is then about half of what arrives between two flushes."""
        n = self._buffered
        if n >= self.chunk_samples:
            return self.chunk_samples
        return int(min(self.chunk_samples, max(64, 2 ** round(np.log2(max(n, 2) / 2)))))

    def _create_datasets(self) -> None:
        g = self._file()["trials"][self._key]
        self._counts = {}
        chunk = self._chunk = self._chunk_for_pace()
        self._created = True
        for name, parts in self._buf.items():
            dt = "f8" if name in ("time_s", "host_time_s") else self.dtype
            q = self.quanta.get(name)
            if q is not None and on_grid(np.concatenate(parts), q) is not None:
                dt = "i4"
                self._counts[name] = q
            d = create_channel(g, name, shape=(0,), maxshape=(None,), dtype=dt, chunks=(chunk,))
            d.attrs["units"] = UNITS.get(name, "")
            if name in self._counts:
                d.attrs[SCALE_ATTR] = q
        create_channel(g, "marks", shape=(0,), maxshape=(None,), dtype=MARK_DTYPE, chunks=(64,))
        self._file().flush()
        self._file().swmr_mode = True

    def _samples(self, e: ev.SamplesAcquired) -> None:
        # Both checks every block (a stat and a statvfs, microseconds): the trial ends within
        # one block of the file going away or the disk filling up.
        if not self._still_ours():
            raise WriterFailure(f"{self.path}: the session file was removed or replaced")
        if e.key != self._key:
            raise DataFileError(f"{self.path}: samples for {e.key!r} while writing {self._key!r}")
        if not self._buf:
            # The datasets are made at the first write (_write_out): their chunk size depends
            # on the pace at which the samples come, counted from the first.
            self._buf = {k: [] for k in e.channels}
            self._last_flush = self.clock()
            self._stamp_first_sample(e)
        if e.channels.keys() != self._buf.keys():
            raise DataFileError(f"{self.path}: trial {e.key}: channels changed within the trial")
        for k, v in e.channels.items():
            self._buf[k].append(np.asarray(v))
        self._buffered += e.n
        self._check_space()  # on failure, this block too goes into the reserve
        now = self.clock()
        if now - self._last_flush >= self.flush_interval_s:
            self._write_out()
            self._file().flush()
            self._last_flush = now
        elif self._buffered >= self.chunk_samples:
            self._append(whole_chunks=True)

    def _stamp_first_sample(self, e: ev.SamplesAcquired) -> None:
        """The trial's attributes known at its first sample (the file is not yet in SWMR mode:
        its datasets are made at the first write)."""
        if self.first_sample_attributes is None:
            return
        try:
            attrs = self.first_sample_attributes(e)
        except Exception as x:  # a clock's failure must not cost the trial
            log.warning("%s: trial %s: first-sample attributes: %r", self.path, e.key, x)
            return
        if attrs:
            set_attrs(self._file()["trials"][self._key], attrs)

    def _write_out(self) -> None:
        """Append everything buffered."""
        self._append(whole_chunks=False)

    def _append(self, whole_chunks: bool) -> None:
        """Append what is buffered; with ``whole_chunks`` only up to the last chunk boundary
        (the rest stays buffered): a compressed chunk written part-full and rewritten later
        leaves its first version's bytes unused in the file."""
        if self._key is None or self.f is None:
            return
        g = self._file()["trials"][self._key]
        if self._buffered and not self._created:
            self._create_datasets()
        n0, n1 = self._written, self._written + self._buffered
        if whole_chunks:
            n1 = n1 // self._chunk * self._chunk
        if n1 > n0:
            rests: dict[str, np.ndarray] = {}
            for k, parts in self._buf.items():
                buffered = np.concatenate(parts)
                block, rests[k] = buffered[: n1 - n0], buffered[n1 - n0 :]
                if k in self._counts:
                    counts = on_grid(block, self._counts[k])
                    if counts is None:
                        g = self._counts_to_float(k, block, n0)
                        continue
                    block = counts
                d = g[k]
                d.resize((n1,))
                d[n0:n1] = block
            # Trimmed only once every channel is written: after a failed write the buffer
            # still holds the whole block (it goes to the unsaved-samples file).
            for k, parts in self._buf.items():
                parts.clear()
                if len(rests[k]):
                    parts.append(rests[k])
            self._written, self._buffered = n1, self._buffered - (n1 - n0)
        if self._marks and "marks" in g:
            d = g["marks"]
            m0 = d.shape[0]
            d.resize((m0 + len(self._marks),))
            d[m0:] = np.array(self._marks, dtype=MARK_DTYPE)
            self._marks = []

    def _counts_to_float(self, name: str, block: np.ndarray, n0: int) -> h5py.Group:
        """A block of a counts channel is not on its grid: rewrite the channel as float64.

        Crash-safe order: the counts are moved aside (one link rename), the float64 dataset is
        written in full and flushed, then the counts are deleted; a reader that finds only
        ``NAME~counts`` reads it (:func:`_record_from_group`). Rare (a sensor that is not what
        ``quanta`` said): it takes the file out of SWMR mode for a moment."""
        q = self._counts.pop(name)
        f = self._reopen_plain()
        g = f["trials"][self._key]
        aside = name + COUNTS_ASIDE
        g.move(name, aside)
        old = g[aside]
        values = np.concatenate([old[:n0].astype(float) * q, np.asarray(block, dtype=float)])
        d = create_channel(
            g, name, shape=(len(values),), maxshape=(None,), dtype="f8", chunks=old.chunks
        )
        d[:] = values
        d.attrs["units"] = old.attrs.get("units", UNITS.get(name, ""))
        f.flush()
        del g[aside]
        # Closed and reopened before SWMR resumes: HDF5's metadata cache in SWMR mode does not
        # take a dataset deleted and another created in the same open (it crashes later).
        self._close_file()
        f = self._open()
        g = f["trials"][self._key]
        f.swmr_mode = True
        log.warning("%s: %s: values off the %g grid; stored as float64", self.path, name, q)
        return g

    def _check_space(self) -> None:
        free = shutil.disk_usage(self.path.parent).free
        if free < self.reserve_bytes:
            raise WriterFailure(
                f"{self.path}: disk full: {_mb(free)} free, below the writer's reserve of "
                f"{_mb(self.reserve_bytes)}"
            )

    def _trial_ended(self, e: ev.TrialEnded) -> None:
        if e.key != self._key:
            raise DataFileError(f"{self.path}: end of {e.key!r} while writing {self._key!r}")
        if e.reason:
            self._marks.append((e.n_samples, b"abort", e.reason.encode()[:240]))
        if not self._buf and self._marks:
            # A trial aborted before its first sample still records why.
            f = self._reopen_plain()
            create_channel(
                f["trials"][self._key],
                "marks",
                data=np.array(self._marks, dtype=MARK_DTYPE),
                maxshape=(None,),
                chunks=(64,),
            )
            self._marks = []
        self._open()
        self._write_out()
        self._file().flush()
        f = self._reopen_plain()
        g = f["trials"][self._key]
        set_attrs(
            g,
            {
                "status": e.status,
                "abort_reason": e.reason or "",
                "n_samples": e.n_samples,
                "ended_utc": now_utc(),
                "loop_stats": e.stats,
            },
        )
        self._close_file()  # closed during the break: a kill there leaves a clean file
        self._key = None
        self._buf = {}

    def _superseded(self, e: ev.TrialSuperseded) -> None:
        f = self._reopen_plain()
        g = f["trials"].get(e.key)
        if g is None:
            self._close_file()
            raise DataFileError(f"{self.path}: no trial {e.key!r} to mark superseded")
        g.attrs["status"] = STATUS_SUPERSEDED
        g.attrs["superseded_reason"] = e.reason
        g.attrs["superseded_utc"] = now_utc()
        if self._key is None:
            self._close_file()
        else:
            f.flush()


def _clear_crash_flags(path: Path) -> int:
    """Clear the "open for write" flags a killed writer left (the caller holds the lock)."""
    try:
        return clear_status_flags(path)
    except SuperblockError as e:
        raise DataFileError(f"{path}: left open by a writer that died, and {e}") from None
    except OSError as e:
        raise DataFileError(
            f"{path}: left open by a writer that died; cannot clear its 'open for write' flag "
            f"({e.strerror or e}); run `h5clear -s {path}` as a user who may write it"
        ) from None


# -- reading ---------------------------------------------------------------------------------------
OPEN_RETRY_S = 3.0  # how long a reader waits for a live writer between its set-up steps


def open_for_reading(path: Path) -> h5py.File:
    """Open a session file read-only, whatever state a writer left it in.

    A file with a live writer (its lock is held) is opened in SWMR mode; any other file in
    plain read mode, whose end-of-file check makes a truncated file an error at once (SWMR
    reading skips it and retries damaged metadata for minutes). A file whose writer died with
    it open has its "open for write" flag cleared first (as ``h5clear -s``), under the lock.

    HDF5's own file locking is off for readers and for the writer (``locking=False``): a
    reader's shared lock would otherwise make the writer's next open fail mid-session. One
    writer is ensured by the writer lock; a reader is kept out of the writer's plain-mode
    moments by the superblock's "open for write" flag, which HDF5 checks on every open.
    """
    if not path.exists():
        raise DataFileError(f"{path}: no such file")
    deadline = time.monotonic() + OPEN_RETRY_S
    while True:
        live = live_writer(path)
        try:
            if live is not None:
                return h5py.File(path, "r", libver=LIBVER, swmr=True, locking=False)
            return h5py.File(path, "r", libver=LIBVER, locking=False)
        except OSError as e:
            msg = str(e)
        crash_flag = "already open for write" in msg or "not already open for SWMR" in msg
        busy = crash_flag or "lock" in msg
        if live is not None and busy and time.monotonic() < deadline:
            time.sleep(0.05)  # the writer is between two set-up steps (plain-mode open)
            continue
        if live is None and crash_flag:
            try:
                with WriterLock(path, wait_s=OPEN_RETRY_S):
                    _clear_crash_flags(path)
            except LockedError as e:
                if live_writer(path) is None:  # no writer: we may not create the lock file
                    raise DataFileError(
                        f"{path}: left open by a writer that died; {e}; run `h5clear -s "
                        f"{path}` as a user who may write there"
                    ) from None
                # else a writer started meanwhile: open it as a live file
            if time.monotonic() < deadline:
                continue
        if "truncat" in msg or "signature" in msg:
            hint = "truncated or damaged"
        elif busy:
            hint = "held open by " + (f"a live writer ({live})" if live else "another process")
        else:
            hint = "damaged"
        raise DataFileError(f"{path}: not a readable HDF5 file ({hint}: {msg})") from None


@contextmanager
def _damage_is_an_error(path: Path):
    """h5py reports a damaged file late (reading an attribute, a chunk): one clear message."""
    try:
        yield
    except DataFileError:
        raise
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as e:
        raise DataFileError(
            f"{path}: damaged or truncated session file ({type(e).__name__}: {e})"
        ) from None


def _attr(obj, key, default=None):
    v = obj.attrs.get(key, default)
    if isinstance(v, bytes):
        v = v.decode()
    if isinstance(v, np.generic):
        v = v.item()
    return v


def _json_attr(obj, key):
    v = _attr(obj, key)
    if v is None or v == "":
        return None
    try:
        return json.loads(v)
    except (TypeError, json.JSONDecodeError):
        return v


_READ_ERRORS = (OSError, RuntimeError, KeyError, ValueError, TypeError)


class SessionFile:
    """A session file's metadata and trials, read-only.

    The file as a whole (superblock, root attributes, the /trials index) must be readable, or
    :class:`DataFileError` names the file. A trial whose attributes or data fail their checksums
    is not fatal: it is listed in :attr:`damaged` (key → what is wrong) and :meth:`records`
    returns it with status ``damaged``, so the analysis lists it as skipped.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.damaged: dict[str, str] = {}
        with _damage_is_an_error(self.path), open_for_reading(self.path) as f:
            if _attr(f, "format") != FORMAT:
                raise DataFileError(
                    f"{self.path}: not a Steerlab session file (no format={FORMAT!r})"
                )
            self.attrs = {k: _attr(f, k) for k in f.attrs}
            if "trials" not in f:
                raise DataFileError(f"{self.path}: session file has no /trials group")
            self.trial_keys = sorted(f["trials"].keys())
            self.trial_attrs = {}
            for k in self.trial_keys:
                try:
                    g = f["trials"][k]
                    if not isinstance(g, h5py.Group):
                        raise TypeError("not a group")
                    self.trial_attrs[k] = {a: _attr(g, a) for a in g.attrs}
                except _READ_ERRORS as e:
                    self.damaged[k] = f"trial group unreadable ({type(e).__name__}: {e})"
                    self.trial_attrs[k] = {}

    @property
    def subject(self) -> str:
        return str(self.attrs.get("subject"))

    def attempts(self) -> dict[int, list[tuple[int, str]]]:
        """trial index → [(attempt, status)], for resuming a session."""
        out: dict[int, list[tuple[int, str]]] = {}
        for k, a in self.trial_attrs.items():
            if k in self.damaged and "trial_index" not in a:
                raise DataFileError(f"{self.path}:/trials/{k}: {self.damaged[k]}; cannot resume")
            out.setdefault(int(a["trial_index"]), []).append(
                (int(a.get("attempt", 1)), str(a["status"]))
            )
        return out

    def records(
        self, *, statuses: set[str] | None = None, extra_channels: Iterable[str] | None = None
    ) -> list[TrialRecord]:
        """All trials as :class:`TrialRecord`, optionally only those with the given status.

        ``extra_channels``: which channels beyond the five interchange ones to read into
        ``record.extra`` (None: all of them; ``()``: none, the fastest for analysis).
        A damaged trial comes back with status ``damaged`` (whatever ``statuses`` asks), empty
        channels and ``abort_reason`` saying what is damaged.
        """
        out = []
        with _damage_is_an_error(self.path), open_for_reading(self.path) as f:
            for key in self.trial_keys:
                attrs = self.trial_attrs[key]
                if key not in self.damaged:
                    if statuses is not None and str(attrs.get("status")) not in statuses:
                        continue
                    try:
                        g = f["trials"][key]
                        out.append(
                            _record_from_group(self.path, key, g, dict(attrs), extra_channels)
                        )
                        continue
                    except _READ_ERRORS as e:
                        self.damaged[key] = _what_is_damaged(e)
                out.append(self._damaged_record(key))
        out.sort(key=lambda r: (r.trial_index or 0, int(r.attrs.get("attempt", 1) or 1)))
        return out

    def _damaged_record(self, key: str) -> TrialRecord:
        a = self.trial_attrs.get(key, {})
        empty = np.zeros(0)

        def get(name, kind, default):
            try:
                return kind(a[name])
            except (KeyError, TypeError, ValueError):
                return default

        return TrialRecord(
            subject=self.subject,
            condition=get("condition", str, key),
            repetition=get("repetition", int, 0),
            familiarization=get("familiarization", bool, False),
            fs_hz=get("fs_hz", float, float("nan")),
            time_s=empty,
            perturbation_torque_Nm=empty,
            driver_torque_Nm=empty,
            wheel_angle_rad=empty,
            grip_force_N=empty,
            trial_index=get("trial_index", int, None),
            status=STATUS_DAMAGED,
            abort_reason=self.damaged[key],
            attrs={**a, "status_recorded": a.get("status")},
            source=f"{self.path}:/trials/{key}",
        )


def _what_is_damaged(e: BaseException) -> str:
    if isinstance(e, DataFileError):
        return str(e)
    return f"damaged ({type(e).__name__}: {e})"


def _read_dataset(where: str, name: str, d: h5py.Dataset, *, values: bool = False) -> np.ndarray:
    """The dataset as stored, or with ``values`` its values in its units (:func:`read_channel`)."""
    try:
        return read_channel(d) if values else d[()]
    except OSError as e:
        what = (
            "a chunk fails its Fletcher-32 checksum"
            if d.fletcher32 and "filter" in str(e)
            else f"unreadable ({e})"
        )
        raise DataFileError(f"{where}: dataset {name!r} is damaged: {what}") from None


def _record_from_group(
    path: Path,
    key: str,
    g: h5py.Group,
    attrs: dict | None = None,
    extra_channels: Iterable[str] | None = None,
) -> TrialRecord:
    where = f"{path}:/trials/{key}"
    if attrs is None:
        attrs = {a: _attr(g, a) for a in g.attrs}
    missing = [
        c for c in ("subject", "condition", "repetition", "fs_hz", "status") if c not in attrs
    ]
    if missing:
        raise DataFileError(f"{where}: missing attribute(s) {missing}")
    for c in ("subject", "condition"):
        try:
            check_name(str(attrs[c]), f"{where}: attribute {c!r}")
        except UnsafeNameError as e:
            raise DataFileError(str(e)) from None
    data: dict[str, np.ndarray] = {}
    wanted = None if extra_channels is None else set(CORE_CHANNELS) | set(extra_channels)
    for stored, d in g.items():
        name = stored
        if stored.endswith(COUNTS_ASIDE):  # a writer died rewriting it (_counts_to_float)
            name = stored[: -len(COUNTS_ASIDE)]
            if name in g:
                continue
        if isinstance(d, h5py.Dataset) and name != "marks" and (wanted is None or name in wanted):
            data[name] = _read_dataset(where, name, d, values=True)
    core = CORE_CHANNELS
    n = min((len(data[c]) for c in core if c in data), default=0)
    for c in core:
        if c not in data:
            if attrs["status"] == STATUS_COMPLETE:
                raise DataFileError(f"{where}: missing dataset {c!r}")
            data[c] = np.zeros(0)
        data[c] = data[c][:n]  # a killed writer may have flushed channels unevenly
    design = None
    dj = _attr(g, "perturbation_design")
    if dj:
        try:
            design = PerturbationDesign.from_json(dj)
        except (KeyError, TypeError, ValueError) as e:
            raise DataFileError(
                f"{where}: unreadable perturbation_design attribute ({e})"
            ) from None
    marks = []
    if "marks" in g:
        for m in _read_dataset(where, "marks", g["marks"]):
            marks.append(
                {
                    "sample": int(m["sample"]),
                    "kind": m["kind"].decode(),
                    "detail": m["detail"].decode(),
                }
            )
    attrs["marks"] = marks
    fam = bool(attrs.get("familiarization", False))
    return TrialRecord(
        subject=str(attrs["subject"]),
        condition=str(attrs["condition"]),
        repetition=int(attrs["repetition"]),
        familiarization=fam,
        fs_hz=float(attrs["fs_hz"]),
        time_s=data.pop("time_s"),
        perturbation_torque_Nm=data.pop("perturbation_torque_Nm"),
        driver_torque_Nm=data.pop("driver_torque_Nm"),
        wheel_angle_rad=data.pop("wheel_angle_rad"),
        grip_force_N=data.pop("grip_force_N"),
        trial_index=int(attrs["trial_index"]) if attrs.get("trial_index") is not None else None,
        status=str(attrs["status"]),
        abort_reason=str(attrs.get("abort_reason") or "") or None,
        measured_start=int(attrs["measured_start"])
        if attrs.get("measured_start") is not None
        else None,
        measured_stop=int(attrs["measured_stop"])
        if attrs.get("measured_stop") is not None
        else None,
        design=design,
        boundary_deg=float(attrs["boundary_deg"])
        if attrs.get("boundary_deg") is not None
        else None,
        extra={k: v[:n] for k, v in data.items()},
        attrs=attrs,
        source=where,
    )


def session_files(directory: str | Path) -> list[Path]:
    d = Path(directory)
    if not d.is_dir():
        raise DataFileError(f"{d}: not a directory")
    return sorted(p for p in d.glob("*.h5"))


def load_study(directory: str | Path, statuses: set[str] | None = None) -> list[TrialRecord]:
    """Every trial of every session file in a directory."""
    files = session_files(directory)
    if not files:
        raise DataFileError(f"{directory}: no session files (*.h5)")
    out = []
    for p in files:
        out.extend(SessionFile(p).records(statuses=statuses))
    return out
