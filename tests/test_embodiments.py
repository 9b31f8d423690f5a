"""The shipped embodiments (robot, screen, phone, cmion_test) and the simulated Spirit competencies.

In one process on the in-memory transport: each embodiment is built from its architecture
configuration exactly as ``cmion-mesh up <name>`` builds it, driven with ``MeshClient.act`` and
played with the blackboard's ``sim/...`` inputs, as the demo does.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh import keys
from cmion_mesh.body.architecture import load_architecture
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.library import load_library
from cmion_mesh.body.validate import validate_file
from cmion_mesh.client import MeshClient
from cmion_mesh.competencies.spirit import SpeechSynthesis
from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import ActionReport, AddContainer, Event, RemoveProperty, SetProperty
from cmion_mesh.mind import Mind, MindAction
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

pytestmark = pytest.mark.timeout(60)
SHIPPED = ["robot", "screen", "phone", "cmion_test", "ros_robot"]
WAIT = 10.0  # upper bound for conditions that normally hold within a few tens of ms


def config(name: str) -> Path:
    return embodiment_dir(name) / "ArchitectureConfiguration.xml"


@pytest.fixture
def client(network: MemoryNetwork, mesh: str) -> Iterator[MeshClient]:
    with MemoryTransport(network, "tester") as t:
        yield MeshClient(t, mesh)


def up(name: str, transport: MemoryTransport, mesh: str) -> Embodiment:
    return Embodiment.from_architecture(config(name), mesh=mesh, transport=transport)


def collect(client: MeshClient, embodiment: str) -> list[Event]:
    seen: list[Event] = []
    client.events(seen.append, embodiment=embodiment)
    return seen


def in_background(fn: Callable[[], ActionReport]) -> tuple[threading.Thread, list[ActionReport]]:
    """Run a blocking ``act`` on a thread, so the test can play the world while it runs."""
    result: list[ActionReport] = []
    worker = threading.Thread(target=lambda: result.append(fn()), name="act")
    worker.start()
    return worker, result


def set_bb(client: MeshClient, embodiment: str, path: str, value: Any) -> None:
    container, _, name = path.rpartition("/")
    client.set_property(embodiment, keys.BLACKBOARD, container, name, value)


# --- every configuration ------------------------------------------------------------------------


@pytest.mark.parametrize("name", SHIPPED)
def test_configuration_validates_and_builds(name: str, transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    arch = load_architecture(config(name))
    assert arch.embodiment == name
    files = [arch.path, arch.rules, arch.library, arch.world_model]
    assert [validate_file(f) for f in files if f is not None] == [
        "ArchitectureConfiguration", "CompetencyManagerRules", "CompetencyLibrary", "WorldModel"]
    expected_minds = [] if name == "cmion_test" else ["cmion_mesh.minds.planner.mind:PlannerMind"]
    assert [c.class_name for c in arch.components] == expected_minds
    with up(name, transport, mesh) as body:
        description = client.describe(name)
        assert description["name"] == name
        assert set(body.rules.types()) <= set(description["competency_types"]), "every rule's types are in the library"


def test_each_embodiment_offers_its_actions(transport: MemoryTransport, mesh: str) -> None:
    expected = {
        "robot": ["Say * *", "GoTo *", "Greet *", "Express *"],
        "screen": ["Say * *", "Greet *", "AskIsGuest *", "AskIsGuest * *", "Express *"],
        "phone": ["Say * *", "Greet *", "Express *"],
        "ros_robot": ["Say * *", "GoTo *", "Greet *", "Express *", "Drive * * *"],
    }
    for name, actions in expected.items():
        body = up(name, transport, mesh)  # not started: the description needs no loop
        try:
            # Migrate <target> is built in by the migration layer when it is on, not by these files.
            assert [a for a in body.describe()["actions"] if not a.startswith("Migrate ")] == actions
        finally:
            body.close()


def test_bad_constructor_parameter_names_the_library_line(tmp_path: Path) -> None:
    library = tmp_path / "lib.xml"
    library.write_text('<CompetencyLibrary>\n<Competency ClassName="cmion_mesh.competencies.spirit:Navigation" '
                       'ConstructorParameters="fast"/>\n</CompetencyLibrary>\n')
    with pytest.raises(ConfigError, match=r"lib.xml:2: .*seconds per step: 'fast' is not a number of seconds"):
        load_library(library)


# --- robot ----------------------------------------------------------------------------------------


def test_robot_goes_to_a_known_location(transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    with up("robot", transport, mesh) as robot:
        events = collect(client, "robot")
        assert robot.world_model.get("Self", "location") == "Office"
        report = client.act("robot", "GoTo", ["Kitchen"], timeout=WAIT)
        assert report.status == "succeeded", report
        assert robot.world_model.get("Self", "location") == "Kitchen"
        assert robot.blackboard.get("navigation", "target") == "Kitchen"
        assert robot.blackboard.get("navigation", "state") == "arrived"
        progress = wait_for(lambda: [e.data["progress"] for e in events if e.name == "Progress"], WAIT, "progress events")
        assert progress[0] == {"location": "Kitchen", "step": 1, "steps": 4}
        # travelSteps in the world model sets the length of a trip
        events.clear()
        assert client.act("robot", "GoTo", ["Lab"], timeout=WAIT).status == "succeeded"
        wait_for(lambda: any(e.name == "Progress" and e.data["progress"]["step"] == 6 for e in events), WAIT, "six steps to the Lab")
        # going where the robot already is takes no step
        events.clear()
        assert client.act("robot", "GoTo", ["Lab"], timeout=WAIT).status == "succeeded"
        assert not any(e.name == "Progress" for e in events)


@pytest.mark.parametrize("place", ["Atlantis", "CoffeeMachine", "Alice"])
def test_robot_refuses_an_unknown_location_with_the_reason(place: str, transport: MemoryTransport, client: MeshClient,
                                                           mesh: str) -> None:
    with up("robot", transport, mesh) as robot:
        report = client.act("robot", "GoTo", [place], timeout=WAIT)
        assert report.status == "failed"
        assert f"unknown location {place!r}: the world model has no object {place!r} with isLocation = true" in report.reason
        assert "known locations: Entrance, Kitchen, Lab, MeetingRoom, Office" in report.reason
        assert robot.world_model.get("Self", "location") == "Office"


def test_robot_says_something(transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    with up("robot", transport, mesh) as robot:
        events = collect(client, "robot")
        report = client.act("robot", "Say", ["greeting", "Alice"], timeout=WAIT)
        assert report.status == "succeeded", report
        text = "Hello Alice, welcome to the building! I am Spirit."
        assert robot.blackboard.get("text", "greeting-Alice") == text, "LanguageGeneration wrote TextOutName"
        assert robot.blackboard.get("speech", "last") == text
        assert robot.world_model.get("Self", "lastUtterance") == text
        assert robot.blackboard.get("animation", "last") == "talk", "the talking animation played alongside"
        assert robot.blackboard.get("animation", "current") is None, "and was cleared at its end"
        assert robot.blackboard.get("speech", "current") is None
        wait_for(lambda: any(e.name == "Spoke" and e.data["text"] == text for e in events), WAIT, "Spoke event")
        # an unknown addressee is named as given; an unknown speech act fails, naming the known ones
        assert client.act("robot", "Say", ["hello", "Zed"], timeout=WAIT).status == "succeeded"
        assert robot.blackboard.get("speech", "last") == "Hello, Zed."
        failed = client.act("robot", "Say", ["sing", "Alice"], timeout=WAIT)
        assert failed.status == "failed" and "no template for speech act 'sing' (known: " in failed.reason


def test_robot_greets_and_expresses(transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    with up("robot", transport, mesh) as robot:
        assert client.act("robot", "Greet", ["Bob"], timeout=WAIT).status == "succeeded"
        assert robot.blackboard.get("speech", "last") == "Hello Bob, welcome to the building! I am Spirit."
        assert client.act("robot", "Express", ["happy"], timeout=WAIT).status == "succeeded"
        assert robot.blackboard.get("animation", "last") == "happy"
        failed = client.act("robot", "Express", ["fly"], timeout=WAIT)
        assert failed.status == "failed" and "cannot play animation 'fly' (it plays: talk, wave, nod" in failed.reason


def test_operator_command_appears_in_the_world_model(transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    with up("robot", transport, mesh) as robot:
        events = collect(client, "robot")
        wait_for(lambda: robot.blackboard.has_container("sim"), WAIT, "CommandInput created the sim container")
        set_bb(client, "robot", "sim/command", "greet  Guest")
        wait_for(lambda: robot.world_model.get("Command", "verb") == "greet", WAIT, "command perceived")
        assert robot.world_model.node("Command").kind == "object"
        assert robot.world_model.get("Command", "object") == "Guest"
        assert robot.world_model.get("Command", "text") == "greet Guest"
        assert robot.world_model.get("Command", "count") == 1
        assert robot.world_model.get("Command", "greet") == "Guest", "one fact holds verb and object, for one-fact triggers"
        wait_for(lambda: robot.blackboard.get("sim", "command") is None, WAIT, "the input consumed")
        set_bb(client, "robot", "sim/command", "greet Guest")
        wait_for(lambda: robot.world_model.get("Command", "count") == 2, WAIT, "a repeated command is a new one")
        set_bb(client, "robot", "sim/command", "count")  # a verb that is one of Command's own properties
        # verb is the command's last write: once it is there, so are the others
        wait_for(lambda: robot.world_model.get("Command", "verb") == "count", WAIT, "the third command perceived")
        assert robot.world_model.get("Command", "count") == 3, "the counter is not overwritten"
        assert robot.world_model.get("Command", "verb") == "count" and robot.world_model.get("Command", "object") == ""
    assert not [e for e in events if e.name == "CompetencyCrashed"]


def test_cancel_stops_a_long_trip(transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    with up("robot", transport, mesh) as robot:
        client.set_property("robot", keys.WORLD_MODEL, "MeetingRoom", "travelSteps", 100_000)  # ~80 minutes
        events = collect(client, "robot")
        worker, result = in_background(lambda: client.act("robot", "GoTo", ["MeetingRoom"], action_id="trip", timeout=WAIT))
        wait_for(lambda: any(e.name == "Progress" for e in events), WAIT, "the robot is moving")
        assert robot.blackboard.get("navigation", "state") == "moving"
        started = time.monotonic()
        assert client.cancel("robot", "trip").status == "accepted"
        worker.join(WAIT)
        assert result and result[0].status == "cancelled", result
        assert time.monotonic() - started < 2.0, "cancel is cooperative but prompt"
        assert robot.world_model.get("Self", "location") == "Office", "it never arrived"
        wait_for(lambda: robot.blackboard.get("navigation", "state") == "stopped", WAIT, "navigation state stopped")


# --- screen ---------------------------------------------------------------------------------------


def test_screen_detects_users_through_the_blackboard(transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    with up("screen", transport, mesh) as screen:
        events = collect(client, "screen")
        wm = screen.world_model
        wait_for(lambda: screen.blackboard.has_container("sim"), WAIT, "UserDetection created the sim container")
        assert not wm.has_container("Visitor")
        set_bb(client, "screen", "sim/userPresent", "Visitor")
        # location is written after present: once it is there, so is the rest
        wait_for(lambda: wm.get("Visitor", "location") == "Entrance", WAIT, "the visitor is seen where the screen is")
        assert wm.get("Visitor", "present") is True
        assert wm.node("Visitor").kind == "agent"
        set_bb(client, "screen", "sim/userPresent", "Visitor, Alice")
        wait_for(lambda: wm.get("Alice", "present") is True, WAIT, "a known user comes too")
        assert wm.get("Alice", "displayName") == "Alice", "a known user keeps what the companion knows of them"
        set_bb(client, "screen", "sim/userPresent", "Alice")
        wait_for(lambda: wm.get("Visitor", "present") is False, WAIT, "the visitor left")
        client.write("screen", keys.BLACKBOARD, RemoveProperty("sim", "userPresent"))
        wait_for(lambda: wm.get("Alice", "present") is False, WAIT, "nobody there")
    assert not [e for e in events if e.name == "CompetencyCrashed"]


class Perceiver(Mind):
    """Records the other agents' actions, as a mind perceives them."""

    def __init__(self) -> None:
        super().__init__("perceiver")
        self.seen: list[MindAction] = []

    def on_remote_action(self, action: MindAction) -> None:
        self.seen.append(action)


