"""TekScan ASCII exports: the two real public files, and malformed files derived from them."""

from __future__ import annotations

import math
import re
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from steerlab.hardware.grip.tekscan import (
    TekscanError,
    TekscanTruncatedWarning,
    read_tekscan,
)

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tekscan"
FSCAN = DATA / "fscan_testL.asf"  # UNITS KPa, 60 × 21, 205 frames, frame lines "Frame N"
ISCAN = DATA / "iscan_test.csv"  # UNITS raw, 28 × 28, 309 frames, frame lines with Raw Sum

pytestmark = pytest.mark.skipif(
    not (FSCAN.is_file() and ISCAN.is_file()),
    reason=f"the public TekScan exports are not in {DATA} (a clone outside the lab workspace)",
)


def _lines(path: Path) -> list[str]:
    return path.read_text().split("\n")


def _line_no(lines: list[str], text: str) -> int:
    """1-based number of the first line equal to ``text``."""
    return lines.index(text) + 1


def _write(tmp_path: Path, lines: list[str], name: str = "bad.asf") -> Path:
    out = tmp_path / name
    out.write_text("\n".join(lines))
    return out


def _fails(path: Path, line_no: int | None, what: str) -> None:
    where = re.escape(f"{path}, line {line_no}:") if line_no else re.escape(f"{path}:")
    with pytest.raises(TekscanError, match=where + ".*" + what):
        read_tekscan(path)


def _spacing_mm(value: str) -> float:
    number, unit = value.split()
    return float(number) * {"mm": 1.0, "centimeters": 10.0}[unit]


# --- the real files -------------------------------------------------------------------------


def test_iscan_raw_sum_of_every_frame_is_the_files_own_raw_sum_exactly():
    movie = read_tekscan(ISCAN)
    assert (movie.rows, movie.cols, movie.n_frames) == (28, 28, 309)
    assert movie.units == "raw"
    assert movie.stated_raw_sum is not None
    # The cells' sums and the stated sums agree exactly, frame by frame (309/309).
    assert int(np.sum(movie.totals() == movie.stated_raw_sum)) == 309
    assert movie.stated_raw_sum[:3].tolist() == [310, 307, 308]
    assert movie.stated_raw_sum[-1] == 29
    np.testing.assert_array_equal(movie.frame_numbers, np.arange(1, 310))


def test_iscan_times_are_the_ones_the_frame_lines_state():
    movie = read_tekscan(ISCAN)
    assert movie.times_from_file
    stated = [float(line.split(",")[1]) for line in _lines(ISCAN) if line.startswith("Frame ")]
    np.testing.assert_array_equal(movie.frame_times_s, stated)
    # The recorded clock runs slower than the nominal 0.1 s per frame: 31.1 s, not 30.8 s.
    assert movie.seconds_per_frame == 0.1
    assert movie.frame_times_s[-1] == 31.1


def test_iscan_force_needs_a_calibration_and_uses_it_linearly():
    movie = read_tekscan(ISCAN)
    with pytest.raises(TekscanError, match=re.escape(str(ISCAN)) + ".*n_per_raw"):
        movie.force_n()
    np.testing.assert_array_equal(movie.force_n(n_per_raw=0.25), movie.stated_raw_sum * 0.25)
    with pytest.raises(TekscanError, match="n_per_raw must be > 0"):
        movie.force_n(n_per_raw=-1.0)


def test_fscan_is_what_the_data_readme_states():
    movie = read_tekscan(FSCAN)
    assert (movie.rows, movie.cols, movie.n_frames) == (60, 21, 205)
    assert movie.seconds_per_frame == 0.032
    assert movie.units == "KPa"
    assert movie.start_frame == 1
    assert movie.stated_raw_sum is None
    assert not movie.times_from_file
    np.testing.assert_allclose(movie.frame_times_s, np.arange(205) * 0.032)
    assert movie.header["COMMENTS"] == "overground walk p10"
    assert movie.header["SATURATION_PRESSURE"] == "1514.73 KPa"
    assert movie.header["START_FRAME"] == "1"  # comments did not swallow the next key
    assert movie.totals().max() == 35819.0
    # 35 819 kPa-cells × 25.8064 mm² = 924.36 N at the peak.
    assert movie.force_n().max() == pytest.approx(924.36, abs=0.01)


@pytest.mark.parametrize("path", [FSCAN, ISCAN], ids=["fscan", "iscan"])
def test_sensel_area_matches_the_sensel_spacing(path):
    # The area comes from SENSEL_AREA (mm2 or cm2); the spacing lines check its conversion.
    movie = read_tekscan(path)
    row_mm = _spacing_mm(movie.header["ROW_SPACING"])
    col_mm = _spacing_mm(movie.header["COL_SPACING"])
    assert movie.sensel_area_m2 == pytest.approx(row_mm * col_mm * 1e-6, rel=1e-9)


