"""The live panel's LPV model from a report's ``results.json``: the one reader in
:mod:`analysis.lpv_results`, which the trackers' calibration uses too. Qt-free."""

from analysis.lpv_results import (
    DEFAULT_ORDER,
    LoadedLPV,
    LPVLoadError,
    load_lpv_model,
    lpv_from_document,
)

__all__ = ["DEFAULT_ORDER", "LPVLoadError", "LoadedLPV", "load_lpv_model", "lpv_from_document"]
