"""Calibration of the trackers on the stationary conditions: the grip → admittance LPV model and
the driver's remnant, from trials with one task each (the paper's experiment).

- LPV: the physical-parameter interpolation (:class:`analysis.lpv.PhysicalLPV`, order 2, RT
  left out for the paper's reasons) over the conditions' arm fits, scheduled on the mean grip
  force. From one subject's trials the points are that subject's own fits and mean grips; from
  several subjects, the group fits at μ = median over subjects (as ``results.json``).
- Disturbance: what the perturbation does not explain. The rig (the protocol's wheel and the
  fitted arm) is simulated driven by the perturbation alone; the measured angle and driver torque
  minus that response are the remnant's doing (and sensor noise). Their SDs and corners (of a
  critically damped second-order spectrum) are the Kalman tracker's disturbance model.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal

from steerlab.analysis.lpv import DEFAULT_EXCLUSIONS, OperatingPoint, PhysicalLPV
from steerlab.analysis.lpv_results import LPVLoadError, points_from_document
from steerlab.analysis.tracking.base import TRACKED, closed_loop_response
from steerlab.protocols.protocol import VirtualWheel
from steerlab.protocols.records import TrialRecord

LPV_ORDER = 2


@dataclass(frozen=True)
class Disturbance:
    """Second-order (critically damped Gauss–Markov) model of what the perturbation does not
    drive in the angle and in the driver torque: SD and corner of each.

    The defaults are used when no stationary trials are at hand (a ``results.json`` without a
    tracking section): typical of the simulated study (median over conditions and subjects).
    """

    angle_sd_rad: float = 0.02
    angle_corner_hz: float = 0.3
    torque_sd_Nm: float = 0.3
    torque_corner_hz: float = 0.5

    def to_dict(self) -> dict[str, float]:
        return {
            "angle_sd_rad": self.angle_sd_rad,
            "angle_corner_Hz": self.angle_corner_hz,
            "torque_sd_Nm": self.torque_sd_Nm,
            "torque_corner_Hz": self.torque_corner_hz,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Disturbance:
        return cls(
            float(d["angle_sd_rad"]),
            float(d["angle_corner_Hz"]),
            float(d["torque_sd_Nm"]),
            float(d["torque_corner_Hz"]),
        )


class CalibrationError(ValueError):
    """The data cannot calibrate the trackers; the message says why."""


@dataclass(frozen=True)
class LPVPrior:
    """The physical LPV model evaluated for whole arrays of grip force at once.

    Same polynomials, scaling and clipping as :class:`analysis.lpv.PhysicalLPV` (read from its
    ``to_dict``), vectorised: the trackers evaluate it at every sample.
    """

    centre: float
    scale: float
    lo: float
    hi: float
    coeffs: tuple[tuple[float, ...], ...]  # per TRACKED parameter, highest power first
    I_i: float

    @classmethod
    def of(cls, model: PhysicalLPV) -> LPVPrior:
        d = model.to_dict()["polynomials"]
        c = d["coefficients_highest_power_first"]
        lo, hi = model.mu_range
        I_i = c["I_i"]["values"]
        return cls(
            centre=float(d["centre_N"]),
            scale=float(d["scale_N"]),
            lo=float(lo),
            hi=float(hi),
            coeffs=tuple(tuple(float(v) for v in c[n]["values"]) for n in TRACKED),
            I_i=float(I_i[-1]) if len(I_i) == 1 else float(np.polyval(I_i, 0.0)),
        )

    def __call__(self, mu: np.ndarray | float) -> np.ndarray:
        """Parameters (…, 4) in TRACKED order at grip force ``mu`` (N), clipped to the range."""
        x = (np.clip(np.asarray(mu, dtype=float), self.lo, self.hi) - self.centre) / self.scale
        out = np.stack([np.polyval(c, x) for c in self.coeffs], axis=-1)
        # A quadratic through positive points can dip below zero between them only in odd
        # cases; keep the arm physical.
        return np.maximum(out, 1e-3)


@dataclass
class Calibration:
    """What every tracker may use; built by :meth:`from_records` or :meth:`from_results`."""

    lpv: PhysicalLPV
    points: list[OperatingPoint]
    I_i: float
    disturbance: Disturbance = field(default_factory=Disturbance)
    wheel: VirtualWheel = field(default_factory=VirtualWheel)
    source: str = ""
    excluded: dict[str, str] = field(default_factory=dict)

    @cached_property
    def prior(self) -> LPVPrior:
        """The LPV model as arrays, built once (every tracker and benchmark step asks)."""
        return LPVPrior.of(self.lpv)

    def parameters_at(self, mu: float) -> dict[str, float]:
        return dict(zip(TRACKED, self.prior(mu).tolist(), strict=True))

    def middle_point(self) -> dict[str, float]:
        """The operating point in the middle of the grip range: a neutral start value."""
        p = self.points[len(self.points) // 2]
        return {n: float(p.parameters[n]) for n in TRACKED}

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "I_i_kgm2": self.I_i,
            "disturbance": self.disturbance.to_dict(),
            "wheel": {
                "inertia_kgm2": self.wheel.inertia_kgm2,
                "damping_Nms_per_rad": self.wheel.damping_nms_per_rad,
                "stiffness_Nm_per_rad": self.wheel.stiffness_nm_per_rad,
            },
            "excluded": dict(self.excluded),
            "operating_points": [
                {"condition": p.condition, "mu_N": p.mu_N, "parameters": dict(p.parameters)}
                for p in self.points
            ],
            "lpv": self.lpv.to_dict(),
        }

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_points(
        cls,
        points: Iterable[OperatingPoint],
        *,
        disturbance: Disturbance | None = None,
        wheel: VirtualWheel | None = None,
        exclude: Mapping[str, str] = DEFAULT_EXCLUSIONS,
        source: str = "",
        order: int = LPV_ORDER,
    ) -> Calibration:
        pts = sorted(points, key=lambda p: p.mu_N)
        used = [p for p in pts if p.condition not in exclude]
        excluded = {p.condition: exclude[p.condition] for p in pts if p.condition in exclude}
        n_mu = len({round(p.mu_N, 9) for p in used})
        if n_mu < 2:
            raise CalibrationError(
                f"{source or 'calibration'}: {n_mu} operating point(s) with distinct grip force; "
                "the LPV model needs at least 2 stationary conditions"
            )
        model = PhysicalLPV.fit(used, order=min(order, n_mu - 1), out_of_range="clip")
        I_vals = {float(p.parameters["I_i"]) for p in used}
        if len(I_vals) > 1:
            raise CalibrationError(f"operating points differ in I_i {sorted(I_vals)}; fix it")
        return cls(
            lpv=model,
            points=used,
            I_i=I_vals.pop(),
            disturbance=disturbance or Disturbance(),
            wheel=wheel or VirtualWheel(),
            source=source,
            excluded=excluded,
        )

    @classmethod
    def from_records(
        cls,
        records: Sequence[TrialRecord],
        *,
        wheel: VirtualWheel | None = None,
        exclude: Mapping[str, str] = DEFAULT_EXCLUSIONS,
        source: str = "stationary trials",
    ) -> Calibration:
        """Fit every stationary condition (:func:`analysis.study.analyze_study`), then the LPV.

        One subject: that subject's own points. Several: the group points (μ = median).
        Time-varying trials among the records are skipped by the study.
        """
        from steerlab.analysis.study import AnalysisOptions, analyze_study

        # The default fit; the side-by-side second weighting is for reports, not needed here.
        study = analyze_study(list(records), options=AnalysisOptions(compare_weightings=False))
        subjects = sorted({r.subject for r in study.subject_conditions})
        if not subjects:
            raise CalibrationError(f"{source}: no analysable stationary trials")
        if len(subjects) == 1:
            pts = [
                OperatingPoint(r.condition, float(r.grip_mean_N), r.fit.params.as_dict())
                for r in study.subject_conditions
                if r.fit is not None and math.isfinite(r.grip_mean_N)
            ]
        else:
            pts = [OperatingPoint(c, mu, p) for c, mu, p, _ in study.operating_points()]
        wheel = wheel or VirtualWheel()
        by_source = {r.source: r for r in records if r.source}
        found = []
        for cell in study.subject_conditions:
            if cell.fit is None:
                continue
            for t in cell.trials:
                rec = by_source.get(t.source)
                if rec is not None:
                    found.append(disturbance_of(cell.fit.params.as_dict(), rec, wheel))
        dist = Disturbance(*np.median(np.array(found), axis=0)) if found else Disturbance()
        return cls.from_points(
            pts,
            disturbance=dist,
            wheel=wheel,
            exclude=exclude,
            source=f"{source} ({', '.join(subjects)})",
        )

    @classmethod
    def from_results(cls, results: str | Path | Mapping[str, Any]) -> Calibration:
        """From a report's ``results.json`` (path or parsed): the group operating points, and
        the remnant model when the report has a tracking section (else the defaults)."""
        if isinstance(results, str | Path):
            where = str(results)
            try:
                doc = json.loads(Path(results).read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
                raise CalibrationError(f"{where}: cannot read results ({e})") from None
        else:
            where, doc = "results", results
        try:
            report = points_from_document(doc, where)
        except LPVLoadError as e:
            raise CalibrationError(str(e)) from None
        meta = doc if isinstance(doc, Mapping) else {}  # a bare list of points has no more
        cal = (meta.get("tracking") or {}).get("calibration") or {}
        dist = Disturbance.from_dict(cal["disturbance"]) if "disturbance" in cal else None
        wheels = [f.get("wheel") for f in meta.get("provenance", {}).get("input_files", [])]
        w = next((x for x in wheels if isinstance(x, Mapping)), None)
        wheel = None
        if w:
            wheel = VirtualWheel(
                float(w.get("inertia_kgm2", 0.3)),
                float(w.get("damping_Nms_per_rad", 2.0)),
                float(w.get("stiffness_Nm_per_rad", 4.2)),
            )
        return cls.from_points(
            report.points,
            disturbance=dist,
            wheel=wheel,
            exclude={},  # the report marked its exclusions already ("included": false)
            source=where,
            order=report.order,
        )


class CalibratedTracker:
    """What every tracker shares: it keeps the calibration it is given and will not track
    without one. What each takes from it is said in its own ``calibrate`` comment, if any."""

    name: str
    calibration: Calibration | None = None

    def calibrate(self, calibration: Calibration) -> None:
        self.calibration = calibration

    def calibrated(self) -> Calibration:
        if self.calibration is None:
            raise RuntimeError(f"{self.name}: calibrate before tracking")
        return self.calibration


def _gm2_corner(x: np.ndarray, fs_hz: float) -> float:
    """Corner (Hz) of a critically damped second-order (Gauss–Markov) process with the same
    SD ratio of derivative to value: for it var(x')/var(x) = ω² exactly. The remnant's effect
    is smooth (a low-passed torque through the rig's low-pass), which a first-order model
    misrepresents. Above 5 Hz sensor noise would dominate the derivative: low-passed first."""
    b, a = signal.butter(2, min(5.0, 0.4 * fs_hz) / (fs_hz / 2))
    y = signal.filtfilt(b, a, x - np.mean(x))
    dy = np.gradient(y) * fs_hz
    sd = float(np.std(y))
    return float(np.std(dy) / sd / (2 * math.pi)) if sd > 0 else 1.0


def disturbance_of(
    params: Mapping[str, float], rec: TrialRecord, wheel: VirtualWheel
) -> tuple[float, float, float, float]:
    """(angle SD, angle corner, torque SD, torque corner) of what the perturbation does not
    drive in one stationary trial, after its run-in (the rig simulated from the perturbation)."""
    arm = {n: float(params[n]) for n in TRACKED}
    th, td = closed_loop_response(
        rec.perturbation_torque_Nm, rec.fs_hz, arm, float(params["I_i"]), wheel
    )
    k0 = rec.measured_start or 0
    k1 = rec.measured_stop or len(th)
    e_th = np.asarray(rec.wheel_angle_rad, dtype=float)[k0:k1] - th[k0:k1]
    e_td = np.asarray(rec.driver_torque_Nm, dtype=float)[k0:k1] - td[k0:k1]
    return (
        float(e_th.std()),
        _gm2_corner(e_th, rec.fs_hz),
        float(e_td.std()),
        _gm2_corner(e_td, rec.fs_hz),
    )