def test_ask_is_guest_answered_by_a_gesture(transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    with up("screen", transport, mesh) as screen:
        mind = Perceiver()
        screen.add(mind)
        worker, result = in_background(lambda: client.act("screen", "AskIsGuest", ["Visitor"], timeout=WAIT))
        # GestureDetect says whom it waits for once the question has been spoken
        wait_for(lambda: screen.blackboard.get("gesture", "waitingFor") == "Visitor", WAIT, "waiting for a gesture")
        assert screen.blackboard.get("speech", "last") == "Hello Visitor, are you the guest I am expecting? Please nod if you are."
        set_bb(client, "screen", "sim/gesture", "yes")
        worker.join(WAIT)
        assert result and result[0].status == "succeeded", result
        assert screen.world_model.get("Visitor", "answer") == "yes"
        assert screen.blackboard.get("sim", "gesture") is None, "the gesture was consumed"
        assert screen.blackboard.get("gesture", "waitingFor") is None
        wait_for(lambda: mind.seen, WAIT, "the mind perceived the gesture")
        assert mind.seen == [MindAction("Gesture", ("yes",), "Visitor")]


def test_ask_is_guest_times_out_when_nobody_answers(transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    with up("screen", transport, mesh) as screen:
        # an old answer, voided by the new question
        screen.world_model.apply_now(AddContainer("", "Visitor", "agent"))
        screen.world_model.apply_now(SetProperty("Visitor", "answer", "yes"))
        started = time.monotonic()
        report = client.act("screen", "AskIsGuest", ["Visitor", "0.2"], timeout=WAIT)
        assert report.status == "failed"
        assert "no gesture from Visitor within 0.2 s" in report.reason
        assert time.monotonic() - started < 5.0
        assert screen.world_model.get("Visitor", "answer") is None
        assert screen.blackboard.get("gesture", "waitingFor") is None
        bad = client.act("screen", "AskIsGuest", ["Visitor", "soon"], timeout=WAIT)
        assert bad.status == "failed" and "Timeout: 'soon' is not a number of seconds" in bad.reason


# --- phone ------------------------------------------------------------------------------------------


def test_phone_says_something(transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    with up("phone", transport, mesh) as phone:
        report = client.act("phone", "Say", ["accompany", "Bob"], timeout=WAIT)
        assert report.status == "succeeded", report
        text = "Bob, I am with you on your phone now; I will show you the way."
        assert phone.blackboard.get("speech", "last") == text
        assert phone.world_model.get("Self", "lastUtterance") == text
        assert phone.blackboard.get("animation", "last") == "talk"
        greeted = client.act("phone", "Greet", ["Bob"], timeout=WAIT)
        assert greeted.status == "succeeded" and phone.blackboard.get("animation", "last") == "smile"


# --- one competency on its own --------------------------------------------------------------------


def test_speech_synthesis_fails_without_text(tmp_path: Path, transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    rules = tmp_path / "rules.xml"
    rules.write_text('<CompetencyManagerRules><Rule><MindAction Name="Speak"/><CompetencyExecutionPlan>'
                     '<Competency ID="1" Type="SpeechSynthesis"><CompetencyParameter Name="TextInName" Value="nothing/here"/>'
                     '</Competency></CompetencyExecutionPlan></Rule></CompetencyManagerRules>')
    with Embodiment("body", mesh=mesh, transport=transport, rules=rules, competencies=[SpeechSynthesis("0.01")]):
        report = client.act("body", "Speak", timeout=WAIT)
        assert report.status == "failed" and "nothing to say: no text on the blackboard under 'nothing/here'" in report.reason
