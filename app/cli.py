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

    paths = import_study(a.csvdir, a.out, overwrite=a.overwrite)
    print(f"imported into {len(paths)} session file(s) in {a.out}")
    return 0


def _cmd_report(a: argparse.Namespace) -> int:
    from steerlab.analysis.armfit import FitOptions
    from steerlab.analysis.report import write_report
    from steerlab.analysis.study import AnalysisOptions

    try:
        fit = FitOptions(weighting=a.weighting, inertia=a.inertia, I_i=a.inertia_value)
    except ValueError as e:
        print(f"steerlab report: {e}", file=sys.stderr)
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

    s = sub.add_parser("simulate", help="run the protocol for N simulated subjects")
    s.add_argument("--subjects", type=int, required=True, help="number of simulated subjects")
    s.add_argument("--out", required=True, help="directory for the session files")
    s.add_argument("--seed", type=int, default=0, help="population and noise seed (default 0)")
    s.add_argument("--protocol", help="protocol TOML (default: the paper's protocol)")
    s.add_argument("--realtime", action="store_true", help="pace at wall-clock speed")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true", help="complete existing session files")
    g.add_argument("--overwrite", action="store_true", help="replace existing session files")
    s.add_argument("--jobs", type=int, default=None, help="worker processes (default: cores)")
    s.add_argument("--model", help="extended world model (model.toml from steerlab diagnose)")
    s.add_argument("--rig-model", help="rig.json of steerlab rig-check: simulate the measured "
                   "wheel instead of the nominal one")  # fmt: skip
    s.set_defaults(func=_cmd_simulate)

    e = sub.add_parser("export", help="session files → trial interchange CSV + JSON")
    e.add_argument("dir")
    e.add_argument("--out", required=True)
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

    i = sub.add_parser("import", help="trial interchange CSV + JSON → session files")
    i.add_argument("csvdir")
    i.add_argument("--out", required=True)
    i.add_argument("--overwrite", action="store_true")
    i.set_defaults(func=_cmd_import)

    r = sub.add_parser("report", help="analyse a study and write the report")
    r.add_argument("dir")
    r.add_argument("--out", required=True)
    r.add_argument(
        "--jobs",
        type=int,
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
        type=float,
        default=0.1,
        help="I_i in kg·m² when --inertia fixed (default 0.1)",
    )
    r.add_argument(
        "--no-compare",
        action="store_true",
        help="skip the second fit with the other weighting (the side-by-side table)",
    )
    r.set_defaults(func=_cmd_report)

    n = sub.add_parser("run", help="run one subject's session on a rig, in real time")
    n.add_argument("--rig", help="rig configuration TOML (default: the simulated rig)")
    n.add_argument("--subject", type=int, required=True, help="subject number (from 1)")
    n.add_argument("--out", default="sessions", help="data root (default: sessions/)")
    n.add_argument("--resume", action="store_true", help="continue an interrupted session")
    n.add_argument("--protocol", help="protocol TOML (default: the paper's protocol)")
    n.add_argument("--no-breaks", action="store_true", help="skip the protocol's breaks")
    n.add_argument("--rig-check", help="rig.json of the rig's last rig check, recorded in the "
                   "session file")  # fmt: skip
    n.set_defaults(func=_cmd_run)

    c = sub.add_parser("rig-check", help="measure the wheel the rig renders (hands off)")
    c.add_argument("--rig", help="rig configuration TOML (default: the simulated rig); its "
                   "[rig_check] table sets the tolerances")  # fmt: skip
    c.add_argument("--out", required=True, help="directory for rig.json, index.html (and the "
                   "hands-off trial's rigcheck.h5)")  # fmt: skip
    c.add_argument("--recording", help="identify from this recording (session file or "
                   "interchange CSV) instead of running a hands-off trial")  # fmt: skip
    c.add_argument("--trial", help="with a session file: the trial group (default: its latest "
                   "complete hands-off trial)")  # fmt: skip
    c.add_argument("--protocol", help="protocol TOML: loop rate and nominal wheel")
    c.add_argument("--periods", type=int, help="perturbation periods of 10 s (default 3)")
    c.add_argument("--overwrite", action="store_true", help="replace DIR/rigcheck.h5")
    c.set_defaults(func=_cmd_rig_check)

    t = sub.add_parser("stop", help="emergency stop of the session running in --out")
    t.add_argument("--out", default="sessions")
    t.add_argument("--subject", type=int, help="the session's subject number (needed when "
                   "several sessions run in --out)")  # fmt: skip
    t.add_argument("--rig", help="the session's rig file, as given to steerlab run")
    t.set_defaults(func=_cmd_stop)

    d = sub.add_parser("diagnose", help="find what the simulation gets wrong on measured data")
    d.add_argument("dir")
    d.add_argument("--out", required=True)
    d.add_argument("--jobs", type=int, default=None, help="worker processes for the "
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

    u = sub.add_parser("gui", help="experimenter GUI and subject dashboard")
    u.add_argument("--rig", help="rig configuration TOML (default: the simulated rig)")
    u.add_argument("--out", default="sessions", help="data root (default: sessions/)")
    u.add_argument("--protocol", help="protocol TOML (default: the paper's protocol)")
    u.set_defaults(func=_cmd_gui)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from steerlab.app.errors import is_user_error

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
