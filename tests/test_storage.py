"""Blackboard and world model: mediation policy, key-space reads, change publications."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError, RequestRejected, StorageError
from cmion_mesh.messages import AddContainer, Container, Event, Property, RemoveContainer, RemoveProperty, SetProperty
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .conftest import CMION_2011
from .test_ion import held

pytestmark = pytest.mark.timeout(30)


@pytest.fixture
def robot(transport: MemoryTransport, mesh: str) -> Iterator[Embodiment]:
    with Embodiment("robot", mesh=mesh, transport=transport, world_model_init=CMION_2011 / "worldModelInit.xml") as e:
        yield e


@pytest.fixture
def client(network: MemoryNetwork, mesh: str) -> Iterator[MeshClient]:
    with MemoryTransport(network, "client") as t:
        yield MeshClient(t, mesh)


def test_cmion_world_model_init_loads_as_is(robot: Embodiment) -> None:
    wm = robot.world_model
    assert wm.node("UserA").kind == "agent" and wm.node("Vase").kind == "object"
    assert wm.property("UserA", "speaksEnglish") == ("True", True)
    assert wm.property("Vase", "broken") == ("False", False)
    assert wm.property("Cake", "chocolate") == ("True", True)
    assert sorted(wm.tree()["children"]) == ["Cake", "UserA", "UserB", "Vase"]


def test_reads_over_the_key_space(robot: Embodiment, client: MeshClient, mesh: str) -> None:
    entries = wait_for(lambda: client.read_store("robot", "wm"), 5, "world model answers")
    prefix = f"cmion/{mesh}/robot/wm"
    assert entries[f"{prefix}/UserB/speaksChinese"] == Property("True", True)
    assert entries[f"{prefix}/Cake"] == Container("object")
    assert entries[prefix] == Container("world_model")
    assert len([e for e in entries.values() if isinstance(e, Property)]) == 9
    # exact key, single-chunk wildcard, nested wildcard
    assert list(client.read(f"{prefix}/Vase/onTable")) == [f"{prefix}/Vase/onTable"]
    assert sorted(client.read(f"{prefix}/*/speaksEnglish")) == [f"{prefix}/UserA/speaksEnglish", f"{prefix}/UserB/speaksEnglish"]
    assert sorted(client.read(f"{prefix}/*")) == [f"{prefix}/{n}" for n in ("Cake", "UserA", "UserB", "Vase")]
    assert client.read(f"{prefix}/Nobody/x") == {}


def test_first_write_in_an_update_wins_and_every_writer_learns(robot: Embodiment, client: MeshClient) -> None:
    results: list[tuple[str, str]] = []

    def write(value: str) -> None:
        results.append((value, client.write("robot", "bb", SetProperty("", "mood", value)).status))

    with held(robot.sim):
        threads = [threading.Thread(target=write, args=(v,)) for v in ("happy", "sad", "calm")]
        for t in threads:
            t.start()
        wait_for(lambda: robot.sim.queued() >= 3, 5, "writes queued")
    for t in threads:
        t.join(10)
    winners = [v for v, s in results if s == "accepted"]
    assert len(winners) == 1 and sorted(s for _, s in results) == ["accepted", "conflict", "conflict"]
    assert robot.blackboard.get("", "mood") == winners[0]
    # In the next update the name is free again.
    client.set_property("robot", "bb", "", "mood", "tired")
    assert robot.blackboard.get("", "mood") == "tired"


def test_writes_to_missing_or_clashing_names_are_rejected_with_reasons(robot: Embodiment, client: MeshClient) -> None:
    with pytest.raises(RequestRejected, match="no container 'arm'"):
        client.set_property("robot", "bb", "arm", "angle", 3)
    assert client.write("robot", "bb", AddContainer("", "arm", "limb")).status == "accepted"
    client.set_property("robot", "bb", "arm", "angle", 3)
    clash = client.write("robot", "bb", SetProperty("", "arm", 1))
    assert clash.status == "rejected" and "is a container" in clash.reason
    again = client.write("robot", "bb", AddContainer("", "arm"))
    assert again.status == "rejected" and "already exists" in again.reason
    missing = client.write("robot", "bb", RemoveProperty("arm", "nothing"))
    assert missing.status == "rejected" and "arm/nothing" in missing.reason
    badkind = client.write("robot", "wm", AddContainer("", "Dog", "animal"))
    assert badkind.status == "rejected" and "'animal'" in badkind.reason
    bad_name = client.write("robot", "bb", SetProperty("", "a*b", 1))
    assert bad_name.status == "rejected" and "'a*b'" in bad_name.reason


def test_every_change_is_published_and_raised_as_an_event(robot: Embodiment, client: MeshClient, mesh: str) -> None:
    changes: list[tuple[str, object]] = []
    events: list[Event] = []
    wait_for(lambda: client.read_store("robot", "wm"), 5, "world model attached")
    client.watch(f"cmion/{mesh}/robot/wm/**", lambda k, e: changes.append((k.split("/wm/")[-1], e)))
    client.events(events.append, embodiment="robot", component="wm")
    client.write("robot", "wm", AddContainer("", "TestUser", "agent"))
    client.set_property("robot", "wm", "TestUser", "test", True, persistent=True)
    client.write("robot", "wm", RemoveProperty("TestUser", "test"))
    client.write("robot", "wm", RemoveContainer("", "TestUser"))
    wait_for(lambda: len(changes) >= 4 and len(events) >= 4, 5, "changes seen")
    assert changes == [
        ("TestUser", Container("agent")),
        ("TestUser/test", Property(True, True)),
        ("TestUser/test", None),
        ("TestUser", None),
    ]
    assert [e.name for e in events] == ["SubContainerAdded", "PropertyChanged", "PropertyRemoved", "SubContainerRemoved"]
    assert events[1].data == {"type": "storage_change", "op": "set_property", "container": "TestUser", "name": "test",
                              "value": True, "persistent": True, "kind": ""}


def test_values_keep_their_types(robot: Embodiment, client: MeshClient) -> None:
    value = {"pose": [1.5, -2, None], "ok": True, "name": "r2", "nested": {"deep": [[1], {"x": "y"}]}}
    client.set_property("robot", "bb", "", "state", value)
    assert client.get_property("robot", "bb", "", "state").value == value
    with pytest.raises(StorageError, match="no property"):
        client.get_property("robot", "bb", "", "absent")


def test_init_file_errors_name_file_and_line(tmp_path: Path) -> None:
    from cmion_mesh.storage import load_world_model_init

    bad = tmp_path / "wm.xml"
    bad.write_text('<WorldModel>\n<Agent Name="A"/>\n<Object Name="A"/>\n</WorldModel>\n')
    with pytest.raises(ConfigError, match=r"wm.xml:3: entity 'A' already defined at line 2"):
        load_world_model_init(bad)
    typed = tmp_path / "typed.xml"
    typed.write_text('<WorldModel><Agent Name="A">\n<Property Name="n" Value="x" Type="int"/></Agent></WorldModel>')
    with pytest.raises(ConfigError, match=r"typed.xml:2: property 'n'"):
        load_world_model_init(typed)
    good = tmp_path / "good.xml"
    good.write_text('<WorldModel><Agent Name="A"><Property Name="n" Value="4" Type="int"/>'
                    '<Property Name="b" Value="TRUE" Type="bool"/><Property Name="j" Value="[1,2]" Type="json"/></Agent></WorldModel>')
    (entity,) = load_world_model_init(good)
    assert [(p.name, p.value) for p in entity.properties] == [("n", 4), ("b", True), ("j", [1, 2])]
