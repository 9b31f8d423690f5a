"""Migration: the ``migration`` component runs the handshake of ``handshake`` on real transports and disks.

The decisions (what each record accepts, what it answers, how a side resolves) and the argument
for why they keep exactly one host are in ``handshake``; custody (who may hand a companion on) is
in ``custody``; the durable records in ``ledger``, the section bytes in ``sections``. This
component moves messages and threads. ``MigrationManager`` keeps the companion's life here and
owns five parts, each an object with the state it owns, that it builds and delegates to:

* ``outgoing.Outgoing``, the source side: the companion leaves for a target (its ``Departure``);
* ``incoming.Incoming``, the target side: a companion arrives (the identities prepared, the offers
  waiting for claims), with ``uploads.Uploads``: the sections senders upload ahead of their
  prepare, and their bounds;
* ``claims.Claims``: who is alive and who claims custody of what, each claim checked before it
  counts; and this embodiment's answer when asked to back its own (``chain``);
* ``forks.Forks``: what the companion living here makes of the claims backed: it stands down for
  good, or freezes on a proven fork until an operator resolves it.

Parts rather than mixins of one class, so that each side's state is visibly its own and one side
reads without the other. A part reaches what they share through the manager (``host.Host``: the
records, the inhabitant and its minds, this embodiment's custody token, the handshake threads, the
way back to the loop) and another part only where the handshake links them (a target asks the
claims and reports forks; a source asks who is alive and whether the companion is frozen). The
claims tell the others what they found through two callbacks wired here. Every module of a part
imports ``host`` and the parts below it, never the manager.

The manager keeps the life cycle. At ``attach`` it opens the claims' watch, gives birth to the seed
companion on its first start, reports the companions whose records are damaged, and takes up each
record where it stood: a source ``prepared`` aborts and resumes, ``handed`` sends its commit again,
``incoming`` asks its source. It inhabits (restores the minds' sections, declares its custody token
``@custody/<holder>/<companion>/<epoch>``, wakes the minds), and at ``detach`` keeps what the
companion learnt. It dispatches each request to the part that answers it.

Before packing, the source raises ``MigrationStarting`` and gives every component one update to
``contribute`` its section (or ``wait`` and ``resolve`` later, within a deadline). The target
raises ``MigrationOccurred`` after activation; each component takes its own section back with
``section(name)``.

Threads (each part's docstring says which of its methods runs where):

* the loop thread runs request handlers, ``start``'s checks, collecting sections, inhabiting and
  every timer (the ``Component`` API);
* one thread per handshake in flight (``spawn``): the source sending its prepare and commit, the
  target asking about an undecided attempt; these threads touch only the records (locked) and hand
  everything else to the loop (``post``); ``detach`` sets ``stopping`` and joins them;
* the transport's worker keeps the set of live embodiments and the custody tokens seen (``claims``);
* one thread (``claims.ClaimChecker``) checks custody claims.

Set ``CMION_MESH_CRASH_AT`` to ``source:prepared``, ``source:handed``, ``source:released``,
``target:incoming`` or ``target:active`` (comma-separated) and the process kills itself with
SIGKILL right after writing that record; the ledger's own points (a torn append, a compaction cut
short) are named in ``crash``. The crash tests use them.

Log lines: the steps of each side are ``outgoing``'s and ``incoming``'s; here, at info, a companion
``born`` here and ``resumed`` here (fields ``companion``, ``epoch``, ``step``, ``reason``), and at
error one that is damaged. Custody conflicts are ``forks``' and ``claims``'.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from cmion_mesh import keys, logs
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import (
    Code,
    CustodyResume,
    CustodyStandDown,
    Migrate,
    MigrateAbort,
    MigrateChain,
    MigrateCommit,
    MigrateHave,
    MigratePrepare,
    MigrateSections,
    MigrateStatus,
    Outcome,
    SetPolicy,
)
from cmion_mesh.migration import custody, handshake, signing
from cmion_mesh.migration.bounds import Quiet, env_limit
from cmion_mesh.migration.claims import Claims
from cmion_mesh.migration.forks import Forks
from cmion_mesh.migration.handshake import POLICY_SECTION
from cmion_mesh.migration.identity import Identity, SectionMemo, max_section
from cmion_mesh.migration.incoming import INCOMING_TIMEOUT_ENV, Incoming, sent_by_source
from cmion_mesh.migration.ledger import HOSTING, Record, Records
from cmion_mesh.migration.outgoing import SECTION_DEADLINE, Outgoing, WaitToken
from cmion_mesh.migration.uploads import MAX_UPLOAD, MAX_UPLOAD_ENV, UPLOAD_IDLE, UPLOAD_IDLE_ENV, Uploads
from cmion_mesh.migration.workers import Workers
from cmion_mesh.mind import Mind
from cmion_mesh.requests import IncomingRequest, send_request, send_request_later
from cmion_mesh.storage import Store
from cmion_mesh.transport.base import Closeable

log = logging.getLogger(__name__)


class MigrationManager(Component):
    """The ``migration`` component: owns the records and the companion's life here, and the parts
    that run both sides of the handshake."""

    requests = {"migrate": Migrate, "prepare": MigratePrepare, "commit": MigrateCommit, "abort": MigrateAbort,
                "status": MigrateStatus, "policy": SetPolicy, "have": MigrateHave, "sections": MigrateSections,
                "chain": MigrateChain, "stand_down": CustodyStandDown, "resume": CustodyResume}
    # The handshake travels on per-sender keys: in secure mode only S's certificate may send as S.
    # ``stand_down`` and ``resume`` are not: only this embodiment's own identity and operators may send them.
    sender_requests = frozenset({"prepare", "commit", "abort", "status", "have", "sections", "chain"})
    # Its constructor opens the state folder (creates it, sweeps what a crash left): never built
    # from a configuration, so that ``validate`` can build every component it names.
    built_by_embodiment = True

    def __init__(self, state_dir: str | os.PathLike[str], *, companion: str | None = None, section_deadline: float = SECTION_DEADLINE,
                 request_timeout: float = 10.0, retry: tuple[float, float] = (0.1, 2.0),
                 admit: dict[str, bytes | None] | None = None, max_upload: int | None = None,
                 upload_idle: float | None = None, incoming_timeout: float | None = None) -> None:
        """``admit``: which companions may enter (name -> trusted identity key, or None to pin it at the
        first commit); None admits any companion (its identity key is pinned at its first commit here).
        ``max_upload``, ``upload_idle``, ``incoming_timeout``: as ``uploads.MAX_UPLOAD``,
        ``uploads.UPLOAD_IDLE`` and ``handshake.INCOMING_BOUND``, else from the environment."""
        super().__init__("migration")
        self.admit = admit
        max_section()  # a bad CMION_MESH_MAX_SECTION stops the start, naming it
        max_upload = max_upload if max_upload is not None else \
            int(env_limit(MAX_UPLOAD_ENV, MAX_UPLOAD, low=1, high=2**50, unit="bytes"))
        upload_idle = upload_idle if upload_idle is not None else env_limit(UPLOAD_IDLE_ENV, UPLOAD_IDLE, low=0.1, high=86400)
        incoming_timeout = incoming_timeout if incoming_timeout is not None else \
            env_limit(INCOMING_TIMEOUT_ENV, handshake.INCOMING_BOUND, low=0.1, high=30 * 86400)
        self.records = Records(state_dir)
        #: Companions whose stored identity is unusable: reported (description, log, event), never run.
        self.damaged = self.records.damaged()
        self.seed = keys.check_name(companion, "companion") if companion else None
        self.request_timeout = request_timeout
        self.retry = retry
        self.identity: Identity | None = None  # the companion living here, when inhabited (loop)
        self.memo = SectionMemo()  # the companion's section bytes last packed or received, with their hashes
        self.stopping = threading.Event()
        self.quiet = Quiet()
        self._token: Closeable | None = None  # this embodiment's custody claim (loop)
        self.workers = Workers("migration")
        # The parts; the claims tell the verdicts and the waiting offers what they found (on the loop).
        self.claims = Claims(self, on_backed=self._claim_backed, on_checked=self._claim_checked)
        self.forks = Forks(self, self.claims)
        self.uploads = Uploads(self, max_upload=max_upload, idle=upload_idle)
        self.incoming = Incoming(self, self.claims, self.forks, self.uploads, timeout=incoming_timeout)
        self.outgoing = Outgoing(self, self.claims, self.forks, section_deadline=section_deadline)

    def _claim_backed(self) -> None:
        self.forks.check_conflict()

    def _claim_checked(self, companion: str) -> None:
        self.incoming.claims_settled(companion)

    # --- state seen from outside (any thread) --------------------------------------------------

    @property
    def inhabitant(self) -> str | None:
        """The companion living here: active, or frozen in a handshake it may still abort. Read
        from the durable record, which the handshake thread moves past its commit point at once."""
        identity = self.identity
        if identity is None or self.forks.halted:
            return None
        record = self.records.get(identity.companion)
        return identity.companion if record is not None and record.state in ("active", "prepared") else None

    def public_key(self) -> str | None:
        """The inhabitant's identity key (base64), for admission lists elsewhere."""
        identity = self.identity
        record = self.records.get(identity.companion) if identity is not None else None
        return record.public_key or None if record is not None else None

    def section(self, component: str) -> Any:
        """The section ``component`` contributed to the identity living here (None if absent)."""
        return None if self.identity is None else self.identity.sections.get(component)

    @property
    def migrating_to(self) -> str | None:
        """The target of the migration under way from here, if any."""
        return self.outgoing.target

    @property
    def last_transfer(self) -> dict[str, int] | None:
        """The last migration from here: bytes of the document sent and in all (``MigrationSucceeded``'s ``transfer``)."""
        return self.outgoing.last_transfer

    def policy(self) -> list[str] | None:
        """The embodiments the companion living here accepts (its ``policy`` section), None for any
        or when nobody lives here (loop thread, as ``describe``)."""
        policy = self.identity.sections.get(POLICY_SECTION) if self.identity is not None else None
        accepts = policy.get("accepts") if isinstance(policy, dict) else None
        return [str(a) for a in accepts] if isinstance(accepts, list) else None

    def custody_report(self) -> dict[str, Any]:
        """What ``describe`` says of custody here: for the companion held here, its state, epoch,
        whether a fork freezes it and the evidence (plain data)."""
        return self.forks.report()

    # --- the source side, for the components (``outgoing``) ----------------------------------------

    def start(self, target: str, companion: str | None = None) -> Future[Outcome]:
        """Start migrating the companion living here to ``target``; thread-safe. The future ends
        with the outcome (accepted when the target committed; rejected with the reason)."""
        return self.outgoing.start(Migrate(companion or self.inhabitant or "", target))

    def contribute(self, component: str, data: Any) -> None:
        """Add ``component``'s section to the migration being packed. Thread-safe (on the loop, at once)."""
        self.outgoing.contribute(component, data)

    def wait(self, component: str) -> WaitToken:
        """Ask the packing to wait for ``component`` (loop thread); ``resolve`` ends the wait."""
        return self.outgoing.wait(component)

    def resolve(self, token: WaitToken, data: Any) -> None:
        """End a wait with the component's section. Thread-safe."""
        self.outgoing.resolve(token, data)

    def refuse(self, token: WaitToken, reason: str) -> None:
        """End a wait by abandoning the migration: the component cannot give its section (its
        reason is the migration's). Thread-safe. Sooner and clearer than the section deadline."""
        self.outgoing.refuse(token, reason)

    # --- life cycle (loop) ----------------------------------------------------------------------

    def attach(self, sim: Simulation) -> None:
        self.claims.open()
        if self.seed is not None and self.records.get(self.seed) is None and self.records.hosting() is None:
            self._give_birth(self.seed)
        for companion, error in self.damaged.items():
            _log_damaged(companion, error)
            self.raise_event("CompanionDamaged", {"companion": companion, "error": error})
        for record in self.records.all():
            if record.companion in self.damaged:
                continue
            if record.state in HOSTING and not record.chain:
                record = self._adopt_legacy(record)
            problem = self.forks.unbacked(record)
            if problem:
                self._report_damaged(record.companion, problem)
                continue
            if record.state == "prepared":
                # Never handed: the target cannot have activated. Abort and resume here.
                self.records.put(handshake.resume(record))
                self.outgoing.send_abort_later(record)
                self.resume(record.companion, "recovered: a migration had not reached its commit point")
            elif record.state == "active":
                self.resume(record.companion, "started")
            elif record.state == "handed":
                self.claim(record.companion, record.epoch)
                self.spawn(f"commit-{record.companion}", self.outgoing.commit_until_acked, record)
            elif record.state == "incoming":
                self.claim(record.companion, record.epoch)
                self.spawn(f"resolve-{record.companion}", self.incoming.resolve_incoming, record)
                self.incoming.expire_later(record)  # from the prepare's time: overdue already, at the next update
        if self.identity is None:
            self.sleep_minds()

    def _give_birth(self, companion: str) -> None:
        """First start of the companion's home: it is born here, at epoch 1, with its identity key."""
        packed = Identity(companion, 1, {}).pack_sections()
        private = signing.new_key()
        chain = [custody.birth(companion, self.sim.embodiment, private, packed.manifest)]
        self.records.put(Record(companion, "active", 1, chain=chain, public_key=signing.encode_public(chain[0].public_key)),
                         document=packed.manifest, sections=packed.data, key=private)
        logs.event(log, f"companion {companion} born here", step="born", companion=companion, epoch=1)

    def _adopt_legacy(self, record: Record) -> Record:
        """A record written before custody chains: an active companion starts its chain here (its old
        key, if kept, stays its identity key); one caught mid-handshake cannot be continued."""
        legacy = self.records.dir / f"{record.companion}.identity.xml"
        if record.state != "active":
            raise ConfigError(f"migration record of {record.companion!r} is mid-handshake ({record.state}) in an older "
                              "format: finish it with the version that started it", path=str(legacy.with_suffix(".record.json")))
        try:
            document = legacy.read_bytes()
        except FileNotFoundError:
            document = Identity(record.companion, record.epoch, {}).pack()
        private = self.records.key(record.companion) or signing.new_key()
        chain = [custody.birth(record.companion, self.sim.embodiment, private, document, record.epoch)]
        record = self.records.put(Record(record.companion, "active", record.epoch, chain=chain,
                                         public_key=signing.encode_public(chain[0].public_key)), document=document, key=private)
        legacy.unlink(missing_ok=True)
        return record

    def detach(self) -> None:
        self.stopping.set()
        self.claims.close()
        self.incoming.close()
        self.uploads.close()
        self.workers.close(10.0)
        self.withdraw_claim()
        identity = self.identity
        record = self.records.get(identity.companion) if identity is not None else None
        if identity is not None and record is not None and record.state == "active":
            # A clean stop keeps what the companion learnt since it arrived.
            self.refresh_sections(identity)
            self._keep(record, identity)
        self.records.close()

    def _keep(self, record: Record, identity: Identity) -> None:
        """Store ``identity`` as the active companion's document (and its sections) here."""
        packed = identity.pack_sections(self.memo)
        self.records.put(record, document=packed.manifest, sections=packed.data)

    def _report_damaged(self, companion: str, error: str) -> None:
        self.damaged[companion] = error
        _log_damaged(companion, error)
        self.raise_event("CompanionDamaged", {"companion": companion, "error": error})

    # --- what the parts share (``host.Host``) ------------------------------------------------------

    def spawn(self, name: str, fn: Callable[..., None], *args: Any) -> bool:
        return self.workers.spawn(name, fn, *args)

    def post(self, fn: Callable[..., None], *args: Any) -> None:
        try:
            self.sim.call(functools.partial(fn, *args))
        except MeshError:
            pass  # closing

    def ask(self, peer: str, op: str, message: Any, timeout: float | None = None) -> Outcome:
        key = keys.request_key(self.sim.mesh, peer, "migration", op, self.sim.embodiment)
        return send_request(self.sim.transport, key, message, timeout=self.request_timeout if timeout is None else timeout)

    def ask_later(self, peer: str, op: str, message: Any) -> Callable[[], Outcome]:
        key = keys.request_key(self.sim.mesh, peer, "migration", op, self.sim.embodiment)
        return send_request_later(self.sim.transport, key, message, timeout=self.request_timeout)

    def step(self, record: Record) -> None:
        # Loop thread. Each durable record of a handshake is one step a watcher (``cmion-mesh view``)
        # can draw: the Migration* events alone say when it starts and ends, not how far it got.
        self.raise_event("MigrationStep", {"companion": record.companion, "attempt": record.attempt, "step": record.state,
                                           "peer": record.peer, "epoch": record.epoch})

    def claim(self, companion: str, epoch: int) -> None:
        self.withdraw_claim()
        self._token = self.sim.transport.declare_token(keys.custody_key(self.sim.mesh, self.sim.embodiment, companion, epoch))

    def withdraw_claim(self) -> None:
        if self._token is not None:
            self._token.close()
            self._token = None

    # --- minds and sections (loop) --------------------------------------------------------------

    def minds(self) -> list[Mind]:
        return [c for c in self.sim.components if isinstance(c, Mind)]

    def sleep_minds(self) -> None:
        for mind in self.minds():
            mind.sleep()

    def wake_minds(self) -> None:
        world = self.sim.components_by_name().get(keys.WORLD_MODEL)
        tree = world.tree() if isinstance(world, Store) else {}
        for mind in self.minds():
            mind.wake()
            mind.on_arrived(tree)

    def refresh_sections(self, identity: Identity) -> None:
        for mind in self.minds():
            identity.sections[mind.name] = mind.state()

    def resume(self, companion: str, why: str) -> None:
        try:
            identity = self.records.identity(companion, self.memo) or Identity(companion, 1, {})
        except ConfigError as exc:  # its stored identity was altered at rest meanwhile: report, never run
            self.identity = None
            self._report_damaged(companion, str(exc))
            self.sleep_minds()
            return
        record = self.records.get(companion)
        if record is not None:
            identity.epoch = record.epoch
        logs.event(log, f"companion {companion} resumed here: {why}", step="resumed", companion=companion,
                   epoch=identity.epoch, reason=why)
        self.inhabit(identity, "CompanionResumed", why)

    def inhabit(self, identity: Identity, event: str, why: str) -> None:
        self.identity = identity
        self.claim(identity.companion, identity.epoch)
        for mind in self.minds():
            state = identity.sections.get(mind.name)
            if isinstance(state, dict) and state:
                mind.restore(state)
        self.raise_event(event, {"companion": identity.companion, "epoch": identity.epoch, "why": why,
                                 "sections": sorted(identity.sections)})
        if not self.forks.halted:
            self.wake_minds()
        self.forks.check_conflict()

    # --- requests (loop) ------------------------------------------------------------------------

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        for request in batch:
            try:
                self._handle(request)
            except MeshError as exc:
                request.reject(str(exc))

    def _handle(self, request: IncomingRequest) -> None:
        match request.payload:
            case Migrate() as payload:
                self.outgoing.on_migrate(request, payload)
            case MigratePrepare() as payload:
                if sent_by_source(request, payload.source, "a prepare"):
                    self.incoming.on_prepare(request, payload)
            case MigrateCommit() as payload:
                if sent_by_source(request, payload.source, "a commit"):
                    self.incoming.on_commit(request, payload)
            case MigrateAbort() as payload:
                self.incoming.on_abort(request, payload)
            case MigrateStatus() as payload:  # asked of either side
                request.answer(handshake.on_status(payload, self.records.get(payload.companion), requester=request.requester).outcome)
            case MigrateHave() as payload:
                if sent_by_source(request, payload.source, "a have"):
                    self.incoming.on_have(request, payload)
            case MigrateSections() as payload:
                if sent_by_source(request, payload.source, "sections"):
                    self.uploads.on_sections(request, payload)
            case MigrateChain() as payload:
                self.claims.on_chain(request, payload)
            case CustodyStandDown() as payload:
                self.forks.on_stand_down(request, payload)
            case CustodyResume() as payload:
                self.forks.on_resume(request, payload)
            case SetPolicy() as payload:
                self._on_policy(request, payload.accepts)
            case other:
                request.reject(f"migration has no request of type {type(other).__name__}")

    def _on_policy(self, request: IncomingRequest, accepts: list[str] | None) -> None:
        """Set the companion's own policy (``accepts``: embodiment names, or None for any); it is
        part of its identity, so it travels with it and every later host enforces it too."""
        identity = self.identity
        record = self.records.get(identity.companion) if identity is not None else None
        if identity is None or record is None or record.state != "active":
            request.reject(f"embodiment {self.sim.embodiment!r} hosts no companion")
            return
        target = self.outgoing.target
        if target is not None:
            request.reject(f"{identity.companion!r} is migrating to {target!r}", Code.BUSY)
            return
        for name in accepts or []:
            keys.check_name(name, "accepted embodiment")
        if accepts is None:
            identity.sections.pop(POLICY_SECTION, None)
        else:
            identity.sections[POLICY_SECTION] = {"accepts": sorted(set(accepts))}
        self.refresh_sections(identity)
        self._keep(record, identity)
        request.accept(identity.sections.get(POLICY_SECTION))
        # Who offers the companion's moves (an MCP server, a mind's tools) hears that they changed.
        self.raise_event("PolicyChanged", {"companion": identity.companion, "accepts": accepts})


