"""Crash safety with real processes: kill -9 at each durable step, restart, exactly one inhabited.

Each embodiment is a daemon in its own process with its own state folder. A crash point
(``CMION_MESH_CRASH_AT``) makes the process SIGKILL itself right after writing that record;
then it is restarted on the same state and port, and the mesh must settle with the companion
inhabiting exactly one embodiment, its identity (the mind's memory) unchanged.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError, OutcomeUnknown
from cmion_mesh.messages import Migrate, MindMessage, MindState
from cmion_mesh.procs import free_port
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .helpers.remote_helpers import Node, diary_embodiment_config

pytestmark = pytest.mark.timeout(180)




@contextmanager
def node_pair(folder: Path, mesh: str, env: dict[str, str] | None = None) -> Iterator[tuple[Node, Node]]:
    """robot (where spirit is born) and screen, connected to each other, not started; stopped at the end."""
    robot_port, screen_port = free_port(), free_port()
    robot = Node("robot", mesh, diary_embodiment_config(folder / "robot", "robot"), folder / "state-robot", robot_port,
                 [f"tcp/127.0.0.1:{screen_port}"], companion="spirit", env=dict(env or {}))
    screen = Node("screen", mesh, diary_embodiment_config(folder / "screen", "screen"), folder / "state-screen", screen_port,
                  [f"tcp/127.0.0.1:{robot_port}"], env=dict(env or {}))
    try:
        yield robot, screen
    finally:
        robot.stop()
        screen.stop()


@pytest.fixture
def nodes(tmp_path: Path, mesh: str) -> Iterator[tuple[Node, Node]]:
    with node_pair(tmp_path, mesh) as pair:
        yield pair


def inhabitants(client: MeshClient, names: tuple[str, ...] = ("robot", "screen")) -> dict[str, Any]:
    found: dict[str, Any] = {}
    for name in names:
        try:
            found[name] = client.describe(name, timeout=1.0).get("inhabitant")
        except MeshError:
            found[name] = "?"
    return found


def memory(client: MeshClient, embodiment: str) -> list[str]:
    state = client.request(embodiment, "mind", "state", MindState(), timeout=5).value
    assert isinstance(state, dict)
    return list(state["entries"])


class Watcher:
    """Samples both embodiments while the test runs; records any moment with two inhabitants."""

    def __init__(self, client: MeshClient) -> None:
        self.client = client
        self.both: list[dict[str, Any]] = []
        self.samples = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="watcher")
        self._thread.start()

    def _run(self) -> None:
        # The two answers are not taken at one instant: the robot asked, then the screen, a
        # migration to the screen that ends in between shows both inhabited although they never
        # were. So the robot is asked again after the screen: two hosts only when the robot was
        # inhabited before and after the screen said it was (the companion goes robot -> screen at
        # most once here, never back).
        while not self._stop.wait(0.05) and self.samples < 5000:
            seen = inhabitants(self.client)
            self.samples += 1
            if seen.get("robot") == "spirit" and seen.get("screen") == "spirit":
                again = inhabitants(self.client, ("robot",))["robot"]
                if again == "spirit":
                    self.both.append({**seen, "robot again": again})

    def close(self) -> None:
        self._stop.set()
        self._thread.join(10)


def settle(client: MeshClient, expected: str | tuple[str, ...], notes: list[str]) -> str:
    """Wait until the companion inhabits exactly one embodiment, one of ``expected``, the other
    empty; check its memory there and return where it is."""
    homes = (expected,) if isinstance(expected, str) else expected
    last: dict[str, Any] = {}

    def one_home() -> str | None:
        last.update(inhabitants(client))
        inhabited = [name for name, who in last.items() if who == "spirit"]
        if len(inhabited) == 1 and inhabited[0] in homes and all(who is None for who in last.values() if who != "spirit"):
            return inhabited[0]
        return None

    try:
        home = wait_for(one_home, 45, f"spirit inhabits exactly one of {', '.join(homes)}")
    except TimeoutError as exc:
        raise AssertionError(f"{exc}; last seen: {last}") from None
    assert home is not None
    assert memory(client, home) == notes, "the identity arrived unchanged"
    return home


def crash_while_migrating(nodes: tuple[Node, Node], mesh: str, crash_at: str, side: Node, notes: list[str],
                          home: str | tuple[str, ...], durable: list[str]) -> None:
    """spirit, born on the robot and told ``notes``, migrates to the screen; ``side`` (one of
    ``nodes``) dies at ``crash_at`` and is restarted: then spirit inhabits exactly one of ``home``
    with the memory ``durable``, and never two embodiments at once meanwhile."""
    robot, screen = nodes
    robot.start(crash_at if side is robot else "")
    screen.start(crash_at if side is screen else "")
    with ZenohTransport(TransportConfig(connect=(robot.endpoint, screen.endpoint), multicast=False)) as t:
        client = MeshClient(t, mesh)
        wait_for(lambda: inhabitants(client) == {"robot": "spirit", "screen": None}, 30, "spirit born on the robot")
        for note in notes:
            assert client.request("robot", "mind", "message", MindMessage({"note": note})).status == "accepted"
        watcher = Watcher(client)
        try:
            try:
                started = client.request("robot", "migration", "migrate", Migrate("spirit", "screen"))
                assert started.status == "accepted", started  # the end is not awaited: only the settled state counts
            except OutcomeUnknown:
                # The source accepts, then writes prepared at once beside the prepare: killed there,
                # it may die before its answer has left. Only the settled state counts.
                if side is not robot or not crash_at.startswith("source:"):
                    raise
            assert side.died() == -9, f"{side.name} did not die at {crash_at}"
            side.start()  # restart on the same state, no crash point
            settle(client, home, durable)
        finally:
            watcher.close()
        assert not watcher.both, f"two inhabited embodiments seen: {watcher.both[:3]}"
        assert watcher.samples > 0


#: A note this long makes the identity larger than what travels inside the prepare (outgoing.INLINE):
#: its sections go apart, in chunks, and the source writes its prepared record while they travel.
LARGE = 300_000

CASES = [
    ("source:prepared", "robot", 0),   # never handed: the source aborts and resumes
    ("source:prepared", "robot", LARGE),  # the same, the crash while the sections are on their way
    ("source:handed", "screen", 0),    # past the commit point: the restarted source commits
    ("source:released", "screen", 0),
    # The prepare's answer never came: the source asks again (a prepare is idempotent). If its tries
    # end before the target is back, it aborts and resumes, and the restarted target asks and drops;
    # if one reaches the restarted target, which still holds the attempt incoming, it is answered
    # and the migration commits. Which comes first is the machine's timing: either is one home.
    ("target:incoming", ("robot", "screen"), 0),
    ("target:active", "screen", 0),    # the target activated before answering: the source's commit retry is acknowledged
]


@pytest.mark.parametrize(("crash_at", "home", "large"), CASES)
def test_kill_at_each_durable_step(nodes: tuple[Node, Node], mesh: str, crash_at: str, home: str | tuple[str, ...],
                                    large: int) -> None:
    robot, screen = nodes
    notes = ["met Ada", f"crash at {crash_at}"] + (["x" * large] if large else [])
    crash_while_migrating(nodes, mesh, crash_at, robot if crash_at.startswith("source") else screen, notes, home, notes)


def test_both_killed_at_once_then_restarted(nodes: tuple[Node, Node], mesh: str) -> None:
    robot, screen = nodes
    robot.start("source:handed")
    screen.start()
    with ZenohTransport(TransportConfig(connect=(robot.endpoint, screen.endpoint), multicast=False)) as t:
        client = MeshClient(t, mesh)
        wait_for(lambda: inhabitants(client) == {"robot": "spirit", "screen": None}, 30, "spirit born on the robot")
        client.request("robot", "mind", "message", MindMessage({"note": "before the storm"}))
        assert client.request("robot", "migration", "migrate", Migrate("spirit", "screen")).status == "accepted"
        assert robot.died() == -9
        assert screen.daemon is not None
        screen.daemon.kill()  # the target dies too, holding 'incoming'
        screen.start()
        robot.start()
        settle(client, "screen", ["before the storm"])
