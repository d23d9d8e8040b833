"""Strict JSON from analysis results: one cleaner for results.json and diagnosis.json.

Light on purpose (numpy only): the diagnosis uses it without the report's pandas.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np


def json_clean(x: Any) -> Any:
    """Strict JSON: numpy scalars and arrays to Python, NaN and infinities to None."""
    if isinstance(x, dict):
        return {str(k): json_clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [json_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_clean(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x
