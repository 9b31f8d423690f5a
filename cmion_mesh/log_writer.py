"""The thread that writes a process's log lines (``logs.configure`` installs it): the thread
that logs a line only hands the record over (``Handoff``), and the writer (``Writer``, thread
``logs-writer``) formats and writes the lines in batches, one write for what came in ``LINGER``.

The queue is bounded: when full, records are dropped and counted, never waited for, and the
count is written in a line of its own. ``Writer.flush`` waits until what was logged is written;
``Writer.stop`` writes what is queued and ends the thread, after which records are written at
once by the thread that logs them.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import signal
import threading
from collections.abc import Callable
from typing import Any, Final

#: Records waiting to be written, at most (below error: errors may use as many again).
QUEUE_SIZE: Final = 10_000
#: Records written together, at most: one write and one flush for them all.
BATCH: Final = 500
#: How long the writer waits, once a record came, for more to write with it (seconds): one wake-up
#: and one write for every line of a burst rather than each, so that the thread that logs them
#: (the update loop) shares the interpreter with the writer less often.
LINGER: Final = 0.02
#: How long ``flush``, ``shutdown`` and ``unconfigure`` wait for the writer, at most (seconds).
DRAIN_TIMEOUT: Final = 5.0
WRITER_THREAD: Final = "logs-writer"

#: Arguments that cannot change once the record is made: formatted later, on the writer.
_IMMUTABLE: Final = frozenset({str, int, float, bool, type(None)})


class _Stop:
    """The writer's last item: what is before it is written, then the thread ends."""


