"""The loop process's PM QoS request (hardware.realtime.hold_shallow_idle): the kernel keeps
every CPU out of deep idle states while the process that asked lives, and no longer."""

import os
import subprocess
import sys
import time

import pytest

from steerlab.hardware.realtime import CPU_DMA_LATENCY, realtime_summary, realtime_warnings


def _current_us() -> int:
    fd = os.open(CPU_DMA_LATENCY, os.O_RDONLY)
    try:
        return int.from_bytes(os.read(fd, 4), sys.byteorder, signed=True)
    finally:
        os.close(fd)


@pytest.mark.skipif(
    not os.access(CPU_DMA_LATENCY, os.R_OK | os.W_OK), reason=f"{CPU_DMA_LATENCY} needs root"
)
def test_the_request_holds_while_the_process_lives():
    before = _current_us()
    child = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from steerlab.hardware.realtime import hold_shallow_idle;"
            "print(hold_shallow_idle(), flush=True); sys.stdin.read()",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert child.stdout.readline().strip() == "0"
        assert _current_us() == 0
    finally:
        child.stdin.close()
        child.wait(10)
    deadline = time.monotonic() + 5
    while _current_us() != before and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _current_us() == before


def test_a_refused_request_is_a_warning_and_in_the_summary():
    applied = {
        "sched_fifo_priority": 20,
        "mlockall": True,
        "cpu_dma_latency_us": "not permitted (Permission denied)",
        "cpus": [0, 1],
    }
    (warning,) = realtime_warnings(applied)
    assert "deep CPU idle states" in warning and "Permission denied" in warning
    assert "deep CPU idle allowed" in realtime_summary(applied)
    assert "shallow CPU idle" in realtime_summary({**applied, "cpu_dma_latency_us": 0})
    assert realtime_warnings({**applied, "cpu_dma_latency_us": 0}) == []


def test_a_machine_that_only_halts_is_named():
    # No cpuidle driver: the PM QoS request is granted but changes nothing; the summary and a
    # warning say so rather than "shallow CPU idle".
    applied = {"sched_fifo_priority": 20, "mlockall": True, "cpu_dma_latency_us": 0,
               "cpuidle_driver": "none", "cpus": [0, 1]}  # fmt: skip
    assert "halt only" in realtime_summary(applied)
    (warning,) = realtime_warnings(applied)
    assert "cpuidle driver: none" in warning and "bare metal" in warning
    assert realtime_warnings({**applied, "cpuidle_driver": "intel_idle"}) == []
    assert "shallow CPU idle" in realtime_summary({**applied, "cpuidle_driver": "intel_idle"})


@pytest.mark.realtime
def test_the_driver_reported_is_the_kernels():
    # tune_process in a process of its own (it takes SCHED_FIFO), read against sysfs directly.
    import json

    from steerlab.hardware.realtime import CPUIDLE_DRIVER

    code = (
        "import json; from steerlab.hardware.realtime import tune_process;"
        "print(json.dumps(tune_process(lock_memory=False)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    applied = json.loads(out.stdout)
    if os.path.exists(CPUIDLE_DRIVER):
        with open(CPUIDLE_DRIVER) as f:
            assert applied["cpuidle_driver"] == f.read().strip()
    else:
        assert "cpuidle_driver" not in applied
