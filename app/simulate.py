"""``steerlab simulate``: run the protocol for N simulated subjects through the engine.

Each trial records the LSL clock at its first sample (``lsl_clock_s``): synthetic time stamps
in batch mode, the host's in real time (:mod:`protocols.lsl_publisher`). Nothing is published
on LSL unless asked (``--lsl``, or ``STEERLAB_LSL=on``): a study of many subjects computed in
batch must not flood a lab's network with streams (``docs/lsl.md``).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from steerlab.hardware.sim.physiology import PopulationSpread, make_population
from steerlab.hardware.sim.world import WorldConfig
from steerlab.hardware.trial_loops import simulated_loop
from steerlab.protocols.datafile import (
    FORMAT,
    DataFileError,
    SessionFile,
    SessionWriter,
    check_free_space,
    creating_path,
    session_bytes,
    session_files,
)
from steerlab.protocols.engine import SessionEngine, State
from steerlab.protocols.events import TrialEnded
from steerlab.protocols.lsl_publisher import (
    SYNTHETIC,
    LabClock,
    close_lab_subscriber,
    lab_clock_for,
    lab_subscriber,
    publish_default,
)
from steerlab.protocols.names import inside
from steerlab.protocols.protocol import Protocol, VirtualWheel, load_protocol
from steerlab.protocols.session import build_plan, subject_id
from steerlab.protocols.writelock import LockedError, WriterLock


class SimulateError(ValueError):
    pass


@dataclass(frozen=True)
class SimulationJob:
    subject_number: int
    out_dir: str
    seed: int
    protocol_path: str | None
    realtime: bool
    world: WorldConfig
    resume: bool
    locked: bool = False  # the calling process holds the file's writer lock
    wheel: VirtualWheel | None = None  # the wheel the loop renders (None: the protocol's)
    wheel_used: dict | None = None  # which wheel, for the session file (see wheel_record)
    lsl: bool = False  # publish the session on LSL (docs/lsl.md)


def session_path(out_dir: str | Path, subject: str) -> Path:
    return Path(out_dir) / f"{subject}.h5"


def run_subject(job: SimulationJob, on_trial: Callable[[TrialEnded], None] | None = None) -> dict:
    """Run one simulated subject's session (or its remaining trials) into its session file."""
    protocol = load_protocol(job.protocol_path)
    # A world model from `steerlab diagnose` (hardware.sim.model_file) carries its own
    # per-condition behaviour; the population is drawn around it.
    population = make_population(
        job.subject_number, seed=job.seed, nominal=getattr(job.world, "baseline", None)
    )
    physiology = population[job.subject_number - 1]
    plan = build_plan(protocol, job.subject_number)
    path = session_path(job.out_dir, plan.subject)
    attempts = SessionFile(path).attempts() if (job.resume and path.exists()) else None
    loop, _ = simulated_loop(
        physiology,
        job.world,
        job.wheel or protocol.wheel,
        pace="paced" if job.realtime else "batch",
        spread=PopulationSpread(),
    )
    engine = SessionEngine(plan, loop, attempts=attempts)
    # In batch mode the samples come faster than real time: their LSL time stamps are synthetic.
    clock = lab_clock_for(loop) if job.realtime else LabClock(SYNTHETIC)
    writer = SessionWriter(
        path,
        lock=not job.locked,
        extra_attributes={
            "simulated": True,
            "simulation_seed": job.seed,
            "simulated_subject": physiology.to_dict(),
            "world": job.world.to_dict(),
            "wheel_used": job.wheel_used or wheel_record(protocol, None),
        },
        quanta=sensor_quanta(job.world),
        # Paced in real time: every 0.5 s, for readers following the file (SWMR) and to lose
        # at most that much in a crash. At full speed whole compressed chunks are written as
        # they fill (a part-full one rewritten later would leave its first version unused in
        # the file, and on a loaded machine 0.5 s of wall time passes within most trials); a
        # killed simulation re-runs its unfinished trial on --resume anyway.
        flush_interval_s=0.5 if job.realtime else 30.0,
        first_sample_attributes=clock.first_sample_attributes,
    )
    lab = lab_subscriber(
        clock,
        job.lsl,
        rig="simulated",
        session_path=path,
        nominal_rate_hz=protocol.loop_rate_hz,
    )
    engine.subscribe(lab)  # first: the clock reads each block's arrival (protocols.lsl_publisher)
    engine.subscribe(writer)
    if on_trial is not None:
        engine.subscribe(lambda e: on_trial(e) if isinstance(e, TrialEnded) else None)
    try:
        state = engine.run()
    finally:
        writer.close()
        close_lab_subscriber(lab)
    return {
        "subject": plan.subject,
        "state": state.value,
        "path": str(path),
        "remaining": len(engine.pending()),
    }


