"""Steerlab: experiment control, data acquisition and analysis for haptic steering-wheel
admittance studies (Pronker, Abbink, van Paassen & Mulder 2017).

Everything is reached as ``steerlab.<package>``: ``steerlab.app`` (CLI and GUI),
``steerlab.hardware`` (drivers, transports, simulated devices), ``steerlab.protocols``
(perturbation design, Latin square, session engine), ``steerlab.analysis`` and
``steerlab.benchmarks``.

In the repository the subpackages live in top-level folders (``app/``, ``analysis/``, ...);
an installed wheel holds them inside ``steerlab/`` (see ``setup.py``). When this package is
imported from a source checkout that was not installed (``pytest`` from the repository, or
``python -m steerlab`` in its root), the checkout's root is added to the package's search path
so that ``steerlab.analysis`` resolves to ``analysis/``.
"""

from __future__ import annotations

from importlib import metadata as _metadata
from pathlib import Path as _Path

try:
    __version__ = _metadata.version("steerlab")
except _metadata.PackageNotFoundError:  # a source checkout that was never installed
    __version__ = "0+unknown"

_checkout = _Path(__file__).resolve().parent.parent
if (_checkout / "pyproject.toml").is_file() and (_checkout / "analysis" / "__init__.py").is_file():
    if str(_checkout) not in __path__:
        __path__.append(str(_checkout))
