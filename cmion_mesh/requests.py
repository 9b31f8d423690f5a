"""Requests and their answers: a request handed to a component, the answers an embodiment gave,
a request sent over the mesh.

* ``IncomingRequest``: what a component's ``handle_requests`` is handed. It is answered once
  (``accept``, ``reject``, ``conflict``, or a ready-made ``answer``; a second answer is ignored),
  or deferred to be answered later from the loop.
* ``Answers``: the answers one embodiment gave over the mesh, counted by status and code (for
  whoever watches the daemon) and, while some session listens on ``@outcome``, told there (a
  recorder sees requests this way: zenoh queries are invisible to a passive subscriber).
* ``send_request``: one request as a zenoh query, to a definite ``Outcome`` or an error saying
  whether it may have been delivered; ``require_accepted`` turns a refusal into ``RequestRejected``.

How requests reach components, which refusals are given before a component sees a request, and
the requests of one update handled together: ``ion.Simulation``.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any, Protocol, TypeVar

from cmion_mesh import keys
from cmion_mesh.errors import MeshError, NotReached, OutcomeUnknown, ProtocolError, RequestRejected
from cmion_mesh.messages import Code, Message, Outcome, RequestAnswered, check_value, decode, encode
from cmion_mesh.transport.base import Matching, Reply, Transport

log = logging.getLogger(__name__)
A = TypeVar("A", bound="Addressee")

DEFAULT_REQUEST_TIMEOUT = 10.0
#: Bound of the cache of ``@outcome`` keys (cleared when full: request names are not ours to bound).
MAX_OUTCOME_KEYS = 4096
#: Refusals that are a step of a protocol, not news for a person: a target lacking sections says so
#: with a refusal, and the source sends them (``migration.outgoing``). Logged at debug only.
ROUTINE_REFUSALS = frozenset({Code.MISSING_SECTIONS})
#: The sender named in the log for a request on a key without one (only handshake keys name theirs).
UNNAMED = "(unnamed)"
#: Characters of a refusal's reason written in its log line.
MAX_REASON = 300


class IncomingRequest:
    """One request handed to a component; answer it with ``accept``, ``reject`` or ``conflict``."""

    __slots__ = ("_answer", "component", "deferred", "name", "outcome", "payload", "requester")

    def __init__(
        self, component: str, name: str, payload: Any, requester: str, answer: Callable[[Outcome], None]
    ) -> None:
        self.component = component
        self.name = name
        self.payload = payload
        self.requester = requester
        self._answer = answer
        self.outcome: Outcome | None = None
        self.deferred = False

    @property
    def answered(self) -> bool:
        return self.outcome is not None

    def _send(self, outcome: Outcome) -> None:
        if self.outcome is not None:
            return  # first answer stands; repeated answers are ignored
        self.outcome = outcome
        try:
            self._answer(outcome)
        except MeshError:  # the requester vanished, or we are closing: its outcome is its own to recover
            log.debug("could not deliver outcome of %s/%s", self.component, self.name, exc_info=True)

    def defer(self) -> None:
        """The handler answers later, from the loop (it waits for something that must not block the
        loop): the request is not refused as unanswered at the end of this update. The handler must
        then answer it, within the requester's timeout."""
        self.deferred = True

    def answer(self, outcome: Outcome) -> None:
        """Send a ready-made outcome (a decision taken elsewhere)."""
        self._send(outcome)

    def accept(self, value: Any = None) -> None:
        self._send(Outcome("accepted", "", check_value(value)))

    def reject(self, reason: str, code: Code = Code.INVALID) -> None:
        self._send(Outcome("rejected", reason, code=code))

    def conflict(self, reason: str) -> None:
        self._send(Outcome("conflict", reason, code=Code.CONFLICT))


