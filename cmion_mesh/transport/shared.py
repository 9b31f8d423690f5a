"""One declaration per selector in a session, however many handlers ask for it.

A daemon's components each subscribe to what they need: three of them watch the mesh's ``@alive``
tokens, both minds of an embodiment subscribe to the same events. Each zenoh declaration is routing
work on every peer (a declaration message to each, an interest; a liveliness subscriber with
history is one liveliness query to each), so in a mesh of sixteen the duplicates were a good part
of what a daemon spent to join. Here the handlers of one (selector, options) share one declaration:

* ``SharedSamples`` hands every batch that the declaration's sink delivers to each handler.
* ``SharedLiveliness`` also keeps the keys alive as its deliveries said, so that a handler added
  later is given them first, as the history its own declaration would have brought: it gets that
  snapshot on the dispatch thread, at the first delivery after it joined, taken before that
  delivery's changes, so that nothing it is told is lost or out of order. Adding one queues a
  ``POKE`` for the sink, so that such a delivery comes even if the network says nothing.

Both run their handlers on the session's dispatch thread (``inbox``), like any handler. Closing a
handler's ``Member`` stops it alone: once ``close`` returns it runs no more (unless it was closed
on the dispatch thread itself); the others go on. When the last one leaves, ``add`` refuses new
handlers (the caller declares afresh) and the owner's ``on_empty`` undeclares.

``Declarations`` is a session's register of them: a handler asking for what is declared joins it.
Nothing here imports zenoh: the adapter (``transport.zenoh``) declares and converts.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Hashable
from typing import Any

from cmion_mesh.transport.base import Closeable, Handle
from cmion_mesh.transport.inbox import Dispatch

log = logging.getLogger(__name__)

#: Put in a liveliness sink to make it deliver (and so give a new handler its snapshot).
POKE = object()


class Member(Handle):
    """One handler of a shared declaration; ``close`` is idempotent."""

    def __init__(self, shared: Shared, handler: Callable[..., None]) -> None:
        self.shared = shared
        self.handler = handler
        self.primed = False  # liveliness: has been given the snapshot of the keys alive
        self.closed = False

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.shared.remove(self)


class Shared:
    """The handlers of one declaration and the sink that feeds them."""

    def __init__(self, dispatch: Dispatch, name: str, on_empty: Callable[[Shared], None],
                 discard: Callable[[Any], None] | None = None) -> None:
        self.name = name
        self._on_empty = on_empty
        self._lock = threading.Lock()
        # Replaced, never changed in place: a delivery reads it without the lock.
        self._members: tuple[Member, ...] = ()
        self._finished = False
        self.sink = dispatch.sink(name, self._deliver, discard)

    @property
    def handlers(self) -> int:
        return len(self._members)

    def add(self, handler: Callable[..., None]) -> Member | None:
        """A new handler, or None once the last one has left (the declaration is going away)."""
        with self._lock:
            if self._finished:
                return None
            member = Member(self, handler)
            later = bool(self._members)
            self._members = (*self._members, member)
        if later:
            self._joined()
        return member

    def _joined(self) -> None:
        """A handler joined one that was already there."""

    def remove(self, member: Member) -> None:
        with self._lock:
            self._members = tuple(m for m in self._members if m is not member)
            last = not self._members and not self._finished
            if last:
                self._finished = True
        self.sink.wait_idle()  # a delivery running now ends before close returns
        if last:
            self._on_empty(self)

    def _deliver(self, items: list[Any]) -> None:
        raise NotImplementedError


class SharedSamples(Shared):
    """A subscriber's deliveries, converted once (``convert``) and handed to every handler."""

    def __init__(self, dispatch: Dispatch, name: str, convert: Callable[[list[Any]], list[Any]],
                 on_empty: Callable[[Shared], None]) -> None:
        super().__init__(dispatch, name, on_empty)
        self._convert = convert

    def _deliver(self, items: list[Any]) -> None:
        members = self._members
        batch = self._convert(items)
        last = len(members) - 1
        for i, member in enumerate(members):
            if member.closed:
                continue
            try:
                # Each handler its own list: one may keep or change what it was given.
                member.handler(batch if i == last else list(batch))
            except Exception:
                log.exception("handler of %s failed", self.name)


class SharedLiveliness(Shared):
    """A liveliness subscriber's changes (``convert``: item -> (key, alive)) handed to every
    handler, a handler that joined later given the keys alive first."""

    def __init__(self, dispatch: Dispatch, name: str, convert: Callable[[Any], tuple[str, bool]],
                 on_empty: Callable[[Shared], None]) -> None:
        super().__init__(dispatch, name, on_empty)
        self._convert = convert
        self._alive: dict[str, None] = {}  # the keys alive, in the order they came (dispatch thread only)

    def _joined(self) -> None:
        self.sink.put(POKE)

    def _deliver(self, items: list[Any]) -> None:
        with self._lock:  # against add: a member is either in this delivery and primed here, or in a later one
            members = self._members
            new = [m for m in members if not m.primed]
            for member in new:
                member.primed = True
        if new and self._alive:
            snapshot = list(self._alive)
            for member in new:
                for key in snapshot:
                    self._call(member, key, True)
        for item in items:
            if item is POKE:
                continue
            key, alive = self._convert(item)
            if alive:
                self._alive[key] = None
            else:
                self._alive.pop(key, None)
            for member in members:
                self._call(member, key, alive)

    def _call(self, member: Member, key: str, alive: bool) -> None:
        if member.closed:
            return
        try:
            member.handler(key, alive)
        except Exception:
            log.exception("handler of %s failed", self.name)


class Declarations:
    """A session's shared declarations, by what they were declared with (``key``): ``join`` adds a
    handler to the one there is, or makes and declares one; the last handler out undeclares it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._shared: dict[Hashable, tuple[Shared, Closeable]] = {}

    def join(self, key: Hashable, handler: Callable[..., None], make: Callable[[Callable[[Shared], None]], Shared],
             declare: Callable[[Shared], Closeable]) -> Member:
        """``handler`` added to the declaration for ``key``; if there is none, ``make`` its fan-out
        (given what to call when its last handler leaves) and ``declare`` the entity feeding its
        sink (what ``declare`` raises, ``join`` raises)."""
        with self._lock:
            found = self._shared.get(key)
            member = found[0].add(handler) if found is not None else None
            if member is not None:
                return member
            shared = make(lambda gone: self._unshare(key, gone))
            member = shared.add(handler)  # before the declaration: its first deliveries (history) are the handler's
            assert member is not None  # a new one is never finished
            self._shared[key] = (shared, declare(shared))
            return member

    def _unshare(self, key: Hashable, shared: Shared) -> None:
        with self._lock:
            found = self._shared.get(key)
            if found is None or found[0] is not shared:
                return  # cleared by the transport's close, which closes every entity itself
            del self._shared[key]
        found[1].close()

    def clear(self) -> None:
        with self._lock:
            self._shared.clear()
