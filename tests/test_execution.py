"""The execution system (``execution``) on its own: plans run on competencies the test drives.

A stepped simulation on the in-memory transport: the test thread is the update loop
(``run_once``), so each step of a plan is seen as it happens, and each competency run ends when
the test says how (``Scripted.finish``) or when it is cancelled."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest

from cmion_mesh import keys
from cmion_mesh.body.execution import ExecutionSystem
from cmion_mesh.body.rules import Plan, Step
from cmion_mesh.competency import Competency
from cmion_mesh.errors import MeshError
from cmion_mesh.ion import Simulation
from cmion_mesh.messages import ExecutionStatus, SetProperty
from cmion_mesh.mind import MindAction
from cmion_mesh.storage import Blackboard, WorldModel
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryTransport

from .helpers.competency_helpers import Scripted, pump

pytestmark = pytest.mark.timeout(60)

def step(id: str, type: str = "Walk", after: tuple[str, ...] = (), **parameters: str) -> Step:
    return Step(id, type, after, tuple(parameters.items()), line=0)


def plan(*steps: Step) -> Plan:
    return Plan(steps, line=1)


class Run:
    def __init__(self) -> None:
        self.ended: list[tuple[str, str]] = []

    def done(self, status: str, reason: str) -> None:
        self.ended.append((status, reason))


class Harness:
    """One embodiment's execution system, stepped by the test."""

    def __init__(self, sim: Simulation, execution: ExecutionSystem) -> None:
        self.sim, self.execution = sim, execution
        self.events: list[tuple[str, dict[str, Any]]] = []
        sim.on_event(lambda e: self.events.append((e.name, e.data)), component="execution")

    def start(self, p: Plan, action: MindAction = MindAction("Do"), **kwargs: Any) -> tuple[str, Run]:
        run = Run()
        run_id = self.execution.execute(p, action, run.done, **kwargs)
        self.sim.run_once()  # dispatches the events the start raised
        return run_id, run

    def pump(self, until: Callable[[], object], what: str) -> None:
        pump(self.sim, until, what)

    def settle(self, run: Run) -> tuple[str, str]:
        self.pump(lambda: run.ended, "the plan's end")
        assert len(run.ended) == 1, run.ended
        return run.ended[0]

    def names(self) -> list[str]:
        return [name for name, _ in self.events]

    def started(self) -> list[tuple[str, str]]:
        """(step, competency) of each step started, in order."""
        return [(d["step"], d["competency"]) for n, d in self.events if n == "StepStarted"]


@pytest.fixture
def embodiment(transport: MemoryTransport, mesh: str) -> Iterator[Callable[..., Harness]]:
    sims: list[Simulation] = []

    def build(*competencies: Competency, stores: bool = False) -> Harness:
        sim = Simulation(transport, mesh=mesh, embodiment="robot")
        sims.append(sim)
        if stores:
            sim.add(Blackboard())
            sim.add(WorldModel())
        execution = ExecutionSystem(competencies)
        sim.add(execution)
        harness = Harness(sim, execution)
        sim.run_once()  # attaches (starts the competencies); this thread is the loop from now on
        return harness

    yield build
    for sim in sims:
        sim.close()


def test_steps_without_dependencies_start_together_and_a_step_waits_for_all_it_depends_on(embodiment: Callable[..., Harness]) -> None:
    legs, arms, voice = Scripted("legs"), Scripted("arms", "Wave"), Scripted("voice", "Say")
    h = embodiment(legs, arms, voice)
    _, run = h.start(plan(step("go"), step("wave", "Wave"), step("say", "Say", after=("go", "wave"))))
    assert h.started() == [("go", "legs"), ("wave", "arms")], "both roots start in the plan's first update"
    legs.finish()
    h.pump(lambda: "StepSucceeded" in h.names(), "go succeeded")
    assert ("say", "voice") not in h.started(), "say still waits for wave"
    arms.finish()
    h.pump(lambda: ("say", "voice") in h.started(), "say started once both succeeded")
    voice.finish()
    assert h.settle(run) == ("succeeded", "")
    assert h.names()[0] == "PlanStarted" and h.names()[-1] == "PlanSucceeded"
    assert h.names().count("StepSucceeded") == 3


def test_a_chain_of_dependencies_runs_one_step_after_another_on_one_competency(embodiment: Callable[..., Harness]) -> None:
    legs = Scripted("legs")
    h = embodiment(legs)
    _, run = h.start(plan(step("c", after=("b",)), step("a"), step("b", after=("a",))))

    def ran(times: int) -> Callable[[], bool]:
        return lambda: len(legs.parameters) == times

    for times, expected in enumerate(("a", "b", "c"), 1):
        h.pump(ran(times), f"{expected} started")
        assert h.started()[-1] == (expected, "legs")
        legs.finish()
    assert h.settle(run) == ("succeeded", "")
    assert [s for s, _ in h.started()] == ["a", "b", "c"]