def _log_damaged(companion: str, error: str) -> None:
    logs.event(log, f"companion {companion} is damaged and will not run here: {error}", level=logging.ERROR,
               companion=companion, reason=error)


class MigrationCompetency(Competency):
    """Migration as a competency (type ``Migration``): a rule maps ``Migrate <target>`` to it.

    Run parameter ``target``, or ``DeviceName`` as CMION's rules name it (``Migration *`` ->
    ``Migration`` with ``DeviceName=$parameter1``). Succeeds once the target has committed; cannot
    be cancelled once the handshake has started (the companion must end up in exactly one place).

    The constructor takes CMION's one parameter, the device table's file name (``devices``): the
    daemon reads that table before its session opens (``body.library.table_for_library``), so here it
    is only kept, as ``device_table``.
    """

    type = "Migration"

    def __init__(self, device_table: str = "", *, name: str | None = None) -> None:
        super().__init__(*((device_table,) if device_table else ()), name=name)
        self.device_table = device_table

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        manager = self.sim.component("migration")
        assert isinstance(manager, MigrationManager)
        target = str(parameters.get("target") or parameters.get("DeviceName") or "")
        future = manager.start(target)
        while True:  # ends with the handshake (every attempt resolves its future) or with the embodiment
            try:
                outcome = future.result(timeout=0.1)
                break
            except TimeoutError:
                if self._stopping.is_set() or self.sim.closed:
                    # The records settle the attempt at the next start; this run's outcome is unknown.
                    return ctx.fail(f"embodiment {self.sim.embodiment!r} stopped before the migration to {target!r} ended")
        if outcome.status != "accepted":
            return ctx.fail(outcome.reason)
        return True
