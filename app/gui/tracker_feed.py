"""Runs the online admittance tracker on every block of samples, in the engine's thread.

Qt-free. The GUI thread may drop frames; the tracker must see every sample, so it is an engine
subscriber (after the session writer) and the panel only reads its latest estimate. A display
aid never ends a trial: any error here is kept and shown, not raised.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from steerlab.protocols.events import SamplesAcquired, TrialStarted

if TYPE_CHECKING:  # imported when a trial starts, not when the GUI does
    from steerlab.analysis.tracking.online import AdmittanceEstimate, Method, OnlineTracker


class TrackerFeed:
    def __init__(self, method: Method = "grip_ekf") -> None:
        self.method: Method = method
        self.results_path: Path | None = None
        self.tracker: OnlineTracker | None = None
        self.estimate: AdmittanceEstimate | None = None  # the newest
        self.error: str | None = None

    def set_results(self, path: str | Path | None) -> None:
        """The report whose LPV operating points calibrate the tracker (next trial on)."""
        self.results_path = Path(path) if path else None

    def __call__(self, event: object) -> None:
        try:
            if isinstance(event, TrialStarted):
                self.tracker, self.estimate, self.error = None, None, None
                if self.results_path is not None:
                    from steerlab.analysis.tracking.online import OnlineTracker

                    fs = float(event.attributes["fs_hz"])
                    self.tracker = OnlineTracker.from_results(self.results_path, fs, self.method)
            elif isinstance(event, SamplesAcquired) and self.tracker is not None:
                self.estimate = self.tracker.update_block(event.channels)
        except Exception as e:  # shown by the panel; the trial goes on
            self.tracker, self.error = None, f"online tracker stopped: {e}"
