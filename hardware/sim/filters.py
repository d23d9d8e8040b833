"""The first-order recursive filter of the simulated world's noise and behaviour schedules.

``scipy.signal.lfilter`` did this before; importing ``scipy.signal`` (which imports
``scipy.stats``) took 1.25 s of every process that simulates (the CLI, the simulated lab's and
the loop's processes), more than everything else they import. This is the same recursion in
the same floating-point order (lfilter's transposed direct form II), so the results are
bit-identical; tests/hardware/test_sim_filters.py checks that against scipy.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _first_order(b0: float, a1: float, x: np.ndarray, z: float) -> tuple[np.ndarray, float]:
    y = np.empty_like(x)
    for n in range(x.shape[0]):
        yn = z + b0 * x[n]
        y[n] = yn
        z = 0.0 * x[n] - a1 * yn  # lfilter's state update with b1 = 0
    return y, z


def first_order_lfilter(
    b0: float, a1: float, x: np.ndarray, zi: float
) -> tuple[np.ndarray, np.ndarray]:
    """``lfilter([b0], [1, a1], x, zi=[zi])``: y[k] = b0 x[k] − a1 y[k−1], from the filter state
    ``zi``; returns (y, final state as a length-1 array), as lfilter does."""
    y, z = _first_order(float(b0), float(a1), np.ascontiguousarray(x, dtype=float), float(zi))
    return y, np.array([z])
