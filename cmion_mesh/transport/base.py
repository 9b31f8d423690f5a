"""The small transport interface that the rest of cmion-mesh talks to.

``transport.zenoh`` implements it over a real zenoh session (the only module that imports
zenoh); ``transport.memory`` implements it in one process for fast unit tests of logic.

Threading contract: handlers given to ``subscribe``, ``subscribe_batches``, ``declare_queryable``
and ``watch_liveliness`` run on a worker thread owned by the transport (never on a zenoh thread),
in order for each of them; the zenoh transport runs every handler of a session on one thread
(``inbox``), so they may call the transport, but they should hand long work on to a queue: a
handler that blocks delays the others. ``subscribe_batches`` hands over everything that has
arrived by the time its worker looks, in order, as one list: the thread hop after it is paid once
per batch, not once per sample.

Blocking publications (``publish`` with ``block``, ``delete``) never make their caller wait for
the network: they are sent in order by a thread of the transport, so that a subscriber that stops
reading delays no update loop (see ``outbox``). A refusal found then is logged, not raised.

Error contract: every method of a transport, and ``reply``/``reply_err``/``finish`` of an
``IncomingQuery``, raises only

* ``ClosedError`` once the transport is closed (``close`` itself never raises), and
* ``TransportError`` when the session refuses or fails the operation: an invalid key
  expression or selector, a session closed underneath, a failing link; the message names the
  operation and the key.

Both are ``MeshError``s, so callers catch that (never bare ``Exception``). Opening a session
raises ``ConfigError`` for settings it cannot take and ``TransportError`` if it cannot open. A
query that nobody answers is not an error: ``get`` returns no replies (outcome unknown).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, NamedTuple, Protocol, TypeVar

import msgspec


# Named tuples rather than dataclasses: one of each is made per message received, and a tuple is
# the cheapest immutable record Python builds (a frozen dataclass costs several times more).
class Sample(NamedTuple):
    key: str
    payload: bytes
    deleted: bool = False
    #: The zenoh attachment, only for a subscription made with ``attachments=True`` (ROS 2 over
    #: rmw_zenoh carries its sequence number and source there); None otherwise.
    attachment: bytes | None = None


class Reply(NamedTuple):
    key: str
    payload: bytes
    ok: bool = True
    attachment: bytes | None = None


class IncomingQuery(Protocol):
    """A query to answer. ``finish()`` must always be called, exactly once, after the replies."""

    @property
    def key(self) -> str: ...
    @property
    def selector(self) -> str: ...
    @property
    def payload(self) -> bytes | None: ...
    @property
    def attachment(self) -> bytes | None: ...
    def reply(self, key: str, payload: bytes, attachment: bytes | None = None) -> None: ...
    def reply_err(self, payload: bytes) -> None: ...
    def finish(self) -> None: ...


class QueryCancel:
    """Ends, from any thread, the ``get`` calls it was given to: they return the replies they had.
    For a query answered only when something ends (a ROS 2 action's result), so that the caller
    can stop waiting when it stops caring. Cancelling twice, or before the query, is harmless."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._cancelled = False
        self._hooks: list[Callable[[], None]] = []

    @property
    def cancelled(self) -> bool:
        return self._cancelled

    def cancel(self) -> None:
        with self._lock:
            if self._cancelled:
                return
            self._cancelled = True
            hooks, self._hooks = self._hooks, []
        for hook in hooks:
            hook()

    def on_cancel(self, hook: Callable[[], None]) -> None:
        """For transports: run ``hook`` on ``cancel`` (at once if it was cancelled already)."""
        with self._lock:
            if not self._cancelled:
                self._hooks.append(hook)
                return
        hook()


#: Most samples ``subscribe_batches`` hands over at once (bounds the latency of the first one).
MAX_BATCH = 256


class Matching(Protocol):
    """Whether some subscriber's pattern intersects a key expression, kept current by the
    transport (``Transport.matching``): reading ``matching`` costs an attribute read."""

    @property
    def matching(self) -> bool: ...
    def close(self) -> None: ...


class Closeable(Protocol):
    def close(self) -> None: ...
    def __enter__(self) -> Closeable: ...
    def __exit__(self, *_: object) -> None: ...


class Handle:
    """Base for things a caller closes: a context manager whose ``close`` is idempotent."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Handle:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


class Closing(Protocol):
    """A handle that says whether it is closed."""

    @property
    def closed(self) -> bool: ...

    def close(self) -> None: ...


H = TypeVar("H", bound=Closing)


class Declared(Generic[H]):
    """What a transport declared, for it to close what is left when it closes. Thread-safe.

    A daemon declares a custody token at each step of each migration and closes it at the next:
    kept for good, the closed ones would grow for as long as the daemon runs. So they are dropped
    as more are added, once the list has doubled since it was last pruned (amortized O(1) an add;
    about twice the open ones are held at most)."""

    __slots__ = ("_items", "_lock", "_prune_at")

    MIN_PRUNE = 64

    def __init__(self) -> None:
        self._items: list[H] = []
        self._lock = threading.Lock()
        self._prune_at = self.MIN_PRUNE

    def add(self, item: H) -> H:
        with self._lock:
            if len(self._items) >= self._prune_at:
                self._items = [held for held in self._items if not held.closed]
                self._prune_at = max(self.MIN_PRUNE, 2 * len(self._items))
            self._items.append(item)
        return item

    def open(self) -> int:
        """How many are not closed."""
        with self._lock:
            return sum(not held.closed for held in self._items)

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)

    def take(self) -> list[H]:
        """All of them (in the order declared), forgotten here: for closing."""
        with self._lock:
            items, self._items = self._items, []
            self._prune_at = self.MIN_PRUNE
        return items


#: The zenoh link lease of a daemon by default (ms): zenoh's own. Each link carries four keep-alives
#: per lease while idle, so a shorter lease is work per peer that grows with the mesh.
LEASE_MS = 10000


class TransportConfig(msgspec.Struct, frozen=True):
    """How to join the mesh.

    Defaults give a zenoh peer that finds others on the LAN by multicast scouting.
    ``connect``/``listen`` endpoints (``tcp/host:port``) and a zenoh JSON5 ``config_file``
    override that, e.g. to go through routers beyond one LAN; ``multicast=False`` keeps the
    session to its explicit endpoints (as the tests do, on loopback only).
    """

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    multicast: bool = True
    multicast_interface: str | None = None
    lease_ms: int | None = None
    overrides: tuple[tuple[str, str], ...] = ()


SampleHandler = Callable[[Sample], None]
BatchHandler = Callable[[list[Sample]], None]
QueryHandler = Callable[[IncomingQuery], None]
LivelinessHandler = Callable[[str, bool], None]


class Transport(Protocol):
    """Publish/subscribe, query/queryable and liveliness, as cmion-mesh needs them."""

    @property
    def id(self) -> str: ...

    def publish(self, key: str, payload: bytes, *, block: bool = True, attachment: bytes | None = None) -> None:
        """Publish. ``block`` (events, changes): a subscriber that reads gets it, however long the
        network makes it wait; the caller never waits: it is queued, in order, for the transport's
        publisher thread (``outbox``), and dropped and counted (``dropped_publications``) only when
        that queue is full. ``block=False``: sent now, dropped for a subscriber whose link is full.
        ``attachment`` travels beside the payload (rmw_zenoh requires one on every ROS 2 sample)."""

    def delete(self, key: str) -> None:
        """A delete on ``key``, queued as a blocking publication is (after those before it)."""

    @property
    def dropped_publications(self) -> int:
        """Blocking publications and deletes dropped so far because they could not be sent in time
        (the publisher's queue was full, or the transport closed while they waited)."""

    def subscribe(self, selector: str, handler: SampleHandler, *, remote_only: bool = False,
                  attachments: bool = False) -> Closeable:
        """``handler`` receives samples in order, on the transport's worker thread."""

    def subscribe_batches(self, selector: str, handler: BatchHandler, *, remote_only: bool = False,
                          attachments: bool = False) -> Closeable:
        """``handler`` receives, in order on the transport's worker thread, lists of the samples
        that arrived since its last call (at least one each; at most ``MAX_BATCH``). ``attachments``:
        fill ``Sample.attachment`` (off by default: the mesh's own keys never carry one)."""

    def declare_queryable(self, selector: str, handler: QueryHandler, *, complete: bool = False) -> Closeable: ...

    def get(self, selector: str, payload: bytes | None = None, *, timeout: float = 10.0,
            attachment: bytes | None = None, cancel: QueryCancel | None = None) -> list[Reply]:
        """Query; all replies (with their attachments). Zero replies means nobody answered: outcome
        unknown, not success. Blocks until every replier finished, ``timeout`` or ``cancel``; a
        caller that must stay responsive meanwhile runs it on a thread of its own."""

    def get_first(self, selector: str, payload: bytes | None = None, *, timeout: float = 10.0) -> Reply | None:
        """Query meant for one replier (a request to one component): the first reply, as soon as it
        comes, without waiting for the query's end (zenoh's final message follows a reply by about
        half a millisecond); None when nobody answered within ``timeout``: outcome unknown."""

    def get_first_later(self, selector: str, payload: bytes | None = None, *,
                        timeout: float = 10.0) -> Callable[[], Reply | None]:
        """``get_first`` in two steps: the query is sent when this returns (so that what the caller
        sends next goes after it), and the function returned waits for its first reply (call it
        once)."""

    def get_values(self, selector: str, *, timeout: float = 10.0) -> dict[str, bytes]:
        """Query with no payload; the payloads of the ok replies by key (of two for one key, the later
        one), error replies left out. What a read of many keys takes: no record per reply (a read of
        100k properties otherwise spends a third of its time making and collecting them)."""

    def declare_token(self, key: str) -> Closeable: ...

    def alive(self, selector: str, *, timeout: float = 2.0) -> list[str]:
        """Keys of the liveliness tokens currently alive under ``selector``."""

    def watch_liveliness(self, selector: str, handler: LivelinessHandler) -> Closeable:
        """``handler(key, alive)`` for every token that appears (including present ones) or vanishes."""

    def matching(self, selector: str) -> Matching:
        """Follow whether any subscriber (of any session, this one included) intersects ``selector``:
        a publication worth making only when someone listens checks ``matching`` first."""

    def wait_subscribers(self, key: str, timeout: float) -> bool:
        """Whether a subscriber whose pattern matches ``key`` is known to this session, waiting up to
        ``timeout`` for one: a publisher that must not publish into the void (``replay``) asks first."""

    def peers(self) -> list[str]:
        """Ids of the sessions this one is connected to (``router:<id>`` for routers), for diagnostics."""

    def close(self) -> None:
        """Close every subscription, queryable and token, then the session; idempotent."""
