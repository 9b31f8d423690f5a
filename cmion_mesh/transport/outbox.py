"""Publications waiting for the network: a bounded queue and the one thread that sends them.

A publication with blocking congestion control (events, store changes) waits inside zenoh while
the link to some subscriber is full; a subscriber that stops reading keeps it full, and zenoh waits
until it gives that link up. Made on the update loop, such a publication held every request and
event of the embodiment for that long (5 s, zenoh's default, each time). The transport hands
blocking publications to an ``Outbox`` instead:

* ``put`` never waits for the network: it queues the publication and returns.
* One thread sends them, in the order they were put (the order of the events of a simulation,
  whose loop is the one thread raising them), each waiting as long as zenoh makes it: a
  subscriber that reads gets every one (blocking semantics), however slow it is for a moment.
* The queue is bounded (``max_items`` publications, ``max_bytes`` of payload). When it is full,
  a new publication is dropped for everyone and counted (``dropped``); the log says so, at most
  once per ``REPORT_INTERVAL`` seconds, with the count since its last report. A publication
  bigger than ``max_bytes`` is taken when the queue is empty (else it could never be sent).
* ``close`` sends what is queued, waiting up to ``drain`` seconds; what is left then is dropped
  (counted, and said in the log). ``put`` after ``close`` raises ``ClosedError``.

The bound is a last resort: the transport also has zenoh give a stuck link up quickly
(``transport.zenoh.CONGESTED_LINK_WAIT_US``), so the queue only grows while one link is being
given up, and the subscriber that stopped reading loses what was meant for it alone.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

from cmion_mesh.errors import ClosedError
from cmion_mesh.transport.base import Handle

log = logging.getLogger(__name__)

#: Publications an outbox holds at most by default.
MAX_ITEMS = 65536
#: Payload bytes an outbox holds at most by default (the daemon's memory, not the network, bounds it).
MAX_BYTES = 64 * 1024 * 1024
#: Bytes counted per publication besides its payload (key, tuple, queue slot): a flood of empty
#: payloads is bounded by bytes too.
OVERHEAD = 128
#: Shortest time between two log lines about dropped publications.
REPORT_INTERVAL = 10.0
#: Publications sent per look at the queue (the counts are updated once per batch).
BATCH = 256

#: Sends one publication: key, payload (None: a delete), attachment.
Send = Callable[[str, bytes | None, bytes | None], None]
#: A queued publication: key, payload, attachment, bytes counted; None tells the thread to stop.
_Item = tuple[str, bytes | None, bytes | None, int] | None


class Outbox(Handle):
    """A bounded FIFO of publications and the thread that sends them with ``send``; thread-safe.
    The thread starts with the first ``put``. A context manager; ``close`` is idempotent."""

    def __init__(self, send: Send, *, name: str = "outbox", max_items: int = MAX_ITEMS, max_bytes: int = MAX_BYTES,
                 drain: float = 2.0) -> None:
        self._send = send
        self.name = name
        self.max_items = max_items
        self.max_bytes = max_bytes
        self.drain = drain
        self._queue: queue.SimpleQueue[_Item] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._items = 0  # queued or being sent
        self._bytes = 0
        self._closed = False
        self._abandon = False  # close gave up waiting: the thread drops what it still holds
        self._thread: threading.Thread | None = None
        #: Publications dropped since the outbox was made: the queue was full, or closed before they went.
        self.dropped = 0
        self._reported = 0
        self._report_after = 0.0
        #: Publications the session refused or failed when they were sent (logged, not raised).
        self.failed = 0
        self._failure_report_after = 0.0

    @property
    def sending(self) -> bool:
        """Whether the thread is still running (after ``close``: it gave up waiting for a link)."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def waiting(self) -> int:
        """Publications queued or being sent."""
        return self._items

    def put(self, key: str, payload: bytes | None, attachment: bytes | None = None) -> bool:
        """Queue a publication (``payload`` None: a delete); False if the queue was full and it was
        dropped. Never waits for the network."""
        size = OVERHEAD + (len(payload) if payload is not None else 0) + (len(attachment) if attachment is not None else 0)
        with self._lock:
            if self._closed:
                raise ClosedError(f"publish {key}: {self.name} is closed")
            if self._items >= self.max_items or (self._items and self._bytes + size > self.max_bytes):
                self.dropped += 1
                now = time.monotonic()
                if now < self._report_after:
                    return False
                count, self._reported = self.dropped - self._reported, self.dropped
                self._report_after = now + REPORT_INTERVAL
                held = (self._items, self._bytes)
            else:
                self._items += 1
                self._bytes += size
                self._queue.put((key, payload, attachment, size))
                if self._thread is None:
                    self._thread = threading.Thread(target=self._run, name=f"zenoh-{self.name}", daemon=True)
                    self._thread.start()
                return True
        log.warning("%s: %d publication(s) dropped since the last report (%d in all; the latest on %s): the queue "
                    "is full, %d publications (%d bytes) waiting for the network", self.name, count, self.dropped, key, *held)
        return False

    def _run(self) -> None:
        get, get_nowait = self._queue.get, self._queue.get_nowait
        stop = False
        while not stop:
            batch = [get()]
            for _ in range(BATCH - 1):
                try:
                    batch.append(get_nowait())
                except queue.Empty:
                    break
            taken = size = skipped = 0
            for item in batch:
                if item is None:
                    stop = True
                    continue
                key, payload, attachment, nbytes = item
                taken += 1
                size += nbytes
                if self._abandon:
                    skipped += 1
                    continue
                try:
                    self._send(key, payload, attachment)
                except Exception as exc:  # the next publication is not this one's to lose
                    self.failed += 1
                    now = time.monotonic()
                    if now >= self._failure_report_after:  # a session closed underneath fails them all
                        self._failure_report_after = now + REPORT_INTERVAL
                        log.warning("%s: could not publish %s (%d failed in all): %s", self.name, key, self.failed, exc)
            with self._lock:
                self._items -= taken
                self._bytes -= size
                self.dropped += skipped

    def close(self) -> None:
        """Send what is queued (waiting up to ``drain`` seconds), then stop the thread."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            thread = self._thread
        if thread is None:
            return
        self._queue.put(None)
        thread.join(self.drain)
        if thread.is_alive():
            self.abandon()

    def abandon(self) -> None:
        """Drop what is still queued (after ``close`` gave up waiting for a link): the thread ends
        once the publication it is sending returns (closing the session returns it)."""
        with self._lock:
            self._abandon = True
            left = self._items
        if left:
            log.warning("%s: %d publication(s) not sent: closed while they waited for the network", self.name, left)

    def join(self, timeout: float) -> None:
        """Wait up to ``timeout`` for the thread to end (after ``close``)."""
        if self._thread is not None:
            self._thread.join(timeout)
