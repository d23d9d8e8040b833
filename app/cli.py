"""The ``steerlab`` command line."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

EXIT_BAD_INPUT = 2


class Progress:
    """A one-line progress bar on stderr (on a non-terminal: a line every 5 s and at the end)."""

    def __init__(self, label: str, stream=None, width: int = 30) -> None:
        self.label, self.stream, self.width = label, stream or sys.stderr, width
        self.t0 = time.monotonic()
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._last = 0.0

    def __call__(self, done: int, total: int, note: str = "") -> None:
        now = time.monotonic()
        if not self.tty and done < total:
            if now - self._last < 5.0:
                return
        self._last = now
        frac = done / total if total else 1.0
        bar = "#" * int(frac * self.width)
        eta = (now - self.t0) / frac * (1 - frac) if frac > 0 else 0.0
        line = f"{self.label} [{bar:<{self.width}}] {done}/{total} {note[:28]:<28} eta {eta:5.0f} s"
        end = "\n" if (done >= total or not self.tty) else ""
        self.stream.write(("\r" if self.tty else "") + line + end)
        self.stream.flush()


def _cmd_simulate(a: argparse.Namespace) -> int:
    from steerlab.app.simulate import simulate_study

    t0 = time.monotonic()
    res = simulate_study(
        a.subjects,
        a.out,
        seed=a.seed,
        protocol_path=a.protocol,
        realtime=a.realtime,
        resume=a.resume,
        overwrite=a.overwrite,
        jobs=a.jobs,
        world=_world_from_model(a.model) if a.model else None,
        progress=Progress("simulate"),
        rig_model=a.rig_model,
        lsl=a.lsl,
    )
    print(f"{len(res)} session file(s) in {a.out} ({time.monotonic() - t0:.1f} s)")
    return 0


def _world_from_model(path: str):
    from steerlab.hardware.sim.model_file import load_world_model

    return load_world_model(path)


def _cmd_rig_check(a: argparse.Namespace) -> int:
    from steerlab.analysis.rigcheck import identify, summary
    from steerlab.app.rigcheck import RigCheckRunError, run_rig_check

    if a.recording:
        if a.overwrite or a.periods is not None:
            raise RigCheckRunError("--periods and --overwrite are for a hands-off trial (--rig)")
        fit, checks = identify(
            a.recording, a.out, rig_path=a.rig, protocol_path=a.protocol, trial=a.trial
        )
    else:
        if a.trial:
            raise RigCheckRunError("--trial picks a trial of a --recording")
        fit, checks = run_rig_check(
            a.rig,
            a.out,
            periods=a.periods or 3,
            protocol_path=a.protocol,
            overwrite=a.overwrite,
        )
    print(f"rig check of {fit.source}:")
    print(summary(fit, checks))
    print(f"written: {Path(a.out) / 'rig.json'}, {Path(a.out) / 'index.html'}")
    return 0


def _cmd_export(a: argparse.Namespace) -> int:
    from steerlab.protocols.interchange import export_study

    paths = export_study(a.dir, a.out, overwrite=a.overwrite, blind=a.blind)
    for line in export_study.last_skipped:  # type: ignore[attr-defined]
        print(f"steerlab export: skipped a damaged trial: {line}", file=sys.stderr)
    print(f"exported {len(paths)} trial(s) to {a.out}")
    return 0


def _cmd_import(a: argparse.Namespace) -> int:
    from steerlab.protocols.interchange import import_study

    paths = import_study(a.csvdir, a.out, overwrite=a.overwrite, require_period=True)
    print(f"imported into {len(paths)} session file(s) in {a.out}")
    return 0


def _cmd_report(a: argparse.Namespace) -> int:
    from steerlab.analysis.armfit import FitOptions
    from steerlab.analysis.report import write_report
    from steerlab.analysis.study import AnalysisOptions

    try:
        fit = FitOptions(weighting=a.weighting, inertia=a.inertia, I_i=a.inertia_value)
    except ValueError as e:
        print(f"steerlab report: error: argument --inertia-value: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    from steerlab.analysis.executors import executor_for

    options = AnalysisOptions(fit=fit, compare_weightings=not a.no_compare)
    if a.jobs is None:
        import os

        a.jobs = min(os.cpu_count() or 1, 4)
    with executor_for(a.scheduler, a.jobs) as ex:
        write_report(
            a.dir, a.out, executor=ex, jobs=a.jobs, progress=Progress("report"), options=options
        )
    print(f"report written to {Path(a.out) / 'index.html'}")
    return 0


def _cmd_run(a: argparse.Namespace) -> int:
    from steerlab.app.run import run_session
    from steerlab.protocols.engine import State

    state = run_session(
        a.rig,
        a.subject,
        a.out,
        resume=a.resume,
        protocol_path=a.protocol,
        breaks=not a.no_breaks,
        rig_check=a.rig_check,
        on_abort=a.on_abort,
        lsl=a.lsl,
    )
    return 0 if state is State.DONE else 3


def _cmd_stop(a: argparse.Namespace) -> int:
    from steerlab.app.run import stop_running

    target = stop_running(a.out, subject=a.subject, rig=a.rig)
    print(f"emergency stop sent to the session of {target.describe()} in {a.out}")
    return 0


def _cmd_diagnose(a: argparse.Namespace) -> int:
    from steerlab.analysis.diagnosis import run_diagnosis
    from steerlab.analysis.executors import executor_for

    if a.jobs is None:
        import os

        # The candidate stage's time limit counts the workers' CPU seconds: the verdict does
        # not depend on the number of jobs, only the wait does.
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
        a.jobs = min(cores or os.cpu_count() or 1, 4)
    with executor_for(a.scheduler, a.jobs) as ex:
        result = run_diagnosis(
            a.dir,
            a.out,
            jobs=a.jobs,
            progress=Progress("diagnose"),
            model=a.model,
            rig_model=a.rig_model,
            nominal_wheel=a.nominal_wheel,
            executor=ex,
        )
    print(result.summary())
    return 0


def _cmd_gui(a: argparse.Namespace) -> int:
    from steerlab.app.gui.main import run_gui

    return run_gui(rig=a.rig, out=a.out, protocol=a.protocol)


# -- other recordings into a study: XDF and TekScan (docs/import.md) -------------------------------
def _import_failed(a: argparse.Namespace, e: Exception) -> int:
    print(f"steerlab {a.command}: error: {e}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _cmd_import_xdf(a: argparse.Namespace) -> int:
    from steerlab.protocols.trial_extras import TrialExtrasError
    from steerlab.protocols.xdf_import import XdfImportError, import_xdf

    try:
        res = import_xdf(
            a.xdf, a.session, match=a.match, method=a.method, streams=a.stream,
            dejitter=a.dejitter, replace=a.replace, dry_run=a.dry_run,
        )  # fmt: skip
    except (XdfImportError, TrialExtrasError) as e:
        return _import_failed(a, e)
    print(res.summary())
    for line in res.problems:
        print(f"steerlab import-xdf: warning: {line}", file=sys.stderr)
    if a.dry_run:
        print("dry run: nothing written")
    return 0


def _cmd_import_tekscan(a: argparse.Namespace) -> int:
    from steerlab.protocols.tekscan_import import TekscanImportError, import_tekscan
    from steerlab.protocols.trial_extras import TrialExtrasError
    from steerlab.protocols.xdf_import import XdfImportError

    try:
        res = import_tekscan(
            a.movie, a.session, trial=a.trial, subject=a.subject, hand=a.hand,
            n_per_raw=a.n_per_raw, sync_frame=a.sync_frame, sync_sample=a.sync_sample,
            sync_mark=a.sync_mark, reference=a.reference, max_lag_s=a.max_lag_s,
            method=a.method, replace=a.replace, allow_truncated=a.allow_truncated,
            dry_run=a.dry_run,
        )  # fmt: skip
    except (TekscanImportError, TrialExtrasError, XdfImportError) as e:
        return _import_failed(a, e)
    print(res.summary())
    if a.dry_run:
        print("dry run: nothing written")
    return 0


def _cmd_record_lsl(a: argparse.Namespace) -> int:
    from steerlab.protocols.xdf_writer import LslRecorder, RecorderError, XdfWriteError

    rec = LslRecorder(
        a.out, types=a.type or (), names=a.name or (), expect=a.expect, resolve_s=a.wait,
        overwrite=a.overwrite,
        on_error=lambda m: print(f"steerlab record-lsl: warning: {m}", file=sys.stderr),
    )  # fmt: skip
    try:
        streams = rec.start()
    except (RecorderError, XdfWriteError) as e:
        return _import_failed(a, e)
    for s in streams:
        print(f"recording {s.name!r} (type {s.type}) as stream {s.stream_id}")
    print("Ctrl-C stops" + (f"; stopping after {a.duration:g} s" if a.duration else ""))
    try:
        if a.duration:
            time.sleep(a.duration)
        else:
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        pass
    path = rec.stop()
    counts = ", ".join(f"{s.name}: {s.samples}" for s in rec.streams)
    print(f"wrote {path} ({counts} samples)")
    return 0


def _add_import_commands(sub) -> None:
    x = _subparser(
        sub,
        "import-xdf",
        "an XDF recording's streams → extra channels of the matching trials",
        "Put the streams of an XDF recording (LabRecorder's, or steerlab record-lsl's) onto the "
        "trials of session files: trials matched by Steerlab's marker stream in the file, or by "
        "each trial's recorded LSL clock; each stream resampled onto the trial's samples "
        "(linear at or above the trial's rate, else the latest sample held) as channels "
        "xdf_STREAM_LABEL with their units, its samples as recorded kept beside them "
        "(docs/import.md). The trials' own channels are never touched.",
        "  steerlab import-xdf lab/S03.xdf --session sessions/study\n"
        "  steerlab import-xdf lab/S03.xdf --session sessions/study/S03.h5 --stream EMG "
        "--method linear",
    )
    x.add_argument("xdf", metavar="FILE.xdf", help="the XDF recording")
    x.add_argument("--session", required=True, help="a session file (.h5) or a folder of them")
    x.add_argument("--match", choices=("auto", "markers", "clock"), default="auto",
                   help="how trials are found on the recording's clock: Steerlab's trial_start "
                   "markers in the file, the trials' lsl_clock_s, or markers when the file has "
                   "them (default)")  # fmt: skip
    x.add_argument("--method", choices=("auto", "linear", "hold"), default="auto",
                   help="resampling: linear interpolation, or zero-order hold of the latest "
                   "sample; default: linear for a regular stream at or above the trial's rate, "
                   "hold otherwise")  # fmt: skip
    x.add_argument("--stream", action="append", metavar="NAME_OR_TYPE",
                   help="import only this stream (its name or type; repeatable); default: every "
                   "stream but Steerlab's own")  # fmt: skip
    x.add_argument("--dejitter", action="store_true", help="let pyxdf put regular streams' "
                   "time stamps on a straight line (default: as recorded)")  # fmt: skip
    x.add_argument("--replace", action="store_true", help="replace channels an earlier import "
                   "made (default: refuse, nothing written)")  # fmt: skip
    x.add_argument("--dry-run", action="store_true", help="match and check, write nothing")
    x.set_defaults(func=_cmd_import_xdf)

    t = _subparser(
        sub,
        "import-tekscan",
        "a TekScan ASCII movie → a trial's grip channel",
        "Put a TekScan ASCII movie (.asf/.csv export; one hand, or both hands together) onto "
        "one trial as grip_force_tekscan_HAND_N, aligned by a sync frame the lab recorded or, "
        "without one, by cross-correlation with the trial's own grip force (else the driver "
        "torque's magnitude), with the lag's uncertainty (docs/import.md). The trial's own "
        "channels are never touched.",
        "  steerlab import-tekscan grip/S03_t05_L.asf --hand left --session sessions/study "
        "--subject S03 --trial 5\n"
        "  steerlab import-tekscan grip/S03_t05.csv --session sessions/study/S03.h5 --trial "
        "05_BT12_rep1_a1 --n-per-raw 0.0125 --sync-frame 12",
    )
    t.add_argument("movie", metavar="FILE", help="the TekScan ASCII export (.asf or .csv)")
    t.add_argument("--session", required=True, help="a session file (.h5) or a folder of them")
    t.add_argument("--subject", help="with a folder: the subject's file (S03 for S03.h5)")
    t.add_argument("--trial", required=True, help="the trial: its index (its latest attempt) "
                   "or its group name (05_BT12_rep1_a1)")  # fmt: skip
    t.add_argument(
        "--hand",
        choices=("left", "right", "total"),
        default="total",
        help="which hand the movie is (total: both hands in one movie; default)",
    )
    t.add_argument("--n-per-raw", type=_positive_number, help="N per raw count, for a movie in "
                   "raw counts (UNITS raw)")  # fmt: skip
    t.add_argument("--sync-frame", type=_whole_number(0), help="the movie's frame at the trial's "
                   "first sample (or at --sync-sample / --sync-mark): align by it, not by "
                   "cross-correlation")  # fmt: skip
    t.add_argument("--sync-sample", type=_whole_number(0), help="with --sync-frame: the trial "
                   "sample the frame is at (default 0)")  # fmt: skip
    t.add_argument("--sync-mark", help="with --sync-frame: the trial's first mark of this kind is "
                   "where the frame is")  # fmt: skip
    t.add_argument("--reference", help="the trial's channel to cross-correlate with (default: "
                   "its grip force of that hand, else |driver_torque_Nm|)")  # fmt: skip
    t.add_argument(
        "--max-lag-s",
        type=_positive_number,
        help="search lags within ± this "
        "(default: every lag that leaves half the shorter recording overlapping)",
    )
    t.add_argument("--method", choices=("auto", "linear", "hold"), default="auto",
                   help="resampling: default hold (latest frame) for a movie slower than the "
                   "trial, else linear")  # fmt: skip
    t.add_argument("--allow-truncated", action="store_true", help="read a movie without its "
                   "closing @@ (warned; an incomplete last frame dropped)")  # fmt: skip
    t.add_argument("--replace", action="store_true", help="replace a channel an earlier import "
                   "made (default: refuse)")  # fmt: skip
    t.add_argument("--dry-run", action="store_true", help="align and report, write nothing")
    t.set_defaults(func=_cmd_import_tekscan)

    r = _subparser(
        sub,
        "record-lsl",
        "record LSL streams into an XDF file (a small LabRecorder)",
        "Record Lab Streaming Layer streams into an XDF file until Ctrl-C (or --duration): their "
        "samples with time stamps, clock offsets every 5 s, as LabRecorder writes them; pyxdf "
        "and steerlab import-xdf read it (docs/import.md).",
        "  steerlab record-lsl --out lab/S03.xdf --type Steerlab --type Markers --type EMG",
    )
    r.add_argument("--out", required=True, help="the XDF file to write")
    r.add_argument("--type", action="append", help="record streams of this type (repeatable)")
    r.add_argument("--name", action="append", help="record the stream of this name (repeatable)")
    r.add_argument("--expect", type=COUNT, default=1, help="wait for at least this many streams "
                   "(default 1)")  # fmt: skip
    r.add_argument("--wait", type=_positive_number, default=5.0, help="how long to look for "
                   "streams, s (default 5)")  # fmt: skip
    r.add_argument("--duration", type=_positive_number, help="stop after this many seconds")
    r.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    r.set_defaults(func=_cmd_record_lsl)


def _whole_number(low: int):
    """An argparse type: a whole number ≥ ``low`` (argparse names the option in its error)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"must be a whole number ≥ {low}, got {text!r}"
            ) from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be a whole number ≥ {low}, got {value}")
        return value

    parse.__name__ = f"whole number ≥ {low}"
    return parse


