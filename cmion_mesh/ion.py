"""ION semantics over the mesh: components, events, requests and the update loop.

CMION ran on the ION framework: a *simulation* steps *components* through *updates*. We keep
its semantics and drive them from arriving work instead of a fixed-rate timer:

* An update starts as soon as work arrives (a request, a remote event, a posted call) and takes
  everything that has arrived by then. An idle simulation blocks in one ``queue.get``: no polling.
  Remote events cross one thread hop: each subscription's transport worker decodes what its
  channel holds and hands it over as one item (``Transport.subscribe_batches``).
* In one update, posted calls run first, then every component receives *all* the requests that
  reached it together (``handle_requests``) so it can mediate conflicts, then events are
  dispatched one at a time in the order raised, including events raised by the handlers.
  Requests raised while handling events are handled in the next update.
* Every request gets a definite ``Outcome``: accepted, rejected with a reason, or conflict (lost
  to another request in the same update). A request a handler leaves unanswered is rejected, with
  the handler's error as the reason if it raised, unless the handler deferred it
  (``IncomingRequest.defer``: it answers later, from the loop). Each request name takes one ``Message`` Struct
  (``Component.requests``); a payload that does not decode to it, ``{}`` or a map without its
  ``type`` included, is rejected (``Code.MALFORMED``) before the component sees it. A request the
  component does not have is rejected (``Code.UNKNOWN_REQUEST``) with the component's
  ``request_catalogue()`` as value: a query on ``.../rq/**`` is answered by every component.
* ``start()`` runs updates on a thread of the simulation's own; a simulation that is not started
  is stepped by its owner with ``run_once()`` (deterministic tests).
* Events are zenoh publications on ``.../ev/<component>/<event>`` (blocking congestion control,
  handed to the transport's publisher thread: raising one never waits for the network, so a
  subscriber that stops reading stalls no update); requests are zenoh queries on
  ``.../rq/<component>/<request>``. Local events and requests
  between components of one simulation are delivered directly, in order, and still published.
  A remote event reaches each subscription whose pattern its key matches once (each ``on_event``
  has its own zenoh subscriber), and only if its fields name the key it was published on.

Here: ``Component``, ``Simulation`` (the loop, its events, how requests reach components) and
``serve``. A request and its answers (``IncomingRequest``, ``send_request``, ``require_accepted``,
the answers told on ``@outcome``) are in ``requests``; ``call_later``'s timers in ``timers``.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

from cmion_mesh import keys
from cmion_mesh.errors import ClosedError, InvalidName, MeshError, OutcomeUnknown, ProtocolError
from cmion_mesh.messages import Code, Event, Message, Outcome, check_value, decode, decoder, encode, tag
from cmion_mesh.requests import DEFAULT_REQUEST_TIMEOUT, Answers, addressed, covered, send_request, unknown_request
from cmion_mesh.requests import IncomingRequest as IncomingRequest  # named by components written before it moved
from cmion_mesh.timers import Timer as Timer  # call_later's, named by components written before it moved
from cmion_mesh.timers import Timers
from cmion_mesh.transport.base import Closeable, Handle, IncomingQuery, Sample, Transport

log = logging.getLogger(__name__)

EventHandler = Callable[[Event], None]
OutcomeHandler = Callable[[Outcome], None]

#: Events dispatched in one update before the rest is carried to the next (a runaway loop of
#: handlers raising events must not starve requests; nothing is dropped).
MAX_EVENTS_PER_UPDATE = 10_000
#: Work items taken into one update.
MAX_ITEMS_PER_UPDATE = 10_000
#: Bound of the per-simulation caches of event keys and of subscriptions matching a key
#: (cleared when full: they only save work, and remote names are not ours to bound).
MAX_CACHED_KEYS = 4096
#: Work waiting for the loop beyond which new requests are answered ``busy`` at once, on the
#: transport's worker: a flood costs the flooder an answer, not this embodiment's memory.
MAX_QUEUED = 4096


class Component:
    """A part of an embodiment that raises events and receives requests.

    ``requests`` maps request names to the ``Message`` Struct their payload decodes to (one Struct
    per request kind, so handlers dispatch with ``match request.payload``). Subclasses override
    ``handle_requests`` to mediate a batch, or ``on_request`` for one at a time.
    """

    requests: Mapping[str, type[Message]] = {}
    #: Requests that must arrive on the per-sender key ``.../rq/<component>/<request>/<sender>``;
    #: the sender (``IncomingRequest.requester``) is then known from the key, which access
    #: control ties to the sender's certificate in secure mode.
    sender_requests: frozenset[str] = frozenset()
    #: One per embodiment, built by the embodiment itself from what it holds (its stores, its
    #: state folder): an architecture configuration cannot name it.
    built_by_embodiment: bool = False

    def __init__(self, name: str) -> None:
        self.name = keys.check_name(name, "component")
        self._sim: Simulation | None = None

    @property
    def sim(self) -> Simulation:
        if self._sim is None:
            raise MeshError(f"component {self.name!r} is not attached to a simulation")
        return self._sim

    def attach(self, sim: Simulation) -> None:
        """Called on the update loop when added: register event handlers here."""

    def detach(self) -> None:
        """Called on the update loop when removed or when the simulation closes."""

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        """All requests that reached this component in one update, in arrival order."""
        for request in batch:
            self.on_request(request)

    def on_request(self, request: IncomingRequest) -> None:
        request.reject(f"component {self.name!r} does not handle {request.name!r}", Code.UNKNOWN_REQUEST)

    def raise_event(self, name: str, data: Any = None) -> None:
        sim = self._sim
        if sim is None:
            raise MeshError(f"component {self.name!r} is not attached to a simulation")
        sim.raise_event(self.name, name, data)

    def request_catalogue(self) -> dict[str, Any]:
        """What this component answers, as plain data: ``{"component", "requests": {name: message
        type}, "per_sender": [names sent on .../<name>/<sender>]}``. It is the value of the
        ``unknown_request`` refusal, so a query on ``.../rq/**`` lists every component's requests."""
        return {"component": self.name, "requests": {name: tag(kind) for name, kind in sorted(self.requests.items())},
                "per_sender": sorted(self.sender_requests)}


class _RequestItem:
    __slots__ = ("component", "request")

    def __init__(self, component: Component, request: IncomingRequest) -> None:
        self.component = component
        self.request = request


class _Subscription(Handle):
    def __init__(self, sim: Simulation, pattern: str, handler: EventHandler) -> None:
        self.sim = sim
        self.pattern = pattern
        self.handler = handler
        self.remote: Closeable | None = None
        self.closed = False

    def on_samples(self, batch: list[Sample]) -> None:
        self.sim._on_remote_events(self, batch)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.sim._unsubscribe(self)
        if self.remote is not None:
            self.remote.close()


_STOP = object()
_decode_event = decoder(Event)
#: Values that are plain data whatever they hold (ints need their range checked: ``check_value``).
_SCALARS = frozenset({str, float, bool, type(None)})


class Simulation:
    """The update loop of one embodiment in one process. A context manager; ``close`` is idempotent."""

    def __init__(self, transport: Transport, *, mesh: str = keys.DEFAULT_MESH, embodiment: str,
                 one_queryable: bool = False) -> None:
        """``one_queryable``: one zenoh queryable (``.../rq/**``) answers the requests of every
        component, rather than one per component: for the process that is the embodiment (a
        daemon), whose dozen declarations are work on every peer of the mesh. A process serving a
        few components of an embodiment that runs elsewhere (a remote mind) keeps one per component,
        so that it is not handed the requests of all the others."""
        self.transport = transport
        self._one_queryable = one_queryable
        self.mesh = keys.check_name(mesh, "mesh")
        self.embodiment = keys.check_name(embodiment, "embodiment")
        self._inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._components: dict[str, Component] = {}
        self._queryables: dict[str, Closeable] = {}
        self._subscriptions: list[_Subscription] = []
        # key -> the subscriptions matching it; replaced (under _lock) when subscriptions change
        self._matching: dict[str, list[_Subscription]] = {}
        # (embodiment, component, event) -> checked event key
        self._event_keys: dict[tuple[str, str, str], str] = {}
        # events to dispatch: (event, key, the one subscription of a remote event or None = all matching)
        self._events: deque[tuple[Event, str, _Subscription | None]] = deque()
        self._timers = Timers()
        self._seq = itertools.count(1)
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None
        self._thread: threading.Thread | None = None
        self._stepper: threading.Thread | None = None  # the owner's thread, when run_once drives it
        self._loop_ident: int | None = None  # thread id of whichever of the two runs updates (on_loop, fast)
        # length of ".../<embodiment>/rq/", which every request key of this embodiment starts with
        self._rq_prefix = f"{keys.embodiment_prefix(self.mesh, self.embodiment)}/{keys.REQUESTS}/"
        self._rq_prefix_len = len(self._rq_prefix)
        self._closed = False
        self._stopped = threading.Event()
        self.updates = 0
        # Counters for whoever watches the daemon (``ops.metrics`` reads them at scrape time): plain
        # ints kept on the loop, and one small uncontended lock per request answered over the mesh.
        #: Events this simulation raised (published) / received from other sessions, so far.
        self.events_raised = 0
        self.events_received = 0
        self._answers = Answers(transport, self.mesh, self.embodiment)

    # --- life cycle ---------------------------------------------------------------------------

    def start(self) -> Simulation:
        if self._stepper is not None:
            raise MeshError(f"simulation {self.embodiment!r} is stepped with run_once: it cannot also run a loop")
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"ion-{self.embodiment}", daemon=True)
            self._thread.start()
        return self

    def __enter__(self) -> Simulation:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._thread is not None:
            self._inbox.put(_STOP)
            if self._thread is not threading.current_thread():
                self._thread.join(10.0)
        else:
            self._shutdown()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    @property
    def closed(self) -> bool:
        return self._closed

    def on_loop(self) -> bool:
        return threading.get_ident() == self._loop_ident

    # --- components ---------------------------------------------------------------------------

    def add(self, component: Component) -> Component:
        """Add a component; its request queryable is declared at once, ``attach`` runs on the loop."""
        with self._lock:
            if self._closed:
                raise ClosedError(f"simulation {self.embodiment!r} is closed")
            if component.name in self._components:
                raise MeshError(f"embodiment {self.embodiment!r} already has a component {component.name!r}")
            self._components[component.name] = component
        component._sim = self
        if component.requests:
            self._answers.follow_listeners()
            prefix = f"{keys.embodiment_prefix(self.mesh, self.embodiment)}/{keys.REQUESTS}"
            if not self._one_queryable:
                tail = "**" if component.sender_requests else "*"
                self._queryables[component.name] = self.transport.declare_queryable(
                    f"{prefix}/{component.name}/{tail}", functools.partial(self._on_query, component))
            elif not self._queryables:
                self._queryables[""] = self.transport.declare_queryable(f"{prefix}/**", self._on_any_query)
        self.call(lambda: component.attach(self))
        return component

    def remove(self, name: str) -> None:
        with self._lock:
            component = self._components.pop(name, None)
        queryable = self._queryables.pop(name, None)
        if queryable is not None:
            queryable.close()
        if component is not None:
            self.call(component.detach)

    def component(self, name: str) -> Component:
        try:
            return self._components[name]
        except KeyError:
            raise MeshError(f"embodiment {self.embodiment!r} has no component {name!r}") from None

    @property
    def components(self) -> list[Component]:
        return list(self._components.values())

    def components_by_name(self) -> dict[str, Component]:
        return dict(self._components)

    # --- work in ----------------------------------------------------------------------------

    def call(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the update loop, at the start of the next update. Thread-safe."""
        if self._closed:
            raise ClosedError(f"simulation {self.embodiment!r} is closed")
        self._inbox.put(fn)

    def post(self, fn: Callable[[], None]) -> bool:
        """``call(fn)`` from a thread reporting to the loop, unless the simulation is closing:
        then nobody waits for the report any more, and False says it was dropped."""
        try:
            self.call(fn)
        except ClosedError:
            return False
        return True

    def queued(self) -> int:
        """Work items waiting for the next update (requests, remote events, calls)."""
        return self._inbox.qsize()

    @property
    def armed_timers(self) -> int:
        """Timers armed and not cancelled; read it on the loop (or from ``call``)."""
        return self._timers.armed

    def call_later(self, delay: float, fn: Callable[[], None]) -> Timer:
        """Run ``fn`` on the loop after ``delay`` seconds (the loop sleeps until then, it does not poll).

        ``cancel()`` on the returned timer drops ``fn`` at once, so a long deadline for work that
        ended early holds nothing (a plan's deadline, for instance)."""
        timer = self._timers.timer(delay, fn)
        if self.on_loop():
            self._timers.arm(timer)
        else:
            self.call(lambda: self._timers.arm(timer))
        return timer

    def _on_any_query(self, query: IncomingQuery) -> None:
        """``one_queryable``'s handler: a request reaches the component whose own queryable it
        would have reached; a key none of them would have is left unanswered (another process of
        the embodiment may serve it: a remote mind). A key expression over many components' keys
        (``.../rq/**``: what do you answer?) is answered by each, with its catalogue, as before."""
        key = query.key
        if "*" not in key and "$" not in key:
            component = addressed(key, self._rq_prefix, self._components)
            if component is not None:
                self._on_query(component, query)
            else:
                query.finish()
            return
        try:
            for component in covered(key, self._rq_prefix, list(self._components.values())):
                outcome = unknown_request(component, "")
                query.reply(key, encode(outcome))
                self._answers.given(component.name, "", "", outcome)
        finally:
            query.finish()

    def _on_query(self, component: Component, query: IncomingQuery) -> None:
        # Runs on the transport's worker: decode, then hand to the loop. Refusals that need no
        # component state are answered here so a bad request never costs an update.
        name, _, sender = query.key[self._rq_prefix_len + len(component.name) + 1:].partition("/")

        answers = self._answers

        def answer(outcome: Outcome) -> None:
            try:
                query.reply(query.key, encode(outcome))
            finally:
                query.finish()
                answers.given(component.name, name, sender, outcome)

        if self._inbox.qsize() >= MAX_QUEUED:
            answer(Outcome("rejected", f"busy: embodiment {self.embodiment!r} has {MAX_QUEUED} requests and events waiting; "
                                       "try again later", code=Code.BUSY))
            return
        kind = component.requests.get(name)
        if kind is None:
            answer(unknown_request(component, name))
            return
        if (name in component.sender_requests) != bool(sender) or "/" in sender:
            form = f"{name}/<sender>" if name in component.sender_requests else name
            reason = f"{query.key}: request {name!r} of {component.name!r} is sent on .../{form}"
            answer(Outcome("rejected", reason, code=Code.WRONG_KEY))
            return
        try:
            payload = decode(query.payload or b"", kind, where=query.key)
        except ProtocolError as exc:
            answer(Outcome("rejected", str(exc), code=Code.MALFORMED))
            return
        if self._closed:
            answer(Outcome("rejected", f"embodiment {self.embodiment!r} is shutting down", code=Code.SHUTTING_DOWN))
            return
        self._inbox.put(_RequestItem(component, IncomingRequest(component.name, name, payload, sender, answer)))

    def answered(self) -> dict[tuple[str, str], int]:
        """Requests answered over the mesh so far, by (status, code): a copy, from any thread."""
        return self._answers.counts()

    def _on_remote_events(self, sub: _Subscription, batch: list[Sample]) -> None:
        # Runs on the subscription's transport worker: decodes what arrived and hands it to the loop
        # in one item (one wake-up of the loop per batch). zenoh matched each key against this
        # subscription's pattern; an event's fields must name that same key.
        events: list[tuple[Event, str, _Subscription | None]] = []
        keys_of = self._event_keys
        for key, payload, deleted, _ in batch:
            if deleted:
                continue
            try:
                event = _decode_event(payload, key)
                named = keys_of.get((event.embodiment, event.component, event.name)) or \
                    self._event_key(event.embodiment, event.component, event.name)
                if named != key:
                    raise ProtocolError(f"{key}: the event says it is {event.embodiment}/{event.component}/{event.name}")
            except ProtocolError as exc:
                log.warning("ignored event: %s", exc)
                continue
            except InvalidName as exc:
                log.warning("ignored event: %s: %s", key, exc)
                continue
            events.append((event, key, sub))
        if events:
            self._inbox.put(events)

    # --- events -----------------------------------------------------------------------------

    def _event_key(self, embodiment: str, component: str, name: str) -> str:
        """``keys.event_key`` in this mesh, cached: names are checked once, not per event."""
        cache = self._event_keys
        key = cache.get((embodiment, component, name))
        if key is None:
            key = keys.event_key(self.mesh, embodiment, component, name)  # raises InvalidName
            if len(cache) >= MAX_CACHED_KEYS:
                cache.clear()
            cache[(embodiment, component, name)] = key
        return key

    def raise_event(self, component: str, name: str, data: Any = None) -> None:
        """Raise an event: published now, dispatched locally in order. Thread-safe.

        Raises ``InvalidName`` at once (on any thread) if a name cannot be a key chunk.
        """
        embodiment = self.embodiment
        key = self._event_keys.get((embodiment, component, name)) or self._event_key(embodiment, component, name)
        if threading.get_ident() != self._loop_ident:
            self.call(lambda: self.raise_event(component, name, data))
            return
        if type(data) not in _SCALARS:
            check_value(data)
        event = Event(embodiment, component, name, data, next(self._seq), time.time())
        self._events.append((event, key, None))
        self.events_raised += 1
        try:
            self.transport.publish(key, encode(event))  # encoded once, whoever subscribes; queued, never waits
        except MeshError as exc:
            log.warning("could not publish %s: %s", key, exc)

    def on_event(
        self, handler: EventHandler, *, embodiment: str | None = None, component: str = "*", event: str = "*"
    ) -> Closeable:
        """Call ``handler`` on the loop for each matching event, local or remote, one at a time."""
        pattern = keys.event_pattern(self.mesh, embodiment or self.embodiment, component, event)
        sub = _Subscription(self, pattern, handler)
        with self._lock:
            self._subscriptions.append(sub)
            self._matching = {}
        sub.remote = self.transport.subscribe_batches(pattern, sub.on_samples, remote_only=True)
        return sub

    def _unsubscribe(self, sub: _Subscription) -> None:
        with self._lock:
            if sub in self._subscriptions:
                self._subscriptions.remove(sub)
                self._matching = {}

    def _subscribers(self, key: str) -> list[_Subscription]:
        """The subscriptions whose pattern matches ``key``, cached until the subscriptions change."""
        subs = self._matching.get(key)
        if subs is None:
            with self._lock:  # computed and stored under the lock that guards changes: never stale
                subs = [sub for sub in self._subscriptions if keys.matches(sub.pattern, key)]
                if len(self._matching) >= MAX_CACHED_KEYS:
                    self._matching = {}
                self._matching[key] = subs
        return subs

    # --- requests out -------------------------------------------------------------------------

    def request(
        self,
        component: str,
        name: str,
        payload: Message,
        *,
        embodiment: str | None = None,
        on_outcome: OutcomeHandler | None = None,
        timeout: float = DEFAULT_REQUEST_TIMEOUT,
    ) -> Future[Outcome]:
        """Send a request; the outcome completes the future and, if given, ``on_outcome`` runs on the loop.

        A request to a component of this simulation goes straight to the inbox; one to another
        embodiment is a zenoh query sent from a worker, never from the loop. If nobody answers,
        the outcome is ``rejected`` with reason ``outcome unknown: ...``; ``on_outcome`` sees it.
        """
        target = embodiment or self.embodiment
        future: Future[Outcome] = Future()

        def settle(outcome: Outcome) -> None:
            if not future.done():
                future.set_result(outcome)
            if on_outcome is not None and not self._closed:
                self.call(lambda: on_outcome(outcome))

        if self._closed:
            settle(Outcome("rejected", f"embodiment {self.embodiment!r} is shutting down", code=Code.SHUTTING_DOWN))
            return future
        local = self._components.get(component) if target == self.embodiment else None
        if local is not None:
            kind = local.requests.get(name)
            if kind is None:
                settle(Outcome("rejected", f"component {component!r} has no request {name!r}", code=Code.UNKNOWN_REQUEST))
            elif not isinstance(payload, kind):
                reason = f"request {name!r} of {component!r} takes {tag(kind)!r}, not {tag(type(payload))!r}"
                settle(Outcome("rejected", reason, code=Code.MALFORMED))
            else:
                item = IncomingRequest(component, name, payload, self.embodiment, settle)
                self._inbox.put(_RequestItem(local, item))
            return future
        key = keys.request_key(self.mesh, target, component, name)
        if self._pool is None:
            with self._lock:
                if self._pool is None:
                    self._pool = ThreadPoolExecutor(max_workers=8, thread_name_prefix=f"rq-{self.embodiment}")

        def remote() -> None:
            try:
                settle(send_request(self.transport, key, payload, timeout=timeout))
            except OutcomeUnknown as exc:
                settle(Outcome("rejected", f"outcome unknown: {exc}", code=Code.OUTCOME_UNKNOWN))

        self._pool.submit(remote)
        return future

    # --- the loop -----------------------------------------------------------------------------

    def run_once(self, timeout: float | None = 0.0) -> int:
        """Run one update on the calling thread; returns the number of work items it ran (calls,
        due timers, requests, remote events).

        For a simulation that is stepped rather than started (deterministic tests): it takes
        everything queued, waiting up to ``timeout`` seconds for a first item (None: until one
        comes; 0: not at all) or for the next timer, and runs due timers, calls, requests and
        events exactly as the loop would. The calling thread counts as the loop from now on.
        """
        if self._thread is not None:
            raise MeshError(f"simulation {self.embodiment!r} runs its own loop: run_once steps one that was not started")
        if self._closed:
            raise ClosedError(f"simulation {self.embodiment!r} is closed")
        self._stepper = threading.current_thread()
        self._loop_ident = threading.get_ident()
        items, _ = self._take(timeout)
        self._update(items)
        return len(items)

    def _take(self, timeout: float | None) -> tuple[list[Any], bool]:
        """The work of one update: wait up to ``timeout`` (or the next timer) for a first item,
        then take what else is queued. Also says whether ``close`` asked the loop to stop."""
        inbox = self._inbox
        next_due = self._timers.next_due()
        if next_due is not None:
            due = max(0.0, next_due - time.monotonic())
            timeout = due if timeout is None else min(timeout, due)
        items: list[Any] = []
        try:
            items.append(inbox.get(timeout=timeout) if timeout is None or timeout > 0 else inbox.get_nowait())
        except queue.Empty:  # a timer is due, or nothing came in time
            pass
        # The loop is the inbox's only reader, so this many get_nowait() cannot fail.
        waiting = inbox.qsize()
        if waiting:
            get = inbox.get_nowait
            items.extend(get() for _ in range(min(waiting, MAX_ITEMS_PER_UPDATE - len(items))))
        if _STOP in items:
            return [item for item in items if item is not _STOP], True
        return items, False

    def _run(self) -> None:
        self._loop_ident = threading.get_ident()
        try:
            stop = False
            while not stop:
                items, stop = self._take(None)
                self._update(items)
        finally:
            self._shutdown()
            self._stopped.set()

    def _update(self, items: list[Any]) -> None:
        self.updates += 1
        for fn in self._timers.pop_due():
            items.insert(0, fn)
        batches: dict[str, list[IncomingRequest]] = {}
        events = self._events
        for item in items:
            kind = type(item)
            if kind is list:  # remote events, in the order their subscription received them
                events.extend(item)
                self.events_received += len(item)
            elif kind is _RequestItem:
                batches.setdefault(item.component.name, []).append(item.request)
            else:
                self._guard("call", item)
        for name, batch in batches.items():
            component = self._components.get(name)
            if component is None:
                for request in batch:
                    request.reject(f"component {name!r} was removed", Code.UNKNOWN_REQUEST)
                continue
            try:
                component.handle_requests(batch)
            except Exception as exc:
                log.exception("%s.handle_requests failed in embodiment %s", name, self.embodiment)
                for request in batch:
                    if not request.answered:
                        request.reject(f"component {name!r} failed on {request.name!r}: {type(exc).__name__}: {exc}",
                                       Code.HANDLER_FAILED)
            for request in batch:
                if not request.answered and not request.deferred:
                    request.reject(f"component {name!r} gave no answer to {request.name!r}", Code.UNANSWERED)
        dispatched = 0
        while events and dispatched < MAX_EVENTS_PER_UPDATE:
            event, key, target = events.popleft()
            dispatched += 1
            if target is not None:  # a remote event, for the one subscription that received it
                if not target.closed:
                    try:
                        target.handler(event)
                    except Exception:
                        log.exception("handler of %s failed in embodiment %s", key, self.embodiment)
                continue
            for sub in self._subscribers(key):
                if not sub.closed:
                    try:
                        sub.handler(event)
                    except Exception:
                        log.exception("handler of %s failed in embodiment %s", key, self.embodiment)
        if self._events:
            self._inbox.put(lambda: None)  # carry the rest into the next update

    def _guard(self, what: str, fn: Callable[..., Any], *args: Any) -> None:
        try:
            fn(*args)
        except Exception:
            log.exception("%s failed in embodiment %s", what, self.embodiment)

    def _shutdown(self) -> None:
        # Queryables first (joining their workers), so no request can slip in after the drain;
        # then whatever is still queued gets a definite answer rather than silence.
        for queryable in list(self._queryables.values()):
            queryable.close()
        self._queryables.clear()
        self._answers.close()
        while True:
            try:
                item = self._inbox.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, _RequestItem):
                item.request.reject(f"embodiment {self.embodiment!r} is shutting down", Code.SHUTTING_DOWN)
        for sub in list(self._subscriptions):
            sub.close()
        for component in reversed(list(self._components.values())):
            self._guard(f"{component.name}.detach", component.detach)


@contextlib.contextmanager
def serve(component: Component, *, embodiment: str, transport: Transport, mesh: str = keys.DEFAULT_MESH) -> Iterator[Simulation]:
    """Host ``component`` for ``embodiment`` from this process (a remote mind, a remote competency):
    a simulation carrying the embodiment's name, so requests and events travel over the mesh."""
    with Simulation(transport, mesh=mesh, embodiment=embodiment) as sim:
        sim.add(component)
        yield sim
