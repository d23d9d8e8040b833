"""The faults a drive's driver has recorded: a bounded history of every one, and the active ones
since the last clear, one per cause. A cause that keeps failing (a frame not sent every cycle)
is one active fault, not thousands."""

from __future__ import annotations

import collections
import threading
from typing import Generic, TypeVar

F = TypeVar("F")


class FaultLog(Generic[F]):
    """Thread-safe: the receive thread, the loop and a watchdog all record."""

    def __init__(self, history: int) -> None:
        self._lock = threading.Lock()
        self._history: collections.deque[F] = collections.deque(maxlen=history)
        self._active: dict[tuple[str, object], F] = {}

    def add(self, fault: F, kind: str, key: object) -> bool:
        """Record ``fault``; False (nothing recorded) when its cause ``(kind, key)`` is active
        already. ``key`` None: every such fault is a cause of its own."""
        with self._lock:
            cause = (kind, key) if key is not None else (kind, id(fault))
            if key is not None and cause in self._active:
                return False
            self._active[cause] = fault
            self._history.append(fault)
            return True

    def clear(self, kind: str | None = None) -> None:
        """Forget the active faults (of ``kind`` only, if given); the history keeps them."""
        with self._lock:
            if kind is None:
                self._active.clear()
            else:
                self._active = {c: f for c, f in self._active.items() if c[0] != kind}

    @property
    def active(self) -> tuple[F, ...]:
        """Active faults, oldest first."""
        with self._lock:
            return tuple(self._active.values())

    @property
    def history(self) -> tuple[F, ...]:
        """Every fault recorded (most recent last, bounded)."""
        with self._lock:
            return tuple(self._history)
