"""The simulated world's first-order filter against scipy's lfilter, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from steerlab.hardware.sim.filters import first_order_lfilter


@pytest.mark.parametrize("a", [0.0, 0.3, 0.999, -0.5])
def test_same_bits_as_lfilter(a):
    rng = np.random.default_rng(7)
    x = rng.standard_normal(5000) * 10.0 ** rng.uniform(-3, 3, 5000)
    b0, zi = np.sqrt(1 - a * a), rng.standard_normal()
    want, want_zf = lfilter([b0], [1.0, -a], x, zi=[zi])
    got, got_zf = first_order_lfilter(b0, -a, x, zi)
    assert np.array_equal(got, want) and np.array_equal(got_zf, want_zf)
    # The schedules' form: y[k] = y[k−1] + a (x[k] − y[k−1]).
    want, _ = lfilter([a], [1.0, a - 1.0], x, zi=[(1.0 - a) * zi])
    got, _ = first_order_lfilter(a, a - 1.0, x, (1.0 - a) * zi)
    assert np.array_equal(got, want)


def test_a_simulating_process_does_not_import_scipy_signal():
    import subprocess
    import sys

    code = (
        "import sys, steerlab.app.simulate, steerlab.hardware.sim.lab;"
        "print('scipy.signal' in sys.modules)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"
