"""Hostile input matrix: every door through which bytes come in, against every kind of bad input.

Doors: requests to a store (``rq/bb/*``, ``rq/wm/*``) and to the manager (``rq/manager/act``),
events arriving on an event key, property values, storage reads, identity documents in
``migrate_prepare``, migration records in a state folder, and configuration files (architecture,
rules, library, world model, planner JSON spec). Kinds: oversized, malformed/garbage, wrong
type or tag, deeply nested, invalid names, huge strings, NaN/inf, unknown fields, huge or
negative integers, non-UTF-8.

Each row asserts that the input is refused with a clear outcome or error naming the key, file or
line; that the component keeps working (a valid request right after succeeds); and that nothing
was written or applied. Components run in-process on the memory transport; two rows go through
a real daemon over zenoh.

Rows with a ``found`` note caught a bug when this matrix was written (fixed since); the note says
what went wrong, so a regression is recognised at once.
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import pytest

from cmion_mesh import keys, xmlsafe
from cmion_mesh.body.architecture import load_architecture
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.library import load_library
from cmion_mesh.body.remote import CompetencyHost
from cmion_mesh.body.rules import load_rules
from cmion_mesh.client import MeshClient
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError, OutcomeUnknown, ProtocolError, XmlError
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import (
    MAX_DEPTH,
    MAX_PAYLOAD,
    Act,
    ActionStatus,
    AddContainer,
    Event,
    MigratePrepare,
    MigrateStatus,
    Outcome,
    Property,
    SetProperty,
    StartRun,
    decode,
    encode,
)
from cmion_mesh.migration import custody, identity, signing
from cmion_mesh.migration import ledger as records
from cmion_mesh.migration.identity import Identity
from cmion_mesh.migration.manager import MigrationManager
from cmion_mesh.minds.planner.spec import load_spec
from cmion_mesh.statedir import LOCK_FILE
from cmion_mesh.storage import WorldModel
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .conftest import CMION_2011
from .helpers.custody_helpers import Holder

pytestmark = pytest.mark.timeout(60)

WAIT = 5.0  # seconds: an answer normally takes a millisecond


# --- helpers -----------------------------------------------------------------------------------------


class Wave(Competency):
    """A competency that succeeds at once."""

    type = "Wave"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        return True


class Probe(Component):
    """Records the events raised under ``cmion/<mesh>/*/ev/outside/*`` (where the intruder publishes)."""

    def __init__(self) -> None:
        super().__init__("probe")
        self.seen: list[Event] = []

    def attach(self, sim: Simulation) -> None:
        sim.on_event(self.seen.append, embodiment="*", component="outside")


RULES = b"""<?xml version="1.0"?>
<CompetencyManagerRules>
  <Rule>
    <MindAction Name="Wave"/>
    <CompetencyExecutionPlan><Competency ID="1" Type="Wave"/></CompetencyExecutionPlan>
  </Rule>
</CompetencyManagerRules>
"""


def mp(**fields: Any) -> bytes:
    """A MessagePack map built by hand, as a hostile peer would."""
    return msgspec.msgpack.encode(fields)


_MARK = "\x00\x01\x02"  # a 3-character str encodes as a3 00 01 02


def bad_utf8(**fields: Any) -> bytes:
    """``mp(**fields)`` with every string equal to ``_MARK`` replaced by three bytes that are not UTF-8."""
    return mp(**fields).replace(b"\xa3\x00\x01\x02", b"\xa3\xff\xfe\xfd")


def nested(depth: int, leaf: Any = 1) -> Any:
    value = leaf
    for _ in range(depth):
        value = [value]
    return value


def deep_msgpack(depth: int) -> bytes:
    """A MessagePack array nested ``depth`` levels (built as bytes: Python would refuse to encode it)."""
    return b"\x91" * depth + b"\x01"


def ask(transport: MemoryTransport, key: str, payload: bytes, *, timeout: float = WAIT) -> Outcome:
    """Send raw bytes as a query; the answer must be exactly one reply that decodes as an ``Outcome``."""
    replies = transport.get(key, payload, timeout=timeout)
    assert len(replies) == 1, f"{key}: expected exactly one reply, got {len(replies)} (no reply = outcome unknown)"
    assert replies[0].ok, replies[0].payload[:200]
    outcome: Outcome = decode(replies[0].payload, Outcome, where=key)
    return outcome


def assert_refused(outcome: Outcome, *fragments: str) -> None:
    assert outcome.status == "rejected", outcome
    for fragment in fragments:
        assert fragment in outcome.reason, f"{fragment!r} not in {outcome.reason!r}"


@pytest.fixture
def rules_file(tmp_path: Path) -> Path:
    path = tmp_path / "rules.xml"
    path.write_bytes(RULES)
    return path


@pytest.fixture
def attacker(network: MemoryNetwork) -> Iterator[MemoryTransport]:
    with MemoryTransport(network, "intruder") as t:
        yield t


@pytest.fixture
def robot(network: MemoryNetwork, mesh: str, rules_file: Path, tmp_path: Path) -> Iterator[Embodiment]:
    transport = MemoryTransport(network, "robot")
    try:
        with Embodiment("robot", mesh=mesh, transport=transport, world_model_init=CMION_2011 / "worldModelInit.xml",
                        rules=rules_file, competencies=[Wave()], components=[Probe(), CompetencyHost(Wave(name="waver"))],
                        state_dir=tmp_path / "robot-state") as e:
            settled(e.sim)
            yield e
    finally:
        transport.close()


def settled(sim: Simulation) -> None:
    """Return once the loop has run everything posted so far (components attach on the loop)."""
    done = threading.Event()
    sim.call(done.set)
    assert done.wait(WAIT), "the update loop is stuck"


def rq(mesh: str, component: str, name: str) -> str:
    return keys.request_key(mesh, "robot", component, name)


# --- requests to a store ----------------------------------------------------------------------------

UNICODE_BUG = ("messages.decode lets UnicodeDecodeError (not a ProtocolError) escape for a str that is not UTF-8: "
               "_on_query raises, the query is never answered (outcome unknown instead of rejected)")

SP = {"type": "set_property", "container": "", "name": "p", "value": 1}


@dataclass(frozen=True)
class StoreRow:
    id: str
    store: str
    request: str
    payload: bytes
    fragments: tuple[str, ...]
    found: str = ""  # the bug this row found when it was written (fixed since): why the row exists


def _sp(**changes: Any) -> bytes:
    return mp(**{**SP, **changes})


STORE_ROWS = [
    StoreRow("empty payload", "bb", "set_property", b"", ("malformed message",)),
    StoreRow("garbage", "bb", "set_property", b"\xc1\xc1garbage", ("malformed message",)),
    StoreRow("oversized", "bb", "set_property", _sp(value="x" * MAX_PAYLOAD), (f"exceeds the {MAX_PAYLOAD}-byte cap",)),
    StoreRow("not a map", "bb", "set_property", msgspec.msgpack.encode([1, 2, 3]), ("malformed message", "Expected `object`")),
    StoreRow("unknown tag", "bb", "set_property", _sp(type="drop_table"), ("malformed message", "drop_table")),
    StoreRow("no tag, although the key says which message it is", "bb", "set_property", mp(container="", name="p", value=1),
             ("malformed message", "missing required field `type`")),
    StoreRow("empty map", "bb", "set_property", mp(), ("malformed message", "missing required field `type`")),
    StoreRow("tag of another request", "bb", "set_property", mp(type="remove_property", container="", name="p"),
             ("malformed message", "remove_property")),
    StoreRow("wrong field type", "bb", "set_property", _sp(name=5), ("malformed message", "$.name")),
    StoreRow("missing field", "bb", "set_property", mp(type="set_property", container="", value=1), ("malformed message", "name")),
    StoreRow("value nested too deep", "bb", "set_property", _sp(value=nested(MAX_DEPTH + 1)), (f"nested deeper than {MAX_DEPTH}",)),
    StoreRow("value nested past the recursion limit", "bb", "set_property",
             mp(**SP).replace(b"\xa5value\x01", b"\xa5value" + deep_msgpack(5000)), ("nested too deeply",)),
    StoreRow("binary value", "bb", "set_property", _sp(value=b"\x00bin"), ("bytes is not plain data",)),
    StoreRow("extension value", "bb", "set_property", _sp(value=msgspec.msgpack.Ext(5, b"x")), ("is not plain data",)),
    StoreRow("non-string map key", "bb", "set_property", _sp(value={1: "one"}), ("map key 1 is not a string",)),
    StoreRow("empty name", "bb", "set_property", _sp(name=""), ("property is empty",)),
    *[StoreRow(f"name with {c!r}", "bb", "set_property", _sp(name=f"a{c}b"), (f"contains {c!r}",)) for c in "/*$#?"],
    StoreRow("name starting with @", "bb", "set_property", _sp(name="@alive"), ("starts with '@'",)),
    StoreRow("name with control character", "bb", "set_property", _sp(name="a\nb"), ("control characters",)),
    StoreRow("padded name", "bb", "set_property", _sp(name=" p "), ("white space",)),
    StoreRow("huge name", "bb", "set_property", _sp(name="n" * 100_000), (f"longer than {keys.MAX_NAME}",)),
    StoreRow("container path with a wildcard", "bb", "set_property", _sp(container="a/*"), ("container path element", "'*'")),
    StoreRow("container path with an empty element", "bb", "set_property", _sp(container="a//b"), ("container path element is empty",)),
    StoreRow("missing container", "bb", "set_property", _sp(container="nowhere"), ("no container 'nowhere'",)),
    StoreRow("world-model entity of a wrong kind", "wm", "add_container", mp(type="add_container", container="", name="x", kind="ghost"),
             ("kind 'ghost' is not one of",)),
    StoreRow("unknown request name", "bb", "drop_table", _sp(), ("has no request 'drop_table'",)),
    StoreRow("non-UTF-8 name", "bb", "set_property", bad_utf8(**{**SP, "name": _MARK}), ("malformed message",), UNICODE_BUG),
    StoreRow("non-UTF-8 tag", "bb", "set_property", bad_utf8(**{**SP, "type": _MARK}), ("malformed message",), UNICODE_BUG),
    StoreRow("non-UTF-8 string value", "wm", "set_property", bad_utf8(**{**SP, "container": "Vase", "value": _MARK}),
             ("malformed message",), UNICODE_BUG),
]


def _params(rows: list[Any]) -> list[Any]:
    return [pytest.param(row, id=row.id) for row in rows]


@pytest.mark.parametrize("row", _params(STORE_ROWS))
def test_store_refuses_hostile_request(row: StoreRow, robot: Embodiment, attacker: MemoryTransport, mesh: str) -> None:
    store = robot.blackboard if row.store == "bb" else robot.world_model
    before = store.tree()
    changes: list[str] = []
    client = MeshClient(attacker, mesh)
    with client.watch(f"cmion/{mesh}/robot/{row.store}/**", lambda key, _: changes.append(key)):
        key = rq(mesh, row.store, row.request)
        outcome = ask(attacker, key, row.payload, timeout=2.0)
        assert_refused(outcome, *row.fragments)
        # A payload that does not decode is refused naming the key; one that does, naming the store.
        assert outcome.reason.startswith((f"{key}: ", f"{row.store}: ", f"{row.store}/", f"component {row.store!r}")), outcome
        assert store.tree() == before, "nothing was written"
        # The store keeps working, and the refused request published nothing before this change.
        client.set_property("robot", row.store, "" if row.store == "bb" else "Vase", "after", 1)
        wait_for(lambda: changes, WAIT, "the valid write is published")
    assert changes == [f"cmion/{mesh}/robot/{row.store}/{'' if row.store == 'bb' else 'Vase/'}after"]


@pytest.mark.parametrize(
    ("payload", "stored"),
    [
        pytest.param(_sp(extra="ignored", more={"a": 1}), 1, id="unknown fields are ignored (forward compatible)"),
        pytest.param(_sp(value=float("inf")), float("inf"), id="inf is plain data"),
        pytest.param(_sp(value=2**64 - 1), 2**64 - 1, id="largest MessagePack int"),
        pytest.param(_sp(value=-(2**63)), -(2**63), id="smallest MessagePack int"),
        pytest.param(_sp(value="é" * 1_000_000), "é" * 1_000_000, id="huge string under the cap"),
        pytest.param(_sp(value=nested(MAX_DEPTH)), nested(MAX_DEPTH), id="nested exactly to the limit"),
    ],
)
def test_store_takes_odd_but_valid_values(payload: bytes, stored: Any, robot: Embodiment, attacker: MemoryTransport, mesh: str) -> None:
    outcome = ask(attacker, rq(mesh, "bb", "set_property"), payload)
    assert outcome.status == "accepted", outcome
    assert robot.blackboard.get("", "p") == stored
    read = MeshClient(attacker, mesh).get_property("robot", "bb", "", "p")
    assert read.value == stored


def test_store_takes_nan(robot: Embodiment, attacker: MemoryTransport, mesh: str) -> None:
    assert ask(attacker, rq(mesh, "bb", "set_property"), _sp(value=float("nan"))).status == "accepted"
    value = MeshClient(attacker, mesh).get_property("robot", "bb", "", "p").value
    assert isinstance(value, float) and value != value


def test_container_nesting_is_bounded(robot: Embodiment, attacker: MemoryTransport, mesh: str) -> None:
    key = rq(mesh, "bb", "add_container")
    refused = None
    for depth in range(1100):
        outcome = ask(attacker, key, mp(type="add_container", container="/".join(["a"] * depth), name="a"))
        if outcome.status != "accepted":
            refused = outcome
            break
    assert refused is not None and "deep" in refused.reason, "some depth is refused, saying why"
    robot.blackboard.tree()
    assert MeshClient(attacker, mesh).read(f"cmion/{mesh}/robot/bb/**"), "wildcard reads still answer"


def test_read_selector_with_many_double_stars_is_cheap(robot: Embodiment, attacker: MemoryTransport, mesh: str) -> None:
    for depth in range(20):
        robot.blackboard.apply_now(AddContainer("/".join(["a"] * depth), "a"))
    started = time.perf_counter()
    assert MeshClient(attacker, mesh).read(f"cmion/{mesh}/robot/bb/" + "**/a/" * 10 + "b", timeout=30) == {}
    assert time.perf_counter() - started < 0.1


