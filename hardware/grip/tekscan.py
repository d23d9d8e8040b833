"""TekScan ASCII movie exports (``.asf``/``.csv``) read into per-frame pressure maps and forces.

Labs that record grip with TekScan Grip gloves (or other TekScan sensors) export each recording
as ASCII: a ``KEY value`` header closed by ``ASCII_DATA @@``, then per frame a ``Frame N`` line
and ROWS lines of COLS comma-separated cells (``B`` = outside the sensor outline), then ``@@``.
The I-Scan export adds ``, <t s>,, <clock>,,,Raw Sum=,,<sum>`` to each frame line.

The reader is strict, because a grip-force analysis must not run on a recording that quietly
lost or mangled frames:

* Every problem raises :class:`TekscanError` naming the file, the line and what is wrong.
  A header line is ``KEY value`` (a key alone gives an empty value); a key given twice is an
  error. ``COMMENTS:`` text runs until a line that looks like a header key.
* A file without the closing ``@@`` is an error, whether or not its last frame is complete:
  a cut at a frame boundary looks exactly like a shorter recording. ``allow_truncated=True``
  reads what is there instead, drops an incomplete last frame, warns with
  :class:`TekscanTruncatedWarning` saying how many frames were kept, and marks the movie
  ``complete=False``; nothing is dropped without both the opt-in and the warning.
* Frame numbers must run from START_FRAME to END_FRAME without gaps (when the header gives
  them), so a missing frame in the middle is an error too.
* Where a frame line states a ``Raw Sum`` and the cells are raw counts (``UNITS raw``), the
  cells must add up to it exactly. For calibrated units the cells are not raw counts, so the
  stated sum is kept but cannot be checked.

Time base: where the frame lines state a time (I-Scan), ``frame_times_s`` is that time, since it
is what the acquisition recorded and it drifts from the nominal rate (309 frames at a nominal
0.1 s span 31.1 s, not 30.8 s). Otherwise it is ``(frame - START_FRAME) * SECONDS_PER_FRAME``,
so both bases put START_FRAME at 0 s.
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Pressure units whose cells can be turned into force, in Pa per unit (keys are lower case).
PRESSURE_UNITS_PA: dict[str, float] = {
    "pa": 1.0,
    "kpa": 1e3,
    "mpa": 1e6,
    "psi": 6894.757293168361,
    "mmhg": 133.322387415,
}
#: Sensel-area units in m² per unit (keys are lower case, ``^`` removed).
AREA_UNITS_M2: dict[str, float] = {"mm2": 1e-6, "cm2": 1e-4, "m2": 1.0, "in2": 0.00064516}

_END_OF_HEADER = "ASCII_DATA @@"
_END_OF_DATA = "@@"
_HEADER_LINE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)(?:[ \t]+(.*))?")
_FRAME_LINE = re.compile(r"Frame[ \t]+(\d+)[ \t]*(.*)")
_RAW_SUM = re.compile(r"Raw Sum=[,\s]*([^,\s]*)")
_QUANTITY = re.compile(r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(\S*)")
# A line after ``COMMENTS:`` ends the comment if it looks like a header key: a known key or an
# all-caps key with an underscore. Comment text shaped like that cannot be told apart.
_KNOWN_KEYS = frozenset(
    "DATA_TYPE VERSION HARDWARE MAP_VERSION HW_TYPE VersaPogoFsx FILENAME SENSOR_TYPE ROWS COLS"
    " ROW_SPACING COL_SPACING SENSEL_AREA NOISE_THRESHOLD SECONDS_PER_FRAME MICRO_SECOND TIME"
    " SATURATION_PRESSURE SENSITIVITY MAP_INDEX SUBMAP START_FRAME END_FRAME UNITS MIRROR_ROW"
    " MIRROR_COL ASCII_DATA SCALE_FACTOR EXPONENT".split()
)
_KEY_LIKE = re.compile(r"[A-Z][A-Z0-9]*(?:_[A-Z0-9]+)+(?:[ \t]|$)")


class TekscanError(ValueError):
    """A TekScan export is malformed or cannot give what was asked; the message names the file
    and, for format problems, the line."""


class TekscanTruncatedWarning(UserWarning):
    """A file without its closing ``@@`` was read anyway (``allow_truncated=True``)."""


@dataclass(frozen=True, eq=False)
class TekscanMovie:
    """One TekScan recording. Arrays are read-only; ``frames`` is NaN where a cell is ``B``."""

    path: Path
    header: dict[str, str]
    rows: int
    cols: int
    seconds_per_frame: float | None
    units: str | None
    sensel_area_m2: float | None
    start_frame: int
    frame_numbers: np.ndarray
    frames: np.ndarray
    frame_times_s: np.ndarray
    times_from_file: bool
    stated_raw_sum: np.ndarray | None
    complete: bool = True

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def outline(self) -> np.ndarray:
        """Cells inside the sensor outline in every frame (rows × cols, bool)."""
        return ~np.isnan(self.frames).any(axis=0)

    def totals(self) -> np.ndarray:
        """Per-frame sum of the cells inside the outline, in the file's units."""
        return np.nansum(self.frames, axis=(1, 2))

    def force_n(self, n_per_raw: float | None = None) -> np.ndarray:
        """Per-frame total force in N.

        Pressure units (:data:`PRESSURE_UNITS_PA`, case-insensitive) give
        sum(pressure) × SENSEL_AREA. Raw counts need a linear calibration ``n_per_raw`` (N per
        raw count; TekScan's own calibrations can be non-linear, so apply such a law to
        :meth:`totals` instead). Other units (e.g. force units per sensel) are refused rather
        than guessed.
        """
        units = (self.units or "").strip()
        if units.lower() == "raw":
            if n_per_raw is None:
                raise TekscanError(
                    f"{self.path}: UNITS raw: the cells are raw sensor counts, so force needs a"
                    " calibration in N per raw count: pass n_per_raw=..."
                )
            if not (math.isfinite(n_per_raw) and n_per_raw > 0):
                raise TekscanError(f"{self.path}: n_per_raw must be > 0, got {n_per_raw!r}")
            return self.totals() * float(n_per_raw)
        if n_per_raw is not None:
            raise TekscanError(
                f"{self.path}: UNITS {units}: the cells are already calibrated; n_per_raw is"
                " only for UNITS raw"
            )
        pa_per_unit = PRESSURE_UNITS_PA.get(units.lower())
        if pa_per_unit is None:
            supported = ", ".join(["raw", "Pa", "KPa", "MPa", "psi", "mmHg"])
            raise TekscanError(
                f"{self.path}: UNITS {units or '(missing)'} cannot be turned into force;"
                f" supported units: {supported}"
            )
        if self.sensel_area_m2 is None:
            raise TekscanError(f"{self.path}: no SENSEL_AREA in the header, needed for force")
        return self.totals() * (pa_per_unit * self.sensel_area_m2)