def test_a_failed_step_falls_back_to_another_competency_of_its_type(embodiment: Callable[..., Harness]) -> None:
    first, second = Scripted("wheels"), Scripted("legs")
    h = embodiment(first, second)
    _, run = h.start(plan(step("go")))
    first.finish(False, "a wheel is stuck")
    h.pump(lambda: ("go", "legs") in h.started(), "the other Walk competency tried")
    second.finish()
    assert h.settle(run) == ("succeeded", "")
    failed = [d for n, d in h.events if n == "StepFailed"]
    assert [(d["competency"], d["reason"]) for d in failed] == [("wheels", "a wheel is stuck")]


def test_when_every_competency_of_the_type_failed_the_plan_fails_with_each_reason(embodiment: Callable[..., Harness]) -> None:
    first, second = Scripted("wheels"), Scripted("legs")
    h = embodiment(first, second)
    _, run = h.start(plan(step("go")))
    first.finish(False, "a wheel is stuck")
    h.pump(lambda: len(h.started()) == 2, "the second tried")
    second.finish(False, "too tired")
    status, reason = h.settle(run)
    assert status == "failed"
    assert reason == "step go (Walk) failed: wheels: a wheel is stuck; legs: too tired"
    assert len(h.started()) == 2, "each competency is tried once per step"


def test_a_failing_step_cancels_the_steps_running_beside_it_and_the_plan_ends_once_they_stopped(
        embodiment: Callable[..., Harness]) -> None:
    legs, arms = Scripted("legs"), Scripted("arms", "Wave")
    h = embodiment(legs, arms)
    _, run = h.start(plan(step("go"), step("wave", "Wave"), step("after", after=("go", "wave"))))
    legs.finish(False, "blocked")
    status, reason = h.settle(run)
    assert (status, reason) == ("failed", "step go (Walk) failed: legs: blocked")
    names = h.names()
    assert names.index("StepCancelled") < names.index("PlanFailed"), "the plan ends after wave stopped"
    assert [d["step"] for n, d in h.events if n == "StepCancelled"] == ["wave"]
    assert ("after", "legs") not in h.started()


def test_of_two_steps_failing_in_one_update_the_plan_fails_once_and_the_later_counts_as_cancelled(
        embodiment: Callable[..., Harness]) -> None:
    """Once the plan is failing, a step that ends failed is counted as cancelled: its failure is not
    the plan's, and nothing more is started for a plan that is ending."""
    legs, arms = Scripted("legs"), Scripted("arms", "Wave")
    legs.finish(False, "blocked")
    arms.finish(False, "tired")
    h = embodiment(legs, arms)
    run = Run()
    h.execution.execute(plan(step("go"), step("wave", "Wave")), MindAction("Do"), run.done)
    wait_for(lambda: h.sim.queued() >= 2, 10, "both results handed to the loop")  # one update takes both
    status, reason = h.settle(run)
    failed = {d["step"] for n, d in h.events if n == "StepFailed"}
    cancelled = {d["step"] for n, d in h.events if n == "StepCancelled"}
    assert len(failed) == 1 and failed | cancelled == {"go", "wave"} and not failed & cancelled, h.events
    assert (status, reason) == ("failed", {"go": "step go (Walk) failed: legs: blocked",
                                           "wave": "step wave (Wave) failed: arms: tired"}[failed.pop()])


def test_a_step_of_a_type_nobody_provides_or_only_unavailable_ones_fails_the_plan(embodiment: Callable[..., Harness]) -> None:
    off = Scripted("off", "Fly")
    off.available = False
    h = embodiment(off)
    _, nothing = h.start(plan(step("up", "Teleport")))
    assert h.settle(nothing) == ("failed", "step up (Teleport) failed: no competency of type 'Teleport'")
    _, unavailable = h.start(plan(step("up", "Fly")))
    assert h.settle(unavailable) == ("failed", "step up (Fly) failed: no available competency of type 'Fly'")
    assert off.parameters == [], "an unavailable competency is never run"


def test_a_busy_type_makes_a_step_wait_and_the_oldest_waiting_step_goes_first(embodiment: Callable[..., Harness]) -> None:
    legs = Scripted("legs")
    h = embodiment(legs)
    first_id, first = h.start(plan(step("go", to="kitchen")))
    second_id, second = h.start(plan(step("go", to="hall")))
    third_id, third = h.start(plan(step("go", to="door")))
    waiting = [d["run_id"] for n, d in h.events if n == "StepWaiting"]
    assert waiting == [second_id, third_id]
    status = h.execution.sim.request("execution", "status", ExecutionStatus())
    h.pump(status.done, "the status answer")
    plans = status.result().value["plans"]
    assert plans == {first_id: {"go": "running"}, second_id: {"go": "waiting"}, third_id: {"go": "waiting"}}
    for run in (first, second, third):
        legs.finish()
        h.settle(run)
    assert [p["to"] for p in legs.parameters] == ["kitchen", "hall", "door"]


