"""``steerlab gui``: the experimenter window and the subject dashboard."""

from __future__ import annotations

import os
import sys
from collections.abc import MutableMapping

from steerlab.app.gui.rig import RigError, check_rig_path
from steerlab.app.gui.system_libs import (
    check_xcb,
    missing_libraries_message,
    no_display,
    uses_xcb,
)
from steerlab.protocols.protocol import load_protocol

#: The GIL switch interval while the GUI runs, s. Python's default (5 ms) lets the GUI thread
#: hold the interpreter for up to 5 ms while the control loop waits for its next 1 ms cycle;
#: at 0.2 ms a plot redraw delays a cycle by at most about that (docs/gui.md, benchmark).
GUI_SWITCH_INTERVAL_S = 0.0002


def configure_process(loop_in_process: bool = True) -> None:
    """Process-wide settings; ``loop_in_process``: the control loop shares this process (the
    built-in simulated rig). A rig file's loop has a process of its own, and Python's default
    switch interval spares the GUI thread needless hand-overs of the interpreter."""
    import pyqtgraph as pg

    if loop_in_process:
        sys.setswitchinterval(GUI_SWITCH_INTERVAL_S)
    pg.setConfigOptions(antialias=False, background="w", foreground="k")


def choose_platform(environ: MutableMapping[str, str] | None = None) -> str | None:
    """None if Qt can start here; else the message that says what to install.

    Runs before any Qt GUI module is loaded: a missing X11 library would otherwise abort the
    interpreter inside ``QApplication`` with a hint naming one package. In a Wayland session
    whose Wayland plugin loads, the GUI falls back to it (QT_QPA_PLATFORM=wayland) and says why.
    """
    env = os.environ if environ is None else environ
    if not uses_xcb(env):
        return None
    xcb = check_xcb()
    if xcb.ok:
        return None
    message = missing_libraries_message(xcb)
    if env.get("WAYLAND_DISPLAY") and check_xcb(platform="wayland").ok:
        env["QT_QPA_PLATFORM"] = "wayland"
        print(f"steerlab gui: note: {message}\nUsing Wayland instead.", file=sys.stderr)
        return None
    return message


def run_gui(rig: str | None, out: str, protocol: str | None) -> int:
    """Open the windows and run until the experimenter window is closed; the exit code."""
    reason = no_display()
    if reason is not None:  # before anything else: Qt would abort the interpreter
        print(f"steerlab gui: {reason}", file=sys.stderr)
        return 2
    proto = load_protocol(protocol)  # ProtocolError: the CLI prints it (exit 2)
    try:
        check_rig_path(rig)
    except RigError as e:
        print(f"steerlab gui: error: {e}", file=sys.stderr)
        return 2
    problem = choose_platform()
    if problem is not None:
        print(f"steerlab gui: error: {problem}", file=sys.stderr)
        return 2

    from PySide6.QtCore import Qt
    from PySide6.QtWidgets import QApplication

    from steerlab.app.gui.dashboard import SubjectDashboard
    from steerlab.app.gui.session_window import ExperimenterWindow, dashboard_span

    configure_process(loop_in_process=rig is None)
    # As `steerlab run` does: the loop's and the lab's processes inherit it, and numba then
    # writes no terminal escape codes as they end.
    os.environ.setdefault("NUMBA_DISABLE_ERROR_MESSAGE_HIGHLIGHTING", "1")
    app = QApplication.instance() or QApplication(sys.argv[:1])
    if not isinstance(app, QApplication):
        raise RuntimeError("steerlab gui: this process already runs a Qt application without a GUI")
    dashboard = SubjectDashboard(span_deg=dashboard_span(proto))
    win = ExperimenterWindow(proto, out, rig_path=rig, dashboard=dashboard)
    win.show()
    dashboard.show()
    win.place_windows()  # the dashboard beside this window or on the second screen, never over it
    app.setQuitOnLastWindowClosed(False)
    # The experimenter window owns the session: closing it ends the program (and closes the
    # dashboard); closing the dashboard alone does not.
    win.destroyed.connect(app.quit)
    win.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose, True)
    return int(app.exec())
