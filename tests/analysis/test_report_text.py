"""How the report page writes numbers and the analysis's sentences (analysis.report)."""

from __future__ import annotations

import re

import pytest

from steerlab.analysis.report import _num, _p, _pm, _prose, _sci


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


def test_a_power_of_ten_is_never_ten_to_the_zero():
    assert _sci(1.234, 2) == "1.2" and _sci(9.99, 3) == "9.99"
    assert _sci(-3.2e-7, 3) == "-3.20 × 10⁻⁷"


@pytest.mark.parametrize(("lo", "hi"), [(1.07, 1.23), (4.4, 5.3), (0.0921, 0.113), (33.0, 38.0)])
def test_a_log_axis_within_a_decade_is_labelled_with_plain_numbers(lo, hi):
    """Matplotlib labels such an axis's minor ticks "1.1 × 10⁰"; the report's figures write
    ordinary magnitudes as the tables do."""
    from steerlab.analysis.figures import log_axes, new_figure

    fig = new_figure(3, 3)
    ax = fig.subplots()
    ax.plot([1, 2], [lo, hi])
    log_axes(ax, "y")
    ax.set_ylim(lo, hi)
    fig.canvas.draw()
    ticks = ax.yaxis.get_major_ticks() + ax.yaxis.get_minor_ticks()
    shown = [t.label1.get_text() for t in ticks if lo <= t.get_loc() <= hi]
    shown = [s for s in shown if s]
    assert shown and all(re.fullmatch(r"\d+(\.\d+)?", s) for s in shown), shown


def test_a_log_axis_keeps_powers_of_ten_outside_ordinary_magnitudes():
    from steerlab.analysis.figures import log_axes, new_figure

    fig = new_figure(3, 3)
    ax = fig.subplots()
    ax.plot([1, 2], [1e-8, 1e-2])
    log_axes(ax, "y")
    fig.canvas.draw()
    lo, hi = ax.get_ylim()
    shown = [t.get_text() for t in ax.get_yticklabels() if lo <= t.get_position()[1] <= hi]
    assert "$\\mathdefault{10^{-7}}$" in shown and "0.01" in shown, shown
