"""The migration handshake's decisions: pure functions from a durable record and a message to the
next record and the answer. ``manager.MigrationManager`` runs them on real transports and disks;
``tests/test_handshake_simulation.py`` runs the same functions through random schedules.

The model (S the source, holder of the companion at epoch e; T the target)::

    S active(e, seq s)
      prepared(e, s+1, A) --- prepare(chain, offer signed by S's key) --->  T checks, stores the document,
                                                                            makes a fresh custody key pair,
                          <--- prepared(T's public custody key) --------  incoming(e, s+1, A)
      handed(A, link)      (commit point: the link hands custody at e+1 to T's key, signed by S's key)
                          --- commit(link), until answered ------------->  active(e+1): the chain grows by the link
                          <--- committed ------------------------------
      released(A)

**Invariant: attempts only move forward.** Attempts of a companion are totally ordered by
``(epoch, seq)``: only the holder at epoch e makes attempts of epoch e, numbering them from its
durable record. A record accepts a message only for the attempt it is in, or -- a prepare -- for
a strictly newer attempt, and only when it is in no handshake and not holding the companion
(``active``, ``prepared``, ``handed``: a host never accepts a prepare for a companion it holds; an
``incoming`` record refuses every other attempt without being touched). ``dropped`` and
``released`` records keep their attempt's order, so an attempt that ended is never resurrected,
across restarts. The replay case: T dropped attempt (e, 1); S, active again, sends (e, 2); a
replayed prepare of (e, 1), before or after, is refused as not newer, and a replayed commit of
(e, 1) names an attempt T is not in. Nothing a network can duplicate, delay or replay moves a
record backwards.

**Safety** (never two hosts): T becomes active only with a commit link signed by S's custody key
for the attempt T holds ``incoming``, which S signs only after recording ``handed``; from
``handed`` S never runs the companion again *unless T says the attempt is dropped*, which T says
only from a durable record that can no longer become active for that attempt (it is ``dropped``,
or it never held the attempt: a later prepare of it makes a new custody key, which the link S
signed does not name). **Liveness**: every undecided state has a peer to ask: S ``prepared``
after a restart aborts and resumes; S ``handed`` sends the commit until it is answered, and when
it is refused asks T (``status of=target``): committed -> released; dropped -> resume; incoming ->
abort it, then ask again. T ``incoming`` asks S (``status of=source``) once the commit is overdue
or after a restart: committed (with the link) -> active; aborted -> dropped. A timeout, an empty
reply or an error is "outcome unknown": asked again, never taken for success, and nothing is
taken over because a peer went quiet.

**An incoming attempt ends** (``expire_incoming``): T drops an attempt that S has neither
committed nor aborted within ``INCOMING_BOUND`` seconds of the prepare's durable record, whether
S is alive or not; the bound counts from the time the record keeps (``Record.since``), so a
restart does not reset it. Giving up takes nothing over, and the argument above holds: T drops
only from ``incoming``, so it has not been told committed (a commit makes it ``active``, never
dropped), and the ``dropped`` record is written before T answers anything about it. S at
``prepared`` has signed no link: it resumes on its own, or once T's answer comes (a repeated
prepare is refused as stale). S at ``handed`` keeps the companion frozen until T answers: its
commit, arriving after the drop, is refused (T holds no incoming attempt), it asks T, is told
``dropped``, and resumes, the one host. The dropped record keeps the attempt's order, so neither
that commit nor a replayed prepare of the attempt ever revives it.

**Durable points, and what may overlap them.** Each durable step is one entry appended to the
ledger and synced (``ledger``, ``journal``): on the critical path in sequence are T ``incoming``
(after T has synced the sections and document it names), S ``handed`` (the commit point) and T
``active`` (before the companion wakes there: a T running it on a record still ``incoming`` could
be told to drop it). S's ``prepared`` is written beside the transfer (the ``have``, the sections
and the prepare itself), not before it; S acts on the prepare's answer only once ``prepared`` is
durable, so ``handed`` still comes after it. A crash before ``prepared`` is durable leaves S ``active`` at the order
before the attempt; S holds no record of the attempt, so asked about it (``on_status``) it answers
``aborted`` and T drops it, and S never signed a link for it. S's next attempt may then carry the
same order as the one T dropped or still holds: T refuses it (not newer, or busy), S resumes and
records that order, and its following attempt is newer. Nothing moves a record backwards, and T
still activates only with a link S signed after recording ``handed``.

Custody (``custody``) makes the same decisions unforgeable by a former host: see its docstring.
Claims of other holders count only once backed (``Claim``: a verified chain and a signature by its
head's key): a target refuses an offer that a claim shows stale or forked (``check_claims``); a
holder stands down for good when a claim extends its chain, and freezes on a proven fork
(``judge``). A record's state, epoch and holder must agree with its chain at rest (``at_rest``).
The one step that moves an order back is an operator's: a holder of a branch of a proven fork that
stands down (``retired``) records the kept branch's chain and order; the orders of the other
branch mean nothing on this one, and its offers are refused as forks of the chain recorded.

**Sections.** A SchemaVersion 2 document is a manifest naming its sections by hash (``identity``);
T must hold every section before it records ``incoming``. Before the prepare of a large identity,
S sends ``have`` (the manifest with the same chain and offer; T checks custody exactly as for a
prepare and records nothing) and T answers which sections it holds already; S sends the others
(``migrate_sections``, or small ones inside the prepare). A prepare whose sections T lacks is
refused ``missing_sections`` without any record written, so it changes nothing above: S sends them
and prepares again, the same attempt.
"""

