"""Simulation testing of the migration handshake, FoundationDB style.

Three embodiments run the real decisions of ``cmion_mesh.handshake`` (the same functions
``MigrationManager`` calls) over a simulated network driven by one seeded random generator. Any
message ever sent may be delivered late, lost, duplicated, reordered or **replayed later**; any
embodiment may crash (losing everything but its durable record, document and key) and restart at
any step; a waiting request may time out while its message is still in flight; and one embodiment
turns hostile once it has held the companion: it keeps every custody key it had and forges
prepares (forks of the chain) and commits with them. After every step: never two embodiments that
may run the companion (``active`` or ``prepared``), and no record ever moves to an attempt that is
not newer than every one it held. After the faults stop and everything is delivered: exactly one
host, its identity byte-identical to the one born.

``python -m bench sim --schedules 1000000`` (or ``python -m bench.simulation``) runs many; a
failing seed prints the trace that replays it (``--seed N --trace``).
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgspec

from cmion_mesh import custody, handshake, signing
from cmion_mesh.custody import Link
from cmion_mesh.handshake import Claim
from cmion_mesh.identity import Identity, unpack
from cmion_mesh.messages import MigrateAbort, MigrateCommit, MigratePrepare, MigrateStatus, Outcome
from cmion_mesh.records import Record

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
    """A handshake thread: ``kind`` source (prepare/commit/status/abort stages) or resolve (target)."""

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
        if record.state in ("active", "prepared", "handed") and node.key is not None and node.name == HOSTILE:
            node.kept.append((list(record.chain), node.key))
        self.note(f"  {node.name}: {record.state}({record.epoch}.{record.seq} {record.attempt[:6]})")
        return record

    def send(self, src: str, dst: str, op: str, payload: Any, reply_to: int = 0) -> None:
        message = Message(self._id(), src, dst, op, payload, reply_to)
        self.flight.append(message)
        self.history.append(message)
        waiting = self.nodes[src].ops.get(reply_to)
        if waiting is not None:
            waiting.awaiting = message.mid

    def claims(self, receiver: str) -> list[Claim]:
        """Backed custody claims: every holder's, its record's chain (which it backs), seen at once by
        everyone (liveliness is not what this simulation faults)."""
        return [Claim(n.name, n.record.chain) for n in self.nodes.values()
                if n.name != receiver and n.record is not None and n.record.state in ("active", "prepared", "handed")]

    # --- the source side, as MigrationManager._send / _commit_until_acked ----------------------------

    def start(self, node: Node, target: str) -> None:
        record = node.record
        if record is None or record.state != "active" or node.key is None or any(o.kind == "source" for o in node.ops.values()):
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

    # --- a hostile former host ------------------------------------------------------------------------

    def forge(self) -> None:
        hostile = self.nodes[HOSTILE]
        if not hostile.kept or (hostile.record is not None and hostile.record.state in ("active", "prepared", "handed")):
            return
        chain, key = self.rng.choice(hostile.kept)
        target = self.rng.choice([n for n in NAMES if n != HOSTILE])
        epoch = chain[-1].epoch
        if self.rng.random() < 0.5:  # a fork: hand custody to a key of its own, then offer from there
            own = self._new_key()
            chain = [*chain, custody.hand_on(key, COMPANION, epoch + 1, HOSTILE, signing.public_of(own), "forged",
                                             custody.digest(b""))]
            key, epoch = own, epoch + 1
        document = Identity(COMPANION, epoch, {"mind": {"memory": ["HACKED"]}}).pack()
        record = Record(COMPANION, "active", epoch, seq=self.rng.randint(0, 1000), chain=chain)
        _, prepare = handshake.offer(record, attempt=f"forged{self._id()}", me=HOSTILE, target=target, document=document, private=key)
        self.note(f"{HOSTILE} (hostile) forges a prepare at epoch {epoch} to {target}")
        outcome = self.handle(self.nodes[target], Message(0, HOSTILE, target, "prepare", prepare))
        if outcome.status == "accepted":
            link = custody.hand_on(key, COMPANION, epoch + 1, target, signing.decode_public(outcome.value["custody_key"]),
                                   prepare.attempt, custody.digest(document))
            commit = MigrateCommit(COMPANION, epoch, prepare.attempt, HOSTILE, target, custody.encode_link(link))
            self.note(f"{HOSTILE} (hostile): {target} accepted the forged prepare; forging its commit")
            self.handle(self.nodes[target], Message(0, HOSTILE, target, "commit", commit))

    # --- the scheduler --------------------------------------------------------------------------------

    def deliver(self, message: Message) -> None:
        node = self.nodes[message.dst]
        if message.is_reply:
            op = node.ops.get(message.reply_to)
            if op is not None and op.awaiting == message.request:
                self._answer(node, op, message.payload)
            return
        outcome = self.handle(node, message)
        self.note(f"{message.src}->{message.dst} {message.op}: {outcome.status} {outcome.reason[:60]}")
        if message.reply_to:
            self.flight.append(Message(self._id(), message.dst, message.src, message.op, outcome, message.reply_to, True, message.mid))

    def _answer(self, node: Node, op: Op, outcome: Outcome | None) -> None:
        if op.kind == "source":
            self._source_answer(node, op, outcome)
        else:
            self._resolve_answer(node, op, outcome)

    def time_out(self) -> None:
        """An op gives up waiting (its message may still be in flight): outcome unknown."""
        waiting = [(node, op) for node in self.nodes.values() for op in list(node.ops.values())]
        if waiting:
            node, op = self.rng.choice(waiting)
            self.note(f"{node.name}: {op.kind} {op.stage} times out")
            self._answer(node, op, None)

    def check(self) -> None:
        hosts = [n.name for n in self.nodes.values() if n.record is not None and n.record.state in ("active", "prepared")]
        if len(hosts) > 1:
            raise InvariantBroken(f"two hosts: {hosts}")

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
        elif roll < 0.93:
            holder = [n for n in self.nodes.values() if n.record is not None and n.record.state == "active"]
            if holder:
                self.start(holder[0], rng.choice([n for n in NAMES if n != holder[0].name]))
        else:
            self.forge()
        self.check()

    def heal(self, limit: int = 5000) -> None:
        """No more faults: deliver everything in order, time out what waits on a lost message."""
        for _ in range(limit):
            awaited = {m.reply_to for m in self.flight}
            stalled = [(node, op) for node in self.nodes.values() for op in list(node.ops.values()) if op.oid not in awaited]
            if stalled:  # waiting for an answer that was lost: its timeout fires
                node, op = stalled[0]
                self._answer(node, op, None)
            elif self.flight:
                self.deliver(self.flight.pop(0))
            else:
                break
            self.check()
        else:
            raise InvariantBroken(f"not quiescent after {limit} steps of healing")
        settled = {n.name: n.record.state for n in self.nodes.values() if n.record is not None}
        hosts = [n for n in self.nodes.values() if n.record is not None and n.record.state == "active"]
        undecided = [name for name, state in settled.items() if state in ("prepared", "handed", "incoming")]
        if len(hosts) != 1 or undecided:
            raise InvariantBroken(f"after healing: {settled}")
        host = hosts[0]
        assert host.record is not None
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
        raise InvariantBroken(f"seed {seed}: {exc}\nreplay: python -m bench.simulation --seed {seed} --trace\n"
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
    parser = argparse.ArgumentParser(prog="python -m bench.simulation", description=__doc__.splitlines()[0])
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
