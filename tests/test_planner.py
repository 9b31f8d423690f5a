"""The reference planner mind: pure planning, then the mind driving a body over the in-memory mesh."""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from cmion_mesh import keys
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import AddContainer, Event, MindMessage, MindState, SetProperty, Wake
from cmion_mesh.minds.planner.mind import PlannerMind
from cmion_mesh.minds.planner.search import find_plan
from cmion_mesh.minds.planner.spec import Goal, Limits, goals_from_data, load_operators, load_spec, operators_from_data, spec_from_data
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

pytestmark = pytest.mark.timeout(60)

WALK = {"name": "walk", "action": "GoTo", "parameters": ["?place"],
        "preconditions": [["Robot", "at", "?from"], ["?place", "room", True]],
        "effects": [["Robot", "at", "?place"]]}
GREET = {"name": "greet", "action": "Greet", "parameters": ["?who"],
         "preconditions": [["Robot", "at", "?p"], ["?who", "at", "?p"]],
         "effects": [["?who", "greeted", True]]}
PICK = {"name": "pick", "action": "Pick", "parameters": ["?item"],
        "preconditions": [["Robot", "at", "?p"], ["?item", "at", "?p"], ["?item", "portable", True], ["Robot", "holding", None]],
        "effects": [["Robot", "holding", "?item"], ["?item", "at", None]]}
GIVE = {"name": "give", "action": "Give", "parameters": ["?item", "?who"],
        "preconditions": [["Robot", "holding", "?item"], ["Robot", "at", "?p"], ["?who", "at", "?p"]],
        "effects": [["?who", "has", "?item"], ["Robot", "holding", None]]}
GREETED = [("Guest", "greeted", True)]


def world() -> dict[str, dict[str, Any]]:
    return {"Robot": {"at": "hall"}, "Guest": {"at": "kitchen"}, "Cake": {"at": "pantry", "portable": True},
            "hall": {"room": True}, "kitchen": {"room": True}, "pantry": {"room": True}}


# --- pure planning -------------------------------------------------------------------------------


def test_plan_binds_variables_over_several_steps() -> None:
    ops = operators_from_data([WALK, GREET, PICK, GIVE])
    result = find_plan(world(), GREETED, ops)
    assert result.found
    assert [(s.action, s.parameters) for s in result.steps] == [("GoTo", ["kitchen"]), ("Greet", ["Guest"])]
    assert result.steps[1].bindings == {"?p": "kitchen", "?who": "Guest"}

    beliefs = world()
    beliefs["Robot"]["at"] = "pantry"
    cake = find_plan(beliefs, [("Guest", "has", "Cake")], ops)
    assert [s.describe() for s in cake.steps] == ["Pick Cake", "GoTo kitchen", "Give Cake Guest"]
    assert cake.cost == 3.0


def test_plan_respects_preconditions() -> None:
    ops = operators_from_data([WALK, GREET])
    beliefs = world()
    del beliefs["kitchen"]["room"]  # no longer a place the robot can walk to
    result = find_plan(beliefs, GREETED, ops)
    assert not result.found and result.reason == "no sequence of operators achieves it"
    # Already holding something: Pick is out until the hands are free.
    beliefs = world()
    beliefs["Robot"].update(at="pantry", holding="Vase")
    assert not find_plan(beliefs, [("Robot", "holding", "Cake")], operators_from_data([PICK])).found


def test_unreachable_goal_is_reported_within_bounds() -> None:
    # 14 independent switches: 16384 states, none of which makes the goal true.
    flip = operators_from_data([{"name": "on", "action": "On", "parameters": ["?s"], "preconditions": [["?s", "on", False]],
                                 "effects": [["?s", "on", True]]}])
    beliefs: dict[str, dict[str, Any]] = {f"s{i}": {"on": False} for i in range(14)}
    result = find_plan(beliefs, [("s0", "broken", True)], flip, max_expanded=300)
    assert not result.found and result.expanded == 300 and "gave up after expanding 300" in result.reason
    shallow = find_plan(beliefs, [("s0", "broken", True)], flip, max_depth=1)
    assert not shallow.found and shallow.reason == "no plan of at most 1 steps"