from __future__ import annotations

import base64
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, InvalidName, MeshError
from cmion_mesh.messages import Code, MigrateAbort, MigrateCommit, MigrateHave, MigratePrepare, MigrateStatus, Outcome
from cmion_mesh.migration import custody, signing
from cmion_mesh.migration.custody import Link, Offer
from cmion_mesh.migration.identity import Bytes, Identity, Manifest, MissingSections, SectionRef, read_manifest
from cmion_mesh.migration.ledger import Record

POLICY_SECTION = "policy"
#: Seconds T keeps an attempt ``incoming`` that its source has neither committed nor aborted,
#: counted from the prepare's durable record: then T drops it (``expire_incoming``).
INCOMING_BOUND = 60.0


class Decision(msgspec.Struct, frozen=True):
    """What to write (key first, then the document and the record) and what to answer."""

    outcome: Outcome
    record: Record | None = None
    document: bytes | None = None
    key: bytes | None = None
    identity: Identity | None = None  # the parsed document of an accepted prepare
    manifest: Manifest | None = None  # the parsed document of an accepted prepare or have
    sections: Mapping[str, Bytes] | None = None  # an accepted prepare's section bytes (sha256 -> bytes)
    fork: custody.Fork | None = None  # a refusal's proof of equivocation, for the log and the operator


class Claim(msgspec.Struct, frozen=True):
    """Another embodiment's claim on a companion, backed: its chain verified and ends with ``holder``,
    who signed the asker's nonce with that link's key (``custody.verify_claim``). A liveliness token
    alone is never one."""

    holder: str
    chain: Sequence[Link]

    @property
    def epoch(self) -> int:
        return self.chain[-1].epoch


#: Finds the bytes of sections (sha256 -> bytes, each checked against its hash), those it can.
SectionSource = Callable[[Sequence[SectionRef]], Mapping[str, Bytes]]


def refused(reason: str, fork: custody.Fork | None = None) -> Decision:
    return Decision(Outcome("rejected", reason), fork=fork)


def refuses(identity: Identity, embodiment: str) -> str:
    """Why the companion itself refuses ``embodiment`` ("" if it accepts it).

    A companion's identity may hold a ``policy`` section ``{"accepts": [embodiment names]}``."""
    policy = identity.sections.get(POLICY_SECTION)
    accepts = policy.get("accepts") if isinstance(policy, dict) else None
    if isinstance(accepts, list) and embodiment not in accepts:
        return f"companion {identity.companion!r} does not accept embodiment {embodiment!r} (its policy: {accepts})"
    return ""


