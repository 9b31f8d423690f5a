"""The language-model mind in real daemons, driven by a chat-completions stand-in in another process
over real HTTP on 127.0.0.1 (tests/helpers/chat_standin.py, written from the public API spec).

It drives the robot through a plan of tool calls and migrates it to the screen, where the
conversation arrives byte-identical (the identity section the screen holds is the robot's,
hash for hash); refused, failing and malformed tool calls return their reason to the model; a slow
answer and an endpoint that goes away mid-turn lose nothing; the budget holds under a model that
calls tools in a loop. The key reaches the endpoint and nothing else.
"""

from __future__ import annotations

import hashlib
import json
import queue
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.messages import Event, MindMessage, MindState
from cmion_mesh.minds.llm.mind import LlmMind
from cmion_mesh.procs import Daemon, cli_argv
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport
from cmion_mesh.transport.zenoh import ZenohTransport

from .conftest import start_daemon
from .helpers.chat_standin import StandIn

pytestmark = pytest.mark.timeout(120)

KEY = "sk-test-5ecret-never-logged-0123456789"
SETTINGS = """
[endpoint]
model = "file-model"
timeout = {timeout}
stream = {stream}
[budget]
requests_per_minute = {rpm}
tool_calls_per_turn = {cap}
backoff_first = 0.2
backoff_cap = 1
"""


def architecture(tmp_path: Path, body: str, *, companion: bool = False, timeout: float = 10, stream: bool = False,
                 rpm: int = 600, cap: int = 8) -> Path:
    """The shipped body's files with a language-model mind whose settings suit a test."""
    settings = tmp_path / f"{body}-llm.toml"
    settings.write_text(SETTINGS.format(timeout=timeout, stream=str(stream).lower(), rpm=rpm, cap=cap))
    shipped = embodiment_dir(body)
    path = tmp_path / f"{body}.xml"
    path.write_text(f"""<ArchitectureConfiguration Embodiment="{body}" {'Companion="spirit"' if companion else ''}
      CompetencyManagerRulesFile="{shipped / 'CompetencyManagerRules.xml'}"
      CompetencyLibraryConfigurationFile="{shipped / 'CompetencyLibrary.xml'}"
      WorldModelInitFile="{shipped / 'WorldModel.xml'}">
      <ArchitectureComponent ClassName="cmion_mesh.minds.llm.mind:LlmMind" ConstructorParameters="mind,{settings}"/>
    </ArchitectureConfiguration>""")
    return path


@pytest.fixture
def standin(monkeypatch: pytest.MonkeyPatch) -> Iterator[StandIn]:
    with StandIn(key=KEY) as s:
        # The daemons inherit this environment: it wins over the settings file's endpoint and model.
        monkeypatch.setenv("CMION_MESH_LLM_BASE_URL", s.base_url)
        monkeypatch.setenv("CMION_MESH_LLM_MODEL", "standin-model")
        monkeypatch.setenv("CMION_MESH_LLM_API_KEY", KEY)
        yield s


class Mesh:
    """Daemons of one mesh and a client of it that collects the minds' events."""

    def __init__(self, mesh: str) -> None:
        self.mesh = mesh
        self.daemons: dict[str, Daemon] = {}
        self.endpoints: dict[str, str] = {}
        self.client: MeshClient | None = None
        self.events: queue.SimpleQueue[Event] = queue.SimpleQueue()
        self.seen: list[Event] = []

    def up(self, name: str, arch: Path, state: Path) -> None:
        connect = [a for e in self.endpoints.values() for a in ("--connect", e)]
        daemon, endpoint = start_daemon(self.mesh, name, str(arch), "--state-dir", str(state), *connect)
        self.daemons[name], self.endpoints[name] = daemon, endpoint

    def connect(self) -> MeshClient:
        transport = ZenohTransport(TransportConfig(connect=tuple(self.endpoints.values()), multicast=False))
        self.client = MeshClient(transport, self.mesh)
        for name in self.endpoints:
            self.client.wait_for_embodiment(name, timeout=20)
            self.client.events(self.events.put, embodiment=name, component="mind")
        return self.client

    def event(self, name: str, timeout: float = 20, **match: Any) -> Event:
        """The first event ``name`` (seen before or arriving) whose data has the values of ``match``."""
        def found() -> Event | None:
            while True:
                try:
                    self.seen.append(self.events.get_nowait())
                except queue.Empty:
                    break
            for e in self.seen:
                data = e.data if isinstance(e.data, dict) else {}
                if e.name == name and all(str(v) in str(data.get(k)) for k, v in match.items()):
                    return e
            return None

        return wait_for(found, timeout, f"event {name} {match}")

    def results(self) -> list[str]:
        while True:
            try:
                self.seen.append(self.events.get_nowait())
            except queue.Empty:
                break
        return [str(e.data["result"]) for e in self.seen if e.name == "LlmToolResult" and isinstance(e.data, dict)]

    def output(self) -> str:
        return "\n".join(line for d in self.daemons.values() for line in d.lines)

    def close(self) -> None:
        if self.client is not None:
            self.client.transport.close()
        for daemon in self.daemons.values():
            daemon.stop()


