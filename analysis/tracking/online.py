"""Admittance tracked live, one loop sample at a time (for the GUI's live admittance panel).

    tracker = OnlineTracker.from_results("report/results.json", fs_hz=1000.0)
    est = tracker.update(perturbation_Nm, driver_torque_Nm, angle_rad, grip_N)   # per sample
    est = tracker.update_block(block)   # or per block of loop channels (DeviceLoop's dict)
    est.k_i, est.admittance(f_hz)

``method="grip_ekf"`` (default) is Steerlab's tracker (:mod:`analysis.tracking.kalman`): the
LPV model's prediction corrected by the perturbation response; it needs the perturbation
running. ``method="lpv"`` is the paper's grip-only LPV model (:mod:`.scheduled`): no
perturbation needed, no correction. Both give, sample for sample, the same numbers as their
offline trackers on the same data (tested). The compiled per-sample step takes some µs;
``update`` measures well under 1 ms including Python's call overhead (benchmark in
``docs/benchmarks.md``); ``update_block`` runs a whole block in one compiled call.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from steerlab.analysis.tracking.base import TRACKED, admittance
from steerlab.analysis.tracking.calibration import Calibration
from steerlab.analysis.tracking.kalman import (
    O_MU,
    O_P,
    O_PRIOR_KI,
    O_SD_LOG_KI,
    EKFConfig,
    KalmanCore,
)
from steerlab.analysis.tracking.scheduled import DEFAULT_GRIP_TAU_S

Method = Literal["grip_ekf", "lpv"]
CHANNELS = ("perturbation_torque_Nm", "driver_torque_Nm", "wheel_angle_rad", "grip_force_N")


@dataclass(frozen=True)
class AdmittanceEstimate:
    """The arm now. Units: N·m/rad, N·m·s/rad, kg·m², N."""

    k_i: float
    b_i: float
    k_c: float
    b_c: float
    I_i: float
    grip_level_N: float  # the grip force the LPV model was evaluated at
    lpv_k_i: float  # what the LPV model alone says k_i is
    k_i_sd_log: float | None  # the filter's own SD of log k_i (grip_ekf only)
    method: str
    samples: int  # samples seen since the start (or the last reset)

    def admittance(self, f_hz: np.ndarray | float) -> np.ndarray:
        """H(f) = θ/T_d of the arm now, rad/(N·m)."""
        p = {"b_i": self.b_i, "k_i": self.k_i, "b_c": self.b_c, "k_c": self.k_c}
        return admittance(p, self.I_i, np.asarray(f_hz, dtype=float))

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "k_i_Nm_per_rad": self.k_i,
            "b_i_Nms_per_rad": self.b_i,
            "k_c_Nm_per_rad": self.k_c,
            "b_c_Nms_per_rad": self.b_c,
            "I_i_kgm2": self.I_i,
            "grip_level_N": self.grip_level_N,
            "lpv_k_i_Nm_per_rad": self.lpv_k_i,
            "k_i_sd_log": self.k_i_sd_log,
            "samples": self.samples,
        }


class OnlineTracker:
    """Sample-by-sample tracker; see the module docstring."""

    def __init__(
        self,
        calibration: Calibration,
        fs_hz: float = 1000.0,
        method: Method = "grip_ekf",
        config: EKFConfig | None = None,
    ) -> None:
        if method not in ("grip_ekf", "lpv"):
            raise ValueError(f"method must be 'grip_ekf' or 'lpv', got {method!r}")
        if not fs_hz > 0:
            raise ValueError(f"fs_hz must be > 0, got {fs_hz}")
        self.calibration = calibration
        self.fs_hz = float(fs_hz)
        self.method: Method = method
        self.config = config or EKFConfig()
        self._prior = calibration.prior
        self.reset()

    @classmethod
    def from_results(
        cls,
        results_json: str | Path | Mapping[str, Any],
        fs_hz: float = 1000.0,
        method: Method = "grip_ekf",
        config: EKFConfig | None = None,
    ) -> OnlineTracker:
        """From a report's ``results.json`` (its LPV operating points; the disturbance model
        from its tracking section when there is one). Raises
        :class:`analysis.tracking.calibration.CalibrationError` with the reason."""
        return cls(Calibration.from_results(results_json), fs_hz, method, config)

    def reset(self) -> None:
        """Forget everything (a new trial, or a new driver)."""
        self._core = KalmanCore(self.calibration, self.fs_hz, self.config)
        self._mu: float | None = None
        self._a_lpv = 1.0 - math.exp(-1.0 / (DEFAULT_GRIP_TAU_S * self.fs_hz))
        self._n = 0
        self.last: AdmittanceEstimate | None = None

    # -- per sample --------------------------------------------------------------------------
    def update(
        self, perturbation_Nm: float, driver_torque_Nm: float, angle_rad: float, grip_N: float
    ) -> AdmittanceEstimate:
        """One loop sample in, the estimate after it out."""
        self._n += 1
        if self.method == "lpv":
            g = float(grip_N)
            self._mu = g if self._mu is None else self._mu + self._a_lpv * (g - self._mu)
            p = self._prior(self._mu)
            est = self._estimate(p, self._mu, float(p[1]), None)
        else:
            out = self._core.update(
                float(perturbation_Nm), float(driver_torque_Nm), float(angle_rad), float(grip_N)
            )
            est = self._from_out(out)
        self.last = est
        return est

    def update_block(self, block: Mapping[str, np.ndarray]) -> AdmittanceEstimate:
        """A block of loop samples (the channels :class:`hardware.loop.DeviceLoop` yields:
        ``perturbation_torque_Nm``, ``driver_torque_Nm``, ``wheel_angle_rad``,
        ``grip_force_N``) in one call; returns the estimate after its last sample."""
        try:
            tp, td, th, g = (np.ascontiguousarray(block[c], dtype=float) for c in CHANNELS)
        except KeyError as e:
            raise KeyError(f"block lacks channel {e}; needs {list(CHANNELS)}") from None
        n = len(th)
        if n == 0:
            if self.last is None:
                raise ValueError("empty block and no estimate yet")
            return self.last
        if self.method == "lpv":
            for k in range(n):
                est = self.update(tp[k], td[k], th[k], g[k])
            return est
        outs = self._core.run_arrays(tp, td, th, g)
        self._n += n
        self.last = self._from_out(outs[-1])
        return self.last

    def _from_out(self, out: np.ndarray) -> AdmittanceEstimate:
        return self._estimate(
            out[O_P : O_P + 4], float(out[O_MU]), float(out[O_PRIOR_KI]), float(out[O_SD_LOG_KI])
        )

    def _estimate(
        self, p: np.ndarray, mu: float, lpv_k_i: float, sd: float | None
    ) -> AdmittanceEstimate:
        v = dict(zip(TRACKED, (float(x) for x in p), strict=True))
        return AdmittanceEstimate(
            k_i=v["k_i"],
            b_i=v["b_i"],
            k_c=v["k_c"],
            b_c=v["b_c"],
            I_i=self.calibration.I_i,
            grip_level_N=mu,
            lpv_k_i=lpv_k_i,
            k_i_sd_log=sd,
            method=self.method,
            samples=self._n,
        )