def test_cost_picks_the_cheaper_plan() -> None:
    teleport = {"name": "teleport", "action": "Teleport", "parameters": ["?who"], "preconditions": [],
                "effects": [["?who", "greeted", True]], "cost": 5}
    ops = operators_from_data([teleport, WALK, GREET])
    assert [s.action for s in find_plan(world(), GREETED, ops).steps] == ["GoTo", "Greet"]
    ops = operators_from_data([{**teleport, "cost": 1.5}, WALK, GREET])
    assert [s.describe() for s in find_plan(world(), GREETED, ops).steps] == ["Teleport Guest"]


def test_banned_steps_are_avoided() -> None:
    ops = operators_from_data([WALK, GREET])
    first = find_plan(world(), GREETED, ops).steps[0]
    detour = find_plan(world(), GREETED, ops, banned=[first.key])
    assert [s.describe() for s in detour.steps] == ["GoTo pantry", "GoTo kitchen", "Greet Guest"] and detour.cost == 3.0
    second = detour.steps[1]
    assert not find_plan(world(), GREETED, ops, banned=[first.key, second.key]).found


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ([{"name": "x"}], "Object missing required field `action`"),
        ([{**WALK, "effects": [["Robot", "at"]]}], r"array` of length 3"),
        ([{**WALK, "cost": -1}], "cost -1.0 is negative"),
        ([WALK, WALK], "two operators are named 'walk'"),
        ([{**WALK, "colour": "red"}], "unknown field `colour`"),
    ],
)
def test_bad_operators_are_refused(data: list[dict[str, Any]], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        operators_from_data(data)


def test_spec_file_loads(tmp_path: Path) -> None:
    path = tmp_path / "spec.json"
    path.write_text(json.dumps({"operators": [WALK, GREET], "goals": [{"name": "g", "facts": [["Guest", "greeted", True]]}],
                                "limits": {"max_depth": 4}}))
    spec = load_spec(path)
    assert [o.name for o in spec.operators] == ["walk", "greet"] == [o.name for o in load_operators(path)]
    assert spec.goals[0].facts == (("Guest", "greeted", True),) and spec.limits == Limits(max_depth=4)
    mind = PlannerMind("mind", str(path))
    assert [g.name for g in mind.pending_goals] == ["g"] and mind.limits.max_depth == 4
    path.write_text('{"operators": [{"name": "x", "action": "X", "cost": "high"}]}')
    with pytest.raises(ConfigError, match=f"^{path}: .*Expected `float`"):
        load_spec(path)


def test_the_documented_spec_example_loads() -> None:
    import cmion_mesh.minds.planner.spec

    doc = cmion_mesh.minds.planner.spec.__doc__ or ""
    start = doc.index("    {\n")
    spec = spec_from_data(msgspec.json.decode(doc[start:doc.index("\n    }\n", start) + 6]))
    assert [o.name for o in spec.operators] == ["walk", "greet"] and spec.limits == Limits()
    assert spec.triggers[0].when == ("Command", "greet", "?who") and spec.emotion is not None


# --- the mind on a body --------------------------------------------------------------------------


RULES = "\n".join(
    f'<Rule><MindAction Name="*">{"".join(f"<Parameter No={chr(34)}{i}{chr(34)} Value={chr(34)}*{chr(34)}/>" for i in range(1, n + 1))}'
    f'</MindAction><CompetencyExecutionPlan><Competency ID="1" Type="Script">'
    f'<CompetencyParameter Name="action" Value="$action"/>'
    f'{"".join(f"<CompetencyParameter Name={chr(34)}p{i}{chr(34)} Value={chr(34)}$parameter{i}{chr(34)}/>" for i in range(1, n + 1))}'
    f"</Competency></CompetencyExecutionPlan></Rule>"
    for n in range(3)
)

WORLD = """<WorldModel>
  <Agent Name="Robot"><Property Name="at" Value="hall"/></Agent>
  <Agent Name="Guest"><Property Name="at" Value="kitchen"/><Property Name="likes" Value="tea" Persistent="true"/></Agent>
  <Object Name="hall"><Property Name="room" Value="true" Type="bool"/></Object>
  <Object Name="kitchen"><Property Name="room" Value="true" Type="bool"/></Object>
</WorldModel>
"""


class Script(Competency):
    """Performs any action: records it, fails when told to, writes world-model facts, can be held."""

    type = "Script"

    def __init__(self) -> None:
        super().__init__(name="script")
        self.calls: list[str] = []
        self.failing: dict[str, int] = {}  # call (or action name) -> failures left; -1: always
        self.writes: dict[str, list[tuple[str, str, Any]]] = {}
        self.held: set[str] = set()
        self.release = threading.Event()
        self.running = ""

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        call = " ".join(str(parameters[k]) for k in ("action", "p1", "p2") if k in parameters)
        self.calls.append(call)
        self.running = call
        try:
            if parameters["action"] in self.held:
                while not self.release.is_set():
                    if not ctx.wait(0.01):
                        return False
            for key in (call, parameters["action"]):
                left = self.failing.get(key, 0)
                if left:
                    self.failing[key] = left - 1 if left > 0 else left
                    return ctx.fail(f"{call} is scripted to fail")
            for entity, prop, value in self.writes.get(call, []):
                ctx.write(keys.WORLD_MODEL, SetProperty(entity, prop, value))
            return True
        finally:
            self.running = ""


@pytest.fixture
def client(network: MemoryNetwork, mesh: str) -> Iterator[MeshClient]:
    with MemoryTransport(network, "tester") as t:
        yield MeshClient(t, mesh)


@contextlib.contextmanager
def body(tmp_path: Path, transport: MemoryTransport, mesh: str, mind: PlannerMind, script: Script) -> Iterator[Embodiment]:
    rules = tmp_path / "rules.xml"
    rules.write_text(f"<CompetencyManagerRules>\n{RULES}\n</CompetencyManagerRules>\n")
    wm = tmp_path / "wm.xml"
    wm.write_text(WORLD)
    with Embodiment("robot", mesh=mesh, transport=transport, rules=rules, world_model_init=wm, competencies=[script]) as robot:
        robot.add(mind)
        yield robot


def mind_state(client: MeshClient) -> dict[str, Any]:
    outcome = client.request("robot", "mind", "state", MindState())
    assert outcome.status == "accepted", outcome
    value: dict[str, Any] = outcome.value
    return value


def kinds(state: dict[str, Any]) -> list[str]:
    return [e["kind"] for e in state["memory"] if e["kind"] != "perceived"]


def wait_state(client: MeshClient, condition: Callable[[dict[str, Any]], Any], what: str) -> dict[str, Any]:
    """The mind's state (read on its loop) once ``condition`` holds for it."""
    seen: list[dict[str, Any]] = []

    def check() -> bool:
        seen.append(mind_state(client))
        return bool(condition(seen[-1]))

    wait_for(check, 10, what)
    return seen[-1]


def achieved(goal: str) -> Callable[[dict[str, Any]], bool]:
    return lambda state: any(g["name"] == goal for g in state["goals"]["achieved"])


def test_goal_achieved_through_two_actions_in_order(tmp_path: Path, transport: MemoryTransport, client: MeshClient,
                                                    mesh: str) -> None:
    script = Script()
    script.writes["GoTo kitchen"] = [("Robot", "at", "kitchen")]
    mind = PlannerMind(operators=[WALK, GREET], goals=[{"name": "greet guest", "facts": [["Guest", "greeted", True]],
                                                        "priority": 2}])
    decisions: list[Event] = []
    client.events(decisions.append, embodiment="robot", component="mind", event="MindDecision")
    with body(tmp_path, transport, mesh, mind, script) as robot:
        state = wait_state(client, achieved("greet guest"), "goal achieved")
        assert script.calls == ["GoTo kitchen", "Greet Guest"]
        assert kinds(state) == ["action_succeeded", "action_succeeded", "goal_achieved"]
        assert state["beliefs"]["Robot"]["at"] == "kitchen" == robot.world_model.get("Robot", "at")
        assert state["beliefs"]["Guest"]["greeted"] is True, "an operator's effect is believed on success"
        assert state["goals"]["pending"] == [] and state["in_flight"] is None and state["plan"]["steps"] == []
        assert state["emotion"]["valence"] > 0
        wait_for(lambda: any(e.data["decision"] == "goal_achieved" for e in decisions), 5, "decision published")
    assert [e.data["decision"] for e in decisions] == ["plan", "act", "act", "goal_achieved"]
    assert [s["action"] for s in decisions[0].data["steps"]] == ["GoTo", "Greet"]


def test_failed_step_makes_the_mind_replan_onto_another_operator(tmp_path: Path, transport: MemoryTransport,
                                                                  client: MeshClient, mesh: str) -> None:
    route_a = {**WALK, "name": "route_a", "parameters": ["?place", "A"]}
    route_b = {**WALK, "name": "route_b", "parameters": ["?place", "B"], "cost": 2}
    script = Script()
    script.failing["GoTo kitchen A"] = -1
    mind = PlannerMind(operators=[route_a, route_b, GREET], goals=[{"name": "greet guest", "facts": [["Guest", "greeted", True]]}])
    with body(tmp_path, transport, mesh, mind, script):
        state = wait_state(client, achieved("greet guest"), "goal achieved")
    assert script.calls == ["GoTo kitchen A", "GoTo kitchen B", "Greet Guest"]
    assert kinds(state) == ["action_failed", "action_succeeded", "action_succeeded", "goal_achieved"]
    failed = state["memory"][[e["kind"] for e in state["memory"]].index("action_failed")]
    assert failed["details"]["operator"] == "route_a" and "scripted to fail" in failed["details"]["reason"]


def test_goal_abandoned_after_k_failures(tmp_path: Path, transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    script = Script()
    script.failing["GoTo"] = -1
    route_b = {**WALK, "name": "route_b", "cost": 2}
    mind = PlannerMind(operators=[WALK, route_b, GREET], goals=[{"name": "greet guest", "facts": [["Guest", "greeted", True]]}],
                       limits=Limits(max_failures=3))
    with body(tmp_path, transport, mesh, mind, script):
        state = wait_state(client, lambda s: s["goals"]["abandoned"], "goal abandoned")
    # walk, then route_b (walk is banned), then walk again once every way has failed recently.
    assert script.calls == ["GoTo kitchen"] * 3
    assert kinds(state) == ["action_failed"] * 3 + ["goal_abandoned"]
    assert [e["details"]["operator"] for e in state["memory"] if e["kind"] == "action_failed"] == ["walk", "route_b", "walk"]
    assert state["goals"]["abandoned"][0]["name"] == "greet guest" and "3 failures" in state["goals"]["abandoned"][0]["reason"]
    assert state["goals"]["pending"] == [] and state["failures"] == {} and state["emotion"]["valence"] < 0


def test_world_model_trigger_adds_a_goal_that_gets_achieved(tmp_path: Path, transport: MemoryTransport, client: MeshClient,
                                                            mesh: str) -> None:
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({
        "operators": [WALK, GREET],
        "triggers": [{"when": ["Command", "greet", "?who"],
                      "goal": {"name": "greet ?who", "facts": [["?who", "greeted", True]], "priority": 5}}],
    }))
    script = Script()
    mind = PlannerMind("mind", str(spec))  # as the daemon builds it from the architecture config
    with body(tmp_path, transport, mesh, mind, script):
        assert client.write("robot", keys.WORLD_MODEL, AddContainer("", "Command", "object")).status == "accepted"
        client.set_property("robot", keys.WORLD_MODEL, "Command", "greet", "Guest")
        state = wait_state(client, achieved("greet Guest"), "triggered goal achieved")
    assert script.calls == ["GoTo kitchen", "Greet Guest"]
    added = next(e for e in state["memory"] if e["kind"] == "goal_added")
    assert added["details"] == {"goal": "greet Guest", "source": 'trigger ["Command","greet","Guest"]'}


def test_message_adds_a_goal(tmp_path: Path, transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    mind = PlannerMind(operators=[WALK, GREET])
    with body(tmp_path, transport, mesh, mind, Script()):
        goal = {"name": "visit", "facts": [["Robot", "at", "kitchen"]]}
        assert client.request("robot", "mind", "message", MindMessage({"goal": goal})).status == "accepted"
        state = wait_state(client, achieved("visit"), "goal from a message achieved")
    assert kinds(state) == ["message", "goal_added", "action_succeeded", "goal_achieved"]


def test_sleep_stops_acting_and_wake_resumes(tmp_path: Path, transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    script = Script()
    script.held.add("GoTo")
    mind = PlannerMind(operators=[WALK, GREET], goals=[{"name": "greet guest", "facts": [["Guest", "greeted", True]]}])
    with body(tmp_path, transport, mesh, mind, script) as robot:
        wait_for(lambda: script.running == "GoTo kitchen", 10, "first step running")
        robot.sim.call(mind.sleep)
        wait_for(lambda: not mind.awake, 5, "mind asleep")
        script.release.set()
        # The step in flight still ends, and its effect is believed, but nothing new is sent.
        state = wait_state(client, lambda s: "action_succeeded" in kinds(s), "first step done")
        assert state["in_flight"] is None and [s["action"] for s in state["plan"]["steps"]] == ["Greet"]
        assert script.calls == ["GoTo kitchen"]
        assert client.request("robot", "mind", "wake", Wake()).value == {"awake": True}
        state = wait_state(client, achieved("greet guest"), "goal achieved after waking")
    assert script.calls == ["GoTo kitchen", "Greet Guest"]


def test_persistent_goal_is_pursued_again_when_undone(tmp_path: Path, transport: MemoryTransport, client: MeshClient,
                                                       mesh: str) -> None:
    script = Script()
    script.writes["GoTo kitchen"] = [("Robot", "at", "kitchen")]
    mind = PlannerMind(operators=[WALK], goals=[{"name": "stay", "facts": [["Robot", "at", "kitchen"]], "persistent": True}])
    with body(tmp_path, transport, mesh, mind, script):
        wait_state(client, lambda s: kinds(s).count("goal_achieved") == 1, "achieved once")
        client.set_property("robot", keys.WORLD_MODEL, "Robot", "at", "hall")
        state = wait_state(client, lambda s: kinds(s).count("goal_achieved") == 2, "achieved again")
    assert script.calls == ["GoTo kitchen", "GoTo kitchen"]
    assert state["goals"]["pending"] == [{"name": "stay", "facts": [["Robot", "at", "kitchen"]], "priority": 0.0,
                                          "persistent": True, "satisfied": True}]
    assert state["goals"]["achieved"] == []


def test_unreachable_goal_is_retried_when_the_world_changes(tmp_path: Path, transport: MemoryTransport, client: MeshClient,
                                                             mesh: str) -> None:
    mind = PlannerMind(operators=[WALK], goals=[{"name": "cellar", "facts": [["Robot", "at", "cellar"]]}],
                       limits=Limits(retry_delay=0.05))
    script = Script()
    with body(tmp_path, transport, mesh, mind, script):
        wait_state(client, lambda s: "goal_unreachable" in kinds(s), "reported unreachable")
        assert client.write("robot", keys.WORLD_MODEL, AddContainer("", "cellar", "object")).status == "accepted"
        client.set_property("robot", keys.WORLD_MODEL, "cellar", "room", True)
        state = wait_state(client, achieved("cellar"), "reached once the cellar is a room")
    assert script.calls == ["GoTo cellar"]
    assert kinds(state) == ["goal_unreachable", "action_succeeded", "goal_achieved"], "reported once, not per perception"


# --- state -------------------------------------------------------------------------------------------


def test_state_round_trips_through_json(tmp_path: Path, transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    script = Script()
    script.failing["GoTo kitchen"] = 1
    mind = PlannerMind(operators=[WALK, GREET], goals=[
        {"name": "greet guest", "facts": [["Guest", "greeted", True]]},
        {"name": "fly", "facts": [["Robot", "flying", True]], "priority": -1},
    ])
    with body(tmp_path, transport, mesh, mind, script):
        wait_state(client, achieved("greet guest"), "goal achieved")
        state = mind_state(client)
    assert [g["name"] for g in state["goals"]["pending"]] == ["fly"], "the unreachable goal stays pending"
    assert {"action_failed", "goal_unreachable", "goal_achieved"} <= set(kinds(state))
    assert state["persistent"] == [["Guest", "likes"]]
    assert state["emotion"] != {"valence": 0.0, "arousal": 0.0}

    wire = msgspec.json.decode(msgspec.json.encode(state))
    fresh = PlannerMind()
    fresh.restore(wire)
    assert fresh.state() == state
    assert list(fresh.memory) == state["memory"] and fresh.emotion == state["emotion"]
    assert fresh.operators == mind.operators


def test_restored_mind_resumes_on_its_new_body(tmp_path: Path, transport: MemoryTransport, client: MeshClient,
                                               mesh: str) -> None:
    elsewhere = PlannerMind(operators=[WALK, GREET], goals=[{"name": "greet guest", "facts": [["Guest", "greeted", True]]}])
    elsewhere.on_property_changed("Guest", "likes", "coffee", True)  # its own knowledge, which travels
    for entity, prop, value in [("Robot", "at", "kitchen"), ("Guest", "at", "kitchen"), ("kitchen", "room", True)]:
        elsewhere.on_property_changed(entity, prop, value, False)  # about the old body: replaced on arrival
    state = elsewhere.state()
    state["in_flight"] = "mind-old-3"  # migrating mid-action: that action stays behind
    script = Script()
    mind = PlannerMind()
    with body(tmp_path, transport, mesh, mind, script) as robot:
        def migrate() -> None:  # what migration does on the target, in one update
            mind.sleep()
            mind.restore(state)
            mind.wake()
            mind.on_arrived(robot.world_model.tree())

        robot.sim.call(migrate)
        after = wait_state(client, achieved("greet guest"), "goal achieved on the new body")
    assert script.calls == ["GoTo kitchen", "Greet Guest"], "planned from the new body's world model (robot in the hall)"
    assert after["beliefs"]["Guest"]["likes"] == "coffee", "persistent beliefs win over the new world model"


def test_restore_drops_an_action_in_flight() -> None:
    mind = PlannerMind(operators=[WALK, GREET], goals=[Goal("greet guest", tuple(GREETED))])
    state = mind.state()
    state["beliefs"] = world()
    state["in_flight"] = "mind-abc-7"
    state["plan"] = {"goal": "greet guest", "steps": [{"operator": "greet", "bindings": {"?p": "kitchen", "?who": "Guest"}}]}
    mind.restore(state)
    again = mind.state()
    assert again["in_flight"] is None and again["plan"] == {"goal": None, "steps": []}
    assert again["beliefs"] == world()
    with pytest.raises(ConfigError, match="unusable state"):
        mind.restore({"version": 99})


def test_replace_beliefs_keeps_persistent_knowledge() -> None:
    mind = PlannerMind()
    mind.on_property_changed("Guest", "likes", "tea", True)
    mind.on_property_changed("Guest", "at", "kitchen", False)
    mind.on_property_changed("Robot", "at", "hall", False)
    tree = {"kind": "world_model", "properties": {}, "children": {
        "Robot": {"kind": "agent", "properties": {"at": {"value": "lobby", "persistent": False}}, "children": {}},
        "Guest": {"kind": "agent", "properties": {"likes": {"value": "coffee", "persistent": True}}, "children": {}},
        "Screen": {"kind": "object", "properties": {"size": {"value": 42, "persistent": True}}, "children": {}},
    }}
    mind.replace_beliefs(tree)
    assert mind.beliefs == {"Robot": {"at": "lobby"}, "Guest": {"likes": "tea"}, "Screen": {"size": 42}}
    assert mind.persistent == {("Guest", "likes"), ("Screen", "size")}


def test_goals_from_data_and_priorities() -> None:
    goals = goals_from_data([{"name": "low", "facts": [["A", "b", 1]]}, {"name": "high", "facts": [["A", "c", 1]], "priority": 3}])
    mind = PlannerMind(goals=goals)
    top = mind.top_goal()
    assert top is not None and top.name == "high"
    with pytest.raises(ConfigError, match="has no facts"):
        goals_from_data([{"name": "empty", "facts": []}])
