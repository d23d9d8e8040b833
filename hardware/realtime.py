"""Real-time tuning of the control loop's process, applied where the process has the rights.

What a lab does for hard guarantees, and what Steerlab does:

- the loop in a process of its own, away from the file writer and the GUI: always
  (``hardware.live.ProcessLoop``);
- a short interpreter switch interval, so other threads hand the GIL back within 0.2 ms: always;
- garbage collection paused during a trial: always (the loop process collects between trials);
- ``SCHED_FIFO`` priority for the loop process's threads: when permitted (root, CAP_SYS_NICE);
- memory locked with ``mlockall`` (no page faults inside the loop): when permitted;
- isolated cores (``isolcpus``, cpusets) and a PREEMPT_RT kernel: the lab's system
  administration, not something a program should do to its host.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

SWITCH_INTERVAL_S = 2e-4
FIFO_PRIORITY = 20
MCL_CURRENT, MCL_FUTURE = 1, 2


def tune_process(*, fifo: bool = True, lock_memory: bool = True) -> dict:
    """Apply what is permitted; return what was applied, for the session file."""
    applied: dict[str, object] = {}
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    applied["switch_interval_s"] = SWITCH_INTERVAL_S
    if fifo and hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
            applied["sched_fifo_priority"] = FIFO_PRIORITY
        except OSError as e:
            applied["sched_fifo_priority"] = f"not permitted ({e.strerror})"
    if lock_memory:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            if libc.mlockall(MCL_CURRENT | MCL_FUTURE) == 0:
                applied["mlockall"] = True
            else:
                applied["mlockall"] = f"not permitted ({os.strerror(ctypes.get_errno())})"
        except OSError as e:
            applied["mlockall"] = f"unavailable ({e})"
    return applied