def read_tekscan(path: str | Path, *, allow_truncated: bool = False) -> TekscanMovie:
    """Read a TekScan ASCII movie export; see the module docstring for what is refused."""
    path = Path(path)
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    lines = [line.rstrip("\r") for line in text.split("\n")]
    header, key_lines, body_start = _parse_header(path, lines)
    return _parse_body(path, lines, header, key_lines, body_start, allow_truncated)


def _fail(path: Path, line_no: int | None, what: str) -> TekscanError:
    where = f"{path}" if line_no is None else f"{path}, line {line_no}"
    return TekscanError(f"{where}: {what}")


def _parse_header(path: Path, lines: list[str]) -> tuple[dict[str, str], dict[str, int], int]:
    """The raw header, the line number of each key, and the index of the first body line."""
    header: dict[str, str] = {}
    key_lines: dict[str, int] = {}
    comments: list[str] | None = None
    for i, raw in enumerate(lines):
        line_no = i + 1
        line = raw.strip()
        if line == _END_OF_HEADER:
            if comments is not None:
                header["COMMENTS"] = "\n".join(comments).strip()
            return header, key_lines, i + 1
        if comments is not None:
            key = line.split(maxsplit=1)[0] if line else ""
            if key not in _KNOWN_KEYS and not _KEY_LIKE.match(line):
                comments.append(line)
                continue
            header["COMMENTS"] = "\n".join(comments).strip()
            comments = None
        if not line:
            continue
        if _FRAME_LINE.fullmatch(line):
            raise _fail(path, line_no, f"frame line {line!r} before the {_END_OF_HEADER!r} line")
        if line.startswith("COMMENTS:"):
            key, value = "COMMENTS", None
            comments = [line[len("COMMENTS:") :].strip()] if line != "COMMENTS:" else []
        else:
            match = _HEADER_LINE.fullmatch(line)
            if match is None:
                raise _fail(path, line_no, f"malformed header line {line!r} (expected KEY value)")
            key, value = match.group(1), (match.group(2) or "").strip()
            if key == "ASCII_DATA":
                raise _fail(path, line_no, f"expected {_END_OF_HEADER!r}, got {line!r}")
        if key in key_lines:
            raise _fail(path, line_no, f"{key} given twice (first on line {key_lines[key]})")
        key_lines[key] = line_no
        if value is not None:
            header[key] = value
    raise _fail(path, None, f"no {_END_OF_HEADER!r} line: the header never ends")


