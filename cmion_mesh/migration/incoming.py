"""The target side of a migration: a companion arrives here (``Incoming``).

A source's ``have`` (before the prepare of a large identity) and its prepare are decided by
``handshake`` on what is recorded here, this embodiment's admission list and the custody claims
backed in the mesh (``claims``): a target refuses an offer that a backed claim shows stale (its
chain extends the offer) or forked (reported by ``forks``). While claims on the companion are
still being checked, the offer waits for them (``CLAIM_WAIT`` at most, ``MAX_WAITING`` offers),
so that the true holder's token is never raced by a fork. The sections a ``have`` leads to are the
uploads' (``uploads``).

An accepted prepare is recorded ``incoming`` (its document and sections on disk, the custody key
made here for the attempt) before the answer, and this embodiment declares its custody token at
once: no moment passes in which nobody claims the companion. The commit makes the record
``active`` at the next epoch and the companion lives here (``MigrationOccurred``); an abort drops
the attempt (``MigrationDropped``). If neither comes, this side asks the source (``status``), as
after a restart in ``incoming``; an attempt still undecided ``handshake.INCOMING_BOUND`` seconds
after its prepare's record (``CMION_MESH_INCOMING_TIMEOUT``; counted across restarts) is dropped,
so a source that vanished cannot occupy this embodiment for good.

A handshake message counts only from the embodiment it names as its source (``sent_by_source``);
each sender's prepares and ``have``s take from its budget (``bounds.TokenBucket``).

Threads:

* the loop runs every request handler, the offers' wait for claims, activation, and the timer that
  drops an attempt at its bound (``_expire``);
* a handshake thread asks the source of an attempt left undecided (``resolve_incoming``: after a
  restart, or once a timer on the loop finds it overdue); it only reads the records and posts what
  it learnt to the loop (``_settle``).

Log lines at info, one per step (fields ``companion``, ``peer`` (the source), ``epoch``,
``attempt``, ``step``): ``incoming`` (the prepare recorded), ``active`` (the companion arrived:
its new ``epoch`` and ``duration_s`` since the prepare was recorded), ``dropped`` (with its
``reason``). Offers refused are the refused requests' lines.
"""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import dataclass
from typing import Any

import msgspec

from cmion_mesh import logs
from cmion_mesh.errors import MeshError, OutcomeUnknown
from cmion_mesh.messages import Code, MigrateAbort, MigrateCommit, MigrateHave, MigratePrepare, MigrateStatus
from cmion_mesh.migration import handshake
from cmion_mesh.migration.bounds import TokenBucket
from cmion_mesh.migration.claims import Claims
from cmion_mesh.migration.forks import Forks
from cmion_mesh.migration.host import Host, crash_point
from cmion_mesh.migration.identity import Bytes, Identity
from cmion_mesh.migration.ledger import Record
from cmion_mesh.migration.uploads import Uploads
from cmion_mesh.requests import IncomingRequest

log = logging.getLogger(__name__)

#: ``CMION_MESH_INCOMING_TIMEOUT`` changes ``handshake.INCOMING_BOUND``, the seconds after its
#: prepare at which an attempt its source has neither committed nor aborted is dropped.
INCOMING_TIMEOUT_ENV = "CMION_MESH_INCOMING_TIMEOUT"
#: Longest wait of a prepare or a ``have`` for the claims on its companion to be checked.
CLAIM_WAIT = 3.0
#: Requests waiting for claims to be checked, beyond which a new one is decided at once.
MAX_WAITING = 32


def sent_by_source(request: IncomingRequest, source: str, what: str) -> bool:
    """A handshake message counts only from the embodiment it names as its source."""
    if request.requester == source:
        return True
    request.reject(f"{request.requester!r} cannot send {what} on behalf of {source!r}")
    return False


@dataclass(eq=False)
class _Waiting:
    """A prepare or ``have`` waiting for the claims on its companion to be checked (loop)."""

    request: IncomingRequest
    message: MigratePrepare | MigrateHave
    deadline: float


