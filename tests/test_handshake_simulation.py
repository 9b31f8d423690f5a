"""The handshake's real decisions through 10,000 random schedules of faults, replays, crashes and a
hostile former host (``bench/simulation.py``); a million run with ``python -m bench.simulation``."""

from __future__ import annotations

import pytest

from bench import simulation
from bench.simulation import InvariantBroken, World

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