class Answers:
    """The answers one embodiment gave over the mesh. ``given`` is called from the loop and from the
    transport's workers (refusals that need no component): the lock keeps the count exact.

    Each refusal is a log line at info (``refused <component>/<request> from <sender>``, fields
    ``code``, ``sender``, ``component``, ``request``, ``reason``) through a ``logs.Throttle`` keyed
    by the sender: a flood writes the first line of each sender a window and then one count, so it
    cannot fill a disk. Accepted answers are only counted."""

    def __init__(self, transport: Transport, mesh: str, embodiment: str) -> None:
        self.transport = transport
        self.mesh = mesh
        self.embodiment = embodiment
        self._counts: dict[tuple[str, str], int] = {}
        self._lock = threading.Lock()
        # Whether someone (a recorder) listens to the answers: followed from the first queryable on,
        # so that an answer costs one attribute read when nobody does.
        self._listeners: Matching | None = None
        self._keys: dict[tuple[str, str], str] = {}
        # Here, not at the top: a one-shot command imports this module for send_request and never
        # answers a request; the log's machinery is the serving side's (start time of one-shots).
        from cmion_mesh import logs

        self._refused = logs.Throttle(log, "refused requests")

    def follow_listeners(self) -> None:
        """Start following who listens on ``@outcome`` (once; before the first queryable)."""
        with self._lock:
            if self._listeners is not None:
                return
            try:
                self._listeners = self.transport.matching(keys.outcome_pattern(self.mesh, self.embodiment))
            except MeshError as exc:  # answers are then not told; requests are served all the same
                log.warning("cannot follow who listens to %s's answers: %s", self.embodiment, exc)

    def given(self, component: str, request: str, sender: str, outcome: Outcome) -> None:
        """Count one answer, and tell it if someone listens."""
        counted = (outcome.status, outcome.code)
        with self._lock:
            self._counts[counted] = self._counts.get(counted, 0) + 1
        if outcome.status != "accepted":
            self._log_refusal(component, request, sender, outcome)
        listeners = self._listeners
        if listeners is not None and listeners.matching:
            self._tell(component, request, sender, outcome)

    def _log_refusal(self, component: str, request: str, sender: str, outcome: Outcome) -> None:
        reason = outcome.reason if len(outcome.reason) <= MAX_REASON else outcome.reason[:MAX_REASON] + "..."
        if outcome.code in ROUTINE_REFUSALS:
            from cmion_mesh import logs  # loaded by __init__ already: a lookup

            logs.event(log, f"{component}/{request} from {sender or UNNAMED}: {outcome.code}", level=logging.DEBUG,
                       code=str(outcome.code), sender=sender or None, component=component, request=request)
            return
        who = sender or UNNAMED
        self._refused(who, "refused %s/%s from %s", component, request, who, code=str(outcome.code or outcome.status),
                      sender=sender or None, component=component, request=request, reason=reason)

    def counts(self) -> dict[tuple[str, str], int]:
        """Answers given so far, by (status, code): a copy, from any thread."""
        with self._lock:
            return dict(self._counts)

    def _tell(self, component: str, request: str, sender: str, outcome: Outcome) -> None:
        """Publish how a request was answered, for whoever listens (only called while someone does).
        Dropped rather than waited for under congestion: a slow listener never slows a request."""
        key = self._keys.get((component, request))
        try:
            if key is None:
                key = keys.outcome_key(self.mesh, self.embodiment, component, request)
                if len(self._keys) >= MAX_OUTCOME_KEYS:
                    self._keys.clear()
                self._keys[(component, request)] = key
            told = RequestAnswered(self.embodiment, component, request, outcome.status, outcome.code, outcome.reason,
                                   sender, time.time())
            self.transport.publish(key, encode(told), block=False)
        except (MeshError, ValueError) as exc:  # a request name no key can carry, a closing session
            log.debug("could not tell the answer to %s/%s: %s", component, request, exc)

    def close(self) -> None:
        if self._listeners is not None:
            self._listeners.close()
        self._refused.flush()  # the counts of the last window: the embodiment stops


