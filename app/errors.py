"""Errors that mean "your input is wrong" (exit 2, one message), not "Steerlab is broken".

Looked up lazily: a raised error's class comes from a module that is already imported, so the
command line never imports the analysis (or the hardware) stack just to know its error types.
"""

from __future__ import annotations

import sys

_USER_ERRORS = (
    ("steerlab.app.simulate", "SimulateError"),
    ("steerlab.app.run", "RunError"),
    ("steerlab.protocols.datafile", "DataFileError"),
    ("steerlab.protocols.writelock", "LockedError"),
    ("steerlab.protocols.names", "UnsafeNameError"),
    ("steerlab.protocols.interchange", "InterchangeError"),
    ("steerlab.protocols.protocol", "ProtocolError"),
    ("steerlab.analysis.report", "ReportError"),
    ("steerlab.analysis.study", "NoAnalysableTrialError"),
    ("steerlab.analysis.diagnosis", "DiagnosisError"),
    ("steerlab.hardware.can.config", "ConfigError"),
    ("steerlab.hardware.live", "RigError"),
    ("steerlab.analysis.rigcheck", "RigCheckError"),
    ("steerlab.app.rigcheck", "RigCheckRunError"),
    ("steerlab.analysis.executors", "SchedulerError"),
)


def is_user_error(exc: BaseException) -> bool:
    for module, name in _USER_ERRORS:
        cls = getattr(sys.modules.get(module), name, None)
        if isinstance(cls, type) and isinstance(exc, cls):
            return True
    return False