@pytest.fixture
def net(mesh: str) -> Iterator[Mesh]:
    m = Mesh(mesh)
    try:
        yield m
    finally:
        m.close()


def tool_messages(body: dict[str, Any]) -> list[str]:
    return [m["content"] for m in body["messages"] if m["role"] == "tool"]


def say(client: MeshClient, body: str, text: str) -> None:
    outcome = client.request(body, "mind", "message", MindMessage({"text": text}))
    assert outcome.status == "accepted", outcome


def test_the_model_drives_the_robot_then_migrates_with_its_conversation(standin: StandIn, net: Mesh, tmp_path: Path) -> None:
    standin.script({"content": "I am in the office."})  # the arrival turn
    net.up("screen", architecture(tmp_path, "screen"), tmp_path / "screen-state")
    net.up("robot", architecture(tmp_path, "robot", companion=True), tmp_path / "robot-state")
    client = net.connect()
    wait_for(lambda: len(standin.requests()) >= 1, 20, "the robot's mind told the model where it is")
    wait_for(lambda: "screen" in client.describe("robot")["alive"], 20, "the robot sees the screen")

    standin.script(
        {"tool_calls": [{"name": "GoTo", "arguments": {"location": "Kitchen"}}]},
        {"tool_calls": [{"name": "Express", "arguments": {"animation": "happy"}}]},
        {"tool_calls": [{"name": "Migrate", "arguments": {"target": "screen"}}]},
        {"content": "Hello from the entrance."},
        default={"content": "ok"},
    )
    say(client, "robot", "Go to the kitchen, smile, then wait for the guest at the entrance screen.")
    net.event("LlmToolResult", tool="Migrate")
    wait_for(lambda: client.describe("screen")["inhabitant"] == "spirit", 30, "the companion lives on the screen")
    wait_for(lambda: len(standin.requests()) >= 5, 30, "the screen's mind asked the model")

    bodies = standin.bodies()
    first = bodies[0]
    assert [t["function"]["name"] for t in first["tools"]] == ["Say", "GoTo", "Greet", "Express", "Migrate"]
    migrate = next(t for t in first["tools"] if t["function"]["name"] == "Migrate")
    assert migrate["function"]["parameters"]["properties"]["target"]["enum"] == ["screen"]
    assert "You are now in the body robot" in first["messages"][-1]["content"]
    assert "Kitchen (object): isLocation=true" in first["messages"][-1]["content"]
    plan = bodies[1:4]
    assert plan[0]["messages"][-1]["content"].startswith("message: Go to the kitchen")
    assert tool_messages(plan[1]) == ["succeeded"] and tool_messages(plan[2]) == ["succeeded", "succeeded"]
    on_screen = bodies[4]
    assert [t["function"]["name"] for t in on_screen["tools"]] == ["Say", "Greet", "AskIsGuest_1", "AskIsGuest_2", "Express", "Migrate"]
    assert tool_messages(on_screen)[-1] == "succeeded: you migrated from robot and now live in screen"
    arrival = on_screen["messages"][-1]["content"]
    assert arrival.startswith("You are now in the body screen (you came from robot). Your tools here: Say(speechAct, addressee)")
    # The robot's conversation as it left is the start of the screen's, message for message.
    assert on_screen["messages"][: len(plan[2]["messages"])] == plan[2]["messages"]

    # Byte-identical: the section the robot packed is the one the screen holds, by its SHA-256.
    left = client.request("robot", "mind", "state", MindState()).value
    assert isinstance(left, dict) and left["body"] == "robot" and left["calls"][0]["tool"] == "Migrate"
    packed = msgspec.msgpack.encode(left)
    held = {p.name for p in (tmp_path / "screen-state").rglob("*") if p.is_file()}
    assert hashlib.sha256(packed).hexdigest() in held
    arrived = client.request("screen", "mind", "state", MindState()).value
    assert isinstance(arrived, dict)
    assert msgspec.json.encode(arrived["messages"][: len(left["messages"])]) == msgspec.json.encode(left["messages"])

    # The key went to the endpoint with every request, and nowhere else.
    assert all(r["auth"] for r in standin.requests())
    stored = b"".join(p.read_bytes() for d in ("robot-state", "screen-state") for p in (tmp_path / d).rglob("*") if p.is_file())
    assert KEY.encode() not in stored
    assert KEY not in net.output()
    assert KEY not in json.dumps(client.describe("robot")) and KEY not in json.dumps([e.data for e in net.seen])
    for body in ("robot", "screen"):
        for store in ("bb", "wm"):
            assert KEY not in repr(client.read_store(body, store))


