"""The trial interchange format: per trial ``NAME.csv`` + ``NAME.json``.

CSV header starts with (in any order, extra columns allowed)
``time_s,perturbation_torque_Nm,driver_torque_Nm,wheel_angle_rad,grip_force_N``.
JSON holds at least ``subject`` and ``condition`` (strings), ``repetition``, ``fs_hz``, and
where known ``familiarization`` (bool) and ``trial_index`` (order in the session, a whole number
≥ 0), and optionally how the recording was made (``sample_timing``, ``torque_timing``,
``wheel_rendering``: docs/data-format.md). A condition must be one of a shipped protocol's, or
of the session the trial was exported from, or declared (``condition_declared``: true).
Sign convention: ``driver_torque_Nm`` is the torque the wheel exerts on the hands, so that
S(Tp,θ)/S(Tp,Td) is positive at low frequency.

Import accepts any sample rate ≥ 100 Hz and data that do not start on a period boundary; every
error names the file, and the row and column where there is one. Nothing is written unless
every input file is good.
"""

from __future__ import annotations

import csv
import difflib
import functools
import json
import math
import os
import shutil
import tempfile
from collections import Counter
from importlib import resources
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from steerlab.protocols.datafile import (
    FORMAT,
    FORMAT_VERSION,
    LIBVER,
    MARK_DTYPE,
    SIGN_CONVENTIONS,
    UNITS,
    SessionFile,
    create_channel,
    now_utc,
    open_for_reading,
    session_files,
    set_attrs,
    software_version,
)
from steerlab.protocols.names import UnsafeNameError, check_name, inside
from steerlab.protocols.perturbation import PerturbationDesign
from steerlab.protocols.protocol import load_protocol
from steerlab.protocols.records import (
    CORE_CHANNELS,
    STATUS_ABORTED,
    STATUS_COMPLETE,
    STATUS_DAMAGED,
    STATUS_INCOMPLETE,
    STATUS_SUPERSEDED,
    TrialRecord,
)
from steerlab.protocols.writelock import LockedError, WriterLock

REQUIRED_META = ("subject", "condition", "repetition", "fs_hz")
MIN_FS_HZ = 100.0


class InterchangeError(ValueError):
    """Bad interchange input; the message names the file, row and column."""


# -- export ----------------------------------------------------------------------------------------
def _fmt_column(values: np.ndarray, exact64: bool) -> list[str]:
    # %.17g round-trips a float64, %.9g a float32: export → import gives the same numbers.
    f = "%.17g" if exact64 else "%.9g"
    return [f % v for v in values]


# What a simulation knows and measured data do not: left out by a blind export.
SIMULATION_TRUTH = ("world", "simulated_subject", "simulation_seed", "simulated", "mechanisms")


def export_study(
    session_dir: str | Path, out_dir: str | Path, *, overwrite: bool = False, blind: bool = False
) -> list[Path]:
    """Write every trial of every session file as CSV + JSON. Returns the CSV paths.

    The trials are written into a new folder beside ``out_dir`` that takes its name only when
    every trial is written: nothing half-written, and nothing written through a link already
    in ``out_dir``. An existing non-empty ``out_dir`` is refused unless ``overwrite``, which
    replaces it as a whole. Damaged trials are left out and listed in :attr:`last_skipped`.

    Every session and trial attribute is exported, so import gives them all back. ``blind``
    leaves out what only a simulation knows (:data:`SIMULATION_TRUTH`, ``true_*`` channels),
    for testing an analysis on simulated data as if measured (``steerlab diagnose``).
    """
    files = session_files(session_dir)
    if not files:
        raise InterchangeError(f"{session_dir}: no session files (*.h5) to export")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InterchangeError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise InterchangeError(
            f"{out}: exists and is not empty; pass --overwrite to replace it, or choose another "
            "--out"
        )
    target = Path(os.path.realpath(out))  # --out itself may be a link to the real folder
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.exporting-", dir=target.parent))
    written: list[Path] = []
    skipped: list[str] = []
    try:
        for path in files:
            sf = SessionFile(path)
            recs = sf.records()
            with open_for_reading(path) as f:
                for rec in recs:
                    if rec.status == STATUS_DAMAGED:
                        skipped.append(f"{rec.source}: {rec.abort_reason}")
                        continue
                    g = f["trials"][rec.source.rsplit("/", 1)[-1]]
                    written.append(_export_trial(rec, g, tmp, sf, blind))
        if target.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.replaced-", dir=target.parent))
            os.rename(target, old / target.name)
            os.rename(tmp, target)
            shutil.rmtree(old)
        else:
            os.rename(tmp, target)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    export_study.last_skipped = skipped  # type: ignore[attr-defined]
    return [target / p.name for p in written]


