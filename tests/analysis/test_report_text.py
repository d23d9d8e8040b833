"""How the report page writes numbers and the analysis's sentences (analysis.report)."""

from __future__ import annotations

import pytest

from steerlab.analysis.report import _num, _p, _pm, _prose


@pytest.mark.parametrize(
    ("value", "sem", "text"),
    [
        (0.0999, 7.22e-4, "0.0999 ± 0.0007"),
        (0.894, 0.0197, "0.894 ± 0.020"),
        (54.2, 1.41, "54.2 ± 1.4"),
        (232.4, 6.80, "232 ± 7"),
        (6.06, 0.113, "6.06 ± 0.11"),
        (1.75, 0.482, "1.8 ± 0.5"),
        (0.0967, 6.49e-4, "0.0967 ± 0.0006"),
    ],
)
def test_value_and_sem_share_the_decimals_the_sem_supports(value, sem, text):
    assert _pm(value, sem) == text


def test_ordinary_magnitudes_are_never_in_scientific_notation():
    assert _num(8.15e-4) == "0.000815" and _num(123456.0) == "123456"
    assert _num(3.2e-7) == "3.20 × 10⁻⁷"  # a real power of ten, not 3.20e-07
    assert _p(2.8e-4) == "2.8 × 10⁻⁴" and _p(0.0123) == "0.012"
    assert "e-0" not in _pm(0.0999, 7.22e-4)


def test_program_notation_becomes_words():
    text = "the zeros are complex at ['BT18', 'BT12'], so de_caigny uses second_order; k_i"
    out = _prose(text)
    assert out == (
        "the zeros are complex at BT18, BT12, so de Caigny uses second-order; k<sub>i</sub>"
    )
    assert (
        _prose("'differs' is then no error; Steerlab's") == "‘differs’ is then no error; Steerlab's"
    )
    assert _prose("(the k_c_rises row)") == "(the “k<sub>c</sub> rises” row)"
