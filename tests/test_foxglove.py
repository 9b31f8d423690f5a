"""Foxglove opens what cmion-mesh shows it: recordings (self-contained JSON Schemas, log lines as
``foxglove.Log``) and the live connection (``cmion-mesh foxglove``, the Foxglove WebSocket protocol)."""

from __future__ import annotations

import json
import math
import signal
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from mcap.reader import make_reader

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import Container, Event, Property, RequestAnswered, decode, encode
from cmion_mesh.procs import Daemon, cli_argv, free_port, unique_mesh
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.tools.demo import start_bodies, stop_bodies
from cmion_mesh.tools.recording import Recorder
from cmion_mesh.tools.recording_format import (
    ERROR,
    EVENT_SCHEMA,
    INFO,
    LOG_SCHEMA,
    RAW_SCHEMA,
    SCHEMAS,
    STORAGE_SCHEMA,
    WARNING,
    plain_value,
    recorded_event,
)
from cmion_mesh.tools.recording_reader import info
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport
from cmion_mesh.transport.zenoh import ZenohTransport
from tests.conftest import DATA
from tests.helpers.mesh_setups import record_demo

pytestmark = pytest.mark.timeout(180)

#: A recording written by the recorder before this format (format 1: ``$ref`` schemas, ``data``
#: and ``value`` as they were): 18 messages, a migration robot -> screen, events whose data is a
#: map, null, a string and a list, world-model samples (a property, a container, a delete), two
#: requests answered (one rejected), an undecodable payload, liveliness.
FORMAT_1 = DATA / "recording-format-1.mcap"


# --- Foxglove's JSON Schema reader, its rules -------------------------------------------------------
#
# Foxglove reads a channel whose schema encoding is ``jsonschema`` with ``parseJsonSchema``
# (foxglove/studio, packages/mcap-support/src/parseJsonSchema.ts, at commit 9abf66535509): it
# walks the schema once, from its root, and throws on the first thing it cannot turn into a
# message definition. Its rules, each an error below:
#
# 1. every object schema, the root included, has ``"type": "object"`` (else it throws
#    ``Expected "type": "object" for schema <name>, got <type>``); ``$ref`` is never followed;
# 2. its ``properties`` is an object (``Object.entries`` of anything else throws);
# 3. a field with ``oneOf``: every alternative has a number ``const`` (an enum of numbers, as
#    ``foxglove.Log``'s level); anything else in a ``oneOf`` throws;
# 4. otherwise a field's ``type`` is exactly one of ``boolean``, ``string``, ``number``,
#    ``integer``, ``object``, ``array``: ``null``, a list of types or no type at all (a bare
#    ``$ref``, an ``anyOf``, ``{}``) throws ``Unsupported type``;
# 5. a string has no ``contentEncoding``, or ``base64``;
# 6. an ``object`` field is read by rules 1-7 (its name ``<parent>.<field>``);
# 7. an ``array`` has an ``items`` object whose ``type`` is ``boolean``, ``string`` (no
#    ``contentEncoding``), ``number``, ``integer`` or ``object`` (read by rules 1-7); an array of
#    arrays throws.

SCALARS = ("boolean", "string", "number", "integer")


def shown(schema: Any, key: str) -> str:
    """``JSON.stringify(schema[key])`` as the reader words its errors (``undefined`` when absent)."""
    return json.dumps(schema[key]) if isinstance(schema, dict) and key in schema else "undefined"


def foxglove_problems(schema: Any, name: str) -> list[str]:
    """What Foxglove's JSON Schema reader throws on ``schema`` (rules above); [] when it reads it."""
    if not isinstance(schema, dict) or schema.get("type") != "object":
        return [f'Expected "type": "object" for schema {name}, got {shown(schema, "type")}']
    properties = schema.get("properties")
    if not isinstance(properties, dict):
        return [f"{name}: properties is not an object"]
    problems: list[str] = []
    for field, sub in properties.items():
        where = f"{name}.{field}"
        if not isinstance(sub, dict):
            problems.append(f"{where}: not a schema")
        elif isinstance(sub.get("oneOf"), list):
            if not all(isinstance(a, dict) and isinstance(a.get("const"), int | float) for a in sub["oneOf"]):
                problems.append(f"Unsupported type for {where}: oneOf alternatives must have number values")
        elif sub.get("type") in SCALARS:
            if sub["type"] == "string" and sub.get("contentEncoding") not in (None, "base64"):
                problems.append(f"Unsupported contentEncoding {sub['contentEncoding']!r} in {where}")
        elif sub.get("type") == "object":
            problems += foxglove_problems(sub, where)
        elif sub.get("type") == "array":
            items = sub.get("items")
            kind = items.get("type") if isinstance(items, dict) else None
            if kind == "object":
                problems += foxglove_problems(items, where)
            elif kind not in SCALARS or (kind == "string" and items.get("contentEncoding") is not None):
                problems.append(f"Unsupported type {shown(items, 'type')} for array item {where}")
        else:
            problems.append(f"Unsupported type {shown(sub, 'type')} for {where}")
    return problems


