"""Migration: a crash-safe queryable handshake that moves a companion between embodiments.

Invariant: at any moment at most one embodiment is inhabited by a companion, and after any
crash or network fault, once things heal, exactly one is. Each side keeps a durable record per
companion (``Records``: temp file, fsync, rename, fsync directory) and moves it through:

source (S, owner at epoch e)           target (T)
  active(e)
  freeze; pack the identity
  prepared(a) ---- prepare(doc) ---->  checks empty (or an older epoch of this companion),
                                       validates the document, stores it,
               <--- prepared --------  incoming(a)
  handed(a)  (commit point: S never runs the companion again)
             ---- commit (until acked)->  active(e+1), restores sections, wakes the mind
               <--- committed -------
  released(a)

A timeout, an empty reply or an error is "outcome unknown", never success. While S is
``prepared`` it may always abort (T cannot activate without a commit, which S sends only after
``handed``). Recovery on restart: S ``prepared`` aborts and resumes; S ``handed`` resumes sending
commit; T ``incoming`` asks S (``status``) and follows its answer, forever if need be: nothing is
taken over because a peer went quiet. Messages are idempotent and keyed by (companion, epoch,
attempt); stale ones are refused.

Before packing, the source raises ``MigrationStarting`` and gives every component one update to
``contribute`` its section (or ``wait`` and ``resolve`` later, within a deadline). Sections that
no component here understands are carried on unchanged. The target raises ``MigrationOccurred``
after activation; each component takes its own section back with ``section(name)``.

Set ``CMION_MESH_CRASH_AT`` to ``source:prepared``, ``source:handed``, ``source:released``,
``target:incoming`` or ``target:active`` (comma-separated) and the process kills itself with
SIGKILL right after writing that record: the crash tests use it.
"""

from __future__ import annotations

import functools
import logging
import os
import signal
import threading
import time
import uuid
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import msgspec

from cmion_mesh import keys, signing
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError, InvalidName, MeshError, OutcomeUnknown
from cmion_mesh.identity import MAX_DOCUMENT, Identity, unpack
from cmion_mesh.ion import Component, IncomingRequest, Simulation, send_request
from cmion_mesh.messages import Migrate, MigrateAbort, MigrateCommit, MigratePrepare, MigrateStatus, Outcome, Request

log = logging.getLogger(__name__)

State = Literal["active", "prepared", "handed", "released", "incoming", "dropped"]
HOSTING: frozenset[str] = frozenset({"active", "prepared", "handed", "incoming"})
#: Largest record file read (a record is a few hundred bytes).
MAX_RECORD = 64 * 1024


class Record(msgspec.Struct, frozen=True):
    """The durable state of one companion on one embodiment."""

    companion: str
    state: State
    epoch: int
    attempt: str = ""
    peer: str = ""  # the target (source side) or the source (target side) of ``attempt``
    updated: float = 0.0
    public_key: str = ""  # the companion's key, pinned when first seen (base64)


