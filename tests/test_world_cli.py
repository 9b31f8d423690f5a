"""Simulating the world from the shell, each part a process of its own over real zenoh (loopback):
one daemon hosting the companion with the FAtiMA connector, the stand-in FAtiMA on its socket, a
Python mind served from another process, and ``cmion-mesh wm add|set|get|remove`` and
``cmion-mesh remote-action`` run as a person runs them."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.messages import Event, SetProperty
from cmion_mesh.procs import Daemon, cli_argv, free_port, unique_mesh
from cmion_mesh.testing.fatima_peer import PeerProcess
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

pytestmark = pytest.mark.timeout(120)


@dataclass
class World:
    mesh: str
    endpoint: str
    fatima: PeerProcess
    perceived: list[dict[str, Any]]  # what the mind in another process perceived

    def cli(self, *args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(cli_argv(*args, "--mesh", self.mesh, "--connect", self.endpoint, "--no-multicast"),
                              capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)

    def ok(self, *args: str) -> str:
        done = self.cli(*args)
        assert done.returncode == 0, done.stderr
        return done.stdout

    def perceives(self, wanted: dict[str, Any]) -> None:
        wait_for(lambda: wanted in list(self.perceived), 15, f"the served mind perceiving {wanted}")


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Iterator[World]:
    tmp = tmp_path_factory.mktemp("world")
    mesh, port, mind_port = unique_mesh(), free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    (tmp / "rules.xml").write_text("<CompetencyManagerRules/>")
    (tmp / "library.xml").write_text("<CompetencyLibrary/>")
    (tmp / "world.xml").write_text('<WorldModel><Agent Name="Self"><Property Name="location" Value="Hall"/></Agent></WorldModel>')
    config = tmp / "ArchitectureConfiguration.xml"
    config.write_text(
        '<ArchitectureConfiguration Embodiment="robot" CompetencyManagerRulesFile="rules.xml"'
        ' CompetencyLibraryConfigurationFile="library.xml" WorldModelInitFile="world.xml">\n'
        f'  <ArchitectureComponent ClassName="cmion.level3.fatima.FAtiMAConnector" ConstructorParameters="modular port:{mind_port}"/>\n'
        "</ArchitectureConfiguration>\n")
    robot = Daemon(cli_argv("up", str(config), "--mesh", mesh, "--listen", endpoint, "--no-multicast",
                            "--state-dir", str(tmp / "state"), "--companion", "spirit"), name="robot")
    with robot:
        robot.wait_line("up in mesh", 30)
        served = Daemon(cli_argv("serve-mind", "tests.helpers.remote_helpers:Perceiver", "--embodiment", "robot", "--mesh", mesh,
                                 "--connect", endpoint, "--no-multicast"), name="perceiver")
        with served, ZenohTransport(TransportConfig(connect=(endpoint,), multicast=False)) as transport, \
                MeshClient(transport, mesh) as client:
            served.wait_line("serving embodiment", 20)
            perceived: list[dict[str, Any]] = []

            def note(event: Event) -> None:
                perceived.append(event.data)

            with client.events(note, embodiment="robot", component="perceiver", event="Perceived"):
                fatima = PeerProcess(mind_port, "--agent", "Spirit", "--prop", "role:TestAgent")
                try:
                    fatima.got("CMD GET-PROPERTIES", timeout=20)  # the companion lives here: the mind is awake
                    fatima.got("ENTITY-ADDED Self")
                    # the served mind's subscriptions are declared: it hears a change made now
                    wait_for(lambda: client.write("robot", "wm", SetProperty("Self", "touched", True)).status == "accepted" and
                             any(p.get("name") == "touched" for p in list(perceived)), 20, "the served mind listening")
                    yield World(mesh, endpoint, fatima, perceived)
                finally:
                    fatima.close()


def test_wm_add_and_remove_reach_minds_as_entities_coming_and_going(world: World) -> None:
    start = world.fatima.mark()
    out = world.ok("wm", "add", "robot", "Visitor", "present=true", "name=Ada", "--json")
    assert json.loads(out) == {"added": f"cmion/{world.mesh}/robot/wm/Visitor", "kind": "agent",
                               "properties": {"present": True, "name": "Ada"}, "persistent": False}
    added = world.fatima.got("ENTITY-ADDED Visitor", start=start)
    world.fatima.got("PROPERTY-CHANGED * Visitor(name) Ada", start=start)
    received = world.fatima.received(start)
    assert received.index(added) < received.index("PROPERTY-CHANGED * Visitor(present) True")
    world.perceives({"op": "added", "entity": "Visitor", "kind": "agent"})
    world.perceives({"op": "changed", "entity": "Visitor", "name": "present", "value": True})
    again = world.cli("wm", "add", "robot", "Visitor")
    assert again.returncode == 1 and "already exists" in again.stderr and len(again.stderr.strip().splitlines()) == 1
    # a vase, an object, then gone
    assert "added object Vase" in world.ok("wm", "add", "robot", "Vase", "--object")
    assert "removed entity Vase" in world.ok("wm", "remove", "robot", "Vase")
    world.fatima.got("ENTITY-REMOVED Vase", start=start)
    world.perceives({"op": "removed", "entity": "Vase", "kind": "object"})
    bad = world.cli("wm", "add", "robot", "Cat", "hungry")
    assert bad.returncode == 2 and "'hungry' is not PROPERTY=VALUE" in bad.stderr
    # a dotted name would be read as entity.property: refused before anything is written, saying what to use
    dotted = world.cli("wm", "add", "robot", "Bad.Name", "x=1")
    assert dotted.returncode == 2 and dotted.stderr.count("\n") == 1, dotted.stderr
    assert "entity 'Bad.Name' holds '.'" in dotted.stderr and "'Bad_Name'" in dotted.stderr
    assert "Bad.Name" not in world.ok("wm", "tree", "robot")
    # properties after the options, as after the name
    assert "added object Box weight=3.5 fragile=false" in world.ok("wm", "add", "robot", "Box", "--object", "weight=3.5",
                                                                   "fragile=false")


def test_dotted_paths_mean_the_same_in_get_and_set(world: World) -> None:
    world.ok("wm", "add", "robot", "Guest")
    assert "Guest/mood = \"happy\"" in world.ok("wm", "set", "robot", "Guest.mood", "happy")
    dotted = json.loads(world.ok("wm", "get", "robot", "Guest.mood", "--json"))
    slashed = json.loads(world.ok("wm", "get", "robot", "Guest/mood", "--json"))
    assert dotted == slashed == {f"cmion/{world.mesh}/robot/wm/Guest/mood": {"type": "property", "value": "happy",
                                                                             "persistent": False}}
    tree = json.loads(world.ok("wm", "tree", "robot", "--json"))
    assert not [key for key in tree if key.endswith("Guest.mood")]
    world.fatima.got("PROPERTY-CHANGED * Guest(mood) happy")
    # no entity: refused, saying how to add it, and no property made anywhere
    ghost = world.cli("wm", "set", "robot", "Ghost.mood", "sad")
    assert ghost.returncode == 1 and "no entity 'Ghost'" in ghost.stderr and "cmion-mesh wm add robot Ghost" in ghost.stderr
    root = world.cli("wm", "set", "robot", "mood", "sad")
    assert root.returncode == 1 and "root holds entities" in root.stderr
    dot = world.cli("wm", "get", "robot", ".mood")
    assert dot.returncode == 2 and "entity.property" in dot.stderr
    assert "removed Guest/mood" in world.ok("wm", "remove", "robot", "Guest.mood")
    gone = world.cli("wm", "get", "robot", "Guest/mood")
    assert gone.returncode == 1 and "no property or container 'Guest/mood'" in gone.stderr


def test_remote_action_reaches_minds_as_a_remote_action(world: World) -> None:
    start = world.fatima.mark()
    out = json.loads(world.ok("remote-action", "robot", "Greet", "Spirit", "--subject", "Visitor", "--json"))
    assert out == {"embodiment": "robot", "name": "Greet", "parameters": ["Spirit"], "subject": "Visitor", "minds": ["fatima"]}
    world.fatima.got("ACTION-FINISHED Visitor Greet Spirit", start=start)
    world.perceives({"op": "remote", "name": "Greet", "parameters": ["Spirit"], "subject": "Visitor"})
    assert "fatima perceived someone do Wave" in world.ok("remote-action", "robot", "Wave")
    world.fatima.got("ACTION-FINISHED World Wave", start=start)
    bad = world.cli("remote-action", "robot", "Two words")
    assert bad.returncode == 1 and "one word" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
