"""The competency manager (``manager``): how mind actions become plans, tried in order until one works.

A stepped simulation on the in-memory transport holds the execution system and the manager; the
rules are a real CompetencyManagerRules file, one rule a line (rule N is on line N + 1), and the
competencies end each run as the test says (``Scripted``)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.body import manager
from cmion_mesh.body.execution import ExecutionSystem
from cmion_mesh.body.manager import CompetencyManager
from cmion_mesh.body.rules import load_rules
from cmion_mesh.competency import Competency
from cmion_mesh.ion import Simulation
from cmion_mesh.messages import Act, ActionStatus, CancelAction, Code, Message, Outcome
from cmion_mesh.transport.memory import MemoryTransport

from .helpers.competency_helpers import Scripted, pump

pytestmark = pytest.mark.timeout(60)


def competency(id: str, type: str, after: str = "", **parameters: str) -> str:
    dependency = f' Dependency="{after}"' if after else ""
    inner = "".join(f'<CompetencyParameter Name="{k}" Value="{v}"/>' for k, v in parameters.items())
    return f'<Competency ID="{id}" Type="{type}"{dependency}>{inner}</Competency>'


def plan(*competencies: str) -> str:
    return f"<CompetencyExecutionPlan>{''.join(competencies)}</CompetencyExecutionPlan>"


def rule(name: str, *plans: str, parameters: tuple[str, ...] = (), subject: str | None = None) -> str:
    listed = "".join(f'<Parameter No="{i}" Value="{v}"/>' for i, v in enumerate(parameters, 1))
    who = f' Subject="{subject}"' if subject is not None else ""
    return f'<Rule><MindAction Name="{name}"{who}>{listed}</MindAction>{"".join(plans)}</Rule>'


class Body:
    """One embodiment's execution system and manager, stepped by the test."""

    def __init__(self, sim: Simulation, rules: Path) -> None:
        self.sim, self.rules = sim, rules
        self.events: list[tuple[str, dict[str, Any]]] = []
        sim.on_event(lambda e: self.events.append((e.name, e.data)), component="manager")

    @property
    def manager(self) -> CompetencyManager:
        component = self.sim.component("manager")
        assert isinstance(component, CompetencyManager)
        return component

    def ask(self, name: str, payload: Message) -> Outcome:
        future: Future[Outcome] = self.sim.request("manager", name, payload)
        pump(self.sim, future.done, f"the answer to {name}")
        return future.result()

    def act(self, name: str, *parameters: str, **fields: Any) -> Outcome:
        return self.ask("act", Act(name, list(parameters), **fields))

    def ended(self, action_id: str) -> dict[str, Any]:
        """The action's end event, once it came."""
        def end() -> dict[str, Any] | None:
            return next((d for n, d in self.events if n in ("ActionSucceeded", "ActionFailed", "ActionCancelled")
                         and d["action_id"] == action_id), None)
        pump(self.sim, end, f"the end of {action_id}")
        found = end()
        assert found is not None
        return found

    def attempts(self, action_id: str) -> list[tuple[str, int]]:
        """(rule line, attempt) of each plan tried for the action."""
        return [(d["rule"].rsplit(":", 1)[1], d["attempt"]) for n, d in self.events
                if n == "ActionAttempt" and d["action_id"] == action_id]

    def line(self, rule_line: int) -> str:
        return f"{self.rules}:{rule_line}"


@pytest.fixture
def body(transport: MemoryTransport, mesh: str, tmp_path: Path) -> Iterator[Callable[..., Body]]:
    sims: list[Simulation] = []

    def build(rules: list[str], *competencies: Competency, default_deadline: float = 60.0) -> Body:
        path = tmp_path / "rules.xml"
        path.write_text("<CompetencyManagerRules>\n" + "\n".join(rules) + "\n</CompetencyManagerRules>\n")
        sim = Simulation(transport, mesh=mesh, embodiment="robot")
        sims.append(sim)
        execution = ExecutionSystem(competencies)
        sim.add(execution)
        sim.add(CompetencyManager(load_rules(path), execution, default_deadline=default_deadline))
        b = Body(sim, path)
        sim.run_once()  # attaches; this thread is the loop from now on
        return b

    yield build
    for sim in sims:
        sim.close()


