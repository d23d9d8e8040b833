"""One-way messages from the loop process to the engine, safe against the sender's death.

The loop process hands its blocks of samples to the engine through a pipe. A
``multiprocessing.Queue`` did that before, and could hang the engine for good: a process killed
while its queue's thread was half-way through writing a block larger than the pipe's buffer
leaves half a message in the pipe, the engine's ``get`` waits for the rest, and since the
engine's process holds the queue's write end too, no end-of-file ever tells it the writer is
gone (found under load in the everyday test tier, ``test_loop_process_dies_mid_trial``).

Here each end is owned by one process: :func:`message_pipe` gives the reader and the write end
to hand to the child, which the parent closes once the child holds it (:meth:`Inbox.started`).
A thread of the reader's own reads the pipe, so :meth:`Inbox.get` never waits longer than its
timeout, and the writer's death, half a message or not, arrives as :class:`WriterGone` once
everything it sent whole has been read. On the sender's side :class:`Outbox` never blocks the
loop: a thread of its own writes.
"""

from __future__ import annotations

import queue
import sys
import threading
import traceback
from multiprocessing.connection import Connection

_GONE = object()
_END = object()


class _Failed:
    def __init__(self, error: BaseException) -> None:
        self.error = error


class WriterGone(EOFError):
    """The sending process closed its end or died; every whole message it sent was read."""


def message_pipe(ctx) -> tuple[Inbox, Connection]:
    """The engine's :class:`Inbox` and the write end for the child (give it to an
    :class:`Outbox` there)."""
    reader, writer = ctx.Pipe(duplex=False)
    return Inbox(reader, writer), writer


class Inbox:
    """The receiving end: messages in the order sent, read by a thread of its own."""

    def __init__(self, reader: Connection, writer: Connection | None = None) -> None:
        self._conn = reader
        self._writer = writer
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._gone = False
        self._thread = threading.Thread(target=self._read, name="steerlab-inbox", daemon=True)
        self._thread.start()

    def started(self) -> None:
        """The child holds the write end now: close ours, so that its death reads as the end."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def _read(self) -> None:
        while True:
            try:
                msg = self._conn.recv()
            except (EOFError, OSError):  # a message cut short reads as EOF too
                self._q.put(_GONE)
                return
            except BaseException as e:  # one that cannot be unpickled: raised by get(), there
                self._q.put(_Failed(e))
                continue
            self._q.put(msg)

    def get(self, timeout: float | None = None):
        """The next message; ``queue.Empty`` after ``timeout`` s without one, :class:`WriterGone`
        once the writer is gone and all it sent whole has been taken; a message that could not
        be unpickled raises its error here, in order, and the messages after it still come."""
        if self._gone:
            raise WriterGone
        msg = self._q.get(timeout=timeout)
        if msg is _GONE:
            self._gone = True
            raise WriterGone
        if isinstance(msg, _Failed):
            raise msg.error
        return msg

    def close(self) -> None:
        self.started()
        # The reading thread ends at the writer's end of file; a daemon, it never holds up exit.
        self._thread.join(1.0)
        if not self._thread.is_alive():
            self._conn.close()


class Outbox:
    """The sending end, in the child: :meth:`put` only queues, a thread writes to the pipe (as
    ``multiprocessing.Queue`` does), so a slow reader never holds up the loop."""

    def __init__(self, writer: Connection) -> None:
        self._conn = writer
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._write, name="steerlab-outbox", daemon=True)
        self._thread.start()

    def put(self, msg) -> None:
        self._q.put(msg)

    def _write(self) -> None:
        while (msg := self._q.get()) is not _END:
            try:
                self._conn.send(msg)
            except (OSError, EOFError):  # the reader is gone: nobody to tell
                return
            except Exception:  # one message that cannot be pickled; say so, send the rest
                print(f"steerlab: a message could not be sent: {msg!r:.200}", file=sys.stderr)
                traceback.print_exc()

    def close(self, timeout: float = 10.0) -> None:
        """Send what is queued (up to ``timeout`` s), then close the pipe."""
        self._q.put(_END)
        self._thread.join(timeout)
        self._conn.close()
