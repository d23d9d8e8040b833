"""A value shared with an executor's workers (analysis.executors.share) reaches each worker
process once and is found there by later tasks."""

from __future__ import annotations

import concurrent.futures as cf
import os
import time

import numpy as np
import pytest

from steerlab.analysis.executors import (
    Shared,
    pool_cpu_clock,
    share,
    shared_value,
    sharing_pool,
)

VALUE = {"spectra": np.arange(1000.0).reshape(10, 100), "name": "set-up"}


def _same(a, b) -> bool:
    return a["name"] == b["name"] and np.array_equal(a["spectra"], b["spectra"])


def test_a_shared_value_is_unpickled_once_per_worker_process():
    with cf.ProcessPoolExecutor(max_workers=1) as ex:
        handle = share(ex, VALUE)
        assert isinstance(handle, Shared) and handle.pickled
        assert _same(ex.submit(shared_value, handle).result(), VALUE)
        # The same key without the value: only a worker that kept the value can answer.
        assert _same(ex.submit(shared_value, Shared(handle.key)).result(), VALUE)


def test_a_sharing_pool_installs_the_value_when_its_workers_start():
    pool, handle = sharing_pool(2, VALUE)
    with pool:
        assert handle.pickled is None
        got = [f.result() for f in [pool.submit(shared_value, handle) for _ in range(4)]]
    assert all(_same(g, VALUE) for g in got)


def test_a_worker_without_the_value_says_so():
    with cf.ProcessPoolExecutor(max_workers=1) as ex:
        with pytest.raises(RuntimeError, match="not started by sharing_pool"):
            ex.submit(shared_value, Shared("no-such-key")).result()


def test_on_dask_the_task_receives_the_value_itself():
    pytest.importorskip("distributed", reason="Dask is the optional extra steerlab[dask]")
    from steerlab.analysis.executors import executor_for

    with executor_for("local:1") as ex:
        assert ex is not None
        handle = share(ex, VALUE)
        assert not isinstance(handle, Shared)  # a scattered Dask future, not the pickle
        assert _same(ex.submit(shared_value, handle).result(), VALUE)


def _burn(seconds: float) -> float:
    t0 = time.process_time()
    while time.process_time() - t0 < seconds:
        pass
    return seconds


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="needs Linux's /proc")
def test_pool_cpu_clock_counts_the_workers_cpu_seconds():
    # The diagnosis' time limit with several jobs: the workers burn 0.6 CPU s each while this
    # process waits, so its own process_time hardly moves and wall time depends on the load.
    with cf.ProcessPoolExecutor(2) as pool:
        clock = pool_cpu_clock(pool)
        assert clock is not None
        own0, c0 = time.process_time(), clock()
        assert list(pool.map(_burn, [0.6, 0.6])) == [0.6, 0.6]
        used = clock() - c0
        own = time.process_time() - own0
        assert own < 0.3
        assert 1.1 < used - own < 1.6  # the workers' 1.2 s, and a little start-up
        # Never decreasing, also once the workers have ended.
        before = clock()
    assert clock() >= before
    assert pool_cpu_clock(None) is None