def _int(path: Path, header: dict[str, str], key_lines: dict[str, int], key: str) -> int | None:
    if key not in header:
        return None
    try:
        return int(header[key])
    except ValueError:
        raise _fail(path, key_lines[key], f"{key} is not an integer: {header[key]!r}") from None


def _size(path: Path, header: dict[str, str], key_lines: dict[str, int], key: str) -> int:
    value = _int(path, header, key_lines, key)
    if value is None:
        raise _fail(path, None, f"no {key} in the header: the frame size is unknown")
    if value <= 0:
        raise _fail(path, key_lines[key], f"{key} must be positive, got {value}")
    return value


def _seconds_per_frame(
    path: Path, header: dict[str, str], key_lines: dict[str, int]
) -> float | None:
    if "SECONDS_PER_FRAME" not in header:
        return None
    try:
        value = float(header["SECONDS_PER_FRAME"])
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise _fail(
            path,
            key_lines["SECONDS_PER_FRAME"],
            f"SECONDS_PER_FRAME must be a positive number, got {header['SECONDS_PER_FRAME']!r}",
        )
    return value


def _sensel_area_m2(path: Path, header: dict[str, str], key_lines: dict[str, int]) -> float | None:
    if "SENSEL_AREA" not in header:
        return None
    value = header["SENSEL_AREA"]
    match = _QUANTITY.fullmatch(value)
    unit = match.group(2).replace("^", "").lower() if match else ""
    if match is None or unit not in AREA_UNITS_M2:
        raise _fail(
            path,
            key_lines["SENSEL_AREA"],
            f"SENSEL_AREA {value!r} is not a number with one of the units"
            f" {', '.join(AREA_UNITS_M2)}",
        )
    return float(match.group(1)) * AREA_UNITS_M2[unit]