def test_key_matching_is_polynomial() -> None:
    started = time.perf_counter()
    assert not keys.matches_chunks(["**", "a"] * 10 + ["b"], ["a"] * 20)
    assert time.perf_counter() - started < 0.05


def test_hostile_read_selectors_are_answered(robot: Embodiment, attacker: MemoryTransport, mesh: str) -> None:
    client = MeshClient(attacker, mesh)
    prefix = f"cmion/{mesh}/robot/wm"
    for selector in (f"{prefix}/$*", f"{prefix}/Vase/" + "x" * 100_000, f"{prefix}/" + "/".join(["*"] * 500),
                     f"{prefix}/**/**/**/**/nothing", f"{prefix}/Vase/broken/deeper"):
        started = time.perf_counter()
        assert client.read(selector, timeout=2.0) == {}, selector[:80]
        assert time.perf_counter() - started < 1.0
    assert client.get_property("robot", "wm", "Vase", "broken").value == "False"


# --- requests to the manager -------------------------------------------------------------------------

DEADLINE_BUG = ("Act.deadline is not checked: an infinite or huge deadline reaches Simulation.call_later, and "
                "queue.get(timeout=...) raises OverflowError on the update loop, which dies: the embodiment stops answering")
DEADLINE_POLICY = ("Act.deadline is not checked: a negative or NaN deadline is silently taken as 'no deadline' "
                   "instead of being refused")