class Addressee(Protocol):
    """What routing a request needs of a component (``ion.Component``)."""

    @property
    def name(self) -> str: ...
    @property
    def requests(self) -> Mapping[str, Any]: ...
    @property
    def sender_requests(self) -> frozenset[str]: ...
    def request_catalogue(self) -> dict[str, Any]: ...


def addressed(key: str, prefix: str, components: Mapping[str, A]) -> A | None:
    """The component a request on the concrete ``key`` reaches (``prefix``: ``.../<embodiment>/rq/``):
    the one whose own queryable would take it, on ``prefix<name>/*`` (``/**`` if it has requests
    naming their sender); None when none would."""
    if not key.startswith(prefix):
        return None
    name, _, tail = key[len(prefix):].partition("/")
    component = components.get(name)
    if component is None or not component.requests:
        return None
    if not component.sender_requests and (not tail or "/" in tail):
        return None
    return component


def covered(selector: str, prefix: str, components: Iterable[A]) -> list[A]:
    """The components whose own queryable (as in ``addressed``) the key expression ``selector`` reaches."""
    return [c for c in components if c.requests and keys.intersects_below(selector, f"{prefix}{c.name}",
                                                                          one_chunk=not c.sender_requests)]


def unknown_request(component: Addressee, name: str) -> Outcome:
    """The refusal of a request ``component`` does not have, its catalogue as value."""
    known = ", ".join(sorted(component.requests)) or "none"
    reason = f"component {component.name!r} has no request {name!r} (known: {known})"
    return Outcome("rejected", reason, component.request_catalogue(), Code.UNKNOWN_REQUEST)


def send_request(transport: Transport, key: str, payload: Message, *, timeout: float = DEFAULT_REQUEST_TIMEOUT) -> Outcome:
    """Send one request as a zenoh query and return its ``Outcome``.

    Raises ``OutcomeUnknown`` when nobody answered, the link failed or the reply is unreadable;
    ``NotReached`` when no component was reached at all (not delivered: safe to send again).
    """
    return send_request_later(transport, key, payload, timeout=timeout)()


def send_request_later(transport: Transport, key: str, payload: Message, *,
                       timeout: float = DEFAULT_REQUEST_TIMEOUT) -> Callable[[], Outcome]:
    """``send_request`` in two steps: the request is sent when this returns (what the caller sends
    next goes after it), and the function returned waits for its ``Outcome`` (call it once), with
    the same errors."""
    started = time.monotonic()
    try:
        first = transport.get_first_later(key, encode(payload), timeout=timeout)
    except MeshError as exc:
        raise OutcomeUnknown(f"{key}: {exc}", key=key) from None
    return functools.partial(_outcome, first, key, started, timeout)


def _outcome(first: Callable[[], Reply | None], key: str, started: float, timeout: float) -> Outcome:
    try:
        reply = first()
    except MeshError as exc:
        raise OutcomeUnknown(f"{key}: {exc}", key=key) from None
    if reply is None:
        waited = time.monotonic() - started
        if waited < timeout * 0.9:  # zero replies before the deadline: no queryable was reached at all
            raise NotReached(f"no component answered {key}: nobody reached (after {waited:.2f} s)", key=key)
        raise OutcomeUnknown(f"no component answered {key} within {timeout:g} s", key=key)
    if not reply.ok:
        raise OutcomeUnknown(f"{key}: error reply {reply.payload[:200]!r}", key=key)
    try:
        outcome: Outcome = decode(reply.payload, Outcome, where=key)
    except ProtocolError as exc:
        raise OutcomeUnknown(str(exc), key=key) from None
    return outcome


def require_accepted(outcome: Outcome, key: str) -> Any:
    """The outcome's value if accepted, else ``RequestRejected`` naming the key and reason."""
    if outcome.status != "accepted":
        raise RequestRejected(f"{key}: {outcome.status}: {outcome.reason}", key=key, status=outcome.status,
                              reason=outcome.reason, code=outcome.code)
    return outcome.value
