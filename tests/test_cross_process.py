"""A storage component in one process; this process speaks to it with plain zenoh only.

Nothing of cmion_mesh's API is used on the client side: payloads are MessagePack maps built
and read by hand, as a client in another language would (see docs/wire.md).
"""

from __future__ import annotations

import json
import queue
import threading
from collections.abc import Iterator
from typing import Any

import msgspec
import pytest
import zenoh

from cmion_mesh.testing.wait import wait_for

from .conftest import CMION_2011, start_daemon

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def robot(mesh: str) -> Iterator[str]:
    daemon, endpoint = start_daemon(mesh, "robot", "--world-model", str(CMION_2011 / "worldModelInit.xml"))
    with daemon:
        yield endpoint
    assert daemon.proc.returncode == 0, "\n".join(daemon.lines)


@pytest.fixture
def session(robot: str) -> Iterator[zenoh.Session]:
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("connect/endpoints", json.dumps([robot]))
    with zenoh.open(config) as s:
        yield s


def plain_get(session: zenoh.Session, selector: str) -> dict[str, Any]:
    out = {}
    for reply in session.get(selector, timeout=5):
        assert reply.ok is not None, reply.err
        out[str(reply.ok.key_expr)] = msgspec.msgpack.decode(reply.ok.payload.to_bytes())
    return out


def plain_request(session: zenoh.Session, key: str, message: dict[str, Any]) -> dict[str, Any]:
    replies = list(session.get(key, payload=msgspec.msgpack.encode(message), timeout=5))
    assert len(replies) == 1 and replies[0].ok is not None
    outcome: dict[str, Any] = msgspec.msgpack.decode(replies[0].ok.payload.to_bytes())
    return outcome


def test_plain_zenoh_reads_watches_and_writes(session: zenoh.Session, mesh: str) -> None:
    wm = f"cmion/{mesh}/robot/wm"
    entries = wait_for(lambda: plain_get(session, f"{wm}/**"), 10, "world model answers a plain get")
    assert entries[f"{wm}/UserA/speaksEnglish"] == {"type": "property", "value": "True", "persistent": True}
    assert entries[f"{wm}/Vase"] == {"type": "container", "kind": "object"}
    assert plain_get(session, f"{wm}/Vase/broken") == {f"{wm}/Vase/broken": {"type": "property", "value": "False", "persistent": False}}

    changes: queue.SimpleQueue[tuple[str, str, Any]] = queue.SimpleQueue()
    sub = session.declare_subscriber(f"cmion/{mesh}/robot/bb/**", zenoh.handlers.FifoChannel(64))
    events = session.declare_subscriber(f"cmion/{mesh}/robot/ev/bb/*", zenoh.handlers.FifoChannel(64))

    def drain() -> None:
        for sample in sub.handler:
            body = msgspec.msgpack.decode(sample.payload.to_bytes()) if sample.kind == zenoh.SampleKind.PUT else None
            changes.put((str(sample.key_expr), str(sample.kind), body))

    reader = threading.Thread(target=drain)
    reader.start()
    try:
        rq = f"cmion/{mesh}/robot/rq/bb"
        # The subscriber's declaration reaches the daemon asynchronously: write until one is seen.
        def first_change_seen() -> bool:
            plain_request(session, f"{rq}/set_property", {"type": "set_property", "container": "", "name": "probe", "value": 0})
            try:
                changes.get(timeout=0.2)
                return True
            except queue.Empty:
                return False

        wait_for(first_change_seen, 10, "subscriber hears changes")
        accepted = plain_request(session, f"{rq}/set_property",
                                 {"type": "set_property", "container": "", "name": "battery", "value": 0.75, "persistent": True})
        assert accepted == {"type": "outcome", "status": "accepted", "reason": "", "value": None, "code": ""}
        key, kind, body = changes.get(timeout=5)
        assert key == f"cmion/{mesh}/robot/bb/battery" and body == {"type": "property", "value": 0.75, "persistent": True}
        rejected = plain_request(session, f"{rq}/set_property", {"type": "set_property", "container": "nowhere", "name": "x", "value": 1})
        assert rejected["status"] == "rejected" and "no container 'nowhere'" in rejected["reason"] and rejected["code"] == "not_found"
        malformed = plain_request(session, f"{rq}/set_property", {"type": "set_property", "name": 5})
        assert malformed["status"] == "rejected" and "malformed" in malformed["reason"] and malformed["code"] == "malformed"
        removed = plain_request(session, f"{rq}/remove_property", {"type": "remove_property", "container": "", "name": "battery"})
        assert removed["status"] == "accepted"
        key, kind, body = changes.get(timeout=5)
        assert key.endswith("/bb/battery") and "DELETE" in kind and body is None
        assert plain_get(session, f"cmion/{mesh}/robot/bb/battery") == {}
        event = msgspec.msgpack.decode(wait_for(events.handler.try_recv, 5, "storage event").payload.to_bytes())
        assert event["type"] == "event" and event["component"] == "bb" and event["name"] == "PropertyChanged"
    finally:
        sub.undeclare()
        events.undeclare()
        reader.join(5)


def test_nobody_answering_is_not_success(session: zenoh.Session, mesh: str) -> None:
    replies = list(session.get(f"cmion/{mesh}/ghost/rq/bb/set_property", payload=b"", timeout=1))
    assert replies == []  # what cmion_mesh turns into OutcomeUnknown; see test_client_outcome_unknown


def test_client_outcome_unknown(robot: str, mesh: str) -> None:
    from cmion_mesh.client import MeshClient
    from cmion_mesh.errors import OutcomeUnknown
    from cmion_mesh.transport.base import TransportConfig
    from cmion_mesh.transport.zenoh import ZenohTransport

    with ZenohTransport(TransportConfig(connect=(robot,), multicast=False)) as t:
        client = MeshClient(t, mesh)
        wait_for(lambda: client.read_store("robot", "bb"), 10, "robot answers")
        with pytest.raises(OutcomeUnknown, match="ghost"):
            client.set_property("ghost", "bb", "", "x", 1)
        client.set_property("robot", "bb", "", "x", 1)
        assert client.get_property("robot", "bb", "", "x").value == 1


def test_cmion_test_scenario_across_processes(mesh: str) -> None:
    """CMION's own test scenario, its rules file unchanged, driven from another process."""
    from cmion_mesh.client import MeshClient
    from cmion_mesh.resources import embodiment_dir
    from cmion_mesh.transport.base import TransportConfig
    from cmion_mesh.transport.zenoh import ZenohTransport

    library = embodiment_dir("cmion_test") / "CompetencyLibrary.xml"
    daemon, endpoint = start_daemon(mesh, "cmion", "--rules", str(CMION_2011 / "CompManagerRulesTest.xml"),
                                    "--library", str(library), "--world-model", str(CMION_2011 / "worldModelInit.xml"))
    with daemon, ZenohTransport(TransportConfig(connect=(endpoint,), multicast=False)) as t:
        client = MeshClient(t, mesh)
        wait_for(lambda: client.read_store("cmion", "wm"), 10, "daemon reachable")
        first = client.act("cmion", "TestAction", ["test"], timeout=30)
        assert first.status == "succeeded" and first.rule.endswith("CompManagerRulesTest.xml:47")
        assert client.get_property("cmion", "wm", "TestUser", "test").value is True
        assert isinstance(client.get_property("cmion", "bb", "", "test").value, float)
        assert client.act("cmion", "TestAction2", timeout=30).status == "succeeded"
    assert daemon.proc.returncode == 0
