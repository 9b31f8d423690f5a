"""The web body's page protocol without a browser: a WebSocket client in the test, the screen
embodiment on the in-memory transport. What the page sends reaches the web competencies and
becomes the world-model writes the simulated sensors make; what the body does is pushed as state."""

from __future__ import annotations

import json
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from websockets.sync.client import ClientConnection, connect

from cmion_mesh import keys
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.messages import ActionReport
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryTransport
from cmion_mesh.web.body import WebBody

WAIT = 30.0


@pytest.fixture
def screen(transport: MemoryTransport, mesh: str) -> Iterator[tuple[Embodiment, WebBody]]:
    with WebBody("127.0.0.1:0") as body:
        embodiment = Embodiment.from_architecture(embodiment_dir("screen") / "ArchitectureConfiguration.xml", mesh=mesh,
                                                  transport=transport)
        embodiment.add(body)
        with embodiment:
            yield embodiment, body


def receive(ws: ClientConnection, wanted: Callable[[dict[str, Any]], bool], what: str) -> dict[str, Any]:
    """The first message that is ``wanted``; every message before it is skipped."""
    deadline = time.monotonic() + WAIT
    for _ in range(10_000):
        left = deadline - time.monotonic()
        if left <= 0:
            break
        message: dict[str, Any] = json.loads(ws.recv(timeout=left))
        if wanted(message):
            return message
    raise TimeoutError(f"no message: {what}")


def test_the_page_senses_and_the_body_pushes(screen: tuple[Embodiment, WebBody], transport: MemoryTransport, mesh: str) -> None:
    embodiment, body = screen
    client = MeshClient(transport, mesh)
    with connect(body.url.replace("http", "ws") + "/ws") as ws:
        first = receive(ws, lambda m: m["type"] == "state", "the state on connecting")
        assert first["embodiment"] == "screen" and first["companion"] is None and first["senses"] == ["answer", "visitor"]

        ws.send(json.dumps({"type": "visitor", "name": "Guest", "present": True}))
        assert receive(ws, lambda m: m["type"] in ("ok", "error"), "the visitor's reply") == {"type": "ok", "input": "visitor"}
        wait_for(lambda: embodiment.world_model.get("Guest", "present") is True, WAIT, "Guest.present from the page")
        ws.send(json.dumps({"type": "visitor", "name": "bad/name"}))
        assert "visitor" in receive(ws, lambda m: m["type"] == "error", "a bad visitor name refused")["error"]

        ws.send(json.dumps({"type": "answer", "value": "yes"}))
        assert receive(ws, lambda m: m["type"] == "error", "an answer nobody asked for")["error"] == "nobody asked a question"

        reports: list[ActionReport] = []
        asking = threading.Thread(target=lambda: reports.append(client.act("screen", "AskIsGuest", ["Guest"], timeout=WAIT)))
        asking.start()
        try:
            spoken = receive(ws, lambda m: m["type"] == "state" and m["speech"] is not None, "the question spoken")
            assert "are you the guest" in spoken["speech"]["text"] and spoken["face"] == "speaking"
            if spoken["speech"]["audio"] is not None:  # espeak-ng installed: the sound is served
                with urllib.request.urlopen(body.url + spoken["speech"]["audio"], timeout=WAIT) as reply:
                    assert reply.headers["content-type"] == "audio/wav" and reply.read(4) == b"RIFF"
            receive(ws, lambda m: m["type"] == "state" and m["asking"] == "Guest" and m["face"] == "listening", "the question")
            ws.send(json.dumps({"type": "answer", "value": "maybe"}))
            assert "yes or no" in receive(ws, lambda m: m["type"] == "error", "an answer that is neither")["error"]
            ws.send(json.dumps({"type": "answer", "value": "yes"}))
            receive(ws, lambda m: m["type"] == "state" and m["asking"] is None, "the question answered")
        finally:
            asking.join(WAIT)
        assert reports and reports[0].status == "succeeded", reports
        assert embodiment.world_model.get("Guest", "answer") == "yes"

        embodiment.sim.raise_event("mind", "Emotion", {"mind": "mind", "valence": 0.6, "arousal": 0.2})
        receive(ws, lambda m: m["type"] == "state" and m["expression"] == "happy", "the mind's mood on the face")


def test_without_a_page_the_web_competencies_are_the_simulations(transport: MemoryTransport, mesh: str) -> None:
    embodiment = Embodiment.from_architecture(embodiment_dir("screen") / "ArchitectureConfiguration.xml", mesh=mesh,
                                              transport=transport)
    client = MeshClient(transport, mesh)
    with embodiment:
        assert client.act("screen", "Say", ["hello", "Alice"], timeout=WAIT).status == "succeeded"
        assert embodiment.blackboard.get("speech", "last") == "Hello, Alice."
        client.set_property("screen", keys.BLACKBOARD, "sim", "userPresent", "Bob")
        wait_for(lambda: embodiment.world_model.get("Bob", "present") is True, WAIT, "the simulated input still works")


def test_with_a_key_only_its_holder_may_act_others_watch(transport: MemoryTransport, mesh: str) -> None:
    """What ``up --certs`` does: the page's inputs become world-model writes on an authenticated mesh."""
    with WebBody("127.0.0.1:0", key="s3cret") as body:
        embodiment = Embodiment.from_architecture(embodiment_dir("screen") / "ArchitectureConfiguration.xml", mesh=mesh,
                                                  transport=transport)
        embodiment.add(body)
        assert body.address == body.url + "/?key=s3cret"
        with embodiment:
            visitor = json.dumps({"type": "visitor", "name": "Eve", "present": True})
            with connect(body.url.replace("http", "ws") + "/ws?key=wrong") as ws:
                assert receive(ws, lambda m: m["type"] == "access", "the page's access") == {"type": "access", "act": False}
                assert receive(ws, lambda m: m["type"] == "state", "the state")["embodiment"] == "screen"  # watching is open
                ws.send(visitor)
                assert "read-only" in receive(ws, lambda m: m["type"] == "error", "the input refused")["error"]
            with connect(body.url.replace("http", "ws") + "/ws?key=s3cret") as ws:
                assert receive(ws, lambda m: m["type"] == "access", "the page's access") == {"type": "access", "act": True}
                ws.send(visitor)
                assert receive(ws, lambda m: m["type"] in ("ok", "error"), "the reply") == {"type": "ok", "input": "visitor"}
            wait_for(lambda: embodiment.world_model.get("Eve", "present") is True, WAIT, "Eve.present from the key holder")


def test_a_command_typed_on_the_robots_page_reaches_its_world_model(transport: MemoryTransport, mesh: str) -> None:
    with WebBody(":0") as body:
        robot = Embodiment.from_architecture(embodiment_dir("robot") / "ArchitectureConfiguration.xml", mesh=mesh,
                                             transport=transport)
        robot.add(body)
        with robot, connect(body.url.replace("http", "ws") + "/ws") as ws:
            assert receive(ws, lambda m: m["type"] == "state", "the state")["senses"] == ["command"]
            ws.send(json.dumps({"type": "command", "text": "  greet   Guest "}))
            assert receive(ws, lambda m: m["type"] in ("ok", "error"), "the reply") == {"type": "ok", "input": "command"}
            wait_for(lambda: robot.world_model.get("Command", "verb") == "greet", WAIT, "the command perceived")
            assert robot.world_model.get("Command", "text") == "greet Guest"
            assert robot.world_model.get("Command", "greet") == "Guest"
            ws.send(json.dumps({"type": "command", "text": "x" * 201}))
            assert "1 to 200 characters" in receive(ws, lambda m: m["type"] == "error", "a too long command")["error"]
