"""Real-time tuning of the control loop's process, applied where the process has the rights.

What a lab does for hard guarantees, and what Steerlab does:

- the loop in a process of its own, away from the file writer and the GUI: always
  (``hardware.live.ProcessLoop``);
- a short interpreter switch interval, so other threads hand the GIL back within 0.2 ms: always;
- garbage collection paused during a trial: always (the loop process collects between trials);
- ``SCHED_FIFO`` priority for the loop process's threads: when permitted (root, CAP_SYS_NICE),
  and only once the process's heavy start-up (imports, compiling the kernels, building the
  simulated world) is done: a FIFO process busy for seconds starves every other of its
  priority on that CPU (a second session's start-up stopped the first one's glove stream);
- memory locked with ``mlockall`` (no page faults inside the loop): when permitted;
- CPU idle states limited to the shallowest (a PM QoS request of 0 µs on
  ``/dev/cpu_dma_latency``, held while the process lives, as ``cyclictest`` does): when
  permitted. An idle core otherwise sleeps in a state it leaves in tens to hundreds of µs. The
  request only acts through a cpuidle driver: where the kernel has none (``cpuidle_driver``
  "none", as on the 2-core development VM) the CPUs halt when idle whatever is asked, and in a
  virtual machine each wake-up goes through the hypervisor; the summary and a warning say so;
- isolated cores (``isolcpus``, cpusets) and a PREEMPT_RT kernel: the lab's system
  administration, not something a program should do to its host.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import sys

#: For a process that will run under SCHED_FIFO: BLAS and OpenMP worker threads busy-wait for
#: work, and at real-time priority two such processes (two sessions on one machine) starve each
#: other for good (seen: two loop processes stuck in scipy's expm at start-up). The loop's linear
#: algebra is 4×4; one thread is all it needs. Set before numpy is imported (in the child).
SINGLE_THREADED_MATH = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

SWITCH_INTERVAL_S = 2e-4
FIFO_PRIORITY = 20
MCL_CURRENT, MCL_FUTURE = 1, 2
CPU_DMA_LATENCY = "/dev/cpu_dma_latency"
#: The kernel's CPU idle driver. "none": the CPUs idle by halting (x86 HLT), the only idle state,
#: so no PM QoS request changes how they idle (seen on the 2-core development VM).
CPUIDLE_DRIVER = "/sys/devices/system/cpu/cpuidle/current_driver"
#: The open PM QoS request: the kernel keeps it while the file is open (this process's life).
_dma_latency_fd: int | None = None


@contextlib.contextmanager
def single_threaded_math_for_children():
    """Within the block, child processes started (spawn, subprocess) get
    :data:`SINGLE_THREADED_MATH` in their environment."""
    saved = {k: os.environ.get(k) for k in SINGLE_THREADED_MATH}
    os.environ.update(SINGLE_THREADED_MATH)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


#: ``STEERLAB_REALTIME=off`` in the environment: no SCHED_FIFO and no mlockall even where
#: permitted, as for a user without the rights (``python -m benchmarks live_loop --no-realtime``,
#: and the tests of the start-up warnings, on a machine where the tests run as root).
REALTIME_ENV = "STEERLAB_REALTIME"


def tune_process(*, fifo: bool = True, lock_memory: bool = True) -> dict:
    """Apply what is permitted; return what was applied, for the session file."""
    applied: dict[str, object] = {}
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    applied["switch_interval_s"] = SWITCH_INTERVAL_S
    if os.environ.get(REALTIME_ENV) == "off":
        fifo = lock_memory = False
        applied["sched_fifo_priority"] = f"not requested ({REALTIME_ENV}=off)"
        applied["mlockall"] = f"not requested ({REALTIME_ENV}=off)"
    if fifo and hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
            applied["sched_fifo_priority"] = FIFO_PRIORITY
        except OSError as e:
            applied["sched_fifo_priority"] = f"not permitted ({e.strerror})"
        else:
            # Linux sets a thread's policy, not the process's: the threads started before
            # (e.g. the simulated lab's, started before its heavy set-up) join in. Threads
            # started later inherit it.
            _fifo_for_other_threads()
    if lock_memory:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            if libc.mlockall(MCL_CURRENT | MCL_FUTURE) == 0:
                applied["mlockall"] = True
            else:
                applied["mlockall"] = f"not permitted ({os.strerror(ctypes.get_errno())})"
        except OSError as e:
            applied["mlockall"] = f"unavailable ({e})"
    if fifo:
        applied["cpu_dma_latency_us"] = hold_shallow_idle()
        driver = cpuidle_driver()
        if driver is not None:
            applied["cpuidle_driver"] = driver
    try:
        applied["cpus"] = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        pass
    return applied


def hold_shallow_idle() -> object:
    """Ask the kernel (PM QoS) to keep every CPU in its shallowest idle state while this
    process lives; 0 (the latency in µs) when granted, else why not."""
    global _dma_latency_fd
    if _dma_latency_fd is not None:
        return 0
    try:
        fd = os.open(CPU_DMA_LATENCY, os.O_WRONLY)
    except OSError as e:
        return f"not permitted ({e.strerror})"
    try:
        os.write(fd, (0).to_bytes(4, sys.byteorder, signed=True))
    except OSError as e:
        os.close(fd)
        return f"not permitted ({e.strerror})"
    _dma_latency_fd = fd
    return 0


def cpuidle_driver() -> str | None:
    """The CPU idle driver the kernel uses ("none": halt only); None where Linux does not say."""
    try:
        with open(CPUIDLE_DRIVER) as f:
            return f.read().strip()
    except OSError:
        return None


def _halts_only(applied: dict) -> bool:
    return applied.get("cpuidle_driver") == "none"


def _fifo_for_other_threads() -> None:
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return
    for tid in tids:
        try:
            if os.sched_getscheduler(tid) == os.SCHED_OTHER:
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
        except OSError:  # ended meanwhile
            pass


def realtime_summary(applied: dict) -> str:
    """One line for the terminal at start-up: what the loop process got."""
    fifo = applied.get("sched_fifo_priority")
    prio = f"SCHED_FIFO {fifo}" if isinstance(fifo, int) else f"no SCHED_FIFO ({fifo})"
    lock = applied.get("mlockall")
    mem = "memory locked" if lock is True else f"memory not locked ({lock})"
    cpus = applied.get("cpus")
    where = f"CPUs {cpus}" if cpus is not None else "CPUs unknown"
    idle = applied.get("cpu_dma_latency_us")
    if idle is None:
        return f"control loop: {prio}, {mem}, {where}"
    if _halts_only(applied):
        shallow = "CPU idle: halt only (no cpuidle driver)"
    else:
        shallow = "shallow CPU idle" if idle == 0 else f"deep CPU idle allowed ({idle})"
    return f"control loop: {prio}, {mem}, {shallow}, {where}"


def realtime_warnings(applied: dict) -> list[str]:
    """What the loop process did not get, as warnings for the terminal and the GUI (empty when
    it got its real-time priority and locked memory, and has a core besides the others)."""
    out = []
    fifo = applied.get("sched_fifo_priority")
    if not isinstance(fifo, int):
        out.append(
            f"the control loop runs without real-time priority (SCHED_FIFO: {fifo}); expect "
            "late cycles when the computer is busy (run as root or grant CAP_SYS_NICE)"
        )
    if applied.get("mlockall") is not True:
        out.append(
            f"the control loop's memory is not locked (mlockall: {applied.get('mlockall')}); a "
            "page fault can delay a cycle (grant CAP_IPC_LOCK or raise RLIMIT_MEMLOCK)"
        )
    idle = applied.get("cpu_dma_latency_us")
    if idle is not None and idle != 0:
        out.append(
            f"deep CPU idle states stay allowed ({CPU_DMA_LATENCY}: {idle}); waking an idle "
            "core can delay the drive's answers by a cycle (run as root, or disable deep "
            "C-states in the BIOS or with the kernel's idle settings)"
        )
    if _halts_only(applied):
        out.append(
            "this machine's CPUs idle by halting whatever Steerlab asks (cpuidle driver: none); "
            "in a virtual machine every wake-up then goes through the hypervisor and the "
            "drive's answers can come late: run sessions with people on a lab PC on bare metal "
            "(docs/live-loop.md)"
        )
    cpus = applied.get("cpus")
    if cpus is not None and len(cpus) < 2:
        out.append(f"the control loop may use only CPU {cpus}: it shares it with everything else")
    return out
