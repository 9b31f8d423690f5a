"""The zenoh adapter: the only module that imports zenoh.

Every subscriber, queryable and liveliness watch gets a callback that zenoh runs on its network
thread (``indirect=False``) and that only puts what came in one bounded queue; one thread per
session runs the handlers (``inbox.Dispatch``), so zenoh's own threads never run a handler and a
slow handler cannot stall the session's receive path (a full queue makes zenoh wait: back-pressure,
not loss). An idle session's thread sleeps in one ``queue.get``: nothing polls. A subscriber's
handler gets everything queued for it when the thread looks (``subscribe_batches``): under load,
the handler and the hop that follows it run once per batch rather than once per sample. Handlers
of one selector (and options) share one zenoh declaration (``shared``): each declared is work on
every peer of the mesh.

Blocking publications and deletes go the other way through one thread of their own (an
``outbox.Outbox``): zenoh makes a blocking put wait while any subscriber's link is full, and the
update loop must not wait for a subscriber that stopped reading. zenoh gives such a link up after
``CONGESTED_LINK_WAIT_US`` rather than its default 5 s, so that the other subscribers' events wait
that long at most behind it.

Errors are mapped at this boundary and nowhere else: every call into zenoh runs inside
``_zenoh_errors``, so what escapes is what ``transport.Transport`` documents - ``ClosedError``
after ``close()``, ``TransportError`` (naming the operation and key) for whatever zenoh refused,
``ConfigError`` for a configuration zenoh cannot take (a listen endpoint it cannot bind among
them: the endpoint given is at fault) - never ``zenoh.ZError``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
import threading
from collections.abc import Callable, Hashable, Iterator
from pathlib import Path
from typing import Any

import zenoh

from cmion_mesh.errors import ClosedError, ConfigError, TransportError
from cmion_mesh.transport.base import (
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
    TransportConfig,
)
from cmion_mesh.transport.inbox import Dispatch, Sink
from cmion_mesh.transport.outbox import Outbox
from cmion_mesh.transport.shared import Declarations, Shared, SharedLiveliness, SharedSamples

log = logging.getLogger(__name__)

#: Channel depth of the raw zenoh baselines (``bench``): what this adapter's per-entity channels held
#: before they became one queue per session (``inbox.CAPACITY``).
CHANNEL_CAPACITY = 4096
#: Keys with a declared publisher (and keys checked) kept at most; cleared when full.
MAX_PUBLISHERS = 4096
_ALL = zenoh.QueryTarget.ALL
_NONE = zenoh.ConsolidationMode.NONE


#: zenoh's refusal to listen: "Can not create a new TCP listener bound to tcp/127.0.0.1:7447:
#: [127.0.0.1:7447: Address already in use (os error 98) at <source file>...] at <source file>...".
_LISTENER = re.compile(r"listener bound to (?P<endpoint>\S+?): \[(?:[^\]]*?: )?(?P<why>[^\]]*?)(?: \(os error \d+\))?(?: at |\])")


def _open_error(exc: zenoh.ZError) -> ConfigError | ClosedError | TransportError:
    """Why a session could not open: a listen endpoint that cannot be bound is one line naming it
    (``ConfigError``: the endpoint given is at fault), anything else a ``TransportError``."""
    found = _LISTENER.search(str(exc))
    if found is not None:
        return ConfigError(f"zenoh cannot listen on {found['endpoint']}: {found['why']}")
    return _mapped("cannot open zenoh session", exc)


def _mapped(what: str, exc: zenoh.ZError, closed: bool = False) -> ClosedError | TransportError:
    """The exception map: a ``zenoh.ZError`` becomes ``ClosedError`` if the transport was closed
    meanwhile, else ``TransportError`` saying what was asked."""
    if closed:
        return ClosedError(f"{what}: the transport is closed")
    return TransportError(f"{what}: {exc}")


@contextlib.contextmanager
def _zenoh_errors(what: str, closed: Callable[[], bool] = lambda: False) -> Iterator[None]:
    """``_mapped`` around a block (the hot paths use try/except themselves: a generator-based
    context manager costs microseconds per message)."""
    try:
        yield
    except zenoh.ZError as exc:
        raise _mapped(what, exc, closed()) from None


def build_config(cfg: TransportConfig) -> zenoh.Config:
    if cfg.config_file:
        path = Path(cfg.config_file)
        if not path.is_file():
            raise ConfigError("zenoh config file not found", path=str(path))
        try:
            zc = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise ConfigError(f"invalid zenoh config: {exc}", path=str(path)) from None
    else:
        zc = zenoh.Config()
    own_wait = cfg.config_file is not None and zc.get_json(CONGESTED_LINK_KEY) != zenoh.Config().get_json(CONGESTED_LINK_KEY)
    for key, raw in settings(cfg):
        if key == CONGESTED_LINK_KEY and own_wait:
            continue
        try:
            zc.insert_json5(key, raw)
        except zenoh.ZError as exc:
            raise ConfigError(f"zenoh setting {key}={raw} refused: {exc}") from None
    return zc


#: How long ``zenoh.open`` may wait for links to the peers it was told of (by gossip or multicast).
#: zenoh's default is 500 ms, and it is paid in full whenever the mesh still gossips the locator of a
#: session that has ended (a refused twin, a finished one-shot command): a start then took 0.5 s
#: instead of 5 ms. Links to live peers come up in a few ms; joining (``presence``) and the clients
#: wait for the mesh's tokens themselves, so nothing relies on ``open`` having waited.
SCOUT_WAIT_MS = 50

#: How long a blocking publication (or a reply, a declaration) waits for room on a link whose
#: queue is full before zenoh gives that link up (closes it; the peer may connect again). zenoh's
#: default is 5 s: that long, every publication of the session stood behind one subscriber that
#: stopped reading, each time it did. A link that takes no batch (64 KiB) in half a second does
#: not keep up with this session; a reader that merely paused for less loses nothing. The outbox
#: (``outbox``) keeps the update loop from waiting at all; this bounds how long the other
#: subscribers' events wait behind the stuck one. A zenoh file that sets its own value keeps it.
CONGESTED_LINK_WAIT_US = 500_000
CONGESTED_LINK_KEY = "transport/link/tx/queue/congestion_control/block/wait_before_close"


def settings(cfg: TransportConfig) -> list[tuple[str, str]]:
    """The zenoh settings (key, JSON5 value) ``build_config`` puts on top of the file or defaults."""
    values: list[tuple[str, Any]] = [("mode", cfg.mode), (CONGESTED_LINK_KEY, CONGESTED_LINK_WAIT_US)]
    if not cfg.config_file:  # a user's zenoh file keeps its own scouting delay
        values.append(("scouting/delay", SCOUT_WAIT_MS))
    if cfg.connect:
        values.append(("connect/endpoints", list(cfg.connect)))
    if cfg.listen:
        values.append(("listen/endpoints", list(cfg.listen)))
    if not cfg.multicast:
        values.append(("scouting/multicast/enabled", False))
    if cfg.multicast_interface:
        values.append(("scouting/multicast/interface", cfg.multicast_interface))
    if cfg.lease_ms:
        values.append(("transport/link/tx/lease", cfg.lease_ms))
        # zenoh sends keep-alives lease/keep_alive apart; 4 per lease tolerates one lost.
        values.append(("transport/link/tx/keep_alive", 4))
    return [(key, json.dumps(value)) for key, value in values] + list(cfg.overrides)


class _Query:
    __slots__ = ("_done", "_query", "attachment", "key", "payload", "selector")

    def __init__(self, query: zenoh.Query) -> None:
        self._query = query
        self._done = False
        self.key = str(query.key_expr)
        # Taken now although cmion never reads it: it costs ~0.2 us, and read lazily it would
        # raise once finish() has dropped the query (the memory transport's would not).
        self.selector = str(query.selector)
        raw = query.payload
        self.payload = raw.to_bytes() if raw is not None else None
        extra = query.attachment
        self.attachment = extra.to_bytes() if extra is not None else None

    def reply(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        try:
            if attachment is None:
                self._query.reply(key, payload)
            else:
                self._query.reply(key, payload, attachment=attachment)
        except zenoh.ZError as exc:
            raise _mapped(f"reply {key} to {self.key}", exc) from None

    def reply_err(self, payload: bytes) -> None:
        with _zenoh_errors(f"error reply to {self.key}"):
            self._query.reply_err(payload)

    def finish(self) -> None:
        if not self._done:
            self._done = True
            try:
                self._query.drop()  # type: ignore[no-untyped-call]
            except zenoh.ZError as exc:
                raise _mapped(f"finish {self.key}", exc) from None


class _Entity(Handle):
    """A declared subscriber/queryable/token, and the sink its callback feeds (none for a token)."""

    def __init__(self, undeclare: Callable[[], None], sink: Sink | None) -> None:
        self._undeclare = undeclare
        self._sink = sink
        self._lock = threading.Lock()
        self._closed = False

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._sink is not None:
            self._sink.close()  # its handler runs no more once this returns
        try:
            self._undeclare()
        except zenoh.ZError:  # session already closed: the entity is gone with it
            pass


def _callback(sink: Sink) -> Any:
    """zenoh's handler for ``sink``: run on zenoh's network thread, it only queues the item."""
    return zenoh.handlers.Callback(sink.put, indirect=False)


_DELETE = zenoh.SampleKind.DELETE
#: Samples are made with the tuple's own constructor: a named tuple's ``__new__`` is a Python
#: function, a frame per sample received (a third of what the rest of the conversion costs). It
#: fills no defaults: every field is given, the attachment too.
_tuple_new = tuple.__new__


def _sample(sample: zenoh.Sample) -> Sample:
    made: Sample = _tuple_new(Sample, (str(sample.key_expr), sample.payload.to_bytes(), sample.kind == _DELETE, None))
    return made


def _sample_attached(sample: zenoh.Sample) -> Sample:
    attachment = sample.attachment
    return Sample(str(sample.key_expr), sample.payload.to_bytes(), sample.kind == _DELETE,
                  attachment.to_bytes() if attachment is not None else None)


def _sample_of(key: str) -> Callable[[zenoh.Sample], Sample]:
    """``_sample`` for a subscription on the concrete ``key``: every sample it gets is on that key,
    so the key is not converted back to a string per sample."""

    def convert(sample: zenoh.Sample) -> Sample:
        made: Sample = _tuple_new(Sample, (key, sample.payload.to_bytes(), sample.kind == _DELETE, None))
        return made

    return convert


_PUT = zenoh.SampleKind.PUT


def _change(sample: zenoh.Sample) -> tuple[str, bool]:
    """A liveliness sample as (key, alive)."""
    return str(sample.key_expr), sample.kind == _PUT


class _Matching:
    """``Transport.matching``: ``matching`` as zenoh's matching listener last said."""

    def __init__(self) -> None:
        self.matching = False
        self.entity: _Entity | None = None

    def update(self, status: Any) -> None:
        self.matching = bool(status.matching)

    def close(self) -> None:
        if self.entity is not None:
            self.entity.close()
        self.matching = False