class Incoming:
    """The target side: offers decided, attempts recorded, activated, settled or dropped."""

    def __init__(self, host: Host, claims: Claims, forks: Forks, uploads: Uploads, *, timeout: float) -> None:
        self.host = host
        self.claims = claims
        self.forks = forks
        self.uploads = uploads
        self.timeout = timeout  # seconds after its prepare at which an undecided attempt is dropped
        self._prepared: dict[str, Identity] = {}  # attempt -> identity parsed at prepare, for its commit (loop)
        self._buckets: dict[str, TokenBucket] = {}  # sender -> prepare budget (loop)
        self._waiting: list[_Waiting] = []  # offers waiting for claims to be checked (loop)

    def close(self) -> None:
        """Refuse the offers still waiting: the component detaches."""
        waiting, self._waiting = self._waiting, []
        for wait in waiting:
            wait.request.reject(f"embodiment {self.host.sim.embodiment!r} is shutting down", Code.SHUTTING_DOWN)

    # --- offers (loop) ----------------------------------------------------------------------------

    def on_have(self, request: IncomingRequest, msg: MigrateHave, waited: bool = False) -> None:
        """Which sections of the offered manifest are here already (each read and checked against its
        hash: a damaged one is missing, and fetched again)."""
        host = self.host
        record = host.records.get(msg.companion)
        early = handshake.precheck(msg, record, me=host.sim.embodiment, held=host.records.hosting(), admit=host.admit)
        if early is not None:
            request.answer(early.outcome)
            return
        if not waited and self._wait_for_claims(request, msg):
            return
        if self.uploads.staged(msg.attempt, msg.source) is None and not self._take_token(msg.source):
            request.reject(f"busy: too many prepares from {msg.source!r}; try again later", Code.BUSY)
            return
        busy = self.uploads.full(msg.source)
        if busy:
            request.reject(busy, Code.BUSY)
            return
        decision = handshake.on_have(msg, record, me=host.sim.embodiment,
                                     held=host.records.hosting(), admit=host.admit, claims=self.claims.backed(msg.companion))
        if decision.fork is not None:
            self.forks.seen_fork(decision.fork, msg.source)
        if decision.manifest is None:
            request.answer(decision.outcome)
            return
        self.uploads.begin(request, msg, decision.manifest)

    def on_prepare(self, request: IncomingRequest, msg: MigratePrepare, waited: bool = False) -> None:
        host = self.host
        me = host.sim.embodiment
        record = host.records.get(msg.companion)
        repeat = record is not None and record.state == "incoming" and record.attempt == msg.attempt
        # Only offers that would cost this embodiment custody checks, XML and disk take from the budget.
        early = handshake.precheck(msg, record, me=me, held=host.records.hosting(), admit=host.admit)
        if early is not None:
            request.answer(early.outcome)
            return
        if not repeat and not waited and self._wait_for_claims(request, msg):
            return
        if not repeat and self.uploads.staged(msg.attempt, msg.source) is None and not self._take_token(msg.source):
            request.reject(f"busy: too many prepares from {msg.source!r}; try again later")
            return
        carried: dict[str, Bytes] = {}
        decision = handshake.on_prepare(msg, record, me=me, held=host.records.hosting(), admit=host.admit,
                                        claims=self.claims.backed(msg.companion),
                                        sections=self.uploads.sections_for(msg, carried),
                                        values={**host.memo.values(), **self.uploads.values(msg.attempt, msg.source)})
        if decision.fork is not None:
            self.forks.seen_fork(decision.fork, msg.source)
        if decision.record is None:
            if decision.outcome.code != Code.MISSING_SECTIONS:
                self.uploads.end(msg.source, msg.attempt)
            request.answer(decision.outcome)
            return
        assert decision.key is not None and decision.identity is not None and decision.manifest is not None
        unsynced = self.uploads.settled(msg.attempt, msg.source)  # its sections durable before incoming names them
        if unsynced:
            self.uploads.end(msg.source, msg.attempt)
            request.reject(f"{me!r} cannot take {msg.companion!r}: {unsynced}", Code.INVALID)
            return
        # The sections it carried were sent because they are missing here, or damaged: written anew.
        incoming = host.records.put(msgspec.structs.replace(decision.record, since=time.time()), document=decision.document,
                                    sections=carried, key=decision.key, replace=True)
        crash_point("target:incoming")
        host.step(incoming)
        log_step(f"companion {msg.companion} incoming from {msg.source}", "incoming", incoming, msg.source)
        self.uploads.end(msg.source, prepared=True)
        self._prepared = {msg.attempt: decision.identity}  # one handshake at a time: parsing it again at commit is waste
        request.answer(decision.outcome)
        # After the answer, off the critical path: the commit is handled on this loop only once this
        # returns, and the source keeps its own claim until then, so no moment passes in which
        # nobody claims the companion.
        host.claim(msg.companion, msg.epoch)
        for ref in decision.manifest.refs:
            if decision.sections is not None:
                host.memo.remember(ref.component, decision.sections[ref.sha256], ref.sha256,
                                   decision.identity.sections.get(ref.component))
        # The commit (or abort) normally follows at once. If the link fails now, the source's one
        # abort may be lost for good: once overdue, ask the source, as after a restart. A timer on
        # the loop rather than a thread waiting: nothing starts on the way to the commit.
        host.sim.call_later(host.retry[1], functools.partial(self._overdue, incoming.companion, incoming.attempt))
        self.expire_later(incoming)

    def _overdue(self, companion: str, attempt: str) -> None:
        """Loop: ``attempt`` is still undecided a while after its prepare: ask its source."""
        current = self.host.records.get(companion)
        if current is not None and current.state == "incoming" and current.attempt == attempt:
            self.host.spawn(f"resolve-{companion}", self.resolve_incoming, current)

    def _take_token(self, source: str) -> bool:
        bucket = self._buckets.setdefault(source, TokenBucket())
        if len(self._buckets) > 1024:
            self._buckets = {source: bucket}  # bounded: forget strangers, keep the one asking
        return bucket.take()

    # --- offers waiting for claims to be checked (loop) ----------------------------------------------

    def _wait_for_claims(self, request: IncomingRequest, msg: MigratePrepare | MigrateHave) -> bool:
        """Whether the offer waits (deferred) for the claims on its companion still being checked, so that
        the true holder's token is never raced by a fork. Bounded: ``CLAIM_WAIT``, ``MAX_WAITING``."""
        if not self.claims.pending(msg.companion) or len(self._waiting) >= MAX_WAITING:
            return False
        request.defer()
        self._waiting.append(_Waiting(request, msg, time.monotonic() + CLAIM_WAIT))
        self.host.sim.call_later(CLAIM_WAIT, functools.partial(self.claims_settled, msg.companion))
        return True

    def claims_settled(self, companion: str) -> None:
        """Decide the offers that wait for claims on ``companion``: all once none is pending, else
        those that waited ``CLAIM_WAIT`` (a claim still unchecked then counts as not backed)."""
        pending = self.claims.pending(companion)
        now = time.monotonic()
        ready = [w for w in self._waiting if w.message.companion == companion and (not pending or w.deadline <= now)]
        if not ready:
            return
        self._waiting = [w for w in self._waiting if w not in ready]
        for wait in ready:
            try:
                match wait.message:
                    case MigratePrepare() as prepare:
                        self.on_prepare(wait.request, prepare, waited=True)
                    case MigrateHave() as have:
                        self.on_have(wait.request, have, waited=True)
            except MeshError as exc:
                wait.request.reject(str(exc))
            if not wait.request.answered:
                wait.request.reject(f"component {self.host.name!r} gave no answer", Code.UNANSWERED)

    # --- the attempt decided (loop) ------------------------------------------------------------------

    def on_commit(self, request: IncomingRequest, msg: MigrateCommit) -> None:
        decision = handshake.on_commit(msg, self.host.records.get(msg.companion), me=self.host.sim.embodiment)
        if decision.record is not None:
            self._activate(decision.record)
        request.answer(decision.outcome)

    def on_abort(self, request: IncomingRequest, msg: MigrateAbort) -> None:
        host = self.host
        decision = handshake.on_abort(msg, host.records.get(msg.companion), requester=request.requester)
        self.uploads.end(request.requester, msg.attempt)
        if decision.record is not None:
            host.records.put(decision.record)
            self._prepared.pop(msg.attempt, None)
            if host.identity is None:
                host.withdraw_claim()
            log_step(f"migration of {msg.companion} from {request.requester} dropped: the source aborted it", "dropped",
                     decision.record, request.requester, attempt=msg.attempt, reason="aborted by the source")
            host.raise_event("MigrationDropped", {"companion": msg.companion, "attempt": msg.attempt,
                                                  "source": request.requester})
        request.answer(decision.outcome)

    def _activate(self, active: Record) -> None:
        host = self.host
        before = host.records.get(active.companion)
        since = before.since or before.updated if before is not None and before.state == "incoming" else 0.0
        # ``active`` is durable before the companion wakes here: were it woken first, a write that
        # failed (a full disk) would leave it running on a record still ``incoming``, which the
        # source may then abort and resume (two hosts).
        active = host.records.put(active)
        crash_point("target:active")
        host.step(active)
        log_step(f"companion {active.companion} arrived from {active.peer}", "active", active, active.peer,
                 duration_s=round(max(0.0, time.time() - since), 4) if since else None)
        self.forks.clear()  # a frozen holder accepts no prepare: any evidence here was of a copy long gone
        identity = self._prepared.pop(active.attempt, None)
        if identity is None:  # restarted since the prepare: the stored document is the truth
            identity = host.records.identity(active.companion, host.memo) or Identity(active.companion, active.epoch, {})
        identity.epoch = active.epoch
        host.inhabit(identity, "MigrationOccurred", f"arrived from {active.peer}")

    # --- an attempt left undecided -------------------------------------------------------------------

    def resolve_incoming(self, record: Record) -> None:
        """Handshake thread: ask the source until it says committed or aborted: after a restart in
        ``incoming``, and a while after a prepare if neither a commit nor an abort has come."""
        host = self.host
        delay = host.retry[0]
        status = MigrateStatus(record.companion, record.attempt, record.epoch, "source")
        while not host.stopping.is_set():
            current = host.records.get(record.companion)
            if current is None or current.state != "incoming" or current.attempt != record.attempt:
                return  # a commit or abort arrived meanwhile
            try:
                reply = host.ask(record.peer, "status", status)
                if reply.status == "accepted" and handshake.settle_incoming(current, reply.value, me=host.sim.embodiment):
                    host.post(self._settle, record, reply.value)
                    return
            except OutcomeUnknown as exc:
                log.info("asking %s about %s: %s", record.peer, record.attempt, exc)
            if host.stopping.wait(delay):
                return
            delay = min(host.retry[1] * 2, delay * 2)

    def _settle(self, record: Record, answer: Any) -> None:
        current = self.host.records.get(record.companion)
        if current is None or current.state != "incoming" or current.attempt != record.attempt:
            return
        settled = handshake.settle_incoming(current, answer, me=self.host.sim.embodiment)
        if settled is None:
            return
        if settled.state == "active":
            self._activate(settled)
        else:
            self._drop(settled, f"{record.peer!r} aborted it")

    def expire_later(self, record: Record) -> None:
        """Loop: drop ``record``'s attempt at its deadline if it is still undecided then. The timer
        holds the names only: a record carries the companion's chain of custody, and the deadline of
        every attempt of the last minute is pending (many, when migrations come one after another)."""
        due = handshake.incoming_deadline(record, self.timeout)
        self.host.sim.call_later(max(0.0, due - time.time()), functools.partial(self._expire, record.companion, record.attempt))

    def _expire(self, companion: str, attempt: str) -> None:
        current = self.host.records.get(companion)
        if current is None or current.state != "incoming" or current.attempt != attempt:
            return  # decided meanwhile
        expired = handshake.expire_incoming(current, now=time.time(), bound=self.timeout)
        if expired is None:  # the clock went back since the timer was set
            self.expire_later(current)
            return
        reason = (f"{current.peer!r} neither committed nor aborted attempt {current.attempt} of {current.companion!r} "
                  f"within {self.timeout:g} s of its prepare")
        self._drop(expired, reason, logging.WARNING)

    def _drop(self, dropped: Record, reason: str, level: int = logging.INFO) -> None:
        """Loop: the attempt ``dropped`` ends here, durably first (the source is told ``dropped`` from
        this record on); the embodiment is free for the next migration."""
        host = self.host
        host.records.put(dropped)
        log_step(f"migration of {dropped.companion} from {dropped.peer} dropped: {reason}", "dropped", dropped, dropped.peer,
                 level=level, reason=reason)
        self._prepared.pop(dropped.attempt, None)
        self.uploads.end(dropped.peer, dropped.attempt)
        if host.identity is None:
            host.withdraw_claim()
        host.raise_event("MigrationDropped", {"companion": dropped.companion, "attempt": dropped.attempt,
                                              "source": dropped.peer, "reason": reason})


def log_step(msg: str, step: str, record: Record, source: str, *, attempt: str | None = None, level: int = logging.INFO,
             **more: Any) -> None:
    """One line for a step of this side of the handshake, with the fields every step has."""
    logs.event(log, msg, level=level, step=step, companion=record.companion, peer=source, epoch=record.epoch,
               attempt=record.attempt if attempt is None else attempt, **more)
