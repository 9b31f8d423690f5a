"""The handshake's threads, reused (``Workers``): a sending side, a commit retried, an abort sent.

A handshake step that waits on the network runs on a thread of its own, never on the update loop.
Starting a thread made the loop wait for it (``Thread.start`` waits until the new thread runs):
about a millisecond on a loaded two-core machine, at the start of every migration and after every
prepare, on the migration's critical path. A worker that finished its job waits for the next one
instead, blocked on a queue (no timer, no wake-up while the daemon is idle); a new thread starts
only when every worker is busy, so a handshake that waits long (a commit retried while the target
is away) never delays another. The threads exist only once a migration ran.

``close`` tells the workers to stop once their jobs end (jobs watch the host's ``stopping``) and
joins them, within a bound.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

_Job = tuple[str, Callable[..., None], tuple[Any, ...]] | None


class Workers:
    """Threads that run ``spawn``'s jobs, each at once: on an idle worker, else on a new one.
    A context manager; ``close`` is idempotent."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self._lock = threading.Lock()
        self._jobs: queue.SimpleQueue[_Job] = queue.SimpleQueue()
        self._idle = 0  # workers waiting for a job (each takes one job from the queue)
        self._threads: list[threading.Thread] = []
        self._closed = False

    def __enter__(self) -> Workers:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    @property
    def threads(self) -> int:
        """Workers started so far (alive until ``close``)."""
        with self._lock:
            return len(self._threads)

    @property
    def idle(self) -> int:
        """Workers waiting for a job."""
        with self._lock:
            return self._idle

    @property
    def alive(self) -> int:
        """Workers whose thread still runs (none once ``close`` returned in time)."""
        with self._lock:
            return sum(thread.is_alive() for thread in self._threads)

    def spawn(self, name: str, fn: Callable[..., None], *args: Any) -> bool:
        """Run ``fn(*args)`` on a worker now; False (not run) once closed: the host is stopping."""
        with self._lock:
            if self._closed:
                return False
            self._jobs.put((name, fn, args))
            if self._idle:
                self._idle -= 1
                return True
            thread = threading.Thread(target=self._run, name=f"{self.prefix}-{len(self._threads)}", daemon=True)
            self._threads.append(thread)
        thread.start()
        return True

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            name, fn, args = job
            try:
                fn(*args)
            except Exception:  # a job's bug is said, and the worker serves the next one
                log.exception("migration job %s failed", name)
            with self._lock:
                self._idle += 1

    def close(self, timeout: float = 10.0) -> None:
        """Stop the workers once their jobs end; joined within ``timeout`` seconds in all."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            threads = list(self._threads)
        for _ in threads:
            self._jobs.put(None)
        deadline = time.monotonic() + timeout
        for thread in threads:
            thread.join(max(0.0, deadline - time.monotonic()))