def test_refused_failing_and_malformed_calls_return_their_reason(standin: StandIn, net: Mesh, tmp_path: Path) -> None:
    standin.script({"content": "ok"})
    net.up("robot", architecture(tmp_path, "robot", companion=True, stream=True), tmp_path / "robot-state")
    client = net.connect()
    wait_for(lambda: len(standin.requests()) >= 1, 20, "the arrival turn")
    standin.script({"tool_calls": [
        {"name": "Fly", "arguments": {"to": "Moon"}},
        {"name": "GoTo", "arguments": {"location": "CoffeeMachine"}},
        {"name": "GoTo", "arguments": {"where": "Kitchen"}},
        {"name": "Express", "arguments": "{not json"},
        {"name": "Express", "arguments": {"animation": "nod"}},
    ]}, default={"content": "ok"})
    say(client, "robot", "try things")
    wait_for(lambda: len(standin.requests()) >= 3, 20, "the results went back to the model")
    body = standin.bodies()[2]
    assert body["stream"] is True
    results = tool_messages(body)
    assert results[0].startswith("refused: this body (robot) has no tool 'Fly'; its tools: Say, GoTo, Greet, Express")
    assert results[1].startswith("failed: ") and "CoffeeMachine" in results[1]
    assert results[2] == "bad arguments: GoTo: unknown argument(s) where; it takes (location)"
    assert results[3].startswith("bad arguments: not JSON")
    assert results[4] == "succeeded"
    calls = [c["function"] for m in body["messages"] if m["role"] == "assistant" for c in m.get("tool_calls") or ()]
    assert calls[-1] == {"name": "Express", "arguments": '{"animation": "nod"}'}, "streamed pieces were put together"


def test_a_slow_answer_and_an_endpoint_gone_mid_turn_lose_nothing(standin: StandIn, net: Mesh, tmp_path: Path) -> None:
    standin.script({"content": "ok"})
    net.up("robot", architecture(tmp_path, "robot", companion=True, timeout=1.5), tmp_path / "robot-state")
    client = net.connect()
    wait_for(lambda: len(standin.requests()) >= 1, 20, "the arrival turn")
    standin.script({"delay": 4, "content": "too late"}, {"delay": 60, "content": "never"})
    say(client, "robot", "the guest Ada is coming at noon")
    down = net.event("LlmEndpointDown")
    assert "no answer within 1.5 s" in str(down.data)
    wait_for(lambda: len(standin.requests()) >= 3, 20, "asked again after the timeout")
    standin.kill()  # gone while it holds the second try
    port = standin.port
    with StandIn(port=port, key=KEY) as again:
        again.script({"tool_calls": [{"name": "Express", "arguments": {"animation": "nod"}}]}, default={"content": "noted"})
        net.event("LlmEndpointUp", timeout=30)
        wait_for(lambda: len(again.requests()) >= 2, 20, "the turn went on")
        first = again.bodies()[0]
        assert first["messages"][-1]["content"] == "message: the guest Ada is coming at noon", "nothing lost"
        assert tool_messages(again.bodies()[1]) == ["succeeded"]
        assert client.describe("robot")["inhabitant"] == "spirit", "the companion kept its body"
        lines = [line for line in net.output().splitlines() if "language-model endpoint" in line and "failed" in line]
        assert lines and "the companion keeps its body" in lines[0]
        assert KEY not in net.output()


