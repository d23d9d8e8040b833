"""Filtered derivatives of a sampled signal, at each sample: a Butterworth low-pass in
state-variable form whose states are the filtered signal and its derivatives.

A drive that reports only its angle (a SENSO-Wheel's rate field is 1 rpm coarse) needs θ̇ for
the wheel's velocity and θ̈ for a driver torque that has to subtract the rim's or the whole
wheel's inertia; differencing a quantised angle would turn its steps into noise.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import expm


class LowPassDerivatives:
    """A Butterworth low-pass H of order 2 or 4 in state-variable form, which gives the
    filtered signal and its first and second derivatives, all through the same H, exactly at
    each sample instant for the input between samples that ``hold`` names:

    - ``"linear"``: a signal continuous between its samples (the angle); taken as a staircase
      instead, its steps would put a ripple of slope × half a sample into the second
      derivative, amplified by ω²;
    - ``"step"``: a value really held from one sample to the next (the torque command, which
      the drive applies from its 0x201 until the next one).

    The second derivative needs order 4: at order 2, H·s² does not fall above the cutoff, so
    the angle's quantization noise (0.009°) reaches θ̈ whole, ω² times (about 3 rad/s² rms at
    40 Hz); at order 4 H·s² falls as 1/ω² and the same noise gives about 0.5 rad/s² at 40 Hz,
    0.1 at 20 Hz (it grows as the cutoff to the power 2.5). The price is delay: below the
    cutoff H delays by Σ 2ζ/ω over its sections, 5.6 ms at 40 Hz for order 2, 10.4 ms for
    order 4; its gain is 0.71 at the cutoff, 0.97 (order 2) or 0.998 (order 4) at half of it.
    Exact discretization keeps it stable at any cutoff below the Nyquist frequency."""

    def __init__(self, cutoff_hz: float, dt_s: float, hold: str = "linear", order: int = 2):
        if hold not in ("linear", "step"):
            raise ValueError(f"hold must be 'linear' or 'step', not {hold!r}")
        if order not in (2, 4):
            raise ValueError(f"order must be 2 or 4, not {order!r}")
        w = 2.0 * math.pi * cutoff_hz
        self.cutoff_hz, self.hold, self.order = cutoff_hz, hold, order
        # Butterworth sections s² + 2ζωs + ω²: ζ = cos(π/4); or cos(π/8), cos(3π/8)
        self._zetas = (
            (math.cos(math.pi / 4),)
            if order == 2
            else (math.cos(math.pi / 8), math.cos(3 * math.pi / 8))
        )
        self._w = w
        self._w2 = w * w
        self._2zw = 2.0 * self._zetas[-1] * w  # the last section's, for its second derivative
        self._dt = dt_s
        # states: per section (y, y'), the last section last; then the input u and its slope v
        n = 2 * len(self._zetas)
        m = np.zeros((n + 2, n + 2))
        source = n  # the first section is driven by u
        for k, zeta in enumerate(self._zetas):
            i = 2 * k
            m[i, i + 1] = 1.0
            m[i + 1, i], m[i + 1, i + 1], m[i + 1, source] = -w * w, -2.0 * zeta * w, w * w
            source = i  # the next section is driven by this one's output
        m[n, n + 1] = 1.0
        e = expm(m * dt_s)
        self._n = n
        self._phi = [[float(e[i, j]) for j in range(n)] for i in range(n)]
        self._gu = [float(e[i, n]) for i in range(n)]  # from u at the interval's start
        self._gv = [float(e[i, n + 1]) for i in range(n)]  # from its slope
        self._x = [0.0] * n
        self._u = 0.0
        self._started = False

    def reset(self) -> None:
        self._started = False

    def step(self, u: float) -> tuple[float, float, float]:
        """Feed the sample at the end of an interval; (filtered, its derivative, its second
        derivative) at that instant."""
        u = float(u)
        n = self._n
        if not self._started:  # start at rest on the first value: no start-up transient
            self._x = [u if i % 2 == 0 else 0.0 for i in range(n)]
            self._u, self._started = u, True
        if self.hold == "linear":
            start, slope = self._u, (u - self._u) / self._dt
        else:  # u held over the interval that ends now
            start, slope = u, 0.0
        x, phi, gu, gv = self._x, self._phi, self._gu, self._gv
        x = [
            sum(phi[i][j] * x[j] for j in range(n)) + gu[i] * start + gv[i] * slope
            for i in range(n)
        ]
        self._x, self._u = x, u
        y, dy = x[n - 2], x[n - 1]
        drive = u if n == 2 else x[n - 4]  # what drives the last section
        return y, dy, self._w2 * (drive - y) - self._2zw * dy

    def response(self, f_hz: float) -> complex:
        """H at ``f_hz``."""
        s = 2j * math.pi * f_hz
        h = 1.0 + 0j
        for zeta in self._zetas:
            h *= self._w2 / (s * s + 2.0 * zeta * self._w * s + self._w2)
        return h
