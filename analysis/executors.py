"""Where the parallel work of a report, a diagnosis or a benchmark runs.

The per-trial analysis, the per-subject arm fits and the diagnosis's candidate fits take any
``concurrent.futures.Executor``. :func:`executor_for` turns a command line's ``--scheduler``
into one:

- ``None``: no executor; the caller uses ``jobs`` local processes (or this process);
- ``"local"`` or ``"local:N"``: a Dask ``LocalCluster`` on this machine (N worker processes,
  one thread each; N defaults to ``jobs``), for trying Dask without a cluster;
- anything else (``"tcp://10.0.0.5:8786"``, a scheduler file's path): the address of a running
  Dask scheduler (``dask scheduler`` on one machine, ``dask worker ADDRESS`` on each other).

Dask is optional (``pip install 'steerlab[dask]'``). The work sent to the workers is plain
functions of plain data, so the results do not depend on where they ran (tested on a
``LocalCluster`` against the in-process run).

Work that needs one large value in every task (the diagnosis's set-up: every trial's spectra)
sends it once per worker, not once per task, through :func:`share` or :func:`sharing_pool`;
the task gets it back with :func:`shared_value`.
"""

from __future__ import annotations

import concurrent.futures as cf
import os
import pickle
import time
import uuid
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any


class SchedulerError(RuntimeError):
    """A ``--scheduler`` that cannot be used (Dask missing, no scheduler at the address)."""


def _parse_local(scheduler: str, jobs: int) -> int | None:
    if scheduler == "local":
        return max(1, jobs)
    if scheduler.startswith("local:"):
        n = scheduler.partition(":")[2]
        if not n.isdigit() or int(n) < 1:
            raise SchedulerError(f"--scheduler {scheduler!r}: 'local:N' needs a worker count N ≥ 1")
        return int(n)
    return None


@contextmanager
def executor_for(
    scheduler: str | None, jobs: int = 1, connect_timeout_s: float = 10.0
) -> Iterator[cf.Executor | None]:
    """The executor for ``scheduler`` (see the module docstring), closed on leaving."""
    if not scheduler:
        yield None
        return
    n_local = _parse_local(scheduler, jobs)
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise SchedulerError(
            f"--scheduler {scheduler!r} needs Dask distributed: pip install 'steerlab[dask]'"
        ) from None
    cluster = None
    try:
        if n_local is not None:
            cluster = LocalCluster(
                n_workers=n_local, threads_per_worker=1, processes=True, dashboard_address=None
            )
            client = Client(cluster)
        else:
            kw = {"scheduler_file": scheduler} if Path(scheduler).is_file() else {}
            client = Client(**kw) if kw else Client(scheduler, timeout=f"{connect_timeout_s}s")
    except (OSError, TimeoutError) as e:
        if cluster is not None:
            cluster.close()
        raise SchedulerError(f"--scheduler {scheduler!r}: no Dask scheduler there ({e})") from e
    executor = client.get_executor()
    _DASK_CLIENTS[executor] = client
    try:
        yield executor
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# The Dask client behind each executor executor_for made: share() scatters through it.
_DASK_CLIENTS: weakref.WeakKeyDictionary[cf.Executor, Any] = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class Shared:
    """A value that tasks find in their worker process's cache under ``key``; ``pickled``
    brings it to a worker that does not have it yet (None: installed when the worker
    started, by :func:`sharing_pool`)."""

    key: str
    pickled: bytes | None = None


# One value per worker process, the latest: a diagnosis shares one set-up at a time, and a
# long-lived Dask worker must not keep every study it ever saw.
_WORKER_CACHE: dict[str, object] = {}


def _install(key: str, value: object) -> None:
    _WORKER_CACHE.clear()
    _WORKER_CACHE[key] = value


def share(executor: cf.Executor, value: object) -> object:
    """A handle to pass to tasks on ``executor`` instead of ``value``; in the task,
    :func:`shared_value` turns it back into the value.

    On Dask (an executor of :func:`executor_for`) the value is scattered to every worker
    once, and Dask hands the task the value itself. On any other executor the handle carries
    the value pickled, and each worker process unpickles it once (tasks that find it in the
    worker's cache skip that).
    """
    client = _DASK_CLIENTS.get(executor)
    if client is not None:
        return client.scatter(value, broadcast=True, hash=False)
    return Shared(uuid.uuid4().hex, pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))


def sharing_pool(jobs: int, value: object) -> tuple[cf.ProcessPoolExecutor, Shared]:
    """A pool of ``jobs`` processes that each hold ``value`` from their start, and the
    handle that finds it there (nothing of the value travels with the tasks)."""
    handle = Shared(uuid.uuid4().hex)
    pool = cf.ProcessPoolExecutor(
        max_workers=jobs, initializer=_install, initargs=(handle.key, value)
    )
    return pool, handle


def pool_cpu_clock(pool: cf.Executor | None) -> Callable[[], float] | None:
    """A clock of CPU seconds: this process's plus those of ``pool``'s worker processes
    (a ``ProcessPoolExecutor``), never decreasing (a worker that has ended keeps what it
    used). None where the workers' CPU time cannot be read (no ``/proc``: not Linux).

    A time limit on this clock does not depend on the machine's load or the number of
    workers, as one on ``time.process_time`` in a single process does not."""
    if pool is None or not hasattr(pool, "_processes") or not os.path.exists("/proc/self/stat"):
        return None
    tick = os.sysconf("SC_CLK_TCK")
    used: dict[int, float] = {}

    def clock() -> float:
        for pid in list(getattr(pool, "_processes", None) or {}):
            try:
                with open(f"/proc/{pid}/stat", "rb") as f:
                    # utime and stime: fields 14 and 15, after the parenthesised name.
                    fields = f.read().rsplit(b")", 1)[1].split()
                used[pid] = (int(fields[11]) + int(fields[12])) / tick
            except (OSError, IndexError, ValueError):
                pass  # ended: its last reading stays
        return time.process_time() + sum(used.values())

    return clock


def travels_light(handle: object) -> bool:
    """Whether a task's handle of :func:`share` or :func:`sharing_pool` is small: it does not
    carry the value (an executor we were given that is not Dask's gets it with every task,
    too dear for tasks of a few tens of milliseconds)."""
    return not (isinstance(handle, Shared) and handle.pickled is not None)


def shared_value(handle: object) -> Any:
    """In a task: the value behind a handle of :func:`share` or :func:`sharing_pool`."""
    if not isinstance(handle, Shared):
        return handle  # Dask resolved its scattered value before calling the task
    try:
        return _WORKER_CACHE[handle.key]
    except KeyError:
        if handle.pickled is None:
            raise RuntimeError(
                "shared_value: this process was not started by sharing_pool and the handle "
                "carries no value"
            ) from None
    value = pickle.loads(handle.pickled)
    _install(handle.key, value)
    return value
