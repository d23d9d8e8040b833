"""The loop process's messages to the engine: a writer killed mid-message cannot hang the reader.

Real processes (spawn), real pipes, real SIGKILL.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import signal
import struct
import time

import numpy as np
import pytest

from steerlab.hardware.messages import Inbox, Outbox, WriterGone, message_pipe

CTX = mp.get_context("spawn")


def _half_message_then_sleep(end) -> None:
    out = Outbox(end)
    out.put(("block", np.arange(5.0)))
    out.put(("status", {"ok": True}))
    time.sleep(0.5)  # both written whole
    os.write(end.fileno(), struct.pack("!i", 1_000_000) + b"x" * 1000)
    time.sleep(60)


def _start(target):
    inbox, end = message_pipe(CTX)
    proc = CTX.Process(target=target, args=(end,), daemon=True)
    proc.start()
    inbox.started()
    return inbox, proc


def test_a_writer_killed_mid_message_reads_as_gone_after_its_whole_messages():
    inbox, proc = _start(_half_message_then_sleep)
    try:
        kind, block = inbox.get(timeout=30)
        assert kind == "block" and np.array_equal(block, np.arange(5.0))
        assert inbox.get(timeout=10) == ("status", {"ok": True})
        time.sleep(1.0)  # the half message is in the pipe now
        os.kill(proc.pid, signal.SIGKILL)
        t0 = time.monotonic()
        with pytest.raises(WriterGone):
            while time.monotonic() - t0 < 10:
                try:
                    inbox.get(timeout=0.1)
                except queue.Empty:
                    continue
        assert time.monotonic() - t0 < 10
        with pytest.raises(WriterGone):  # and stays gone
            inbox.get(timeout=0.1)
    finally:
        proc.kill()
        proc.join(5)
        inbox.close()


def test_a_live_writer_mid_message_never_holds_get_past_its_timeout():
    inbox, proc = _start(_half_message_then_sleep)
    try:
        inbox.get(timeout=30)
        inbox.get(timeout=10)
        time.sleep(1.0)
        t0 = time.monotonic()
        with pytest.raises(queue.Empty):
            inbox.get(timeout=0.2)
        assert time.monotonic() - t0 < 2.0
    finally:
        proc.kill()
        proc.join(5)
        inbox.close()


def _put_much_then_close(end) -> None:
    out = Outbox(end)
    t0 = time.monotonic()
    for i in range(200):  # 200 × 80 kB: far more than a pipe holds, nobody reading yet
        out.put(("block", np.full(10_000, float(i))))
    took = time.monotonic() - t0
    out.put(("took", took))
    out.close()


def test_put_never_waits_for_the_reader_and_close_delivers_everything():
    # A raw pipe nobody reads for 2 s: a put that wrote to the pipe itself would wait for it.
    reader, end = CTX.Pipe(duplex=False)
    proc = CTX.Process(target=_put_much_then_close, args=(end,), daemon=True)
    proc.start()
    end.close()
    try:
        time.sleep(2.0)
        inbox = Inbox(reader)
        got = [inbox.get(timeout=30) for _ in range(201)]
        assert [float(b[1][0]) for b in got[:200]] == [float(i) for i in range(200)]
        kind, took = got[200]
        assert kind == "took" and took < 1.0
        proc.join(10)
        assert proc.exitcode == 0
        with pytest.raises(WriterGone):
            inbox.get(timeout=5)
        inbox.close()
    finally:
        proc.kill()