@pytest.mark.parametrize("path", [FSCAN, ISCAN], ids=["fscan", "iscan"])
def test_cells_and_outline_are_those_of_the_text(path):
    lines = _lines(path)
    movie = read_tekscan(path)
    first = _line_no(lines, next(line for line in lines if line.startswith("Frame 1")))
    text_rows = [line.split(",") for line in lines[first : first + movie.rows]]
    outside = np.array([[cell == "B" for cell in row] for row in text_rows])
    np.testing.assert_array_equal(movie.outline, ~outside)
    np.testing.assert_array_equal(np.isnan(movie.frames[0]), outside)
    last = max(k for k, line in enumerate(lines) if line.startswith("Frame "))
    last_rows = [line.split(",") for line in lines[last + 1 : last + 1 + movie.rows]]
    expected = [[math.nan if c == "B" else float(c) for c in row] for row in last_rows]
    np.testing.assert_array_equal(movie.frames[-1], expected)
    assert not movie.frames.flags.writeable


def test_the_fscan_file_parses_well_under_a_second():
    # CPU time, not wall time: benchmark sessions share this machine.
    start = time.process_time()
    read_tekscan(FSCAN)
    assert time.process_time() - start < 1.0


def test_windows_line_endings_read_the_same(tmp_path):
    crlf = tmp_path / "crlf.csv"
    crlf.write_bytes(ISCAN.read_bytes().replace(b"\n", b"\r\n"))
    np.testing.assert_array_equal(read_tekscan(crlf).frames, read_tekscan(ISCAN).frames)


# --- units ----------------------------------------------------------------------------------


# Independent of the module's table: psi from the pound and the inch, mmHg within 1e-6 of torr.
PA_PER_UNIT = {"psi": 0.45359237 * 9.80665 / 0.0254**2, "MPa": 1e6, "mmHg": 101325 / 760}


@pytest.mark.parametrize("units", sorted(PA_PER_UNIT))
def test_other_pressure_units_are_converted(tmp_path, units):
    lines = [f"UNITS {units}" if line == "UNITS KPa" else line for line in _lines(FSCAN)]
    movie = read_tekscan(_write(tmp_path, lines))
    expected = movie.totals() * PA_PER_UNIT[units] * 25.8064e-6
    np.testing.assert_allclose(movie.force_n(), expected, rtol=1e-6)


def test_force_units_are_refused_not_guessed(tmp_path):
    lines = ["UNITS lbf" if line == "UNITS KPa" else line for line in _lines(FSCAN)]
    movie = read_tekscan(_write(tmp_path, lines))
    with pytest.raises(TekscanError, match="UNITS lbf cannot be turned into force.*KPa"):
        movie.force_n()


def test_a_calibration_is_refused_for_calibrated_units():
    with pytest.raises(TekscanError, match="already calibrated"):
        read_tekscan(FSCAN).force_n(n_per_raw=0.1)


def test_an_unknown_sensel_area_unit_is_an_error(tmp_path):
    lines = _lines(FSCAN)
    at = _line_no(lines, "SENSEL_AREA 25.8064 mm2")
    lines[at - 1] = "SENSEL_AREA 25.8064 furlongs2"
    _fails(_write(tmp_path, lines), at, "SENSEL_AREA")


# --- malformed files ------------------------------------------------------------------------


def test_a_malformed_header_line(tmp_path):
    lines = _lines(FSCAN)
    at = _line_no(lines, "ROWS 60")
    lines[at - 1] = "ROWS=60"
    _fails(_write(tmp_path, lines), at, "malformed header line 'ROWS=60'")


def test_a_non_integer_size(tmp_path):
    lines = _lines(FSCAN)
    at = _line_no(lines, "COLS 21")
    lines[at - 1] = "COLS 2l"
    _fails(_write(tmp_path, lines), at, "COLS is not an integer")


def test_a_missing_ascii_data_line(tmp_path):
    lines = _lines(FSCAN)
    del lines[_line_no(lines, "ASCII_DATA @@") - 1]
    _fails(_write(tmp_path, lines), _line_no(lines, "Frame 1"), "before the 'ASCII_DATA @@'")
    header_only = lines[: _line_no(lines, "Frame 1") - 1]
    _fails(_write(tmp_path, header_only, "header.asf"), None, "no 'ASCII_DATA @@' line")


@pytest.mark.parametrize("key", ["ROWS", "COLS"])
def test_a_missing_frame_size(tmp_path, key):
    lines = [line for line in _lines(FSCAN) if not line.startswith(f"{key} ")]
    _fails(_write(tmp_path, lines), None, f"no {key} in the header")