def link_text(link: Link) -> str:
    """A link as plain data (base64 text), for an answer's value."""
    return base64.b64encode(custody.encode_link(link)).decode()


def link_of_text(text: Any) -> Link:
    try:
        raw = base64.b64decode(str(text), validate=True)
    except ValueError as exc:
        raise signing.SignatureRefused(f"malformed custody link: {exc}") from None
    return custody.decode_link(raw)


# --- target side --------------------------------------------------------------------------------------


def on_prepare(msg: MigratePrepare, record: Record | None, *, me: str, held: Record | None,
               admit: Mapping[str, bytes | None] | None, claims: Sequence[Claim],
               new_key: Callable[[], bytes] = signing.new_key, sections: SectionSource | None = None,
               values: Mapping[str, Any] | None = None) -> Decision:
    """A prepare at T. ``held``: the record of a companion T holds, if any; ``claims``: the other
    embodiments' backed claims on the companion (never bare custody tokens);
    ``sections``: where T finds the bytes of the sections a version 2 document names; ``values``:
    immutable values T holds already decoded, by their bytes' hash (``identity.SectionMemo.values``)."""
    checked = _check_offer(msg, msg.document, record, me=me, held=held, admit=admit, claims=claims)
    if isinstance(checked, Decision):
        return checked
    if _repeated(msg, record):
        assert record is not None
        return Decision(Outcome("accepted", "", {"state": "prepared", "custody_key": record.custody_key}))
    chain = checked
    try:
        manifest = read_manifest(msg.document, name=f"identity of {msg.companion} from {msg.source}")
        found = sections(manifest.refs) if sections is not None and manifest.refs else {}
        identity = manifest.identity(found, values)
    except MissingSections as exc:
        missing = sorted({ref.sha256 for ref in exc.missing})
        return Decision(Outcome("rejected", f"{me!r} lacks {len(missing)} section(s) of {msg.companion!r}: {exc.detail}",
                                {"missing": missing}, Code.MISSING_SECTIONS))
    except ConfigError as exc:
        return refused(str(exc))
    if identity.companion != msg.companion or identity.epoch != msg.epoch:
        return refused(f"document is for {identity.companion!r} at epoch {identity.epoch}, not {msg.companion!r} at epoch {msg.epoch}")
    policy = refuses(identity, me)
    if policy:
        return refused(policy)
    private = new_key()
    public = signing.encode_public(signing.public_of(private))
    incoming = Record(msg.companion, "incoming", msg.epoch, msg.attempt, msg.source, seq=msg.seq, chain=chain,
                      custody_key=public, public_key=record.public_key if record is not None else "")
    return Decision(Outcome("accepted", "", {"state": "prepared", "custody_key": public}), incoming, msg.document, private,
                    identity, manifest, {ref.sha256: found[ref.sha256] for ref in manifest.refs})


def on_have(msg: MigrateHave, record: Record | None, *, me: str, held: Record | None,
            admit: Mapping[str, bytes | None] | None, claims: Sequence[Claim]) -> Decision:
    """A ``have`` at T: the checks of a prepare of the same offer, nothing recorded. Accepted, the
    decision carries the manifest; which sections T holds is for the caller to say (its disk)."""
    checked = _check_offer(msg, msg.manifest, record, me=me, held=held, admit=admit, claims=claims)
    if isinstance(checked, Decision):
        return checked
    try:
        manifest = read_manifest(msg.manifest, name=f"identity of {msg.companion} from {msg.source}")
    except ConfigError as exc:
        return refused(str(exc))
    if manifest.schema_version < 2:
        return refused(f"have takes a SchemaVersion 2 manifest; this one is SchemaVersion {manifest.schema_version}")
    if manifest.companion != msg.companion or manifest.epoch != msg.epoch:
        return refused(f"document is for {manifest.companion!r} at epoch {manifest.epoch}, not {msg.companion!r} at epoch {msg.epoch}")
    return Decision(Outcome("accepted"), manifest=manifest)