def _positive_number(text: str) -> float:
    """An argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


COUNT = _whole_number(1)  # --subjects, --jobs, --periods, subject numbers
SEED = _whole_number(0)


def _subparser(sub, name: str, help: str, description: str, example: str):
    """A subcommand with its one-line help, a description and examples in the epilog (kept as
    written: the raw formatter does not wrap, so the description is wrapped here)."""
    import textwrap

    return sub.add_parser(
        name,
        help=help,
        description=textwrap.fill(description, 88),
        epilog="example:\n" + example,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )


SCHEDULER_HELP = (
    "run the parallel work on Dask (pip install 'steerlab[dask]'): a scheduler's address "
    "(tcp://HOST:8786), a scheduler file, or local[:N] for a LocalCluster of N workers"
)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="steerlab",
        description="Experiment control, data acquisition and analysis for steering-wheel "
        "admittance studies (Pronker et al. 2017).",
    )
    from steerlab import __version__

    p.add_argument("--version", action="version", version=f"steerlab {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    s = _subparser(
        sub,
        "simulate",
        "run the protocol for N simulated subjects",
        "Run the protocol for N simulated subjects through the engine and the simulated rig: one "
        "session file (S01.h5 …) per subject.",
        "  steerlab simulate --subjects 18 --out sessions/demo --overwrite\n"
        "  steerlab simulate --subjects 2 --out sessions/drive --protocol driving.toml\n\n"
        "--subjects N is how many subjects (S01 … SNN); steerlab run --subject N says which one\n"
        "subject a session on a rig is.",
    )
    s.add_argument("--subjects", type=COUNT, required=True, metavar="N",
                   help="how many simulated subjects, S01 … SNN (≥ 1); not which one: that is "
                   "run --subject")  # fmt: skip
    s.add_argument("--out", required=True, help="directory for the session files")
    s.add_argument("--seed", type=SEED, default=0, help="population and noise seed, ≥ 0 "
                   "(default 0)")  # fmt: skip
    s.add_argument("--protocol", help="protocol TOML (default: the paper's protocol)")
    s.add_argument("--realtime", action="store_true", help="pace at wall-clock speed")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true", help="complete existing session files")
    g.add_argument("--overwrite", action="store_true", help="replace existing session files")
    s.add_argument("--jobs", type=COUNT, default=None, help="worker processes, ≥ 1 (default: "
                   "cores)")  # fmt: skip
    s.add_argument("--model", help="extended world model (model.toml from steerlab diagnose)")
    s.add_argument("--rig-model", help="rig.json of steerlab rig-check: simulate the measured "
                   "wheel instead of the nominal one")  # fmt: skip
    s.add_argument("--lsl", action=argparse.BooleanOptionalAction, default=None,
                   help="publish each session's signals and events on the Lab Streaming Layer "
                   "(LabRecorder; batch time stamps are synthetic, docs/lsl.md); default off "
                   "(STEERLAB_LSL=on changes it): a batch study must not flood a lab's "
                   "network")  # fmt: skip
    s.set_defaults(func=_cmd_simulate)

    e = _subparser(
        sub,
        "export",
        "session files → trial interchange CSV + JSON",
        "Write every trial of the session files in DIR in the trial interchange format: a CSV "
        "and a JSON per trial (docs/data-format.md). Damaged trials are left out and named.",
        "  steerlab export sessions/demo --out exported/demo",
    )
    e.add_argument("dir", metavar="DIR", help="folder of session files (*.h5)")
    e.add_argument("--out", required=True, help="folder for the CSV + JSON files (absent or "
                   "empty, unless --overwrite)")  # fmt: skip
    e.add_argument(
        "--overwrite", action="store_true", help="replace --out if it exists and is not empty"
    )
    e.add_argument(
        "--blind",
        action="store_true",
        help="leave out what only a simulation knows (its world, subject, seed, true_* "
        "channels), to analyse simulated data as if measured",
    )
    e.set_defaults(func=_cmd_export)

    i = _subparser(
        sub,
        "import",
        "trial interchange CSV + JSON → session files",
        "Read trials in the interchange format (NAME.csv + NAME.json, any rate ≥ 100 Hz, any "
        "start phase) and write one session file per subject. Nothing is written unless every "
        "trial is good (docs/data-format.md).",
        "  steerlab import exported/demo --out sessions/imported",
    )
    i.add_argument("csvdir", metavar="CSVDIR", help="folder of trials: NAME.csv + NAME.json each")
    i.add_argument("--out", required=True, help="folder for the session files (SUBJECT.h5)")
    i.add_argument("--overwrite", action="store_true", help="replace session files that exist "
                   "in --out")  # fmt: skip
    i.set_defaults(func=_cmd_import)

    r = _subparser(
        sub,
        "report",
        "analyse a study and write the report",
        "Analyse the session files in DIR: admittance per subject and condition, the arm-model "
        "fits, the grip-scheduled LPV model, the statistics; writes index.html, results.json "
        "and per_subject.csv.",
        "  steerlab report sessions/demo --out reports/demo\n"
        "  steerlab report sessions/demo --out reports/paper --weighting paper --jobs 2",
    )
    r.add_argument("dir", metavar="DIR", help="folder of session files (*.h5)")
    r.add_argument("--out", required=True, help="folder for the report (index.html, "
                   "results.json, per_subject.csv)")  # fmt: skip
    r.add_argument(
        "--jobs",
        type=COUNT,
        default=None,
        help="worker processes for the trials and the subjects' fits (default: the CPU count, "
        "at most 4)",
    )
    r.add_argument("--scheduler", help=SCHEDULER_HELP)
    r.add_argument(
        "--weighting",
        choices=("inverse_variance", "paper"),
        default="inverse_variance",
        help="arm-fit weights: 1/var(Ĥ) from the noise smoothed across frequency (default: "
        "maximum likelihood, docs/method-estimator.md) or the paper's coherence × 1/f",
    )
    r.add_argument(
        "--inertia",
        choices=("subject", "free", "fixed"),
        default="subject",
        help="I_i: one per subject shared by its conditions (default), one per fit, or held "
        "at --inertia-value",
    )
    r.add_argument(
        "--inertia-value",
        type=_positive_number,
        default=0.1,
        help="I_i in kg·m² when --inertia fixed (default 0.1)",
    )
    r.add_argument(
        "--no-compare",
        action="store_true",
        help="skip the second fit with the other weighting (the side-by-side table)",
    )
    r.set_defaults(func=_cmd_report)

    n = _subparser(
        sub,
        "run",
        "run one subject's session on a rig, in real time",
        "Run one subject's session on a rig in real time (the simulated rig by default), with "
        "pause, abort, redo and resume; Ctrl-C or Enter is an emergency stop.",
        "  steerlab run --subject 3 --out sessions\n"
        "  steerlab run --rig RIG.toml --subject 3 --out sessions --resume\n"
        "\n"
        "exit codes:\n"
        "  0    every trial of the session is complete\n"
        "  2    bad input (protocol, rig file, subject; the session file exists without\n"
        "       --resume, or another process writes it): nothing was run\n"
        "  3    the session stopped before its end: an emergency stop, a trial a fault aborted\n"
        "       (--on-abort stop, or aborted trials in a row), the engine broken; every sample\n"
        "       is in the file, continue with --resume\n"
        "  130  Ctrl-C while the input was still being checked (from the rig's bring-up on,\n"
        "       Ctrl-C is an emergency stop: 3)",
    )
    n.add_argument("--rig", help="rig configuration TOML (default: the simulated rig)")
    n.add_argument("--subject", type=COUNT, required=True, metavar="N", help="which subject: "
                   "its number, from 1 (3: S03); not how many (simulate --subjects)")  # fmt: skip
    n.add_argument("--out", default="sessions", help="data root (default: sessions/)")
    n.add_argument("--resume", action="store_true", help="continue an interrupted session")
    n.add_argument("--protocol", help="protocol TOML (default: the paper's protocol)")
    n.add_argument("--no-breaks", action="store_true", help="skip the protocol's breaks")
    n.add_argument("--rig-check", help="rig.json of the rig's last rig check, recorded in the "
                   "session file")  # fmt: skip
    n.add_argument("--on-abort", choices=("ask", "redo", "next", "stop"), help="after a trial "
                   "a fault aborted: ask (default when stdin is a terminal), redo it, go on to "
                   "the next (it is run again after the others), or stop the session (default "
                   "otherwise); an emergency stop always ends the session")  # fmt: skip
    n.add_argument("--lsl", action=argparse.BooleanOptionalAction, default=None,
                   help="publish the session's signals and events on the Lab Streaming Layer, "
                   "for LabRecorder beside EMG or EEG (docs/lsl.md); default on "
                   "(STEERLAB_LSL=off changes it); the trials record the LSL clock "
                   "either way")  # fmt: skip
    n.set_defaults(func=_cmd_run)

    c = _subparser(
        sub,
        "rig-check",
        "measure the wheel the rig renders (hands off)",
        "Measure the wheel the rig really renders (inertia, damping, stiffness, friction, "
        "imbalance, actuator lag, with SEMs) from a hands-off trial or a recording, and judge "
        "it against the rig file's tolerances (docs/rig-check.md).",
        "  steerlab rig-check --rig RIG.toml --out rigcheck/today\n"
        "  steerlab rig-check --recording rigcheck/today/rigcheck.h5 --out rigcheck/again",
    )
    c.add_argument("--rig", help="rig configuration TOML (default: the simulated rig); its "
                   "[rig_check] table sets the tolerances")  # fmt: skip
    c.add_argument("--out", required=True, help="directory for rig.json, index.html (and the "
                   "hands-off trial's rigcheck.h5)")  # fmt: skip
    c.add_argument("--recording", help="identify from this recording (session file or "
                   "interchange CSV) instead of running a hands-off trial")  # fmt: skip
    c.add_argument("--trial", help="with a session file: the trial group (default: its latest "
                   "complete hands-off trial)")  # fmt: skip
    c.add_argument("--protocol", help="protocol TOML: loop rate and nominal wheel")
    c.add_argument("--periods", type=COUNT, help="perturbation periods of 10 s, ≥ 1 (default 3)")
    c.add_argument("--overwrite", action="store_true", help="replace DIR/rigcheck.h5")
    c.set_defaults(func=_cmd_rig_check)

    t = _subparser(
        sub,
        "stop",
        "emergency stop of the session running in --out",
        "Emergency stop of the session running in a data folder, as Ctrl-C or Enter in its "
        "terminal.",
        "  steerlab stop --out sessions --subject 3",
    )
    t.add_argument("--out", default="sessions", help="the data root the session writes to "
                   "(default: sessions/)")  # fmt: skip
    t.add_argument("--subject", type=COUNT, help="the session's subject number (needed when "
                   "several sessions run in --out)")  # fmt: skip
    t.add_argument("--rig", help="the session's rig file, as given to steerlab run")
    t.set_defaults(func=_cmd_stop)

    d = _subparser(
        sub,
        "diagnose",
        "find what the simulation gets wrong on measured data",
        "Compare the simulation with measured session files: where they depart, which "
        "mechanism explains it, and the extended model (docs/diagnosis.md).",
        "  steerlab diagnose sessions/lab --out diagnosis/lab\n"
        "  steerlab diagnose sessions/lab --out diagnosis/lab --rig-model rigcheck/today/rig.json",
    )
    d.add_argument("dir", metavar="DIR", help="folder of measured session files (*.h5)")
    d.add_argument("--out", required=True, help="folder for the diagnosis (index.html, "
                   "diagnosis.json, model.toml)")  # fmt: skip
    d.add_argument("--jobs", type=COUNT, default=None, help="worker processes for the "
                   "candidates' fits (default: cores, at most 4)")  # fmt: skip
    d.add_argument("--scheduler", help=SCHEDULER_HELP)
    d.add_argument("--model", help="model.toml of an earlier diagnosis: its mechanisms become "
                   "the baseline")  # fmt: skip
    w = d.add_mutually_exclusive_group()
    w.add_argument("--rig-model", help="rig.json of steerlab rig-check: simulate the measured "
                   "wheel (default: the measured wheel the session files record, else the "
                   "nominal one)")  # fmt: skip
    w.add_argument("--nominal-wheel", action="store_true", help="simulate the nominal wheel "
                   "even if the session files record a measured one")  # fmt: skip
    d.set_defaults(func=_cmd_diagnose)

    u = _subparser(
        sub,
        "gui",
        "experimenter GUI and subject dashboard",
        "Open the experimenter's window and, on the subject's screen, the dashboard (docs/gui.md).",
        "  steerlab gui\n  steerlab gui --rig RIG.toml --out sessions",
    )
    u.add_argument("--rig", help="rig configuration TOML (default: the simulated rig)")
    u.add_argument("--out", default="sessions", help="data root (default: sessions/)")
    u.add_argument("--protocol", help="protocol TOML (default: the paper's protocol)")
    u.set_defaults(func=_cmd_gui)
    _add_import_commands(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from steerlab.app.errors import is_user_error

    for folder in (getattr(args, "dir", None), getattr(args, "csvdir", None)):
        if folder is not None and not Path(folder).exists():
            print(f"steerlab {args.command}: error: no such folder: {folder}", file=sys.stderr)
            return EXIT_BAD_INPUT
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print(f"steerlab {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        if not is_user_error(e):
            raise
        print(f"steerlab {args.command}: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
