"""Errors that mean "your input is wrong" (exit 2, one message), not "Steerlab is broken".

Looked up lazily: a raised error's class comes from a module that is already imported, so the
command line never imports the analysis (or the hardware) stack just to know its error types.
"""

from __future__ import annotations

import sys

_USER_ERRORS = (
    ("app.simulate", "SimulateError"),
    ("app.run", "RunError"),
    ("protocols.datafile", "DataFileError"),
    ("protocols.writelock", "LockedError"),
    ("protocols.names", "UnsafeNameError"),
    ("protocols.interchange", "InterchangeError"),
    ("protocols.protocol", "ProtocolError"),
    ("analysis.report", "ReportError"),
    ("analysis.study", "NoAnalysableTrialError"),
    ("analysis.diagnosis", "DiagnosisError"),
    ("hardware.can.config", "ConfigError"),
    ("hardware.live", "RigError"),
    ("analysis.rigcheck", "RigCheckError"),
    ("app.rigcheck", "RigCheckRunError"),
)


def is_user_error(exc: BaseException) -> bool:
    for module, name in _USER_ERRORS:
        cls = getattr(sys.modules.get(module), name, None)
        if isinstance(cls, type) and isinstance(exc, cls):
            return True
    return False