def _repeated(msg: MigratePrepare | MigrateHave, record: Record | None) -> bool:
    """Whether ``record`` is T ``incoming`` for the very attempt ``msg`` offers (a repeated message)."""
    return record is not None and record.state == "incoming" and record.attempt == msg.attempt \
        and record.order == (msg.epoch, msg.seq)


def precheck(msg: MigratePrepare | MigrateHave, record: Record | None, *, me: str, held: Record | None,
             admit: Mapping[str, bytes | None] | None) -> Decision | None:
    """The checks of an offer that cost nothing (names, target, admission, the records here): the
    refusal, or None. A stale or misdirected offer, replayed in a flood, is refused by these alone."""
    try:
        keys.check_name(msg.companion, "companion")
        keys.check_name(msg.source, "source")
        keys.check_name(msg.attempt, "attempt")
    except InvalidName as exc:
        return refused(str(exc))
    if msg.target != me:
        return refused(f"this is {me!r}, not {msg.target!r}")
    if admit is not None and msg.companion not in admit:
        return refused(f"admission: companion {msg.companion!r} may not enter {me!r}")
    attempt = (msg.epoch, msg.seq)
    if _repeated(msg, record):
        return None
    if record is not None:
        if record.state in ("active", "prepared", "handed"):
            return refused(f"custody: {me!r} holds {msg.companion!r} itself (epoch {record.epoch}); "
                           "a host never accepts a prepare for a companion it holds")
        if record.state == "incoming":
            return refused(f"busy: {me!r} is in migration {record.attempt} of {msg.companion!r} from {record.peer!r}, "
                           "not yet decided")
        if attempt <= record.order:
            return refused(f"stale: attempt {msg.attempt} ({msg.epoch}.{msg.seq}) of {msg.companion!r} is not newer than "
                           f"{record.epoch}.{record.seq}, {record.state} here")
    if held is not None and held.companion != msg.companion:
        return refused(f"{me!r} is occupied by companion {held.companion!r}")
    return None


def _check_offer(msg: MigratePrepare | MigrateHave, document: bytes, record: Record | None, *, me: str, held: Record | None,
                 admit: Mapping[str, bytes | None] | None, claims: Sequence[Claim]) -> list[Link] | Decision:
    """The checks of an offer that need no XML: ``precheck``, then custody. The verified chain, or the refusal."""
    early = precheck(msg, record, me=me, held=held, admit=admit)
    if early is not None:
        return early
    if _repeated(msg, record):
        assert record is not None
        return list(record.chain)  # checked when it was first offered; the answer is the same
    trusted = admit.get(msg.companion) if admit is not None else None
    if trusted is None and record is not None and record.public_key:
        trusted = signing.decode_public(record.public_key)
    try:
        chain = custody.decode_chain(msg.chain)
        custody.verify_chain(chain, msg.companion, identity=trusted)
        if record is not None and record.chain:
            relation, fork = custody.compare(record.chain, chain)
            if fork is not None:
                return refused(f"custody: the chain offered forks from the one known here: {fork.describe()}", fork)
            if relation == "stale":
                return refused(f"custody: stale: the chain of custody here reaches epoch {record.chain[-1].epoch}, "
                               f"the offer only {chain[-1].epoch}")
        why, fork = check_claims(chain, claims, source=msg.source)
        if why:
            return refused(why, fork)
        digest = custody.digest(document)
        custody.verify_offer(chain, Offer(msg.companion, msg.epoch, msg.seq, msg.attempt, msg.source, msg.target, digest), msg.proof)
    except signing.SignatureRefused as exc:
        return refused(f"refused: {exc}")
    return chain


