"""The source side of a migration: the companion living here leaves for a target (``Outgoing``).

An attempt (``Departure``) begins with ``MigrationManager.start``, a ``migrate`` request or the
``Migration`` competency. Before packing, the source raises ``MigrationStarting`` and gives every
component one update to ``contribute`` its section (or ``wait`` and ``resolve`` later, within
``SECTION_DEADLINE``; ``refuse`` abandons the migration sooner). Sections that no component here
understands are carried on unchanged; the minds sleep until the handshake is decided.

**Sections travel apart** (SchemaVersion 2, ``identity``): the source packs the identity into a
manifest and section bytes off the loop; for a small identity it sends them all inside the
prepare; for a larger one it first sends ``have`` and the target answers which sections it holds
from an earlier visit (checked against their hash), then only the others cross, as raw bytes in
``migrate_sections`` chunks, while the source writes its own copy to its disk. The prepare is
idempotent: a lost answer is asked again, and sections the target says it lacks are sent first.

Once the target has accepted the prepare this side records ``handed``: the commit point, after
which the companion never runs here again (its custody token stays until the target has taken
it, so no moment passes in which nobody in the mesh claims it). It sends the commit until the
target answers; a refusal is settled by asking the target what it made of the attempt, never by
looping on it. ``MigrationSucceeded`` says how many bytes were sent (``transfer``);
``MigrationFailed`` says why the companion stays, and runs, here.

Threads:

* the loop runs ``begin`` (the checks), ``contribute``/``wait``/``resolve``/``refuse``, the packing
  and every step that touches the inhabitant or raises an event (``_abandon``, ``_handed``,
  ``_released``, ``_taken_back``); ``departure`` is the loop's;
* a handshake thread (``Host.spawn``: reused workers) per attempt runs ``_send`` and then
  ``commit_until_acked`` (also after a restart in ``handed``), and one per abort sent
  (``send_abort_later``): they touch only the records (locked) and hand everything else to the
  loop (``Host.post``);
* ``_send`` has another write this side's copy of the sections, then the ``prepared`` record that
  names them, beside the ``have``, the chunks (two send them) and the prepare itself; it is waited
  for before the prepare's answer is acted on (``handed`` comes after ``prepared``, always).

``start``, ``contribute``, ``resolve`` and ``refuse`` may be called from any thread.

Log lines at info, one per step (fields ``companion``, ``peer`` (the target), ``epoch``,
``attempt``, ``step``): ``started``, ``prepared``, ``handed`` (the commit point), ``released``
(the companion left: ``duration_s`` from the start, and the new ``epoch``), ``aborted`` (with
its ``reason``); a ``migrate`` refused before it starts is the refused request's line.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
import uuid
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import msgspec

from cmion_mesh import keys, logs
from cmion_mesh.errors import MeshError, OutcomeUnknown
from cmion_mesh.messages import (
    Code,
    Migrate,
    MigrateAbort,
    MigrateCommit,
    MigratePrepare,
    MigrateSections,
    MigrateStatus,
    Outcome,
    SectionChunk,
)
from cmion_mesh.migration import custody, handshake
from cmion_mesh.migration.claims import Claims
from cmion_mesh.migration.forks import RESOLVE, Forks
from cmion_mesh.migration.handshake import refuses
from cmion_mesh.migration.host import Host, crash_point
from cmion_mesh.migration.identity import Identity, Packed, SectionRef
from cmion_mesh.migration.ledger import Record
from cmion_mesh.requests import IncomingRequest

log = logging.getLogger(__name__)

#: Seconds the components of the source have to give their sections once a migration starts.
SECTION_DEADLINE = 5.0
#: Missing sections that together are at most this many bytes travel inside the prepare: a small
#: identity takes no round trip more than it used to (and no ``have``).
INLINE = 256 * 1024
#: Bytes of sections per ``migrate_sections`` request: a large section goes in chunks of this size.
CHUNK = 4 * 1024 * 1024
#: ``migrate_sections`` requests in flight at once.
IN_FLIGHT = 2


class _Refused(MeshError):
    """The target refused a step of the handshake before the prepare (the reason is its answer)."""


@dataclass(eq=False)
class Departure:
    """One attempt to migrate the companion from here (loop; ``transfer`` is the handshake thread's)."""

    companion: str
    target: str
    epoch: int
    attempt: str
    future: Future[Outcome]
    contributions: dict[str, Any] = field(default_factory=dict)
    waits: set[str] = field(default_factory=set)
    packed: bool = False
    transfer: dict[str, int] = field(default_factory=dict)  # bytes sent / of the document (handshake thread)
    started: float = field(default_factory=time.monotonic)


class WaitToken(msgspec.Struct, frozen=True):
    attempt: str
    component: str


class _AnswerFuture(Future[Outcome]):
    """Rejects a ``migrate`` request refused at once; a started one is accepted by the handler and
    its end is reported by events (``MigrationSucceeded`` / ``MigrationFailed``)."""

    def __init__(self, request: IncomingRequest) -> None:
        super().__init__()
        self.request = request

    def set_result(self, result: Outcome) -> None:
        if not self.request.answered:
            if result.status == "accepted":
                self.request.accept(result.value)
            else:
                self.request.reject(result.reason)
        super().set_result(result)


class Outgoing:
    """The source side: one ``departure`` at a time, from its checks until the target committed."""

    def __init__(self, host: Host, claims: Claims, forks: Forks, *, section_deadline: float) -> None:
        self.host = host
        self.claims = claims
        self.forks = forks
        self.section_deadline = section_deadline
        self.departure: Departure | None = None  # loop
        #: The last migration from here: bytes of the document sent and in all (``MigrationSucceeded``'s ``transfer``).
        self.last_transfer: dict[str, int] | None = None

    @property
    def target(self) -> str | None:
        """The target of the migration under way from here, if any."""
        out = self.departure
        return out.target if out is not None else None

    # --- an attempt begins (loop) ---------------------------------------------------------------

    def start(self, request: Migrate) -> Future[Outcome]:
        """Begin ``request`` on the loop; thread-safe. The future ends with the outcome (accepted when
        the target committed; rejected with the reason)."""
        future: Future[Outcome] = Future()
        self.host.post(self._start_from_thread, request, future)
        return future

    def _start_from_thread(self, request: Migrate, future: Future[Outcome]) -> None:
        self.begin(request, future)

    def on_migrate(self, request: IncomingRequest, payload: Migrate) -> None:
        """The ``migrate`` request: refused at once, or accepted once started (its end is an event)."""
        out = self.begin(payload, _AnswerFuture(request))
        if out is not None:  # started: the end is reported by MigrationSucceeded/Failed events
            request.accept({"attempt": out.attempt, "companion": out.companion, "target": out.target})

    def begin(self, request: Migrate, future: Future[Outcome]) -> Departure | None:
        host = self.host
        me = host.sim.embodiment

        def refuse(reason: str) -> None:
            host.raise_event("MigrationFailed", {"companion": request.companion, "target": request.target, "reason": reason})
            future.set_result(Outcome("rejected", reason))

        identity = host.identity
        if identity is None:
            refuse(f"embodiment {me!r} hosts no companion")
            return None
        if request.companion and request.companion != identity.companion:
            refuse(f"companion {request.companion!r} does not live on {me!r} "
                   f"(its inhabitant is {identity.companion!r})")
            return None
        if self.forks.frozen is not None:
            refuse(f"custody of {identity.companion!r} is frozen by a fork of its chain "
                   f"({'; '.join(f.describe() for _, f in self.forks.frozen.forks(me))}): "
                   f"an operator resolves it with `{RESOLVE.format(companion=identity.companion)}`")
            return None
        if self.departure is not None:
            refuse(f"a migration of {identity.companion!r} to {self.departure.target!r} is already under way")
            return None
        try:
            keys.check_name(request.target, "target")
        except MeshError as exc:
            refuse(str(exc))
            return None
        if request.target == me:
            refuse(f"{identity.companion!r} already lives on {request.target!r}")
            return None
        if not self.claims.is_alive(request.target):
            refuse(f"unknown target: embodiment {request.target!r} is not alive in mesh {host.sim.mesh!r}")
            return None
        record = host.records.get(identity.companion)
        if record is None or record.state != "active":
            refuse(f"{identity.companion!r} is not active here")
            return None
        refused_by = refuses(identity, request.target)
        if refused_by:
            refuse(refused_by)
            return None
        out = Departure(identity.companion, request.target, record.epoch, uuid.uuid4().hex, future)
        self.departure = out
        host.raise_event("MigrationStarting", {"companion": out.companion, "target": out.target, "attempt": out.attempt,
                                               "epoch": out.epoch})
        logs.event(log, f"migration of {out.companion} to {out.target} started", step="started", companion=out.companion,
                   peer=out.target, epoch=out.epoch, attempt=out.attempt)
        host.sleep_minds()  # freeze: the companion acts nowhere until the handshake is decided
        # The event is dispatched in this update; sections are collected from the next one on.
        host.sim.call(functools.partial(self._maybe_pack, out))
        host.sim.call_later(self.section_deadline, functools.partial(self._section_deadline, out))
        return out

    # --- the components' sections (loop) --------------------------------------------------------

    def contribute(self, component: str, data: Any) -> None:
        """Add ``component``'s section to the migration being packed. Thread-safe.

        On the loop (a ``MigrationStarting`` handler) it applies at once: posted, it would queue
        behind the packing that the same update already scheduled, and miss the document."""
        if self.host.sim.on_loop():
            self._contribute(component, data)
        else:
            self.host.post(self._contribute, component, data)

    def _contribute(self, component: str, data: Any) -> None:
        out = self.departure
        if out is not None and not out.packed:
            out.contributions[component] = data
            out.waits.discard(component)
            self._maybe_pack(out)

    def wait(self, component: str) -> WaitToken:
        """Ask the packing to wait for ``component`` (loop thread); ``resolve`` ends the wait."""
        out = self.departure
        if out is None or out.packed:
            raise MeshError("no migration is being packed")
        out.waits.add(component)
        return WaitToken(out.attempt, component)

    def resolve(self, token: WaitToken, data: Any) -> None:
        """End a wait with the component's section. Thread-safe."""
        self.host.post(self._resolve, token, data)

    def _resolve(self, token: WaitToken, data: Any) -> None:
        out = self.departure
        if out is not None and out.attempt == token.attempt:
            self._contribute(token.component, data)

    def refuse(self, token: WaitToken, reason: str) -> None:
        """End a wait by abandoning the migration: the component cannot give its section (its
        reason is the migration's). Thread-safe. Sooner and clearer than the section deadline."""
        self.host.post(self._refuse, token, reason)

    def _refuse(self, token: WaitToken, reason: str) -> None:
        out = self.departure
        if out is not None and out.attempt == token.attempt and not out.packed:
            self._abandon(out, f"{token.component}: {reason}")

    def _section_deadline(self, out: Departure) -> None:
        if self.departure is out and not out.packed:
            self._abandon(out, f"components {sorted(out.waits)} did not give their sections within {self.section_deadline:g} s")

    def _abandon(self, out: Departure, reason: str) -> None:
        self.departure = None
        self.claims.forget(out.target, out.companion)
        log_step(f"migration of {out.companion} to {out.target} aborted: {reason}", "aborted", out.companion, out.target,
                 out.epoch, out.attempt, reason=reason)
        self.host.raise_event("MigrationFailed", {"companion": out.companion, "target": out.target, "attempt": out.attempt,
                                                  "reason": reason})
        if not self.forks.halted:
            for mind in self.host.minds():
                mind.wake()
        if not out.future.done():
            out.future.set_result(Outcome("rejected", reason))

    def _maybe_pack(self, out: Departure) -> None:
        if self.departure is not out or out.packed or out.waits:
            return
        identity = self.host.identity
        assert identity is not None
        self.host.refresh_sections(identity)
        sections = dict(identity.sections)  # carried-on sections stay unless freshly contributed
        sections.update(out.contributions)
        out.packed = True
        # Encoding and hashing happen on the handshake thread: the minds sleep, nothing changes these.
        self.host.spawn(f"send-{out.companion}", self._send, out, Identity(out.companion, out.epoch, sections))

    # --- the handshake (a handshake thread) --------------------------------------------------------

    def _send(self, out: Departure, identity: Identity) -> None:
        """Handshake thread: pack, send what the target lacks, prepare, then (once handed) commit."""
        host = self.host
        known = set(host.memo.held())  # sections packed or received here before: a target may hold them
        try:
            packed = identity.pack_sections(host.memo)
        except (MeshError, ValueError) as exc:
            host.post(self._abandon, out, f"cannot pack the identity: {exc}")
            return
        active = host.records.get(out.companion)
        private = host.records.key(out.companion)
        if active is None or active.state != "active" or private is None:
            host.post(self._aborted, out, f"{out.companion!r} is not active here with its custody key")
            return
        prepared, message = handshake.offer(active, attempt=out.attempt, me=host.sim.embodiment, target=out.target,
                                            document=packed.manifest, private=private)
        refs = list({ref.sha256: ref for ref in packed.refs}.values())
        out.transfer = {"sent": 0, "total": packed.size, "sections": len(refs), "sections_sent": 0}
        stored: list[BaseException] = []
        written: list[Record] = []
        done = threading.Event()

        def store() -> None:
            # This side's copy, written while the target receives its own; then, once the sections
            # are on disk, the prepared record that names them, still while the chunks (or the
            # prepare itself) travel: a crash from here on is the crash at source:prepared (never
            # handed: the source resumes). It is waited for before anything acts on the prepare's answer.
            try:
                try:
                    written.append(host.records.put(prepared, document=packed.manifest, sections=packed.data))
                except OSError as exc:
                    stored.append(exc)
                    return
                crash_point("source:prepared")
                host.post(host.step, written[0])  # before handed's, which waits for this
                log_prepared(written[0])
            finally:
                done.set()

        # On a worker of its own from now on, beside have, the chunks and the prepare (for a small
        # identity, beside the prepare's round trip): the append's fdatasync is off the critical path.
        if not host.spawn(f"store-{out.companion}", store):
            store()  # stopping: no worker takes jobs any more
        self.claims.receiving(out.target, out.companion, out.epoch)
        try:
            inline = refs
            if sum(ref.size for ref in refs) > INLINE:
                # A large section new here since the last packing is at no target: it follows the
                # have at once rather than after its answer (a round trip less).
                early = [ref for ref in refs if ref.sha256 not in known and ref.size > INLINE]
                inline, bulk = self._ask_have(out, message, refs, packed, early)
                self._send_bulk(out, message, packed, bulk)
        except (_Refused, OutcomeUnknown) as exc:
            done.wait()
            why = f"{out.target} refused: {exc}" if isinstance(exc, _Refused) else f"outcome unknown ({exc})"
            if written:  # active again; the prepare was never sent, so the target holds nothing of this attempt
                host.records.put(handshake.resume(written[0]))
            host.post(self._abandon, out, f"{why}; the companion stays here")
            return
        reply, unknown = self._prepare(out, message, packed, inline)
        done.wait()  # prepared is durable before anything acts on the answer (handed comes after it)
        if stored or not written:
            # Nothing here names the attempt (this side stays active): the target may hold it
            # incoming, so it is told; asked, this side would answer "aborted" anyway.
            self.send_abort_later(prepared)
            host.post(self._abandon, out, f"cannot store the identity here: {stored[0] if stored else 'not written'}")
            return
        prepared = written[0]
        after = handshake.after_prepare(prepared, reply, private=private, document=packed.manifest) if reply is not None \
            else handshake.resume(prepared)
        if after.state != "handed":
            host.records.put(after)
            if reply is None or reply.status == "accepted":
                self.send_abort_later(prepared)  # T may hold it incoming: tell it, or it will ask us
            reason = (f"{out.target} refused: {reply.reason}" if reply is not None and reply.status != "accepted"
                      else f"{out.target} gave no custody key" if reply is not None
                      else f"outcome unknown ({unknown}); the companion resumes here")
            host.post(self._aborted, out, reason)
            return
        handed = host.records.put(after)
        crash_point("source:handed")
        assert handed.link is not None
        self.claims.vouch(handed.peer, handed.companion, handed.link.epoch, [*handed.chain, handed.link])
        host.post(host.step, handed)
        log_step(f"companion {handed.companion} handed to {handed.peer}", "handed", handed.companion, handed.peer,
                 handed.epoch, handed.attempt)
        host.post(self._handed, out)
        self.commit_until_acked(handed)

    def _prepare(self, out: Departure, message: MigratePrepare, packed: Packed,
                 inline: list[SectionRef]) -> tuple[Outcome | None, str]:
        """Send the prepare, with ``inline`` sections inside; prepare is idempotent, so a lost reply
        is asked again, and sections the target says it lacks are sent before asking again."""
        host = self.host
        reply: Outcome | None = None
        unknown = ""
        tries = lossy = 0
        while tries < 3 and lossy < 3:  # missing sections twice over is a target losing them: give up
            sections = [packed.data[ref.sha256] for ref in inline]
            out.transfer["sent"] += len(message.document) + sum(len(b) for b in sections)
            out.transfer["sections_sent"] += len(sections)
            try:
                reply = host.ask(out.target, "prepare", msgspec.structs.replace(message, sections=sections))
            except OutcomeUnknown as exc:
                reply, unknown = None, str(exc)
                lossy += 1
                if host.stopping.wait(host.retry[0]):
                    break
                continue
            tries += 1
            value = reply.value if isinstance(reply.value, dict) else {}
            missing = set(value.get("missing") or []) if reply.code == Code.MISSING_SECTIONS else set()
            wanted = [ref for ref in packed.refs if ref.sha256 in missing]
            if not wanted:
                break
            log.info("%s lacks %d section(s) of %s: sending them", out.target, len(wanted), out.companion)
            wanted = list({ref.sha256: ref for ref in wanted}.values())
            inline = wanted
            if sum(ref.size for ref in wanted) > INLINE:
                try:
                    inline, bulk = self._ask_have(out, message, wanted, packed)
                    self._send_bulk(out, message, packed, bulk)
                except (_Refused, OutcomeUnknown) as exc:
                    unknown = str(exc)
                    break
        return reply, unknown

    def _ask_have(self, out: Departure, message: MigratePrepare, refs: list[SectionRef], packed: Packed,
                  early: list[SectionRef] | None = None) -> tuple[list[SectionRef], list[SectionRef]]:
        """``have``: of the sections the target lacks, the small ones (at most ``INLINE`` bytes
        together), for the prepare to carry, and the others, to send apart (``_send_bulk``).
        ``early``: sections sent right behind the have, before its answer (the target takes chunks
        in order after it); those it took are not among the others."""
        answer = self.host.ask_later(out.target, "have", handshake.have(message))
        taken: set[str] = set()
        if early:
            try:
                self._send_bulk(out, message, packed, early)
                taken = {ref.sha256 for ref in early}
            except (_Refused, OutcomeUnknown) as exc:
                # The have waited (claims on the companion being checked), or was refused: they
                # go again once it is answered, or the refusal below says why.
                log.debug("sections sent behind the have of %s not taken yet: %s", out.attempt, exc)
        reply = answer()
        if reply.status != "accepted":
            raise _Refused(reply.reason)
        value = reply.value if isinstance(reply.value, dict) else {}
        held = set(value.get("have") or []) | taken
        missing = sorted((ref for ref in refs if ref.sha256 not in held), key=lambda r: r.size)
        inline: list[SectionRef] = []
        budget = INLINE
        while missing and missing[0].size <= budget:
            budget -= missing[0].size
            inline.append(missing.pop(0))
        return inline, missing

    def _send_bulk(self, out: Departure, message: MigratePrepare, packed: Packed, missing: list[SectionRef]) -> None:
        """The sections ``missing`` in ``migrate_sections`` chunks, two requests in flight."""
        batches: list[list[SectionChunk]] = [[]]
        size = 0
        for ref in missing:
            data = memoryview(packed.data[ref.sha256])
            for offset in range(0, max(1, ref.size), CHUNK):
                piece = data[offset:offset + CHUNK]
                if batches[-1] and size + len(piece) > CHUNK:
                    batches.append([])
                    size = 0
                batches[-1].append(SectionChunk(ref.sha256, offset, piece))
                size += len(piece)
        batches = [b for b in batches if b]
        if len(batches) > 1:
            # Two requests in flight: the target checks and writes one while the next is on its way.
            with ThreadPoolExecutor(IN_FLIGHT, thread_name_prefix=f"migration-chunks-{out.companion}") as pool:
                for _ in pool.map(functools.partial(self._send_chunks, out, message), batches):
                    pass
        elif batches:
            self._send_chunks(out, message, batches[0])
        out.transfer["sent"] += sum(len(c.data) for batch in batches for c in batch)
        out.transfer["sections_sent"] += len(missing)

    def _send_chunks(self, out: Departure, message: MigratePrepare, chunks: list[SectionChunk]) -> None:
        request = MigrateSections(message.companion, message.attempt, message.source, message.target, chunks)
        for attempt in range(3):  # chunks are idempotent: a lost answer is asked again
            try:
                reply = self.host.ask(out.target, "sections", request)
                break
            except OutcomeUnknown:
                if attempt == 2 or self.host.stopping.wait(self.host.retry[0]):
                    raise
        if reply.status != "accepted":
            raise _Refused(reply.reason)

    def commit_until_acked(self, handed: Record) -> None:
        """Handshake thread: send the commit until the target answers; a refusal is settled by
        asking the target what it made of the attempt (never by looping on the refusal)."""
        host = self.host
        assert handed.link is not None
        message = MigrateCommit(handed.companion, handed.epoch, handed.attempt, host.sim.embodiment, handed.peer,
                                custody.encode_link(handed.link))
        status = MigrateStatus(handed.companion, handed.attempt, handed.epoch, "target")
        delay = host.retry[0]
        while not host.stopping.is_set():
            try:
                reply = host.ask(handed.peer, "commit", message)
                if reply.status == "accepted":
                    self._finish_handed(msgspec.structs.replace(handed, state="released"))
                    return
                log.warning("%s refused the commit of %s (%s): asking it where it stands", handed.peer, handed.companion,
                            reply.reason)
                answer = host.ask(handed.peer, "status", status)
                next_step, record = handshake.after_refused_commit(handed, answer.value if answer.status == "accepted" else None)
                if next_step == "released" and record is not None:
                    self._finish_handed(record)
                    return
                if next_step == "resume" and record is not None:
                    host.records.put(record)
                    host.post(self._taken_back, record, handed, f"{handed.peer} dropped attempt {handed.attempt}")
                    return
                if next_step == "abort":
                    host.ask(handed.peer, "abort", MigrateAbort(handed.companion, handed.epoch, handed.attempt))
                    continue  # then ask again: dropped -> resume
                host.post(host.raise_event, "MigrationStuck", {"companion": handed.companion, "target": handed.peer,
                                                               "reason": reply.reason})
            except OutcomeUnknown as exc:
                log.info("commit of %s to %s: %s; retrying", handed.companion, handed.peer, exc)
            if host.stopping.wait(delay):
                return
            delay = min(host.retry[1], delay * 2)

    def _finish_handed(self, released: Record) -> None:
        self.host.records.put(released)
        crash_point("source:released")
        self.host.post(self._released, released)

    def send_abort_later(self, record: Record) -> None:
        """Tell ``record``'s target, from a thread of its own, that its attempt is aborted."""
        host = self.host

        def abort() -> None:
            try:
                host.ask(record.peer, "abort", MigrateAbort(record.companion, record.epoch, record.attempt), timeout=2.0)
            except OutcomeUnknown:
                pass  # the target will ask us (status) and hear "aborted"

        host.spawn(f"abort-{record.companion}", abort)

    # --- how the attempt ended (loop) ----------------------------------------------------------------

    def _aborted(self, out: Departure, reason: str) -> None:
        self._abandon(out, reason)
        self.host.resume(out.companion, f"migration to {out.target} failed")

    def _handed(self, out: Departure) -> None:
        # The commit point: never run the companion here again. The custody claim stays until the
        # target has taken it, so no moment passes in which nobody in the mesh claims the companion.
        # A fork found meanwhile goes with the branch: the target meets the other one itself.
        self.host.identity = None
        self.forks.clear()

    def _taken_back(self, record: Record, handed: Record, why: str) -> None:
        out = self.departure
        self.departure = None
        self.claims.forget(handed.peer, record.companion)
        reason = f"migration of {record.companion!r} to {why}; the companion resumes here"
        log_step(f"migration of {record.companion} to {handed.peer} aborted: {why}", "aborted", record.companion,
                 handed.peer, handed.epoch, handed.attempt, reason=why)
        self.host.raise_event("MigrationFailed", {"companion": record.companion, "attempt": out.attempt if out else "",
                                                  "reason": reason})
        if out is not None and not out.future.done():
            out.future.set_result(Outcome("rejected", reason))
        self.host.resume(record.companion, reason)

    def _released(self, record: Record) -> None:
        host = self.host
        out = self.departure
        self.departure = None
        if host.identity is None:
            host.withdraw_claim()
        data: dict[str, Any] = {"companion": record.companion, "target": record.peer, "attempt": record.attempt,
                                "epoch": record.epoch + 1}
        if out is not None and out.attempt == record.attempt and out.transfer:
            data["transfer"] = dict(out.transfer)
            self.last_transfer = dict(out.transfer)
        host.raise_event("MigrationSucceeded", data)
        log_step(f"companion {record.companion} left for {record.peer}", "released", record.companion, record.peer,
                 record.epoch + 1, record.attempt,
                 duration_s=round(time.monotonic() - out.started, 4) if out is not None and out.attempt == record.attempt else None)
        if out is not None and out.attempt == record.attempt and not out.future.done():
            out.future.set_result(Outcome("accepted", "", data))


def log_step(msg: str, step: str, companion: str, peer: str, epoch: int, attempt: str, **more: Any) -> None:
    """One info line for a step of this side of the handshake, with the fields every step has."""
    logs.event(log, msg, step=step, companion=companion, peer=peer, epoch=epoch, attempt=attempt, **more)


def log_prepared(record: Record) -> None:
    log_step(f"companion {record.companion} prepared for {record.peer}", "prepared", record.companion, record.peer,
             record.epoch, record.attempt)
