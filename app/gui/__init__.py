"""Experimenter GUI and subject dashboard (``steerlab gui``), docs/gui.md.

Model/view split: :mod:`app.gui.controller`, :mod:`app.gui.livedata`, :mod:`app.gui.quality`,
:mod:`app.gui.lpv_loader` and :mod:`app.gui.rig` are Qt-free; the widgets subscribe to them.
Engine events reach the Qt thread through the one signal of :class:`app.gui.bridge.EngineBridge`.
"""