ACT = {"type": "act", "name": "Wave"}


@dataclass(frozen=True)
class ManagerRow:
    id: str
    request: str
    payload: bytes
    fragments: tuple[str, ...]
    found: str = ""  # the bug this row found when it was written (fixed since): why the row exists


MANAGER_ROWS = [
    ManagerRow("garbage", "act", b"\xff\x00\x01", ("malformed message",)),
    ManagerRow("oversized", "act", mp(**ACT, subject="s" * MAX_PAYLOAD), ("byte cap",)),
    ManagerRow("storage write sent as an action", "act", _sp(), ("malformed message", "set_property")),
    ManagerRow("parameters not strings", "act", mp(**ACT, parameters=[1, 2]), ("malformed message", "$.parameters[0]")),
    ManagerRow("parameters nested", "act", mp(**ACT, parameters=nested(40)), ("malformed message",)),
    ManagerRow("name of the wrong type", "act", mp(type="act", name={"a": 1}), ("malformed message", "$.name")),
    ManagerRow("deadline of the wrong type", "act", mp(**ACT, deadline="soon"), ("malformed message", "$.deadline")),
    ManagerRow("unknown action", "act", mp(type="act", name="Explode"), ("no rule matches action 'Explode'",)),
    ManagerRow("empty action name", "act", mp(type="act", name=""), ("no rule matches",)),
    ManagerRow("infinite deadline", "act", mp(**ACT, deadline=float("inf")), ("deadline",), DEADLINE_BUG),
    ManagerRow("huge deadline", "act", mp(**ACT, deadline=1e12), ("deadline",), DEADLINE_BUG),
    ManagerRow("negative deadline", "act", mp(**ACT, deadline=-1.0), ("deadline",), DEADLINE_POLICY),
    ManagerRow("NaN deadline", "act", mp(**ACT, deadline=float("nan")), ("deadline",), DEADLINE_POLICY),
    ManagerRow("huge action id", "act", mp(**ACT, action_id="i" * 1_000_000), ("action id",),
               "Act fields have no cap but the payload's: the manager keeps the last 1024 reports, so 1024 acts "
               "with 16 MiB ids (even refused ones) pin 16 GiB"),
    ManagerRow("cancel of an unknown id", "cancel", mp(type="cancel_action", action_id="nope"), ("no running action with id 'nope'",)),
    ManagerRow("status with an odd id", "status", mp(type="action_status", action_id=[1, {"x": None}]),
               ("malformed message", "$.action_id")),
    ManagerRow("status of an unknown id", "status", mp(type="action_status", action_id="nope"), ("no action with id 'nope'",)),
    ManagerRow("status in the old untyped form", "status", mp(type="request", args={"action_id": "nope"}),
               ("malformed message", "'request'")),
    ManagerRow("non-UTF-8 action name", "act", bad_utf8(type="act", name=_MARK), ("malformed message",), UNICODE_BUG),
]


@pytest.mark.parametrize("row", _params(MANAGER_ROWS))
def test_manager_refuses_hostile_request(row: ManagerRow, robot: Embodiment, attacker: MemoryTransport, mesh: str) -> None:
    assert_refused(ask(attacker, rq(mesh, "manager", row.request), row.payload, timeout=2.0), *row.fragments)
    assert robot.manager.active == [], "no action was started"
    # The manager (and the update loop behind it) keeps working.
    outcome = ask(attacker, rq(mesh, "manager", "act"), encode(Act("Wave", action_id="after")), timeout=2.0)
    assert outcome.status == "accepted", outcome
    wait_for(lambda: _status(attacker, mesh, "after") == "succeeded", WAIT, "the valid action succeeds")


def _status(transport: MemoryTransport, mesh: str, action_id: str) -> str:
    outcome = ask(transport, rq(mesh, "manager", "status"), encode(ActionStatus(action_id)), timeout=2.0)
    return str(outcome.value.get("status")) if isinstance(outcome.value, dict) else ""


def test_remote_competency_refuses_non_plain_parameters(robot: Embodiment, attacker: MemoryTransport, mesh: str) -> None:
    payload = mp(type="start_run", run_id="r1", parameters={"blob": b"\x00", "ext": msgspec.msgpack.Ext(1, b"")})
    assert_refused(ask(attacker, rq(mesh, "waver", "start"), payload), "not plain data")
    assert ask(attacker, rq(mesh, "waver", "start"), encode(StartRun("r2", {"speed": 1}))).status == "accepted"


def test_a_far_timer_does_not_kill_the_update_loop(robot: Embodiment, attacker: MemoryTransport, mesh: str) -> None:
    robot.sim.call_later(1e300, lambda: None)
    settled(robot.sim)  # the timer is armed: the loop now waits for it, or for work
    outcome = ask(attacker, rq(mesh, "bb", "set_property"), _sp(), timeout=2.0)
    assert outcome.status == "accepted"


# --- events --------------------------------------------------------------------------------------------

EV = {"type": "event", "embodiment": "intruder", "component": "outside", "name": "Hello", "data": None}


@dataclass(frozen=True)
class EventRow:
    id: str
    payload: bytes
    fragment: str
    found: str = ""  # the bug this row found when it was written (fixed since): why the row exists


def _ev(**changes: Any) -> bytes:
    return mp(**{**EV, **changes})


EVENT_ROWS = [
    EventRow("garbage", b"\xc1garbage", "malformed message"),
    EventRow("empty payload", b"", "malformed message"),
    EventRow("oversized", _ev(data="d" * MAX_PAYLOAD), "byte cap"),
    EventRow("a property, not an event", mp(type="property", value=1), "malformed message"),
    EventRow("fields name another key (spoofed embodiment)", _ev(embodiment="robot"), "the event says it is robot/outside/Hello"),
    EventRow("fields name another event", _ev(name="Other"), "the event says it is"),
    EventRow("invalid name in the fields", _ev(component="out/side"), "contains '/'",
             "Simulation._on_remote_event logs the InvalidName alone: the warning does not say on which key the event came"),
    EventRow("data nested too deep", _ev(data=nested(MAX_DEPTH + 1)), "nested deeper"),
    EventRow("data nested past the recursion limit", mp(**EV).replace(b"\xa4data\xc0", b"\xa4data" + deep_msgpack(5000)),
             "nested too deeply"),
    EventRow("binary data", _ev(data={"blob": b"\x00"}), "bytes is not plain data"),
    EventRow("seq of the wrong type", _ev(seq="first"), "$.seq"),
    EventRow("non-UTF-8 string in the data", bad_utf8(**{**EV, "data": _MARK}), "malformed message",
             "messages.decode raises UnicodeDecodeError: the transport worker logs a traceback instead of the "
             "'ignored event' warning naming the key"),
]