def test_the_budget_holds_under_a_model_that_calls_tools_in_a_loop(standin: StandIn, net: Mesh, tmp_path: Path) -> None:
    loop = {"tool_calls": [{"name": "Express", "arguments": {"animation": "nod"}}], "force": True}
    standin.script({"content": "ok"}, default=loop)
    net.up("robot", architecture(tmp_path, "robot", companion=True, rpm=6, cap=3), tmp_path / "robot-state")
    client = net.connect()
    wait_for(lambda: len(standin.requests()) >= 1, 20, "the arrival turn")
    say(client, "robot", "nod")
    wait_for(lambda: len(standin.requests()) >= 5, 20, "the loop ran into the cap")
    results = net.results()
    wait_for(lambda: any(r.startswith("refused: the cap of 3") for r in net.results()), 20, "the fourth call refused")
    results = net.results()
    assert results.count("succeeded") == 3
    bodies = standin.bodies()
    assert all("tools" in b for b in bodies[1:4]) and "tools" not in bodies[4], "past the cap, no tools are offered"
    say(client, "robot", "nod again")  # the sixth request of the minute
    wait_for(lambda: len(standin.requests()) >= 6, 20, "the sixth request")
    say(client, "robot", "and again")  # a seventh would break 6 a minute: it waits
    wait = net.event("LlmBudgetWait")
    assert float(wait.data["seconds"]) > 30  # type: ignore[index]
    assert len(standin.requests()) == 6
    assert net.results().count("succeeded") == 3, "no action past the cap"


def test_a_mind_in_another_process_reads_the_bodys_tools_over_the_mesh(standin: StandIn, net: Mesh, tmp_path: Path) -> None:
    net.up("robot", embodiment_dir("robot"), tmp_path / "robot-state")  # the shipped robot, its planner mind and all
    settings = tmp_path / "llm.toml"
    settings.write_text(SETTINGS.format(timeout=10, stream="false", rpm=600, cap=8))
    standin.script({"tool_calls": [{"name": "GoTo", "arguments": {"location": "Kitchen"}}]}, default={"content": "ok"})
    mind = Daemon(cli_argv("serve-mind", "cmion_mesh.minds.llm.mind:LlmMind", "--embodiment", "robot", "--parameters",
                           f"remote,{settings}", "--mesh", net.mesh, "--no-multicast", "--connect", net.endpoints["robot"]),
                  name="serve-mind")
    with mind:
        mind.wait_line("serving embodiment", 20)
        wait_for(lambda: len(standin.requests()) >= 2, 30, "the remote mind acted and told the model")
        first, second = standin.bodies()[:2]
        assert [t["function"]["name"] for t in first["tools"]][:4] == ["Say", "GoTo", "Greet", "Express"]
        assert "You are now in the body robot" in first["messages"][-1]["content"]
        assert "(not known here" in first["messages"][-1]["content"], "a remote mind perceives the world's changes only"
        assert tool_messages(second) == ["succeeded"]


def test_close_ends_a_request_in_flight(standin: StandIn, tmp_path: Path, network: MemoryNetwork, mesh: str) -> None:
    standin.script({"delay": 60, "content": "never read"})
    settings = tmp_path / "llm.toml"
    settings.write_text(SETTINGS.format(timeout=120, stream="false", rpm=600, cap=8))
    mind = LlmMind("mind", str(settings))
    with MemoryTransport(network, "robot") as t:
        body = Embodiment("robot", mesh=mesh, transport=t, rules=embodiment_dir("robot") / "CompetencyManagerRules.xml",
                          components=[mind]).start()
        try:
            wait_for(lambda: len(standin.requests()) == 1, 20, "the arrival turn is at the endpoint, which holds it")
            assert mind.running
        finally:
            body.close()
        assert not mind.running, "the worker stopped although the endpoint had not answered"
        assert mind.conversation.messages == [] and mind.conversation.inbox, "nothing committed, nothing lost"
