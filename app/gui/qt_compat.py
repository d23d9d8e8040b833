"""Work around a reference-count bug of PySide6 6.12 on CPython 3.11. Imported for its effect.

PySide6-Essentials 6.12.0 returns ``None`` from every void method, and ``True``/``False`` from
``Signal.emit``, without taking a reference. From CPython 3.12 on these objects are immortal
(PEP 683) and nothing happens; on 3.11 each call takes one reference away, and when the count
reaches zero the interpreter aborts ("Fatal Python error: none_dealloc" / "bool_dealloc").
Measured in the experimenter window during a trial: about 900–2700 references to ``None`` lost
per second, from about 60 000: a hard crash a minute into a session. PySide6 6.11.3 does not
have the bug.

The real fix is a dependency pin (``PySide6-Essentials<6.12`` on Python < 3.12, or Python ≥
3.12). Until then, :func:`protect` detects the bug with a probe and, only if it is present,
gives the three singletons a reference count no session can use up, which is what CPython 3.12
does for them.
"""

from __future__ import annotations

import ctypes
import sys

from PySide6.QtCore import QObject

_HEADROOM = 1 << 40  # at 10⁴ lost references per second: ~3500 years
_protected = False


def has_refcount_bug(calls: int = 200) -> bool:
    """True if calling a void PySide6 method loses references to ``None``."""
    if sys.version_info >= (3, 12):
        return False
    probe = QObject()
    before = sys.getrefcount(None)
    for _ in range(calls):
        probe.setObjectName("steerlab-probe")
    return sys.getrefcount(None) - before <= -calls // 2


def protect() -> bool:
    """Apply the workaround if needed (idempotent); True if it was applied in this process."""
    global _protected
    if _protected:
        return True
    if not has_refcount_bug():
        return False
    for obj in (None, True, False):
        # ob_refcnt is the first field of every CPython object (Include/object.h).
        ctypes.c_ssize_t.from_address(id(obj)).value += _HEADROOM
    _protected = True
    return True


protect()
