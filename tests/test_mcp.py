"""``cmion-mesh mcp``: the official MCP SDK's client, in this process, drives a companion through
the server in another (``cmion-mesh mcp`` spawned over stdio, or serving streamable HTTP), against
two real daemons (robot, screen) in processes of their own."""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import anyio
import mcp_types as types
import pytest
from mcp import Client, StdioServerParameters
from mcp.client.subscriptions import ResourceUpdated

from cmion_mesh.client import MeshClient
from cmion_mesh.messages import Event
from cmion_mesh.procs import Daemon, cli_argv, free_port, unique_mesh
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.tools.demo import Scenario, stop_bodies
from cmion_mesh.transport import certs
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

pytestmark = pytest.mark.timeout(180)
BODIES = ("robot", "screen")


@pytest.fixture(scope="module")
def bodies(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Scenario]:
    mesh = unique_mesh()
    state = tmp_path_factory.mktemp("mcp")
    scenario = Scenario(mesh, {name: f"tcp/127.0.0.1:{free_port()}" for name in BODIES})
    try:
        for name in BODIES:
            others = [a for other in BODIES if other != name for a in ("--connect", scenario.endpoints[other])]
            scenario.daemons[name] = Daemon(cli_argv("up", name, "--mesh", mesh, "--listen", scenario.endpoints[name],
                                                     "--no-multicast", "--state-dir", str(state / name), *others), name=name)
        for daemon in scenario.daemons.values():
            daemon.wait_line("up in mesh", 30)
        yield scenario
    finally:
        stop_bodies(scenario)


def net(s: Scenario) -> list[str]:
    return ["--mesh", s.mesh, "--no-multicast", "--connect", s.endpoints["robot"]]


@contextlib.contextmanager
def mesh_client(s: Scenario) -> Iterator[MeshClient]:
    with ZenohTransport(TransportConfig(connect=(s.endpoints["robot"],), multicast=False)) as t, MeshClient(t, s.mesh) as c:
        yield c


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cli_argv(*args), capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)


class Inbox:
    """What the server sent the client besides answers (notifications), in order."""

    def __init__(self) -> None:
        self.notifications: list[Any] = []
        self.changed = anyio.Event()

    async def __call__(self, message: Any) -> None:
        if isinstance(message, types.ServerNotification):
            self.notifications.append(message)
            self.changed.set()
            self.changed = anyio.Event()

    async def wait(self, kind: type, after: int = 0, timeout: float = 15.0) -> Any:
        with anyio.fail_after(timeout):
            while True:
                for message in self.notifications[after:]:
                    if isinstance(message, kind):
                        return message
                await self.changed.wait()


@contextlib.asynccontextmanager
async def stdio(s: Scenario, *extra: str, inbox: Inbox | None = None) -> AsyncIterator[Client]:
    argv = cli_argv("mcp", "spirit", *extra, *net(s))
    params = StdioServerParameters(command=argv[0], args=argv[1:], env=dict(os.environ))
    # mode="legacy": the initialize handshake, as desktop clients speak it today.
    async with Client(params, mode="legacy", message_handler=inbox) as client:
        yield client


def tool_names(result: types.ListToolsResult) -> list[str]:
    return [t.name for t in result.tools]


def abilities_of(s: Scenario, body: str) -> list[str]:
    with mesh_client(s) as client:
        client.join(body)
        return [a["tool"] for a in client.describe(body)["abilities"] if a["action"] != "Migrate"]


def set_policy(s: Scenario, accepts: list[str] | None) -> None:
    with mesh_client(s) as client:
        client.join("robot")
        client.set_policy("spirit", accepts)


def text(result: types.CallToolResult) -> str:
    return " ".join(c.text for c in result.content if isinstance(c, types.TextContent))


