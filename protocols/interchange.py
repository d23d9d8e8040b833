"""The trial interchange format: per trial ``NAME.csv`` + ``NAME.json``.

CSV header starts with (in any order, extra columns allowed)
``time_s,perturbation_torque_Nm,driver_torque_Nm,wheel_angle_rad,grip_force_N``.
JSON holds at least ``subject``, ``condition``, ``repetition``, ``fs_hz``, and where known
``familiarization`` (bool) and ``trial_index`` (1-based order in the session).
Sign convention: ``driver_torque_Nm`` is the torque the wheel exerts on the hands, so that
S(Tp,θ)/S(Tp,Td) is positive at low frequency.

Import accepts any sample rate ≥ 100 Hz and data that do not start on a period boundary; every
error names the file, and the row and column where there is one. Nothing is written unless
every input file is good.
"""

from __future__ import annotations

import csv
import json
import math
import os
import tempfile
from pathlib import Path

import h5py
import numpy as np

from protocols.datafile import (
    FORMAT,
    FORMAT_VERSION,
    MARK_DTYPE,
    SIGN_CONVENTIONS,
    UNITS,
    SessionFile,
    _now,
    _open_for_reading,
    _set_attrs,
    session_files,
    software_version,
)
from protocols.records import CORE_CHANNELS, STATUS_COMPLETE, TrialRecord

REQUIRED_META = ("subject", "condition", "repetition", "fs_hz")
MIN_FS_HZ = 100.0


class InterchangeError(ValueError):
    """Bad interchange input; the message names the file, row and column."""


# -- export ----------------------------------------------------------------------------------------
def _fmt_column(values: np.ndarray, exact64: bool) -> list[str]:
    # %.17g round-trips a float64, %.9g a float32: export → import gives the same numbers.
    f = "%.17g" if exact64 else "%.9g"
    return [f % v for v in values]


def export_study(session_dir: str | Path, out_dir: str | Path) -> list[Path]:
    """Write every trial of every session file as CSV + JSON. Returns the CSV paths."""
    files = session_files(session_dir)
    if not files:
        raise InterchangeError(f"{session_dir}: no session files (*.h5) to export")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for path in files:
        sf = SessionFile(path)
        with _open_for_reading(path) as f:
            for rec in sf.records():
                g = f["trials"][rec.source.rsplit("/", 1)[-1]]
                written.append(_export_trial(rec, g, out, sf))
    return written


def trial_name(rec: TrialRecord) -> str:
    idx = f"T{rec.trial_index:02d}_" if rec.trial_index is not None else ""
    rep = "fam" if rec.familiarization else f"rep{rec.repetition}"
    att = int(rec.attrs.get("attempt", 1))
    suffix = f"_a{att}" if att != 1 else ""
    return f"{rec.subject}_{idx}{rec.condition}_{rep}{suffix}"


def _export_trial(rec: TrialRecord, g: h5py.Group, out: Path, sf: SessionFile) -> Path:
    name = trial_name(rec)
    cols = {c: getattr(rec, c) for c in CORE_CHANNELS}
    cols.update(rec.extra)
    n = len(rec.time_s)
    text_cols = []
    dtypes = {}
    for c, v in cols.items():
        exact64 = not (c in g and g[c].dtype == np.float32)
        dtypes[c] = "float64" if exact64 else "float32"
        text_cols.append(_fmt_column(v[:n], exact64))
    csv_path = out / f"{name}.csv"
    with open(csv_path, "w", newline="") as fh:
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
        "latin_square_row": rec.attrs.get("latin_square_row"),
        "units": {c: UNITS.get(c, "") for c in cols},
        # Columns recorded as float32 are written with 9 digits; import stores them as float32
        # again, so export → import gives back the same numbers.
        "dtypes": dtypes,
        "sign_conventions": SIGN_CONVENTIONS,
        "perturbation_design": rec.design.to_dict() if rec.design is not None else None,
        "source": rec.source,
    }
    (out / f"{name}.json").write_text(json.dumps(meta, indent=1))
    return csv_path


