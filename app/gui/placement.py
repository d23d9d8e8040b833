"""Where the subject's window goes when both windows share one screen. Qt-free.

Without a window manager (a lab PC started straight into X, Xvfb) every new window opens at
the screen's top-left corner, so the subject's dashboard would cover the experimenter's
window and its EMERGENCY STOP. With a second screen the dashboard goes there (the subject's
monitor); on one screen the two windows are put side by side, experimenter on the left (the
stop button is at its top-left), dashboard in the column to its right.

Rectangles are ``(x, y, width, height)`` in screen pixels, frames included.
"""

from __future__ import annotations

Rect = tuple[int, int, int, int]

#: The dashboard is never made narrower than this to make room (ours: its ±30° scale stays
#: readable at about 6 px per degree).
MIN_DASHBOARD_WIDTH = 360
GAP = 8


def overlaps(a: Rect, b: Rect) -> bool:
    ax, ay, aw, ah = a
    bx, by, bw, bh = b
    return ax < bx + bw and bx < ax + aw and ay < by + bh and by < ay + ah


def side_by_side(
    screen: Rect,
    experimenter: tuple[int, int],
    experimenter_min: tuple[int, int],
    dashboard: tuple[int, int],
) -> tuple[Rect, Rect]:
    """(experimenter rect, dashboard rect) on one screen, not overlapping if it can be done.

    The experimenter window keeps its size if the dashboard fits beside it at
    ``MIN_DASHBOARD_WIDTH`` or more; otherwise it shrinks, down to its minimum. The dashboard
    takes the rest of the width (up to its own size). On a screen too small for both at their
    minimum the dashboard is put against the right edge: it then covers the experimenter
    window's right side, never its top-left, where the stop button is.
    """
    sx, sy, sw, sh = screen
    ew, eh = experimenter
    emin_w, emin_h = experimenter_min
    dw, dh = dashboard
    ew = max(emin_w, min(ew, sw - GAP - MIN_DASHBOARD_WIDTH))
    eh = max(emin_h, min(eh, sh))
    free = sw - ew - GAP
    dw = min(dw, max(free, MIN_DASHBOARD_WIDTH))
    dh = min(dh, sh)
    dx = sx + ew + GAP if free >= dw else sx + sw - dw
    return (sx, sy, ew, eh), (dx, sy, dw, dh)