def check_claims(chain: Sequence[Link], claims: Sequence[Claim], *, source: str) -> tuple[str, custody.Fork | None]:
    """Why a backed claim forbids taking ``chain`` (offered by ``source``): its holder holds a newer
    chain that extends it (the source handed the companion on), a chain that forks from it (proof of
    equivocation), or another companion of the same name; ("", None) if none does. A claim whose
    chain the offer extends is a former holder's, not yet withdrawn: no objection."""
    companion = chain[-1].companion
    for claim in claims:
        relation, fork = custody.compare(chain, claim.chain)
        if fork is not None:
            return (f"custody: {claim.holder!r} holds {companion!r} on a branch that forks from the chain offered by "
                    f"{source!r}: {fork.describe()} (equivocation)"), fork
        if relation == "behind":
            return (f"custody: {claim.holder!r} holds {companion!r} at epoch {claim.epoch}, newer than the offer's "
                    f"epoch {chain[-1].epoch}: {source!r} handed it on"), None
        if relation == "foreign":
            return (f"custody: {claim.holder!r} holds another companion named {companion!r} (another identity key): "
                    "admit the one to trust here (--admit NAME=KEY)"), None
    return "", None


# --- a holder and the others' claims ---------------------------------------------------------------------


class Verdict(msgspec.Struct, frozen=True):
    """What backed claims mean for a holder: branches that fork from its chain (each claimant with
    the proof), or a claim whose chain extends its own (its key signed the next link: it handed the
    companion on, and runs it no more)."""

    forks: tuple[tuple[Claim, custody.Fork], ...] = ()
    superseded_by: Claim | None = None


def judge(record: Record, claims: Sequence[Claim]) -> Verdict:
    """A holder's verdict on the others' backed claims. Epochs and names count for nothing: a stale
    claim (a prefix of this chain) is no conflict, a fork is one that no branch wins by itself."""
    forks: list[tuple[Claim, custody.Fork]] = []
    superseded: Claim | None = None
    for claim in claims:
        relation, fork = custody.compare(record.chain, claim.chain)
        if fork is not None:
            forks.append((claim, fork))
        elif relation == "behind" and superseded is None:
            superseded = claim
    return Verdict(tuple(forks), superseded)


def superseded(record: Record, claim: Claim) -> Record:
    """The record of a holder whose key signed the link past its head that ``claim``'s chain holds (a
    state folder rolled back, a target that said it dropped an attempt it kept): ``released`` by that
    link, as if it had recorded the hand-over itself."""
    link = claim.chain[len(record.chain)]
    return msgspec.structs.replace(record, state="released", attempt=link.attempt, peer=link.holder, link=link,
                                   custody_key="")


def retired(record: Record, kept: Sequence[Link]) -> Record:
    """A holder of a branch of a proven fork, standing down for the branch an operator keeps
    (``kept``, verified): ``dropped``, knowing the kept chain, so that offers of its own branch are
    refused as forks and the keeper's next attempt is newer."""
    head = kept[-1]
    return msgspec.structs.replace(record, state="dropped", epoch=head.epoch, seq=0, attempt="", peer=head.holder,
                                   chain=list(kept), link=None, custody_key="")


def at_rest(record: Record, *, me: str, key: bytes | None) -> str:
    """Why ``record``, as stored, is not backed by its chain of custody ("" if it is). ``key``: the
    custody private key stored beside it. Active, prepared, handed: the chain ends with ``me`` at the
    record's epoch and ``key`` is that link's key; handed and released: the link it signed extends
    the chain by one, to the record's peer and attempt; incoming: the chain ends with the source at
    the record's epoch and ``key`` is the one made for the attempt; dropped: the epoch is the chain's."""
    if not record.chain:
        return "" if record.state in ("released", "dropped") else f"its {record.state} record holds no chain of custody"
    try:
        identity = signing.decode_public(record.public_key) if record.public_key else None
        custody.verify_chain(record.chain, record.companion, identity=identity)
    except MeshError as exc:
        return f"its chain of custody does not verify: {exc}"
    head = record.chain[-1]
    if head.epoch != record.epoch:
        return f"the record says epoch {record.epoch}, its chain of custody ends at epoch {head.epoch}"
    if record.state in ("active", "prepared", "handed", "released") and head.holder != me:
        return f"its chain of custody says {head.holder!r} held it at epoch {head.epoch}, not {me!r}"
    if record.state == "incoming" and head.holder != record.peer:
        return f"its chain of custody ends with {head.holder!r}, not with the source {record.peer!r}"
    if record.state in ("active", "prepared", "handed", "incoming"):
        expected = head.public_key if record.state != "incoming" else None
        try:
            public = signing.public_of(key) if key is not None else None
            if record.state == "incoming":
                expected = signing.decode_public(record.custody_key)
        except (ValueError, MeshError):
            return "its custody key is unusable"
        if public is None:
            return "its custody key is missing"
        if public != expected:
            return f"its custody key is not the one its chain of custody names for epoch {head.epoch}" \
                if record.state != "incoming" else "its custody key is not the one it gave for the attempt"
    if record.state in ("handed", "released"):
        link = record.link
        if link is None:
            return f"a {record.state} record without the link it signed"
        try:
            custody.check_link(head, link, companion=record.companion, attempt=record.attempt, holder=record.peer,
                               public_key=link.public_key, document_sha256=link.document_sha256)
        except MeshError as exc:
            return f"the link it signed does not extend its chain of custody: {exc}"
    return ""


