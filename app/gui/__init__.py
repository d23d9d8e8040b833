"""Experimenter GUI and subject dashboard (``steerlab gui``), docs/gui.md.

Model/view split: :mod:`app.gui.controller`, :mod:`app.gui.livedata`, :mod:`app.gui.quality`
and :mod:`app.gui.rig` are Qt-free; the widgets subscribe to them. The live panel's LPV model is
read by :mod:`analysis.lpv_results`, the reader the trackers' calibration uses too.
Engine events reach the Qt thread through the one signal of :class:`app.gui.bridge.EngineBridge`.
"""