class Writer:
    """One thread that writes the records handed to it, in batches, through ``target`` (its
    formatter and stream). A record costs its caller one put in a queue; the line is formatted and
    written here. The queue is bounded: when full, records are dropped and counted, never waited
    for, and the count is written in a line of its own."""

    def __init__(self, target: logging.StreamHandler[Any], embodiment: Callable[[], str | None]) -> None:
        self.target, self.embodiment = target, embodiment
        self.queue: queue.SimpleQueue[logging.LogRecord | threading.Event | _Stop] = queue.SimpleQueue()
        self._dropped = 0
        self._dropped_lock = threading.Lock()
        self.stopped = False  # then records are written at once, by the thread that logs them
        self._hurry = threading.Event()  # a flush or stop is waiting: no lingering
        self.thread = threading.Thread(target=self._run, name=WRITER_THREAD, daemon=True)
        # Started with every signal blocked (a thread inherits its creator's mask): a daemon collects
        # SIGINT/SIGTERM on its main thread with sigwait (``signals.Stopper``), and a signal the
        # kernel handed to this thread instead would take the default action, ending the process.
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, signal.valid_signals())
        try:
            self.thread.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)

    def put(self, record: logging.LogRecord) -> None:
        if self.stopped:
            self.write([record])
            return
        size = self.queue.qsize()
        # Errors are not dropped until the queue holds twice its size: they are the lines that matter.
        if size >= QUEUE_SIZE and (record.levelno < logging.ERROR or size >= 2 * QUEUE_SIZE):
            with self._dropped_lock:
                self._dropped += 1
            return
        self.queue.put(record)

    def flush(self, timeout: float = DRAIN_TIMEOUT) -> bool:
        """Wait until what was put before is written (at most ``timeout``): True when it is."""
        if not self.thread.is_alive() or threading.current_thread() is self.thread:
            return not self.thread.is_alive()
        done = threading.Event()
        self.queue.put(done)
        self._hurry.set()
        return done.wait(timeout)

    def stop(self, timeout: float = DRAIN_TIMEOUT) -> None:
        """Write what is queued, then end the thread (waiting ``timeout`` at most; idempotent)."""
        self.stopped = True
        if threading.current_thread() is self.thread:
            return
        if self.thread.is_alive():
            self.queue.put(_Stop())
            self._hurry.set()
            self.thread.join(timeout)
        if not self.thread.is_alive():  # what was put while it stopped (not when the stream is stuck)
            self._handle(self._drain(None))

    def _drain(self, first: object) -> list[object]:
        batch = [first] if first is not None else []
        while len(batch) < BATCH or first is None:
            try:
                batch.append(self.queue.get_nowait())
            except queue.Empty:
                break
        return batch

    def _handle(self, batch: list[object]) -> bool:
        """Write the records of ``batch`` and tell the waiting ``flush``es: True when it says stop."""
        stopping = False
        records: list[logging.LogRecord] = []
        marks: list[threading.Event] = []
        for item in batch:
            if isinstance(item, logging.LogRecord):
                records.append(item)
            elif isinstance(item, threading.Event):
                marks.append(item)
            else:
                stopping = True
        with self._dropped_lock:
            dropped, self._dropped = self._dropped, 0
        if dropped:
            records.append(self._dropped_record(dropped))
        self.write(records)
        for mark in marks:
            mark.set()
        return stopping

    def _run(self) -> None:
        while True:
            first = self.queue.get()
            if isinstance(first, logging.LogRecord):
                self._hurry.wait(LINGER)
            self._hurry.clear()  # before the drain: a flush coming after it sets it again
            if self._handle(self._drain(first)):
                return

    def write(self, records: list[logging.LogRecord]) -> None:
        """Format ``records`` and write them with one write and one flush (on any thread)."""
        target = self.target
        lines = []
        for record in records:
            try:
                line = getattr(record, "_logs_line", None)  # formatted on the caller's thread (see ``Handoff``)
                lines.append(line if isinstance(line, str) else target.format(record))
            except Exception:
                target.handleError(record)
        if not lines:
            return
        text = "\n".join(lines) + "\n"
        with target.lock or contextlib.nullcontext():
            try:
                reopen = getattr(target, "reopenIfNeeded", None)
                if reopen is not None:  # a WatchedFileHandler: logrotate moved the file, write to the new one
                    reopen()
                if target.stream is None and isinstance(target, logging.FileHandler):
                    # Closed by someone else's ``logging.config.dictConfig`` (uvicorn's, when a web
                    # body starts): opened again, as ``FileHandler.emit`` does.
                    target.stream = target._open()
                stream = target.stream
                stream.write(text)
                stream.flush()
            except Exception:
                target.handleError(records[-1])

    def _dropped_record(self, count: int) -> logging.LogRecord:
        record = logging.getLogger(__name__).makeRecord(
            __name__, logging.WARNING, __file__, 0, "%d log lines dropped: more came than could be written", (count,),
            None, extra={"fields": {"dropped": count}})
        record.embodiment = self.embodiment()
        return record


class Handoff(logging.Handler):
    """The handler ``configure`` installs: it hands each record to the writer thread and returns.

    Nothing is formatted on the caller's thread (the update loop, at an action's end) unless the
    record could change before the writer reads it: arguments or fields that are not immutable
    scalars are formatted here (the writer then writes that line as is), and so are records with
    an exception (the traceback is read while its frames are as they were). Once the writer is
    stopped (``shutdown``), records are written here, at once (``Writer.put``)."""

    def __init__(self, writer: Writer) -> None:
        super().__init__()
        self.writer = writer
        self.formatter = writer.target.formatter  # what it writes with (its own ``format`` is not called)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            if getattr(record, "embodiment", None) is None:
                record.embodiment = self.writer.embodiment()  # as it is now, not when the line is written
            if record.exc_info or record.stack_info or not _immutable(record):
                record._logs_line = self.writer.target.format(record)
            self.writer.put(record)
        except Exception:
            self.handleError(record)

    def flush(self) -> None:
        self.writer.flush()


def _immutable(record: logging.LogRecord) -> bool:
    args = record.args
    if args and (not isinstance(args, tuple) or any(type(arg) not in _IMMUTABLE for arg in args)):
        return False
    fields = getattr(record, "fields", None)
    if fields:
        if type(fields) is not dict or any(type(value) not in _IMMUTABLE for value in fields.values()):
            return False
        # The dict itself may be the caller's, and change: the writer reads a copy.
        record.fields = fields.copy()
    return type(record.msg) is str