def test_tools_follow_the_companion_and_actions_return_their_outcome(bodies: Scenario) -> None:
    robot, screen = abilities_of(bodies, "robot"), abilities_of(bodies, "screen")
    assert "GoTo" in robot and "GoTo" not in screen  # a screen cannot navigate

    async def main() -> None:
        inbox = Inbox()
        async with stdio(bodies, "--allow-actions", inbox=inbox) as client:
            assert tool_names(await client.list_tools()) == ["migrate", "peers", *robot]
            seen = len(inbox.notifications)
            await anyio.to_thread.run_sync(set_policy, bodies, ["robot", "phone"])  # the screen is not accepted
            await inbox.wait(types.ToolListChangedNotification, after=seen)
            assert (await client.list_tools()).tools[0].input_schema["properties"]["target"]["enum"] == []
            refused = await client.call_tool("migrate", {"target": "screen"})
            assert refused.is_error and "'screen' is not an embodiment the companion may move to now" in text(refused)
            seen = len(inbox.notifications)
            await anyio.to_thread.run_sync(set_policy, bodies, None)
            await inbox.wait(types.ToolListChangedNotification, after=seen)
            assert (await client.list_tools()).tools[0].input_schema["properties"]["target"]["enum"] == ["screen"]
            ok = await client.call_tool("GoTo", {"location": "Kitchen"})
            assert not ok.is_error and ok.structured_content["status"] == "succeeded", ok
            assert ok.structured_content["embodiment"] == "robot"
            failed = await client.call_tool("GoTo", {"location": "CoffeeMachine"})
            assert failed.is_error and "unknown location 'CoffeeMachine'" in text(failed), failed
            wrong = await client.call_tool("GoTo", {"where": "Kitchen"})
            assert wrong.is_error and "unknown argument(s) where" in text(wrong)
            peers = await client.call_tool("peers", {})
            assert {p["name"]: p["inhabitant"] for p in peers.structured_content["peers"]} == {"robot": "spirit", "screen": None}
            seen = len(inbox.notifications)
            moved = await client.call_tool("migrate", {"target": "screen"})
            assert not moved.is_error and moved.structured_content["source"] == "robot", moved
            await inbox.wait(types.ToolListChangedNotification, after=seen)
            with anyio.fail_after(10):
                while tool_names(tools := await client.list_tools()) != ["migrate", "peers", *screen]:
                    await anyio.sleep(0.05)
            assert tools.tools[0].input_schema["properties"]["target"]["enum"] == ["robot"]
            resources = await client.list_resources()
            assert all("(on screen)" in (r.title or "") for r in resources.resources)
            gone = await client.call_tool("GoTo", {"location": "Kitchen"})
            assert gone.is_error and "no tool 'GoTo': spirit lives in screen now, which offers migrate, peers" in text(gone)
            back = await client.call_tool("migrate", {"target": "robot"})
            assert not back.is_error, back
            with anyio.fail_after(10):
                while "GoTo" not in tool_names(await client.list_tools()):
                    await anyio.sleep(0.05)

    anyio.run(main)


def test_a_cancelled_call_cancels_the_action_in_the_body(bodies: Scenario) -> None:
    assert cli("wm", "set", "robot", "Lab/travelSteps", "100000", *net(bodies)).returncode == 0  # a very long trip
    progress: list[tuple[float, str | None]] = []
    with mesh_client(bodies) as watcher:
        watcher.join("robot")
        ends: list[Event] = []
        handle = watcher.events(ends.append, embodiment="robot", component="manager", event="ActionCancelled")
        try:
            async def main() -> None:
                async with stdio(bodies, "--allow-actions") as client:
                    async def on_progress(value: float, total: float | None, message: str | None) -> None:
                        progress.append((value, message))

                    async with anyio.create_task_group() as group:
                        async def call() -> None:
                            await client.call_tool("GoTo", {"location": "Lab"}, progress_callback=on_progress)

                        group.start_soon(call)
                        with anyio.fail_after(20):
                            while len(progress) < 3:
                                await anyio.sleep(0.02)
                        group.cancel_scope.cancel()  # the SDK sends notifications/cancelled

            anyio.run(main)
            wait_for(lambda: [e for e in ends if e.data.get("name") == "GoTo"], 15, "the action cancelled in the body")
        finally:
            handle.close()
            assert cli("wm", "set", "robot", "Lab/travelSteps", "6", *net(bodies)).returncode == 0
    assert [v for v, _ in progress] == sorted(v for v, _ in progress)
    assert any(m and "step" in m and "to Lab" in m for _, m in progress), progress


@pytest.mark.filterwarnings("ignore:resources/subscribe is removed")
def test_world_model_is_read_and_subscribed(bodies: Scenario) -> None:
    async def main() -> None:
        inbox = Inbox()
        async with stdio(bodies, inbox=inbox) as client:
            uris = {r.name: r.uri for r in (await client.list_resources()).resources}
            assert set(uris) == {"world-model", "blackboard"}
            read = await client.read_resource(uris["world-model"])
            first = read.contents[0]
            assert isinstance(first, types.TextResourceContents)
            assert '"embodiment": "robot"' in first.text and '"Self/displayName": "Spirit"' in first.text
            await client.subscribe_resource(uris["world-model"])
            seen = len(inbox.notifications)
            written = await anyio.to_thread.run_sync(lambda: cli("wm", "set", "robot", "Self.mood", "cheerful", *net(bodies)))
            assert written.returncode == 0, written
            updated = await inbox.wait(types.ResourceUpdatedNotification, after=seen)
            assert updated.params.uri == uris["world-model"]
            again = (await client.read_resource(uris["world-model"])).contents[0]
            assert isinstance(again, types.TextResourceContents) and '"Self/mood": "cheerful"' in again.text

    anyio.run(main)


def test_read_only_lists_the_tools_and_refuses_to_act(bodies: Scenario) -> None:
    async def main() -> None:
        async with stdio(bodies) as client:
            assert "GoTo" in tool_names(await client.list_tools())
            refused = await client.call_tool("GoTo", {"location": "Kitchen"})
            assert refused.is_error and "read-only" in text(refused) and "--allow-actions" in text(refused)
            moved = await client.call_tool("migrate", {"target": "screen"})
            assert moved.is_error and "read-only" in text(moved)
            peers = await client.call_tool("peers", {})
            assert not peers.is_error

    anyio.run(main)
    with mesh_client(bodies) as client:
        assert client.find_companion("spirit") == "robot"