@pytest.mark.parametrize("row", _params(EVENT_ROWS))
def test_hostile_event_is_ignored_with_a_warning(row: EventRow, robot: Embodiment, attacker: MemoryTransport, mesh: str,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    probe = robot.sim.component("probe")
    assert isinstance(probe, Probe)
    key = keys.event_key(mesh, "intruder", "outside", "Hello")
    with caplog.at_level(logging.WARNING):
        attacker.publish(key, row.payload)
        attacker.delete(key)  # a delete on an event key means nothing
        attacker.publish(key, encode(Event("intruder", "outside", "Hello", {"n": 1})))
        wait_for(lambda: probe.seen, WAIT, "the valid event arrives")
    assert [e.data for e in probe.seen] == [{"n": 1}], "only the valid event was dispatched"
    warnings = [r.getMessage() for r in caplog.records if r.name == "cmion_mesh.ion" and "ignored event" in r.getMessage()]
    assert len(warnings) == 1 and key in warnings[0] and row.fragment in warnings[0], warnings
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], "no handler failed"


# --- replies a hostile peer gives to a client ----------------------------------------------------------


@pytest.mark.parametrize(
    "reply",
    [
        pytest.param(b"\xc1", id="garbage"),
        pytest.param(mp(type="outcome", status="maybe"), id="unknown status"),
        pytest.param(mp(type="property", value=nested(MAX_DEPTH + 1)), id="value nested too deep"),
        pytest.param(mp(type="property", value=b"\x00"), id="binary value"),
    ],
)
def test_client_refuses_hostile_replies(reply: bytes, network: MemoryNetwork, mesh: str) -> None:
    """A hostile peer answering a client's reads and requests: skipped, or an error naming the key."""

    def answer(query: Any) -> None:
        try:
            query.reply(query.key, reply)
        finally:
            query.finish()

    with MemoryTransport(network, "fake") as fake, MemoryTransport(network, "client") as mine:
        fake.declare_queryable(f"cmion/{mesh}/fake/**", answer)
        client = MeshClient(mine, mesh)
        assert client.read(f"cmion/{mesh}/fake/bb/**") == {}, "unreadable entries are skipped"
        key = keys.storage_key(mesh, "fake", "bb", (), "p")
        with pytest.raises(ProtocolError, match=f"^{key}: "):
            client.get_property("fake", "bb", "", "p")
        key = keys.request_key(mesh, "fake", "bb", "set_property")
        with pytest.raises(OutcomeUnknown, match=f"^{key}: "):
            client.write("fake", "bb", SetProperty("", "p", 1), timeout=1.0)


@pytest.mark.parametrize(
    "hostile",
    [
        pytest.param({"b": b"\xc1"}, id="garbage"),
        pytest.param({"b": b""}, id="empty"),
        pytest.param({"b": mp(type="property", value=nested(MAX_DEPTH + 1))}, id="value nested too deep"),
        pytest.param({"b": mp(type="property", value=b"\x00")}, id="binary value"),
        pytest.param({"b": mp(type="outcome", status="accepted")}, id="another message"),
        # Two messages in one payload and none in the next: decoded as one array, every entry
        # between them would shift by one and carry its neighbour's value.
        pytest.param({"b": encode(Property(2)) + encode(Property(3)), "d": b""}, id="misaligned"),
        pytest.param({"b": encode(Property(2)) + b"\xa5", "d": b"abcde"}, id="a string across two"),
    ],
)
def test_a_wildcard_read_keeps_each_good_entry_with_its_own_value(hostile: dict[str, bytes], network: MemoryNetwork,
                                                                   mesh: str) -> None:
    """A store answering many keys is decoded in one call; one hostile payload among them costs
    only its own entry (and one that swallows its neighbour's bytes, only the two)."""
    good = {name: encode(Property(i)) for i, name in enumerate("acdef")}
    payloads = {**good, **hostile}

    def answer(query: Any) -> None:
        try:
            for name, payload in sorted(payloads.items()):
                query.reply(keys.storage_key(mesh, "fake", "bb", (), name), payload)
        finally:
            query.finish()

    with MemoryTransport(network, "fake") as fake, MemoryTransport(network, "client") as mine:
        fake.declare_queryable(f"cmion/{mesh}/fake/**", answer)
        got = MeshClient(mine, mesh).read(f"cmion/{mesh}/fake/bb/**")
    want = {keys.storage_key(mesh, "fake", "bb", (), name): decode(payload, Property)
            for name, payload in good.items() if name not in hostile}
    assert got == want
    assert list(got) == sorted(want), "in key order"


# --- identity documents in migrate_prepare ------------------------------------------------------------

COMPANION = "s"
SOURCE = "robot"
WHERE = f"identity of {COMPANION} from {SOURCE}"


def doc(body: str = "", *, companion: str = COMPANION, epoch: str = "1", version: str = "1") -> bytes:
    """An identity document, one element per line so that errors can name a line."""
    return (f'<?xml version="1.0" encoding="UTF-8"?>\n<Identity SchemaVersion="{version}" Companion="{companion}" '
            f'Epoch="{epoch}">\n{body}</Identity>\n').encode()


def section(content: str, component: str = "mind") -> str:
    return f'<Section Component="{component}">{content}</Section>\n'


def billion_laughs(root: str) -> bytes:
    """Nine levels of entities, each ten of the one below: 10^9 "lol" once expanded. The DOCTYPE is on line 2."""
    entities = [' <!ENTITY lol0 "lol">'] + [f' <!ENTITY lol{i} "{f"&lol{i - 1};" * 10}">' for i in range(1, 10)]
    return (f'<?xml version="1.0"?>\n<!DOCTYPE {root} [\n' + "\n".join(entities) + f"\n]>\n<{root}>&lol9;</{root}>\n").encode()


@dataclass(frozen=True)
class PrepareRow:
    id: str
    document: bytes
    fragments: tuple[str, ...]
    companion: str = COMPANION
    source: str = SOURCE
    tamper: Callable[[MigratePrepare], bytes] | None = None
    found: str = ""  # the bug this row found when it was written (fixed since): why the row exists


def _signed(companion: str, epoch: int, attempt: str, source: str, target: str, document: bytes, private: bytes) -> MigratePrepare:
    """A prepare made by ``source`` holding ``companion`` since its birth at ``epoch`` (key ``private``)."""
    return Holder(companion, source, epoch, private=private).prepare(target, document, attempt)


def _bad_utf8_chain(message: MigratePrepare) -> bytes:
    raw = custody.encode_chain(custody.decode_chain(message.chain)).replace(COMPANION.encode(), b"\xff", 1)
    return encode(msgspec.structs.replace(message, chain=raw))


