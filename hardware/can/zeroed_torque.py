"""A drive's driver-torque channel, zeroed from the values of the cycles just run.

Whatever gives the torque (a sensor in a drive's PDO, a sensor node, a SENSO-Wheel's hand
sensor, a reconstruction), the offset is measured the same way: with the wheel released and the
loop running, the mean of the values the last cycles latched.
"""

from __future__ import annotations

import collections
from collections.abc import Callable

from .errors import DriveError


class ZeroedTorque:
    """:class:`hardware.interfaces.ColumnTorque` over ``latest`` (the value the last cycle
    latched) and ``recent`` (the values of the cycles before it, newest last)."""

    def __init__(
        self, latest: Callable[[], float], recent: collections.deque[float], what: str
    ) -> None:
        self._latest = latest
        self._recent = recent
        self._what = what
        self.offset_nm = 0.0

    def read(self) -> float:
        return self._latest() - self.offset_nm

    def clear_recent(self) -> None:
        """Forget earlier values: the next zero() sees only the cycles that follow."""
        self._recent.clear()

    def zero(self) -> None:
        """:raises DriveError: no value received yet (zero() needs sync() running)."""
        samples = list(self._recent)
        if not samples:
            raise DriveError(f"no {self._what} received yet; zero() needs sync() running")
        self.offset_nm = sum(samples) / len(samples)