def _activation(record: Record, link: Link, me: str) -> Record:
    """The active record of T once ``link`` proves S handed ``record``'s attempt to T (raises SignatureRefused)."""
    custody.check_link(record.chain[-1], link, companion=record.companion, attempt=record.attempt, holder=me,
                       public_key=signing.decode_public(record.custody_key), document_sha256=bytes.fromhex(record.document))
    chain = [*record.chain, link]
    # The identity key is pinned here, at the commit, never at a prepare that may still be aborted.
    return msgspec.structs.replace(record, state="active", epoch=link.epoch, seq=0, chain=chain, custody_key="", since=0.0,
                                   public_key=signing.encode_public(custody.identity_key(chain)))


def on_commit(msg: MigrateCommit, record: Record | None, *, me: str) -> Decision:
    if record is not None and record.peer != msg.source:
        return refused(f"{msg.source!r} is not the source of {msg.companion!r}'s migration here")
    if record is not None and record.state == "active" and record.attempt == msg.attempt:
        return Decision(Outcome("accepted", "", {"state": "committed"}))
    if record is None or record.state != "incoming" or record.attempt != msg.attempt or record.epoch != msg.epoch:
        return refused(f"no incoming migration {msg.attempt} of {msg.companion!r} here")
    try:
        active = _activation(record, custody.decode_link(msg.link), me)
    except signing.SignatureRefused as exc:
        return refused(f"refused: {exc}")
    return Decision(Outcome("accepted", "", {"state": "committed"}), active)


def on_abort(msg: MigrateAbort, record: Record | None, *, requester: str) -> Decision:
    if record is not None and record.state == "incoming" and record.attempt == msg.attempt:
        if record.peer != requester:
            return refused(f"only {record.peer!r}, the source of attempt {msg.attempt}, may abort it")
        return Decision(Outcome("accepted", "", {"state": "dropped"}), dropped(record))
    return Decision(Outcome("accepted", "", {"state": "dropped"}))


def dropped(record: Record) -> Record:
    """T's record of an attempt that ended without a commit. Its order stays (never resurrected); the
    chain it offered stays only if it extends custody pinned here before: an aborted offer teaches nothing."""
    return msgspec.structs.replace(record, state="dropped", custody_key="", since=0.0,
                                   chain=record.chain if record.public_key else [])


def on_status(msg: MigrateStatus, record: Record | None, *, requester: str) -> Decision:
    """What this embodiment made of an attempt, as its source (``of="source"``) or its target."""
    if record is not None and record.attempt == msg.attempt and record.peer != requester:
        return refused(f"attempt {msg.attempt} is not {requester!r}'s to ask about")
    ours = record is not None and record.attempt == msg.attempt
    if msg.of == "source":
        if ours and record is not None and record.state == "prepared":
            return Decision(Outcome("accepted", "", {"state": "pending"}))
        if ours and record is not None and record.state in ("handed", "released") and record.link is not None:
            return Decision(Outcome("accepted", "", {"state": "committed", "link": link_text(record.link)}))
        return Decision(Outcome("accepted", "", {"state": "aborted"}))
    if ours and record is not None and record.state == "incoming":
        return Decision(Outcome("accepted", "", {"state": "incoming"}))
    if record is not None and ((ours and record.state != "dropped") or record.epoch > msg.epoch):
        return Decision(Outcome("accepted", "", {"state": "committed"}))
    return Decision(Outcome("accepted", "", {"state": "dropped"}))


