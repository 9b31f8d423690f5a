"""What ``persistent`` means (in one process, in-memory transport): a persistent property survives
a restart of its embodiment; a persistent world-model property travels with the companion."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from cmion_mesh.body.embodiment import PERSISTENT_FILE, Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import Refused
from cmion_mesh.messages import AddContainer
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.storage import WorldModel
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .helpers.memory_bodies import close

pytestmark = pytest.mark.timeout(60)
ROBOT_WM = embodiment_dir("robot") / "WorldModel.xml"


@pytest.fixture
def client(network: MemoryNetwork, mesh: str) -> Iterator[MeshClient]:
    with MemoryTransport(network, "cli") as t, MeshClient(t, mesh) as c:
        yield c


def body(network: MemoryNetwork, mesh: str, name: str, state: Path, companion: str | None = None) -> Embodiment:
    return Embodiment(name, mesh=mesh, transport=MemoryTransport(network, name), state_dir=state / name, companion=companion,
                      world_model_init=ROBOT_WM)


def test_persistent_properties_survive_a_restart_and_the_others_do_not(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                                      client: MeshClient) -> None:
    robot = body(network, mesh, "robot", tmp_path).start()
    try:
        client.set_property("robot", "bb", "", "battery", 0.8, persistent=True)
        client.set_property("robot", "bb", "", "scratch", "gone after a restart")
        client.write("robot", "bb", AddContainer("", "plans", "notes"))
        client.set_property("robot", "bb", "plans", "next", "Kitchen", persistent=True)
        client.set_property("robot", "wm", "Self", "location", "Lab", persistent=True)  # was not persistent in the file
        client.set_property("robot", "wm", "Alice", "role", "boss", persistent=False)  # was persistent: no longer
    finally:
        close(robot)
    assert (tmp_path / "robot" / PERSISTENT_FILE.format(store="blackboard")).exists()
    again = body(network, mesh, "robot", tmp_path).start()
    try:
        assert again.blackboard.property("", "battery") == (0.8, True)
        assert again.blackboard.get("", "scratch") is None
        assert again.blackboard.node("plans").kind == "notes" and again.blackboard.property("plans", "next") == ("Kitchen", True)
        assert again.world_model.property("Self", "location") == ("Lab", True), "the saved value wins over the init file"
        assert again.world_model.property("Alice", "role") == ("staff", True), "not saved: the init file's value again"
    finally:
        close(again)


def test_persistent_world_model_properties_travel_with_the_companion(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                                     client: MeshClient) -> None:
    robot = body(network, mesh, "robot", tmp_path, companion="spirit").start()
    screen = Embodiment("screen", mesh=mesh, transport=MemoryTransport(network, "screen"), state_dir=tmp_path / "screen").start()
    try:
        wait_for(lambda: robot.inhabitant == "spirit", 5, "spirit born on the robot")
        client.write("robot", "wm", AddContainer("", "Ada", "agent"))
        client.set_property("robot", "wm", "Ada", "favourite", "tea", persistent=True)
        client.set_property("robot", "wm", "Ada", "here", True)  # the body's own knowledge: stays
        client.set_property("robot", "bb", "", "battery", 0.5, persistent=True)  # the blackboard is the body's
        client.migrate("spirit", "screen", timeout=20)
        wm: WorldModel = screen.world_model
        wait_for(lambda: wm.get("Ada", "favourite") == "tea", 5, "Ada's favourite arrived with the companion")
        assert wm.node("Ada").kind == "agent" and wm.property("Ada", "favourite") == ("tea", True)
        assert wm.property("Self", "displayName") == ("Spirit", True) and wm.get("Alice", "role") == "staff"
        assert wm.get("Ada", "here") is None and wm.get("Self", "location") is None
        assert screen.blackboard.get("", "battery") is None
        assert robot.world_model.get("Ada", "favourite") == "tea", "the source keeps its copy"
    finally:
        close(robot, screen)
    again = Embodiment("screen", mesh=mesh, transport=MemoryTransport(network, "screen"), state_dir=tmp_path / "screen").start()
    try:
        assert again.world_model.property("Ada", "favourite") == ("tea", True), "kept across the target's restart too"
    finally:
        close(again)


def test_two_embodiments_never_share_a_state_folder(network: MemoryNetwork, mesh: str, tmp_path: Path) -> None:
    first = body(network, mesh, "robot", tmp_path).start()
    try:
        with pytest.raises(Refused, match=r"state folder .*robot is in use by another daemon \(pid \d+\)"):
            Embodiment("robot2", mesh=mesh, transport=MemoryTransport(network, "robot2"), state_dir=tmp_path / "robot")
    finally:
        close(first)
    close(body(network, mesh, "robot", tmp_path).start())  # free again once the first is closed
