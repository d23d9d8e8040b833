"""The quick quality check shown after each trial. Qt-free; computed from the samples in memory.

Figures (all over the measured segment ``[measured_start, measured_stop)`` unless said):

- coherence Γ = sqrt(|S_{Tp,θ}|² / (S_{Tp,Tp} S_{θ,θ})) at the perturbation's excited bins,
  one value per double band. The cross- and auto-spectra are averaged over the band's bins and
  over the whole periods received, with the Fourier coefficients of :mod:`analysis.frf`
  (X_k = (2/P) Σ x[n] e^{-2πikn/P}). With one bin of one period Γ is 1 whatever the noise, so
  the per-band average is what makes it informative; this is the same estimator as the
  analysis, on one trial;
- angle RMS about the centre, degrees;
- time outside the boundary: percentage of measured samples with |θ| > boundary (None without
  a boundary, RT; with the lines on the centre, PT, nearly every sample counts);
- lost samples (a complete trial): planned minus received by the GUI (the engine's own count is
  shown beside it). An aborted trial loses nothing: the samples after its end were never
  acquired, and are reported as "not recorded (aborted)", planned minus the engine's count;
- loop timing: the loop's ``trial_stats()`` carried by the ``TrialEnded`` event. A late cycle
  (later than the loop's threshold, 0.5 ms) means, on a rig whose devices keep their own
  time, a sample taken off its due time: flagged above :data:`LATE_WARN_FRACTION`, with what
  to do. On a rig whose world steps once per cycle (``steps_by_sample``: the built-in
  simulated rig) a late cycle changes no recorded value, and the row says so instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from steerlab.protocols.perturbation import PerturbationDesign

#: Below this median band coherence the trial is flagged (ours: the paper's coherence is
#: "high except at the lowest frequencies"; 0.5 catches a slack grip or a wrong sign early).
COHERENCE_WARN = 0.5
#: Late cycles above this fraction are flagged (on a rig whose devices keep their own time).
LATE_WARN_FRACTION = 0.001
#: What to do about late cycles on such a rig (docs/live-loop.md, "What a lab PC needs").
LATE_ADVICE = (
    "samples unevenly spaced in time; close other programs and give Steerlab real-time "
    'priority (docs/live-loop.md, "What a lab PC needs")'
)
#: Why late cycles do not matter on a rig whose world steps once per cycle.
LATE_HARMLESS = (
    "harmless here: the simulated world steps once per cycle, not by the clock, so no "
    "recorded value changes (the loop shares the GUI's process; with --rig it has its own)"
)


@dataclass(frozen=True)
class QualityCheck:
    key: str
    condition: str
    status: str
    n_planned: int
    n_received: int
    n_engine: int  # samples the engine counted (TrialEnded.n_samples)
    n_measured: int  # measured-segment samples received
    n_periods: int  # whole periods used for the coherence
    band_frequencies_hz: np.ndarray
    coherence: np.ndarray  # per double band; empty without a whole period
    angle_rms_deg: float | None
    boundary_deg: float
    outside_boundary_percent: float | None
    loop: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    steps_by_sample: bool = False  # the rig's world steps once per cycle: lateness is harmless

    @property
    def lost_samples(self) -> int:
        """Samples of a complete trial the display did not receive (0 for an ended trial)."""
        return self.n_planned - self.n_received if self.status == "complete" else 0

    @property
    def not_recorded(self) -> int:
        """Planned samples an aborted (or otherwise ended) trial never acquired."""
        return 0 if self.status == "complete" else max(self.n_planned - self.n_engine, 0)

    @property
    def coherence_median(self) -> float | None:
        return float(np.median(self.coherence)) if self.coherence.size else None

    @property
    def coherence_min(self) -> float | None:
        return float(np.min(self.coherence)) if self.coherence.size else None

    def rows(self) -> list[tuple[str, str]]:
        """(label, value) pairs for display."""

        def f(v: float | None, fmt: str, unit: str = "") -> str:
            return "—" if v is None else f"{v:{fmt}}{unit}"

        lp = self.loop
        out = [
            ("trial", f"{self.key} ({self.status})"),
            (
                "coherence (median / min)",
                f"{f(self.coherence_median, '.2f')} / {f(self.coherence_min, '.2f')}"
                f"  over {self.coherence.size} bands, {self.n_periods} period(s)",
            ),
            ("angle RMS", f(self.angle_rms_deg, ".2f", "°")),
            (
                "outside boundary",
                "no boundary"
                if self.outside_boundary_percent is None
                else f"{self.outside_boundary_percent:.1f} % (±{self.boundary_deg:g}°)",
            ),
            (
                "samples",
                f"{self.n_received} of {self.n_planned} received, "
                + (
                    f"{self.lost_samples} lost"
                    if self.status == "complete"
                    else f"{self.not_recorded} not recorded ({self.status})"
                )
                + f" (engine: {self.n_engine})",
            ),
        ]
        if "period_error_p50_ms" in lp:
            out.append(
                (
                    "loop period error",
                    f"p50 {lp['period_error_p50_ms']:.3f}  p99 {lp['period_error_p99_ms']:.3f}"
                    f"  max {lp['period_error_max_ms']:.2f} ms",
                )
            )
            out.append(("late cycles", self.late_cycles_text()))
        else:
            # Words, not a dict's repr: a loop that is not paced reports counts only.
            counts = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in lp.items())
            out.append(
                ("loop timing", "not paced, no timing figures" + (f" ({counts})" if counts else ""))
            )
        return out

    def late_cycles_text(self) -> str:
        """The late cycles in words: how many, what late means, the worst against the limit
        that aborts a trial, and whether it matters here."""
        lp = self.loop
        late, cycles = int(lp.get("late_cycles", 0)), int(lp.get("cycles", 0))
        text = f"{late} of {cycles} cycles"
        if "late_threshold_ms" in lp:
            text += f" > {lp['late_threshold_ms']:g} ms late"
        else:
            text += " late"
        worst = lp.get("period_error_max_ms")
        limit = lp.get("stall_limit_ms")
        if worst is not None:
            abort = f"; a trial aborts at {_ms(limit)}" if limit is not None else ""
            text += f" (worst {_ms(worst)}{abort})"
        if self.steps_by_sample:
            return f"{text}; {LATE_HARMLESS}"
        if late:
            text += "; a late cycle samples the rig off its due time"
        return text


def _ms(v: float) -> str:
    """A duration in ms as a person reads it: 12 ms, 0.6 ms, 1000 ms."""
    return f"{v:.0f} ms" if v >= 10 else f"{v:.1g} ms" if v < 1 else f"{v:.1f} ms"


def late_warning(stats: dict) -> bool:
    """More late cycles than :data:`LATE_WARN_FRACTION` of the trial's cycles."""
    cycles = stats.get("cycles") or 0
    return cycles > 0 and stats.get("late_cycles", 0) > LATE_WARN_FRACTION * cycles