def test_streamable_http_on_loopback(bodies: Scenario, tmp_path: Path) -> None:
    with Daemon(cli_argv("mcp", "spirit", "--http", "127.0.0.1:0", "--allow-actions", *net(bodies)), name="mcp") as server:
        line = server.wait_line("mcp server of companion", 30)
        url = line.split(" at ", 1)[1].split()[0]
        assert url.startswith("http://127.0.0.1:") and url.endswith("/mcp")

        async def main() -> None:
            async with Client(url) as client:  # mode "auto": the SDK's newest protocol (2026-07-28) when the server has it
                assert "GoTo" in tool_names(await client.list_tools())
                ok = await client.call_tool("GoTo", {"location": "Kitchen"})
                assert not ok.is_error and ok.structured_content["status"] == "succeeded", ok
                uri = "cmion-mesh://spirit/world-model"
                async with client.listen(tools_list_changed=True, resource_subscriptions=[uri]) as events:
                    written = await anyio.to_thread.run_sync(lambda: cli("wm", "set", "robot", "Self.mood", "calm", *net(bodies)))
                    assert written.returncode == 0, written
                    with anyio.fail_after(15):
                        async for event in events:
                            if isinstance(event, ResourceUpdated) and event.uri == uri:
                                break
                read = (await client.read_resource(uri)).contents[0]
                assert isinstance(read, types.TextResourceContents) and '"Self/mood": "calm"' in read.text

        anyio.run(main)


def test_a_body_that_vanishes_mid_action_gives_outcome_unknown_naming_it(tmp_path: Path) -> None:
    mesh, endpoint = unique_mesh(), f"tcp/127.0.0.1:{free_port()}"
    robot = Daemon(cli_argv("up", "robot", "--mesh", mesh, "--listen", endpoint, "--no-multicast",
                            "--state-dir", str(tmp_path / "robot")), name="robot")
    with robot:
        robot.wait_line("up in mesh", 30)
        assert cli("wm", "set", "robot", "Lab/travelSteps", "100000", "--mesh", mesh, "--no-multicast",
                   "--connect", endpoint).returncode == 0
        argv = cli_argv("mcp", "spirit", "--allow-actions", "--mesh", mesh, "--no-multicast", "--connect", endpoint)

        async def main() -> None:
            params = StdioServerParameters(command=argv[0], args=argv[1:], env=dict(os.environ))
            async with Client(params, mode="legacy") as client:
                started = anyio.Event()

                async def on_progress(value: float, total: float | None, message: str | None) -> None:
                    started.set()

                results: list[types.CallToolResult] = []
                async with anyio.create_task_group() as group:
                    async def call() -> None:
                        results.append(await client.call_tool("GoTo", {"location": "Lab"}, progress_callback=on_progress))

                    group.start_soon(call)
                    with anyio.fail_after(20):
                        await started.wait()
                    robot.kill()
                result = results[0]
                assert result.is_error and text(result).startswith("outcome unknown: robot left the mesh"), result
                assert result.structured_content["status"] == "unknown"

        anyio.run(main)


def test_secure_mode_speaks_as_a_certificate_and_the_access_rules_apply(tmp_path: Path) -> None:
    pki = tmp_path / "pki"
    certs.init(pki)
    certs.issue(pki, "robot")
    certs.issue(pki, "phone")  # a member: another embodiment's identity
    certs.issue(pki, "admin", role="operator")
    mesh, port = unique_mesh(), free_port()
    common = ["--mesh", mesh, "--certs", str(pki), "--no-multicast"]
    with Daemon(cli_argv("up", "robot", "--name", "robot", *common, "--listen", f"tcp/127.0.0.1:{port}",
                         "--state-dir", str(tmp_path / "robot")), name="robot") as robot:
        robot.wait_line("up in mesh", 30)

        async def main(identity: str) -> types.CallToolResult:
            argv = cli_argv("mcp", "spirit", "--allow-actions", *common, "--identity", identity, "--connect", f"tls/127.0.0.1:{port}")
            params = StdioServerParameters(command=argv[0], args=argv[1:], env=dict(os.environ))
            async with Client(params, mode="legacy") as client:
                assert "GoTo" in tool_names(await client.list_tools())  # a member may read what the body offers
                return await client.call_tool("GoTo", {"location": "Kitchen"})

        operator = anyio.run(main, "admin")
        assert not operator.is_error and operator.structured_content["status"] == "succeeded", operator
        member = anyio.run(main, "phone")
        assert member.is_error and member.structured_content["status"] == "not_reached", member
        assert text(member).startswith("not delivered, nothing was done") and "an operator's certificate may act" in text(member)
