"""Simulating the world from code: entities added and removed, remote actions, containers a write
creates, and one grammar of world-model paths; every one perceived by minds as a sensor's
perception is (in-memory transport; the commands over real daemons are in ``test_world_cli.py``)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh import keys
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.rules import load_rules, substitute
from cmion_mesh.client import MeshClient
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import InvalidName, RequestRejected, StorageError
from cmion_mesh.messages import AddContainer, Code, Container, Event, Outcome, Property, RemoveContainer, SetProperty
from cmion_mesh.mind import Mind, MindAction
from cmion_mesh.minds.fatima.connector import FAtiMAConnector
from cmion_mesh.testing.fatima_peer import Peer
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .test_ion import held

pytestmark = pytest.mark.timeout(60)

RULES = """<CompetencyManagerRules>
  <Rule><MindAction Name="Blink"><Parameter No="1" Value="*"/></MindAction>
    <CompetencyExecutionPlan><Competency ID="1" Type="Blink">
      <CompetencyParameter Name="times" Value="$parameter1"/></Competency></CompetencyExecutionPlan></Rule>
  <Rule><MindAction Name="Sense"/>
    <CompetencyExecutionPlan><Competency ID="1" Type="Sense"/></CompetencyExecutionPlan></Rule>
</CompetencyManagerRules>
"""


class Watcher(Mind):
    """A mind that notes every perception, in order."""

    def __init__(self, name: str = "watcher") -> None:
        super().__init__(name)
        self.seen: list[tuple[Any, ...]] = []

    def on_entity_added(self, name: str, kind: str) -> None:
        self.seen.append(("added", name, kind))

    def on_entity_removed(self, name: str, kind: str) -> None:
        self.seen.append(("removed", name, kind))

    def on_property_changed(self, entity: str, name: str, value: Any, persistent: bool) -> None:
        self.seen.append(("changed", entity, name, value, persistent))

    def on_property_removed(self, entity: str, name: str, persistent: bool) -> None:
        self.seen.append(("property removed", entity, name))

    def on_remote_action(self, action: MindAction) -> None:
        self.seen.append(("remote", action))


class Blink(Competency):
    """Counts its blinks on the blackboard, in a container nobody made."""

    type = "Blink"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        for count in range(1, int(parameters["times"]) + 1):
            ctx.bb_set("blink/count", count)
        return True


class Sense(Competency):
    """A sensor: a visitor comes, greets the companion, and goes."""

    type = "Sense"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        ctx.wm_add("Visitor", {"present": True, "name": "Ada"})
        ctx.remote_action("Greet", ["Spirit"], subject="Visitor")
        ctx.wm_remove("Visitor")
        return True


#: What a mind perceives of a visitor who comes, greets the companion and goes.
VISIT = [("added", "Visitor", "agent"), ("changed", "Visitor", "present", True, False),
         ("changed", "Visitor", "name", "Ada", False), ("remote", MindAction("Greet", ("Spirit",), "Visitor")),
         ("removed", "Visitor", "agent")]


@pytest.fixture
def robot(tmp_path: Path, network: MemoryNetwork, mesh: str) -> Iterator[tuple[Embodiment, Watcher]]:
    (tmp_path / "rules.xml").write_text(RULES)
    mind = Watcher()
    with MemoryTransport(network, "robot") as transport, Embodiment(
            "robot", mesh=mesh, transport=transport, rules=load_rules(tmp_path / "rules.xml"),
            competencies=[Blink(), Sense()], components=[mind]) as embodiment:
        yield embodiment, mind


@pytest.fixture
def client(network: MemoryNetwork, mesh: str) -> Iterator[MeshClient]:
    with MemoryTransport(network, "client") as t, MeshClient(t, mesh) as c:
        yield c


def test_an_entity_added_and_removed_reaches_a_mind_as_a_sensors_does(robot: tuple[Embodiment, Watcher],
                                                                      client: MeshClient) -> None:
    embodiment, mind = robot
    assert client.act("robot", "Sense", timeout=10).status == "succeeded"
    wait_for(lambda: len(mind.seen) >= len(VISIT), 5, "the sensor's visit perceived")
    assert mind.seen == VISIT
    mind.seen.clear()
    client.add_entity("robot", "Visitor", {"present": True, "name": "Ada"})
    assert client.remote_action("robot", "Greet", ["Spirit"], "Visitor") == ["watcher"]
    client.remove_entity("robot", "Visitor")
    wait_for(lambda: len(mind.seen) >= len(VISIT), 5, "the simulated visit perceived")
    assert mind.seen == VISIT
    assert "Visitor" not in embodiment.world_model.tree()["children"]


def test_an_entity_comes_whole_or_not_at_all(robot: tuple[Embodiment, Watcher], client: MeshClient, mesh: str) -> None:
    embodiment, mind = robot
    changes: list[tuple[str, Any]] = []
    client.watch(f"cmion/{mesh}/robot/wm/**", lambda key, entry: changes.append((key.split("/wm/")[-1], entry)))
    client.add_entity("robot", "Vase", {"onTable": True}, kind="object", persistent=True)
    wait_for(lambda: len(changes) >= 2, 5, "the entity and its property published")
    assert changes == [("Vase", Container("object")), ("Vase/onTable", Property(True, True))]
    assert embodiment.world_model.persistent_items() == [{"path": ["Vase"], "kinds": ["object"], "name": "onTable",
                                                          "value": True}]
    for entity, properties, kind, code, why in (
            ("Vase", {}, "object", Code.EXISTS, "already exists"),
            ("Dog", {}, "animal", Code.INVALID, "'animal'"),
            ("Cat", {"a*b": 1}, "agent", Code.INVALID, r"'a\*b'"),
            ("Cat", {"when": {1: 2}}, "agent", Code.MALFORMED, "not a string"),
            ("Cat/x", {}, "agent", Code.INVALID, "'Cat/x'")):
        with pytest.raises(RequestRejected, match=why) as refused:
            client.add_entity("robot", entity, properties, kind=kind)
        assert refused.value.code == code
    assert sorted(embodiment.world_model.tree()["children"]) == ["Vase"]
    wait_for(lambda: len(mind.seen) >= 2, 5, "the mind heard the one entity added")
    assert mind.seen == [("added", "Vase", "object"), ("changed", "Vase", "onTable", True, True)]
    with pytest.raises(RequestRejected, match="no such container") as gone:
        client.remove_entity("robot", "Nobody")
    assert gone.value.code == Code.NOT_FOUND


def test_a_remote_action_minds_cannot_be_told_is_refused(robot: tuple[Embodiment, Watcher], client: MeshClient) -> None:
    _, mind = robot
    for name, parameters, subject in (("Two words", [], ""), ("Greet", ["a b"], ""), ("Greet", [], "the visitor"),
                                      ("", [], ""), ("Greet", ["x"] * 65, "")):
        with pytest.raises(RequestRejected, match="remote action") as refused:
            client.remote_action("robot", name, parameters, subject)
        assert refused.value.code == Code.INVALID
    assert client.remote_action("robot", "Wave") == ["watcher"]
    wait_for(lambda: mind.seen, 5, "the valid one perceived")
    assert mind.seen == [("remote", MindAction("Wave", (), ""))]
    mind.sleep()  # an asleep mind perceives nothing, and the answer says no mind was awake
    assert client.remote_action("robot", "Wave") == []


def test_bb_set_from_a_competency_creates_its_container(robot: tuple[Embodiment, Watcher], client: MeshClient) -> None:
    embodiment, _ = robot
    events: list[Event] = []
    client.events(events.append, embodiment="robot", component="bb")
    wait_for(lambda: client.read_store("robot", "bb"), 5, "the blackboard answers")
    report = client.act("robot", "Blink", ["3"], timeout=10)
    assert report.status == "succeeded", report.reason
    assert embodiment.blackboard.get("blink", "count") == 3 and embodiment.blackboard.node("blink").kind == "container"
    wait_for(lambda: len(events) >= 4, 5, "the blackboard's events")
    assert [(e.name, e.data["container"], e.data["name"]) for e in events] == [
        ("SubContainerAdded", "", "blink"), *[("PropertyChanged", "blink", "count")] * 3]


def test_a_write_creating_containers_is_mediated_and_whole(robot: tuple[Embodiment, Watcher], client: MeshClient) -> None:
    embodiment, _ = robot
    outcomes: dict[str, str] = {}

    def write(label: str, message: SetProperty | RemoveContainer) -> None:
        outcomes[label] = client.write("robot", "bb", message).status

    embodiment.blackboard.apply_now(SetProperty("", "lamp", "on"))
    embodiment.blackboard.apply_now(SetProperty("", "keep", 1, create=True))
    # In one update: two writes needing the same new containers both pass (the first makes them);
    # a write of a name removed earlier in the update loses, as any second write to a name does.
    embodiment.blackboard.apply_now(SetProperty("old", "x", 1, create=True))
    with held(embodiment.sim):
        writes = [("x", SetProperty("a/b", "x", 1, create=True)), ("y", SetProperty("a/b", "y", 2, create=True)),
                  ("remove old", RemoveContainer("", "old")), ("old again", SetProperty("old", "z", 3, create=True))]
        threads: list[threading.Thread] = []
        for label, message in writes:  # one at a time, so that they arrive in this order
            threads.append(threading.Thread(target=write, args=(label, message)))
            threads[-1].start()
            wait_for(lambda: embodiment.sim.queued() >= len(threads), 5, f"{label} queued")
    for t in threads:
        t.join(10)
    assert outcomes == {"x": "accepted", "y": "accepted", "remove old": "accepted", "old again": "conflict"}
    assert embodiment.blackboard.tree("a") == {"kind": "container", "properties": {}, "children": {
        "b": {"kind": "container", "children": {},
              "properties": {"x": {"value": 1, "persistent": False}, "y": {"value": 2, "persistent": False}}}}}
    # Through a property, or with a value that is not plain data: refused, and nothing added.
    through = client.write("robot", "bb", SetProperty("lamp/shade", "colour", "red", create=True))
    assert through.status == "rejected" and through.code == Code.INVALID and "bb/lamp is a property" in through.reason
    with pytest.raises(ValueError, match="not plain data"):
        embodiment.blackboard.apply_now(SetProperty("new/deeper", "v", object(), create=True))
    assert not embodiment.blackboard.has_container("new")
    deep = client.write("robot", "bb", SetProperty("/".join(["d"] * 33), "v", 1, create=True))
    assert deep.status == "rejected" and "nest at most 32" in deep.reason and not embodiment.blackboard.has_container("d")
    # Without ``create``, a missing container is refused, as it always was.
    plain = client.write("robot", "bb", SetProperty("nowhere", "v", 1))
    assert plain.status == "rejected" and plain.code == Code.NOT_FOUND and "no container 'nowhere'" in plain.reason


def test_world_model_paths_mean_the_same_in_every_read_and_write(robot: tuple[Embodiment, Watcher], client: MeshClient,
                                                                 mesh: str) -> None:
    embodiment, _ = robot
    assert keys.store_path("wm", "Self.pose.x") == keys.store_path("wm", "Self/pose.x") == ("Self", "pose.x")
    assert keys.store_path("wm", "my.robot/location") == ("my.robot", "location")
    assert keys.store_path("wm", "my.robot") == ("my", "robot")  # an entity with a dot: slashes only
    assert keys.store_path("bb", "a.b/c.d") == ("a.b", "c.d") and keys.store_path("bb", "a.b") == ("a.b",)
    assert keys.property_path("wm", "Visitor.mood") == ("Visitor", "mood") == keys.property_path("wm", "Visitor/mood")
    for bad in (".mood", "Visitor.", "a//b"):
        with pytest.raises(InvalidName):
            keys.store_path("wm", bad)
    # The entity must be there: a dotted set never makes a root property named "Visitor.mood".
    with pytest.raises(RequestRejected, match="no entity 'Visitor'") as missing:
        client.set_property("robot", "wm", *keys.property_path("wm", "Visitor.mood"), "happy")
    assert missing.value.code == Code.NOT_FOUND
    client.add_entity("robot", "Visitor")
    # An entity's name holds no dot: "my.robot" would be added, then read as my's property robot.
    with pytest.raises(RequestRejected, match=r"entity 'my\.robot' holds '\.'.*'my_robot'") as dotted_entity:
        client.add_entity("robot", "my.robot", kind="object")
    assert dotted_entity.value.code == Code.INVALID
    refused_container = client.write("robot", "wm", AddContainer("", "my.robot", "object"))
    assert refused_container.status == "rejected" and refused_container.code == Code.INVALID
    client.add_entity("robot", "my_robot", kind="object")
    client.set_property("robot", "wm", *keys.property_path("wm", "Visitor.mood"), "happy")
    client.set_property("robot", "wm", *keys.property_path("wm", "my_robot/pose.x"), 1.5)
    prefix = f"cmion/{mesh}/robot/wm"
    dotted, slashed = client.lookup("robot", "wm", "Visitor.mood"), client.lookup("robot", "wm", "Visitor/mood")
    assert dotted == slashed == {f"{prefix}/Visitor/mood": Property("happy")}
    assert client.lookup("robot", "wm", "my_robot/pose.x") == {f"{prefix}/my_robot/pose.x": Property(1.5)}
    assert embodiment.world_model.property("Visitor", "mood") == ("happy", False)
    # $WM(...) reads by the same grammar
    def wm(container: str, name: str) -> Any:
        return embodiment.world_model.property(container, name)[0]

    action = MindAction("Look")
    assert substitute("$WM(Visitor.mood) $WM(Visitor/mood) $WM(my_robot/pose.x)", action, bb=lambda _: None, wm=wm) == \
        "happy happy 1.5"
    # The world model's root holds entities only
    refused = client.write("robot", "wm", SetProperty("", "Visitor.mood", "sad"))
    assert refused.status == "rejected" and refused.code == Code.INVALID and "root holds entities" in refused.reason
    assert set(embodiment.world_model.tree()["properties"]) == set()
    client.remove_property("robot", "wm", "Visitor.mood")
    with pytest.raises(StorageError, match=r"no property or container 'Visitor\.mood'"):
        client.lookup("robot", "wm", "Visitor.mood", timeout=2)
    client.remove_container("robot", "wm", "Visitor")
    assert sorted(embodiment.world_model.tree()["children"]) == ["my_robot"]


def test_a_mind_adds_and_removes_entities_without_waiting(robot: tuple[Embodiment, Watcher]) -> None:
    embodiment, mind = robot
    outcomes: list[str] = []
    def note(outcome: Outcome) -> None:
        outcomes.append(outcome.status)

    def add() -> None:
        mind.wm_add("Cup", {"full": False}, kind="object", on_outcome=note)

    def fill_and_remove() -> None:
        mind.wm_set("Cup", "full", True, on_outcome=note)
        mind.wm_remove("Cup", on_outcome=note)

    # A mind runs on the update loop, where the world model answers: its writes never wait there.
    embodiment.sim.call(add)
    wait_for(lambda: outcomes, 5, "the mind's write answered")
    embodiment.sim.call(fill_and_remove)
    wait_for(lambda: len(outcomes) == 3 and len(mind.seen) >= 4, 5, "the mind's writes perceived")
    assert outcomes == ["accepted"] * 3
    assert mind.seen == [("added", "Cup", "object"), ("changed", "Cup", "full", False, False),
                         ("changed", "Cup", "full", True, False), ("removed", "Cup", "object")]


def test_fatima_hears_entities_and_remote_actions_over_its_line_protocol(network: MemoryNetwork, mesh: str,
                                                                         client: MeshClient) -> None:
    mind = FAtiMAConnector("modular", "port:0")
    with MemoryTransport(network, "robot") as transport, Embodiment("robot", mesh=mesh, transport=transport,
                                                                    components=[mind]):
        wait_for(lambda: mind.listener is not None, 5, "the connector listening")
        assert mind.listener is not None
        with Peer("127.0.0.1", mind.listener.port) as peer:
            peer.connect()
            peer.wait_for(lambda line: line == "CMD GET-PROPERTIES")
            client.add_entity("robot", "Visitor", {"present": True})
            peer.wait_for(lambda line: line == "PROPERTY-CHANGED * Visitor(present) True")
            lines = list(peer.received)
            assert lines.index("ENTITY-ADDED Visitor") < lines.index("PROPERTY-CHANGED * Visitor(present) True")
            assert client.remote_action("robot", "Greet", ["Spirit"], "Visitor") == ["fatima"]
            peer.wait_for(lambda line: line == "ACTION-FINISHED Visitor Greet Spirit")
            client.remove_entity("robot", "Visitor")
            peer.wait_for(lambda line: line == "ENTITY-REMOVED Visitor")
