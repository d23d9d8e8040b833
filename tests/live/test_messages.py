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
from contextlib import contextmanager

import numpy as np
import pytest

from steerlab.hardware.messages import Inbox, Outbox, WriterGone, message_pipe

CTX = mp.get_context("spawn")


def _half_message_then_sleep(end, written) -> None:
    out = Outbox(end)
    out.put(("block", np.arange(5.0)))
    out.put(("status", {"ok": True}))
    time.sleep(0.5)  # both written whole
    os.write(end.fileno(), struct.pack("!i", 1_000_000) + b"x" * 1000)
    written.set()
    time.sleep(60)


@contextmanager
def _writer(target, *args):
    """A spawned process running ``target(end, *args)`` on the write end of an Inbox's pipe;
    killed, and the inbox closed, on leaving."""
    inbox, end = message_pipe(CTX)
    proc = CTX.Process(target=target, args=(end, *args), daemon=True)
    proc.start()
    inbox.started()
    try:
        yield inbox, proc
    finally:
        proc.kill()
        proc.join(5)
        inbox.close()


@contextmanager
def _half_message_written():
    written = CTX.Event()
    with _writer(_half_message_then_sleep, written) as (inbox, proc):
        assert written.wait(30)
        yield inbox, proc


def test_a_writer_killed_mid_message_reads_as_gone_after_its_whole_messages():
    with _half_message_written() as (inbox, proc):
        kind, block = inbox.get(timeout=30)
        assert kind == "block" and np.array_equal(block, np.arange(5.0))
        assert inbox.get(timeout=10) == ("status", {"ok": True})
        os.kill(proc.pid, signal.SIGKILL)  # the half message is in the pipe
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


def test_a_live_writer_mid_message_never_holds_get_past_its_timeout():
    with _half_message_written() as (inbox, _proc):
        inbox.get(timeout=30)
        inbox.get(timeout=10)
        t0 = time.monotonic()
        with pytest.raises(queue.Empty):
            inbox.get(timeout=0.2)
        assert time.monotonic() - t0 < 2.0


def _put_much_then_close(end, putting) -> None:
    out = Outbox(end)
    putting.set()
    t0 = time.monotonic()
    for i in range(200):  # 200 × 80 kB: far more than a pipe holds, nobody reading yet
        out.put(("block", np.full(10_000, float(i))))
    took = time.monotonic() - t0
    out.put(("took", took))
    out.close()


def test_put_never_waits_for_the_reader_and_close_delivers_everything():
    # A raw pipe nobody reads for 2 s: a put that wrote to the pipe itself would wait for it.
    reader, end = CTX.Pipe(duplex=False)
    putting = CTX.Event()
    proc = CTX.Process(target=_put_much_then_close, args=(end, putting), daemon=True)
    proc.start()
    end.close()
    try:
        assert putting.wait(30)
        time.sleep(2.0)
        inbox = Inbox(reader)
        got = [inbox.get(timeout=30) for _ in range(201)]
        assert [float(b[1][0]) for b in got[:200]] == [float(i) for i in range(200)]
        kind, took = got[200]
        assert kind == "took" and took < 1.0  # a put that wrote to the pipe: ≥ 2 s
        proc.join(10)
        assert proc.exitcode == 0
        with pytest.raises(WriterGone):
            inbox.get(timeout=5)
        inbox.close()
    finally:
        proc.kill()


class _Unloadable:
    """Pickles, but cannot be unpickled (as a message from a newer loop might not be)."""

    def __reduce__(self):
        return (_refuse, ())


def _refuse():
    raise ValueError("cannot be rebuilt here")


def _send_unloadable_between(end) -> None:
    out = Outbox(end)
    out.put(("block", 1))
    out.put(("bad", _Unloadable()))
    out.put(("end", 2))
    out.close()


def test_a_message_that_cannot_be_unpickled_raises_in_order_and_the_rest_still_comes():
    with _writer(_send_unloadable_between) as (inbox, _proc):
        assert inbox.get(timeout=30) == ("block", 1)
        with pytest.raises(ValueError, match="cannot be rebuilt"):
            inbox.get(timeout=10)
        assert inbox.get(timeout=10) == ("end", 2)
        with pytest.raises(WriterGone):
            inbox.get(timeout=10)
