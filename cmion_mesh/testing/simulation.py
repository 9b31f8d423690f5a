"""Simulation testing of the migration handshake, FoundationDB style.

Three embodiments run the real decisions of ``cmion_mesh.migration.handshake`` (the same functions
``MigrationManager`` calls) over a simulated network driven by one seeded random generator. Any
message ever sent may be delivered late, lost, duplicated, reordered or **replayed later**; any
embodiment may crash (losing everything but its durable record, document and key) and restart at
any step; a waiting request may time out while its message is still in flight; a target may give
up an incoming attempt at any point (its bound passed: ``handshake.expire_incoming``); the mesh may split
in two and join again (who sees whose custody claims); and one embodiment turns hostile once it has
held the companion: it keeps every custody key it had, declares bare custody tokens (at any epoch,
or with a chain that does not back them), signs forks of the chain offline (to itself, epochs
inflated), claims them, and offers them (prepares and commits) to the others.

Claims count only when backed (``handshake.Claim``: here, ``custody.verify_claim`` on what the
claimant can show), as in ``MigrationManager``: a target decides with the backed claims it sees, and
after every step each holder judges the backed claims it sees (``handshake.judge``: it stands
down when one extends its chain, freezes on a proven fork). After every step: no two embodiments
run the companion (``active`` or ``prepared``, not frozen) unless they cannot see each other and one
of them runs a forged branch (accepted across the split); a forged branch never runs where a
holder of another branch is seen; every frozen embodiment holds a proof of equivocation that
verifies, names the hostile one, and includes a forged link (a bare token freezes nobody); and no
record ever moves to an attempt that is not newer than every one it held. When the faults stop,
the split heals and the hostile one is revoked (its tokens gone), everything is delivered, then an
operator keeps the true branch (``handshake.retired`` for the others): exactly one host, not
frozen, its chain free of forged links, its identity byte-identical to the one born.

``python -m bench sim --schedules 1000000`` (or ``python -m cmion_mesh.testing.simulation``) runs many; a
failing seed prints the trace that replays it (``--seed N --trace``).
"""

from __future__ import annotations

import random
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgspec

from cmion_mesh.messages import MigrateAbort, MigrateCommit, MigratePrepare, MigrateStatus, Outcome
from cmion_mesh.migration import custody, handshake, signing
from cmion_mesh.migration.custody import Fork, Link
from cmion_mesh.migration.handshake import Claim
from cmion_mesh.migration.identity import Identity, unpack
from cmion_mesh.migration.ledger import Record

COMPANION = "spirit"
SECTIONS: dict[str, Any] = {"mind": {"memory": ["met Ada", "kitchen"]}, "face": {"smile": 0.7}}
NAMES = ("a", "b", "c")
HOSTILE = "c"


class InvariantBroken(AssertionError):
    pass


@dataclass
class Message:
    mid: int
    src: str
    dst: str
    op: str
    payload: Any
    reply_to: int = 0  # the op waiting for the answer (0: nobody)
    is_reply: bool = False
    request: int = 0  # a reply: the request it answers


@dataclass
class Op:
    """A handshake thread: ``kind`` source (prepare/commit/status/abort stages) or resolve (target),
    or a target's timer: ``expire`` drops its incoming attempt when it fires (``time_out``)."""

    oid: int
    kind: str
    stage: str
    record: Record
    document: bytes = b""
    message: Any = None
    tries: int = 0
    awaiting: int = 0  # the request whose answer it waits for: answers to others are not its own


@dataclass
class Node:
    name: str
    record: Record | None = None
    documents: dict[str, bytes] = field(default_factory=dict)
    key: bytes | None = None
    ops: dict[int, Op] = field(default_factory=dict)
    orders: tuple[int, int] = (0, 0)  # the newest attempt order any of its records has held
    kept: list[tuple[list[Link], bytes]] = field(default_factory=list)  # a hostile one keeps its custody keys
    frozen: Fork | None = None  # the proof of a fork that freezes it
    backups: list[tuple[Record, dict[str, bytes], bytes | None]] = field(default_factory=list)  # its state folder, as it was
    rolled: bool = False  # runs from a backup of its state folder, restored (until it takes part in a handshake again)
    stale: bool = False  # prepared, and a claim extends its chain: it stands down once its handshake ends

    @property
    def running(self) -> bool:
        return self.record is not None and self.record.state in ("active", "prepared") and self.frozen is None and not self.stale


