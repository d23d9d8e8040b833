"""``steerlab gui``: the experimenter window and the subject dashboard."""

from __future__ import annotations

import sys

from steerlab.app.gui.rig import RigError, check_rig_path
from steerlab.protocols.protocol import load_protocol

#: The GIL switch interval while the GUI runs, s. Python's default (5 ms) lets the GUI thread
#: hold the interpreter for up to 5 ms while the control loop waits for its next 1 ms cycle;
#: at 0.2 ms a plot redraw delays a cycle by at most about that (docs/gui.md, benchmark).
GUI_SWITCH_INTERVAL_S = 0.0002


def configure_process() -> None:
    """Process-wide settings for a GUI that shares its process with the control loop."""
    import pyqtgraph as pg

    sys.setswitchinterval(GUI_SWITCH_INTERVAL_S)
    pg.setConfigOptions(antialias=False, background="w", foreground="k")


def run_gui(rig: str | None, out: str, protocol: str | None) -> int:
    """Open the windows and run until the experimenter window is closed; the exit code."""
    proto = load_protocol(protocol)  # ProtocolError: the CLI prints it (exit 2)
    try:
        check_rig_path(rig)
    except RigError as e:
        print(f"steerlab gui: error: {e}", file=sys.stderr)
        return 2

    from PySide6.QtCore import Qt
    from PySide6.QtWidgets import QApplication

    from steerlab.app.gui.dashboard import SubjectDashboard
    from steerlab.app.gui.session_window import ExperimenterWindow, dashboard_span

    configure_process()
    app = QApplication.instance() or QApplication(sys.argv[:1])
    dashboard = SubjectDashboard(span_deg=dashboard_span(proto))
    win = ExperimenterWindow(proto, out, rig_path=rig, dashboard=dashboard)
    win.show()
    dashboard.show()
    app.setQuitOnLastWindowClosed(False)
    # The experimenter window owns the session: closing it ends the program (and closes the
    # dashboard); closing the dashboard alone does not.
    win.destroyed.connect(app.quit)
    win.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose, True)
    return int(app.exec())