PREPARE_ROWS = [
    PrepareRow("garbage message", b"", ("malformed message", "rq/migration/prepare"),
               tamper=lambda m: b"\x00garbage"),
    PrepareRow("document over the payload cap", b"<Identity" + b" " * MAX_PAYLOAD + b"/>", ("byte cap",)),
    PrepareRow("malformed XML", doc(section("{}")).replace(b"</Section>", b"</Sect>"), (f"{WHERE}:3:", "malformed XML")),
    PrepareRow("XXE", b'<!DOCTYPE Identity [<!ENTITY x SYSTEM "file:///etc/passwd">]>\n' + doc("&x;"),
               (f"{WHERE}:1:", "internal DTD subset")),
    PrepareRow("billion laughs", billion_laughs("Identity"), (f"{WHERE}:2:", "DOCTYPE")),
    PrepareRow("undeclared entity", doc(section("&xxe;")), (f"{WHERE}:3:", "entity reference &xxe;")),
    PrepareRow("not UTF-8", doc(section('"caf\xe9"')).replace("é".encode(), b"\xe9"), (WHERE, "not valid UTF-8")),
    PrepareRow("UTF-32", "<Identity/>".encode("utf-32"), (WHERE, "UTF-32")),
    PrepareRow("encoding name with a NUL", doc().replace(b"UTF-8", b"UTF\x00-8"), (f"{WHERE}:1:", "encoding")),
    PrepareRow("wrong root element", b"<Identidad/>", (WHERE, "does not match schema identity.xsd")),
    PrepareRow("missing Epoch", doc().replace(b' Epoch="1"', b""), (f"{WHERE}:2:", "Epoch")),
    PrepareRow("negative Epoch", doc(epoch="-1"), (f"{WHERE}:2:", "'-1'")),
    PrepareRow("unknown attribute", doc().replace(b"<Identity ", b'<Identity Admin="yes" '), (f"{WHERE}:2:", "Admin")),
    PrepareRow("unknown element", doc("<Root/>\n"), (f"{WHERE}:3:", "Root")),
    PrepareRow("same section twice", doc(section("1") + section("2")), (WHERE, "does not match schema")),
    PrepareRow("invalid section name", doc(section("1", component="a/b")), (f"{WHERE}:3:", "Component")),
    PrepareRow("nested too deep", doc(section("<a><b><c><d><e><f><g><h/></g></f></e></d></c></b></a>")), (WHERE, "nested deeper than 8")),
    PrepareRow("too many elements", doc(section("1", "m0") + "".join(f"<X{i}/>" for i in range(2001))), (WHERE, "more than 2000 elements")),
    PrepareRow("document for another companion", doc(companion="t"), ("document is for 't' at epoch 1, not 's' at epoch 1",)),
    PrepareRow("document at another epoch", doc(epoch="7"), ("document is for 's' at epoch 7",)),
    PrepareRow("section not JSON", doc(section("{oops")), (f"{WHERE}:3:", "section 'mind': not plain JSON data")),
    PrepareRow("section JSON with trailing text", doc(section('{"a": 1} {"b": 2}')), (f"{WHERE}:3:", "not plain JSON data")),
    PrepareRow("section nested too deep", doc(section("[" * 40 + "]" * 40)), (f"{WHERE}:3:", "nested deeper than 32")),
    PrepareRow("section out of range number", doc(section("1e400")), (f"{WHERE}:3:", "out of range")),
    PrepareRow("section nested past the recursion limit", doc(section("[" * 5000 + "]" * 5000)), (f"{WHERE}:3:", "section 'mind'")),
    PrepareRow("Epoch of 5000 digits", doc(epoch="9" * 5000), (WHERE, "Epoch")),
    PrepareRow("companion with a line feed", doc(companion="s&#10;"), ("companion",), companion="s\n"),
    # Refused because the sender in the (per-sender) key, a checked name, can never be 'no/where'.
    PrepareRow("source that is not a name", doc(), ("no/where",), source="no/where"),
    PrepareRow("unsigned", doc(), ("bad signature on the offer",), tamper=lambda m: encode(msgspec.structs.replace(m, proof=b""))),
    PrepareRow("bad signature", doc(), ("bad signature on the offer",),
               tamper=lambda m: encode(msgspec.structs.replace(m, proof=bytes(64)))),
    PrepareRow("chain garbage", doc(), ("malformed custody chain",), tamper=lambda m: encode(msgspec.structs.replace(m, chain=b"\xc1"))),
    PrepareRow("chain empty", doc(), ("no chain of custody",),
               tamper=lambda m: encode(msgspec.structs.replace(m, chain=custody.encode_chain([])))),
    PrepareRow("birth link not self-signed", doc(), ("bad self-signature",),
               tamper=lambda m: encode(msgspec.structs.replace(m, chain=custody.encode_chain(
                   [msgspec.structs.replace(custody.decode_chain(m.chain)[0], signature=bytes(64))])))),
    PrepareRow("chain of another companion", doc(), ("custody link 0 is of 't'",),
               tamper=lambda m: encode(msgspec.structs.replace(m, chain=custody.encode_chain(
                   [custody.birth("t", SOURCE, signing.new_key(), b"")])))),
    PrepareRow("another target", doc(), ("this is 'screen', not 'phone'",),
               tamper=lambda m: encode(msgspec.structs.replace(m, target="phone"))),
    PrepareRow("epoch as a string", doc(), ("malformed message", "$.epoch"),
               tamper=lambda m: msgspec.msgpack.encode({**msgspec.structs.asdict(m), "type": "migrate_prepare", "epoch": "1"})),
    PrepareRow("chain not UTF-8", doc(), ("malformed custody chain",), tamper=_bad_utf8_chain),
]


def migration_key(mesh: str, request: str, sender: str = SOURCE) -> str:
    """``.../rq/migration/<request>`` on ``screen``, in its per-sender form where the component wants one."""
    if request in getattr(MigrationManager, "sender_requests", frozenset()):
        return keys.request_key(mesh, "screen", "migration", request, sender)
    return keys.request_key(mesh, "screen", "migration", request)


@pytest.fixture
def screen(network: MemoryNetwork, mesh: str, tmp_path: Path) -> Iterator[tuple[Embodiment, Path]]:
    transport = MemoryTransport(network, "screen")
    state = tmp_path / "screen-state"
    try:
        with Embodiment("screen", mesh=mesh, transport=transport, state_dir=state) as e:
            settled(e.sim)
            yield e, state
    finally:
        transport.close()


@pytest.mark.parametrize("row", _params(PREPARE_ROWS))
def test_prepare_refuses_hostile_identity(row: PrepareRow, screen: tuple[Embodiment, Path], attacker: MemoryTransport,
                                          mesh: str) -> None:
    embodiment, state = screen
    key = migration_key(mesh, "prepare")
    private = signing.new_key()
    message = _signed(row.companion, 1, "a1", row.source, "screen", row.document, private)
    payload = row.tamper(message) if row.tamper else encode(message)
    outcome = ask(attacker, key, payload)
    assert_refused(outcome, *row.fragments)
    assert "gave no answer" not in outcome.reason
    assert sorted(p.name for p in state.iterdir() if p.name != LOCK_FILE) == [], "nothing was stored"
    assert embodiment.inhabitant is None
    # The migration component keeps working: a well-formed prepare is accepted.
    status = ask(attacker, migration_key(mesh, "status"), encode(MigrateStatus("s", "a1")))
    assert status.status == "accepted"
    good = _signed("s", 1, "a2", SOURCE, "screen", Identity("s", 1, {"mind": {"notes": ["hi"]}}).pack(), private)
    assert ask(attacker, key, encode(good)).status == "accepted"


