"""Names that come from data (subject, condition, trial) are data, never paths.

Every such name is checked against :data:`SAFE_NAME` where it enters Steerlab (protocol loader,
interchange import, the GUI's session start, a session file being read), so it can be used as a
file name and an HDF5 group name as it is: no ``/``, no ``..``, no NUL, no control or white-space
characters, not empty, at most 64 characters.

:func:`inside` checks that a path Steerlab is about to write lies inside the output folder,
without following a symbolic link out of it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}")
RULE = "1–64 characters: letters, digits, '_', '-', '.', '+', starting with a letter or digit"


class UnsafeNameError(ValueError):
    pass


def check_name(value: object, what: str) -> str:
    """``value`` if it is a safe name, else :class:`UnsafeNameError` saying why (``what`` names
    the field, e.g. ``"fast.toml: [[conditions]] #2.name"``)."""
    if not isinstance(value, str):
        raise UnsafeNameError(f"{what}: expected a name (a string), got {value!r}")
    if SAFE_NAME.fullmatch(value) is None:
        raise UnsafeNameError(f"{what}: {value!r} is not a safe name ({RULE})")
    return value


def inside(root: str | Path, path: str | Path) -> Path:
    """``path`` if writing it cannot land outside ``root``; else :class:`UnsafeNameError`.

    ``path`` must be lexically inside ``root``; no component between them may be a symbolic
    link (an existing link at ``path`` itself counts: writing through it would follow it).
    """
    root_p = Path(os.path.abspath(root))
    p = Path(os.path.abspath(path))
    try:
        rel = p.relative_to(root_p)
    except ValueError:
        raise UnsafeNameError(f"{path}: outside the output folder {root}; not writing it") from None
    if ".." in rel.parts:
        raise UnsafeNameError(f"{path}: outside the output folder {root}; not writing it")
    cur = root_p
    for part in rel.parts:
        cur = cur / part
        if cur.is_symlink():
            raise UnsafeNameError(
                f"{cur}: is a symbolic link inside the output folder {root}; not writing through "
                "it (remove it, or choose another --out)"
            )
    return p