def band_coherence(
    tp: np.ndarray,
    theta: np.ndarray,
    bins: np.ndarray,
    band_of_bin: np.ndarray,
    period_samples: int,
) -> tuple[np.ndarray, int]:
    """Coherence Tp→θ per band from whole periods of ``tp`` and ``theta``; (Γ per band, periods)."""
    p = int(period_samples)
    n_per = min(len(tp), len(theta)) // p
    bands = np.unique(band_of_bin)
    if n_per == 0:
        return np.zeros(0), 0
    x = np.asarray(tp[: n_per * p], dtype=float).reshape(n_per, p)
    y = np.asarray(theta[: n_per * p], dtype=float).reshape(n_per, p)
    fx = np.fft.rfft(x, axis=1)[:, bins] * (2.0 / p)
    fy = np.fft.rfft(y, axis=1)[:, bins] * (2.0 / p)
    out = np.empty(len(bands))
    for j, b in enumerate(bands):
        m = band_of_bin == b
        sxy = np.mean(np.conj(fx[:, m]) * fy[:, m])
        sxx = np.mean(np.abs(fx[:, m]) ** 2)
        syy = np.mean(np.abs(fy[:, m]) ** 2)
        den = sxx * syy
        out[j] = math.sqrt(abs(sxy) ** 2 / den) if den > 0 else 0.0
    return out, n_per


def quality_check(
    channels: dict[str, np.ndarray],
    *,
    key: str,
    condition: str,
    status: str,
    fs_hz: float,
    measured_start: int,
    measured_stop: int,
    design: PerturbationDesign,
    boundary_deg: float,
    n_planned: int,
    n_engine: int,
    loop_stats: dict | None = None,
    steps_by_sample: bool = False,
) -> QualityCheck:
    """Quality figures of one trial from its samples (see the module docstring).

    ``steps_by_sample``: the rig's world advances one sample per loop cycle whatever the clock
    (the built-in simulated rig), so a late cycle changes no recorded value: not a warning."""
    tp = np.asarray(channels.get("perturbation_torque_Nm", np.zeros(0)), dtype=float)
    th = np.asarray(channels.get("wheel_angle_rad", np.zeros(0)), dtype=float)
    n_rx = min(len(tp), len(th))
    seg = slice(measured_start, min(measured_stop, n_rx))
    tp_m, th_m = tp[seg], th[seg]
    n_meas = len(th_m)
    p = int(round(design.period_s * fs_hz))
    bands = np.unique(design.band_of_bin)
    freqs = np.array([design.frequencies_hz[design.band_of_bin == b].mean() for b in bands])
    coh, n_per = band_coherence(tp_m, th_m, design.bins, design.band_of_bin, p)
    if not coh.size:
        freqs = np.zeros(0)
    deg = np.degrees(th_m)
    rms = float(np.sqrt(np.mean(deg**2))) if n_meas else None
    if not math.isfinite(boundary_deg) or n_meas == 0:
        outside = None
    else:
        outside = float(100.0 * np.count_nonzero(np.abs(deg) > boundary_deg) / n_meas)
    stats = dict(loop_stats or {})
    warn = []
    if status != "complete":
        warn.append(f"trial {status}")
    if n_planned - n_rx > 0 and status == "complete":
        warn.append(f"{n_planned - n_rx} samples lost")
    if n_engine != n_rx:
        warn.append(f"the display received {n_rx} samples, the engine counted {n_engine}")
    if coh.size and float(np.median(coh)) < COHERENCE_WARN:
        warn.append(f"low coherence (median {float(np.median(coh)):.2f})")
    if late_warning(stats) and not steps_by_sample:
        pct = 100.0 * stats["late_cycles"] / stats["cycles"]
        warn.append(f"{stats['late_cycles']} late loop cycles ({pct:.1f} %): {LATE_ADVICE}")
    if "stats_error" in stats:
        warn.append(f"no loop timing: {stats['stats_error']}")
    return QualityCheck(
        key=key,
        condition=condition,
        status=status,
        n_planned=int(n_planned),
        n_received=int(n_rx),
        n_engine=int(n_engine),
        n_measured=int(n_meas),
        n_periods=int(n_per),
        band_frequencies_hz=freqs,
        coherence=coh,
        angle_rms_deg=rms,
        boundary_deg=float(boundary_deg),
        outside_boundary_percent=outside,
        loop=stats,
        warnings=tuple(warn),
        steps_by_sample=steps_by_sample,
    )
