"""What the network delivers, and the one thread that hands it to the handlers (``Dispatch``).

zenoh calls a callback given ``indirect=False`` on its own network thread. The callbacks of every
subscriber, queryable and liveliness watch of a session (``Sink.put``) only put the item, as it
came, in one bounded queue; one thread (``Dispatch``) takes it out and runs the handler. A channel
per entity drained by a thread of its own, as before, cost a thread each (twenty in a daemon),
and each of them woke ten times a second while idle: zenoh's blocking ``recv`` looks for Python
signals that often. Here an idle session's thread sleeps in one ``queue.get`` and nothing wakes it.

* Per entity, items reach the handler in the order they came. Each time it looks, the thread
  takes what the queue holds (``MAX_BATCH`` at most) and hands each entity its items together, in
  the order of their first arrival: under load, a batch handler runs once per batch.
* The queue is bounded (``CAPACITY`` items): when it is full, the network thread waits in
  ``put`` until the handlers catch up, as zenoh's FIFO channels made it wait (back-pressure
  rather than loss). Handlers should hand long work on (the ``Transport`` contract).
* ``Sink.close`` stops its handler: nothing of it runs once ``close`` returns (unless closed from
  a handler, on the thread itself); items still queued for it are given to ``discard`` (a query
  must be finalized). ``Dispatch.close`` ends the thread; idempotent, as every close here.

Nothing here imports zenoh: the adapter (``transport.zenoh``) makes the callbacks.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from typing import Any

from cmion_mesh.transport.base import MAX_BATCH

log = logging.getLogger(__name__)

#: Items queued at most for all the entities of a session together.
CAPACITY = 16384

_STOP: tuple[None, None] = (None, None)  # tells the thread to end


class Sink:
    """One entity's end of the queue: ``put`` (any thread) queues an item for ``handle``, which
    the dispatch thread calls with a list of them."""

    def __init__(self, dispatch: Dispatch, name: str, handle: Callable[[list[Any]], None],
                 discard: Callable[[Any], None] | None = None) -> None:
        self.dispatch = dispatch
        self.name = name
        self._handle = handle
        self._discard = discard
        self._running = threading.Lock()  # held while the handler runs
        self.closed = False

    def put(self, item: Any) -> None:
        """zenoh's callback: queue the item (never raises; waits only while the queue is full)."""
        if not self.closed:
            self.dispatch.put(self, item)

    def deliver(self, items: list[Any]) -> None:
        with self._running:
            if self.closed:
                self.drop(items)
                return
            try:
                self._handle(items)
            except Exception:
                log.exception("handler of %s failed", self.name)

    def drop(self, items: list[Any]) -> None:
        if self._discard is not None:
            for item in items:
                try:
                    self._discard(item)
                except Exception:  # a query already finalized: nothing left to do
                    log.debug("discarding an item of %s", self.name, exc_info=True)

    def close(self) -> None:
        self.closed = True
        self.wait_idle()

    def wait_idle(self) -> None:
        """Wait for a delivery running now to end (at once on the dispatch thread: it is the caller)."""
        if threading.current_thread() is not self.dispatch.thread:
            with self._running:
                pass


class Dispatch:
    """The bounded queue of a session's deliveries and the thread that runs their handlers. The
    thread starts with the first item. A context manager; ``close`` is idempotent."""

    def __init__(self, name: str = "zenoh-dispatch", capacity: int = CAPACITY) -> None:
        self.name = name
        self._queue: queue.Queue[tuple[Sink | None, Any]] = queue.Queue(capacity)
        self._lock = threading.Lock()
        self.thread: threading.Thread | None = None
        self._closed = False

    def sink(self, name: str, handle: Callable[[list[Any]], None], discard: Callable[[Any], None] | None = None) -> Sink:
        return Sink(self, name, handle, discard)

    def put(self, sink: Sink, item: Any) -> None:
        if self.thread is None:
            with self._lock:
                if self.thread is None and not self._closed:
                    self.thread = threading.Thread(target=self._run, name=self.name, daemon=True)
                    self.thread.start()
        if self._closed:
            sink.drop([item])
            return
        self._queue.put((sink, item))

    def _run(self) -> None:
        get, get_nowait = self._queue.get, self._queue.get_nowait
        while True:
            sink, value = get()
            if sink is None:
                return
            batches: dict[Sink, list[Any]] = {sink: [value]}
            stop = False
            for _ in range(MAX_BATCH - 1):
                try:
                    sink, value = get_nowait()
                except queue.Empty:
                    break
                if sink is None:
                    stop = True
                    break
                batches.setdefault(sink, []).append(value)
            for target, values in batches.items():
                target.deliver(values)
            if stop:
                return

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            thread = self.thread
        if thread is None:
            return
        self._queue.put(_STOP)  # after what is queued: that is delivered (or discarded by its closed sink) first
        if thread is not threading.current_thread():
            thread.join(5.0)
        while True:
            try:
                sink, value = self._queue.get_nowait()
            except queue.Empty:
                break
            if sink is not None:
                sink.drop([value])

    def __enter__(self) -> Dispatch:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()
