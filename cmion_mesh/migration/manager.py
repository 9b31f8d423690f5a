"""Migration: the ``migration`` component runs the handshake of ``handshake`` on real transports and disks.

The decisions (what each record accepts, what it answers, how a side resolves) and the argument
for why they keep exactly one host are in ``handshake``; custody (who may hand a companion on) is
in ``custody``; the durable records in ``records``. This module moves messages and threads:

* the loop thread runs request handlers (a target's section checks and writes among them), ``_start``,
  collecting sections and inhabiting (the ``Component`` API);
* one thread per handshake in flight sends the prepare and the commit (``_send``,
  ``_commit_until_acked``) or asks a peer about an undecided attempt (``_resolve_incoming``);
  these threads touch only the records (locked) and hand everything else to the loop (``_post``);
  a loop timer drops an incoming attempt still undecided at its bound (``_expire_incoming``), which
  counts from the prepare's record, across restarts;
  while sending sections, ``_send`` has one short-lived thread write this side's copy of them, then
  the ``prepared`` record that names them, and two send chunks, all joined before it goes on;
* the transport's worker keeps the set of live embodiments and the custody tokens seen
  (``_on_token``, ``_on_custody``), under ``_watch_lock``; it only records a token and queues its
  check;
* one thread (``ClaimChecker``) checks custody claims: it asks each claimant for its chain of
  custody and a signature by its head's key over a fresh nonce (``chain``), verifies them, keeps
  the claims so backed (``claims``) and posts the verdict to the loop (``_check_conflict``).

Before packing, the source raises ``MigrationStarting`` and gives every component one update to
``contribute`` its section (or ``wait`` and ``resolve`` later, within a deadline). Sections that
no component here understands are carried on unchanged. The target raises ``MigrationOccurred``
after activation; each component takes its own section back with ``section(name)``.

A holder says so in the mesh with a liveliness token ``@custody/<holder>/<companion>/<epoch>``.
A token is a hint to go and look, never evidence: a claim counts only once its claimant backs it
(``chain``: its chain of custody, verified from the identity key trusted here, ending with it at
the epoch claimed, and the asker's nonce signed by that link's key). A claim that cannot be backed
is ignored, and logged naming the claimant. Backed claims decide two things (``handshake``):

* a target refuses an offer that a backed claim shows stale (its chain extends the offer) or forked
  (two links for one epoch signed by one key: the proof names who equivocated); while claims on
  the companion are still being checked, the offer waits for them (``CLAIM_WAIT`` at most);
* a holder stands down for good when a backed claim extends its chain (its own key signed the link
  past its head: a rolled-back state folder), and on a proven fork it freezes: no branch wins by
  itself, epochs and names count for nothing. The evidence is kept in the state folder (a restart
  does not unfreeze it), the fork is reported (``CustodyFork`` event, the log, the description)
  with the command that resolves it: ``cmion-mesh custody resolve COMPANION --keep EMBODIMENT``
  makes every other branch holder stand down (``stand_down``: the kept chain recorded, on disk
  before the answer), then tells the keeper to run it again (``resume``).

A record whose state, epoch or holder its chain of custody does not back (``handshake.at_rest``)
is reported damaged at start and never run.

**Sections travel apart** (SchemaVersion 2, ``identity``): the source packs the identity into a
manifest and section bytes off the loop; for a small identity it sends them all inside the
prepare; for a larger one it first sends ``have`` and the target answers which sections it holds
from an earlier visit (checked against their hash), then only the others cross, as raw bytes in
``migrate_sections`` chunks, while the source writes its own copy to its disk. The target answers
each request once what it received is on its disk. ``MigrationSucceeded`` says how many bytes were
sent (``transfer``).

A target holds one upload (``have`` and its sections) per sender, at most ``MAX_UPLOADS``. Every
byte received counts, before it is written, against what one sender may upload ahead of its
prepare (``MAX_UPLOAD``) and against the section folder's bound (``records.MAX_CACHE``, making room
by evicting the cache); a chunk over either is refused naming its sender. An upload that never
becomes a prepare is deleted when its sender's next ``have`` replaces it, when its prepare is
refused or aborted, and once idle for ``UPLOAD_IDLE`` seconds.

Set ``CMION_MESH_CRASH_AT`` to ``source:prepared``, ``source:handed``, ``source:released``,
``target:incoming`` or ``target:active`` (comma-separated) and the process kills itself with
SIGKILL right after writing that record: the crash tests use it.
"""

from __future__ import annotations

import base64
import binascii
import functools
import heapq
import logging
import os
import secrets
import signal
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError, MeshError, OutcomeUnknown
from cmion_mesh.ion import Component, IncomingRequest, Simulation, Timer
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
    SectionChunk,
    SetPolicy,
)
from cmion_mesh.migration import custody, handshake, signing
from cmion_mesh.migration.handshake import POLICY_SECTION, Claim, refuses
from cmion_mesh.migration.identity import Bytes, Identity, Packed, SectionMemo, SectionRef, max_section, sha256_hex
from cmion_mesh.migration.ledger import HOSTING, MAX_CACHE_ENV, IncomingSection, Record, Records, env_limit
from cmion_mesh.migration.signing import SignatureRefused
from cmion_mesh.mind import Mind
from cmion_mesh.requests import send_request
from cmion_mesh.storage import Store
from cmion_mesh.transport.base import Closeable

log = logging.getLogger(__name__)

#: Prepares a sender may have refused or dropped in a burst, and how many more per second: a
#: stranger's flood of prepares costs it ``rejected: busy``, not this embodiment's disk or time.
PREPARE_BURST = 20
PREPARE_RATE = 5.0
#: Seconds the components of the source have to give their sections once a migration starts.
SECTION_DEADLINE = 5.0
#: Missing sections that together are at most this many bytes travel inside the prepare: a small
#: identity takes no round trip more than it used to (and no ``have``).
INLINE = 256 * 1024
#: Bytes of sections per ``migrate_sections`` request: a large section goes in chunks of this size.
CHUNK = 4 * 1024 * 1024
#: ``migrate_sections`` requests in flight at once.
IN_FLIGHT = 2
#: Target: most bytes of sections one sender may have uploaded here ahead of its prepare (``have``
#: then ``migrate_sections``); ``CMION_MESH_MAX_UPLOAD`` changes it. Half the section cache
#: (``records.MAX_CACHE``, which bounds all uploads together): no one sender takes all of it.
MAX_UPLOAD = 512 * 1024 * 1024
MAX_UPLOAD_ENV = "CMION_MESH_MAX_UPLOAD"
#: Target: seconds an upload may wait for its next chunk or its prepare before it expires (its
#: bytes deleted); ``CMION_MESH_UPLOAD_IDLE`` changes it.
UPLOAD_IDLE = 60.0
UPLOAD_IDLE_ENV = "CMION_MESH_UPLOAD_IDLE"
#: Target: uploads held at once (one per sender); a ``have`` beyond them is refused busy.
MAX_UPLOADS = 8
#: Target: ``CMION_MESH_INCOMING_TIMEOUT`` changes ``handshake.INCOMING_BOUND``, the seconds after
#: its prepare at which an attempt its source has neither committed nor aborted is dropped.
INCOMING_TIMEOUT_ENV = "CMION_MESH_INCOMING_TIMEOUT"
#: Pins of the section store held by the uploads staged here (one owner per sender).
_STAGING = "staging"
#: Seconds a claimant has to back its custody token (``chain``).
CHAIN_TIMEOUT = 2.0
#: Longest wait of a prepare or a ``have`` for the claims on its companion to be checked.
CLAIM_WAIT = 3.0
#: Claims waiting to be checked (per claimant, in all) beyond which new ones are dropped, logged.
CLAIMS_PER_CLAIMANT = 8
MAX_CLAIMS = 256
#: Requests waiting for claims to be checked, beyond which a new one is decided at once.
MAX_WAITING = 32
#: Tries to back a claim (the first pause between them, doubling): a refusal or a claim that does
#: not verify is asked once more (the token may be on its way out), a claimant that does not
#: answer a few times.
CLAIM_TRIES = 4
CLAIM_RETRY = 0.25
#: Seconds between two log lines about claims of the same claimant ignored.
QUIET = 60.0
#: The command that resolves a fork, in logs and descriptions.
RESOLVE = "cmion-mesh custody resolve {companion} --keep EMBODIMENT"


class _Refused(MeshError):
    """The target refused a step of the handshake before the prepare (the reason is its answer)."""


def _sent_by_source(request: IncomingRequest, source: str, what: str) -> bool:
    """A handshake message counts only from the embodiment it names as its source."""
    if request.requester == source:
        return True
    request.reject(f"{request.requester!r} cannot send {what} on behalf of {source!r}")
    return False


def crash_point(point: str) -> None:
    """Die here, hard, if the crash tests asked for it (``CMION_MESH_CRASH_AT``)."""
    wanted = os.environ.get("CMION_MESH_CRASH_AT", "")
    if wanted and point in {p.strip() for p in wanted.split(",")}:
        log.warning("crash point %s: killing this process", point)
        os.kill(os.getpid(), signal.SIGKILL)


@dataclass(eq=False)
class _Outgoing:
    companion: str
    target: str
    epoch: int
    attempt: str
    future: Future[Outcome]
    contributions: dict[str, Any] = field(default_factory=dict)
    waits: set[str] = field(default_factory=set)
    packed: bool = False
    transfer: dict[str, int] = field(default_factory=dict)  # bytes sent / of the document (handshake thread)