def test_identity_over_its_own_cap_is_refused_unparsed() -> None:
    data = b"<Identity" + b" " * identity.MAX_DOCUMENT + b"/>"
    with pytest.raises(XmlError, match=rf"^<net>:1: document is larger than the limit of {identity.MAX_DOCUMENT} bytes"):
        identity.unpack(data, name="<net>")


# --- migration records in a state folder ----------------------------------------------------------------

GOOD_RECORD = {"companion": "s", "state": "active", "epoch": 1}


@dataclass(frozen=True)
class RecordRow:
    id: str
    files: dict[str, bytes | None]  # name -> content; None makes a directory of that name
    culprit: str
    fragment: str
    found: str = ""  # the bug this row found when it was written (fixed since): why the row exists


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _record(**changes: Any) -> bytes:
    return json.dumps({**GOOD_RECORD, **changes}).encode()


RECORDS_NO_CAP = "Records reads every *.record.json whole: no size cap"
RECORD_ROWS = [
    RecordRow("garbage", {"s.record.json": b"\x00\x01garbage"}, "s.record.json", "unreadable migration record"),
    RecordRow("empty", {"s.record.json": b""}, "s.record.json", "truncated"),
    RecordRow("truncated", {"s.record.json": _record()[:-3]}, "s.record.json", "truncated"),
    RecordRow("JSON of the wrong shape", {"s.record.json": b"[1, 2]"}, "s.record.json", "Expected `object`"),
    RecordRow("unknown state", {"s.record.json": _record(state="zombie")}, "s.record.json", "zombie"),
    RecordRow("epoch as a string", {"s.record.json": _record(epoch="1")}, "s.record.json", "$.epoch"),
    RecordRow("epoch out of range", {"s.record.json": _record()[:-2] + b"1e400}"}, "s.record.json", "out of range"),
    RecordRow("one bad among good", {"a.record.json": _record(companion="a", state="released"), "b.record.json": b"{"},
              "b.record.json", "unreadable migration record"),
    RecordRow("not UTF-8", {"s.record.json": _record(peer=_MARK).replace(b"\\u0000\\u0001\\u0002", b"\xff\xfe")}, "s.record.json",
              "unreadable migration record", "Records catches DecodeError/ValidationError, not the UnicodeDecodeError msgspec "
              "raises for a non-UTF-8 string: the embodiment fails with UnicodeDecodeError naming no file"),
    RecordRow("nested past the recursion limit", {"s.record.json": _record()[:-1] + b', "x": ' + b"[" * 5000 + b"]" * 5000 + b"}"},
              "s.record.json", "unreadable migration record",
              "an unknown field nested 5000 deep makes msgspec raise RecursionError, which Records does not catch"),
    RecordRow("oversized", {"s.record.json": _record() + b" " * records.MAX_RECORD}, "s.record.json", "larger than", RECORDS_NO_CAP),
    RecordRow("a directory", {"s.record.json": None}, "s.record.json", "record",
              "Records reads with Path.read_bytes and does not catch OSError: IsADirectoryError escapes"),
    RecordRow("companion that is not a name", {"s.record.json": _record(companion="../escape")}, "s.record.json", "companion",
              "Records does not check record.companion: '../escape' is accepted, and its identity document is then "
              "read from outside the state folder"),
    RecordRow("companion other than the file's", {"s.record.json": _record(companion="t")}, "s.record.json", "'t'",
              "Records keys a record by its companion field, not its file: s.record.json holding 't' is taken as 't' "
              "(and shadows or is shadowed by t.record.json)"),
    RecordRow("negative epoch", {"s.record.json": _record(epoch=-3)}, "s.record.json", "epoch",
              "Records accepts a negative epoch (epochs start at 1)"),
]


