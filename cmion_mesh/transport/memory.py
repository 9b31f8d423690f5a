"""An in-process transport with the same threading contract as zenoh's, for fast unit tests of logic.

Never proof that the network works: tests that say so use ``ZenohTransport`` across processes.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
from collections.abc import Callable
from typing import Any

from cmion_mesh.errors import ClosedError
from cmion_mesh.keys import matches as _matches
from cmion_mesh.transport.base import (
    MAX_BATCH,
    BatchHandler,
    Closeable,
    Declared,
    Handle,
    LivelinessHandler,
    QueryCancel,
    QueryHandler,
    Reply,
    Sample,
    SampleHandler,
)

_STOP = object()
log = logging.getLogger(__name__)


def matches(pattern: str, key: str) -> bool:
    """As zenoh matches: ``@`` chunks (``@alive``, ``@outcome``...) only by themselves."""
    return _matches(pattern, key, verbatim=True)


def _intersects(a: str, b: str) -> bool:
    # Good enough for tests: one side is concrete, or both are equal patterns.
    return matches(a, b) or matches(b, a) or a == b


class _Worker:
    """Drains its queue on a thread of its own; ``batches``: hands over lists of what it found queued."""

    def __init__(self, name: str, handle: Callable[[Any], None], *, batches: bool = False) -> None:
        self.queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._handle = handle
        self._batches = batches
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            items = [self.queue.get()]
            if self._batches:
                for _ in range(min(self.queue.qsize(), MAX_BATCH - 1)):  # the only reader: cannot fail
                    items.append(self.queue.get_nowait())
            stop = any(item is _STOP for item in items)
            items = [item for item in items if item is not _STOP]
            try:
                if self._batches and items:
                    self._handle(items)
                else:
                    for item in items:
                        self._handle(item)
            except Exception:  # mirror zenoh_transport: a failing handler does not kill the worker
                log.exception("handler failed")
            if stop:
                return

    def stop(self) -> None:
        self.queue.put(_STOP)
        if self.thread is not threading.current_thread():
            self.thread.join(5.0)


class MemoryNetwork:
    """A shared medium: every ``MemoryTransport`` on it hears the others."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.subs: dict[int, tuple[str, _Worker, bool, MemoryTransport, bool]] = {}
        self.queryables: dict[int, tuple[str, _Worker, MemoryTransport]] = {}
        self.tokens: dict[int, str] = {}
        self.watchers: dict[int, tuple[str, _Worker]] = {}
        self.members: set[str] = set()  # ids of the open transports
        self.ids = itertools.count()