def test_a_frame_with_a_row_missing(tmp_path):
    lines = _lines(FSCAN)
    frame_3 = _line_no(lines, "Frame 3")
    del lines[frame_3 + 10]
    at = _line_no(lines, "Frame 4") - 1  # the blank line that ends frame 3 early
    _fails(_write(tmp_path, lines), at, f"frame 3 \\(line {frame_3}\\) has 59 rows, ROWS is 60")


def test_a_frame_with_a_row_too_many(tmp_path):
    lines = _lines(FSCAN)
    frame_3 = _line_no(lines, "Frame 3")
    lines.insert(frame_3, lines[frame_3])
    _fails(_write(tmp_path, lines), frame_3 + 61, "frame 3 has more than ROWS = 60 rows")


def test_a_row_with_a_cell_missing(tmp_path):
    lines = _lines(FSCAN)
    at = _line_no(lines, "Frame 7") + 30
    lines[at - 1] = lines[at - 1].split(",", 1)[1]
    _fails(_write(tmp_path, lines), at, "frame 7: 20 cells in a row, COLS is 21")


@pytest.mark.parametrize("cell", ["x", "", "nan", "inf", "1e"])
def test_a_non_numeric_cell(tmp_path, cell):
    lines = _lines(FSCAN)
    at = _line_no(lines, "Frame 100") + 40
    cells = lines[at - 1].split(",")
    cells[12] = cell
    lines[at - 1] = ",".join(cells)
    _fails(_write(tmp_path, lines), at, f"cell 13 is {cell!r}, not a number or B")


def test_a_missing_frame_in_the_middle(tmp_path):
    lines = _lines(FSCAN)
    start = _line_no(lines, "Frame 100") - 1
    del lines[start : start + 62]
    _fails(_write(tmp_path, lines), start + 1, "frame 101 where frame 100 was expected")


def test_fewer_frames_than_end_frame_with_the_closing_marker(tmp_path):
    lines = _lines(FSCAN)
    start = _line_no(lines, "Frame 205") - 1
    del lines[start:-2]  # keep the closing "@@" and the final newline
    at = _line_no(lines, "@@")
    _fails(_write(tmp_path, lines), at, "ends after frame 204 but END_FRAME is 205")


def test_a_raw_sum_that_disagrees_with_the_cells(tmp_path):
    lines = _lines(ISCAN)
    at = next(k for k, line in enumerate(lines) if line.startswith("Frame 42,")) + 1
    stated = int(lines[at - 1].rsplit(",", 1)[1])
    lines[at - 1] = lines[at - 1].rsplit(",", 1)[0] + f",{stated + 1}"
    _fails(
        _write(tmp_path, lines, "bad.csv"),
        at,
        f"frame 42 states Raw Sum {stated + 1} but its cells add up to {stated}",
    )


def test_text_after_the_closing_marker(tmp_path):
    lines = _lines(FSCAN) + ["Frame 206"]
    _fails(_write(tmp_path, lines), len(lines), "text after the closing @@")


# --- truncated files ------------------------------------------------------------------------


def _cut_in_the_last_frame(tmp_path: Path) -> Path:
    """The F-Scan file ending in the 25th row of frame 205, as a copy cut short would."""
    lines = _lines(FSCAN)
    return _write(tmp_path, lines[: _line_no(lines, "Frame 205") + 25])


def test_a_file_cut_inside_a_frame_is_an_error(tmp_path):
    path = _cut_in_the_last_frame(tmp_path)
    last = len(_lines(path))
    _fails(path, last, "no closing @@: the file is truncated.*allow_truncated")


def test_a_file_cut_at_a_frame_boundary_is_an_error_too(tmp_path):
    lines = [line for line in _lines(FSCAN) if line != "@@"]
    _fails(_write(tmp_path, lines), len(lines), "no closing @@")


def test_allow_truncated_drops_the_incomplete_frame_and_says_so(tmp_path):
    path = _cut_in_the_last_frame(tmp_path)
    with pytest.warns(
        TekscanTruncatedWarning, match="kept 204 complete frames of the 205.*dropped 1"
    ):
        movie = read_tekscan(path, allow_truncated=True)
    assert not movie.complete
    assert movie.n_frames == 204
    np.testing.assert_array_equal(movie.frames, read_tekscan(FSCAN).frames[:204])


def test_allow_truncated_still_warns_when_no_frame_is_dropped(tmp_path):
    lines = [line for line in _lines(FSCAN) if line != "@@"]
    with pytest.warns(TekscanTruncatedWarning, match="kept 205 complete frames"):
        movie = read_tekscan(_write(tmp_path, lines), allow_truncated=True)
    assert movie.n_frames == 205 and not movie.complete


def test_a_complete_file_gives_no_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_tekscan(FSCAN, allow_truncated=True).complete