export_study.last_skipped = []  # type: ignore[attr-defined]


def trial_name(rec: TrialRecord) -> str:
    idx = f"T{rec.trial_index:02d}_" if rec.trial_index is not None else ""
    rep = "fam" if rec.familiarization else f"rep{rec.repetition}"
    att = int(rec.attrs.get("attempt", 1))
    suffix = f"_a{att}" if att != 1 else ""
    return f"{rec.subject}_{idx}{rec.condition}_{rep}{suffix}"


# -- attributes as JSON, exactly: every value HDF5 held comes back with its type -----------------
def encode_attr(v):
    if isinstance(v, np.ndarray):
        return {"__array__": [encode_attr(x) for x in v.tolist()], "dtype": v.dtype.str}
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, bytes):
        return {"__bytes__": v.hex()}
    if isinstance(v, float) and not math.isfinite(v):
        return {"__float__": repr(v)}
    if v is None or isinstance(v, str | bool | int | float):
        return v
    return str(v)


def decode_attr(v, where: str):
    if isinstance(v, dict):
        try:
            if set(v) == {"__float__"} and v["__float__"] in ("nan", "inf", "-inf"):
                return float(v["__float__"])
            if set(v) == {"__bytes__"}:
                return bytes.fromhex(v["__bytes__"])
            if set(v) == {"__array__", "dtype"}:
                items = [decode_attr(x, where) for x in v["__array__"]]
                return np.asarray(items, dtype=np.dtype(v["dtype"]))
        except (TypeError, ValueError, OverflowError) as e:
            raise InterchangeError(f"{where}: unreadable value {v!r} ({e})") from None
        raise InterchangeError(f"{where}: unreadable value {v!r}")
    if v is None or isinstance(v, str | bool | int | float):
        if isinstance(v, str) and "\x00" in v:
            raise InterchangeError(f"{where}: a NUL character in {v!r}")
        if isinstance(v, int) and not isinstance(v, bool) and not -(2**63) <= v < 2**63:
            raise InterchangeError(f"{where}: {v} does not fit a 64-bit integer")
        return v
    raise InterchangeError(f"{where}: expected a string, number or true/false, got {v!r}")


def _attributes(meta: dict, key: str, path: Path) -> dict:
    raw = meta.get(key) or {}
    if not isinstance(raw, dict):
        raise InterchangeError(f"{path}: field {key!r} must be an object")
    out = {}
    for k, v in raw.items():
        if not k or "\x00" in k or len(k) > 255:
            raise InterchangeError(f"{path}: field {key!r}: bad attribute name {k!r}")
        if k in _NOT_ATTRIBUTES:
            continue
        out[k] = decode_attr(v, f"{path}: field {key!r}.{k}")
    return out


_NOT_ATTRIBUTES = {"marks", "status_recorded"}  # reader-side additions, not stored attributes