def sensor_quanta(world: WorldConfig) -> dict[str, float]:
    """The simulated sensors' resolution, for the writer to store those channels as counts:
    the encoder's rad per count (the same expression as the world's kernel) and the column
    torque sensor's N·m per count."""
    s = world.sensors
    out = {}
    if s.encoder_counts_per_rev:
        out["wheel_angle_rad"] = 2 * np.pi / s.encoder_counts_per_rev
    if s.torque_resolution:
        out["driver_torque_Nm"] = float(s.torque_resolution)
    return out


def _run_subject_reporting(job: SimulationJob, queue) -> dict:
    return run_subject(job, on_trial=lambda e: queue.put(f"{job.subject_number}:{e.key}"))


def check_output(
    out_dir: Path,
    subjects: list[str],
    *,
    resume: bool,
    overwrite: bool,
    protocol: Protocol | None = None,
) -> None:
    """Refuse to touch existing session files unless told how (never silently overwrite)."""
    if resume and overwrite:
        raise SimulateError("--resume and --overwrite exclude each other")
    if out_dir.exists() and not out_dir.is_dir():
        raise SimulateError(f"{out_dir}: exists and is not a directory")
    existing = [s for s in subjects if session_path(out_dir, s).exists()]
    if existing and not (resume or overwrite):
        raise SimulateError(
            f"{out_dir}: session files exist already for {', '.join(existing)}; "
            "pass --resume to complete them or --overwrite to replace them"
        )
    if resume:
        for s in existing:
            try:
                sf = SessionFile(session_path(out_dir, s))
            except DataFileError as e:
                raise SimulateError(f"cannot resume: {e}") from None
            if protocol is not None and sf.attrs.get("protocol_toml") != protocol.source_text:
                raise SimulateError(
                    f"cannot resume {sf.path}: it was recorded with a different protocol "
                    "(pass the same --protocol as the first run)"
                )


def wheel_record(protocol: Protocol, rig_model: dict | None) -> dict:
    """Which wheel a simulation used: the protocol's nominal one, or a rig check's."""
    if rig_model is None:
        w = protocol.wheel
        return {
            "source": "nominal",
            "detail": f"protocol {protocol.name}",
            "inertia_kgm2": w.inertia_kgm2,
            "damping_Nms_per_rad": w.damping_nms_per_rad,
            "stiffness_Nm_per_rad": w.stiffness_nm_per_rad,
        }
    from steerlab.analysis.rigcheck import PARAMS

    return {
        "source": "measured",
        "detail": rig_model["_path"],
        **{k: rig_model[k]["value"] for k in PARAMS},
        "vaf_percent": rig_model.get("vaf_percent"),
    }


def simulate_study(
    n_subjects: int,
    out_dir: str | Path,
    *,
    seed: int = 0,
    protocol_path: str | None = None,
    realtime: bool = False,
    resume: bool = False,
    overwrite: bool = False,
    jobs: int | None = None,
    world: WorldConfig | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    rig_model: str | Path | None = None,
    lsl: bool | None = None,
) -> list[dict]:
    """``rig_model``: a rig check's ``rig.json``: the simulated wheel is the measured one
    (inertia, rendered damping and stiffness, friction, imbalance, actuator lag).
    ``lsl``: publish each session on LSL (None: no, unless ``STEERLAB_LSL=on``)."""
    try:
        publish = publish_default(False) if lsl is None else bool(lsl)
    except ValueError as e:
        raise SimulateError(str(e)) from None
    if n_subjects < 1:
        raise SimulateError(f"--subjects must be ≥ 1, got {n_subjects}")
    # 0 would otherwise read as "not given" (the default) and a negative count as 1.
    if jobs is not None and jobs < 1:
        raise SimulateError(f"--jobs must be ≥ 1, got {jobs}")
    if seed < 0:
        raise SimulateError(f"--seed must be ≥ 0, got {seed}")
    protocol: Protocol = load_protocol(protocol_path)  # validates before anything is written
    out = Path(out_dir)
    subjects = [subject_id(i) for i in range(1, n_subjects + 1)]
    if resume and overwrite:
        raise SimulateError("--resume and --overwrite exclude each other")
    if out.exists() and not out.is_dir():
        raise SimulateError(f"{out}: exists and is not a directory")
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as held:
        try:
            # Every file this run writes or removes is locked first, then checked.
            for s in subjects:
                held.enter_context(WriterLock(inside(out, session_path(out, s))))
            check_output(out, subjects, resume=resume, overwrite=overwrite, protocol=protocol)
            stale = _stale_files(out, subjects) if overwrite else []
            for p in stale:
                held.enter_context(WriterLock(p))
        except (LockedError, SimulateError) as e:
            held.close()
            if created:
                with contextlib.suppress(OSError):
                    out.rmdir()
            if isinstance(e, LockedError):
                raise SimulateError(str(e)) from None
            raise
        check_free_space(out, n_subjects * session_bytes(build_plan(protocol, 1)))
        for s in subjects:
            creating_path(session_path(out, s)).unlink(missing_ok=True)  # a killed creation
        if overwrite:
            for s in subjects:
                session_path(out, s).unlink(missing_ok=True)
            for p in stale:
                p.unlink()
        return _simulate_locked(
            out, subjects, n_subjects, seed, protocol_path, protocol, realtime, resume, jobs,
            world, progress, rig_model, publish,
        )  # fmt: skip


