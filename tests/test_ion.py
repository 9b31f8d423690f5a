"""ION semantics on the in-memory transport: mediation, ordering, definite answers."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from cmion_mesh.errors import ClosedError, MeshError, RequestRejected
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import Code, Event, Message, MindMessage, MindState, Outcome, decode, encode
from cmion_mesh.mind import Mind
from cmion_mesh.requests import IncomingRequest, send_request
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

pytestmark = pytest.mark.timeout(30)


@contextmanager
def held(sim: Simulation) -> Iterator[None]:
    """Block the update loop so that everything sent meanwhile lands in one update."""
    entered, release = threading.Event(), threading.Event()

    def block() -> None:
        entered.set()
        release.wait(10)

    sim.call(block)
    assert entered.wait(5)
    try:
        yield
    finally:
        release.set()


class Claim(Message, frozen=True, tag="claim"):
    slot: int
    who: str = ""


class Silent(Message, frozen=True, tag="silent"):
    pass


class Boom(Message, frozen=True, tag="boom"):
    pass


class Recorder(Component):
    """Accepts the first claim per slot in each batch, conflicts the rest."""

    requests = {"claim": Claim, "silent": Silent, "boom": Boom}

    def __init__(self, name: str = "arbiter") -> None:
        super().__init__(name)
        self.batches: list[list[str]] = []

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        self.batches.append([r.payload.who for r in batch if isinstance(r.payload, Claim)])
        taken: set[Any] = set()
        for r in batch:
            match r.payload:
                case Boom():
                    raise RuntimeError("handler bug")
                case Silent():
                    continue
                case Claim(slot=slot) if slot in taken:
                    r.conflict(f"slot {slot} taken in this update")
                case Claim(slot=slot):
                    taken.add(slot)
                    r.accept({"slot": slot})


@pytest.fixture
def sim(transport: MemoryTransport, mesh: str) -> Iterator[Simulation]:
    with Simulation(transport, mesh=mesh, embodiment="robot") as s:
        yield s


@pytest.fixture
def stepped(transport: MemoryTransport, mesh: str) -> Iterator[Simulation]:
    """A simulation that is never started: the test runs each update with ``run_once``."""
    s = Simulation(transport, mesh=mesh, embodiment="robot")
    try:
        yield s
    finally:
        s.close()


def test_requests_in_one_update_are_mediated_together_and_all_answered(stepped: Simulation, network: MemoryNetwork) -> None:
    arbiter = stepped.add(Recorder())
    assert stepped.run_once() == 1, "the update that attaches the component"
    with MemoryTransport(network, "remote") as remote:
        results: dict[str, Outcome] = {}

        def ask(who: str, slot: int) -> None:
            key = f"cmion/{stepped.mesh}/robot/rq/arbiter/claim"
            results[who] = send_request(remote, key, Claim(slot, who))

        threads = [threading.Thread(target=ask, args=(w, s)) for w, s in (("a", 1), ("b", 1), ("c", 2))]
        for t in threads:
            t.start()
        # The three queries wait in the inbox until the test runs the update.
        wait_for(lambda: stepped.queued() >= 3, 5, "three requests queued")
        assert stepped.run_once() == 3
        for t in threads:
            t.join(10)
    assert arbiter.batches == [sorted(arbiter.batches[0])] and sorted(arbiter.batches[0]) == ["a", "b", "c"], \
        "all three were handed over together"
    statuses = {w: o.status for w, o in results.items()}
    assert sorted(statuses.values()) == ["accepted", "accepted", "conflict"]
    loser = next(w for w, s in statuses.items() if s == "conflict")
    assert "slot 1 taken" in results[loser].reason
    assert results["c"].value == {"slot": 2}


def test_unanswered_and_failing_requests_still_get_definite_answers(sim: Simulation) -> None:
    sim.add(Recorder())
    silent = sim.request("arbiter", "silent", Silent()).result(5)
    assert silent.status == "rejected" and "gave no answer" in silent.reason and silent.code == Code.UNANSWERED
    boom = sim.request("arbiter", "boom", Boom()).result(5)
    assert boom.status == "rejected" and "RuntimeError: handler bug" in boom.reason and boom.code == Code.HANDLER_FAILED
    unknown = sim.request("arbiter", "nope", Silent()).result(5)
    assert unknown.status == "rejected" and "'nope'" in unknown.reason and unknown.code == Code.UNKNOWN_REQUEST
    mistyped = sim.request("arbiter", "claim", Silent()).result(5)
    assert mistyped.status == "rejected" and "takes 'claim', not 'silent'" in mistyped.reason and mistyped.code == Code.MALFORMED


def test_remote_unknown_and_malformed_requests_are_rejected_with_reason(sim: Simulation, network: MemoryNetwork) -> None:
    sim.add(Recorder())
    with MemoryTransport(network, "remote") as remote:
        (reply,) = remote.get(f"cmion/{sim.mesh}/robot/rq/arbiter/nope", b"")
        assert "has no request 'nope'" in decode(reply.payload, Outcome).reason
        (reply,) = remote.get(f"cmion/{sim.mesh}/robot/rq/arbiter/claim", b"\xc1garbage")
        outcome = decode(reply.payload, Outcome)
        assert outcome.status == "rejected" and "malformed" in outcome.reason and outcome.code == Code.MALFORMED
        for untyped in (b"\x80", b"\x81\xa4slot\x01", b"\x81\xa4type\xa6silent"):  # {}, {slot: 1}, another request's type
            (reply,) = remote.get(f"cmion/{sim.mesh}/robot/rq/arbiter/claim", untyped)
            outcome = decode(reply.payload, Outcome)
            assert outcome.status == "rejected" and outcome.code == Code.MALFORMED, untyped


class PerSender(Component):
    """Takes claims on keys naming their sender (``.../rq/<name>/claim/<sender>``)."""

    requests = {"claim": Claim}
    sender_requests = frozenset({"claim"})

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        for r in batch:
            r.accept({"from": r.requester})


def test_one_queryable_answers_for_each_component_and_leaves_other_keys_to_others(network: MemoryNetwork, mesh: str) -> None:
    """A daemon's simulation declares one request queryable for all its components: each request
    reaches the component its key names, on the keys its own queryable took; a key none of them
    takes stays unanswered (not reached), and a component of the embodiment served by another
    process (a remote mind) is still answered by that process alone."""
    with MemoryTransport(network, "robot") as t, MemoryTransport(network, "elsewhere") as t2, \
            MemoryTransport(network, "asker") as asker, \
            Simulation(t, mesh=mesh, embodiment="robot", one_queryable=True) as sim, \
            Simulation(t2, mesh=mesh, embodiment="robot") as elsewhere:
        sim.add(Recorder())
        sim.add(PerSender("desk"))
        elsewhere.add(Recorder("far"))
        rq = f"cmion/{mesh}/robot/rq"
        with network.lock:
            declared = sorted(sel for sel, _, owner in network.queryables.values() if owner is t)
        assert declared == [f"{rq}/**"], "one declaration for the two components"

        def ask(key: str, payload: bytes) -> list[Outcome]:
            return [decode(reply.payload, Outcome) for reply in asker.get(key, payload, timeout=5)]

        claim = encode(Claim(1, "ann"))
        assert [o.value for o in ask(f"{rq}/arbiter/claim", claim)] == [{"slot": 1}]
        assert [o.value for o in ask(f"{rq}/desk/claim/ann", claim)] == [{"from": "ann"}]
        assert [o.value for o in ask(f"{rq}/far/claim", claim)] == [{"slot": 1}], "the other process alone answers"
        (wrong,) = ask(f"{rq}/desk/claim", claim)
        assert wrong.code == Code.WRONG_KEY, "a sender request without its sender is refused, as before"
        assert ask(f"{rq}/nobody/claim", claim) == [], "no component of that name: not reached"
        assert ask(f"{rq}/arbiter/claim/ann", claim) == [], "a key arbiter's own queryable would not have taken"
        assert ask(f"{rq}/arbiter", claim) == []
        listed = ask(f"{rq}/**", b"")  # what do you answer? each component, its catalogue, as before
        assert sorted(o.value["component"] for o in listed) == ["arbiter", "desk", "far"]
        assert {o.code for o in listed} == {Code.UNKNOWN_REQUEST}
        sim.remove("arbiter")
        assert ask(f"{rq}/arbiter/claim", claim) == [], "removed: not reached any more"
        assert [o.value for o in ask(f"{rq}/desk/claim/bob", claim)] == [{"from": "bob"}]


class Chain(Component):
    """On event n (< 3) raises n+1 twice: checks order and same-update dispatch."""

    def __init__(self, log: list[tuple[int, str, int]]) -> None:
        super().__init__("chain")
        self.log = log

    def attach(self, sim: Simulation) -> None:
        sim.on_event(self.first, component="chain")
        sim.on_event(self.second, component="chain", event="step")

    def first(self, event: Event) -> None:
        self.log.append((self.sim.updates, "first", event.data))
        if event.data < 3:
            self.raise_event("step", event.data + 1)
            self.raise_event("step", event.data + 10)

    def second(self, event: Event) -> None:
        self.log.append((self.sim.updates, "second", event.data))


def test_events_raised_in_handlers_are_dispatched_in_the_same_update_in_order(stepped: Simulation, network: MemoryNetwork) -> None:
    log: list[tuple[int, str, int]] = []
    chain = stepped.add(Chain(log))
    stepped.run_once()
    seen: list[int] = []
    with MemoryTransport(network, "observer") as observer:
        observer.subscribe(f"cmion/{stepped.mesh}/robot/ev/chain/step", lambda s: seen.append(decode(s.payload, Event).data))
        stepped.call(lambda: chain.raise_event("step", 1))
        assert stepped.run_once() == 1
        assert len(log) == 10, "the whole chain ran in that one update"
        wait_for(lambda: len(seen) >= 5, 5, "events published")
    updates = {u for u, _, _ in log}
    assert len(updates) == 1, f"all in one update: {log}"
    # Breadth-first in the order raised; each event reaches both handlers before the next event.
    assert [(h, d) for _, h, d in log] == [
        ("first", 1), ("second", 1),
        ("first", 2), ("second", 2), ("first", 11), ("second", 11),
        ("first", 3), ("second", 3), ("first", 12), ("second", 12),
    ]
    assert seen == [1, 2, 11, 3, 12], "publication order is raise order"


def test_a_stepped_simulation_runs_timers_when_due_and_never_waits_unasked(stepped: Simulation) -> None:
    fired: list[str] = []
    stepped.run_once()  # from now on this thread is the simulation's loop
    stepped.call_later(0.05, lambda: fired.append("timer"))
    assert stepped.run_once() == 0 and fired == [], "not due yet, and timeout 0 waits for nothing"
    assert stepped.run_once(timeout=5) == 1 and fired == ["timer"], "waits for the timer, not for the timeout"
    with pytest.raises(MeshError, match="stepped with run_once"):
        stepped.start()


def test_events_from_other_threads_and_processes_are_handled_one_at_a_time(sim: Simulation, network: MemoryNetwork, mesh: str) -> None:
    active = []
    overlap = []
    got: list[Any] = []

    def handler(event: Event) -> None:
        active.append(1)
        if len(active) > 1:
            overlap.append(event)
        got.append((event.embodiment, event.data))
        active.pop()

    subscribed = threading.Event()

    def subscribe() -> None:
        sim.on_event(handler, embodiment="*", component="sensor")
        subscribed.set()

    sim.call(subscribe)
    assert subscribed.wait(5), "subscription"
    with MemoryTransport(network, "phone") as phone, Simulation(phone, mesh=mesh, embodiment="phone") as other:
        threads = [threading.Thread(target=lambda i=i: sim.raise_event("sensor", "tick", i)) for i in range(20)]
        for t in threads:
            t.start()
        for i in range(20):
            other.raise_event("sensor", "tick", 100 + i)
        for t in threads:
            t.join(5)
        wait_for(lambda: len(got) == 40, 5, "40 events handled")
    assert not overlap
    assert [d for e, d in got if e == "phone"] == list(range(100, 120)), "remote events keep their order"


def test_idle_loop_blocks_without_polling(sim: Simulation) -> None:
    sim.add(Recorder())
    wait_for(lambda: sim.updates >= 1, 5, "first update")
    before = sim.updates
    tid = next(t.native_id for t in threading.enumerate() if t.name == "ion-robot")
    stat = f"/proc/self/task/{tid}/stat"

    def cpu_ticks() -> int:
        with open(stat) as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])

    ticks = cpu_ticks()
    threading.Event().wait(0.5)  # an observation window: nothing is expected to happen in it
    assert sim.updates == before, "no update runs without work"
    assert cpu_ticks() - ticks == 0, "the idle loop burnt CPU"
    with open(stat) as f:
        assert f.read().rsplit(")", 1)[1].split()[0] == "S"


def test_close_answers_pending_requests_and_is_idempotent(transport: MemoryTransport, mesh: str) -> None:
    sim = Simulation(transport, mesh=mesh, embodiment="robot").start()
    sim.add(Recorder())
    release = threading.Event()
    sim.call(lambda: release.wait(5))
    pending = [sim.request("arbiter", "claim", Claim(i)) for i in range(3)]
    closer = threading.Thread(target=sim.close)
    closer.start()
    release.set()
    closer.join(10)
    outcomes = [f.result(5) for f in pending]
    assert all(o.status in ("accepted", "rejected") for o in outcomes)
    sim.close()
    assert sim.request("arbiter", "claim", Claim(0)).result(1).status == "rejected"
    with pytest.raises(ClosedError):
        sim.call(lambda: None)


def test_duplicate_component_names_are_refused(sim: Simulation) -> None:
    sim.add(Recorder("x"))
    with pytest.raises(MeshError, match="'x'"):
        sim.add(Recorder("x"))


def test_runaway_event_storm_is_carried_over_not_dropped(sim: Simulation) -> None:
    count = [0]

    class Storm(Component):
        def attach(self, s: Simulation) -> None:
            s.on_event(self.on, component="storm")

        def on(self, event: Event) -> None:
            count[0] += 1
            if event.data < 25_000:
                self.raise_event("e", event.data + 1)

    storm = sim.add(Storm("storm"))
    start = sim.updates
    sim.call(lambda: storm.raise_event("e", 1))
    wait_for(lambda: count[0] == 25_000, 20, "all storm events handled")
    assert sim.updates - start >= 3, "spread over several updates"
    assert os.getpid()


class Picky(Mind):
    """Refuses messages it cannot take, with the reason (as the FAtiMA connector does)."""

    def __init__(self) -> None:
        super().__init__("picky")
        self.taken: list[Any] = []

    def on_message(self, data: dict[str, Any]) -> None:
        if "refuse" in data:
            raise MeshError(f"mind {self.name!r} cannot take {data['refuse']!r}")
        if "busy" in data:
            raise RequestRejected("not now", reason="not now", code=Code.BUSY)
        if "crash" in data:
            raise RuntimeError("mind bug")
        self.taken.append(data["note"])


def test_a_message_the_mind_refuses_fails_alone(stepped: Simulation) -> None:
    """Each message of one update gets its own answer: one the mind refuses (or fails on) does not
    reject the others of its batch."""
    mind = stepped.add(Picky())
    stepped.run_once()
    futures = [stepped.request("picky", "message", MindMessage(data)) for data in
               ({"note": 1}, {"refuse": "x"}, {"busy": True}, {"crash": True}, {"note": 2})]
    state = stepped.request("picky", "state", MindState())
    assert stepped.run_once() == 6, "one update: the six requests are one batch"
    outcomes = [f.result(5) for f in futures]
    assert [o.status for o in outcomes] == ["accepted", "rejected", "rejected", "rejected", "accepted"]
    assert (outcomes[1].reason, outcomes[1].code) == ("mind 'picky' cannot take 'x'", Code.INVALID)
    assert (outcomes[2].reason, outcomes[2].code) == ("not now", Code.BUSY)
    assert "RuntimeError: mind bug" in outcomes[3].reason and outcomes[3].code == Code.HANDLER_FAILED
    assert state.result(5).status == "accepted" and isinstance(mind, Picky) and mind.taken == [1, 2]
