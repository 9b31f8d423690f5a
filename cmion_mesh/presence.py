"""Who is alive in a mesh, as one session sees it.

A daemon declares the liveliness token ``cmion/<mesh>/@alive/<name>`` once it serves requests.
A session that has just opened knows nobody: tokens arrive as its links come up (tens of ms).
``Presence`` keeps the set of live embodiments current from a liveliness watch, so that a
one-shot command can *join, then ask*: wait, with a deadline, for the embodiments it needs.

The claim a daemon makes on its name before it declares that token is ``claim.py``'s.
"""

from __future__ import annotations

import difflib
import threading
from collections.abc import Callable, Iterable

from cmion_mesh import keys
from cmion_mesh.transport.base import Closeable, Handle, Transport

Listener = Callable[[str, bool], None]


def did_you_mean(name: str, known: Iterable[str]) -> str:
    """`` (did you mean 'robot'?)`` when a known name is close to ``name``, else ``""``."""
    names = sorted(set(known))
    if name in names:
        return ""
    close = difflib.get_close_matches(name, names, n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def alive_list(names: Iterable[str]) -> str:
    """The names alive, for a message: sorted, or ``none``."""
    return ", ".join(sorted(names)) or "none"


class Presence(Handle):
    """The embodiments alive in ``mesh`` as this session sees them, kept current by a liveliness watch."""

    def __init__(self, transport: Transport, mesh: str) -> None:
        self.mesh = keys.check_name(mesh, "mesh")
        self._alive: set[str] = set()
        self._cond = threading.Condition()
        self._listeners: list[Listener] = []
        self._watch = transport.watch_liveliness(f"{keys.mesh_prefix(mesh)}/{keys.ALIVE}/*", self._on_token)

    def _on_token(self, key: str, alive: bool) -> None:
        name = key.rsplit("/", 1)[-1]
        with self._cond:
            if alive:
                self._alive.add(name)
            else:
                self._alive.discard(name)
            listeners = list(self._listeners)
            self._cond.notify_all()
        for listener in listeners:
            listener(name, alive)

    def alive(self) -> set[str]:
        with self._cond:
            return set(self._alive)

    def wait(self, predicate: Callable[[set[str]], bool], timeout: float) -> bool:
        """Wait until ``predicate(alive names)`` holds; False when ``timeout`` passes first."""
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self._alive), max(0.0, timeout))

    def listen(self, listener: Listener, *, replay: bool = False) -> Closeable:
        """``listener(name, alive)`` on every change from now on (on the transport's worker). With
        ``replay``, first ``listener(name, True)`` for each embodiment alive now, from this thread:
        a listener added while the watch delivers the first tokens misses none of them (one may be
        told twice, never left out of date)."""
        with self._cond:
            self._listeners.append(listener)
            if replay:  # under the lock: no change is applied between the snapshot and its telling
                for name in sorted(self._alive):
                    listener(name, True)
        return _Listening(self, listener)

    def close(self) -> None:
        self._watch.close()


class _Listening(Handle):
    """A listener of ``Presence.listen``; closing it stops the calls (idempotent)."""

    def __init__(self, presence: Presence, listener: Listener) -> None:
        self._presence = presence
        self._listener = listener

    def close(self) -> None:
        presence = self._presence
        with presence._cond:
            if self._listener in presence._listeners:
                presence._listeners.remove(self._listener)
