"""The view's server side without a browser: what it makes of events, bounded queues for slow
pages, and who may open its WebSocket. The mesh is the in-memory transport."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator
from typing import Any

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect

from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.messages import Event, encode
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport
from cmion_mesh.web import view_model
from cmion_mesh.web.server import WebServer
from cmion_mesh.web.view import MeshView
from cmion_mesh.web.view_model import Model, Page


def event(embodiment: str, component: str, name: str, data: Any = None, seq: int = 1) -> Event:
    return Event(embodiment, component, name, data, seq, time.time())


def test_a_page_queue_drops_the_oldest_events_and_counts_them() -> None:
    page = Page(1)
    for i in range(view_model.PAGE_EVENTS + 25):
        page.event({"seq": i})
    assert len(page.events) == view_model.PAGE_EVENTS
    assert page.dropped == 25
    assert page.events[0] == {"seq": 25}


def test_a_page_too_far_behind_on_state_gets_a_snapshot_instead() -> None:
    page = Page(1)
    for i in range(view_model.PAGE_CHANGES + 1):
        page.change({"n": i})
    assert page.resync and page.changes == []
    page.change({"n": "more"})
    assert page.changes == []  # the snapshot will say it


def test_migration_steps_are_put_together_from_both_sides() -> None:
    model = Model("m")
    a = {"companion": "spirit", "attempt": "a1"}
    # As a view may hear them: each side's in order, the two sides' interleaved any way.
    for e in (event("robot", "migration", "MigrationStarting", {**a, "target": "screen", "epoch": 1}),
              event("robot", "migration", "MigrationStep", {**a, "step": "prepared", "peer": "screen"}),
              event("robot", "migration", "MigrationStep", {**a, "step": "handed", "peer": "screen"}),
              event("robot", "migration", "MigrationSucceeded", {**a, "target": "screen", "epoch": 2}),
              event("screen", "migration", "MigrationStep", {**a, "step": "incoming", "peer": "robot"}),
              event("screen", "migration", "MigrationStep", {**a, "step": "active", "peer": "robot", "epoch": 2})):
        model.migration_event(e)
    (m,) = model.migrations.values()
    assert (m["source"], m["target"], m["status"], m["epoch"]) == ("robot", "screen", "succeeded", 2)
    assert [s["step"] for s in m["steps"]] == ["starting", "prepared", "incoming", "handed", "active", "released"]
    # Refused before any attempt: a failed migration of its own, with the reason.
    model.migration_event(event("robot", "migration", "MigrationFailed", {"companion": "spirit", "target": "moon",
                                                                          "reason": "unknown target"}, seq=9))
    failed = model.migrations["robot#9"]
    assert (failed["status"], failed["reason"], failed["target"]) == ("failed", "unknown target", "moon")


def test_plans_follow_execution_events_and_only_so_many_finished_ones_are_kept() -> None:
    model = Model("m")
    for i in range(view_model.PLANS_KEPT + 10):
        run = {"run_id": f"plan-{i}"}
        model.plan_event(event("robot", "execution", "PlanStarted", {**run, "action": "Greet", "steps": 1}))
        model.plan_event(event("robot", "execution", "StepStarted", {**run, "step": "s1", "type": "Speech", "competency": "say"}))
        model.plan_event(event("robot", "execution", "StepSucceeded", {**run, "step": "s1", "type": "Speech"}))
        model.plan_event(event("robot", "execution", "PlanSucceeded", run))
    model.plan_event(event("robot", "execution", "PlanStarted", {"run_id": "running", "action": "Wave", "steps": 2}))
    assert len(model.plans) == view_model.PLANS_KEPT + 1
    assert model.plans["robot/running"]["state"] == "running"
    last = model.plans[f"robot/plan-{view_model.PLANS_KEPT + 9}"]
    assert last["state"] == "succeeded" and last["steps"]["s1"]["status"] == "succeeded"
    model.alive("robot", False)
    assert model.plans["robot/running"]["state"] == "vanished"


@pytest.fixture
def served(network: MemoryNetwork, mesh: str) -> Iterator[tuple[MeshView, str, MemoryTransport]]:
    """A view on the in-memory mesh, served on a loopback port; and a transport to publish with."""
    with MemoryTransport(network, "view") as transport, MeshClient(transport, mesh) as client, \
            MeshView(client, loopback=True) as mesh_view, WebServer(mesh_view.app, name="view") as web, \
            MemoryTransport(network, "robot") as robot:
        mesh_view.start(web.call_soon)
        yield mesh_view, web.url.replace("http://", "ws://") + "/ws", robot


def receive(ws: ClientConnection) -> dict[str, Any]:
    message: dict[str, Any] = json.loads(ws.recv(timeout=10))
    return message


def test_a_page_that_does_not_read_holds_up_neither_the_mesh_nor_another_page(
    served: tuple[MeshView, str, MemoryTransport], mesh: str
) -> None:
    mesh_view, url, robot = served
    count = 6 * view_model.PAGE_EVENTS  # 12 MB: more than the sockets' buffers and the queue hold
    # The page that does not read: a small receive buffer, and a client that stops reading its
    # socket once one message waits, so the view's writes to it soon block.
    small = socket.create_connection(("127.0.0.1", int(url.split(":")[2].split("/")[0])))
    small.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    with connect(url, sock=small, max_size=None, max_queue=1, close_timeout=0.5), connect(url, max_size=None) as fast:
        assert receive(fast)["type"] == "snapshot"
        wait_for(lambda: len(mesh_view.pages) == 2, 10, "both pages connected")
        key = keys.event_key(mesh, "robot", "test", "Tick")
        started = time.monotonic()
        for seq in range(1, count + 1):
            robot.publish(key, encode(Event("robot", "test", "Tick", {"pad": "x" * 2000}, seq, time.time())))
        published = time.monotonic() - started
        seen = 0
        for _ in range(count):  # bounded: at most one message per event
            message = receive(fast)
            seen = max([seen, *(e["seq"] for e in message.get("events", []))])
            if seen == count:
                break
        assert seen == count, f"the reading page saw events up to {seen} of {count}"
        (slow_page,) = [p for p in mesh_view.pages if p.number == 1]
        wait_for(lambda: slow_page.dropped > 0, 10, "the page that does not read losing its oldest events")
        assert len(slow_page.events) <= view_model.PAGE_EVENTS
        assert len(mesh_view.model.ring) == view_model.RING
    print(f"{count} events published in {published:.2f} s while one page read nothing")


def test_a_page_from_another_site_may_not_open_the_socket(served: tuple[MeshView, str, MemoryTransport]) -> None:
    _, url, _ = served
    with pytest.raises(InvalidStatus), connect(url, origin="http://evil.example"):  # type: ignore[arg-type]
        pass
    host = url.split("/")[2]
    # DNS rebinding: a foreign name that resolves to loopback, its page "same origin" with itself.
    port = int(host.rsplit(":", 1)[1])
    rebound = socket.create_connection(("127.0.0.1", port))
    with pytest.raises(InvalidStatus), connect(f"ws://evil.example:{port}/ws", sock=rebound,
                                               origin=f"http://evil.example:{port}"):  # type: ignore[arg-type]
        pass
    with connect(url, origin=f"http://{host}", max_size=None) as ws:  # type: ignore[arg-type]
        assert receive(ws)["type"] == "snapshot"


def test_a_rebound_name_may_not_read_the_snapshot(served: tuple[MeshView, str, MemoryTransport]) -> None:
    _, url, _ = served
    port = int(url.split("/")[2].rsplit(":", 1)[1])
    with socket.create_connection(("127.0.0.1", port), timeout=10) as rebound:
        rebound.sendall(f"GET /api/snapshot HTTP/1.1\r\nHost: evil.example:{port}\r\nConnection: close\r\n\r\n".encode())
        status = rebound.makefile("rb").readline()
    assert b" 403 " in status, status
    with socket.create_connection(("127.0.0.1", port), timeout=10) as own:
        own.sendall(f"GET /api/snapshot HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n".encode())
        status = own.makefile("rb").readline()
    assert b" 200 " in status, status


def test_a_read_only_view_refuses_actions_and_bad_messages(served: tuple[MeshView, str, MemoryTransport]) -> None:
    _, url, _ = served
    with connect(url, max_size=None) as ws:
        assert receive(ws)["type"] == "snapshot"
        ws.send(json.dumps({"type": "act", "id": "x", "embodiment": "robot", "name": "Greet"}))
        ws.send("not json")
        ws.send(json.dumps({"type": "shutdown"}))
        got: list[dict[str, Any]] = []
        for _ in range(10):
            message = receive(ws)
            got.extend(message.get("changes", []))
            if len(got) >= 3:
                break
        assert got[0]["type"] == "action_result" and got[0]["status"] == "refused" and "read-only" in got[0]["reason"]
        assert [g["type"] for g in got[1:]] == ["error", "error"]
