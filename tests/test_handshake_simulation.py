"""The handshake's real decisions through 10,000 random schedules of faults, replays, crashes,
targets giving up incoming attempts at their bound, and a hostile former host (``bench/simulation.py``);
a million run with ``python -m bench.simulation``."""

from __future__ import annotations

import pytest

from bench import simulation
from bench.simulation import InvariantBroken, World
from cmion_mesh import handshake
from cmion_mesh.messages import MigrateStatus
from cmion_mesh.records import Record

SCHEDULES = 10_000


@pytest.mark.timeout(240)
def test_ten_thousand_schedules_keep_exactly_one_host() -> None:
    simulation.run_many(SCHEDULES)


def test_a_broken_rule_is_caught_with_a_replayable_seed(monkeypatch: pytest.MonkeyPatch) -> None:
    """The simulation must be able to fail: accept any prepare, whatever the record says, and a
    replayed or hostile prepare soon makes two hosts, reported with the seed that replays it."""
    real = simulation.handshake.on_prepare

    def careless(msg, record, **kwargs):  # type: ignore[no-untyped-def]
        return real(msg, None, **{**kwargs, "held": None, "live_claims": {}})

    monkeypatch.setattr(simulation.handshake, "on_prepare", careless)
    with pytest.raises(InvariantBroken, match=r"seed \d+: .*\nreplay: python -m bench.simulation --seed \d+ --trace"):
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
    world._answer(b, timer, None)
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