class ZenohTransport:
    """A zenoh session behind the ``Transport`` interface. A context manager; ``close`` is idempotent."""

    def __init__(self, config: TransportConfig | None = None) -> None:
        self.config = config or TransportConfig()
        zc = build_config(self.config)
        try:
            self._session = zenoh.open(zc)
        except zenoh.ZError as exc:
            raise _open_error(exc) from None
        self._entities: Declared[_Entity] = Declared()
        self._lock = threading.Lock()
        self._closed = False
        self._publishers: dict[str, zenoh.Publisher] = {}  # the outbox's thread's own
        self._checked: set[str] = set()  # keys zenoh took: checked once, not per publication
        self._outbox = Outbox(self._send, name="publisher")
        self._dispatch = Dispatch()
        # The subscribers and liveliness watches of this session, by what they were declared with:
        # a handler asking for the same again joins the declaration there is (``shared``).
        self._declarations = Declarations()

    @property
    def id(self) -> str:
        with _zenoh_errors("session id"):
            return str(self._session.zid())

    def __enter__(self) -> ZenohTransport:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def _errors(self, what: str) -> contextlib.AbstractContextManager[None]:
        """``_zenoh_errors`` for this session, after checking that it is still open."""
        if self._closed:
            raise ClosedError(f"{what}: the transport is closed")
        return _zenoh_errors(what, lambda: self._closed)

    def _track(self, entity: _Entity) -> _Entity:
        with self._lock:
            return self._entities.add(entity)

    def publish(self, key: str, payload: bytes, *, block: bool = True, attachment: bytes | None = None) -> None:
        if block:
            self._outbox_put(key, payload, attachment)
            return
        with self._errors(f"publish {key}"):
            if attachment is None:
                self._session.put(key, payload, congestion_control=zenoh.CongestionControl.DROP)
            else:
                self._session.put(key, payload, congestion_control=zenoh.CongestionControl.DROP, attachment=attachment)

    def delete(self, key: str) -> None:
        self._outbox_put(key, None, None)

    def _outbox_put(self, key: str, payload: bytes | None, attachment: bytes | None) -> None:
        """Hand a blocking publication to the outbox, its key checked here so that a key zenoh
        refuses is the caller's ``TransportError``, not a line in the log."""
        if self._closed:
            raise ClosedError(f"publish {key}: the transport is closed")
        if key not in self._checked:
            with self._errors(f"publish {key}"):
                zenoh.KeyExpr(key)
            if len(self._checked) >= MAX_PUBLISHERS:
                self._checked.clear()
            self._checked.add(key)
        self._outbox.put(key, payload, attachment)

    def _send(self, key: str, payload: bytes | None, attachment: bytes | None) -> None:
        """Send one blocking publication: on the outbox's thread only (it owns ``_publishers``)."""
        block = zenoh.CongestionControl.BLOCK
        try:
            if payload is None:
                self._session.delete(key, congestion_control=block)
            elif attachment is not None:
                self._session.put(key, payload, congestion_control=block, attachment=attachment)
            else:
                # A declared publisher per key keeps routing state warm for repeated events.
                pub = self._publishers.get(key)
                if pub is None:
                    if len(self._publishers) >= MAX_PUBLISHERS:
                        self._publishers.clear()
                    pub = self._publishers[key] = self._session.declare_publisher(key, congestion_control=block)
                pub.put(payload)
        except zenoh.ZError as exc:
            raise _mapped(f"publish {key}", exc, self._closed) from None

    @property
    def dropped_publications(self) -> int:
        return self._outbox.dropped

    @property
    def declarations(self) -> int:
        """Subscribers, queryables, liveliness subscribers and tokens, and matching listeners this
        session has declared and not undeclared (handlers sharing one count once): each is work on
        every peer of the mesh."""
        with self._lock:
            return self._entities.open()

    def subscribe(self, selector: str, handler: SampleHandler, *, remote_only: bool = False,
                  attachments: bool = False) -> Closeable:
        def each(batch: list[Sample]) -> None:
            for sample in batch:
                try:
                    handler(sample)
                except Exception:  # one sample's failure is not the next one's
                    log.exception("handler of %s failed", selector)

        return self.subscribe_batches(selector, each, remote_only=remote_only, attachments=attachments)

    def subscribe_batches(self, selector: str, handler: BatchHandler, *, remote_only: bool = False,
                          attachments: bool = False) -> Closeable:
        origin = zenoh.Locality.REMOTE if remote_only else zenoh.Locality.ANY
        concrete = "*" not in selector and "$" not in selector
        convert = _sample_attached if attachments else _sample_of(selector) if concrete else None

        def samples(items: list[zenoh.Sample]) -> list[Sample]:
            make = convert or _sample  # looked up here, not at declaration: bench.breakdown wraps _sample
            return [make(item) for item in items]

        def declare(sink: Sink) -> Callable[[], None]:
            return self._session.declare_subscriber(selector, _callback(sink), allowed_origin=origin).undeclare

        return self._join(("sub", selector, remote_only, attachments), handler, f"subscribe {selector}",
                          lambda on_empty: SharedSamples(self._dispatch, f"sub:{selector}", samples, on_empty), declare)

    def _join(self, key: Hashable, handler: Callable[..., None], what: str,
              make: Callable[[Callable[[Shared], None]], Shared], declare: Callable[[Sink], Callable[[], None]]) -> Closeable:
        """``Declarations.join``, the zenoh entity declared (``declare``) and tracked here."""
        if self._closed:
            raise ClosedError(f"{what}: the transport is closed")

        def entity(shared: Shared) -> _Entity:
            with self._errors(what):
                undeclare = declare(shared.sink)
            return self._track(_Entity(undeclare, shared.sink))

        return self._declarations.join(key, handler, make, entity)


    def declare_queryable(self, selector: str, handler: QueryHandler, *, complete: bool = False) -> Closeable:
        def deliver(queries: list[zenoh.Query]) -> None:
            for query in queries:
                wrapped = _Query(query)
                try:
                    handler(wrapped)
                except Exception:
                    wrapped.finish()
                    log.exception("handler of queryable %s failed", selector)

        sink = self._dispatch.sink(f"qbl:{selector}", deliver, discard=lambda query: query.drop())
        with self._errors(f"declare queryable {selector}"):
            queryable = self._session.declare_queryable(selector, _callback(sink), complete=complete)
        return self._track(_Entity(queryable.undeclare, sink))

    def get(self, selector: str, payload: bytes | None = None, *, timeout: float = 10.0,
            attachment: bytes | None = None, cancel: QueryCancel | None = None) -> list[Reply]:
        if attachment is not None or cancel is not None:
            return self._get_attached(selector, payload, timeout, attachment, cancel)
        if self._closed:
            raise ClosedError(f"query {selector}: the transport is closed")
        # A concrete key intersects only itself: every reply to it is on it (no conversion back).
        concrete = "*" not in selector and "$" not in selector and "?" not in selector
        out: list[Reply] = []
        try:
            for reply in self._session.get(selector, payload=payload, timeout=timeout, target=_ALL, consolidation=_NONE):
                ok = reply.ok
                if ok is not None:
                    out.append(Reply(selector if concrete else str(ok.key_expr), ok.payload.to_bytes(), True))
                else:
                    err = reply.err
                    out.append(Reply(selector, err.payload.to_bytes() if err is not None else b"", False))
        except zenoh.ZError as exc:
            raise _mapped(f"query {selector}", exc, self._closed) from None
        return out

    def get_first(self, selector: str, payload: bytes | None = None, *, timeout: float = 10.0) -> Reply | None:
        return self.get_first_later(selector, payload, timeout=timeout)()

    def get_first_later(self, selector: str, payload: bytes | None = None, *,
                        timeout: float = 10.0) -> Callable[[], Reply | None]:
        if self._closed:
            raise ClosedError(f"query {selector}: the transport is closed")
        concrete = "*" not in selector and "$" not in selector and "?" not in selector
        try:
            replies = self._session.get(selector, payload=payload, timeout=timeout, target=_ALL, consolidation=_NONE)
        except zenoh.ZError as exc:
            raise _mapped(f"query {selector}", exc, self._closed) from None

        def first() -> Reply | None:
            try:
                for reply in replies:
                    ok = reply.ok
                    if ok is not None:
                        return Reply(selector if concrete else str(ok.key_expr), ok.payload.to_bytes(), True)
                    err = reply.err
                    return Reply(selector, err.payload.to_bytes() if err is not None else b"", False)
            except zenoh.ZError as exc:
                raise _mapped(f"query {selector}", exc, self._closed) from None
            return None  # the handler's channel goes with it: later replies are dropped by zenoh

        return first

    def _get_attached(self, selector: str, payload: bytes | None, timeout: float, attachment: bytes | None,
                      cancel: QueryCancel | None) -> list[Reply]:
        """``get`` with an attachment or a cancel, the replies' attachments kept (ROS 2 services:
        the reply's sequence number pairs it with its request)."""
        out: list[Reply] = []
        token = None
        if cancel is not None:
            token = zenoh.CancellationToken()
            cancel.on_cancel(token.cancel)
        with self._errors(f"query {selector}"):
            for reply in self._session.get(selector, payload=payload, timeout=timeout, target=_ALL, consolidation=_NONE,
                                           attachment=attachment, cancellation_token=token):
                ok = reply.ok
                if ok is not None:
                    extra = ok.attachment
                    out.append(Reply(str(ok.key_expr), ok.payload.to_bytes(), True, extra.to_bytes() if extra is not None else None))
                else:
                    err = reply.err
                    out.append(Reply(selector, err.payload.to_bytes() if err is not None else b"", False))
        return out

    def get_values(self, selector: str, *, timeout: float = 10.0) -> dict[str, bytes]:
        if self._closed:
            raise ClosedError(f"query {selector}: the transport is closed")
        out: dict[str, bytes] = {}
        try:
            for reply in self._session.get(selector, timeout=timeout, target=_ALL, consolidation=_NONE):
                ok = reply.ok
                if ok is not None:
                    out[str(ok.key_expr)] = ok.payload.to_bytes()
        except zenoh.ZError as exc:
            raise _mapped(f"query {selector}", exc, self._closed) from None
        return out

    def declare_token(self, key: str) -> Closeable:
        with self._errors(f"declare token {key}"):
            token = self._session.liveliness().declare_token(key)
        return self._track(_Entity(token.undeclare, None))

    def alive(self, selector: str, *, timeout: float = 2.0) -> list[str]:
        with self._errors(f"liveliness query {selector}"):
            return [str(reply.ok.key_expr) for reply in self._session.liveliness().get(selector, timeout=timeout)
                    if reply.ok is not None]

    def watch_liveliness(self, selector: str, handler: LivelinessHandler) -> Closeable:
        """One liveliness subscriber with history per selector: each declared is a liveliness query
        to every peer. A handler that joins it later is given the keys alive first (``shared``)."""

        def declare(sink: Sink) -> Callable[[], None]:
            return self._session.liveliness().declare_subscriber(selector, _callback(sink), history=True).undeclare

        return self._join(("live", selector), handler, f"watch liveliness {selector}",
                          lambda on_empty: SharedLiveliness(self._dispatch, f"liveliness {selector}", _change, on_empty),
                          declare)

    def matching(self, selector: str) -> _Matching:
        with self._errors(f"matching subscribers of {selector}"):
            publisher = self._session.declare_publisher(selector)
        try:
            found = _Matching()
            # The listener's callback runs on a zenoh thread: it only sets a flag (never blocks).
            listener = publisher.declare_matching_listener(found.update)
        except zenoh.ZError as exc:
            with contextlib.suppress(zenoh.ZError):
                publisher.undeclare()  # type: ignore[no-untyped-call]
            raise _mapped(f"matching subscribers of {selector}", exc, self._closed) from None
        found.matching = bool(getattr(publisher.matching_status, "matching", False))

        def undeclare() -> None:
            with contextlib.suppress(zenoh.ZError):
                listener.undeclare()  # type: ignore[no-untyped-call]
            publisher.undeclare()  # type: ignore[no-untyped-call]

        found.entity = self._track(_Entity(undeclare, None))
        return found

    def wait_subscribers(self, key: str, timeout: float) -> bool:
        with self._errors(f"matching subscribers of {key}"):
            publisher = self._session.declare_publisher(key)
        try:
            found = threading.Event()
            # The listener's callback runs on a zenoh thread: it only sets an Event (never blocks).
            listener = publisher.declare_matching_listener(lambda status: found.set() if status.matching else None)
            try:
                # zenoh's stubs say bool; it is a MatchingStatus
                return bool(getattr(publisher.matching_status, "matching", False)) or found.wait(max(0.0, timeout))
            finally:
                with contextlib.suppress(zenoh.ZError):
                    listener.undeclare()  # type: ignore[no-untyped-call]
        except zenoh.ZError as exc:
            raise _mapped(f"matching subscribers of {key}", exc, self._closed) from None
        finally:
            with contextlib.suppress(zenoh.ZError):
                publisher.undeclare()  # type: ignore[no-untyped-call]

    def peers(self) -> list[str]:
        """Zenoh ids of the peers and routers this session is connected to (for diagnostics)."""
        with self._errors("list peers"):
            info = self._session.info
            return [str(z) for z in info.peers_zid()] + [f"router:{z}" for z in info.routers_zid()]

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities = self._entities.take()
        self._declarations.clear()
        # What is queued goes out first (a tool that publishes, then closes, loses nothing), while
        # the session is still open; a link that takes nothing more is given up by zenoh meanwhile.
        self._outbox.close()
        if not self._outbox.sending:
            for pub in self._publishers.values():
                with contextlib.suppress(zenoh.ZError):  # gone already: closing is all that was asked
                    pub.undeclare()  # type: ignore[no-untyped-call]
        for entity in entities:
            entity.close()
        try:
            self._session.close()  # type: ignore[no-untyped-call]
        except zenoh.ZError as exc:
            log.debug("closing the zenoh session: %s", exc)
        self._dispatch.close()
        self._outbox.join(5.0)  # a publication still waiting returned when the session closed
        self._publishers.clear()
