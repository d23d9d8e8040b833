from __future__ import annotations

import itertools

import pytest

from steerlab.protocols.latin_square import condition_order, williams_square
from steerlab.protocols.session import build_plan


@pytest.mark.parametrize("n", [2, 4, 6, 8])
def test_williams_even(n):
    rows = williams_square(n)
    assert len(rows) == n
    for pos in range(n):
        assert sorted(r[pos] for r in rows) == list(range(n)), "each condition once per position"
    for r in rows:
        assert sorted(r) == list(range(n))
    pairs = [(r[i], r[i + 1]) for r in rows for i in range(n - 1)]
    assert sorted(pairs) == sorted(itertools.permutations(range(n), 2)), (
        "every condition immediately followed by every other exactly once"
    )


@pytest.mark.parametrize("n", [3, 5])
def test_williams_odd_needs_mirror(n):
    rows = williams_square(n)
    assert len(rows) == 2 * n
    pairs = [(r[i], r[i + 1]) for r in rows for i in range(n - 1)]
    for a, b in itertools.permutations(range(n), 2):
        assert pairs.count((a, b)) == 2


def test_rows_from_subject_number():
    conds = ["RT", "BT18", "BT12", "BT8", "BT5", "PT"]
    orders = [condition_order(s, conds)[1] for s in range(1, 7)]
    assert len({tuple(o) for o in orders}) == 6
    assert condition_order(7, conds) == condition_order(1, conds)
    assert condition_order(1, conds)[1] == ["RT", "BT18", "PT", "BT12", "BT5", "BT8"]
    with pytest.raises(ValueError, match="start at 1"):
        condition_order(0, conds)


def test_session_plan(default_protocol):
    plan = build_plan(default_protocol, 3)
    assert plan.subject == "S03" and plan.latin_square_row == 2
    assert len(plan.trials) == 18
    assert [t.trial_index for t in plan.trials] == list(range(1, 19))
    for k, cond in enumerate(plan.condition_order):
        block = plan.trials[3 * k : 3 * k + 3]
        assert [t.condition for t in block] == [cond] * 3
        assert [(t.familiarization, t.repetition) for t in block] == [
            (True, 0),
            (False, 1),
            (False, 2),
        ]
    setup = plan.setup(plan.trials[0])
    fs = default_protocol.loop_rate_hz
    assert setup.measured_start == 5 * fs and setup.measured_stop == 50 * fs
    tp = setup.perturbation_nm
    assert len(tp) == 51 * fs
    # Fade-in from zero, fade-out to zero: no torque step at either end.
    assert tp[0] == 0.0 and abs(tp[-1]) < 1e-3
    assert abs(tp[1] - tp[0]) < 1e-3
    # The measured period is exactly one period of the design, starting at phase 0.
    seg = tp[setup.measured_start : setup.measured_stop]
    assert abs(seg.std() - 2.26) < 0.02
    assert max(abs(seg - plan.design.one_period(fs))) < 1e-9