class World:
    def __init__(self, seed: int, *, steps: int = 60, trace: bool = False) -> None:
        self.rng = random.Random(seed)
        self.seed = seed
        self.steps = steps
        self.log: list[str] = []
        self.trace = trace
        self.nodes = {n: Node(n) for n in NAMES}
        self.flight: list[Message] = []
        self.history: list[Message] = []
        self.next_id = 1
        self.expired = 0  # incoming attempts dropped at their bound
        self.sides: dict[str, int] | None = None  # a split mesh: who sees whose custody claims
        self.tokens: list[tuple[int, list[Link] | None, bytes | None]] = []  # the hostile one's (epoch, chain, key)
        self.forged: set[bytes] = set()  # signatures of the links it signed off the protocol
        self.revoked = False
        self.equivocators = {HOSTILE}
        self._backed: dict[tuple[int, tuple[bytes, ...]], bool] = {}
        home = self.nodes["a"]
        document = Identity(COMPANION, 1, SECTIONS).pack()
        home.key = self._new_key()
        chain = [custody.birth(COMPANION, "a", home.key, document)]
        self._write(home, Record(COMPANION, "active", 1, chain=chain, public_key=signing.encode_public(chain[0].public_key)),
                    document)

    # --- plumbing -----------------------------------------------------------------------------------

    def _id(self) -> int:
        self.next_id += 1
        return self.next_id

    def _new_key(self) -> bytes:
        return self.rng.randbytes(32)

    def note(self, text: str) -> None:
        self.log.append(text)
        if self.trace:
            print(text)

    def _write(self, node: Node, record: Record, document: bytes | None = None, key: bytes | None = None) -> Record:
        """Durable write, as ``Records.put`` does; checks that attempts only move forward."""
        if key is not None:
            node.key = key
        if document is not None:
            digest = custody.digest(document).hex()
            node.documents = {digest: document}
            record = msgspec.structs.replace(record, document=digest)
        elif record.state not in ("active", "prepared", "handed", "incoming"):
            node.documents = {}
            record = msgspec.structs.replace(record, document="")
        previous = node.record
        entering = record.state == "incoming" and (previous is None or previous.attempt != record.attempt)
        if entering and record.order <= node.orders:
            raise InvariantBroken(f"{node.name} resurrected attempt {record.attempt} {record.order} <= {node.orders}")
        node.orders = max(node.orders, record.order)
        node.record = record
        node.stale = False
        if record.state in ("active", "prepared", "handed") and node.key is not None and node.name == HOSTILE:
            node.kept.append((list(record.chain), node.key))
        if record.state == "active":
            node.backups = [*node.backups[-2:], (record, dict(node.documents), node.key)]
        if node.rolled and record.state == "handed" and record.link is not None:
            self.forged.add(record.link.signature)  # a copy from a backup hands on again: a second link of its epoch
            self.equivocators.add(node.name)
        if entering or record.state == "released":
            node.rolled = False
        self.note(f"  {node.name}: {record.state}({record.epoch}.{record.seq} {record.attempt[:6]})")
        return record

    def send(self, src: str, dst: str, op: str, payload: Any, reply_to: int = 0) -> None:
        message = Message(self._id(), src, dst, op, payload, reply_to)
        self.flight.append(message)
        self.history.append(message)
        waiting = self.nodes[src].ops.get(reply_to)
        if waiting is not None:
            waiting.awaiting = message.mid

    def sees(self, a: str, b: str) -> bool:
        return self.sides is None or self.sides[a] == self.sides[b]

    def claims(self, receiver: str) -> list[Claim]:
        """The backed claims ``receiver`` sees: every holder's (its record's chain, which it backs), and
        the hostile one's tokens that it can back (``custody.verify_claim``); bare ones never count."""
        found = [Claim(n.name, n.record.chain) for n in self.nodes.values()
                 if n.name != receiver and self.sees(receiver, n.name) and n.record is not None
                 and n.record.state in ("active", "prepared", "handed")]
        if not self.revoked and receiver != HOSTILE and self.sees(receiver, HOSTILE):
            found.extend(Claim(HOSTILE, chain) for epoch, chain, key in self.tokens
                         if chain is not None and self._backs(epoch, chain, key))
        return found

    def _backs(self, epoch: int, chain: list[Link], key: bytes | None) -> bool:
        """Whether the hostile one can back its token at ``epoch`` with ``chain`` (checked once)."""
        memo = (epoch, tuple(link.signature for link in chain))
        backed = self._backed.get(memo)
        if backed is None:
            proof = custody.ClaimProof(COMPANION, epoch, HOSTILE, "asker", b"nonce")
            try:
                custody.verify_claim(chain, proof, custody.sign_claim(key, proof) if key else b"")
                backed = True
            except signing.SignatureRefused:
                backed = False
            self._backed[memo] = backed
        return backed

    # --- the source side, as outgoing.Outgoing._send / commit_until_acked ----------------------------

    def start(self, node: Node, target: str) -> None:
        record = node.record
        if record is None or record.state != "active" or node.key is None or node.frozen is not None \
                or any(o.kind == "source" for o in node.ops.values()):
            return
        document = Identity(COMPANION, record.epoch, SECTIONS).pack()
        attempt = f"{self._id():06d}"
        prepared, message = handshake.offer(record, attempt=attempt, me=node.name, target=target, document=document, private=node.key)
        self.note(f"{node.name} migrates to {target}: attempt {attempt}")
        prepared = self._write(node, prepared, document)
        op = Op(self._id(), "source", "prepare", prepared, document, message)
        node.ops[op.oid] = op
        self.send(node.name, target, "prepare", message, op.oid)

    def _source_answer(self, node: Node, op: Op, outcome: Outcome | None) -> None:
        key = node.key or b""
        if op.stage == "prepare":
            if outcome is None and op.tries < 2:
                op.tries += 1
                self.send(node.name, op.record.peer, "prepare", op.message, op.oid)
                return
            after = handshake.after_prepare(op.record, outcome, private=key, document=op.document) if outcome is not None \
                else handshake.resume(op.record)
            after = self._write(node, after)
            if after.state != "handed":
                if outcome is None or outcome.status == "accepted":
                    self.send(node.name, op.record.peer, "abort", MigrateAbort(COMPANION, op.record.epoch, op.record.attempt))
                del node.ops[op.oid]
                return
            op.record = after
            self._send_commit(node, op)
        elif op.stage == "commit":
            if outcome is not None and outcome.status == "accepted":
                self._release(node, op, msgspec.structs.replace(op.record, state="released"))
            elif outcome is not None:
                op.stage = "status"
                self.send(node.name, op.record.peer, "status",
                          MigrateStatus(COMPANION, op.record.attempt, op.record.epoch, "target"), op.oid)
            else:
                self._send_commit(node, op)
        elif op.stage == "status":
            answer = outcome.value if outcome is not None and outcome.status == "accepted" else None
            step, record = handshake.after_refused_commit(op.record, answer)
            if step == "released" and record is not None:
                self._release(node, op, record)
            elif step == "resume" and record is not None:
                self._write(node, record)
                del node.ops[op.oid]
            elif step == "abort":
                op.stage = "abort"
                self.send(node.name, op.record.peer, "abort", MigrateAbort(COMPANION, op.record.epoch, op.record.attempt), op.oid)
            else:
                self._send_commit(node, op)
        elif op.stage == "abort":
            self._send_commit(node, op)

    def _send_commit(self, node: Node, op: Op) -> None:
        assert op.record.link is not None
        op.stage = "commit"
        self.send(node.name, op.record.peer, "commit", MigrateCommit(COMPANION, op.record.epoch, op.record.attempt, node.name,
                                                                     op.record.peer, custody.encode_link(op.record.link)), op.oid)

    def _release(self, node: Node, op: Op, record: Record) -> None:
        self._write(node, record)
        del node.ops[op.oid]

    # --- the target side, as MigrationManager._handle ---------------------------------------------------

    def handle(self, node: Node, message: Message) -> Outcome:
        record = node.record
        payload = message.payload
        if isinstance(payload, MigratePrepare):
            if message.src != payload.source:
                return Outcome("rejected", "not on behalf of another")
            held = record if record is not None and record.state in ("active", "prepared", "handed", "incoming") else None
            decision = handshake.on_prepare(payload, record, me=node.name, held=held, admit=None,
                                            claims=self.claims(node.name), new_key=self._new_key)
            if decision.record is not None:
                self._write(node, decision.record, decision.document, decision.key)
                op = Op(self._id(), "resolve", "ask", decision.record)
                node.ops[op.oid] = op
                self._ask_source(node, op)
                self._expire_later(node, decision.record)
            return decision.outcome
        if isinstance(payload, MigrateCommit):
            if message.src != payload.source:
                return Outcome("rejected", "not on behalf of another")
            decision = handshake.on_commit(payload, record, me=node.name)
            if decision.record is not None:
                self._write(node, decision.record)
            return decision.outcome
        if isinstance(payload, MigrateAbort):
            decision = handshake.on_abort(payload, record, requester=message.src)
            if decision.record is not None:
                self._write(node, decision.record)
            return decision.outcome
        assert isinstance(payload, MigrateStatus)
        return handshake.on_status(payload, record, requester=message.src).outcome

    def _ask_source(self, node: Node, op: Op) -> None:
        self.send(node.name, op.record.peer, "status", MigrateStatus(COMPANION, op.record.attempt, op.record.epoch, "source"), op.oid)

    def _expire_later(self, node: Node, record: Record) -> None:
        op = Op(self._id(), "expire", "wait", record)
        node.ops[op.oid] = op

    def _expire(self, node: Node, op: Op) -> None:
        """The incoming attempt's bound has passed, whatever else is under way (incoming.Incoming._expire)."""
        del node.ops[op.oid]
        current = node.record
        if current is None or current.state != "incoming" or current.attempt != op.record.attempt:
            return
        bound = handshake.INCOMING_BOUND
        expired = handshake.expire_incoming(current, now=handshake.incoming_deadline(current, bound), bound=bound)
        if expired is None:
            raise InvariantBroken(f"{node.name}: attempt {current.attempt} past its deadline is not dropped")
        self.expired += 1
        self.note(f"{node.name}: incoming {current.attempt[:6]} past its bound: dropped")
        self._write(node, expired)

    def _resolve_answer(self, node: Node, op: Op, outcome: Outcome | None) -> None:
        current = node.record
        if current is None or current.state != "incoming" or current.attempt != op.record.attempt:
            del node.ops[op.oid]
            return
        settled = handshake.settle_incoming(current, outcome.value, me=node.name) if outcome is not None \
            and outcome.status == "accepted" else None
        if settled is None:
            self._ask_source(node, op)
            return
        self._write(node, settled)
        del node.ops[op.oid]

    # --- crashes and restarts, as MigrationManager.attach ---------------------------------------------

    def crash(self, node: Node) -> None:
        self.note(f"{node.name} crashes and restarts")
        node.ops.clear()
        record = node.record
        if record is None:
            return
        if record.state == "prepared":
            self._write(node, handshake.resume(record))
            self.send(node.name, record.peer, "abort", MigrateAbort(COMPANION, record.epoch, record.attempt))
        elif record.state == "handed":
            op = Op(self._id(), "source", "commit", record)
            node.ops[op.oid] = op
            self._send_commit(node, op)
        elif record.state == "incoming":
            op = Op(self._id(), "resolve", "ask", record)
            node.ops[op.oid] = op
            self._ask_source(node, op)
            self._expire_later(node, record)  # the bound counts from the prepare: it may have passed

    # --- a hostile former host ------------------------------------------------------------------------

    def forge(self) -> None:
        rng = self.rng
        hostile = self.nodes[HOSTILE]
        if self.revoked:
            return
        roll = rng.random()
        if roll < 0.15:  # a bare token, at any epoch: a hint nobody can back
            self.declare(rng.randint(1, 1000), None, None)
            return
        if not hostile.kept or (hostile.record is not None and hostile.record.state in ("active", "prepared", "handed")):
            return
        chain, key = rng.choice(hostile.kept)
        if roll < 0.25:  # a chain it held, claimed at an inflated epoch: its head does not back it
            self.declare(chain[-1].epoch + rng.randint(1, 500), chain, key)
            return
        epoch = chain[-1].epoch
        if roll < 0.4 or rng.random() < 0.6:  # a fork: links to itself, fresh keys, epochs inflated
            for _ in range(rng.choice((1, 1, 2, 3, 12))):
                own = self._new_key()
                link = custody.hand_on(key, COMPANION, epoch + 1, HOSTILE, signing.public_of(own), "forged", custody.digest(b""))
                self.forged.add(link.signature)
                chain, key, epoch = [*chain, link], own, epoch + 1
        if roll < 0.4:  # claims the branch it forged: backed (it holds the key at its head)
            self.declare(epoch, chain, key)
            return
        target = rng.choice([n for n in NAMES if n != HOSTILE])
        document = Identity(COMPANION, epoch, {"mind": {"memory": ["HACKED"]}}).pack()
        record = Record(COMPANION, "active", epoch, seq=self.rng.randint(0, 1000), chain=chain)
        _, prepare = handshake.offer(record, attempt=f"forged{self._id()}", me=HOSTILE, target=target, document=document, private=key)
        self.note(f"{HOSTILE} (hostile) forges a prepare at epoch {epoch} to {target}")
        outcome = self.handle(self.nodes[target], Message(0, HOSTILE, target, "prepare", prepare))
        if outcome.status == "accepted":
            link = custody.hand_on(key, COMPANION, epoch + 1, target, signing.decode_public(outcome.value["custody_key"]),
                                   prepare.attempt, custody.digest(document))
            self.forged.add(link.signature)
            commit = MigrateCommit(COMPANION, epoch, prepare.attempt, HOSTILE, target, custody.encode_link(link))
            self.note(f"{HOSTILE} (hostile): {target} accepted the forged prepare; forging its commit")
            self.handle(self.nodes[target], Message(0, HOSTILE, target, "commit", commit))

    def declare(self, epoch: int, chain: list[Link] | None, key: bytes | None) -> None:
        self.note(f"{HOSTILE} (hostile) declares a custody token at epoch {epoch}"
                  + (" (bare)" if chain is None else f" with a chain to epoch {chain[-1].epoch}"))
        self.tokens = [*self.tokens[-2:], (epoch, chain, key)]  # a few at a time; older ones withdrawn

    # --- every holder judges the claims it sees, as forks.Forks.check_conflict -----------------------------

    def settle(self) -> None:
        for node in self.nodes.values():
            record = node.record
            if record is None or record.state not in ("active", "prepared"):
                if record is None or record.state not in ("handed", "incoming"):
                    node.frozen = None  # no copy left to freeze: Records.put drops the evidence
                continue
            verdict = handshake.judge(record, self.claims(node.name))
            if verdict.superseded_by is not None and record.state == "active":
                self.note(f"{node.name}: superseded by {verdict.superseded_by.holder}")
                node.frozen = None
                self._write(node, handshake.superseded(record, verdict.superseded_by))
            elif verdict.superseded_by is not None:
                node.stale = True
            elif verdict.forks and node.frozen is None:
                node.frozen = verdict.forks[0][1]
                self.note(f"{node.name}: FROZEN, {node.frozen.describe()}")

    def roll_back(self) -> None:
        """An embodiment that holds no copy now is restored from a backup of its state folder, taken when
        it held the companion: it starts with that active record (attack 5 of the custody review)."""
        candidates = [n for n in self.nodes.values() if n.backups and n.name != HOSTILE
                      and (n.record is None or n.record.state in ("released", "dropped"))]
        if not candidates or self.revoked:
            return
        node = self.rng.choice(candidates)
        record, documents, key = self.rng.choice(node.backups)
        self.note(f"{node.name} is restored from a backup: active at epoch {record.epoch}")
        node.ops.clear()
        node.record, node.documents, node.key = record, documents, key
        node.orders = record.order  # the fault itself moves its durable state back
        node.rolled = True
        node.frozen = None

    def split(self) -> None:
        if self.sides is None:
            self.sides = {name: self.rng.randint(0, 1) for name in NAMES}
            self.note(f"the mesh splits: {self.sides}")
        else:
            self.sides = None
            self.note("the mesh joins again")

    # --- the scheduler --------------------------------------------------------------------------------

    def deliver(self, message: Message) -> None:
        node = self.nodes[message.dst]
        if message.is_reply:
            op = node.ops.get(message.reply_to)
            if op is not None and op.awaiting == message.request:
                self.answer(node, op, message.payload)
            return
        outcome = self.handle(node, message)
        self.note(f"{message.src}->{message.dst} {message.op}: {outcome.status} {outcome.reason[:60]}")
        if message.reply_to:
            self.flight.append(Message(self._id(), message.dst, message.src, message.op, outcome, message.reply_to, True, message.mid))

    def answer(self, node: Node, op: Op, outcome: Outcome | None) -> None:
        """``op`` of ``node`` ends with ``outcome`` (None: unknown), or fires (a timer)."""
        if op.kind == "source":
            self._source_answer(node, op, outcome)
        elif op.kind == "expire":
            self._expire(node, op)
        else:
            self._resolve_answer(node, op, outcome)

    def time_out(self) -> None:
        """An op gives up waiting (its message may still be in flight): outcome unknown; or a
        target's incoming attempt reaches its bound."""
        waiting = [(node, op) for node in self.nodes.values() for op in list(node.ops.values())]
        if waiting:
            node, op = self.rng.choice(waiting)
            self.note(f"{node.name}: {op.kind} {op.stage} times out")
            self.answer(node, op, None)

    def check(self) -> None:
        running = [n for n in self.nodes.values() if n.running]
        for i, one in enumerate(running):
            for other in running[i + 1:]:
                if self.sees(one.name, other.name) or not any(self._forged(n) or n.rolled for n in (one, other)):
                    raise InvariantBroken(f"two hosts: {[one.name, other.name]}")
        for node in running:
            if self._forged(node):
                assert node.record is not None
                for claim in self.claims(node.name):
                    if custody.compare(node.record.chain, claim.chain)[0] == "fork":
                        raise InvariantBroken(f"{node.name} runs a forged branch while it sees {claim.holder}'s")
        for node in self.nodes.values():
            fork = node.frozen
            if fork is None:
                continue
            custody.verify_fork(fork)
            if fork.equivocator not in self.equivocators or not {fork.first.signature, fork.second.signature} & self.forged:
                raise InvariantBroken(f"{node.name} frozen without a proof of an equivocation: {fork.describe()}")

    def _forged(self, node: Node) -> bool:
        return node.record is not None and any(link.signature in self.forged for link in node.record.chain)

    def step(self) -> None:
        rng = self.rng
        roll = rng.random()
        if roll < 0.45 and self.flight:
            self.deliver(self.flight.pop(rng.randrange(len(self.flight))))
        elif roll < 0.52 and self.flight:
            lost = self.flight.pop(rng.randrange(len(self.flight)))
            self.note(f"lost {lost.src}->{lost.dst} {lost.op}")
        elif roll < 0.58 and self.flight:
            copy = rng.choice(self.flight)
            self.flight.append(Message(self._id(), copy.src, copy.dst, copy.op, copy.payload, copy.reply_to, copy.is_reply, copy.request))
        elif roll < 0.66 and self.history:
            old = rng.choice(self.history)
            self.note(f"replay {old.src}->{old.dst} {old.op}")
            self.flight.append(Message(self._id(), old.src, old.dst, old.op, old.payload))
        elif roll < 0.74:
            self.time_out()
        elif roll < 0.78:
            self.crash(self.nodes[rng.choice(NAMES)])
        elif roll < 0.8:
            self.split()
        elif roll < 0.805:
            self.roll_back()
        elif roll < 0.91:
            holder = [n for n in self.nodes.values() if n.record is not None and n.record.state == "active"]
            if holder:
                self.start(holder[0], rng.choice([n for n in NAMES if n != holder[0].name]))
        else:
            self.forge()
        self.settle()
        self.check()

    def heal(self, limit: int = 5000) -> None:
        """No more faults: the mesh joins, the hostile one is revoked; deliver everything in order, time
        out what waits on a lost message; then an operator resolves a fork, and the rest is delivered."""
        self.sides = None
        self.revoked = True
        self.settle()
        self.check()
        self.deliver_all(limit)
        if any(n.frozen is not None for n in self.nodes.values()):
            self.resolve()
            self.deliver_all(limit)
        self._final()

    def resolve(self) -> None:
        """The operator keeps the true branch (no forged link) and retires every other copy first."""
        keep = [n for n in self.nodes.values() if n.record is not None and n.record.state == "active" and not self._forged(n)]
        if len(keep) != 1:
            raise InvariantBroken(f"no single true branch to keep: {[n.name for n in keep]}")
        kept = keep[0]
        assert kept.record is not None
        for node in self.nodes.values():
            record = node.record
            if node is not kept and record is not None and record.state == "active":
                retired = self._write(node, handshake.retired(record, kept.record.chain))
                node.orders = retired.order  # the operator's step back: another branch's orders mean nothing here
                node.frozen = None
        self.note(f"the operator keeps {kept.name}")
        kept.frozen = None
        self.settle()
        self.check()

    def deliver_all(self, limit: int) -> None:
        for _ in range(limit):
            awaited = {m.reply_to for m in self.flight}
            # A bound is long beside a delivery: healing settles by messages (expiry is tried while faulty).
            stalled = [(node, op) for node in self.nodes.values() for op in list(node.ops.values())
                       if op.oid not in awaited and op.kind != "expire"]
            if stalled:  # waiting for an answer that was lost: its timeout fires
                node, op = stalled[0]
                self.answer(node, op, None)
            elif self.flight:
                self.deliver(self.flight.pop(0))
            else:
                break
            self.settle()
            self.check()
        else:
            raise InvariantBroken(f"not quiescent after {limit} steps of healing")

    def _final(self) -> None:
        settled = {n.name: n.record.state for n in self.nodes.values() if n.record is not None}
        hosts = [n for n in self.nodes.values() if n.record is not None and n.record.state == "active"]
        undecided = [name for name, state in settled.items() if state in ("prepared", "handed", "incoming")]
        if len(hosts) != 1 or undecided or not hosts[0].running:
            raise InvariantBroken(f"after healing: {settled}, frozen: {[n.name for n in hosts if n.frozen]}")
        host = hosts[0]
        assert host.record is not None
        if self._forged(host):
            raise InvariantBroken(f"{host.name} runs a forged branch after healing")
        document = host.documents.get(host.record.document, b"")
        if unpack(document).sections != SECTIONS or custody.digest(document).hex() != host.record.document:
            raise InvariantBroken(f"the identity on {host.name} is not the one born")
        custody.verify_chain(host.record.chain, COMPANION)
        if host.record.chain[-1].holder != host.name:
            raise InvariantBroken(f"{host.name} hosts the companion but its chain ends at {host.record.chain[-1].holder}")

    def run(self) -> None:
        for _ in range(self.steps):
            self.step()
        self.heal()