def check_channel_messages(schemas: dict[str, dict[str, Any]], messages: list[tuple[str, Any]]) -> None:
    """Every schema read by Foxglove's rules and a valid JSON Schema; every message valid by its schema."""
    for name, schema in schemas.items():
        assert foxglove_problems(schema, name) == [], name
        jsonschema.Draft202012Validator.check_schema(schema)
    validators = {name: jsonschema.Draft202012Validator(schema) for name, schema in schemas.items()}
    for name, message in messages:
        errors = [e.message for e in validators[name].iter_errors(message)]
        assert errors == [], (name, message)


def read_recording(path: Path) -> tuple[dict[str, dict[str, Any]], list[tuple[str, str, Any]]]:
    """A recording's schemas (name -> JSON Schema) and messages (topic, schema name, decoded)."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        assert {c.message_encoding for c in summary.channels.values()} == {"json"}
        schemas = {s.name: json.loads(s.data) for s in summary.schemas.values()}
        messages = [(channel.topic, schema.name, json.loads(message.data))
                    for schema, channel, message in reader.iter_messages(log_time_order=False) if schema is not None]
    return schemas, messages


# --- the schemas ------------------------------------------------------------------------------------


def test_the_rules_refuse_what_recordings_of_format_1_hold() -> None:
    """The checks are Foxglove's: they throw on the schemas the recorder wrote before, as Foxglove did."""
    with open(FORMAT_1, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    old = {s.name: json.loads(s.data) for s in summary.schemas.values()}
    assert foxglove_problems(old[EVENT_SCHEMA], EVENT_SCHEMA) == ['Expected "type": "object" for schema cmion_mesh.Event, got undefined']
    # With its $ref resolved by hand, the event's data, the entry and the status have no type still.
    for name, field in ((EVENT_SCHEMA, "data"), (STORAGE_SCHEMA, "entry"), ("cmion_mesh.RequestAnswered", "status")):
        resolved = old[name]["$defs"][name.split(".")[1]]
        assert f"Unsupported type undefined for {name}.{field}" in foxglove_problems(resolved, name)


def test_every_schema_is_self_contained_and_read_by_foxglove() -> None:
    for name, data in SCHEMAS.items():
        schema = json.loads(data)
        assert "$ref" not in data.decode() and "$defs" not in schema, name
        assert schema["title"] == name
        assert foxglove_problems(schema, name) == [], name
        jsonschema.Draft202012Validator.check_schema(schema)
    log = json.loads(SCHEMAS[LOG_SCHEMA])
    # foxglove.Log as Foxglove defines it (its Log panel reads these fields).
    assert set(log["required"]) == {"timestamp", "level", "message", "name", "file", "line"}
    assert [a["const"] for a in log["properties"]["level"]["oneOf"]] == [0, 1, 2, 3, 4, 5]


PLAIN_VALUES: list[Any] = [None, {"k": [1, "a", None], "n": {"m": 2.5}}, "hello", 3, 2.5, True, False, 0, "", [0.5, 1.25], []]


def test_every_kind_of_sample_is_recorded_valid_and_reads_back(tmp_path: Path) -> None:
    network = MemoryNetwork()
    events = [Event("robot", "arm", f"E{i}", value, i + 1, 1.7e9 + i) for i, value in enumerate(PLAIN_VALUES)]
    events += [Event("robot", "migration", "MigrationFailed", {"companion": "spirit", "reason": "no"}, 50, 1.7e9),
               Event("robot", "migration", "CustodyFork", {"companion": "spirit"}, 51, 1.7e9),
               Event("robot", "arm", "NotANumber", math.nan, 52, 1.7e9)]
    with MemoryTransport(network, "mesh") as t:
        token = t.declare_token("cmion/m/@custody/robot/spirit/4")
        with Recorder(t, "m", tmp_path / "all.mcap") as recorder:
            for event in events:
                t.publish(f"cmion/m/robot/ev/{event.component}/{event.name}", encode(event))
            for i, value in enumerate(PLAIN_VALUES):
                t.publish(f"cmion/m/robot/wm/thing/p{i}", encode(Property(value, i % 2 == 0)))
            t.publish("cmion/m/robot/bb/room", encode(Container("place")))
            t.delete("cmion/m/robot/wm/thing/p0")
            refused = RequestAnswered("robot", "manager", "act", "rejected", "not_found", "no")
            t.publish("cmion/m/robot/@outcome/manager/act", encode(refused))
            t.publish("cmion/m/robot/ev/arm/Broken", b"\xc1")
            t.publish("cmion/m/robot/elsewhere", b"bytes")
            wait_for(lambda: recorder.stats.samples >= len(events) + len(PLAIN_VALUES) + 6, 10, "every sample written")
        token.close()
    schemas, messages = read_recording(tmp_path / "all.mcap")
    assert set(schemas) == set(SCHEMAS)
    check_channel_messages(schemas, [(name, message) for _, name, message in messages])
    recorded = {m["name"]: m for _, name, m in messages if name == EVENT_SCHEMA}
    for event in events:
        back = recorded_event(json.dumps(recorded[event.name]).encode())
        want = None if isinstance(event.data, float) and math.isnan(event.data) else event.data
        assert (back.data, type(back.data)) == (want, type(want)), event.name
        assert back == Event(event.embodiment, event.component, event.name, want, event.seq, event.time)
    entries = {m["key"].rsplit("/", 1)[-1]: m for _, name, m in messages if name == STORAGE_SCHEMA and not m["deleted"]}
    for i, value in enumerate(PLAIN_VALUES):
        entry = entries[f"p{i}"]["entry"]
        assert (entry["type"], plain_value(entry, "value"), entry["persistent"]) == ("property", value, i % 2 == 0)
    assert entries["room"]["entry"]["kind"] == "place"
    deleted = [m for _, name, m in messages if name == STORAGE_SCHEMA and m["deleted"]]
    assert deleted == [{"key": "cmion/m/robot/wm/thing/p0", "deleted": True}], "a delete has no entry (not null)"
    lines = [(m["level"], m["name"], m["message"]) for topic, name, m in messages if name == LOG_SCHEMA]
    assert {topic for topic, name, _ in messages if name == LOG_SCHEMA} == {"log:cmion/m"}
    assert (INFO, "robot", "robot holds spirit (epoch 4)") in lines
    assert (WARNING, "robot", "migration MigrationFailed: companion=spirit reason=no") in lines
    assert (ERROR, "robot", "migration CustodyFork: companion=spirit") in lines
    assert (WARNING, "robot", "manager/act: rejected not_found: no") in lines
    assert any(level == WARNING and text.startswith("not understood: cmion/m/robot/ev/arm/Broken") for level, _, text in lines)
    assert not any("E1" in text for _, _, text in lines), "events of other components are not the story"


def test_a_recording_of_format_1_reads_as_before(tmp_path: Path) -> None:
    from cmion_mesh.tools.replay import replay

    summary = info(FORMAT_1)
    assert summary["messages"] == 18 and summary["embodiments"] == ["robot", "screen"]
    assert [(m["source"], m["target"], m["steps"], m["outcome"]) for m in summary["migrations"]] == \
        [("robot", "screen", ["robot:prepared", "screen:incoming", "robot:handed", "screen:active"], "succeeded")]
    assert summary["requests"] == {"accepted": 1, "rejected": 1} and not summary["truncated"]
    network = MemoryNetwork()
    heard: list[Event] = []
    with MemoryTransport(network, "listener") as listener, MemoryTransport(network, "replay") as replaying, \
            listener.subscribe("cmion/fresh/**", lambda s: heard.append(decode(s.payload, Event))):
        stats = replay(MeshClient(replaying, "fresh"), FORMAT_1, rate=0)
        wait_for(lambda: len(heard) == 9, 10, "nine replayed events")
    assert stats.published == 9 and stats.undecodable == 0
    data = {e.name: e.data for e in heard}
    assert data["InviteMigration"] is None and data["Said"] == "hello" and data["Joints"] == [0.5, 1.25]
    assert data["MigrationStarting"] == {"companion": "spirit", "target": "screen", "attempt": "ab12cd34"}


# --- the live server, in this process -----------------------------------------------------------------


def test_the_server_refuses_an_address_in_use_naming_it_and_closes_once() -> None:
    from cmion_mesh.tools.foxglove import FoxgloveServer

    network = MemoryNetwork()
    with MemoryTransport(network, "mesh") as t, FoxgloveServer(t, "m", port=0) as server:
        assert server.url == f"ws://127.0.0.1:{server.port}" and server.port > 0
        with pytest.raises(ConfigError, match=f"cannot serve Foxglove on 127.0.0.1:{server.port}"):
            FoxgloveServer(t, "m", port=server.port)
        server.close()
        server.close()


def test_without_foxglove_sdk_the_server_says_how_to_install_it(monkeypatch: pytest.MonkeyPatch) -> None:
    from cmion_mesh.tools.foxglove import FoxgloveServer

    monkeypatch.setitem(sys.modules, "foxglove", None)  # what an install without the extra has
    with MemoryTransport(MemoryNetwork(), "mesh") as t, pytest.raises(ConfigError, match=r"pip install 'cmion-mesh\[foxglove\]'"):
        FoxgloveServer(t, "m", port=0)


def test_a_channels_first_subscriber_gets_its_last_messages_then_the_rest() -> None:
    """Messages said on a channel before anyone subscribed are kept (the last ``KEEP``) for the
    first client that does; a second client on the channel gets only what is said after."""
    from websockets.sync.client import connect

    from cmion_mesh.tools.foxglove import KEEP, FoxgloveServer
    from tests.helpers.foxglove_client import MESSAGE_HEADER, SUBPROTOCOLS

    def subscribe(ws: Any, topic: str) -> None:
        for _ in range(100):  # bounded: serverInfo, then the advertisements
            message = json.loads(ws.recv(timeout=10))
            ids = [c["id"] for c in message.get("channels", []) if c["topic"] == topic]
            if ids:
                ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": ids[0]}]}))
                return
        raise AssertionError(f"{topic} never advertised")

    def seqs(ws: Any, count: int) -> list[int]:
        return [json.loads(ws.recv(timeout=10)[MESSAGE_HEADER.size:])["seq"] for _ in range(count)]

    key = "cmion/m/robot/ev/arm/Tick"
    network = MemoryNetwork()
    with MemoryTransport(network, "mesh") as t, FoxgloveServer(t, "m", port=0) as server:
        for i in range(1, KEEP + 11):
            t.publish(key, encode(Event("robot", "arm", "Tick", None, i, 1.7e9)))
        wait_for(lambda: server.messages == KEEP + 10, 10, "every tick served")
        with connect(server.url, subprotocols=SUBPROTOCOLS) as first, connect(server.url, subprotocols=SUBPROTOCOLS) as second:
            subscribe(first, key)
            assert seqs(first, KEEP) == list(range(11, KEEP + 11)), "the last KEEP, in order"
            subscribe(second, key)
            wait_for(lambda: server.subscribers(key) == 2, 10, "both subscribed")
            t.publish(key, encode(Event("robot", "arm", "Tick", None, 99, 1.7e9)))
            assert seqs(first, 1) == [99] and seqs(second, 1) == [99]


# --- a real recording, a real mesh ------------------------------------------------------------------


@pytest.fixture(scope="module")
def demo_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_demo(tmp_path_factory.mktemp("foxglove") / "demo.mcap")


@pytest.mark.mesh
def test_every_schema_of_the_demos_recording_is_read_by_foxglove_and_holds_its_messages(demo_recording: Path) -> None:
    schemas, messages = read_recording(demo_recording)
    assert set(schemas) == set(SCHEMAS) - {RAW_SCHEMA}, "every kind of message but raw ones (none in the demo)"
    check_channel_messages(schemas, [(name, message) for _, name, message in messages])
    lines = {(m["name"], m["message"]) for _, name, m in messages if name == LOG_SCHEMA}
    migration = [m for _, name, m in messages if name == EVENT_SCHEMA and m["component"] == "migration"]
    assert len([m for m in migration if m["name"] == "MigrationStep"]) == 12, "three hops of four steps"
    for event in migration:  # each with its log line
        assert any(name == event["embodiment"] and text.startswith(f"migration {event['name']}: ") for name, text in lines), event
    assert ("screen", "screen holds spirit (epoch 2)") in lines


@pytest.fixture
def bodies(tmp_path: Path) -> Iterator[tuple[str, list[str]]]:
    mesh = unique_mesh("fox")
    scenario = start_bodies(mesh, tmp_path / "state")
    try:
        yield mesh, list(scenario.endpoints.values())
    finally:
        stop_bodies(scenario)


@pytest.mark.mesh
def test_a_foxglove_client_in_another_process_sees_a_migration_live(bodies: tuple[str, list[str]]) -> None:
    mesh, endpoints = bodies
    net = [a for e in endpoints for a in ("--connect", e)] + ["--no-multicast"]
    port = free_port()
    with Daemon(cli_argv("foxglove", "--mesh", mesh, "--web", f"127.0.0.1:{port}", *net), name="foxglove") as server:
        line = server.wait_line("serving mesh", 30)
        assert f"ws://127.0.0.1:{port}" in line, line
        with Daemon([sys.executable, "-m", "tests.helpers.foxglove_client", f"ws://127.0.0.1:{port}",
                     "/ev/migration/", f"log:cmion/{mesh}", "@custody"], name="client") as client:
            ready = json.loads(client.wait_line("READY", 30).split(" ", 1)[1])
            assert ready["subprotocol"] == "foxglove.sdk.v1" and ready["server"]["op"] == "serverInfo"
            # The daemons' tokens were advertised and latched: the client is in step with the mesh.
            client.wait_line("robot holds spirit", 30)
            with ZenohTransport(TransportConfig(connect=tuple(endpoints), multicast=False)) as t:
                result = MeshClient(t, mesh).migrate("spirit", "screen", timeout=60)
            assert result["target"] == "screen"
            attempt = result["attempt"]

            def received() -> list[dict[str, Any]]:
                return [json.loads(line.split(" ", 1)[1]) for line in client.lines if line.startswith("M ")]

            def steps() -> list[tuple[str, str]]:
                # In the order they were raised (the daemons share this host's clock): a channel's
                # first subscriber gets what was said before it subscribed at once, maybe after what
                # others said since, and a batch of samples shares one receive time.
                said = sorted((m["message"] for m in received() if m["topic"].endswith("/ev/migration/MigrationStep")),
                              key=lambda event: event["time"])
                return [(event["embodiment"], event["data"]["step"]) for event in said]

            wait_for(lambda: len(steps()) >= 4, 30, "the handshake's four steps")
            wait_for(lambda: any(m["topic"].endswith("/MigrationSucceeded") for m in received()), 30, "the migration's end")
        assert server.stop(signal.SIGINT) == 0, server.lines  # Ctrl-C: it says what it served and exits 0
        assert server.lines[-1].startswith("served "), server.lines
    got = received()
    # The source writes its prepared beside the transfer (issue 32), so prepared and incoming come
    # in either order; each step once, none lost on a channel advertised with the first of them.
    said = steps()
    assert len(said) == 4 and set(said[:2]) == {("robot", "prepared"), ("screen", "incoming")}, said
    assert said[2:] == [("robot", "handed"), ("screen", "active")], said
    schemas = {m["schemaName"]: json.loads(m["schema"]) for m in got if "schema" in m}
    assert {EVENT_SCHEMA, LOG_SCHEMA} <= set(schemas) and all(json.loads(SCHEMAS[n]) == s for n, s in schemas.items())
    check_channel_messages(schemas, [(m["schemaName"], m["message"]) for m in got])
    events = [recorded_event(json.dumps(m["message"]).encode()) for m in got if m["schemaName"] == EVENT_SCHEMA]
    assert {e.name for e in events} >= {"MigrationStarting", "MigrationStep", "MigrationSucceeded"}
    assert all(e.data["companion"] == "spirit" for e in events)
    assert {e.data["attempt"] for e in events if "attempt" in e.data} == {attempt}  # MigrationOccurred has none
    lines = [m["message"]["message"] for m in got if m["schemaName"] == LOG_SCHEMA]
    assert any(line.startswith("screen holds spirit") for line in lines)
    assert all(m["log_time"] > 0 for m in got)
