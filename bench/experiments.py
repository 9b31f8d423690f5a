"""What-if patches: emulate proposed cmion_mesh changes without editing cmion_mesh.

``python -m bench --experiment keycache,inline`` applies the named patches in the measuring
process and (through ``BENCH_EXPERIMENTS``) in every child, so the table shows what a change
would buy, measured exactly like the real thing. These are monkeypatches for measurement only;
the real change belongs in ``cmion_mesh``. Results carry the list of experiments applied.

* ``keycache``: memoize the pure key functions (``keys.check_name``, ``event_key``,
  ``request_key``, ``storage_key``, ``matches``) that run several times per event and request.
* ``namecache``: memoize only ``keys.check_name`` (the validation every key function repeats).
* ``inline``: "leader/follower" update loop: a thread that hands work to an *idle* simulation
  runs the update itself instead of waking the loop thread (one thread hop less per message);
  updates stay one at a time and in arrival order, and ``on_loop()`` is true for whichever
  thread runs the update. A busy simulation still queues the work for its loop thread.
* ``quiet-store``: diagnostic only: stores do not publish changes nor raise change events
  (shows what the post-reply work of a write costs the next request on a 2-core machine).
"""

from __future__ import annotations

import functools
import os
import queue
import threading
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

ENV = "BENCH_EXPERIMENTS"


def _keycache() -> None:
    from cmion_mesh import keys

    for name in ("check_name", "event_key", "request_key", "matches", "embodiment_prefix", "mesh_prefix"):
        setattr(keys, name, functools.lru_cache(maxsize=65536)(getattr(keys, name)))
    storage_key = keys.storage_key
    cached = functools.lru_cache(maxsize=65536)(lambda m, e, s, p, n: storage_key(m, e, s, p, n))

    def storage_key_cached(mesh: str, embodiment: str, store: str, path: Any, name: str | None = None) -> str:
        return cached(mesh, embodiment, store, tuple(path), name)

    keys.storage_key = storage_key_cached


def _namecache() -> None:
    from cmion_mesh import keys

    keys.check_name = functools.lru_cache(maxsize=65536)(keys.check_name)


class InlineInbox:
    """A stand-in for ``Simulation._inbox`` (a ``SimpleQueue``) that runs updates on the putter's thread when idle."""

    def __init__(self, sim: Any, stop: object) -> None:
        self.sim = sim
        self.stop = stop
        self.items: deque[Any] = deque()
        self.cond = threading.Condition()
        self.owner: threading.Thread | None = None  # the thread running an update, if any

    def put(self, item: Any) -> None:
        me = threading.current_thread()
        with self.cond:
            self.items.append(item)
            if self.owner is not None or item is self.stop or self.sim._thread is None or self.sim._closed:
                self.cond.notify()
                return
            self.owner = me
            batch = list(self.items)
            self.items.clear()
        try:
            self.sim._update(batch)
        finally:
            with self.cond:
                self.owner = None
                self.cond.notify()  # whatever arrived meanwhile goes to the loop thread

    def get(self, timeout: float | None = None) -> Any:
        me = threading.current_thread()
        with self.cond:
            if self.owner is me:
                self.owner = None  # the loop thread's previous update has ended
            ready = self.cond.wait_for(lambda: self.items and self.owner is None, timeout)
            if not ready:
                self.cond.wait_for(lambda: self.owner is None)
                self.owner = me
                raise queue.Empty
            self.owner = me
            return self.items.popleft()

    def get_nowait(self) -> Any:
        with self.cond:
            if not self.items:
                raise queue.Empty
            return self.items.popleft()


def _inline() -> None:
    from cmion_mesh import ion

    init = ion.Simulation.__init__

    def patched_init(self: Any, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        self._inbox = InlineInbox(self, ion._STOP)

    def on_loop(self: Any) -> bool:
        return self._inbox.owner is threading.current_thread()

    ion.Simulation.__init__ = patched_init  # type: ignore[method-assign]
    ion.Simulation.on_loop = on_loop  # type: ignore[method-assign]


def _quiet_store() -> None:
    from cmion_mesh import storage

    def no_publish(self: Any, changes: list[Any]) -> None:
        return None

    storage.Store._publish = no_publish  # type: ignore[method-assign]


EXPERIMENTS: dict[str, Callable[[], None]] = {
    "keycache": _keycache,
    "namecache": _namecache,
    "inline": _inline,
    "quiet-store": _quiet_store,
}
_applied: list[str] = []


def apply(names: Iterable[str]) -> list[str]:
    """Apply the named experiments (once each) here and in children started afterwards."""
    wanted = [n.strip() for n in names if n.strip()]
    unknown = sorted(set(wanted) - set(EXPERIMENTS))
    if unknown:
        raise ValueError(f"unknown experiment: {', '.join(unknown)} (known: {', '.join(EXPERIMENTS)})")
    for name in wanted:
        if name not in _applied:
            EXPERIMENTS[name]()
            _applied.append(name)
    os.environ[ENV] = ",".join(_applied)
    return list(_applied)


def apply_from_env() -> list[str]:
    return apply(os.environ.get(ENV, "").split(","))


def applied() -> list[str]:
    return list(_applied)