def _frame_line_extras(path: Path, line_no: int, rest: str) -> tuple[float | None, float | None]:
    """The time and the Raw Sum stated after ``Frame N``, either of which may be absent."""
    if not rest:
        return None, None
    if not rest.startswith(","):
        raise _fail(path, line_no, f"unexpected text after the frame number: {rest!r}")
    time_field = rest[1:].split(",", 1)[0].strip()
    time_s = None
    if time_field:
        try:
            time_s = float(time_field)
        except ValueError:
            raise _fail(path, line_no, f"frame time {time_field!r} is not a number") from None
    raw_sum = None
    match = _RAW_SUM.search(rest)
    if match is not None:
        try:
            raw_sum = float(match.group(1))
        except ValueError:
            raise _fail(path, line_no, f"Raw Sum {match.group(1)!r} is not a number") from None
    elif "Raw Sum" in rest:
        raise _fail(path, line_no, "malformed Raw Sum (expected 'Raw Sum=,,<number>')")
    return time_s, raw_sum


def _parse_body(
    path: Path,
    lines: list[str],
    header: dict[str, str],
    key_lines: dict[str, int],
    body_start: int,
    allow_truncated: bool,
) -> TekscanMovie:
    rows = _size(path, header, key_lines, "ROWS")
    cols = _size(path, header, key_lines, "COLS")
    seconds_per_frame = _seconds_per_frame(path, header, key_lines)
    sensel_area_m2 = _sensel_area_m2(path, header, key_lines)
    start_frame = _int(path, header, key_lines, "START_FRAME")
    end_frame = _int(path, header, key_lines, "END_FRAME")

    numbers: list[int] = []
    frame_line_nos: list[int] = []
    times: list[float | None] = []
    raw_sums: list[float | None] = []
    cells: list[str] = []
    row_line_nos: list[int] = []
    rows_in_frame = rows  # no frame open
    closed_at: int | None = None

    def close_frame(line_no: int, why: str) -> None:
        if rows_in_frame < rows:
            raise _fail(
                path,
                line_no,
                f"frame {numbers[-1]} (line {frame_line_nos[-1]}) has {rows_in_frame} rows,"
                f" ROWS is {rows}; {why}",
            )

    for i in range(body_start, len(lines)):
        line_no = i + 1
        line = lines[i].strip()
        if closed_at is not None:
            if line:
                raise _fail(path, line_no, f"text after the closing @@ (line {closed_at})")
            continue
        if not line:
            if numbers and 0 < rows_in_frame < rows:
                close_frame(line_no, "blank line inside the frame")
            continue
        if line == _END_OF_DATA:
            if numbers:
                close_frame(line_no, "the data ends")
            closed_at = line_no
            continue
        frame = _FRAME_LINE.fullmatch(line)
        if frame is not None:
            if numbers:
                close_frame(line_no, "the next frame starts")
            number = int(frame.group(1))
            expected = numbers[-1] + 1 if numbers else start_frame
            if expected is not None and number != expected:
                raise _fail(path, line_no, f"frame {number} where frame {expected} was expected")
            time_s, raw_sum = _frame_line_extras(path, line_no, frame.group(2).strip())
            if numbers and (time_s is None) != (times[-1] is None):
                raise _fail(path, line_no, "some frame lines state a time and others do not")
            if numbers and (raw_sum is None) != (raw_sums[-1] is None):
                raise _fail(path, line_no, "some frame lines state a Raw Sum and others do not")
            numbers.append(number)
            frame_line_nos.append(line_no)
            times.append(time_s)
            raw_sums.append(raw_sum)
            rows_in_frame = 0
            continue
        if not numbers:
            raise _fail(path, line_no, f"expected a 'Frame N' line, got {line[:40]!r}")
        if rows_in_frame >= rows:
            raise _fail(path, line_no, f"frame {numbers[-1]} has more than ROWS = {rows} rows")
        tokens = line.replace(" ", "").replace("\t", "").split(",")
        if len(tokens) == cols + 1 and tokens[-1] == "":
            tokens.pop()  # a trailing comma
        if len(tokens) != cols:
            raise _fail(
                path, line_no, f"frame {numbers[-1]}: {len(tokens)} cells in a row, COLS is {cols}"
            )
        cells.extend(tokens)
        row_line_nos.append(line_no)
        rows_in_frame += 1

    complete = closed_at is not None
    if not complete:
        what = "no closing @@: the file is truncated"
        if not allow_truncated:
            raise _fail(path, len(lines), what + " (allow_truncated=True reads it anyway)")
        dropped = 0
        announced = ""
        if start_frame is not None and end_frame is not None:
            announced = f" of the {end_frame - start_frame + 1} the header announces"
        if numbers and rows_in_frame < rows:
            del cells[len(cells) - rows_in_frame * cols :]
            del row_line_nos[len(row_line_nos) - rows_in_frame :]
            for kept in (numbers, frame_line_nos, times, raw_sums):
                kept.pop()
            dropped = 1
        warnings.warn(
            f"{path}: {what}; kept {len(numbers)} complete frames"
            + announced
            + (f", dropped {dropped} incomplete frame" if dropped else ""),
            TekscanTruncatedWarning,
            stacklevel=3,
        )
    if not numbers:
        raise _fail(path, None, "no frames after the header")
    if complete and end_frame is not None and numbers[-1] != end_frame:
        raise _fail(
            path,
            closed_at,
            f"the data ends after frame {numbers[-1]} but END_FRAME is {end_frame}",
        )

    frames = _cells_to_array(path, cells, row_line_nos, cols).reshape(len(numbers), rows, cols)
    if start_frame is None:
        start_frame = numbers[0]
    frame_numbers = np.array(numbers, dtype=np.int64)
    times_from_file = times[0] is not None
    if times_from_file:
        frame_times_s = np.array(times, dtype=float)
    elif seconds_per_frame is not None:
        frame_times_s = (frame_numbers - start_frame) * seconds_per_frame
    else:
        raise _fail(path, None, "no SECONDS_PER_FRAME and the frame lines state no time")

    stated_raw_sum = None
    if raw_sums[0] is not None:
        stated_raw_sum = np.array(raw_sums, dtype=float)
        if header.get("UNITS", "").strip().lower() == "raw":
            sums = np.nansum(frames, axis=(1, 2))
            bad = np.flatnonzero(sums != stated_raw_sum)
            if bad.size:
                k = int(bad[0])
                raise _fail(
                    path,
                    frame_line_nos[k],
                    f"frame {numbers[k]} states Raw Sum {stated_raw_sum[k]:g} but its cells"
                    f" add up to {sums[k]:g} ({bad.size} frames disagree)",
                )

    for array in (frame_numbers, frames, frame_times_s, stated_raw_sum):
        if array is not None:
            array.setflags(write=False)
    return TekscanMovie(
        path=path,
        header=header,
        rows=rows,
        cols=cols,
        seconds_per_frame=seconds_per_frame,
        units=header.get("UNITS"),
        sensel_area_m2=sensel_area_m2,
        start_frame=start_frame,
        frame_numbers=frame_numbers,
        frames=frames,
        frame_times_s=frame_times_s,
        times_from_file=times_from_file,
        stated_raw_sum=stated_raw_sum,
        complete=complete,
    )


def _cells_to_array(path: Path, cells: list[str], row_line_nos: list[int], cols: int) -> np.ndarray:
    """Cells as floats, NaN for ``B``; anything else that is not a finite number is an error."""
    text = np.array(cells)
    outside = text == "B"
    try:
        values = np.where(outside, "nan", text).astype(float)
    except ValueError:
        values = None
    if values is not None:
        bad = ~outside & ~np.isfinite(values)
        if not bad.any():
            return values
        first = int(np.flatnonzero(bad)[0])
    else:
        first = next(k for k, cell in enumerate(cells) if not _is_number(cell))
    line_no = row_line_nos[first // cols]
    raise _fail(path, line_no, f"cell {first % cols + 1} is {cells[first]!r}, not a number or B")


def _is_number(cell: str) -> bool:
    if cell == "B":
        return True
    try:
        return math.isfinite(float(cell))
    except ValueError:
        return False