@pytest.mark.parametrize("row", _params(RECORD_ROWS))
def test_corrupt_state_folder_refuses_to_start(row: RecordRow, network: MemoryNetwork, mesh: str, tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    for name, content in row.files.items():
        if content is None:
            (state / name).mkdir()
        else:
            (state / name).write_bytes(content)
    with (MemoryTransport(network, "robot") as transport, pytest.raises(ConfigError) as refused,
          Embodiment("robot", mesh=mesh, transport=transport, state_dir=state) as e):
        time.sleep(0.1)
        pytest.fail(f"started, inhabited by {e.inhabitant!r}")
    assert str(state / row.culprit) in str(refused.value), refused.value
    assert row.fragment in str(refused.value), refused.value


DAMAGED_ROWS = [
    RecordRow("identity document of the active companion is corrupt",
              {"s.record.json": _record(document=_sha(b"<Identity")), f"s.{_sha(b'<Identity')}.identity.xml": b"<Identity"},
              f"s.{_sha(b'<Identity')}.identity.xml", "malformed XML",
              "the document is first read in MigrationManager.attach, on the loop: the XmlError is logged and the "
              "embodiment runs without its companion, its record still saying active"),
    RecordRow("identity document of the active companion is oversized",
              {"s.record.json": _record(document=_sha(b"big")),
               f"s.{_sha(b'big')}.identity.xml": b"<Identity" + b" " * identity.MAX_DOCUMENT + b"/>"},
              f"s.{_sha(b'big')}.identity.xml", "altered at rest",
              "Records.document reads the whole file, and the refusal happens on the loop: the embodiment runs without "
              "its companion"),
    RecordRow("identity document altered at rest", {"s.record.json": _record(document=_sha(b"<Identity/>")),
                                                    f"s.{_sha(b'<Identity/>')}.identity.xml": b"<Identity Companion='x'/>"},
              f"s.{_sha(b'<Identity/>')}.identity.xml", "altered at rest"),
    RecordRow("identity document missing", {"s.record.json": _record(document=_sha(b"gone"))},
              f"s.{_sha(b'gone')}.identity.xml", "missing"),
]


@pytest.mark.parametrize("row", _params(DAMAGED_ROWS))
def test_damaged_identity_at_rest_is_reported_not_run(row: RecordRow, network: MemoryNetwork, mesh: str, tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    for name, content in row.files.items():
        assert content is not None
        (state / name).write_bytes(content)
    with MemoryTransport(network, "robot") as transport, Embodiment("robot", mesh=mesh, transport=transport, state_dir=state) as e:
        settled(e.sim)
        assert e.inhabitant is None, "an altered or unusable identity is never run"
        assert e.migration is not None
        error = e.migration.damaged.get("s", "")
        assert str(state / row.culprit) in error and row.fragment in error, error
        assert e.describe()["damaged"] == {"s": error}


# --- configuration files ----------------------------------------------------------------------------


def _load_world_model(path: Path) -> object:
    return WorldModel().load_init(path)


def _load_architecture(path: Path) -> object:
    return load_architecture(path).build_components()


LOADERS: dict[str, tuple[Callable[[Path], object], str]] = {
    "world model": (_load_world_model, "WorldModel"),
    "rules": (load_rules, "CompetencyManagerRules"),
    "library": (load_library, "CompetencyLibrary"),
    "architecture": (_load_architecture, "ArchitectureConfiguration"),
}


@dataclass(frozen=True)
class ConfigRow:
    id: str
    loader: str
    content: bytes
    fragment: str
    line: int | None = None
    found: str = ""  # the bug this row found when it was written (fixed since): why the row exists


def _xml_kinds(loader: str, root: str) -> list[ConfigRow]:
    """The same hostile XML, for every loader."""
    return [
        ConfigRow(f"{loader}: oversized", loader, f"<{root}>".encode() + b" " * xmlsafe.DEFAULT_MAX_BYTES + f"</{root}>".encode(),
                  f"larger than the limit of {xmlsafe.DEFAULT_MAX_BYTES} bytes"),
        ConfigRow(f"{loader}: garbage", loader, b"\x00\x01\x02 garbage", "malformed XML", 1),
        ConfigRow(f"{loader}: malformed", loader, f"<?xml version='1.0'?>\n<{root}>\n<\n".encode(), "malformed XML", 3),
        ConfigRow(f"{loader}: XXE", loader, f'<!DOCTYPE {root} [<!ENTITY x SYSTEM "file:///etc/passwd">]>\n<{root}>&x;</{root}>'.encode(),
                  "internal DTD subset", 1),
        ConfigRow(f"{loader}: billion laughs", loader, billion_laughs(root), "DOCTYPE", 2),
        ConfigRow(f"{loader}: wrong root", loader, b"<Something/>", "does not match schema", 1),
        ConfigRow(f"{loader}: deeply nested", loader, f"<{root}>".encode() + b"<a>" * 100 + b"</a>" * 100 + f"</{root}>".encode(),
                  "nested deeper than 64", 1),
        ConfigRow(f"{loader}: not UTF-8", loader, f"<{root} x='\xe9'/>".encode("latin-1"), "not valid UTF-8", 1),
        ConfigRow(f"{loader}: encoding unknown", loader, f'<?xml version="1.0" encoding="klingon"?>\n<{root}/>'.encode(),
                  "unsupported encoding 'klingon'", 1),
        ConfigRow(f"{loader}: encoding name with a NUL", loader, f'<?xml version="1.0" encoding="UTF\x00-8"?>\n<{root}/>'.encode(),
                  "encoding", 1, ENCODING_BUG),
    ]


ENCODING_BUG = ("xmlsafe._decode calls codecs.lookup on the declared encoding and catches LookupError only: a NUL "
                "in the name makes it raise ValueError")


def _wm(*properties: str, entity: str = 'Agent Name="A"') -> bytes:
    tag = entity.split()[0]
    return ("<WorldModel>\n" + f"<{entity}>\n" + "".join(f"{p}\n" for p in properties) + f"</{tag}>\n</WorldModel>\n").encode()


BIGINT_BUG = ("world-model values are not checked against MessagePack's int range: storing one raises OverflowError "
              "in Store._apply (world model half loaded, no ConfigError)")
CLASS_BUG = "classes.import_class catches ImportError only: a relative module name makes import_module raise TypeError"

CONFIG_ROWS = [
    *[row for name, (_, root) in LOADERS.items() for row in _xml_kinds(name, root)],
    ConfigRow("world model: entity name with a slash", "world model", _wm(entity='Agent Name="a/b"'), "contains '/'", 2),
    ConfigRow("world model: entity defined twice", "world model",
              b'<WorldModel>\n<Agent Name="A"/>\n<Object Name="A"/>\n</WorldModel>', "already defined at line 2", 3),
    ConfigRow("world model: property name empty", "world model", _wm('<Property Name="" Value="1"/>'), "property name is empty", 3),
    ConfigRow("world model: int that is not", "world model", _wm('<Property Name="p" Value="x" Type="int"/>'), "property 'p'", 3),
    ConfigRow("world model: int of 5000 digits", "world model", _wm(f'<Property Name="p" Value="{"9" * 5000}" Type="int"/>'),
              "digits", 3),
    ConfigRow("world model: bool that is not", "world model", _wm('<Property Name="p" Value="maybe" Type="bool"/>'), "not a boolean", 3),
    ConfigRow("world model: unknown type", "world model", _wm('<Property Name="p" Value="1" Type="pickle"/>'), "pickle", 3),
    ConfigRow("world model: JSON not plain data", "world model", _wm('<Property Name="p" Value="{oops" Type="json"/>'),
              "property 'p'", 3),
    ConfigRow("world model: JSON nested too deep", "world model",
              _wm(f'<Property Name="p" Value="{"[" * 40 + "]" * 40}" Type="json"/>'), "nested deeper than 32", 3),
    ConfigRow("world model: JSON nested past the recursion limit", "world model",
              _wm(f'<Property Name="p" Value="{"[" * 5000 + "]" * 5000}" Type="json"/>'), "property 'p'", 3,
              "storage._typed catches ValueError/DecodeError, not the RecursionError msgspec raises for deep JSON"),
    ConfigRow("world model: int beyond 64 bits", "world model", _wm(f'<Property Name="p" Value="{"9" * 30}" Type="int"/>'),
              "property 'p'", 3, BIGINT_BUG),
    ConfigRow("world model: JSON int beyond 64 bits", "world model", _wm(f'<Property Name="p" Value="[{"9" * 30}]" Type="json"/>'),
              "property 'p'", 3, BIGINT_BUG),
    ConfigRow("rules: parameter number not a number", "rules",
              b'<CompetencyManagerRules>\n<Rule>\n<MindAction Name="A">\n<Parameter No="one" Value="x"/>\n</MindAction>\n'
              b'<CompetencyExecutionPlan/>\n</Rule>\n</CompetencyManagerRules>', "positiveInteger", 4),
    ConfigRow("rules: parameter number of 5000 digits", "rules",
              b'<CompetencyManagerRules>\n<Rule>\n<MindAction Name="A">\n<Parameter No="' + b"9" * 5000
              + b'" Value="x"/>\n</MindAction>\n<CompetencyExecutionPlan/>\n</Rule>\n</CompetencyManagerRules>',
              "is not a whole number", 4),
    ConfigRow("rules: dependency cycle", "rules",
              b'<CompetencyManagerRules>\n<Rule>\n<MindAction Name="A"/>\n<CompetencyExecutionPlan>\n'
              b'<Competency ID="1" Type="T" Dependency="2"/>\n<Competency ID="2" Type="T" Dependency="1"/>\n'
              b"</CompetencyExecutionPlan>\n</Rule>\n</CompetencyManagerRules>", "dependency cycle", 5),
    ConfigRow("library: unknown module", "library",
              b'<CompetencyLibrary>\n<Competency ClassName="no.such.module:X"/>\n</CompetencyLibrary>',
              "cannot import module 'no.such.module'", 2),
    ConfigRow("library: not a competency", "library", b'<CompetencyLibrary>\n<Competency ClassName="builtins:dict"/>\n</CompetencyLibrary>',
              "not a", 2),
    ConfigRow("library: not a class", "library", b'<CompetencyLibrary>\n<Competency ClassName="os.path:join"/>\n</CompetencyLibrary>',
              "not a class", 2),
    ConfigRow("library: relative module", "library", b'<CompetencyLibrary>\n<Competency ClassName=".hidden:X"/>\n</CompetencyLibrary>',
              ".hidden", 2, CLASS_BUG),
    ConfigRow("architecture: referenced file missing", "architecture",
              b'<ArchitectureConfiguration CompetencyManagerRulesFile="nowhere.xml" CompetencyLibraryConfigurationFile="library.xml"/>',
              "CompetencyManagerRulesFile 'nowhere.xml' not found", 1),
    ConfigRow("architecture: invalid embodiment name", "architecture",
              b'<ArchitectureConfiguration Embodiment="a/b" CompetencyManagerRulesFile="rules.xml" '
              b'CompetencyLibraryConfigurationFile="library.xml"/>', "Embodiment", 1),
    ConfigRow("architecture: public key not base64", "architecture",
              b'<ArchitectureConfiguration CompetencyManagerRulesFile="rules.xml" CompetencyLibraryConfigurationFile="library.xml">\n'
              b'<AdmitCompanion Name="s" PublicKey="!!!"/>\n</ArchitectureConfiguration>', "not base64", 2),
    ConfigRow("architecture: component of an unknown class", "architecture",
              b'<ArchitectureConfiguration CompetencyManagerRulesFile="rules.xml" CompetencyLibraryConfigurationFile="library.xml">\n'
              b'<ArchitectureComponent ClassName="no.such:Mind"/>\n</ArchitectureConfiguration>', "cannot import module", 2),
    ConfigRow("architecture: referenced file name too long", "architecture",
              b'<ArchitectureConfiguration CompetencyManagerRulesFile="' + b"r" * 5000
              + b'" CompetencyLibraryConfigurationFile="library.xml"/>', "CompetencyManagerRulesFile", 1,
              "architecture.referenced() calls Path.is_file(), which raises OSError (file name too long) instead of "
              "returning False: the OSError escapes"),
    ConfigRow("architecture: component of a relative module", "architecture",
              b'<ArchitectureConfiguration CompetencyManagerRulesFile="rules.xml" CompetencyLibraryConfigurationFile="library.xml">\n'
              b'<ArchitectureComponent ClassName="..up:Mind"/>\n</ArchitectureConfiguration>', "..up", 2, CLASS_BUG),
]


@pytest.mark.parametrize("row", _params(CONFIG_ROWS))
def test_hostile_config_file_is_refused(row: ConfigRow, tmp_path: Path) -> None:
    (tmp_path / "rules.xml").write_bytes(RULES)
    (tmp_path / "library.xml").write_bytes(b"<CompetencyLibrary/>")
    path = tmp_path / "hostile.xml"
    path.write_bytes(row.content)
    load, _ = LOADERS[row.loader]
    with pytest.raises(ConfigError) as refused:
        load(path)
    message = str(refused.value)
    where = f"{path}:{row.line}:" if row.line is not None else str(path)
    assert message.startswith(where), message
    assert row.fragment in message, message


def test_world_model_is_untouched_by_a_refused_file(tmp_path: Path) -> None:
    path = tmp_path / "wm.xml"
    path.write_bytes(_wm('<Property Name="ok" Value="1"/>', '<Property Name="p" Value="x" Type="int"/>'))
    world = WorldModel()
    with pytest.raises(ConfigError):
        world.load_init(path)
    assert world.tree()["children"] == {}, "nothing was applied"


def test_world_model_with_a_huge_int_is_refused_before_anything_is_applied(tmp_path: Path) -> None:
    path = tmp_path / "wm.xml"
    path.write_bytes(b'<WorldModel>\n<Agent Name="A"/>\n<Agent Name="B">\n<Property Name="p" Value="' + b"9" * 30
                     + b'" Type="int"/>\n</Agent>\n</WorldModel>')
    world = WorldModel()
    with pytest.raises(ConfigError, match=rf"^{path}:4:"):
        world.load_init(path)
    assert world.tree()["children"] == {}


SPEC_OK = {"operators": [{"name": "greet", "action": "Greet", "effects": [["Guest", "greeted", True]]}]}


def _spec(**changes: Any) -> bytes:
    return json.dumps({**SPEC_OK, **changes}).encode()


@pytest.mark.parametrize(
    ("content", "fragment"),
    [
        pytest.param(b" " * (16 * 1024 * 1024 + 1), "larger than 16 MiB", id="oversized"),
        pytest.param(b"", "not JSON", id="empty"),
        pytest.param(b"{operators: []}", "not JSON", id="not JSON"),
        pytest.param(b"\x00\x01garbage", "not JSON", id="garbage"),
        pytest.param(b"42", "a JSON object or a list of operators", id="a number"),
        pytest.param(b'"spec"', "a JSON object or a list of operators", id="a string"),
        pytest.param(_spec(surprise=1), "surprise", id="unknown field"),
        pytest.param(_spec(operators=[{"name": "x"}]), "action", id="missing field"),
        pytest.param(_spec(operators=[{"name": "x", "action": "X", "cost": -1}]), "negative", id="negative cost"),
        pytest.param(_spec(operators=[{"name": "x", "action": "X", "cost": "free"}]), "cost", id="cost of the wrong type"),
        pytest.param(_spec(goals=[{"name": "g", "facts": [["", "p", 1]]}]), "empty entity", id="empty entity"),
        pytest.param(_spec(goals=[{"name": "g", "facts": [["e", "p", nested(40)]]}]), "nested deeper", id="value nested too deep"),
        pytest.param(_spec(limits={"max_depth": 0}), "max_depth must be at least 1", id="zero limit"),
        pytest.param(_spec(emotion={"decay": 2}), "decay", id="decay out of range"),
        pytest.param(_spec(operators=[SPEC_OK["operators"][0]] * 2), "two operators are named 'greet'", id="duplicate operator"),
        pytest.param(b'{"limits": {"retry_delay": 1e400}}', "out of range", id="number out of range"),
        pytest.param(b'{"operators": [{"name": "' + b"\xff" + b'", "action": "A"}]}', "not JSON", id="not UTF-8"),
        pytest.param(b"[" * 5000 + b"]" * 5000, "not JSON", id="nested past the recursion limit"),
    ],
)
def test_hostile_planner_spec_is_refused(content: bytes, fragment: str, tmp_path: Path) -> None:
    path = tmp_path / "spec.json"
    path.write_bytes(content)
    with pytest.raises(ConfigError) as refused:
        load_spec(path)
    assert str(refused.value).startswith(f"{path}: "), refused.value
    assert fragment in str(refused.value), refused.value


# --- through a real daemon over zenoh ----------------------------------------------------------------


@pytest.mark.parametrize(
    "payload",
    [
        pytest.param(b"\xc1garbage", id="garbage"),
        pytest.param(bad_utf8(**{**SP, "name": _MARK}), id="non-UTF-8"),
    ],
)
def test_daemon_over_zenoh_refuses_and_keeps_answering(payload: bytes, mesh: str) -> None:
    import zenoh

    from .conftest import start_daemon

    daemon, endpoint = start_daemon(mesh, "robot")
    with daemon:
        config = zenoh.Config()
        config.insert_json5("mode", '"peer"')
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("connect/endpoints", json.dumps([endpoint]))
        with zenoh.open(config) as session:
            key = keys.request_key(mesh, "robot", "bb", "set_property")

            def outcomes(data: bytes) -> list[Outcome]:
                replies = list(session.get(key, payload=data, timeout=3))
                assert all(r.ok is not None for r in replies), replies
                return [decode(r.ok.payload.to_bytes(), Outcome, where=key) for r in replies if r.ok is not None]

            wait_for(lambda: outcomes(encode(SetProperty("", "ready", 1))), 10, "the daemon answers")
            refused = outcomes(payload)
            assert len(refused) == 1, f"exactly one reply, got {refused}"
            assert_refused(refused[0], "malformed message", key)
            assert [o.status for o in outcomes(encode(SetProperty("", "after", 1)))] == ["accepted"]