def _stale_files(out: Path, subjects: list[str]) -> list[Path]:
    """Session files in ``out`` from an earlier study that ``--overwrite`` replaces. Anything
    there that is not a Steerlab session file is not ours to remove: refuse."""
    ours = {session_path(out, s).name for s in subjects}
    stale = []
    for p in session_files(out):
        if p.name in ours:
            continue
        if p.is_symlink() or not p.is_file():
            raise SimulateError(f"{p}: not a regular file; not removing it (--overwrite)")
        try:
            fmt = SessionFile(p).attrs.get("format")
        except DataFileError as e:
            raise SimulateError(
                f"--overwrite would leave {p} beside the new study and cannot tell what it is "
                f"({e}); move it away first"
            ) from None
        if fmt != FORMAT:
            raise SimulateError(f"{p}: not a Steerlab session file; move it away first")
        stale.append(p)
    return stale


def _simulate_locked(
    out: Path,
    subjects: list[str],
    n_subjects: int,
    seed: int,
    protocol_path: str | None,
    protocol: Protocol,
    realtime: bool,
    resume: bool,
    jobs: int | None,
    world: WorldConfig | None,
    progress: Callable[[int, int, str], None] | None,
    rig_model: str | Path | None = None,
    publish: bool = False,
) -> list[dict]:
    world = world or WorldConfig(fs_hz=protocol.loop_rate_hz)
    wheel, measured = None, None
    if rig_model is not None:
        from steerlab.analysis.rigcheck import load_rig_model, measured_world

        measured = load_rig_model(rig_model)
        world, wheel = measured_world(measured, world, protocol.wheel, protocol.loop_rate_hz)
    used = wheel_record(protocol, measured)
    jobs_list = [
        SimulationJob(
            i,
            str(out),
            seed,
            protocol_path,
            realtime,
            world,
            resume,
            locked=True,
            wheel=wheel,
            wheel_used=used,
            lsl=publish,
        )  # fmt: skip
        for i in range(1, n_subjects + 1)
    ]
    total = n_subjects * len(build_plan(protocol, 1).trials)
    done = 0

    def tick(label: str) -> None:
        nonlocal done
        done += 1
        if progress:
            progress(done, total, label)

    results = []
    jobs = jobs or min(n_subjects, os.cpu_count() or 1)
    if jobs <= 1 or realtime or n_subjects == 1:
        for job in jobs_list:
            results.append(run_subject(job, on_trial=lambda e: tick(e.key)))
    else:
        import multiprocessing as mp
        import queue as queue_mod

        with mp.Manager() as manager, ProcessPoolExecutor(max_workers=jobs) as pool:
            q = manager.Queue()
            futs = [pool.submit(_run_subject_reporting, j, q) for j in jobs_list]
            pending = set(futs)
            while pending:
                try:
                    tick(q.get(timeout=0.2))
                except queue_mod.Empty:
                    pass
                pending = {f for f in pending if not f.done()}
            while not q.empty():
                tick(q.get())
            for fut in as_completed(futs):
                results.append(fut.result())
    results.sort(key=lambda r: r["subject"])
    bad = [r for r in results if r["state"] != State.DONE.value]
    if bad:
        raise SimulateError(f"sessions not completed: {bad}")
    return results
