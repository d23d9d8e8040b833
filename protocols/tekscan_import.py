"""``steerlab import-tekscan``: a TekScan ASCII movie as a trial's grip channel.

A lab that records grip with TekScan sensors (Grip gloves, I-Scan, F-Scan) exports each movie as
ASCII (``hardware/grip/tekscan.py`` reads it, strictly). One movie is one hand (``left`` or
``right``) or both hands together (``total``), for one trial. This module puts the movie's
force onto that trial's samples (``docs/import.md``):

* **force**: per frame, the cells' total in N (pressure units × SENSEL_AREA; a raw-count movie
  needs ``n_per_raw``, N per raw count).
* **alignment** (``analysis/alignment.py``): trial time = movie time + ``lag_s``, from a sync
  event when the lab recorded one (``sync_frame``: the movie's frame at the trial's first
  sample, or at ``sync_sample``, or at the trial's first mark of kind ``sync_mark``), else by
  cross-correlation of the movie's force with a channel of the trial that saw the same grip
  (``reference``; default: the session glove's force of that hand, ``grip_force_N`` for
  ``total``, and the driver torque's magnitude when the trial has no grip force), with the
  lag's uncertainty.
* **resampling** onto the trial's samples: ``hold`` (the latest frame, as Steerlab holds its own
  glove's frames) for a movie slower than the trial, ``linear`` otherwise; ``method`` forces one.

Where it goes (``protocols/trial_extras.py``): a channel ``grip_force_tekscan_HAND_N``
(``grip_force_tekscan_N`` for ``total``) beside the trial's own, which is never touched, with
the alignment as attributes; and the movie's frames as recorded in
``imported/tekscan_HAND``: ``frame_numbers``, ``frame_times_s`` (the movie's time), ``time_s``
(the trial's), ``totals`` (the cells' sum, in the file's units), ``stated_raw_sum`` (where the
file states one per frame: equal to ``totals`` for a raw-count movie, the reader checks it),
``force_N``; the file's header as JSON.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from steerlab.analysis.alignment import (
    Alignment,
    AlignmentError,
    align_by_sync,
    align_by_xcorr,
    choose_method,
    resample,
)
from steerlab.hardware.grip.tekscan import TekscanError, TekscanMovie, read_tekscan
from steerlab.protocols.datafile import (
    DataFileError,
    SessionFile,
    open_for_reading,
    read_channel,
)
from steerlab.protocols.trial_extras import SourceGroup, TrialAdditions, add_to_trials
from steerlab.protocols.xdf_import import session_paths

COMMAND = "steerlab import-tekscan"
HANDS = ("left", "right", "total")


class TekscanImportError(ValueError):
    """The movie cannot be put onto the trial as asked; the message names the file/trial."""


def channel_name(hand: str) -> str:
    return "grip_force_tekscan_N" if hand == "total" else f"grip_force_tekscan_{hand}_N"


def group_name(hand: str) -> str:
    return f"tekscan_{hand}"


@dataclass
class TrialData:
    path: Path
    key: str
    attrs: dict
    time_s: np.ndarray
    channels: dict[str, np.ndarray]
    marks: list[dict]

    @property
    def fs_hz(self) -> float:
        return float(self.attrs.get("fs_hz") or math.nan)

    @property
    def where(self) -> str:
        return f"{self.path}:/trials/{self.key}"


def find_trial(session: str | Path, trial: str, subject: str | None = None) -> TrialData:
    """The trial ``trial`` (its group name, or its trial index: then its latest attempt) of the
    session file at ``session`` (a file, or a folder with ``subject``'s file or only one)."""
    paths = session_paths(session)
    if subject is not None:
        paths = [p for p in paths if p.stem == subject]
        if not paths:
            raise TekscanImportError(f"{session}: no session file of subject {subject!r}")
    if len(paths) > 1:
        raise TekscanImportError(
            f"{session}: {len(paths)} session files; say which subject (--subject)"
        )
    path = paths[0]
    try:
        sf = SessionFile(path)
        key = None
        if trial in sf.trial_keys:
            key = trial
        else:
            try:
                index = int(trial)
            except ValueError:
                raise TekscanImportError(
                    f"{path}: no trial {trial!r} (give its group name, e.g."
                    f" {sf.trial_keys[0] if sf.trial_keys else '01_RT_fam_a1'}, or its index)"
                ) from None
            found = [
                (int(a.get("attempt", 1) or 1), k)
                for k, a in sf.trial_attrs.items()
                if a.get("trial_index") is not None and int(a["trial_index"]) == index
            ]
            if not found:
                raise TekscanImportError(f"{path}: no trial with index {index}")
            key = max(found)[1]
        if key in sf.damaged:
            raise TekscanImportError(f"{path}:/trials/{key}: {sf.damaged[key]}")
        with open_for_reading(path) as f:
            g = f["trials"][key]
            if "time_s" not in g:
                raise TekscanImportError(f"{path}:/trials/{key}: no samples")
            channels = {
                n: read_channel(d)
                for n, d in g.items()
                if n
                in (
                    "grip_force_N",
                    "grip_force_left_N",
                    "grip_force_right_N",
                    "driver_torque_Nm",
                )  # fmt: skip
            }
            marks = []
            if "marks" in g:
                for m in g["marks"][()]:
                    marks.append({"sample": int(m["sample"]), "kind": m["kind"].decode()})
            return TrialData(
                path=path,
                key=key,
                attrs=dict(sf.trial_attrs[key]),
                time_s=read_channel(g["time_s"]),
                channels=channels,
                marks=marks,
            )
    except DataFileError as e:
        raise TekscanImportError(str(e)) from None


def default_reference(hand: str, trial: TrialData) -> str:
    """The trial's channel to correlate with: the glove's force of that hand, else the total,
    else the driver torque's magnitude (``|driver_torque_Nm|``)."""
    order = [f"grip_force_{hand}_N", "grip_force_N"] if hand != "total" else ["grip_force_N"]
    for name in order:
        v = trial.channels.get(name)
        if v is not None and np.isfinite(v).sum() > 1 and np.nanstd(v) > 0:
            return name
    return "|driver_torque_Nm|"


def reference_values(name: str, trial: TrialData) -> np.ndarray:
    if name.startswith("|") and name.endswith("|"):
        inner = name[1:-1]
        if inner not in trial.channels:
            raise TekscanImportError(f"{trial.where}: no channel {inner!r} for the reference")
        return np.abs(trial.channels[inner])
    if name not in trial.channels:
        raise TekscanImportError(f"{trial.where}: no channel {name!r} for the reference")
    return trial.channels[name]


def movie_force(movie: TekscanMovie, n_per_raw: float | None) -> np.ndarray:
    try:
        return movie.force_n(n_per_raw=n_per_raw)
    except TekscanError as e:
        msg = str(e).replace("pass n_per_raw=...", "pass --n-per-raw N_PER_COUNT")
        raise TekscanImportError(msg) from None


def frame_interval(movie: TekscanMovie) -> float:
    if movie.n_frames > 1:
        return float(np.median(np.diff(movie.frame_times_s)))
    return float(movie.seconds_per_frame or math.nan)


def align(
    movie: TekscanMovie,
    force: np.ndarray,
    trial: TrialData,
    *,
    hand: str,
    sync_frame: int | None = None,
    sync_sample: int | None = None,
    sync_mark: str | None = None,
    reference: str | None = None,
    max_lag_s: float | None = None,
) -> tuple[Alignment, str | None]:
    """(alignment, the reference channel or None for a sync event)."""
    fi = frame_interval(movie)
    if sync_frame is not None:
        hits = np.flatnonzero(movie.frame_numbers == sync_frame)
        if not hits.size:
            raise TekscanImportError(
                f"{movie.path}: no frame {sync_frame} (frames {movie.frame_numbers[0]}…"
                f"{movie.frame_numbers[-1]})"
            )
        frame_t = float(movie.frame_times_s[hits[0]])
        if sync_mark is not None:
            marks = [m for m in trial.marks if m["kind"] == sync_mark]
            if not marks:
                kinds = sorted({m["kind"] for m in trial.marks}) or ["none"]
                raise TekscanImportError(
                    f"{trial.where}: no mark of kind {sync_mark!r} (its marks: {', '.join(kinds)})"
                )
            sample, what = marks[0]["sample"], f"frame {sync_frame} at mark {sync_mark!r}"
        else:
            sample = sync_sample or 0
            what = f"frame {sync_frame} at trial sample {sample}"
        if not 0 <= sample < len(trial.time_s):
            raise TekscanImportError(f"{trial.where}: no sample {sample}")
        t_trial = float(trial.time_s[sample])
        ts = 1.0 / trial.fs_hz if trial.fs_hz > 0 else 0.0
        return align_by_sync(frame_t, t_trial, frame_interval_s=fi, trial_interval_s=ts,
                             what=what), None  # fmt: skip
    if sync_sample is not None or sync_mark is not None:
        raise TekscanImportError("--sync-sample and --sync-mark need --sync-frame")
    ref = reference or default_reference(hand, trial)
    values = reference_values(ref, trial)
    try:
        return align_by_xcorr(
            movie.frame_times_s, force, trial.time_s, values, max_lag_s=max_lag_s, reference=ref
        ), ref
    except AlignmentError as e:
        raise TekscanImportError(f"{movie.path} against {trial.where}: {e}") from None


@dataclass
class TekscanImport:
    movie: Path
    trial: str
    hand: str
    channel: str
    alignment: Alignment
    reference: str | None
    method: str
    n_frames: int
    n_frames_in_trial: int
    n_nan: int
    written: list[str]

    def summary(self) -> str:
        a = self.alignment
        how = (
            f"cross-correlation with {self.reference} (peak r = {a.peak_correlation:.3f})"
            if a.method == "cross_correlation"
            else "a sync event"
        )
        lines = [
            f"{self.movie} → {self.trial}: {self.channel}",
            f"  lag {a.lag_s:+.4f} s ± {a.sem_s:.4f} s (trial time = movie time + lag), by {how}",
            f"  {self.n_frames_in_trial} of {self.n_frames} frames within the trial; resampled by"
            f" {self.method}; {self.n_nan} trial samples without a frame (NaN)",
        ]
        if a.method == "cross_correlation" and (a.other_peak_fraction > 0.05 or a.edge_fraction
                                                > 0.05):  # fmt: skip
            lines.append(
                f"  warning: the correlation peak is not well defined ({a.other_peak_fraction:.0%}"
                " of the bootstrap replicates peaked elsewhere): check the lag, or give"
                " --sync-frame"
            )
        lines += [f"  wrote {w}" for w in self.written]
        return "\n".join(lines)


def import_tekscan(
    movie_path: str | Path,
    session: str | Path,
    *,
    trial: str,
    subject: str | None = None,
    hand: str = "total",
    n_per_raw: float | None = None,
    sync_frame: int | None = None,
    sync_sample: int | None = None,
    sync_mark: str | None = None,
    reference: str | None = None,
    max_lag_s: float | None = None,
    method: str = "auto",
    replace: bool = False,
    allow_truncated: bool = False,
    dry_run: bool = False,
) -> TekscanImport:
    """Read the movie, align it to the trial, resample its force onto the trial's samples and
    add it to the trial (module docstring)."""
    if hand not in HANDS:
        raise TekscanImportError(f"--hand must be one of {', '.join(HANDS)}, not {hand!r}")
    if method not in ("auto", "linear", "hold"):
        raise TekscanImportError(f"--method must be auto, linear or hold, not {method!r}")
    try:
        movie = read_tekscan(movie_path, allow_truncated=allow_truncated)
    except TekscanError as e:
        raise TekscanImportError(str(e)) from None
    except OSError as e:
        raise TekscanImportError(f"{movie_path}: cannot read ({e.strerror or e})") from None
    force = movie_force(movie, n_per_raw)
    tr = find_trial(session, trial, subject)
    alignment, ref = align(
        movie, force, tr, hand=hand, sync_frame=sync_frame, sync_sample=sync_sample,
        sync_mark=sync_mark, reference=reference, max_lag_s=max_lag_s,
    )  # fmt: skip
    trial_t = alignment.to_trial_time(movie.frame_times_s)
    fi = frame_interval(movie)
    rate = 1.0 / fi if fi > 0 else 0.0
    used = method if method != "auto" else choose_method(rate, tr.fs_hz)
    values = resample(trial_t, force, tr.time_s, method=used, max_gap_s=2.5 * fi)
    half = 0.5 / tr.fs_hz if tr.fs_hz > 0 else 0.0
    inside = int(((trial_t >= tr.time_s[0] - half) & (trial_t <= tr.time_s[-1] + half)).sum())
    if inside == 0:
        raise TekscanImportError(
            f"{movie.path}: no frame falls within {tr.where} at lag {alignment.lag_s:+.4f} s"
            f" (the movie spans {trial_t[0]:.3f}–{trial_t[-1]:.3f} s of trial time, the trial"
            f" {tr.time_s[0]:.3f}–{tr.time_s[-1]:.3f} s)"
        )
    name = channel_name(hand)
    common = {
        "source_file": str(movie.path),
        "hand": hand,
        "movie_units": movie.units or "",
        "n_per_raw": n_per_raw,
        "reference_channel": ref,
        **alignment.attributes(),
    }
    datasets = {
        "frame_numbers": np.asarray(movie.frame_numbers),
        "frame_times_s": np.asarray(movie.frame_times_s),
        "time_s": trial_t,
        "totals": movie.totals(),
        "force_N": force,
    }
    if movie.stated_raw_sum is not None:
        datasets["stated_raw_sum"] = np.asarray(movie.stated_raw_sum)
    add = TrialAdditions(
        tr.key,
        channels={
            name: (
                values,
                {
                    **common,
                    "units": "N",
                    "resample_method": used,
                    "n_frames_in_trial": inside,
                    "n_nan": int(np.isnan(values).sum()),
                },
            )
        },
        groups={
            group_name(hand): SourceGroup(
                datasets,
                {**common, "header": json.dumps(movie.header), "complete": movie.complete},
            )
        },
    )
    written = [] if dry_run else add_to_trials(tr.path, [add], command=COMMAND, replace=replace)
    return TekscanImport(
        movie=movie.path,
        trial=tr.where,
        hand=hand,
        channel=name,
        alignment=alignment,
        reference=ref,
        method=used,
        n_frames=movie.n_frames,
        n_frames_in_trial=inside,
        n_nan=int(np.isnan(values).sum()),
        written=written,
    )