def test_an_action_runs_the_plan_of_its_most_specific_rule_with_its_parameters_and_subject(body: Callable[..., Body]) -> None:
    legs = Scripted("legs")
    b = body([
        rule("Go", plan(competency("1", "Walk", to="$parameter1", speed="$parameter2", who="$subject")), parameters=("*", "*")),
        rule("Go", plan(competency("1", "Walk", to="the $parameter1", speed="slowly", act="$action")), parameters=("*", "slow")),
    ], legs)
    legs.finish()
    legs.finish()
    slow = b.act("Go", "kitchen", "slow", subject="spirit")
    assert slow.status == "accepted"
    assert b.ended(slow.value["action_id"])["rule"] == b.line(3)
    fast = b.act("Go", "hall", "fast", subject="spirit")
    assert b.ended(fast.value["action_id"])["rule"] == b.line(2)
    assert legs.parameters == [{"to": "the kitchen", "speed": "slowly", "act": "Go"},
                               {"to": "hall", "speed": "fast", "who": "spirit"}]


def test_a_rule_for_one_subject_is_only_for_that_subject(body: Callable[..., Body]) -> None:
    voice = Scripted("voice", "Say")
    b = body([rule("Greet", plan(competency("1", "Say", text="hello")), subject="spirit")], voice)
    other = b.act("Greet", subject="ghost")
    assert other.status == "rejected" and other.code == Code.NOT_FOUND
    assert "no rule matches action 'Greet'" in other.reason
    voice.finish()
    mine = b.act("Greet", subject="spirit")
    assert b.ended(mine.value["action_id"])["status"] == "succeeded"


def test_a_failed_plan_falls_back_to_the_rules_next_plan_then_to_the_next_rule(body: Callable[..., Body]) -> None:
    legs, wheels = Scripted("legs"), Scripted("wheels", "Roll")
    b = body([
        rule("Go", plan(competency("1", "Walk", how="last resort")), parameters=("*",)),
        rule("Go", plan(competency("1", "Walk", how="first")), plan(competency("1", "Roll", how="second")), parameters=("home",)),
    ], legs, wheels)
    legs.finish(False, "stairs")
    wheels.finish(False, "flat tyre")
    legs.finish()
    outcome = b.act("Go", "home", action_id="go-home")
    assert outcome.status == "accepted" and outcome.value == {"action_id": "go-home"}
    end = b.ended("go-home")
    assert (end["status"], end["rule"], end["attempt"]) == ("succeeded", b.line(2), 3)
    assert b.attempts("go-home") == [("3", 1), ("3", 2), ("2", 3)]
    assert [p["how"] for p in legs.parameters + wheels.parameters] == ["first", "last resort", "second"]


def test_when_every_plan_failed_the_action_fails_with_every_reason_including_plans_skipped(body: Callable[..., Body]) -> None:
    legs = Scripted("legs")
    b = body([
        rule("Go", plan(competency("1", "Walk"))),
        rule("Go", plan(competency("1", "Fly"), competency("2", "Walk", after="1"))),
    ], legs)
    legs.finish(False, "stairs")
    action_id = b.act("Go").value["action_id"]
    end = b.ended(action_id)
    assert end["status"] == "failed"
    assert end["reason"] == ("rule at line 3, plan 1: step 1 needs competency type 'Fly', which no competency of this embodiment "
                             "provides; rule at line 2: step 1 (Walk) failed: legs: stairs")
    assert b.attempts(action_id) == [("2", 1)], "a plan needing a type this body lacks is never started"


def test_an_action_no_rule_or_no_executable_plan_can_do_is_refused_and_reported_failed(body: Callable[..., Body]) -> None:
    b = body([rule("Fly", plan(competency("1", "Wings")))], Scripted("legs"))
    unknown = b.act("Swim", action_id="s1")
    assert unknown.status == "rejected" and unknown.code == Code.NOT_FOUND
    assert unknown.reason.startswith("no rule matches action 'Swim'")
    impossible = b.act("Fly", action_id="f1")
    assert impossible.code == Code.NOT_FOUND
    assert impossible.reason == ("no executable plan for 'Fly': rule at line 2, plan 1: step 1 needs competency type 'Wings', "
                                 "which no competency of this embodiment provides")
    assert [(n, d["action_id"]) for n, d in b.events] == [("ActionFailed", "s1"), ("ActionFailed", "f1")]
    report = b.ask("status", ActionStatus("f1"))
    assert (report.value["status"], report.value["reason"]) == ("failed", impossible.reason)


