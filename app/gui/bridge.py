"""Engine events → the Qt thread, through one signal.

:class:`EngineBridge` is an engine subscriber. It is called on the engine thread; it hands
samples to :class:`~app.gui.livedata.LiveData` (a ring buffer the plots read on their own timer)
and re-emits every other event through its one signal ``event``, connected with a queued
connection so the slot runs on the GUI thread. Samples do not cross as events: the queue then
never grows with the data rate, and a slow GUI drops frames, not samples, and never blocks the
engine (a queued emit only posts the event).

The bridge never raises into the engine: a display fault must not abort a trial. It reports the
fault through the same signal as a :class:`BridgeFault`.
"""

from __future__ import annotations

import traceback
from dataclasses import dataclass

from PySide6.QtCore import QObject, Qt, Signal

import steerlab.app.gui.qt_compat  # noqa: F401 (PySide6 6.12 on Python 3.11: see that module)
from steerlab.app.gui.livedata import LiveData
from steerlab.protocols import events as ev


@dataclass(frozen=True)
class BridgeFault:
    message: str


class EngineBridge(QObject):
    # Not "event": that would hide QObject.event(), the handler Qt calls for every QEvent.
    engine_event = Signal(object)

    def __init__(self, live: LiveData, parent: QObject | None = None) -> None:
        super().__init__(parent)
        self.live = live
        self.n_blocks = 0
        self._faulted = False

    def connect_to(self, slot) -> None:
        # Explicitly queued: the slot must run on the GUI thread even if emit is on another.
        self.engine_event.connect(slot, Qt.ConnectionType.QueuedConnection)

    def __call__(self, event: object) -> None:
        if isinstance(event, ev.TrialStarted):
            self._faulted = False
        try:
            self.live(event)
        except Exception as e:
            if not self._faulted:  # once per trial: a fault per block would flood the queue
                self._faulted = True
                self.engine_event.emit(
                    BridgeFault(f"live display: {e!r}\n{traceback.format_exc()}")
                )
        if isinstance(event, ev.SamplesAcquired):
            self.n_blocks += 1
            return
        self.engine_event.emit(event)
