"""Errors that mean "your input is wrong" (exit 2, one message), not "Steerlab is broken"."""

from __future__ import annotations

from analysis.report import ReportError
from app.run import USER_ERRORS as RUN_ERRORS
from app.simulate import SimulateError
from protocols.datafile import DataFileError
from protocols.interchange import InterchangeError
from protocols.protocol import ProtocolError

USER_ERRORS: tuple[type[Exception], ...] = (
    SimulateError,
    DataFileError,
    InterchangeError,
    ProtocolError,
    ReportError,
    *RUN_ERRORS,
)