def test_action_ids_are_given_when_missing_and_one_is_used_once_at_a_time(body: Callable[..., Body]) -> None:
    legs = Scripted("legs")
    b = body([rule("Go", plan(competency("1", "Walk")))], legs)
    assert b.act("Go").value == {"action_id": "robot-1"}
    duplicate = b.act("Go", action_id="robot-1")
    assert duplicate.code == Code.EXISTS and "'robot-1' is already running" in duplicate.reason
    legs.finish()
    b.ended("robot-1")
    assert b.act("Go", action_id="robot-1").status == "accepted", "an id that ended may be used again"
    assert b.act("Go").value == {"action_id": "robot-2"}


def test_more_actions_than_may_run_at_once_are_refused_busy(body: Callable[..., Body], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(manager, "MAX_RUNNING", 2)
    b = body([rule("Go", plan(competency("1", "Walk")))], Scripted("legs"))
    assert [b.act("Go").status for _ in range(2)] == ["accepted", "accepted"]
    third = b.act("Go")
    assert third.code == Code.BUSY and "2 actions are running on 'robot'" in third.reason


def test_cancel_ends_the_running_plan_and_no_other_plan_is_tried(body: Callable[..., Body]) -> None:
    legs, wheels = Scripted("legs"), Scripted("wheels", "Roll")
    b = body([rule("Go", plan(competency("1", "Walk")), plan(competency("1", "Roll")))], legs, wheels)
    b.act("Go", action_id="trip")
    pump(b.sim, lambda: legs.parameters, "the first plan running")
    assert b.manager.actions_running("Walk") == ["trip"] and b.manager.actions_running("Roll") == []
    assert b.ask("cancel", CancelAction("trip")).value == {"action_id": "trip"}
    end = b.ended("trip")
    assert (end["status"], end["attempt"]) == ("cancelled", 1)
    assert wheels.parameters == []
    again = b.ask("cancel", CancelAction("trip"))
    assert again.code == Code.NOT_FOUND and "no running action with id 'trip'" in again.reason


def test_the_plans_deadline_is_the_actions_or_else_the_embodiments(body: Callable[..., Body]) -> None:
    b = body([rule("Go", plan(competency("1", "Walk")))], Scripted("legs"), default_deadline=0.2)
    hurried = b.act("Go", deadline=0.1).value["action_id"]
    assert "plan deadline of 0.1 s passed" in b.ended(hurried)["reason"]
    default = b.act("Go").value["action_id"]
    assert "plan deadline of 0.2 s passed" in b.ended(default)["reason"]


def test_status_says_how_an_action_stands_while_it_runs_and_after(body: Callable[..., Body],
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(CompetencyManager, "HISTORY", 2)
    legs = Scripted("legs")
    b = body([rule("Go", plan(competency("1", "Walk")), parameters=("*",))], legs)
    b.act("Go", "hall", action_id="a1", subject="spirit")
    running = b.ask("status", ActionStatus("a1")).value
    assert running == {"type": "action_report", "action_id": "a1", "name": "Go", "parameters": ["hall"], "subject": "spirit",
                       "status": "running", "reason": "", "rule": b.line(2), "attempt": 1}
    assert b.ask("status", ActionStatus()).value == {"running": ["a1"]}
    for action_id in ("a1", "a2", "a3"):
        if action_id != "a1":
            b.act("Go", "hall", action_id=action_id)
        legs.finish()
        b.ended(action_id)
    assert b.ask("status", ActionStatus()).value == {"running": []}
    assert b.ask("status", ActionStatus("a3")).value["status"] == "succeeded"
    forgotten = b.ask("status", ActionStatus("a1"))
    assert forgotten.code == Code.NOT_FOUND, "only the last HISTORY finished actions are remembered"
