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
"""

from __future__ import annotations

import concurrent.futures as cf
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


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
    try:
        yield client.get_executor()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