def _export_trial(
    rec: TrialRecord, g: h5py.Group, out: Path, sf: SessionFile, blind: bool = False
) -> Path:
    name = trial_name(rec)
    cols = {c: getattr(rec, c) for c in CORE_CHANNELS}
    cols.update({k: v for k, v in rec.extra.items() if not (blind and k.startswith("true_"))})
    hidden = set(SIMULATION_TRUTH) if blind else set()
    design = rec.design.to_dict() if rec.design is not None else None
    if design is not None and not math.isfinite(design.get("crest_factor", 0.0)):
        # Not known (a design imported without it): left out, as import reads its absence.
        del design["crest_factor"]
    n = len(rec.time_s)
    text_cols = []
    dtypes = {}
    for c, v in cols.items():
        exact64 = not (c in g and g[c].dtype == np.float32)
        dtypes[c] = "float64" if exact64 else "float32"
        text_cols.append(_fmt_column(v[:n], exact64))
    csv_path = inside(out, out / f"{name}.csv")
    json_path = inside(out, out / f"{name}.json")
    with open(csv_path, "x", newline="") as fh:
        fh.write(",".join(cols) + "\n")
        for row in zip(*text_cols, strict=True):
            fh.write(",".join(row) + "\n")
    meta = {
        "subject": rec.subject,
        "condition": rec.condition,
        "repetition": rec.repetition,
        "fs_hz": rec.fs_hz,
        "familiarization": rec.familiarization,
        "trial_index": rec.trial_index,
        "attempt": int(rec.attrs.get("attempt", 1)),
        "status": rec.status,
        "abort_reason": rec.abort_reason,
        "boundary_deg": rec.boundary_deg
        if rec.boundary_deg is None or math.isfinite(rec.boundary_deg)
        else "inf",
        "measured_start": rec.measured_start,
        "measured_stop": rec.measured_stop,
        "latin_square_row": rec.attrs.get("latin_square_row", sf.attrs.get("latin_square_row")),
        "units": {c: UNITS.get(c, "") for c in cols},
        # Columns recorded as float32 are written with 9 digits; import stores them as float32
        # again, so export → import gives back the same numbers.
        "dtypes": dtypes,
        "sign_conventions": SIGN_CONVENTIONS,
        "perturbation_design": design,
        "source": rec.source,
        # Everything the session file held, so that import gives it all back.
        "marks": rec.attrs.get("marks", []),
        "trial_attributes": {
            k: encode_attr(v)
            for k, v in rec.attrs.items()
            if k not in _NOT_ATTRIBUTES and k not in hidden
        },
        "session_attributes": {k: encode_attr(v) for k, v in sf.attrs.items() if k not in hidden},
    }
    with open(json_path, "x") as fh:
        fh.write(json.dumps(meta, indent=1, allow_nan=False))
    return csv_path


# -- import ----------------------------------------------------------------------------------------
STATUSES = (STATUS_COMPLETE, STATUS_ABORTED, STATUS_INCOMPLETE, STATUS_SUPERSEDED)
MAX_FS_HZ = 1e6
MIN_TRIAL_ROWS = 100  # a complete trial; an aborted or incomplete one may be shorter
FLOAT32_MAX = float(np.finfo(np.float32).max)


def _whole(meta: dict, key: str, path: Path, *, low: int | None = None, null: bool = True):
    v = meta.get(key)
    if v is None and null:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or (low is not None and v < low):
        need = f"a whole number ≥ {low}" if low is not None else "a whole number"
        raise InterchangeError(f"{path}: field {key!r} must be {need}, got {v!r}")
    if not -(2**63) <= v < 2**63:
        raise InterchangeError(f"{path}: field {key!r}: {v} does not fit a 64-bit integer")
    return v


# How a recording says it was made (issue 36): when the angle and the torque were read relative
# to the command ("start": Steerlab's loop reads, then commands; "end": at the end of the
# interval over which the command was held; or a number of samples), and whether the wheel's
# damping and spring were rendered by the loop from sampled values or acted continuously.
SAMPLE_TIMINGS = {"start": 0.0, "end": 1.0}
MAX_STATED_OFFSET = 10.0
RENDERINGS = ("sampled", "continuous")


def stated_timing(value: Any, where: str, key: str = "sample_timing") -> float:
    """A ``sample_timing`` or ``torque_timing`` (``key``) as an offset in samples after the
    command; ``ValueError`` naming ``where`` and ``key`` for anything else."""
    if isinstance(value, str) and value in SAMPLE_TIMINGS:
        return SAMPLE_TIMINGS[value]
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or not -MAX_STATED_OFFSET <= value <= MAX_STATED_OFFSET:
        raise ValueError(
            f'{where}: field {key!r} must be "start", "end" or a number of samples '
            f"between -{MAX_STATED_OFFSET:g} and {MAX_STATED_OFFSET:g}, got {value!r}"
        )
    return float(value)


def check_rendering(value: Any, where: str) -> str:
    """A ``wheel_rendering``; ``ValueError`` naming ``where`` for anything else."""
    if value not in RENDERINGS:
        raise ValueError(
            f"{where}: field 'wheel_rendering' must be one of {list(RENDERINGS)}, got {value!r}"
        )
    return str(value)


