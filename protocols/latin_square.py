"""Balanced Latin squares (Williams 1949) for counterbalancing condition order.

For an even number of conditions n, n rows suffice: every condition appears once in every
position, and every condition is immediately followed by every other exactly once. For odd n
the square and its mirror image together (2n rows) give that balance.
"""

from __future__ import annotations


def williams_square(n: int) -> list[list[int]]:
    """Rows of condition indices 0..n-1."""
    if n < 1:
        raise ValueError(f"a Latin square needs at least one condition, got {n}")
    # First row 0, 1, n-1, 2, n-2, ...: the successive differences then take every value once.
    first = [0]
    lo, hi = 1, n - 1
    for j in range(1, n):
        if j % 2 == 1:
            first.append(lo)
            lo += 1
        else:
            first.append(hi)
            hi -= 1
    rows = [[(c + r) % n for c in first] for r in range(n)]
    if n % 2 == 1:
        rows += [list(reversed(row)) for row in rows]
    return rows


def subject_row(subject_number: int, n_conditions: int) -> int:
    """Latin-square row for a subject (numbered from 1): subjects 1..n take rows 0..n-1."""
    if subject_number < 1:
        raise ValueError(f"subject numbers start at 1, got {subject_number}")
    return (subject_number - 1) % len(williams_square(n_conditions))


def condition_order(subject_number: int, conditions: list[str]) -> tuple[int, list[str]]:
    """(row, conditions in the order this subject performs them)."""
    square = williams_square(len(conditions))
    row = subject_row(subject_number, len(conditions))
    return row, [conditions[i] for i in square[row]]