class Records:
    """Durable records and identity documents in one directory, written atomically."""

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self._lock = threading.RLock()
        self._cache: dict[str, Record] = {}
        for path in sorted(self.dir.glob("*.record.json")):
            companion, record = self._load(path)
            self._cache[companion] = record

    @staticmethod
    def _load(path: Path) -> tuple[str, Record]:
        try:
            with open(path, "rb") as f:
                raw = f.read(MAX_RECORD + 1)
        except OSError as exc:
            raise ConfigError(f"unreadable migration record: {exc.strerror or exc}", path=str(path)) from None
        if len(raw) > MAX_RECORD:
            raise ConfigError(f"migration record larger than {MAX_RECORD} bytes", path=str(path))
        try:
            record = msgspec.json.decode(raw, type=Record)
        except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise ConfigError(f"unreadable migration record: {exc}", path=str(path)) from None
        try:
            keys.check_name(record.companion, "companion")
        except InvalidName as exc:
            raise ConfigError(f"unusable migration record: {exc}", path=str(path)) from None
        if path.name != f"{record.companion}.record.json":
            raise ConfigError(f"the record is of companion {record.companion!r}, not of the one its file is named after",
                              path=str(path))
        if record.epoch < 0:
            raise ConfigError(f"unusable migration record: negative epoch {record.epoch}", path=str(path))
        return record.companion, record

    def _write(self, name: str, data: bytes) -> None:
        target = self.dir / name
        tmp = self.dir / f".{name}.{os.getpid()}.{threading.get_ident()}.tmp"
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
        fd = os.open(self.dir, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def get(self, companion: str) -> Record | None:
        with self._lock:
            return self._cache.get(companion)

    def put(self, record: Record) -> Record:
        record = msgspec.structs.replace(record, updated=time.time())
        with self._lock:
            self._write(f"{keys.check_name(record.companion, 'companion')}.record.json", msgspec.json.encode(record))
            self._cache[record.companion] = record
        return record

    def move(self, companion: str, state: State, epoch: int, attempt: str = "", peer: str = "",
             public_key: str | None = None) -> Record:
        """Write the companion's next state; the pinned public key is kept unless a new one is given."""
        with self._lock:
            current = self._cache.get(companion)
            pinned = public_key if public_key is not None else (current.public_key if current else "")
            return self.put(Record(companion, state, epoch, attempt, peer, public_key=pinned))

    def all(self) -> list[Record]:
        with self._lock:
            return list(self._cache.values())

    def hosting(self) -> Record | None:
        """The companion this embodiment holds (active, or in a handshake), if any."""
        with self._lock:
            held = [r for r in self._cache.values() if r.state in HOSTING]
        return held[0] if held else None

    def put_document(self, companion: str, data: bytes) -> None:
        with self._lock:
            self._write(f"{keys.check_name(companion, 'companion')}.identity.xml", data)

    def document(self, companion: str) -> bytes | None:
        path = self.dir / f"{companion}.identity.xml"
        try:
            with open(path, "rb") as f:
                return f.read(MAX_DOCUMENT + 1)  # one more than unpack takes, so excess is noticed
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise ConfigError(f"unreadable identity document: {exc.strerror or exc}", path=str(path)) from None

    def check_documents(self) -> None:
        """``ConfigError`` naming the file if the document of a companion held here is unusable."""
        for record in self.all():
            data = self.document(record.companion) if record.state in HOSTING else None
            if data is not None:
                unpack(data, name=str(self.dir / f"{record.companion}.identity.xml"))

    def put_key(self, companion: str, private: bytes) -> None:
        with self._lock:
            signing.save_private(self.dir / f"{keys.check_name(companion, 'companion')}.key", private)

    def key(self, companion: str) -> bytes | None:
        path = self.dir / f"{companion}.key"
        return path.read_bytes() if path.exists() else None


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


@dataclass(frozen=True)
class WaitToken:
    attempt: str
    component: str


class MigrationManager(Component):
    """The ``migration`` component: owns the records, runs both sides of the handshake."""

    requests = {"migrate": Migrate, "prepare": MigratePrepare, "commit": MigrateCommit, "abort": MigrateAbort,
                "status": MigrateStatus, "policy": Request}
    # The handshake travels on per-sender keys: in secure mode only S's certificate may send as S.
    sender_requests = frozenset({"prepare", "commit", "abort", "status"})

    def __init__(self, state_dir: str | os.PathLike[str], *, companion: str | None = None, section_deadline: float = 5.0,
                 request_timeout: float = 10.0, retry: tuple[float, float] = (0.1, 2.0),
                 admit: dict[str, bytes | None] | None = None) -> None:
        """``admit``: which companions may enter (name -> trusted public key, or None to pin it on
        first sight); None admits any companion (its key is pinned on first sight)."""
        super().__init__("migration")
        self.admit = admit
        self.records = Records(state_dir)
        self.records.check_documents()
        self.seed = keys.check_name(companion, "companion") if companion else None
        self.section_deadline = section_deadline
        self.request_timeout = request_timeout
        self.retry = retry
        self.identity: Identity | None = None  # the companion living here, when inhabited
        self._outgoing: _Outgoing | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._alive: set[str] = set()  # embodiments whose liveliness token is present
        self._prepared: dict[str, Identity] = {}  # attempt -> identity parsed at prepare, for its commit
        self._alive_watch: Any = None

    # --- state seen from outside ---------------------------------------------------------------

    @property
    def inhabitant(self) -> str | None:
        """The companion living here: active, or frozen in a handshake it may still abort. Read
        from the durable record, which the handshake thread moves past its commit point at once."""
        identity = self.identity
        if identity is None:
            return None
        record = self.records.get(identity.companion)
        return identity.companion if record is not None and record.state in ("active", "prepared") else None

    def public_key(self) -> str | None:
        """The inhabitant's public key (base64), for admission lists elsewhere."""
        identity = self.identity
        record = self.records.get(identity.companion) if identity is not None else None
        return record.public_key or None if record is not None else None

    def section(self, component: str) -> Any:
        """The section ``component`` contributed to the identity living here (None if absent)."""
        return None if self.identity is None else self.identity.sections.get(component)

    # --- life cycle -----------------------------------------------------------------------------

    def attach(self, sim: Simulation) -> None:
        # Kept current by the transport's worker, so that choosing a target never blocks the loop.
        self._alive_watch = sim.transport.watch_liveliness(f"{keys.mesh_prefix(sim.mesh)}/{keys.ALIVE}/*", self._on_token)
        if self.seed is not None and self.records.get(self.seed) is None and self.records.hosting() is None:
            # First start of the companion's home: it is born here, at epoch 1.
            identity = Identity(self.seed, 1, {})
            private = signing.new_key()
            self.records.put_key(self.seed, private)
            self.records.put_document(self.seed, identity.pack())
            self.records.move(self.seed, "active", 1, public_key=signing.encode_public(signing.public_of(private)))
        for record in self.records.all():
            if record.state == "prepared":
                # Never handed: the target cannot have activated. Abort and resume here.
                self.records.move(record.companion, "active", record.epoch)
                self._send_abort_later(record)
                self._resume(record.companion, "recovered: a migration had not reached its commit point")
            elif record.state == "active":
                self._resume(record.companion, "started")
            elif record.state == "handed":
                self._spawn(f"commit-{record.companion}", self._commit_until_acked, record)
            elif record.state == "incoming":
                self._spawn(f"resolve-{record.companion}", self._resolve_incoming, record)
        if self.identity is None:
            self._minds_sleep()

    def _on_token(self, key: str, alive: bool) -> None:
        name = key.rsplit("/", 1)[-1]
        if alive:
            self._alive.add(name)
        else:
            self._alive.discard(name)

    def detach(self) -> None:
        if self._alive_watch is not None:
            self._alive_watch.close()
            self._alive_watch = None
        self._stop.set()
        for thread in self._threads:
            thread.join(10.0)
        self._threads.clear()
        identity = self.identity
        if identity is not None:
            # A clean stop keeps what the companion learnt since it arrived.
            self._refresh_sections(identity)
            self.records.put_document(identity.companion, identity.pack())

    def _spawn(self, name: str, fn: Any, *args: Any) -> None:
        thread = threading.Thread(target=fn, args=args, name=f"migration-{name}", daemon=True)
        self._threads = [t for t in self._threads if t.is_alive()]
        self._threads.append(thread)
        thread.start()

    def _post(self, fn: Any, *args: Any) -> None:
        try:
            self.sim.call(functools.partial(fn, *args))
        except MeshError:
            pass  # closing

    # --- minds and sections (loop) --------------------------------------------------------------

    def _minds(self) -> list[Any]:
        from cmion_mesh.mind import Mind

        return [c for c in self.sim.components if isinstance(c, Mind)]

    def _minds_sleep(self) -> None:
        for mind in self._minds():
            mind.sleep()

    def _refresh_sections(self, identity: Identity) -> None:
        for mind in self._minds():
            identity.sections[mind.name] = mind.state()

    def _resume(self, companion: str, why: str) -> None:
        data = self.records.document(companion)
        identity = unpack(data, name=f"{companion}.identity.xml") if data else Identity(companion, 1, {})
        record = self.records.get(companion)
        if record is not None:
            identity.epoch = record.epoch
        self._inhabit(identity, "CompanionResumed", why)

    def _inhabit(self, identity: Identity, event: str, why: str) -> None:
        self.identity = identity
        for mind in self._minds():
            state = identity.sections.get(mind.name)
            if isinstance(state, dict) and state:
                mind.restore(state)
        self.raise_event(event, {"companion": identity.companion, "epoch": identity.epoch, "why": why,
                                 "sections": sorted(identity.sections)})
        from cmion_mesh.storage import Store

        world = self.sim.components_by_name().get(keys.WORLD_MODEL)
        tree = world.tree() if isinstance(world, Store) else {}
        for mind in self._minds():
            mind.wake()
            mind.on_arrived(tree)

    # --- outgoing (source side) ---------------------------------------------------------------

    def start(self, target: str, companion: str | None = None) -> Future[Outcome]:
        """Start migrating the companion living here to ``target``; thread-safe. The future ends
        with the outcome (accepted when the target committed; rejected with the reason)."""
        future: Future[Outcome] = Future()
        self._post(self._start, Migrate(companion or self.inhabitant or "", target), future)
        return future

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
        if request.target not in self._alive:
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
        """Add ``component``'s section to the migration being packed. Thread-safe."""
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

    def _section_deadline(self, out: _Outgoing) -> None:
        if self._outgoing is out and not out.packed:
            self._abandon(out, f"components {sorted(out.waits)} did not give their sections within {self.section_deadline:g} s")

    def _abandon(self, out: _Outgoing, reason: str) -> None:
        self._outgoing = None
        self.raise_event("MigrationFailed", {"companion": out.companion, "target": out.target, "attempt": out.attempt,
                                             "reason": reason})
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
        try:
            document = Identity(out.companion, out.epoch, sections).pack()
        except (MeshError, ValueError) as exc:
            self._abandon(out, f"cannot pack the identity: {exc}")
            return
        self._spawn(f"send-{out.companion}", self._send, out, document)

    def _send(self, out: _Outgoing, document: bytes) -> None:
        self.records.put_document(out.companion, document)
        prepared = self.records.move(out.companion, "prepared", out.epoch, out.attempt, out.target)
        crash_point("source:prepared")
        private = self.records.key(out.companion) or b""
        envelope, signature = (signing.seal(private, out.companion, out.epoch, out.attempt, self.sim.embodiment, out.target, document)
                               if private else (b"", b""))
        message = MigratePrepare(out.companion, out.epoch, out.attempt, self.sim.embodiment, out.target, document,
                                 envelope, signature, private)
        key = keys.request_key(self.sim.mesh, out.target, "migration", "prepare", self.sim.embodiment)
        reply: Outcome | None = None
        unknown = ""
        for _ in range(3):  # prepare is idempotent: a lost reply may be asked again
            try:
                reply = send_request(self.sim.transport, key, message, timeout=self.request_timeout)
                break
            except OutcomeUnknown as exc:
                unknown = str(exc)
                if self._stop.wait(self.retry[0]):
                    break
        if reply is None or reply.status != "accepted":
            reason = (f"{out.target} refused: {reply.reason}" if reply is not None
                      else f"outcome unknown ({unknown}); the companion resumes here")
            self.records.move(out.companion, "active", out.epoch)
            if reply is None:
                self._send_abort_later(prepared)
            self._post(self._aborted, out, reason)
            return
        handed = self.records.move(out.companion, "handed", out.epoch, out.attempt, out.target)
        crash_point("source:handed")
        self._post(self._handed, out)
        self._commit_until_acked(handed)

    def _aborted(self, out: _Outgoing, reason: str) -> None:
        self._abandon(out, reason)
        self._resume(out.companion, f"migration to {out.target} failed")

    def _handed(self, out: _Outgoing) -> None:
        self.identity = None  # the commit point: never run the companion here again

    def _commit_until_acked(self, handed: Record) -> None:
        message = MigrateCommit(handed.companion, handed.epoch, handed.attempt, self.sim.embodiment, handed.peer)
        key = keys.request_key(self.sim.mesh, handed.peer, "migration", "commit", self.sim.embodiment)
        delay = self.retry[0]
        while not self._stop.is_set():
            try:
                reply = send_request(self.sim.transport, key, message, timeout=self.request_timeout)
                if reply.status == "accepted":
                    break
                log.error("%s refused the commit of %s (%s): retrying", handed.peer, handed.companion, reply.reason)
                self._post(self.raise_event, "MigrationStuck", {"companion": handed.companion, "target": handed.peer,
                                                                "reason": reply.reason})
            except OutcomeUnknown as exc:
                log.info("commit of %s to %s: %s; retrying", handed.companion, handed.peer, exc)
            if self._stop.wait(delay):
                return
            delay = min(self.retry[1], delay * 2)
        else:
            return
        self.records.move(handed.companion, "released", handed.epoch, handed.attempt, handed.peer)
        crash_point("source:released")
        self._post(self._released, handed)

    def _released(self, record: Record) -> None:
        out = self._outgoing
        self._outgoing = None
        data = {"companion": record.companion, "target": record.peer, "attempt": record.attempt, "epoch": record.epoch + 1}
        self.raise_event("MigrationSucceeded", data)
        if out is not None and out.attempt == record.attempt and not out.future.done():
            out.future.set_result(Outcome("accepted", "", data))

    def _send_abort_later(self, record: Record) -> None:
        def abort() -> None:
            key = keys.request_key(self.sim.mesh, record.peer, "migration", "abort", self.sim.embodiment)
            try:
                send_request(self.sim.transport, key, MigrateAbort(record.companion, record.epoch, record.attempt), timeout=2.0)
            except OutcomeUnknown:
                pass  # the target will ask us (status) and hear "aborted"

        self._spawn(f"abort-{record.companion}", abort)

    # --- incoming (target side) and queries (loop) --------------------------------------------

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        for request in batch:
            payload = request.payload
            try:
                if isinstance(payload, Migrate):
                    out = self._start(payload, _AnswerFuture(request))
                    if out is not None:  # started: the end is reported by MigrationSucceeded/Failed events
                        request.accept({"attempt": out.attempt, "companion": out.companion, "target": out.target})
                elif isinstance(payload, MigratePrepare):
                    if request.requester != payload.source:
                        request.reject(f"{request.requester!r} cannot send a prepare on behalf of {payload.source!r}")
                    else:
                        self._on_prepare(request, payload)
                elif isinstance(payload, MigrateCommit):
                    if request.requester != payload.source:
                        request.reject(f"{request.requester!r} cannot send a commit on behalf of {payload.source!r}")
                    else:
                        self._on_commit(request, payload)
                elif isinstance(payload, MigrateAbort):
                    self._on_abort(request, payload)
                elif isinstance(payload, MigrateStatus):
                    self._on_status(request, payload)
                elif isinstance(payload, Request):
                    self._on_policy(request, payload.args.get("accepts"))
            except ConfigError as exc:
                request.reject(str(exc))

    def _on_policy(self, request: IncomingRequest, accepts: Any) -> None:
        """Set the companion's own policy (``accepts``: embodiment names, or None for any); it is
        part of its identity, so it travels with it and every later host enforces it too."""
        identity = self.identity
        if identity is None:
            request.reject(f"embodiment {self.sim.embodiment!r} hosts no companion")
            return
        if accepts is None:
            identity.sections.pop(POLICY_SECTION, None)
        elif isinstance(accepts, list) and all(isinstance(a, str) for a in accepts):
            for name in accepts:
                keys.check_name(name, "accepted embodiment")
            identity.sections[POLICY_SECTION] = {"accepts": sorted(set(accepts))}
        else:
            request.reject("policy: 'accepts' must be a list of embodiment names, or null")
            return
        self._refresh_sections(identity)
        self.records.put_document(identity.companion, identity.pack())
        request.accept(identity.sections.get(POLICY_SECTION))

    def attempt_state(self, companion: str, attempt: str) -> str:
        """What this embodiment, as a source, made of ``attempt``: committed, aborted or pending."""
        record = self.records.get(companion)
        if record is None or record.attempt != attempt:
            return "aborted"
        return {"prepared": "pending", "handed": "committed", "released": "committed"}.get(record.state, "aborted")

    def _on_prepare(self, request: IncomingRequest, msg: MigratePrepare) -> None:
        me = self.sim.embodiment
        try:
            keys.check_name(msg.companion, "companion")
            keys.check_name(msg.source, "source")
            keys.check_name(msg.attempt, "attempt")
        except InvalidName as exc:
            request.reject(str(exc))
            return
        if msg.target != me:
            request.reject(f"this is {me!r}, not {msg.target!r}")
            return
        record = self.records.get(msg.companion)
        refusal = self._check_signature(msg, record)
        if refusal:
            request.reject(refusal)
            return
        held = self.records.hosting()
        if held is not None and held.companion != msg.companion:
            request.reject(f"{me!r} is occupied by companion {held.companion!r}")
            return
        if record is not None:
            if record.state == "incoming" and record.attempt == msg.attempt:
                request.accept({"state": "prepared"})  # a repeated prepare: same answer
                return
            if record.state in ("active", "prepared", "handed") and record.epoch >= msg.epoch:
                request.reject(f"stale: {me!r} holds {msg.companion!r} at epoch {record.epoch} >= {msg.epoch}")
                return
            if record.epoch > msg.epoch:
                request.reject(f"stale: {me!r} knows {msg.companion!r} at epoch {record.epoch} > {msg.epoch}")
                return
        identity = unpack(msg.document, name=f"identity of {msg.companion} from {msg.source}")
        if identity.companion != msg.companion or identity.epoch != msg.epoch:
            request.reject(f"document is for {identity.companion!r} at epoch {identity.epoch}, "
                           f"not {msg.companion!r} at epoch {msg.epoch}")
            return
        refused_by = refuses(identity, me)
        if refused_by:
            request.reject(refused_by)
            return
        self._prepared = {msg.attempt: identity}  # one handshake at a time: parsing it again at commit is waste
        self.records.put_key(msg.companion, msg.companion_key)
        self.records.put_document(msg.companion, msg.document)
        public = signing.encode_public(signing.public_of(msg.companion_key))
        incoming = self.records.move(msg.companion, "incoming", msg.epoch, msg.attempt, msg.source, public_key=public)
        crash_point("target:incoming")
        request.accept({"state": "prepared"})
        # The commit (or abort) normally follows at once. If the link fails now, the source's one
        # abort may be lost for good: once overdue, ask the source, as after a restart.
        self._spawn(f"resolve-{msg.companion}", self._resolve_incoming, incoming, self.retry[1])

    def _check_signature(self, msg: MigratePrepare, record: Record | None) -> str:
        """Why this prepare is refused before its XML is read ("" when the envelope holds)."""
        if self.admit is not None and msg.companion not in self.admit:
            return f"admission: companion {msg.companion!r} may not enter {self.sim.embodiment!r}"
        trusted = self.admit.get(msg.companion) if self.admit is not None else None
        if trusted is None and record is not None and record.public_key:
            trusted = signing.decode_public(record.public_key)  # pinned when first seen
        if not msg.envelope or not msg.signature:
            return f"refused: the identity of {msg.companion!r} is not signed"
        expected = signing.Envelope(msg.companion, msg.epoch, msg.attempt, msg.source, msg.target, b"", b"")
        try:
            envelope = signing.verify(msg.envelope, msg.signature, expected=expected, document=msg.document, trusted_key=trusted)
            if len(msg.companion_key) != 32 or signing.public_of(msg.companion_key) != envelope.public_key:
                return "refused: the companion's key does not match its signature"
        except signing.SignatureRefused as exc:
            return f"refused: {exc}"
        return ""

    def _on_commit(self, request: IncomingRequest, msg: MigrateCommit) -> None:
        record = self.records.get(msg.companion)
        if record is not None and record.peer != msg.source:
            request.reject(f"{msg.source!r} is not the source of {msg.companion!r}'s migration here")
            return
        if record is not None and record.state == "active" and record.attempt == msg.attempt:
            request.accept({"state": "committed"})
            return
        if record is None or record.state != "incoming" or record.attempt != msg.attempt:
            request.reject(f"no incoming migration {msg.attempt} of {msg.companion!r} here")
            return
        self._activate(record)
        request.accept({"state": "committed"})

    def _activate(self, incoming: Record) -> None:
        active = self.records.move(incoming.companion, "active", incoming.epoch + 1, incoming.attempt, incoming.peer)
        crash_point("target:active")
        identity = self._prepared.pop(incoming.attempt, None)
        if identity is None:  # restarted since the prepare: the stored document is the truth
            data = self.records.document(incoming.companion)
            identity = unpack(data or b"", name=f"{incoming.companion}.identity.xml")
        identity.epoch = active.epoch
        self._inhabit(identity, "MigrationOccurred", f"arrived from {incoming.peer}")

    def _on_abort(self, request: IncomingRequest, msg: MigrateAbort) -> None:
        record = self.records.get(msg.companion)
        if record is not None and record.state == "incoming" and record.attempt == msg.attempt:
            if record.peer != request.requester:
                request.reject(f"only {record.peer!r}, the source of attempt {msg.attempt}, may abort it")
                return
            self.records.move(msg.companion, "dropped", record.epoch, record.attempt, record.peer)
        request.accept()

    def _on_status(self, request: IncomingRequest, msg: MigrateStatus) -> None:
        record = self.records.get(msg.companion)
        if record is not None and record.attempt == msg.attempt and record.peer != request.requester:
            request.reject(f"attempt {msg.attempt} is not {request.requester!r}'s to ask about")
            return
        request.accept({"state": self.attempt_state(msg.companion, msg.attempt)})

    def _resolve_incoming(self, record: Record, overdue: float = 0.0) -> None:
        """Ask the source until it says committed or aborted: after a restart in ``incoming``, and
        ``overdue`` seconds after a prepare if neither a commit nor an abort has come by then."""
        if overdue and self._stop.wait(overdue):
            return
        key = keys.request_key(self.sim.mesh, record.peer, "migration", "status", self.sim.embodiment)
        delay = self.retry[0]
        while not self._stop.is_set():
            current = self.records.get(record.companion)
            if current is None or current.state != "incoming" or current.attempt != record.attempt:
                return  # a commit or abort arrived meanwhile
            try:
                reply = send_request(self.sim.transport, key, MigrateStatus(record.companion, record.attempt),
                                     timeout=self.request_timeout)
                state = reply.value.get("state") if isinstance(reply.value, dict) else None
                if state in ("committed", "aborted"):
                    self._post(self._settle_incoming, record, state)
                    return
            except OutcomeUnknown as exc:
                log.info("asking %s about %s: %s", record.peer, record.attempt, exc)
            if self._stop.wait(delay):
                return
            delay = min(self.retry[1] * 2, delay * 2)

    def _settle_incoming(self, record: Record, state: str) -> None:
        current = self.records.get(record.companion)
        if current is None or current.state != "incoming" or current.attempt != record.attempt:
            return
        if state == "committed":
            self._activate(current)
        else:
            self.records.move(record.companion, "dropped", record.epoch, record.attempt, record.peer)
            self.raise_event("MigrationDropped", {"companion": record.companion, "attempt": record.attempt,
                                                  "source": record.peer})


POLICY_SECTION = "policy"


def refuses(identity: Identity, embodiment: str) -> str:
    """Why the companion itself refuses ``embodiment`` ("" if it accepts it).

    A companion's identity may hold a ``policy`` section ``{"accepts": [embodiment names]}``."""
    policy = identity.sections.get(POLICY_SECTION)
    accepts = policy.get("accepts") if isinstance(policy, dict) else None
    if isinstance(accepts, list) and embodiment not in accepts:
        return f"companion {identity.companion!r} does not accept embodiment {embodiment!r} (its policy: {accepts})"
    return ""


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

    Parameter ``target``. Succeeds once the target has committed; cannot be cancelled once the
    handshake has started (the companion must end up in exactly one place).
    """

    type = "Migration"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        manager = self.sim.component("migration")
        assert isinstance(manager, MigrationManager)
        target = str(parameters.get("target", ""))
        outcome = manager.start(target).result(timeout=None)
        if outcome.status != "accepted":
            return ctx.fail(outcome.reason)
        return True
