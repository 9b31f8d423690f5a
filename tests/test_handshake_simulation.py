"""The handshake's real decisions through 10,000 random schedules of faults, replays, crashes, splits
of the mesh, restored backups, targets giving up incoming attempts at their bound, and a hostile former
host that declares bare tokens and forges, claims and offers forks (``cmion_mesh/testing/simulation.py``); a million
run with ``python -m cmion_mesh.testing.simulation``."""

from __future__ import annotations

import pytest

from cmion_mesh.messages import MigrateCommit, MigrateStatus
from cmion_mesh.migration import custody, handshake, signing
from cmion_mesh.migration.identity import Identity
from cmion_mesh.migration.ledger import Record
from cmion_mesh.testing import simulation
from cmion_mesh.testing.simulation import HOSTILE, InvariantBroken, Message, World

SCHEDULES = 10_000


@pytest.mark.timeout(240)
def test_ten_thousand_schedules_keep_exactly_one_host() -> None:
    simulation.run_many(SCHEDULES)


def test_a_broken_rule_is_caught_with_a_replayable_seed(monkeypatch: pytest.MonkeyPatch) -> None:
    """The simulation must be able to fail: accept any prepare, whatever the record says, and a
    replayed or hostile prepare soon makes two hosts, reported with the seed that replays it."""
    real = simulation.handshake.on_prepare

    def careless(msg, record, **kwargs):  # type: ignore[no-untyped-def]
        return real(msg, None, **{**kwargs, "held": None, "claims": []})

    monkeypatch.setattr(simulation.handshake, "on_prepare", careless)
    with pytest.raises(InvariantBroken, match=r"seed \d+: .*\nreplay: python -m cmion_mesh.testing.simulation --seed \d+ --trace"):
        simulation.run_many(500)


def test_the_replay_of_a_dropped_attempt_is_refused() -> None:
    """The lost-companion scenario: b dropped attempt (e, 1); a replay of its prepare while a newer
    attempt is incoming, and after it is decided, changes nothing."""
    world = World(0, steps=0)
    a, b = world.nodes["a"], world.nodes["b"]
    world.start(a, "b")
    first = world.flight.pop()
    world.deliver(first)  # b: incoming (1, 1)
    world.deliver(world.flight.pop())  # the answer: a is handed
    world.crash(a)
    assert a.record is not None and a.record.state == "handed"
    world.heal()
    assert b.record is not None and b.record.state == "active"
    # a replay of the first prepare, now and forever, is refused without touching b
    before = b.record
    world.deliver(simulation.Message(999, "a", "b", "prepare", first.payload))
    assert b.record == before


def test_an_incoming_attempt_past_its_bound_is_dropped_and_its_source_resumes() -> None:
    """b accepts a's prepare, restarts, and gives the attempt up at its bound while a's commit is in
    flight: the commit is refused, a (handed) asks b, is told dropped and resumes, the one host."""
    world = World(0, steps=0)
    a, b = world.nodes["a"], world.nodes["b"]

    def record(node: simulation.Node) -> Record:
        assert node.record is not None
        return node.record

    world.start(a, "b")
    world.deliver(world.flight.pop())  # the prepare: b incoming, asking a (status) and with its timer
    world.deliver(world.flight.pop())  # its answer: a handed, its commit sent
    commit = world.flight.pop()
    assert commit.op == "commit" and record(a).state == "handed"
    world.crash(b)  # a restart keeps the deadline: the timer is set again from the record
    assert record(b).state == "incoming"
    timer = next(op for op in b.ops.values() if op.kind == "expire")
    world.answer(b, timer, None)
    assert record(b).state == "dropped" and world.expired == 1
    status = handshake.on_status(MigrateStatus("spirit", record(b).attempt, record(b).epoch, "target"), record(b), requester="a")
    assert status.outcome.value == {"state": "dropped"}
    world.deliver(commit)
    refused = world.flight[-1]
    assert refused.is_reply and refused.payload.status == "rejected" and record(b).state == "dropped"
    world.heal()
    assert record(a).state == "active" and record(a).epoch == 1 and record(b).state == "dropped"
    # and a later attempt from a is newer than the dropped one: b takes it
    world.start(a, "b")
    world.heal()
    assert record(b).state == "active" and record(a).state == "released"


def test_targets_give_up_incoming_attempts_across_the_schedules() -> None:
    """The timer fires at random points of the schedules (``time_out``), and the invariants hold."""
    expired = sum(simulation.run_schedule(seed).expired for seed in range(300))
    assert expired > 50, expired


def test_a_bare_token_freezes_nobody_and_refuses_no_migration() -> None:
    world = World(0, steps=0)
    a, b = world.nodes["a"], world.nodes["b"]
    assert a.record is not None and a.key is not None
    world.declare(1002, None, None)  # bare
    world.declare(1003, list(a.record.chain), a.key)  # a chain that ends at epoch 1: it backs no claim at 1003
    world.settle()
    assert a.running and a.frozen is None
    world.start(a, "b")
    world.deliver_all(1000)
    assert b.running and b.record is not None and b.record.epoch == 2 and a.frozen is None and b.frozen is None


def test_an_inflated_fork_across_a_split_freezes_both_and_the_operator_keeps_the_true_one() -> None:
    world = World(0, steps=0)
    a, b, c = (world.nodes[n] for n in "abc")
    world.start(a, HOSTILE)
    world.deliver_all(1000)
    world.start(c, "a")
    world.deliver_all(1000)
    assert a.record is not None and a.record.epoch == 3 and a.running
    chain, key = next((chain, key) for chain, key in c.kept if chain[-1].epoch == 2)
    for _ in range(501):  # offline, to itself, fresh keys: up to epoch 503
        own = signing.new_key()
        link = custody.hand_on(key, "spirit", chain[-1].epoch + 1, HOSTILE, signing.public_of(own), "forged", custody.digest(b""))
        world.forged.add(link.signature)
        chain, key = [*chain, link], own
    world.sides = {"a": 0, "b": 1, "c": 1}  # b cannot see a
    document = Identity("spirit", 503, {"mind": {"memory": ["HACKED"]}}).pack()
    _, prepare = handshake.offer(Record("spirit", "active", 503, chain=chain), attempt="forged", me=HOSTILE, target="b",
                                 document=document, private=key)
    answer = world.handle(b, Message(0, HOSTILE, "b", "prepare", prepare))
    assert answer.status == "accepted", answer
    link = custody.hand_on(key, "spirit", 504, "b", signing.decode_public(answer.value["custody_key"]), "forged",
                           custody.digest(document))
    world.forged.add(link.signature)
    assert world.handle(b, Message(0, HOSTILE, "b", "commit", MigrateCommit("spirit", 503, "forged", HOSTILE, "b",
                                                                            custody.encode_link(link)))).status == "accepted"
    world.settle()
    world.check()
    assert a.running and b.running, "across the split, each runs its branch"
    world.sides = None  # they meet: no branch wins by itself, 500 epochs ahead or not
    world.settle()
    world.check()
    assert a.frozen is not None and b.frozen is not None and not a.running and not b.running
    assert a.frozen.equivocator == b.frozen.equivocator == HOSTILE and a.frozen.epoch == 3
    world.heal()  # the operator keeps a's branch; b stands down first
    assert a.running and b.record is not None and b.record.state == "dropped" and b.record.chain == a.record.chain