def incoming_deadline(record: Record, bound: float) -> float:
    """When T gives up ``record``'s attempt if it is still undecided (seconds since the epoch): ``bound``
    after its prepare was recorded (a record written before ``since`` existed: after its last write)."""
    return (record.since or record.updated) + bound


def expire_incoming(record: Record, *, now: float, bound: float = INCOMING_BOUND) -> Record | None:
    """T ``incoming`` at ``now``: the dropped record once ``bound`` seconds have passed since the
    prepare was recorded, else None (the commit, the abort or the source's answer may still come)."""
    if record.state != "incoming" or now < incoming_deadline(record, bound):
        return None
    return dropped(record)


def settle_incoming(record: Record, answer: Any, *, me: str) -> Record | None:
    """T ``incoming``, told by S what became of the attempt: the next record, or None to ask again."""
    state = answer.get("state") if isinstance(answer, dict) else None
    if state == "aborted":
        return dropped(record)
    if state == "committed":
        try:
            return _activation(record, link_of_text(answer.get("link", "")), me)
        except signing.SignatureRefused:
            return None  # not a link that proves the hand-over: ask again, never take it over
    return None


# --- source side ------------------------------------------------------------------------------------


def offer(record: Record, *, attempt: str, me: str, target: str, document: bytes, private: bytes) -> tuple[Record, MigratePrepare]:
    """S, active: the ``prepared`` record of a new attempt and its prepare."""
    seq = record.seq + 1
    digest = custody.digest(document)
    proof = custody.sign_offer(private, Offer(record.companion, record.epoch, seq, attempt, me, target, digest))
    prepared = msgspec.structs.replace(record, state="prepared", seq=seq, attempt=attempt, peer=target, link=None)
    message = MigratePrepare(record.companion, record.epoch, seq, attempt, me, target, document,
                             custody.encode_chain(record.chain), proof)
    return prepared, message


def have(prepare: MigratePrepare) -> MigrateHave:
    """The ``have`` that goes before ``prepare``: the same offer, its document as the manifest."""
    return MigrateHave(prepare.companion, prepare.epoch, prepare.seq, prepare.attempt, prepare.source, prepare.target,
                       prepare.document, prepare.chain, prepare.proof)


Next = Literal["commit", "resume", "released", "abort", "ask", "retry"]


def after_prepare(prepared: Record, outcome: Outcome, *, private: bytes, document: bytes) -> Record:
    """S ``prepared``, answered: ``handed`` with the link when T prepared, else ``active`` again."""
    value = outcome.value if isinstance(outcome.value, dict) else {}
    if outcome.status == "accepted":
        try:
            public = signing.decode_public(str(value.get("custody_key", "")))
        except Exception:
            public = b""
        if public:
            link = custody.hand_on(private, prepared.companion, prepared.epoch + 1, prepared.peer, public, prepared.attempt,
                                   custody.digest(document))
            return msgspec.structs.replace(prepared, state="handed", link=link)
    return resume(prepared)


def resume(record: Record) -> Record:
    """S takes the companion back at the same epoch; the attempt's order stays, so the next is newer."""
    return msgspec.structs.replace(record, state="active", attempt="", peer="", link=None)


def after_refused_commit(handed: Record, answer: Any) -> tuple[Next, Record | None]:
    """S ``handed`` whose commit was refused, told by T (``status of=target``) where it stands."""
    state = answer.get("state") if isinstance(answer, dict) else None
    if state == "committed":
        return "released", msgspec.structs.replace(handed, state="released")
    if state == "dropped":
        return "resume", resume(handed)
    if state == "incoming":
        return "abort", None
    return "retry", None