@dataclass(eq=False)
class _Staging:
    """Target: the sections gathered for one attempt between its ``have`` and its prepare (loop):
    an upload, one per sender, that ends with the prepare or expires (``_unstage``)."""

    attempt: str
    source: str
    refs: dict[str, SectionRef]  # sha256 -> section, as the manifest offered names them
    data: dict[str, Bytes] = field(default_factory=dict)  # checked bytes: held here already, or received
    partial: dict[str, IncomingSection] = field(default_factory=dict)
    stored: set[str] = field(default_factory=set)  # sections this upload wrote: deleted if no prepare names them
    received: int = 0  # bytes of this upload written to disk (partial sections included)
    last: float = field(default_factory=time.monotonic)  # when it last took a chunk (or began)

    def abandon(self) -> None:
        for incoming in self.partial.values():
            incoming.abandon()
        self.partial.clear()


@dataclass(frozen=True)
class WaitToken:
    attempt: str
    component: str


ClaimKey = tuple[str, str, int]  # claimant, companion, epoch


class ClaimChecker:
    """One thread that checks custody claims, off the loop and off zenoh's callbacks.

    ``submit`` queues a claim once while it is pending (bounded per claimant and in all);
    ``check(key, tries)``, given, does the work and returns None when done or the seconds after
    which to try again; ``done(key)`` is called once the claim is no longer pending. A context
    manager; ``close`` is idempotent and joins the thread."""

    def __init__(self, check: Callable[[ClaimKey, int], float | None], done: Callable[[ClaimKey], None]) -> None:
        self._check = check
        self._done = done
        self._cond = threading.Condition()
        self._queue: list[tuple[float, int, ClaimKey, int]] = []  # (due, order, key, tries): a heap
        self._pending: set[ClaimKey] = set()
        self._order = 0
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="migration-claims", daemon=True)

    def start(self) -> ClaimChecker:
        self._thread.start()
        return self

    def __enter__(self) -> ClaimChecker:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.close()

    def submit(self, key: ClaimKey) -> bool:
        """Queue ``key`` (once while it is pending); False beyond the bounds: then it is not checked."""
        with self._cond:
            if self._closed or key in self._pending:
                return True
            if len(self._pending) >= MAX_CLAIMS or sum(k[0] == key[0] for k in self._pending) >= CLAIMS_PER_CLAIMANT:
                return False
            self._pending.add(key)
            self._push(0.0, key, 0)
            return True

    def _push(self, due: float, key: ClaimKey, tries: int) -> None:
        self._order += 1
        heapq.heappush(self._queue, (due, self._order, key, tries))
        self._cond.notify()

    def pending(self, companion: str) -> bool:
        with self._cond:
            return any(k[1] == companion for k in self._pending)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(CHAIN_TIMEOUT + 5.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._closed and (not self._queue or self._queue[0][0] > time.monotonic()):
                    self._cond.wait(self._queue[0][0] - time.monotonic() if self._queue else None)
                if self._closed:
                    return
                _, _, key, tries = heapq.heappop(self._queue)
            try:
                again = self._check(key, tries)
            except Exception:  # a bug in one check must not end the checking of all the others
                log.exception("checking the custody claim of %s on %s at epoch %d failed", *key)
                again = None
            with self._cond:
                if again is not None and not self._closed:
                    self._push(time.monotonic() + again, key, tries + 1)
                    continue
                self._pending.discard(key)
            self._done(key)


@dataclass(eq=False)
class _Waiting:
    """A prepare or ``have`` waiting for the claims on its companion to be checked (loop)."""

    request: IncomingRequest
    message: MigratePrepare | MigrateHave
    deadline: float


class _Quiet:
    """Says whether to log about ``key`` now: at most once per ``QUIET`` seconds each (any thread)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}
        self._muted: dict[str, int] = {}

    def allow(self, key: str) -> int | None:
        """None to keep quiet, else how many lines about ``key`` were left out since the last."""
        now = time.monotonic()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last < QUIET:
                self._muted[key] = self._muted.get(key, 0) + 1
                return None
            if len(self._last) > 1024:
                self._last.clear()  # bounded: strangers are forgotten
            self._last[key] = now
            return self._muted.pop(key, 0)


class TokenBucket:
    """A token bucket: ``take()`` is False once a sender has used its burst faster than the rate."""

    def __init__(self, burst: int = PREPARE_BURST, rate: float = PREPARE_RATE) -> None:
        self.burst = burst
        self.rate = rate
        self.tokens = float(burst)
        self.at = time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.at) * self.rate)
        self.at = now
        if self.tokens < 1:
            return False
        self.tokens -= 1
        return True


class MigrationManager(Component):
    """The ``migration`` component: owns the records, runs both sides of the handshake."""

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
        ``max_upload``, ``upload_idle``, ``incoming_timeout``: as ``MAX_UPLOAD``, ``UPLOAD_IDLE`` and
        ``handshake.INCOMING_BOUND``, else from the environment."""
        super().__init__("migration")
        self.admit = admit
        max_section()  # a bad CMION_MESH_MAX_SECTION stops the start, naming it
        self.max_upload = max_upload if max_upload is not None else \
            int(env_limit(MAX_UPLOAD_ENV, MAX_UPLOAD, low=1, high=2**50, unit="bytes"))
        self.upload_idle = upload_idle if upload_idle is not None else env_limit(UPLOAD_IDLE_ENV, UPLOAD_IDLE, low=0.1, high=86400)
        self.incoming_timeout = incoming_timeout if incoming_timeout is not None else \
            env_limit(INCOMING_TIMEOUT_ENV, handshake.INCOMING_BOUND, low=0.1, high=30 * 86400)
        self.records = Records(state_dir)
        #: Companions whose stored identity is unusable: reported (description, log, event), never run.
        self.damaged = self.records.damaged()
        self.seed = keys.check_name(companion, "companion") if companion else None
        self.section_deadline = section_deadline
        self.request_timeout = request_timeout
        self.retry = retry
        self.identity: Identity | None = None  # the companion living here, when inhabited (loop)
        #: The evidence of a fork of the inhabitant's chain of custody that freezes it here, until an
        #: operator resolves it (loop; kept in the state folder too).
        self.frozen: custody.Freeze | None = None
        #: A backed claim extends the chain of the inhabitant, caught in its own handshake: it runs no
        #: more, and stands down for good once the handshake ends here (loop).
        self.superseded_by: Claim | None = None
        self._outgoing: _Outgoing | None = None  # loop
        self._prepared: dict[str, Identity] = {}  # attempt -> identity parsed at prepare, for its commit (loop)
        self._buckets: dict[str, TokenBucket] = {}  # sender -> prepare budget (loop)
        self._stagings: dict[str, _Staging] = {}  # target: sender -> sections gathered for its next prepare (loop)
        self._upload_timer: Timer | None = None  # expires idle uploads (loop)
        self._memo = SectionMemo()  # the companion's section bytes last packed or received, with their hashes
        #: The last migration from here: bytes of the document sent and in all (``MigrationSucceeded``'s ``transfer``).
        self.last_transfer: dict[str, int] | None = None
        self._token: Closeable | None = None  # this embodiment's custody claim (loop)
        self._stop = threading.Event()
        self._threads_lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._watch_lock = threading.Lock()
        self._alive: set[str] = set()  # embodiments whose liveliness token is present (transport worker)
        self._tokens: dict[str, set[tuple[str, int]]] = {}  # companion -> {(holder, epoch)}: hints (transport worker)
        self._backed: dict[str, dict[tuple[str, int], Claim]] = {}  # companion -> claims backed (claim checker)
        self._stood_down: set[ClaimKey] = set()  # claims of branch holders an operator retired: ignored
        self._checker: ClaimChecker | None = None
        self._waiting: list[_Waiting] = []  # offers waiting for claims to be checked (loop)
        self._quiet = _Quiet()
        self._chain_buckets: dict[str, TokenBucket] = {}  # asker -> chain requests budget (loop)
        self._watches: list[Closeable] = []

    # --- state seen from outside (any thread) --------------------------------------------------

    @property
    def inhabitant(self) -> str | None:
        """The companion living here: active, or frozen in a handshake it may still abort. Read
        from the durable record, which the handshake thread moves past its commit point at once."""
        identity = self.identity
        if identity is None or self.frozen is not None or self.superseded_by is not None:
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
        out = self._outgoing
        return out.target if out is not None else None

    def claims(self, companion: str) -> list[Claim]:
        """The other embodiments' claims on ``companion`` that their claimants backed (``chain``): a
        bare custody token is never one."""
        with self._watch_lock:
            backed = self._backed.get(companion, {})
            return [claim for (holder, epoch), claim in sorted(backed.items())
                    if (holder, companion, epoch) not in self._stood_down]

    def custody_report(self) -> dict[str, Any]:
        """What ``describe`` says of custody here: for the companion held here, its state, epoch,
        whether a fork freezes it and the evidence (plain data)."""
        report: dict[str, Any] = {}
        for record in self.records.all():
            if record.state not in HOSTING:
                continue
            entry: dict[str, Any] = {"state": record.state, "epoch": record.epoch, "frozen": False}
            freeze, superseded = self.frozen, self.superseded_by
            if freeze is not None and freeze.companion == record.companion:
                entry.update(fork_report(freeze, self.sim.embodiment))
            if superseded is not None:
                entry["superseded_by"] = {"holder": superseded.holder, "epoch": superseded.epoch}
            if record.companion in self.damaged:
                entry["damaged"] = True
            report[record.companion] = entry
        return report

    # --- life cycle (loop) ----------------------------------------------------------------------

    def attach(self, sim: Simulation) -> None:
        self._checker = ClaimChecker(self._check_claim, self._claim_checked).start()
        # Kept current by the transport's worker, so that choosing a target never blocks the loop.
        self._watches = [sim.transport.watch_liveliness(f"{keys.mesh_prefix(sim.mesh)}/{keys.ALIVE}/*", self._on_token),
                         sim.transport.watch_liveliness(keys.custody_pattern(sim.mesh), self._on_custody)]
        if self.seed is not None and self.records.get(self.seed) is None and self.records.hosting() is None:
            self._give_birth(self.seed)
        for companion, error in self.damaged.items():
            log.error("companion %s is damaged and will not run here: %s", companion, error)
            self.raise_event("CompanionDamaged", {"companion": companion, "error": error})
        for record in self.records.all():
            if record.companion in self.damaged:
                continue
            if record.state in HOSTING and not record.chain:
                record = self._adopt_legacy(record)
            problem = self._unbacked(record)
            if problem:
                self._report_damaged(record.companion, problem)
                continue
            if record.state == "prepared":
                # Never handed: the target cannot have activated. Abort and resume here.
                self.records.put(handshake.resume(record))
                self._send_abort_later(record)
                self._resume(record.companion, "recovered: a migration had not reached its commit point")
            elif record.state == "active":
                self._resume(record.companion, "started")
            elif record.state == "handed":
                self._claim(record.companion, record.epoch)
                self._spawn(f"commit-{record.companion}", self._commit_until_acked, record)
            elif record.state == "incoming":
                self._claim(record.companion, record.epoch)
                self._spawn(f"resolve-{record.companion}", self._resolve_incoming, record)
                self._expire_later(record)  # from the prepare's time: overdue already, at the next update
        if self.identity is None:
            self._minds_sleep()

    def _give_birth(self, companion: str) -> None:
        """First start of the companion's home: it is born here, at epoch 1, with its identity key."""
        packed = Identity(companion, 1, {}).pack_sections()
        private = signing.new_key()
        chain = [custody.birth(companion, self.sim.embodiment, private, packed.manifest)]
        self.records.put_key(companion, private)
        self.records.put(Record(companion, "active", 1, chain=chain, public_key=signing.encode_public(chain[0].public_key)),
                         document=packed.manifest, sections=packed.data)

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
        self.records.put_key(record.companion, private)
        record = self.records.put(Record(record.companion, "active", record.epoch, chain=chain,
                                         public_key=signing.encode_public(chain[0].public_key)), document=document)
        legacy.unlink(missing_ok=True)
        return record

    def detach(self) -> None:
        for watch in self._watches:
            watch.close()
        self._watches = []
        self._stop.set()
        if self._checker is not None:
            self._checker.close()
        waiting, self._waiting = self._waiting, []
        for wait in waiting:
            wait.request.reject(f"embodiment {self.sim.embodiment!r} is shutting down", Code.SHUTTING_DOWN)
        for source in list(self._stagings):
            self._unstage(source)
        if self._upload_timer is not None:
            self._upload_timer.cancel()
            self._upload_timer = None
        with self._threads_lock:
            threads, self._threads = self._threads, []
        for thread in threads:
            thread.join(10.0)
        self._withdraw_claim()
        identity = self.identity
        record = self.records.get(identity.companion) if identity is not None else None
        if identity is not None and record is not None and record.state == "active":
            # A clean stop keeps what the companion learnt since it arrived.
            self._refresh_sections(identity)
            self._keep(record, identity)

    def _keep(self, record: Record, identity: Identity) -> None:
        """Store ``identity`` as the active companion's document (and its sections) here."""
        packed = identity.pack_sections(self._memo)
        self.records.put(record, document=packed.manifest, sections=packed.data)

    def _spawn(self, name: str, fn: Callable[..., None], *args: Any) -> None:
        thread = threading.Thread(target=fn, args=args, name=f"migration-{name}", daemon=True)
        with self._threads_lock:
            self._threads = [t for t in self._threads if t.is_alive()]
            self._threads.append(thread)
        thread.start()

    def _post(self, fn: Callable[..., None], *args: Any) -> None:
        try:
            self.sim.call(functools.partial(fn, *args))
        except MeshError:
            pass  # closing

    # --- the mesh as seen by liveliness (transport worker) ----------------------------------------

    def _on_token(self, key: str, alive: bool) -> None:
        name = key.rsplit("/", 1)[-1]
        with self._watch_lock:
            if alive:
                self._alive.add(name)
            else:
                self._alive.discard(name)

    def _on_custody(self, key: str, alive: bool) -> None:
        """A custody token came or went: a hint, recorded; its claim is checked on the claim checker."""
        try:
            holder, companion, epoch_text = key.split("/")[-3:]
            epoch = int(epoch_text)
        except ValueError:
            log.warning("ignored custody token %s: not <holder>/<companion>/<epoch>", key)
            return
        with self._watch_lock:
            tokens = self._tokens.setdefault(companion, set())
            if alive:
                tokens.add((holder, epoch))
            else:
                tokens.discard((holder, epoch))
                self._backed.get(companion, {}).pop((holder, epoch), None)  # the token went: its claim goes
                self._stood_down.discard((holder, companion, epoch))
                if not tokens:
                    del self._tokens[companion]
                    self._backed.pop(companion, None)
        checker = self._checker
        if alive and holder != self.sim.embodiment and checker is not None and not checker.submit((holder, companion, epoch)):
            self._ignore(holder, companion, epoch, "too many claims are waiting to be checked")

    def _is_alive(self, name: str) -> bool:
        with self._watch_lock:
            return name in self._alive

    # --- claims checked (the claim checker's thread) ----------------------------------------------

    def _trusted(self, companion: str) -> bytes | None:
        """The identity key trusted here for ``companion``: admitted, or pinned (None: none yet)."""
        trusted = self.admit.get(companion) if self.admit is not None else None
        record = self.records.get(companion)
        if trusted is None and record is not None and record.public_key:
            trusted = signing.decode_public(record.public_key)
        return trusted

    def _token_present(self, holder: str, companion: str, epoch: int) -> bool:
        with self._watch_lock:
            return (holder, epoch) in self._tokens.get(companion, ())

    def _check_claim(self, key: ClaimKey, tries: int) -> float | None:
        """Ask the claimant to back its token, and keep the claim if it does; None when done, or the
        seconds after which to try again."""
        holder, companion, epoch = key
        if not self._token_present(holder, companion, epoch) or self._stop.is_set():
            return None  # gone meanwhile: nothing to check
        me = self.sim.embodiment
        nonce = secrets.token_bytes(16)
        try:
            reply = self._request(holder, "chain", MigrateChain(companion, epoch, nonce), timeout=CHAIN_TIMEOUT)
        except OutcomeUnknown as exc:
            return self._not_backed(key, tries, f"it does not answer ({exc})", CLAIM_TRIES)
        if reply.status != "accepted":
            return self._not_backed(key, tries, f"it does not back it: {reply.reason}")
        value = reply.value if isinstance(reply.value, dict) else {}
        if value.get("state") == "incoming" and value.get("epoch") == epoch:
            return None  # receiving it: no custody yet, so neither a claim nor an objection to anyone
        try:
            chain = custody.decode_chain(base64.b64decode(str(value.get("chain", "")), validate=True))
            proof = base64.b64decode(str(value.get("proof", "")), validate=True)
            custody.verify_claim(chain, custody.ClaimProof(companion, epoch, holder, me, nonce), proof,
                                 identity=self._trusted(companion))
        except (SignatureRefused, binascii.Error, ValueError) as exc:
            return self._not_backed(key, tries, str(exc))
        with self._watch_lock:
            if (holder, epoch) not in self._tokens.get(companion, ()):
                return None
            self._backed.setdefault(companion, {})[(holder, epoch)] = Claim(holder, chain)
        self._post(self._check_conflict)
        return None

    def _not_backed(self, key: ClaimKey, tries: int, why: str, limit: int = 2) -> float | None:
        """A claim not backed this time: asked again shortly (its token may be on its way out), and
        ignored, and logged, if it still is not."""
        if tries + 1 < limit and not self._stop.is_set():
            return CLAIM_RETRY * (1 << tries)
        if self._token_present(*key):
            self._ignore(*key, why)
        return None

    def _ignore(self, holder: str, companion: str, epoch: int, why: str) -> None:
        muted = self._quiet.allow(f"claim:{holder}")
        if muted is not None:
            more = f" ({muted} more of its claims ignored since the last report)" if muted else ""
            log.warning("ignored the custody claim of %r on %r at epoch %d: %s. A custody token is a hint, not proof: "
                        "only a claim backed by its chain of custody counts%s", holder, companion, epoch, why, more)

    def _claim_checked(self, key: ClaimKey) -> None:
        self._post(self._claims_settled, key[1])

    # --- custody claims, forks and conflicts (loop) --------------------------------------------------

    def _claim(self, companion: str, epoch: int) -> None:
        self._withdraw_claim()
        self._token = self.sim.transport.declare_token(keys.custody_key(self.sim.mesh, self.sim.embodiment, companion, epoch))

    def _withdraw_claim(self) -> None:
        if self._token is not None:
            self._token.close()
            self._token = None

    def _on_chain(self, request: IncomingRequest, msg: MigrateChain) -> None:
        """Back this embodiment's custody token: the chain held here and, when it holds custody, the
        asker's nonce signed by the key at the chain's head."""
        me = self.sim.embodiment
        record = self.records.get(msg.companion)
        if record is None or record.state not in HOSTING or msg.companion in self.damaged:
            request.reject(f"{me!r} holds no custody of {msg.companion!r}", Code.NOT_FOUND)
            return
        if record.epoch != msg.epoch:
            request.reject(f"{me!r} holds {msg.companion!r} at epoch {record.epoch}, not {msg.epoch}", Code.NOT_FOUND)
            return
        bucket = self._chain_buckets.setdefault(request.requester, TokenBucket())
        if len(self._chain_buckets) > 1024:
            self._chain_buckets = {request.requester: bucket}
        if not bucket.take():
            request.reject(f"busy: too many chain requests from {request.requester!r}; try again later", Code.BUSY)
            return
        proof = b""
        private = self.records.key(msg.companion) if record.state != "incoming" else None
        if private is not None:
            proof = custody.sign_claim(private, custody.ClaimProof(msg.companion, record.epoch, me, request.requester,
                                                                   msg.nonce))
        request.accept({"state": record.state, "epoch": record.epoch, "proof": base64.b64encode(proof).decode(),
                        "chain": base64.b64encode(custody.encode_chain(record.chain)).decode()})

    def _check_conflict(self) -> None:
        """The inhabitant's verdict on the others' backed claims: stand down for good when one extends
        its chain, freeze on a proven fork (no branch wins by itself)."""
        identity = self.identity
        if identity is None:
            return
        record = self.records.get(identity.companion)
        if record is None or record.state not in ("active", "prepared"):
            return
        verdict = handshake.judge(record, self.claims(identity.companion))
        superseded = verdict.superseded_by
        if superseded is None and self.superseded_by is not None \
                and custody.compare(record.chain, self.superseded_by.chain)[0] == "behind":
            superseded = self.superseded_by  # seen while in a handshake: the proof stands if its token went since
        self.superseded_by = superseded
        if superseded is not None and record.state == "active":
            self._superseded(record, superseded)
        elif verdict.forks:
            self._freeze(record, verdict.forks)

    def _superseded(self, record: Record, claim: Claim) -> None:
        released = self.records.put(handshake.superseded(record, claim))
        assert released.link is not None
        self.identity = None
        self.frozen = None
        self.superseded_by = None
        self._minds_sleep()
        self._withdraw_claim()
        log.error("custody of %s moved on without this copy: %r holds it at epoch %d, by a link that this embodiment's "
                  "custody key of epoch %d signed to %r (a state folder rolled back?): this copy stands down for good",
                  record.companion, claim.holder, claim.epoch, record.epoch, released.link.holder)
        self.raise_event("CustodySuperseded", {"companion": record.companion, "holder": claim.holder, "epoch": claim.epoch,
                                               "handed_to": released.link.holder, "handed_at": record.epoch + 1})

    def _freeze(self, record: Record, forks: Sequence[tuple[Claim, custody.Fork]]) -> None:
        me = self.sim.embodiment
        held = self.frozen if self.frozen is not None and self.frozen.companion == record.companion else None
        branches = dict(held.branches) if held is not None else {}
        new = [(claim, fork) for claim, fork in forks if branches.get(claim.holder) != list(claim.chain)]
        if not new:
            return
        branches[me] = list(record.chain)
        for claim, _ in new:
            branches[claim.holder] = list(claim.chain)
        freeze = custody.Freeze(record.companion, branches, time.time())
        self.records.put_freeze(freeze)  # on disk before anything acts on it: a restart stays frozen
        self.frozen = freeze
        self._minds_sleep()
        for claim, fork in new:
            log.error("CUSTODY FORK of %s: %s. This embodiment holds one branch (epoch %d), %r the other (epoch %d). No "
                      "branch wins by itself: %s is frozen here until an operator resolves it (`cmion-mesh custody show %s`, "
                      "then `%s`)%s", record.companion, fork.describe(), record.epoch, claim.holder, claim.epoch,
                      record.companion, record.companion, RESOLVE.format(companion=record.companion),
                      f"; revoke the equivocator: `cmion-mesh certs revoke PKI {fork.equivocator}`" if fork.equivocator else "")
        self.raise_event("CustodyFork", {"companion": record.companion, "frozen": True, **fork_report(freeze, me)})

    def _seen_fork(self, fork: custody.Fork, source: str) -> None:
        """A target refused an offer because of a proven fork: logged (per equivocator, quietly) and raised."""
        muted = self._quiet.allow(f"fork:{fork.companion}:{fork.equivocator}:{fork.epoch}")
        if muted is not None:
            log.error("CUSTODY FORK of %s: %s (the offer of %r refused here). Equivocation: revoke it "
                      "(`cmion-mesh certs revoke PKI %s`)", fork.companion, fork.describe(), source, fork.equivocator)
        self.raise_event("CustodyFork", {"companion": fork.companion, "frozen": False, "refused_from": source,
                                         "forks": [fork_summary(fork)], "equivocators": [fork.equivocator]})

    def _unbacked(self, record: Record) -> str:
        """Why ``record``, as stored here, must not run ("" if it may); loads a fork's evidence that
        still freezes it."""
        key = self.records.key(record.companion) if record.state in HOSTING else None
        problem = handshake.at_rest(record, me=self.sim.embodiment, key=key)
        if problem:
            return f"its migration record is not backed by its chain of custody: {problem} " \
                   f"({self.records.dir / (record.companion + '.record.json')})"
        if record.state in ("active", "prepared"):
            try:
                freeze = self.records.freeze(record.companion)
            except ConfigError as exc:
                return str(exc)
            if freeze is not None and freeze.branches.get(self.sim.embodiment) == list(record.chain) \
                    and freeze.forks(self.sim.embodiment):
                self.frozen = freeze
                log.error("custody of %s is frozen here by a fork of its chain (%s), until an operator resolves it: `%s`",
                          record.companion, "; ".join(f.describe() for _, f in freeze.forks(self.sim.embodiment)),
                          RESOLVE.format(companion=record.companion))
            elif freeze is not None:
                self.records.thaw(record.companion)  # evidence about a chain this record no longer holds
        return ""

    def _report_damaged(self, companion: str, error: str) -> None:
        self.damaged[companion] = error
        log.error("companion %s is damaged and will not run here: %s", companion, error)
        self.raise_event("CompanionDamaged", {"companion": companion, "error": error})

    # --- offers waiting for claims to be checked (loop) ----------------------------------------------

    def _wait_for_claims(self, request: IncomingRequest, msg: MigratePrepare | MigrateHave) -> bool:
        """Whether the offer waits (deferred) for the claims on its companion still being checked, so that
        the true holder's token is never raced by a fork. Bounded: ``CLAIM_WAIT``, ``MAX_WAITING``."""
        checker = self._checker
        if checker is None or not checker.pending(msg.companion) or len(self._waiting) >= MAX_WAITING:
            return False
        request.defer()
        self._waiting.append(_Waiting(request, msg, time.monotonic() + CLAIM_WAIT))
        self.sim.call_later(CLAIM_WAIT, functools.partial(self._claims_settled, msg.companion))
        return True

    def _claims_settled(self, companion: str) -> None:
        """Decide the offers that wait for claims on ``companion``: all once none is pending, else
        those that waited ``CLAIM_WAIT`` (a claim still unchecked then counts as not backed)."""
        checker = self._checker
        pending = checker is not None and checker.pending(companion)
        now = time.monotonic()
        ready = [w for w in self._waiting if w.message.companion == companion and (not pending or w.deadline <= now)]
        if not ready:
            return
        self._waiting = [w for w in self._waiting if w not in ready]
        for wait in ready:
            try:
                match wait.message:
                    case MigratePrepare() as prepare:
                        self._on_prepare(wait.request, prepare, waited=True)
                    case MigrateHave() as have:
                        self._on_have(wait.request, have, waited=True)
            except MeshError as exc:
                wait.request.reject(str(exc))
            if not wait.request.answered:
                wait.request.reject(f"component {self.name!r} gave no answer", Code.UNANSWERED)

    # --- an operator resolves a fork (loop) --------------------------------------------------------

    def _on_stand_down(self, request: IncomingRequest, msg: CustodyStandDown) -> None:
        """Retire this copy, for the branch of ``msg.keep``: only a copy whose chain forks from the kept
        one, or that the kept one extends; answered once the retired record is on disk."""
        me = self.sim.embodiment
        record = self.records.get(msg.companion)
        if record is None or record.state not in HOSTING:
            request.accept({"state": record.state if record is not None else "none"})  # nothing here to retire
            return
        if record.state != "active":
            request.reject(f"{me!r} is in a migration of {msg.companion!r} ({record.state}); try again when it ends", Code.BUSY)
            return
        if msg.keep == me:
            request.reject(f"{me!r} is the embodiment to keep", Code.INVALID)
            return
        try:
            kept = custody.decode_chain(msg.chain)
            custody.verify_chain(kept, msg.companion, identity=self._trusted(msg.companion))
        except SignatureRefused as exc:
            request.reject(f"the chain of {msg.keep!r} does not verify here: {exc}", Code.INVALID)
            return
        if kept[-1].holder != msg.keep:
            request.reject(f"the chain given ends with {kept[-1].holder!r}, not {msg.keep!r}", Code.INVALID)
            return
        relation, fork = custody.compare(record.chain, kept)
        if relation not in ("fork", "behind"):
            request.reject(f"keeping {msg.keep!r} would make two: the chain here ({me!r}, epoch {record.epoch}) is "
                           f"{'the same as' if relation == 'same' else 'newer than' if relation == 'stale' else 'foreign to'} "
                           f"the one kept", Code.CONFLICT)
            return
        retired = self.records.put(handshake.retired(record, kept))  # on disk before the answer
        self.identity = None
        self.frozen = None
        self.superseded_by = None
        self._minds_sleep()
        self._withdraw_claim()
        log.warning("custody of %s: this copy (epoch %d) stood down for the branch of %r (epoch %d), as an operator "
                    "resolved the fork%s", msg.companion, record.epoch, msg.keep, retired.epoch,
                    f" ({fork.describe()})" if fork is not None else "")
        self.raise_event("CustodyStoodDown", {"companion": msg.companion, "keep": msg.keep, "epoch": record.epoch,
                                              "kept_epoch": retired.epoch})
        request.accept({"state": retired.state, "epoch": retired.epoch})

    def _on_resume(self, request: IncomingRequest, msg: CustodyResume) -> None:
        """The keeper of a resolved fork runs the companion again, once the others stood down."""
        identity = self.identity
        record = self.records.get(msg.companion)
        if identity is None or identity.companion != msg.companion or record is None or record.state != "active":
            request.reject(f"{self.sim.embodiment!r} does not hold {msg.companion!r}", Code.NOT_FOUND)
            return
        freeze = self.frozen
        if freeze is None:
            request.accept({"state": "running"})
            return
        with self._watch_lock:
            for holder, epoch in self._tokens.get(msg.companion, ()):
                if holder in msg.retired:
                    self._stood_down.add((holder, msg.companion, epoch))
        left = sorted(h for h in freeze.branches if h != self.sim.embodiment and h not in msg.retired)
        if left:
            request.reject(f"the branches of {', '.join(map(repr, left))} have not stood down: resuming would make two",
                           Code.CONFLICT)
            return
        self.records.thaw(msg.companion)
        self.frozen = None
        log.warning("custody of %s: the fork is resolved (%s stood down); it runs here again", msg.companion,
                    ", ".join(map(repr, msg.retired)) or "nobody else")
        self.raise_event("CustodyResolved", {"companion": msg.companion, "retired": list(msg.retired)})
        self._check_conflict()
        if self.frozen is not None:
            request.reject(f"another branch of {msg.companion!r} is claimed still: frozen again", Code.CONFLICT)
            return
        self._wake_minds()
        request.accept({"state": "running"})

    # --- minds and sections (loop) --------------------------------------------------------------

    def _minds(self) -> list[Mind]:
        return [c for c in self.sim.components if isinstance(c, Mind)]

    def _minds_sleep(self) -> None:
        for mind in self._minds():
            mind.sleep()

    def _wake_minds(self) -> None:
        world = self.sim.components_by_name().get(keys.WORLD_MODEL)
        tree = world.tree() if isinstance(world, Store) else {}
        for mind in self._minds():
            mind.wake()
            mind.on_arrived(tree)

    def _refresh_sections(self, identity: Identity) -> None:
        for mind in self._minds():
            identity.sections[mind.name] = mind.state()

    def _resume(self, companion: str, why: str) -> None:
        try:
            identity = self.records.identity(companion, self._memo) or Identity(companion, 1, {})
        except ConfigError as exc:  # its stored identity was altered at rest meanwhile: report, never run
            self.identity = None
            self._report_damaged(companion, str(exc))
            self._minds_sleep()
            return
        record = self.records.get(companion)
        if record is not None:
            identity.epoch = record.epoch
        self._inhabit(identity, "CompanionResumed", why)

    def _inhabit(self, identity: Identity, event: str, why: str) -> None:
        self.identity = identity
        self._claim(identity.companion, identity.epoch)
        for mind in self._minds():
            state = identity.sections.get(mind.name)
            if isinstance(state, dict) and state:
                mind.restore(state)
        self.raise_event(event, {"companion": identity.companion, "epoch": identity.epoch, "why": why,
                                 "sections": sorted(identity.sections)})
        if self.frozen is None and self.superseded_by is None:
            self._wake_minds()
        self._check_conflict()

    # --- outgoing (source side) ---------------------------------------------------------------

    def start(self, target: str, companion: str | None = None) -> Future[Outcome]:
        """Start migrating the companion living here to ``target``; thread-safe. The future ends
        with the outcome (accepted when the target committed; rejected with the reason)."""
        future: Future[Outcome] = Future()
        self._post(self._start_from_thread, Migrate(companion or self.inhabitant or "", target), future)
        return future

    def _start_from_thread(self, request: Migrate, future: Future[Outcome]) -> None:
        self._start(request, future)

    def _start(self, request: Migrate, future: Future[Outcome]) -> _Outgoing | None:
        def refuse(reason: str) -> None:
            self.raise_event("MigrationFailed", {"companion": request.companion, "target": request.target, "reason": reason})
            future.set_result(Outcome("rejected", reason))

        identity = self.identity
        if identity is None:
            refuse(f"embodiment {self.sim.embodiment!r} hosts no companion")
            return None
        if request.companion and request.companion != identity.companion:
            refuse(f"companion {request.companion!r} does not live on {self.sim.embodiment!r} "
                   f"(its inhabitant is {identity.companion!r})")
            return None
        if self.frozen is not None:
            refuse(f"custody of {identity.companion!r} is frozen by a fork of its chain "
                   f"({'; '.join(f.describe() for _, f in self.frozen.forks(self.sim.embodiment))}): "
                   f"an operator resolves it with `{RESOLVE.format(companion=identity.companion)}`")
            return None
        if self._outgoing is not None:
            refuse(f"a migration of {identity.companion!r} to {self._outgoing.target!r} is already under way")
            return None
        try:
            keys.check_name(request.target, "target")
        except MeshError as exc:
            refuse(str(exc))
            return None
        if request.target == self.sim.embodiment:
            refuse(f"{identity.companion!r} already lives on {request.target!r}")
            return None
        if not self._is_alive(request.target):
            refuse(f"unknown target: embodiment {request.target!r} is not alive in mesh {self.sim.mesh!r}")
            return None
        record = self.records.get(identity.companion)
        if record is None or record.state != "active":
            refuse(f"{identity.companion!r} is not active here")
            return None
        refused_by = refuses(identity, request.target)
        if refused_by:
            refuse(refused_by)
            return None
        out = _Outgoing(identity.companion, request.target, record.epoch, uuid.uuid4().hex, future)
        self._outgoing = out
        self.raise_event("MigrationStarting", {"companion": out.companion, "target": out.target, "attempt": out.attempt,
                                               "epoch": out.epoch})
        self._minds_sleep()  # freeze: the companion acts nowhere until the handshake is decided
        # The event is dispatched in this update; sections are collected from the next one on.
        self.sim.call(functools.partial(self._maybe_pack, out))
        self.sim.call_later(self.section_deadline, functools.partial(self._section_deadline, out))
        return out

    def contribute(self, component: str, data: Any) -> None:
        """Add ``component``'s section to the migration being packed. Thread-safe.

        On the loop (a ``MigrationStarting`` handler) it applies at once: posted, it would queue
        behind the packing that the same update already scheduled, and miss the document."""
        if self.sim.on_loop():
            self._contribute(component, data)
        else:
            self._post(self._contribute, component, data)

    def _contribute(self, component: str, data: Any) -> None:
        out = self._outgoing
        if out is not None and not out.packed:
            out.contributions[component] = data
            out.waits.discard(component)
            self._maybe_pack(out)

    def wait(self, component: str) -> WaitToken:
        """Ask the packing to wait for ``component`` (loop thread); ``resolve`` ends the wait."""
        out = self._outgoing
        if out is None or out.packed:
            raise MeshError("no migration is being packed")
        out.waits.add(component)
        return WaitToken(out.attempt, component)

    def resolve(self, token: WaitToken, data: Any) -> None:
        """End a wait with the component's section. Thread-safe."""
        self._post(self._resolve, token, data)

    def _resolve(self, token: WaitToken, data: Any) -> None:
        out = self._outgoing
        if out is not None and out.attempt == token.attempt:
            self._contribute(token.component, data)

    def refuse(self, token: WaitToken, reason: str) -> None:
        """End a wait by abandoning the migration: the component cannot give its section (its
        reason is the migration's). Thread-safe. Sooner and clearer than the section deadline."""
        self._post(self._refuse, token, reason)

    def _refuse(self, token: WaitToken, reason: str) -> None:
        out = self._outgoing
        if out is not None and out.attempt == token.attempt and not out.packed:
            self._abandon(out, f"{token.component}: {reason}")

    def _section_deadline(self, out: _Outgoing) -> None:
        if self._outgoing is out and not out.packed:
            self._abandon(out, f"components {sorted(out.waits)} did not give their sections within {self.section_deadline:g} s")

    def _abandon(self, out: _Outgoing, reason: str) -> None:
        self._outgoing = None
        self.raise_event("MigrationFailed", {"companion": out.companion, "target": out.target, "attempt": out.attempt,
                                             "reason": reason})
        if self.frozen is None and self.superseded_by is None:
            for mind in self._minds():
                mind.wake()
        if not out.future.done():
            out.future.set_result(Outcome("rejected", reason))

    def _maybe_pack(self, out: _Outgoing) -> None:
        if self._outgoing is not out or out.packed or out.waits:
            return
        identity = self.identity
        assert identity is not None
        self._refresh_sections(identity)
        sections = dict(identity.sections)  # carried-on sections stay unless freshly contributed
        sections.update(out.contributions)
        out.packed = True
        # Encoding and hashing happen on the handshake thread: the minds sleep, nothing changes these.
        self._spawn(f"send-{out.companion}", self._send, out, Identity(out.companion, out.epoch, sections))

    def _request(self, peer: str, op: str, message: Any, timeout: float | None = None) -> Outcome:
        key = keys.request_key(self.sim.mesh, peer, "migration", op, self.sim.embodiment)
        return send_request(self.sim.transport, key, message, timeout=self.request_timeout if timeout is None else timeout)

    def _send(self, out: _Outgoing, identity: Identity) -> None:
        """Handshake thread: pack, send what the target lacks, prepare, then (once handed) commit."""
        try:
            packed = identity.pack_sections(self._memo)
        except (MeshError, ValueError) as exc:
            self._post(self._abandon, out, f"cannot pack the identity: {exc}")
            return
        active = self.records.get(out.companion)
        private = self.records.key(out.companion)
        if active is None or active.state != "active" or private is None:
            self._post(self._aborted, out, f"{out.companion!r} is not active here with its custody key")
            return
        prepared, message = handshake.offer(active, attempt=out.attempt, me=self.sim.embodiment, target=out.target,
                                            document=packed.manifest, private=private)
        refs = list({ref.sha256: ref for ref in packed.refs}.values())
        out.transfer = {"sent": 0, "total": packed.size, "sections": len(refs), "sections_sent": 0}
        stored: list[BaseException] = []
        written: list[Record] = []

        def store() -> None:
            # This side's copy, written while the target receives its own; then, once the sections
            # are on disk, the prepared record that names them, still while the chunks travel: a crash
            # from here on is the crash at source:prepared (never handed: the source resumes).
            try:
                self.records.sections.write(packed.data)
                written.append(self.records.put(prepared, document=packed.manifest))
            except OSError as exc:
                stored.append(exc)
                return
            crash_point("source:prepared")
            self._post(self._step, written[0])

        writer = threading.Thread(target=store, name=f"migration-store-{out.companion}", daemon=True)
        try:
            inline = refs
            if sum(ref.size for ref in refs) > INLINE:
                writer.start()  # from now on, beside have and the chunks
                inline, bulk = self._ask_have(out, message, refs)
                self._send_bulk(out, message, packed, bulk)
        except (_Refused, OutcomeUnknown) as exc:
            if writer.is_alive():
                writer.join()
            why = f"{out.target} refused: {exc}" if isinstance(exc, _Refused) else f"outcome unknown ({exc})"
            if written:  # active again; the prepare was never sent, so the target holds nothing of this attempt
                self.records.put(handshake.resume(written[0]))
            self._post(self._abandon, out, f"{why}; the companion stays here")
            return
        if writer.is_alive():
            writer.join()
        if stored:
            self._post(self._abandon, out, f"cannot store the identity here: {stored[0]}")
            return
        if written:
            prepared = written[0]
        else:  # a small identity: this side's copy goes with its record
            try:
                prepared = self.records.put(prepared, document=packed.manifest, sections=packed.data)
            except OSError as exc:
                self._post(self._abandon, out, f"cannot store the identity here: {exc}")
                return
            crash_point("source:prepared")
            self._post(self._step, prepared)
        reply, unknown = self._prepare(out, message, packed, inline)
        after = handshake.after_prepare(prepared, reply, private=private, document=packed.manifest) if reply is not None \
            else handshake.resume(prepared)
        if after.state != "handed":
            self.records.put(after)
            if reply is None or reply.status == "accepted":
                self._send_abort_later(prepared)  # T may hold it incoming: tell it, or it will ask us
            reason = (f"{out.target} refused: {reply.reason}" if reply is not None and reply.status != "accepted"
                      else f"{out.target} gave no custody key" if reply is not None
                      else f"outcome unknown ({unknown}); the companion resumes here")
            self._post(self._aborted, out, reason)
            return
        handed = self.records.put(after)
        crash_point("source:handed")
        self._post(self._step, handed)
        self._post(self._handed, out)
        self._commit_until_acked(handed)

    def _prepare(self, out: _Outgoing, message: MigratePrepare, packed: Packed,
                 inline: list[SectionRef]) -> tuple[Outcome | None, str]:
        """Send the prepare, with ``inline`` sections inside; prepare is idempotent, so a lost reply
        is asked again, and sections the target says it lacks are sent before asking again."""
        reply: Outcome | None = None
        unknown = ""
        tries = lossy = 0
        while tries < 3 and lossy < 3:  # missing sections twice over is a target losing them: give up
            sections = [packed.data[ref.sha256] for ref in inline]
            out.transfer["sent"] += len(message.document) + sum(len(b) for b in sections)
            out.transfer["sections_sent"] += len(sections)
            try:
                reply = self._request(out.target, "prepare", msgspec.structs.replace(message, sections=sections))
            except OutcomeUnknown as exc:
                reply, unknown = None, str(exc)
                lossy += 1
                if self._stop.wait(self.retry[0]):
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
                    inline, bulk = self._ask_have(out, message, wanted)
                    self._send_bulk(out, message, packed, bulk)
                except (_Refused, OutcomeUnknown) as exc:
                    unknown = str(exc)
                    break
        return reply, unknown

    def _ask_have(self, out: _Outgoing, message: MigratePrepare,
                  refs: list[SectionRef]) -> tuple[list[SectionRef], list[SectionRef]]:
        """``have``: of the sections the target lacks, the small ones (at most ``INLINE`` bytes
        together), for the prepare to carry, and the others, to send apart (``_send_bulk``)."""
        reply = self._request(out.target, "have", handshake.have(message))
        if reply.status != "accepted":
            raise _Refused(reply.reason)
        value = reply.value if isinstance(reply.value, dict) else {}
        held = set(value.get("have") or [])
        missing = sorted((ref for ref in refs if ref.sha256 not in held), key=lambda r: r.size)
        inline: list[SectionRef] = []
        budget = INLINE
        while missing and missing[0].size <= budget:
            budget -= missing[0].size
            inline.append(missing.pop(0))
        return inline, missing

    def _send_bulk(self, out: _Outgoing, message: MigratePrepare, packed: Packed, missing: list[SectionRef]) -> None:
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
                batches[-1].append(SectionChunk(ref.sha256, offset, piece))  # type: ignore[arg-type]  # encoded as bin, uncopied
                size += len(piece)
            out.transfer["sections_sent"] += 1
        batches = [b for b in batches if b]
        if len(batches) > 1:
            # Two requests in flight: the target checks and writes one while the next is on its way.
            with ThreadPoolExecutor(IN_FLIGHT, thread_name_prefix=f"migration-chunks-{out.companion}") as pool:
                for _ in pool.map(functools.partial(self._send_chunks, out, message), batches):
                    pass
        elif batches:
            self._send_chunks(out, message, batches[0])
        out.transfer["sent"] += sum(len(c.data) for batch in batches for c in batch)

    def _send_chunks(self, out: _Outgoing, message: MigratePrepare, chunks: list[SectionChunk]) -> None:
        request = MigrateSections(message.companion, message.attempt, message.source, message.target, chunks)
        for attempt in range(3):  # chunks are idempotent: a lost answer is asked again
            try:
                reply = self._request(out.target, "sections", request)
                break
            except OutcomeUnknown:
                if attempt == 2 or self._stop.wait(self.retry[0]):
                    raise
        if reply.status != "accepted":
            raise _Refused(reply.reason)

    def _step(self, record: Record) -> None:
        # Loop thread. Each durable record of a handshake is one step a watcher (``cmion-mesh view``)
        # can draw: the Migration* events alone say when it starts and ends, not how far it got.
        self.raise_event("MigrationStep", {"companion": record.companion, "attempt": record.attempt, "step": record.state,
                                           "peer": record.peer, "epoch": record.epoch})

    def _aborted(self, out: _Outgoing, reason: str) -> None:
        self._abandon(out, reason)
        self._resume(out.companion, f"migration to {out.target} failed")

    def _handed(self, out: _Outgoing) -> None:
        # The commit point: never run the companion here again. The custody claim stays until the
        # target has taken it, so no moment passes in which nobody in the mesh claims the companion.
        # A fork found meanwhile goes with the branch: the target meets the other one itself.
        self.identity = None
        self.frozen = None
        self.superseded_by = None

    def _commit_until_acked(self, handed: Record) -> None:
        """Handshake thread: send the commit until the target answers; a refusal is settled by
        asking the target what it made of the attempt (never by looping on the refusal)."""
        assert handed.link is not None
        message = MigrateCommit(handed.companion, handed.epoch, handed.attempt, self.sim.embodiment, handed.peer,
                                custody.encode_link(handed.link))
        status = MigrateStatus(handed.companion, handed.attempt, handed.epoch, "target")
        delay = self.retry[0]
        while not self._stop.is_set():
            try:
                reply = self._request(handed.peer, "commit", message)
                if reply.status == "accepted":
                    self._finish_handed(msgspec.structs.replace(handed, state="released"))
                    return
                log.warning("%s refused the commit of %s (%s): asking it where it stands", handed.peer, handed.companion,
                            reply.reason)
                answer = self._request(handed.peer, "status", status)
                next_step, record = handshake.after_refused_commit(handed, answer.value if answer.status == "accepted" else None)
                if next_step == "released" and record is not None:
                    self._finish_handed(record)
                    return
                if next_step == "resume" and record is not None:
                    self.records.put(record)
                    self._post(self._taken_back, record, f"{handed.peer} dropped attempt {handed.attempt}")
                    return
                if next_step == "abort":
                    self._request(handed.peer, "abort", MigrateAbort(handed.companion, handed.epoch, handed.attempt))
                    continue  # then ask again: dropped -> resume
                self._post(self.raise_event, "MigrationStuck", {"companion": handed.companion, "target": handed.peer,
                                                                "reason": reply.reason})
            except OutcomeUnknown as exc:
                log.info("commit of %s to %s: %s; retrying", handed.companion, handed.peer, exc)
            if self._stop.wait(delay):
                return
            delay = min(self.retry[1], delay * 2)

    def _finish_handed(self, released: Record) -> None:
        self.records.put(released)
        crash_point("source:released")
        self._post(self._released, released)

    def _taken_back(self, record: Record, why: str) -> None:
        out = self._outgoing
        self._outgoing = None
        reason = f"migration of {record.companion!r} to {why}; the companion resumes here"
        self.raise_event("MigrationFailed", {"companion": record.companion, "attempt": out.attempt if out else "", "reason": reason})
        if out is not None and not out.future.done():
            out.future.set_result(Outcome("rejected", reason))
        self._resume(record.companion, reason)

    def _released(self, record: Record) -> None:
        out = self._outgoing
        self._outgoing = None
        if self.identity is None:
            self._withdraw_claim()
        data: dict[str, Any] = {"companion": record.companion, "target": record.peer, "attempt": record.attempt,
                                "epoch": record.epoch + 1}
        if out is not None and out.attempt == record.attempt and out.transfer:
            data["transfer"] = dict(out.transfer)
            self.last_transfer = dict(out.transfer)
        self.raise_event("MigrationSucceeded", data)
        if out is not None and out.attempt == record.attempt and not out.future.done():
            out.future.set_result(Outcome("accepted", "", data))

    def _send_abort_later(self, record: Record) -> None:
        def abort() -> None:
            try:
                self._request(record.peer, "abort", MigrateAbort(record.companion, record.epoch, record.attempt), timeout=2.0)
            except OutcomeUnknown:
                pass  # the target will ask us (status) and hear "aborted"

        self._spawn(f"abort-{record.companion}", abort)

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
                out = self._start(payload, _AnswerFuture(request))
                if out is not None:  # started: the end is reported by MigrationSucceeded/Failed events
                    request.accept({"attempt": out.attempt, "companion": out.companion, "target": out.target})
            case MigratePrepare() as payload:
                if _sent_by_source(request, payload.source, "a prepare"):
                    self._on_prepare(request, payload)
            case MigrateCommit() as payload:
                if _sent_by_source(request, payload.source, "a commit"):
                    self._on_commit(request, payload)
            case MigrateAbort() as payload:
                decision = handshake.on_abort(payload, self.records.get(payload.companion), requester=request.requester)
                self._unstage(request.requester, payload.attempt)
                if decision.record is not None:
                    self.records.put(decision.record)
                    self._prepared.pop(payload.attempt, None)
                    if self.identity is None:
                        self._withdraw_claim()
                    self.raise_event("MigrationDropped", {"companion": payload.companion, "attempt": payload.attempt,
                                                          "source": request.requester})
                request.answer(decision.outcome)
            case MigrateStatus() as payload:
                request.answer(handshake.on_status(payload, self.records.get(payload.companion), requester=request.requester).outcome)
            case MigrateHave() as payload:
                if _sent_by_source(request, payload.source, "a have"):
                    self._on_have(request, payload)
            case MigrateSections() as payload:
                if _sent_by_source(request, payload.source, "sections"):
                    self._on_sections(request, payload)
            case MigrateChain() as payload:
                self._on_chain(request, payload)
            case CustodyStandDown() as payload:
                self._on_stand_down(request, payload)
            case CustodyResume() as payload:
                self._on_resume(request, payload)
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
        if self._outgoing is not None:
            request.reject(f"{identity.companion!r} is migrating to {self._outgoing.target!r}", Code.BUSY)
            return
        for name in accepts or []:
            keys.check_name(name, "accepted embodiment")
        if accepts is None:
            identity.sections.pop(POLICY_SECTION, None)
        else:
            identity.sections[POLICY_SECTION] = {"accepts": sorted(set(accepts))}
        self._refresh_sections(identity)
        self._keep(record, identity)
        request.accept(identity.sections.get(POLICY_SECTION))

    def _take_token(self, source: str) -> bool:
        bucket = self._buckets.setdefault(source, TokenBucket())
        if len(self._buckets) > 1024:
            self._buckets = {source: bucket}  # bounded: forget strangers, keep the one asking
        return bucket.take()

    def _staged(self, attempt: str, source: str) -> _Staging | None:
        staging = self._stagings.get(source)
        return staging if staging is not None and staging.attempt == attempt else None

    def _unstage(self, source: str, attempt: str | None = None, *, prepared: bool = False) -> None:
        """End ``source``'s upload (of ``attempt``, if given). Unless a record now names them
        (``prepared``), the sections it wrote are deleted: an upload that never became a prepare
        leaves nothing behind, but what another upload holds or a record names."""
        staging = self._stagings.get(source)
        if staging is None or (attempt is not None and staging.attempt != attempt):
            return
        del self._stagings[source]
        self._end_upload(staging, prepared=prepared)

    def _end_upload(self, staging: _Staging, *, prepared: bool = False) -> None:
        staging.abandon()
        store = self.records.sections
        if self._stagings.get(staging.source) is None:
            store.unpin(f"{_STAGING}/{staging.source}")
        if staging.stored and not prepared:
            removed = store.discard(staging.stored, self.records.referenced())
            if removed:
                log.info("upload of attempt %s from %s ended without a prepare: %d bytes of sections deleted",
                         staging.attempt, staging.source, removed)

    def _expire_uploads(self) -> None:
        """Loop timer: end the uploads idle for ``upload_idle`` seconds; wake again for the next."""
        self._upload_timer = None
        now = time.monotonic()
        for source, staging in list(self._stagings.items()):
            if now - staging.last >= self.upload_idle:
                log.info("upload of attempt %s from %s idle for %g s: expired", staging.attempt, source, self.upload_idle)
                self._unstage(source)
        if self._stagings and not self._stop.is_set():
            due = min(s.last for s in self._stagings.values()) + self.upload_idle
            self._upload_timer = self.sim.call_later(max(0.0, due - now), self._expire_uploads)

    def _upload_room(self, staging: _Staging, size: int) -> str:
        """"" if ``size`` more bytes of ``staging``'s upload may be written now, else why not (naming
        its sender): at most ``max_upload`` per sender, and the section folder within its bound."""
        me, store = self.sim.embodiment, self.records.sections
        if staging.received + size > self.max_upload:
            return (f"{staging.source!r} has uploaded {staging.received} bytes of sections to {me!r} for attempt "
                    f"{staging.attempt}; {size} more is over the {self.max_upload} one sender may upload ahead of its "
                    f"prepare ({MAX_UPLOAD_ENV})")
        if not store.make_room(size, self.records.referenced):
            return (f"busy: the section store of {me!r} is full ({store.size} of {store.max_cache} bytes, "
                    f"{MAX_CACHE_ENV}, held by uploads not yet prepared and by companions here): {size} bytes more "
                    f"from {staging.source!r} are refused; try again later")
        staging.received += size
        return ""

    def _on_have(self, request: IncomingRequest, msg: MigrateHave, waited: bool = False) -> None:
        """Target: which sections of the offered manifest are here already (each read and checked
        against its hash: a damaged one is missing, and fetched again)."""
        record = self.records.get(msg.companion)
        early = handshake.precheck(msg, record, me=self.sim.embodiment, held=self.records.hosting(), admit=self.admit)
        if early is not None:
            request.answer(early.outcome)
            return
        if not waited and self._wait_for_claims(request, msg):
            return
        if self._staged(msg.attempt, msg.source) is None and not self._take_token(msg.source):
            request.reject(f"busy: too many prepares from {msg.source!r}; try again later", Code.BUSY)
            return
        if msg.source not in self._stagings and len(self._stagings) >= MAX_UPLOADS:
            request.reject(f"busy: {len(self._stagings)} uploads to {self.sim.embodiment!r} are in progress, the most it "
                           f"takes at once; {msg.source!r} may try again later", Code.BUSY)
            return
        decision = handshake.on_have(msg, record, me=self.sim.embodiment,
                                     held=self.records.hosting(), admit=self.admit, claims=self.claims(msg.companion))
        if decision.fork is not None:
            self._seen_fork(decision.fork, msg.source)
        if decision.manifest is None:
            request.answer(decision.outcome)
            return
        staging = _Staging(msg.attempt, msg.source, {ref.sha256: ref for ref in decision.manifest.refs})
        store = self.records.sections
        found, errors = store.read_many((ref for ref in staging.refs.values() if store.holds(ref)), self._memo.held())
        for error in errors.values():
            log.warning("%s; fetching it again from %s", error, msg.source)
        # What nobody names yet is bounded by the cache, and by what one sender may upload: a larger
        # offer would fill the disk.
        missing = sum(ref.size for ref in staging.refs.values() if ref.sha256 not in found)
        if missing > store.max_cache:
            request.reject(f"the sections of {msg.companion!r} missing at {self.sim.embodiment!r} total {missing} bytes, "
                           f"over its section cache of {store.max_cache} bytes ({MAX_CACHE_ENV})", Code.INVALID)
            return
        if missing > self.max_upload:
            request.reject(f"the sections of {msg.companion!r} that {msg.source!r} would upload to {self.sim.embodiment!r} "
                           f"total {missing} bytes, over the {self.max_upload} one sender may upload ahead of its prepare "
                           f"({MAX_UPLOAD_ENV})", Code.INVALID)
            return
        staging.data = dict(found)
        # One upload per sender: a newer have replaces it (and deletes what it wrote, but what the new one holds).
        replaced = self._stagings.get(msg.source)
        self._stagings[msg.source] = staging
        store.pin(f"{_STAGING}/{msg.source}", staging.refs)
        if replaced is not None:
            self._end_upload(replaced)
        if self._upload_timer is None:
            self._upload_timer = self.sim.call_later(self.upload_idle, self._expire_uploads)
        request.accept({"have": sorted(found)})

    def _on_sections(self, request: IncomingRequest, msg: MigrateSections) -> None:
        """Target: chunks of sections; each completed section is checked against its hash and written
        (fsync) before the answer."""
        staging = self._staged(msg.attempt, msg.source)
        if staging is None or msg.target != self.sim.embodiment:
            request.reject(f"no have of attempt {msg.attempt} from {msg.source!r} at {self.sim.embodiment!r}: "
                           "sections are sent after it", Code.NOT_FOUND)
            return
        complete: list[str] = []
        problems: list[str] = []
        refusals: list[str] = []
        store = self.records.sections

        def room(size: int) -> str:  # new bytes are counted before they are written
            why = self._upload_room(staging, size)
            if why:
                refusals.append(why)
            return why

        for chunk in msg.chunks:
            ref = staging.refs.get(chunk.sha256)
            if ref is None:
                problems.append(f"section {chunk.sha256} is not in the manifest of attempt {msg.attempt}")
                break
            if chunk.sha256 in staging.data:
                continue
            incoming = staging.partial.get(chunk.sha256)
            if incoming is None:
                incoming = staging.partial[chunk.sha256] = store.receive(ref)
            problem = incoming.add(chunk.offset, chunk.data, room)
            if not problem and incoming.complete:
                del staging.partial[chunk.sha256]
                problem = incoming.finish()  # replaces a damaged file of that name, if any
                if not problem:
                    staging.data[chunk.sha256] = incoming.data
                    staging.stored.add(chunk.sha256)
                    complete.append(chunk.sha256)
            if problem:
                problems.append(problem if refusals else f"section {ref.component!r} of {msg.companion!r}: {problem}")
                break
        if complete:
            store.sync()
        if problems:
            request.reject("; ".join(problems), Code.BUSY if refusals and refusals[-1].startswith("busy") else Code.INVALID)
        else:
            staging.last = time.monotonic()  # only chunks it takes keep an upload alive
            request.accept({"stored": sorted(complete)})
        log.debug("sections of attempt %s: %d stored", msg.attempt, len(complete))

    def _sections_for(self, msg: MigratePrepare, carried: dict[str, Bytes]) -> handshake.SectionSource:
        """Where a prepare's sections are: inside it (those used are put in ``carried``), staged since
        its ``have``, or on this disk."""

        def find(refs: Sequence[SectionRef]) -> dict[str, Bytes]:
            inline: dict[str, Bytes] = {sha256_hex(data): data for data in msg.sections}
            staging = self._staged(msg.attempt, msg.source)
            found: dict[str, Bytes] = {}
            for ref in refs:
                data = inline.get(ref.sha256)
                if data is not None:
                    carried[ref.sha256] = data
                elif staging is not None:
                    data = staging.data.get(ref.sha256)
                if data is not None:
                    found[ref.sha256] = data
            store = self.records.sections
            read, errors = store.read_many(r for r in refs if r.sha256 not in found and store.holds(r))
            for error in errors.values():
                log.warning("%s; asking %s for it again", error, msg.source)
            found.update(read)
            return found

        return find

    def _on_prepare(self, request: IncomingRequest, msg: MigratePrepare, waited: bool = False) -> None:
        record = self.records.get(msg.companion)
        repeat = record is not None and record.state == "incoming" and record.attempt == msg.attempt
        # Only offers that would cost this embodiment custody checks, XML and disk take from the budget.
        early = handshake.precheck(msg, record, me=self.sim.embodiment, held=self.records.hosting(), admit=self.admit)
        if early is not None:
            request.answer(early.outcome)
            return
        if not repeat and not waited and self._wait_for_claims(request, msg):
            return
        if not repeat and self._staged(msg.attempt, msg.source) is None and not self._take_token(msg.source):
            request.reject(f"busy: too many prepares from {msg.source!r}; try again later")
            return
        carried: dict[str, Bytes] = {}
        decision = handshake.on_prepare(msg, record, me=self.sim.embodiment, held=self.records.hosting(), admit=self.admit,
                                        claims=self.claims(msg.companion), sections=self._sections_for(msg, carried),
                                        values=self._memo.values())
        if decision.fork is not None:
            self._seen_fork(decision.fork, msg.source)
        if decision.record is None:
            if decision.outcome.code != Code.MISSING_SECTIONS:
                self._unstage(msg.source, msg.attempt)
            request.answer(decision.outcome)
            return
        assert decision.key is not None and decision.identity is not None and decision.manifest is not None
        # The sections it carried were sent because they are missing here, or damaged: written anew.
        incoming = self.records.put(msgspec.structs.replace(decision.record, since=time.time()), document=decision.document,
                                    sections=carried, key=decision.key, replace=True)
        crash_point("target:incoming")
        self._step(incoming)
        self._unstage(msg.source, prepared=True)
        for ref in decision.manifest.refs:
            if decision.sections is not None:
                self._memo.remember(ref.component, decision.sections[ref.sha256], ref.sha256,
                                    decision.identity.sections.get(ref.component))
        self._claim(msg.companion, msg.epoch)  # receiving: no moment passes in which nobody claims it
        self._prepared = {msg.attempt: decision.identity}  # one handshake at a time: parsing it again at commit is waste
        request.answer(decision.outcome)
        # The commit (or abort) normally follows at once. If the link fails now, the source's one
        # abort may be lost for good: once overdue, ask the source, as after a restart.
        self._spawn(f"resolve-{msg.companion}", self._resolve_incoming, incoming, self.retry[1])
        self._expire_later(incoming)

    def _on_commit(self, request: IncomingRequest, msg: MigrateCommit) -> None:
        decision = handshake.on_commit(msg, self.records.get(msg.companion), me=self.sim.embodiment)
        if decision.record is not None:
            self._activate(decision.record)
        request.answer(decision.outcome)

    def _activate(self, active: Record) -> None:
        active = self.records.put(active)
        crash_point("target:active")
        self._step(active)
        self.frozen = None  # a frozen holder accepts no prepare: any evidence here was of a copy long gone
        self.superseded_by = None
        identity = self._prepared.pop(active.attempt, None)
        if identity is None:  # restarted since the prepare: the stored document is the truth
            identity = self.records.identity(active.companion, self._memo) or Identity(active.companion, active.epoch, {})
        identity.epoch = active.epoch
        self._inhabit(identity, "MigrationOccurred", f"arrived from {active.peer}")

    def _resolve_incoming(self, record: Record, overdue: float = 0.0) -> None:
        """Handshake thread: ask the source until it says committed or aborted: after a restart in
        ``incoming``, and ``overdue`` seconds after a prepare if neither a commit nor an abort has come."""
        if overdue and self._stop.wait(overdue):
            return
        delay = self.retry[0]
        status = MigrateStatus(record.companion, record.attempt, record.epoch, "source")
        while not self._stop.is_set():
            current = self.records.get(record.companion)
            if current is None or current.state != "incoming" or current.attempt != record.attempt:
                return  # a commit or abort arrived meanwhile
            try:
                reply = self._request(record.peer, "status", status)
                if reply.status == "accepted" and handshake.settle_incoming(current, reply.value, me=self.sim.embodiment):
                    self._post(self._settle_incoming, record, reply.value)
                    return
            except OutcomeUnknown as exc:
                log.info("asking %s about %s: %s", record.peer, record.attempt, exc)
            if self._stop.wait(delay):
                return
            delay = min(self.retry[1] * 2, delay * 2)

    def _settle_incoming(self, record: Record, answer: Any) -> None:
        current = self.records.get(record.companion)
        if current is None or current.state != "incoming" or current.attempt != record.attempt:
            return
        settled = handshake.settle_incoming(current, answer, me=self.sim.embodiment)
        if settled is None:
            return
        if settled.state == "active":
            self._activate(settled)
        else:
            self._drop_incoming(settled, f"{record.peer!r} aborted it")

    def _expire_later(self, record: Record) -> None:
        """Loop: drop ``record``'s attempt at its deadline if it is still undecided then."""
        due = handshake.incoming_deadline(record, self.incoming_timeout)
        self.sim.call_later(max(0.0, due - time.time()), functools.partial(self._expire_incoming, record))

    def _expire_incoming(self, record: Record) -> None:
        current = self.records.get(record.companion)
        if current is None or current.state != "incoming" or current.attempt != record.attempt:
            return  # decided meanwhile
        expired = handshake.expire_incoming(current, now=time.time(), bound=self.incoming_timeout)
        if expired is None:  # the clock went back since the timer was set
            self._expire_later(current)
            return
        reason = (f"{current.peer!r} neither committed nor aborted attempt {current.attempt} of {current.companion!r} "
                  f"within {self.incoming_timeout:g} s of its prepare")
        log.warning("dropping the incoming migration: %s", reason)
        self._drop_incoming(expired, reason)

    def _drop_incoming(self, dropped: Record, reason: str) -> None:
        """Loop: the attempt ``dropped`` ends here, durably first (the source is told ``dropped`` from
        this record on); the embodiment is free for the next migration."""
        self.records.put(dropped)
        self._prepared.pop(dropped.attempt, None)
        self._unstage(dropped.peer, dropped.attempt)
        if self.identity is None:
            self._withdraw_claim()
        self.raise_event("MigrationDropped", {"companion": dropped.companion, "attempt": dropped.attempt,
                                              "source": dropped.peer, "reason": reason})


def fork_summary(fork: custody.Fork) -> dict[str, Any]:
    """A proof of equivocation as plain data, for people and tools (its links are checked where it was found)."""

    def link(item: custody.Link) -> dict[str, Any]:
        return {"holder": item.holder, "epoch": item.epoch, "attempt": item.attempt,
                "key": signing.encode_public(item.public_key)}

    return {"epoch": fork.epoch, "equivocator": fork.equivocator, "description": fork.describe(),
            "links": [link(fork.first), link(fork.second)], "after": link(fork.prefix[-1]) if fork.prefix else None}


def fork_report(freeze: custody.Freeze, me: str) -> dict[str, Any]:
    """What a frozen holder says of its fork (``describe``, ``CustodyFork``): the proofs, each branch's
    holder with its epoch and the equivocators it includes (a branch an equivocator holds is kept
    only when forced), and the command that resolves it."""
    forks = freeze.forks(me)
    equivocators = sorted({fork.equivocator for _, fork in forks if fork.equivocator})
    branches: dict[str, Any] = {}
    for holder, chain in sorted(freeze.branches.items()):
        tainted = sorted({fork.equivocator for _, fork in forks if fork.equivocator in custody.after_fork(chain, fork)})
        branches[holder] = {"epoch": chain[-1].epoch if chain else 0, "equivocators": tainted}
    return {"frozen": True, "forks": [{"with": holder, **fork_summary(fork)} for holder, fork in forks],
            "equivocators": equivocators, "branches": branches, "since": freeze.found,
            "resolve": RESOLVE.format(companion=freeze.companion)}


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


class MigrationCompetency(Competency):
    """Migration as a competency (type ``Migration``): a rule maps ``Migrate <target>`` to it.

    Run parameter ``target``, or ``DeviceName`` as CMION's rules name it (``Migration *`` ->
    ``Migration`` with ``DeviceName=$parameter1``). Succeeds once the target has committed; cannot
    be cancelled once the handshake has started (the companion must end up in exactly one place).

    The constructor takes CMION's one parameter, the device table's file name (``devices``): the
    daemon reads that table before its session opens (``devices.table_for_library``), so here it
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