class _MemQuery:
    def __init__(self, selector: str, payload: bytes | None, sink: list[Reply], done: threading.Event,
                 attachment: bytes | None = None) -> None:
        self.key = selector.split("?")[0]
        self.selector = selector
        self.payload = payload
        self.attachment = attachment
        self._sink = sink
        self._done = done

    def reply(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        self._sink.append(Reply(key, payload, True, attachment))

    def reply_err(self, payload: bytes) -> None:
        self._sink.append(Reply(self.key, payload, False))

    def finish(self) -> None:
        self._done.set()


class _Handle(Handle):
    def __init__(self, close: Callable[[], None]) -> None:
        self._close = close
        self._closed = False

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._close()


class _MemMatching:
    """``Transport.matching`` in one memory network: the subscriptions are looked at when asked."""

    def __init__(self, transport: MemoryTransport, selector: str) -> None:
        self._transport = transport
        self._selector = selector
        self._closed = False

    @property
    def matching(self) -> bool:
        if self._closed or self._transport._closed:
            return False
        with self._transport.net.lock:
            return any(_intersects(self._selector, sub[0]) for sub in self._transport.net.subs.values())

    def close(self) -> None:
        self._closed = True


class MemoryTransport:
    def __init__(self, network: MemoryNetwork, name: str = "mem") -> None:
        self.net = network
        self._id = f"{name}-{next(network.ids)}"
        self._mine: Declared[_Handle] = Declared()
        self._closed = False
        with network.lock:
            network.members.add(self._id)

    @property
    def id(self) -> str:
        return self._id

    def __enter__(self) -> MemoryTransport:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def _check(self) -> None:
        if self._closed:
            raise ClosedError(f"transport {self._id} is closed")

    @property
    def dropped_publications(self) -> int:
        return 0  # delivered at once, into unbounded queues

    def publish(self, key: str, payload: bytes, *, block: bool = True, attachment: bytes | None = None) -> None:
        self._deliver(Sample(key, payload, False, attachment))

    def delete(self, key: str) -> None:
        self._deliver(Sample(key, b"", True))

    def _deliver(self, sample: Sample) -> None:
        self._check()
        with self.net.lock:
            targets = [
                (w, attached) for sel, w, remote_only, owner, attached in self.net.subs.values()
                if matches(sel, sample.key) and not (remote_only and owner is self)
            ]
        bare = sample._replace(attachment=None)
        for worker, attached in targets:
            worker.queue.put(sample if attached else bare)

    def subscribe(self, selector: str, handler: SampleHandler, *, remote_only: bool = False,
                  attachments: bool = False) -> Closeable:
        return self._subscribe(selector, _Worker(f"mem-sub:{selector}", handler), remote_only, attachments)

    def subscribe_batches(self, selector: str, handler: BatchHandler, *, remote_only: bool = False,
                          attachments: bool = False) -> Closeable:
        return self._subscribe(selector, _Worker(f"mem-sub:{selector}", handler, batches=True), remote_only, attachments)

    def _subscribe(self, selector: str, worker: _Worker, remote_only: bool, attachments: bool = False) -> Closeable:
        try:
            self._check()
        except ClosedError:
            worker.stop()
            raise
        with self.net.lock:
            sid = next(self.net.ids)
            self.net.subs[sid] = (selector, worker, remote_only, self, attachments)
        def unsubscribe() -> None:
            with self.net.lock:
                self.net.subs.pop(sid, None)
            worker.stop()

        return self._remember(unsubscribe)

    def declare_queryable(self, selector: str, handler: QueryHandler, *, complete: bool = False) -> Closeable:
        self._check()
        worker = _Worker(f"mem-qbl:{selector}", handler)
        with self.net.lock:
            qid = next(self.net.ids)
            self.net.queryables[qid] = (selector, worker, self)
        def undeclare() -> None:
            with self.net.lock:
                self.net.queryables.pop(qid, None)
            worker.stop()

        return self._remember(undeclare)

    def get(self, selector: str, payload: bytes | None = None, *, timeout: float = 10.0,
            attachment: bytes | None = None, cancel: QueryCancel | None = None) -> list[Reply]:
        replies, dones = self._send_query(selector, payload, attachment)
        if cancel is not None:
            def finish_all() -> None:
                for done in dones:
                    done.set()

            cancel.on_cancel(finish_all)
        for done in dones:
            done.wait(timeout)
        return list(replies)

    def _send_query(self, selector: str, payload: bytes | None,
                    attachment: bytes | None = None) -> tuple[list[Reply], list[threading.Event]]:
        self._check()
        key = selector.split("?")[0]
        with self.net.lock:
            targets = [w for sel, w, _ in self.net.queryables.values() if _intersects(sel, key)]
        replies: list[Reply] = []
        dones = []
        for worker in targets:
            done = threading.Event()
            worker.queue.put(_MemQuery(selector, payload, replies, done, attachment))
            dones.append(done)
        return replies, dones

    def get_first(self, selector: str, payload: bytes | None = None, *, timeout: float = 10.0) -> Reply | None:
        replies = self.get(selector, payload, timeout=timeout)
        return replies[0] if replies else None

    def get_first_later(self, selector: str, payload: bytes | None = None, *,
                        timeout: float = 10.0) -> Callable[[], Reply | None]:
        replies, dones = self._send_query(selector, payload)

        def first() -> Reply | None:
            for done in dones:
                done.wait(timeout)
            return replies[0] if replies else None

        return first

    def get_values(self, selector: str, *, timeout: float = 10.0) -> dict[str, bytes]:
        return {key: payload for key, payload, ok, _ in self.get(selector, timeout=timeout) if ok}

    def declare_token(self, key: str) -> Closeable:
        self._check()
        with self.net.lock:
            tid = next(self.net.ids)
            self.net.tokens[tid] = key
            watchers = [w for sel, w in self.net.watchers.values() if matches(sel, key)]
        for w in watchers:
            w.queue.put((key, True))

        def undeclare() -> None:
            with self.net.lock:
                self.net.tokens.pop(tid, None)
                gone = [w for sel, w in self.net.watchers.values() if matches(sel, key)]
            for w in gone:
                w.queue.put((key, False))

        return self._remember(undeclare)

    def alive(self, selector: str, *, timeout: float = 2.0) -> list[str]:
        self._check()
        with self.net.lock:
            return [k for k in self.net.tokens.values() if matches(selector, k)]

    def watch_liveliness(self, selector: str, handler: LivelinessHandler) -> Closeable:
        self._check()
        worker = _Worker(f"mem-live:{selector}", lambda item: handler(*item))
        with self.net.lock:
            wid = next(self.net.ids)
            self.net.watchers[wid] = (selector, worker)
            for k in self.net.tokens.values():
                if matches(selector, k):
                    worker.queue.put((k, True))
        def unwatch() -> None:
            with self.net.lock:
                self.net.watchers.pop(wid, None)
            worker.stop()

        return self._remember(unwatch)

    def matching(self, selector: str) -> _MemMatching:
        self._check()
        return _MemMatching(self, selector)

    def wait_subscribers(self, key: str, timeout: float) -> bool:
        # Subscriptions of one memory network are known at once: nothing to wait for.
        self._check()
        with self.net.lock:
            return any(matches(sel, key) for sel, _, remote_only, owner, *_ in self.net.subs.values()
                       if not (remote_only and owner is self))

    def peers(self) -> list[str]:
        """The other open transports of the network: each hears every other."""
        self._check()
        with self.net.lock:
            return sorted(self.net.members - {self._id})

    def _remember(self, close: Callable[[], Any]) -> Closeable:
        return self._mine.add(_Handle(close))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with self.net.lock:
            self.net.members.discard(self._id)
        for handle in reversed(self._mine.take()):
            handle.close()
