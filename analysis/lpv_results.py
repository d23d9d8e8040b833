"""Read the LPV admittance model back from a report's ``results.json``.

One reader for everything that takes the model from a report: the GUI's live panel
(:mod:`app.gui.live_admittance`) and the trackers' calibration
(:meth:`analysis.tracking.Calibration.from_results`), so both fit the same polynomials from the
same points, in the report's ``lpv.order``.

Only the operating points are needed: ``(condition, mu_N, parameters)`` per condition,
as ``analysis.pipeline.StudyResults.lpv_dict`` writes them under ``lpv.operating_points``
(docs/results.md). From those the physical-parameter LPV model (the interpolation the paper's
discussion recommends, :class:`analysis.lpv.PhysicalLPV`) is refitted here: it is cheap, and it
is then evaluated with the GUI's own μ outside the report's range rules (clipped to the
operating points' range).

Accepted shapes: the whole ``results.json``; ``{"operating_points": [...]}``; or a bare list of
``{"condition", "mu_N", "parameters"}``. A parameter may be a number or ``{"value": number}``.
Points with ``"included": false`` (RT, for the paper's reasons) are left out.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from steerlab.analysis.lpv import PARAMETER_NAMES, OperatingPoint, PhysicalLPV

DEFAULT_ORDER = 2  # the paper's polynomial order


class LPVLoadError(ValueError):
    """The file holds no usable LPV model; the message says why."""


@dataclass(frozen=True)
class LoadedLPV:
    model: PhysicalLPV
    source: str
    conditions: tuple[str, ...]
    excluded: tuple[str, ...]
    order: int

    @property
    def mu_range(self) -> tuple[float, float]:
        return self.model.mu_range

    def describe(self) -> str:
        lo, hi = self.mu_range
        ex = f"; left out: {', '.join(self.excluded)}" if self.excluded else ""
        return (
            f"{Path(self.source).name}: physical LPV, order {self.order}, "
            f"{', '.join(self.conditions)} (μ {lo:.0f}–{hi:.0f} N){ex}"
        )


def _number(v: Any, where: str) -> float:
    if isinstance(v, dict):
        v = v.get("value")
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise LPVLoadError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def _points_list(doc: Any, where: str) -> tuple[list, int | None, str | None]:
    if isinstance(doc, list):
        return doc, None, None
    if not isinstance(doc, dict):
        raise LPVLoadError(f"{where}: expected a JSON object or list")
    lpv = doc.get("lpv", doc)
    if lpv is None:
        raise LPVLoadError(f"{where}: the report has no LPV section")
    if not isinstance(lpv, dict) or "operating_points" not in lpv:
        raise LPVLoadError(f"{where}: no lpv.operating_points (is this a report's results.json?)")
    pts = lpv["operating_points"]
    if not isinstance(pts, list):
        raise LPVLoadError(f"{where}: lpv.operating_points must be a list")
    order = lpv.get("order")
    return pts, order if isinstance(order, int) else None, lpv.get("error")


@dataclass(frozen=True)
class ReportPoints:
    """The operating points a report lists, before any model is fitted."""

    points: list[OperatingPoint]  # the included ones
    excluded: tuple[str, ...]  # conditions marked ``"included": false``
    order: int  # the report's polynomial order, lowered to what the points can carry


def points_from_document(doc: Any, source: str = "<results>") -> ReportPoints:
    """The included operating points and the polynomial order to fit them with."""
    raw, order, error = _points_list(doc, source)
    points, excluded = [], []
    for i, p in enumerate(raw):
        where = f"{source}: operating point #{i + 1}"
        if not isinstance(p, dict):
            raise LPVLoadError(f"{where}: expected an object")
        cond = str(p.get("condition", f"#{i + 1}"))
        if p.get("included") is False:
            excluded.append(cond)
            continue
        params = p.get("parameters")
        if not isinstance(params, dict):
            raise LPVLoadError(f"{where} ({cond}): no parameters")
        missing = [k for k in PARAMETER_NAMES if k not in params]
        if missing:
            raise LPVLoadError(f"{where} ({cond}): parameters miss {missing}")
        vals = {k: _number(params[k], f"{where} ({cond}).{k}") for k in PARAMETER_NAMES}
        points.append(OperatingPoint(cond, _number(p.get("mu_N"), f"{where}.mu_N"), vals))
    if len(points) < 2:
        why = f" (the report says: {error})" if error else ""
        raise LPVLoadError(
            f"{source}: {len(points)} usable operating point(s); an LPV model needs at least 2"
            + why
        )
    # Fewer distinct points than the paper's order needs: lower the order rather than fail.
    n_mu = len({p.mu_N for p in points})
    return ReportPoints(points, tuple(excluded), min(order or DEFAULT_ORDER, n_mu - 1))


def lpv_from_document(doc: Any, source: str = "<results>") -> LoadedLPV:
    rp = points_from_document(doc, source)
    try:
        model = PhysicalLPV.fit(rp.points, order=rp.order, out_of_range="clip")
    except (ValueError, KeyError) as e:
        raise LPVLoadError(f"{source}: cannot build the LPV model: {e}") from None
    return LoadedLPV(
        model=model,
        source=source,
        conditions=tuple(p.condition for p in model.points),
        excluded=rp.excluded,
        order=rp.order,
    )


def load_lpv_model(path: str | Path) -> LoadedLPV:
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except OSError as e:
        raise LPVLoadError(f"{p}: cannot read: {e.strerror or e}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise LPVLoadError(f"{p}: not a JSON file ({e})") from None
    return lpv_from_document(doc, str(p))