def run_schedule(seed: int, *, steps: int = 60, trace: bool = False) -> World:
    world = World(seed, steps=steps, trace=trace)
    try:
        world.run()
    except Exception as exc:  # any failure of a schedule is reported with its seed and trace
        raise InvariantBroken(f"seed {seed}: {exc}\nreplay: python -m cmion_mesh.testing.simulation --seed {seed} --trace\n"
                              + "\n".join(world.log[-40:])) from None
    return world


def run_many(count: int, *, first: int = 0, steps: int = 60, progress: Callable[[int], None] | None = None) -> float:
    """Run ``count`` schedules from seed ``first``; returns schedules per second."""
    started = time.perf_counter()
    for seed in range(first, first + count):
        run_schedule(seed, steps=steps)
        if progress is not None and (seed - first + 1) % 10_000 == 0:
            progress(seed - first + 1)
    return count / max(1e-9, time.perf_counter() - started)


def main(argv: list[str] | None = None) -> int:
    import argparse  # its command line only: importing the package loads no argparse
    parser = argparse.ArgumentParser(prog="python -m cmion_mesh.testing.simulation", description=__doc__.splitlines()[0])
    parser.add_argument("--schedules", type=int, default=10_000, help="how many random schedules (default 10,000)")
    parser.add_argument("--first", type=int, default=0, help="the first seed")
    parser.add_argument("--steps", type=int, default=60, help="faulty steps per schedule before healing")
    parser.add_argument("--seed", type=int, help="run this one seed")
    parser.add_argument("--trace", action="store_true", help="print every step of --seed")
    args = parser.parse_args(argv)
    if args.seed is not None:
        run_schedule(args.seed, steps=args.steps, trace=args.trace)
        print(f"seed {args.seed}: invariants held")
        return 0
    rate = run_many(args.schedules, first=args.first, steps=args.steps,
                    progress=lambda n: print(f"{n} schedules", file=sys.stderr, flush=True))
    print(f"{args.schedules} schedules from seed {args.first}: invariants held; {rate:.0f} schedules/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