def test_cancel_stops_the_running_steps_and_reports_cancelled_once_they_stopped(embodiment: Callable[..., Harness]) -> None:
    legs, arms, other = Scripted("legs"), Scripted("arms", "Wave"), Scripted("other", "Wave")
    h = embodiment(legs, arms, other)
    run_id, run = h.start(plan(step("go"), step("wave", "Wave")))
    _, queued = h.start(plan(step("go")))  # waits for legs
    assert h.execution.cancel(run_id)
    assert h.settle(run) == ("cancelled", "cancelled")
    names = h.names()
    assert names.count("StepCancelled") == 2 and names.index("PlanCancelled") > max(
        i for i, n in enumerate(names) if n == "StepCancelled")
    assert not h.execution.cancel(run_id), "a plan that ended cannot be cancelled again"
    assert not h.execution.cancel("no-such-plan")
    h.pump(lambda: ("go", "legs") in h.started()[2:], "the queued plan got the legs the cancelled one freed")
    legs.finish()
    assert h.settle(queued) == ("succeeded", "")
    assert other.parameters == [], "a cancelled step does not fall back to another competency"


def test_a_late_result_of_a_cancelled_step_changes_nothing(embodiment: Callable[..., Harness]) -> None:
    legs = Scripted("legs")
    h = embodiment(legs)
    run_id, run = h.start(plan(step("go")))
    h.pump(lambda: legs.parameters, "the run began")
    h.execution.cancel(run_id)
    legs.finish()  # said after the cancel: the run is reported cancelled all the same
    assert h.settle(run) == ("cancelled", "cancelled")
    assert "StepSucceeded" not in h.names()


def test_the_plans_deadline_fails_it_and_cancels_what_runs(embodiment: Callable[..., Harness]) -> None:
    legs = Scripted("legs")
    h = embodiment(legs)
    _, run = h.start(plan(step("go")), deadline=0.2)
    assert h.settle(run) == ("failed", "plan deadline of 0.2 s passed")
    assert [d["step"] for n, d in h.events if n == "StepCancelled"] == ["go"]


def test_a_competency_that_vanishes_mid_step_fails_the_step_over_to_another(embodiment: Callable[..., Harness]) -> None:
    wheels, legs = Scripted("wheels"), Scripted("legs")
    h = embodiment(wheels, legs)
    _, run = h.start(plan(step("go")))
    h.pump(lambda: wheels.parameters, "wheels running")
    h.execution.remove_competency("wheels")
    h.pump(lambda: len(h.started()) == 2, "the step started again")
    assert h.started() == [("go", "wheels"), ("go", "legs")]
    legs.finish()
    assert h.settle(run) == ("succeeded", "")
    assert [d["reason"] for n, d in h.events if n == "StepFailed"] == ["competency 'wheels' vanished"]


def test_parameters_are_substituted_when_the_step_starts_not_when_the_plan_does(embodiment: Callable[..., Harness]) -> None:
    legs, voice = Scripted("legs"), Scripted("voice", "Say")
    h = embodiment(legs, voice, stores=True)
    blackboard = h.sim.component(keys.BLACKBOARD)
    assert isinstance(blackboard, Blackboard)
    blackboard.apply_now(SetProperty("", "room", "hall"))
    p = plan(step("go", to="$parameter1", mood="$BB(room)"), step("say", "Say", after=("go",), text="in $BB(room), $subject"))
    _, run = h.start(p, MindAction("Visit", ("kitchen",), "spirit"))
    blackboard.apply_now(SetProperty("", "room", "kitchen"))  # the robot arrived while go ran
    legs.finish()
    h.pump(lambda: voice.parameters, "say started")
    voice.finish()
    assert h.settle(run) == ("succeeded", "")
    assert legs.parameters == [{"to": "kitchen", "mood": "hall"}]
    assert voice.parameters == [{"text": "in kitchen, spirit"}]


def test_a_parameter_that_cannot_be_substituted_fails_the_step_naming_it(embodiment: Callable[..., Harness]) -> None:
    legs = Scripted("legs")
    h = embodiment(legs, stores=True)
    _, run = h.start(plan(step("go", to="$WM(Ada.location)")))
    status, reason = h.settle(run)
    assert status == "failed" and "step go (Walk), parameter 'to'" in reason and "$WM(Ada.location)" in reason
    assert legs.parameters == []


def test_an_empty_plan_succeeds_and_a_run_id_is_used_once_at_a_time(embodiment: Callable[..., Harness]) -> None:
    legs = Scripted("legs")
    h = embodiment(legs)
    _, empty = h.start(plan())
    assert h.settle(empty) == ("succeeded", "")
    h.start(plan(step("go")), run_id="mine")
    with pytest.raises(MeshError, match="'mine' is already running"):
        h.start(plan(step("go")), run_id="mine")
    assert h.execution.running_plans("Walk") == ["mine"] and h.execution.running_plans("Say") == []