# -- import ----------------------------------------------------------------------------------------
def _read_meta(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise InterchangeError(f"{path}: cannot read: {e.strerror or e}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
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
    if fs < MIN_FS_HZ:
        raise InterchangeError(
            f"{path}: field 'fs_hz' is {fs} Hz; Steerlab needs ≥ {MIN_FS_HZ:g} Hz"
        )
    rep = meta["repetition"]
    if isinstance(rep, bool) or not isinstance(rep, int) or rep < 0:
        raise InterchangeError(
            f"{path}: field 'repetition' must be a whole number ≥ 0, got {rep!r}"
        )
    for k in ("subject", "condition"):
        if not isinstance(meta[k], str | int) or str(meta[k]).strip() == "":
            raise InterchangeError(
                f"{path}: field {k!r} must be a non-empty string, got {meta[k]!r}"
            )
    fam = meta.get("familiarization", False)
    if not isinstance(fam, bool):
        raise InterchangeError(
            f"{path}: field 'familiarization' must be true or false, got {fam!r}"
        )
    ti = meta.get("trial_index")
    if ti is not None and (isinstance(ti, bool) or not isinstance(ti, int)):
        raise InterchangeError(f"{path}: field 'trial_index' must be a whole number, got {ti!r}")
    return meta


def _read_csv(path: Path, fs_hz: float) -> dict[str, np.ndarray]:
    try:
        fh = open(path, newline="", encoding="utf-8")
    except OSError as e:
        raise InterchangeError(f"{path}: cannot read: {e.strerror or e}") from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise InterchangeError(f"{path}: empty file, expected a header row") from None
        missing = [c for c in CORE_CHANNELS if c not in header]
        if missing:
            raise InterchangeError(f"{path}: row 1 (header): missing column(s) {missing}")
        dup = {h for h in header if header.count(h) > 1}
        if dup:
            raise InterchangeError(f"{path}: row 1 (header): duplicate column(s) {sorted(dup)}")
        arr = _fast_parse(path, len(header))
        rows: list[list[float]] = []
        for i, row in enumerate(reader if arr is None else (), start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise InterchangeError(
                    f"{path}: row {i}: {len(row)} cells, the header has {len(header)}"
                )
            vals = []
            for j, cell in enumerate(row):
                try:
                    v = float(cell)
                except ValueError:
                    raise InterchangeError(
                        f"{path}: row {i}, column {header[j]!r}: not a number: {cell!r}"
                    ) from None
                if not math.isfinite(v):
                    raise InterchangeError(
                        f"{path}: row {i}, column {header[j]!r}: {cell!r} is not finite"
                    )
                vals.append(v)
            rows.append(vals)
    if arr is None:
        arr = np.asarray(rows, dtype=float).reshape(-1, len(header))
    if len(arr) < 2:
        raise InterchangeError(f"{path}: {len(arr)} data row(s); a trial needs many samples")
    data = {h: arr[:, j].copy() for j, h in enumerate(header)}
    t = data["time_s"]
    dt = np.diff(t)
    bad = np.flatnonzero(np.abs(dt - 1.0 / fs_hz) > 0.01 / fs_hz + 1e-9 * abs(t[1:]).max())
    if len(bad):
        i = int(bad[0])
        raise InterchangeError(
            f"{path}: row {i + 3}, column 'time_s': step {dt[i]:.6g} s from the previous row; "
            f"fs_hz {fs_hz} needs {1 / fs_hz:.6g} s (samples must be evenly spaced, no gaps)"
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


def _fast_parse(path: Path, n_cols: int) -> np.ndarray | None:
    """numpy's C parser for well-formed files; None sends the caller to the row-by-row
    parser, whose only job then is to say exactly where the file is wrong."""
    try:
        arr = np.loadtxt(path, delimiter=",", skiprows=1, dtype=float, ndmin=2, encoding="utf-8")
    except (ValueError, OSError):
        return None
    if arr.shape[1] != n_cols or not np.all(np.isfinite(arr)):
        return None
    return arr


def read_trial(csv_path: Path) -> TrialRecord:
    meta_path = csv_path.with_suffix(".json")
    if not meta_path.exists():
        raise InterchangeError(f"{csv_path}: no metadata file {meta_path.name} beside it")
    meta = _read_meta(meta_path)
    data = _read_csv(csv_path, float(meta["fs_hz"]))
    core = {c: data.pop(c) for c in CORE_CHANNELS}
    bd = meta.get("boundary_deg")
    return TrialRecord(
        subject=str(meta["subject"]),
        condition=str(meta["condition"]),
        repetition=int(meta["repetition"]),
        familiarization=bool(meta.get("familiarization", False)),
        fs_hz=float(meta["fs_hz"]),
        trial_index=meta.get("trial_index"),
        status=str(meta.get("status", STATUS_COMPLETE)),
        abort_reason=meta.get("abort_reason"),
        measured_start=meta.get("measured_start"),
        measured_stop=meta.get("measured_stop"),
        boundary_deg=float(bd) if bd is not None else None,
        extra=data,
        attrs={
            k: v
            for k, v in meta.items()
            if k not in ("units", "sign_conventions", "source", "dtypes")
        },
        dtypes=_dtypes(meta, csv_path),
        source=str(csv_path),
        **core,
    )


def import_study(
    csv_dir: str | Path, out_dir: str | Path, *, overwrite: bool = False
) -> list[Path]:
    """Read every NAME.csv + NAME.json; write one session file per subject into ``out_dir``."""
    src = Path(csv_dir)
    if not src.is_dir():
        raise InterchangeError(f"{src}: not a directory")
    csvs = sorted(src.glob("*.csv"))
    if not csvs:
        raise InterchangeError(f"{src}: no trial files (*.csv)")
    records = [read_trial(p) for p in csvs]  # every input checked before anything is written
    by_subject: dict[str, list[TrialRecord]] = {}
    for r in records:
        by_subject.setdefault(r.subject, []).append(r)
    out = Path(out_dir)
    targets = {s: out / f"{_safe(s)}.h5" for s in by_subject}
    existing = [str(p) for p in targets.values() if p.exists()]
    if existing and not overwrite:
        raise InterchangeError(f"{out}: session files exist already: {existing}; not overwriting")
    out.mkdir(parents=True, exist_ok=True)
    tmp_paths = []
    try:
        for s, recs in by_subject.items():
            fd, tmp = tempfile.mkstemp(suffix=".h5.tmp", dir=out)
            os.close(fd)
            tmp_paths.append((Path(tmp), targets[s]))
            write_records(Path(tmp), s, recs, source=str(src))
        for tmp, final in tmp_paths:
            os.replace(tmp, final)
    finally:
        for tmp, _ in tmp_paths:
            Path(tmp).unlink(missing_ok=True)
    return sorted(targets.values())


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)


def write_records(
    path: Path, subject: str, records: list[TrialRecord], *, source: str = ""
) -> None:
    """A complete session file from already-recorded trials (no engine, no SWMR needed)."""
    with h5py.File(path, "w", libver="latest") as f:
        _set_attrs(
            f,
            {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "software_version": software_version(),
                "created_utc": _now(),
                "subject": subject,
                "imported_from": source,
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
                **{k: v for k, v in r.attrs.items() if k not in ("perturbation_design", "marks")},
                "subject": r.subject,
                "condition": r.condition,
                "repetition": r.repetition,
                "familiarization": r.familiarization,
                "trial_index": r.trial_index,
                "attempt": att,
                "fs_hz": r.fs_hz,
                "status": r.status,
                "abort_reason": r.abort_reason or "",
                "n_samples": r.n_samples,
                "measured_start": r.measured_start,
                "measured_stop": r.measured_stop,
                "boundary_deg": r.boundary_deg,
                "imported_from": r.source,
                "units": UNITS,
            }
            dj = r.attrs.get("perturbation_design")
            if r.design is not None:
                attrs["perturbation_design"] = r.design.to_json()
            elif isinstance(dj, dict):
                attrs["perturbation_design"] = json.dumps(dj)
            _set_attrs(g, attrs)
            for c in CORE_CHANNELS:
                g.create_dataset(c, data=np.asarray(getattr(r, c), dtype=r.dtypes.get(c, "f8")))
            for c, v in r.extra.items():
                g.create_dataset(c, data=np.asarray(v, dtype=r.dtypes.get(c, "f8")))
            g.create_dataset("marks", shape=(0,), maxshape=(None,), dtype=MARK_DTYPE, chunks=(64,))
