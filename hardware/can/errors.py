"""The errors a drive of any kind raises (:mod:`hardware.drives`)."""

from __future__ import annotations


class DriveError(RuntimeError):
    """The drive could not do what was asked."""


class DriveEnableError(DriveError):
    """enable() failed; the message says at which step and what the drive answered."""