def _read_meta(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text(encoding="utf-8"), parse_constant=_no_constant(path))
    except OSError as e:
        raise InterchangeError(f"{path}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise InterchangeError(f"{path}: not UTF-8 text (byte {e.start}: {e.reason})") from None
    except (json.JSONDecodeError, RecursionError) as e:
        raise InterchangeError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise InterchangeError(f"{path}: expected a JSON object")
    missing = [k for k in REQUIRED_META if k not in meta]
    if missing:
        raise InterchangeError(
            f"{path}: missing field(s) {missing}; required: {list(REQUIRED_META)}"
        )
    fs = meta["fs_hz"]
    if isinstance(fs, bool) or not isinstance(fs, int | float) or not math.isfinite(fs):
        raise InterchangeError(f"{path}: field 'fs_hz' must be a number, got {fs!r}")
    if not MIN_FS_HZ <= fs <= MAX_FS_HZ:
        raise InterchangeError(
            f"{path}: field 'fs_hz' is {fs} Hz; Steerlab needs ≥ {MIN_FS_HZ:g} Hz "
            f"(and at most {MAX_FS_HZ:g})"
        )
    rep = meta["repetition"]
    if isinstance(rep, bool) or not isinstance(rep, int) or not 0 <= rep < 2**31:
        raise InterchangeError(
            f"{path}: field 'repetition' must be a whole number ≥ 0, got {rep!r}"
        )
    for k, example in (("subject", "S01"), ("condition", "BT12")):
        v = meta[k]
        # A number is refused, not turned into text: 1 and "S01" would name different
        # subjects, and a condition 12 is no protocol's.
        if not isinstance(v, str):
            raise InterchangeError(
                f'{path}: field {k!r} must be a string such as "{example}", got {v!r}'
            )
        try:
            check_name(v, f"{path}: field {k!r}")
        except UnsafeNameError as e:
            raise InterchangeError(str(e)) from None
    fam = meta.get("familiarization", False)
    if not isinstance(fam, bool):
        raise InterchangeError(
            f"{path}: field 'familiarization' must be true or false, got {fam!r}"
        )
    # Other labs number their trials from 0: any whole number ≥ 0, distinct within a subject.
    _whole(meta, "trial_index", path, low=0)
    try:
        for key in ("sample_timing", "torque_timing"):
            if key in meta:
                stated_timing(meta[key], str(path), key)
        if "wheel_rendering" in meta:
            check_rendering(meta["wheel_rendering"], str(path))
    except ValueError as e:
        raise InterchangeError(str(e)) from None
    _whole(meta, "attempt", path, low=1)
    _whole(meta, "latin_square_row", path, low=0)
    start = _whole(meta, "measured_start", path, low=0)
    stop = _whole(meta, "measured_stop", path, low=0)
    if start is not None and stop is not None and not start < stop:
        raise InterchangeError(
            f"{path}: fields 'measured_start' ({start}) and 'measured_stop' ({stop}): the start "
            "must come before the stop"
        )
    status = meta.get("status", STATUS_COMPLETE)
    if status not in STATUSES:
        raise InterchangeError(
            f"{path}: field 'status' must be one of {list(STATUSES)}, got {status!r}"
        )
    reason = meta.get("abort_reason")
    if reason is not None and (not isinstance(reason, str) or "\x00" in reason):
        raise InterchangeError(f"{path}: field 'abort_reason' must be text, got {reason!r}")
    bd = meta.get("boundary_deg")
    if bd is not None:
        ok = bd == "inf" or (
            isinstance(bd, int | float) and not isinstance(bd, bool) and bd >= 0 and bd < 1e300
        )
        if not ok:
            raise InterchangeError(
                f"{path}: field 'boundary_deg' must be a number ≥ 0 or \"inf\", got {bd!r}"
            )
    pd = meta.get("perturbation_design")
    if pd is not None:
        meta["_design"] = _design(pd, path)
    marks = meta.get("marks") or []
    if not isinstance(marks, list) or not all(
        isinstance(m, dict)
        and isinstance(m.get("sample"), int)
        and not isinstance(m.get("sample"), bool)
        and 0 <= m["sample"] < 2**62
        and isinstance(m.get("kind"), str)
        and isinstance(m.get("detail"), str)
        for m in marks
    ):
        raise InterchangeError(
            f"{path}: field 'marks' must be a list of {{sample, kind, detail}} objects"
        )
    meta["_session_attributes"] = _attributes(meta, "session_attributes", path)
    meta["_trial_attributes"] = _attributes(meta, "trial_attributes", path)
    _check_condition(meta, path)
    return meta


@functools.cache
def shipped_conditions() -> tuple[str, ...]:
    """The conditions of every protocol shipped with Steerlab (``protocols/*.toml``), in file
    order, each once."""
    shipped = sorted(
        f.name for f in resources.files("steerlab.protocols").iterdir() if f.name.endswith(".toml")
    )
    names: dict[str, None] = {}
    for name in shipped:
        names.update(dict.fromkeys(load_protocol(name).condition_names))
    return tuple(names)


def _check_condition(meta: dict, path: Path) -> None:
    """A condition no protocol knows is most often a typo (BT13 for BT12, BT18): refused, unless
    the trial declares it (``condition_declared``: true, here or among its exported trial
    attributes) or the session it was exported from lists it (``condition_order``)."""
    declared = meta.get("condition_declared", False)
    if not isinstance(declared, bool):
        raise InterchangeError(
            f"{path}: field 'condition_declared' must be true or false, got {declared!r}"
        )
    # Stored in a session file as an HDF5 boolean (uint8), it comes back from an export as 1.
    stored = meta["_trial_attributes"].get("condition_declared")
    if declared or (isinstance(stored, bool | int) and stored == 1):
        return
    cond = meta["condition"]
    order = meta["_session_attributes"].get("condition_order")
    if isinstance(order, str):  # files of format version 1 hold it as JSON text
        try:
            order = json.loads(order)
        except ValueError:
            order = None
    session = [str(c) for c in order] if isinstance(order, list | tuple | np.ndarray) else []
    known = shipped_conditions()
    if cond in known or cond in session:
        return
    close = difflib.get_close_matches(cond, known, n=3, cutoff=0.6)
    hint = f" (did you mean {' or '.join(close)}?)" if close else ""
    raise InterchangeError(
        f"{path}: field 'condition': {cond!r} is not a condition of any Steerlab protocol"
        f"{hint}; known: {', '.join(known)}. If it is a new condition, add "
        '"condition_declared": true to the JSON'
    )


def _no_constant(path: Path):
    def f(name: str):
        raise InterchangeError(f"{path}: not valid JSON ({name} is not a JSON value)")

    return f


def _design(d, path: Path) -> PerturbationDesign:
    where = f"{path}: field 'perturbation_design'"
    if not isinstance(d, dict):
        raise InterchangeError(f"{where}: expected an object, got {d!r}")
    try:
        design = PerturbationDesign.from_dict(d)
        n = len(design.bins)
        arrays = (design.amplitudes_nm, design.phases_rad, design.band_of_bin)
        if any(np.ndim(x) != 1 or len(x) != n for x in (design.bins, *arrays)):
            raise ValueError("bins, amplitudes_Nm, phases_rad and band_of_bin differ in length")
        if not (math.isfinite(design.period_s) and design.period_s > 0):
            raise ValueError(f"period_s must be a finite number > 0, got {design.period_s}")
        if not all(np.all(np.isfinite(x)) for x in arrays) or np.any(design.bins < 1):
            raise ValueError("non-finite values, or a bin < 1")
    except InterchangeError:
        raise
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise InterchangeError(f"{where}: unreadable ({type(e).__name__}: {e})") from None
    return design


def _read_csv(path: Path, fs_hz: float, dtypes: dict[str, str]) -> dict[str, np.ndarray]:
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise InterchangeError(f"{path}: cannot read: {e.strerror or e}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line_no = raw.count(b"\n", 0, e.start) + 1
        raise InterchangeError(
            f"{path}: row {line_no}: not UTF-8 text (byte {e.start}: {e.reason})"
        ) from None
    if "\x00" in text:
        line_no = text.count("\n", 0, text.index("\x00")) + 1
        raise InterchangeError(f"{path}: row {line_no}: a NUL character")
    lines = text.splitlines()
    reader = csv.reader(lines)
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise InterchangeError(f"{path}: empty file, expected a header row") from None
    except csv.Error as e:
        raise InterchangeError(f"{path}: row 1 (header): {e}") from None
    names = set(header)
    missing = [c for c in CORE_CHANNELS if c not in names]
    if missing:
        raise InterchangeError(f"{path}: row 1 (header): missing column(s) {missing}")
    dup = sorted(h for h, k in Counter(header).items() if k > 1)  # linear, not quadratic
    if dup:
        raise InterchangeError(f"{path}: row 1 (header): duplicate column(s) {dup[:20]}")
    arr = _fast_parse(text, len(header))
    # An extra column may say "nothing here" with NaN (a channel imported from another
    # recording that does not cover the whole trial); the core channels are measured throughout.
    may_be_nan = [h not in CORE_CHANNELS for h in header]
    rows: list[list[float]] = []
    try:
        for i, row in enumerate(reader if arr is None else (), start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise InterchangeError(
                    f"{path}: row {i}: {len(row)} cells, the header has {len(header)}"
                )
            vals: list[float] = []
            for j, cell in enumerate(row):
                try:
                    v = float(cell)
                except ValueError:
                    raise InterchangeError(
                        f"{path}: row {i}, column {header[j]!r}: not a number: {cell[:40]!r}"
                    ) from None
                if not math.isfinite(v) and not (math.isnan(v) and may_be_nan[j]):
                    raise InterchangeError(
                        f"{path}: row {i}, column {header[j]!r}: {cell[:40]!r} is not finite"
                    )
                vals.append(v)
            rows.append(vals)
    except csv.Error as e:
        raise InterchangeError(f"{path}: row {reader.line_num}: {e}") from None
    if arr is None:
        arr = np.asarray(rows, dtype=float).reshape(-1, len(header))
    data = {h: arr[:, j].copy() for j, h in enumerate(header)}
    for c, dt in dtypes.items():
        if dt == "float32" and c in data:
            big = np.flatnonzero(np.abs(data[c]) > FLOAT32_MAX)
            if len(big):
                raise InterchangeError(
                    f"{path}: row {int(big[0]) + 2}, column {c!r}: {data[c][big[0]]:g} does not "
                    "fit the column's float32 (it would become infinite)"
                )
    t = data["time_s"]
    if len(t) >= 2:
        steps = np.diff(t)
        bad = np.flatnonzero(np.abs(steps - 1.0 / fs_hz) > 0.01 / fs_hz + 1e-9 * abs(t[1:]).max())
        if len(bad):
            i = int(bad[0])
            raise InterchangeError(
                f"{path}: row {i + 3}, column 'time_s': step {steps[i]:.6g} s from the previous "
                f"row; fs_hz {fs_hz} needs {1 / fs_hz:.6g} s (samples must be evenly spaced, "
                "no gaps)"
            )
    return data


def _dtypes(meta: dict, where: Path) -> dict[str, str]:
    d = meta.get("dtypes") or {}
    if not isinstance(d, dict) or any(v not in ("float32", "float64") for v in d.values()):
        raise InterchangeError(
            f"{where.with_suffix('.json')}: field 'dtypes' must map columns to "
            "'float32' or 'float64'"
        )
    return d


def _fast_parse(text: str, n_cols: int) -> np.ndarray | None:
    """numpy's C parser for well-formed files; None sends the caller to the row-by-row
    parser, whose only job then is to say exactly where the file is wrong."""
    import io

    try:
        arr = np.loadtxt(io.StringIO(text), delimiter=",", skiprows=1, dtype=float, ndmin=2)
    except (ValueError, OSError, IndexError):
        return None
    if arr.size == 0:
        return np.zeros((0, n_cols))
    if arr.shape[1] != n_cols or not np.all(np.isfinite(arr)):
        return None
    return arr


_META_ONLY = {"units", "sign_conventions", "source", "dtypes", "marks", "trial_attributes",
              "session_attributes", "perturbation_design"}  # fmt: skip


@functools.cache
def default_period_s() -> float:
    """The paper protocol's perturbation period: the analysis assumes it for a trial that
    carries no ``perturbation_design``."""
    return load_protocol().perturbation.period_s


def _check_length(csv_path: Path, meta: dict, n: int, fs: float) -> None:
    """A complete trial shorter than one perturbation period has nothing the analysis can use:
    refused here, with the numbers, rather than skipped later without them."""
    design = meta.get("_design")
    period = design.period_s if design is not None else default_period_s()
    need = math.ceil(period * fs - 1e-9)
    if n >= need:
        return
    whence = (
        "its 'perturbation_design'"
        if design is not None
        else "the paper protocol's; a trial perturbed with another period says so in its "
        "JSON's 'perturbation_design'"
    )
    raise InterchangeError(
        f"{csv_path}: {n} data rows at {fs:g} Hz = {n / fs:.3g} s, shorter than one "
        f"perturbation period: {period:g} s ({need} rows; the period is {whence}). Nothing of "
        'it can be analysed; a trial that ended early has "status": "aborted" or "incomplete"'
    )


def read_trial(csv_path: Path, *, require_period: bool = False) -> TrialRecord:
    """One trial from ``NAME.csv`` and ``NAME.json``. ``require_period``: refuse a complete
    trial shorter than one perturbation period (``steerlab import`` does)."""
    meta_path = csv_path.with_suffix(".json")
    if not meta_path.exists():
        raise InterchangeError(f"{csv_path}: no metadata file {meta_path.name} beside it")
    meta = _read_meta(meta_path)
    dtypes = _dtypes(meta, csv_path)
    fs = float(meta["fs_hz"])
    data = _read_csv(csv_path, fs, dtypes)
    n = len(data["time_s"])
    status = meta.get("status", STATUS_COMPLETE)
    if status == STATUS_COMPLETE and n < MIN_TRIAL_ROWS:
        raise InterchangeError(
            f"{csv_path}: {n} data row(s); a complete trial needs at least {MIN_TRIAL_ROWS} "
            "(an aborted or incomplete one may have fewer)"
        )
    if status == STATUS_COMPLETE and require_period:
        _check_length(csv_path, meta, n, fs)
    # measured_start/stop may lie past the data: a trial stopped early keeps its planned
    # window (the analysis decides what a short trial is good for).
    start, stop = meta.get("measured_start"), meta.get("measured_stop")
    core = {c: data.pop(c) for c in CORE_CHANNELS}
    bd = meta.get("boundary_deg")
    attrs = dict(meta["_trial_attributes"])
    attrs.update({k: v for k, v in meta.items() if k not in _META_ONLY and not k.startswith("_")})
    return TrialRecord(
        subject=str(meta["subject"]),
        condition=str(meta["condition"]),
        repetition=int(meta["repetition"]),
        familiarization=bool(meta.get("familiarization", False)),
        fs_hz=fs,
        trial_index=meta.get("trial_index"),
        status=str(status),
        abort_reason=meta.get("abort_reason"),
        measured_start=start,
        measured_stop=stop,
        design=meta.get("_design"),
        boundary_deg=float(bd) if bd is not None else None,
        extra=data,
        attrs={
            **attrs,
            "marks": meta.get("marks") or [],
            "session_attributes": meta["_session_attributes"],
        },
        dtypes=dtypes,
        source=str(csv_path),
        **core,
    )


def import_study(
    csv_dir: str | Path,
    out_dir: str | Path,
    *,
    overwrite: bool = False,
    require_period: bool = False,
) -> list[Path]:
    """Read every NAME.csv + NAME.json; write one session file per subject into ``out_dir``.
    ``require_period``: as for :func:`read_trial`."""
    src = Path(csv_dir)
    if not src.exists():
        raise InterchangeError(f"no such folder: {src}")
    if not src.is_dir():
        raise InterchangeError(f"{src}: not a folder")
    csvs = sorted(src.glob("*.csv"))
    if not csvs:
        raise InterchangeError(f"{src}: no trial files (*.csv)")
    # Every input is checked before anything is written.
    records = [read_trial(p, require_period=require_period) for p in csvs]
    by_subject: dict[str, list[TrialRecord]] = {}
    for r in records:
        by_subject.setdefault(r.subject, []).append(r)
    out = Path(out_dir)
    try:
        targets = {s: inside(out, out / f"{check_name(s, 'subject')}.h5") for s in by_subject}
    except UnsafeNameError as e:
        raise InterchangeError(str(e)) from None
    existing = [str(p) for p in targets.values() if p.exists() or p.is_symlink()]
    if existing and not overwrite:
        raise InterchangeError(f"{out}: session files exist already: {existing}; not overwriting")
    out.mkdir(parents=True, exist_ok=True)
    locks = []
    tmp_paths = []
    try:
        for p in targets.values():
            try:
                locks.append(WriterLock(p).acquire())
            except LockedError as e:
                raise InterchangeError(str(e)) from None
        for s, recs in by_subject.items():
            fd, tmp = tempfile.mkstemp(suffix=".h5.tmp", dir=out)
            os.close(fd)
            tmp_paths.append((Path(tmp), targets[s]))
            write_records(Path(tmp), s, recs, source=str(src))
        for tmp_path, final in tmp_paths:
            os.replace(tmp_path, final)
    finally:
        for tmp_path, _ in tmp_paths:
            tmp_path.unlink(missing_ok=True)
        for lock in locks:
            lock.release()
    return sorted(targets.values())


_SESSION_OWN = ("format", "format_version", "subject", "units", "sign_conventions")


def write_records(
    path: Path, subject: str, records: list[TrialRecord], *, source: str = ""
) -> None:
    """A complete session file from already-recorded trials (no engine, no SWMR needed).

    Session and trial attributes a record carries (``attrs["session_attributes"]`` and its
    other ``attrs``, from an exported session file) are written back as they were.
    """
    session_attrs: dict = {}
    for r in records:
        sa = r.attrs.get("session_attributes") or {}
        for k, v in sa.items():
            if k in session_attrs and not _same(session_attrs[k], v):
                raise InterchangeError(
                    f"{r.source}: session attribute {k!r} differs from another trial of "
                    f"subject {subject}"
                )
            session_attrs[k] = v
    with h5py.File(path, "w", libver=LIBVER) as f:
        set_attrs(
            f,
            {
                "software_version": software_version(),
                "created_utc": now_utc(),
                **{k: v for k, v in session_attrs.items() if k not in _SESSION_OWN},
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "subject": subject,
                "imported_from": source,
                "imported_utc": now_utc(),
                "units": UNITS,
                "sign_conventions": SIGN_CONVENTIONS,
            },
        )
        trials = f.create_group("trials")
        used = set()
        for i, r in enumerate(
            sorted(records, key=lambda r: (r.trial_index or 0, r.condition, r.repetition))
        ):
            att = int(r.attrs.get("attempt", 1) or 1)
            idx = r.trial_index if r.trial_index is not None else i + 1
            label = "fam" if r.familiarization else f"rep{r.repetition}"
            key = f"{idx:02d}_{r.condition}_{label}_a{att}"
            while key in used:
                att += 1
                key = f"{idx:02d}_{r.condition}_{label}_a{att}"
            used.add(key)
            g = trials.create_group(key)
            attrs = {
                **{
                    k: v
                    for k, v in r.attrs.items()
                    if k not in ("perturbation_design", "marks", "session_attributes")
                },
                "subject": r.subject,
                "condition": r.condition,
                "repetition": r.repetition,
                "familiarization": r.familiarization,
                "trial_index": r.trial_index,
                "attempt": att,
                "fs_hz": r.fs_hz,
                "status": r.status,
                "abort_reason": r.abort_reason or "",
                "n_samples": r.attrs.get("n_samples", r.n_samples),
                "measured_start": r.measured_start,
                "measured_stop": r.measured_stop,
                "boundary_deg": r.boundary_deg,
                "imported_from": r.source,
                "units": UNITS,
            }
            dj = r.attrs.get("perturbation_design")
            if r.design is not None:
                attrs["perturbation_design"] = (
                    dj if isinstance(dj, str) and _same_design(dj, r.design) else r.design.to_json()
                )
            elif isinstance(dj, dict):
                attrs["perturbation_design"] = json.dumps(dj)
            set_attrs(g, attrs)
            for c in CORE_CHANNELS:
                create_channel(g, c, data=np.asarray(getattr(r, c), dtype=r.dtypes.get(c, "f8")))
            for c, v in r.extra.items():
                create_channel(g, c, data=np.asarray(v, dtype=r.dtypes.get(c, "f8")))
            marks = [
                (int(m["sample"]), m["kind"].encode()[:16], m["detail"].encode()[:240])
                for m in r.attrs.get("marks") or []
            ]
            create_channel(
                g,
                "marks",
                data=np.array(marks, dtype=MARK_DTYPE),
                maxshape=(None,),
                chunks=(64,),
            )


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b))
    return a == b or (a != a and b != b)


def _same_design(text: str, design: PerturbationDesign) -> bool:
    try:
        d = PerturbationDesign.from_json(text)
    except (KeyError, TypeError, ValueError):
        return False
    return d.period_s == design.period_s and np.array_equal(d.bins, design.bins)
