"""Competencies, execution system and competency manager (in one process, in-memory transport)."""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.action_runs import ACTION_END_EVENTS
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.library import load_library
from cmion_mesh.client import MeshClient
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError, RequestRejected
from cmion_mesh.messages import Event
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .conftest import CMION_2011

pytestmark = pytest.mark.timeout(60)
TEST_LIBRARY = embodiment_dir("cmion_test") / "CompetencyLibrary.xml"
TEST_RULES = CMION_2011 / "CompManagerRulesTest.xml"


@pytest.fixture
def client(network: MemoryNetwork, mesh: str) -> Iterator[MeshClient]:
    with MemoryTransport(network, "mind") as t:
        yield MeshClient(t, mesh)


def collect(client: MeshClient, embodiment: str = "robot", component: str = "*") -> list[Event]:
    seen: list[Event] = []
    client.events(seen.append, embodiment=embodiment, component=component)
    return seen


def heard_end(events: list[Event], action_id: str) -> None:
    """Wait until ``events`` (a ``collect`` of the manager's events) holds the end of ``action_id``:
    the act returns on its own subscription, which this one may trail; its events are in order."""
    wait_for(lambda: any(e.name in ACTION_END_EVENTS and e.data.get("action_id") == action_id for e in events), 10,
             f"the end of {action_id} among the collected events")


def test_cmion_test_scenario(transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    with Embodiment("robot", mesh=mesh, transport=transport, rules=TEST_RULES, library=TEST_LIBRARY,
                    world_model_init=CMION_2011 / "worldModelInit.xml") as robot:
        events = collect(client)
        report = client.act("robot", "TestAction", ["test"], timeout=20)
        assert report.status == "succeeded", report
        assert report.rule.endswith("CompManagerRulesTest.xml:47"), "rule 3 (line of its <Rule>) did it"
        def plans() -> list[str]:
            return [e.name for e in events if e.component == "execution" and e.name.startswith("Plan") and e.name != "PlanStarted"]

        # The action's end reaches the client on its own subscription: the plan events may come after it.
        wait_for(lambda: len(plans()) >= 2, 10, "both plans' end events")
        assert plans() == ["PlanFailed", "PlanSucceeded"], "rule 1 failed first, then rule 3 succeeded"
        started = [e.data["type"] for e in events if e.name == "StepStarted"]
        assert started == ["TestType1", "TestType2", "TestType3"], "rule 2 never ran"
        assert isinstance(robot.blackboard.get("", "test"), float), "type 2 wrote a random number under the given name"
        assert robot.world_model.node("TestUser").kind == "agent"
        assert robot.world_model.get("TestUser", "test") is True

        events.clear()
        report2 = client.act("robot", "TestAction2", timeout=20)
        assert report2.status == "succeeded"
        wait_for(lambda: any(e.name == "StepSucceeded" for e in events), 10, "the step's end event")
        steps = [(e.name, e.data["competency"]) for e in events if e.name in ("StepFailed", "StepSucceeded")]
        assert steps == [("StepFailed", "TestCompetency4"), ("StepSucceeded", "TestCompetency5")], "same-type fallback"

        with pytest.raises(RequestRejected, match="no rule matches action 'TestAction a b'"):
            client.act("robot", "TestAction", ["a", "b"])
        for _ in range(50):
            client.act("robot", "TestAction2", timeout=20)
        armed: queue.SimpleQueue[int] = queue.SimpleQueue()
        robot.sim.call(lambda: armed.put(robot.sim.armed_timers))
        assert armed.get(timeout=5) == 0, "a finished plan's deadline timer is dropped, not kept until it expires"
        # the background competency (type 6) is running
        wait_for(lambda: robot.blackboard.get("", "TestCompetency6Ticks"), 5, "background ticks")


def test_library_loads_constructor_parameters_and_background() -> None:
    competencies = {c.name: c for c in load_library(TEST_LIBRARY)}
    assert competencies["TestCompetency5"].constructor_parameters == ("Pizza", "Pasta")
    assert competencies["TestCompetency5"].type == competencies["TestCompetency4"].type == "TestType4"
    assert [c.name for c in competencies.values() if c.background] == ["TestCompetency6"]


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ('<Competency ClassName="no.such.module:X"/>', "cannot import module 'no.such.module'"),
        ('<Competency ClassName="cmion_mesh.competency:Nope"/>', "has no class 'Nope'"),
        ('<Competency ClassName="cmion_mesh.messages:Property"/>', "is not a cmion_mesh.competency.Competency subclass"),
        ('<Competency ClassName="cmion_mesh.competencies.cmion_test:TestCompetency1" ConstructorParameters="a"/>'
         '\n<Competency ClassName="cmion_mesh.competencies.cmion_test:TestCompetency1"/>', "already in the library"),
    ],
)
def test_bad_library_entries_name_file_and_line(tmp_path: Path, entry: str, message: str) -> None:
    path = tmp_path / "lib.xml"
    path.write_text(f"<CompetencyLibrary>\n{entry}\n</CompetencyLibrary>\n")
    with pytest.raises(ConfigError, match=message) as info:
        load_library(path)
    assert str(info.value).startswith(f"{path}:")


class Gate(Competency):
    """Runs until released or cancelled; records overlap."""

    type = "Gate"
    running: set[str] = set()
    peak = [0]
    lock = threading.Lock()

    def __init__(self, name: str, release: threading.Event) -> None:
        super().__init__(name=name)
        self.release = release

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        with Gate.lock:
            Gate.running.add(self.name)
            Gate.peak[0] = max(Gate.peak[0], len(Gate.running))
        try:
            while not self.release.is_set():
                if not ctx.wait(0.01):
                    return False
            return parameters.get("ok", "yes") == "yes"
        finally:
            with Gate.lock:
                Gate.running.discard(self.name)


def rules_file(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "rules.xml"
    path.write_text(f"<CompetencyManagerRules>\n{body}\n</CompetencyManagerRules>\n")
    return path


PARALLEL = """
<Rule><MindAction Name="Do"/><CompetencyExecutionPlan>
  <Competency ID="a" Type="Gate"/>
  <Competency ID="b" Type="Gate"/>
  <Competency ID="c" Type="Gate"/>
  <Competency ID="d" Type="Gate" Dependency="a,b,c"/>
</CompetencyExecutionPlan></Rule>
"""


def test_independent_steps_really_run_in_parallel_and_dependencies_wait(
    tmp_path: Path, transport: MemoryTransport, client: MeshClient, mesh: str
) -> None:
    release = threading.Event()
    gates = [Gate(f"g{i}", release) for i in range(3)]
    Gate.peak[0] = 0
    with Embodiment("robot", mesh=mesh, transport=transport, rules=rules_file(tmp_path, PARALLEL), competencies=gates):
        events = collect(client, component="execution")
        result: list[Any] = []
        worker = threading.Thread(target=lambda: result.append(client.act("robot", "Do", timeout=20)))
        worker.start()
        wait_for(lambda: len(Gate.running) == 3, 10, "a, b and c running at once")
        assert not any(e.name == "StepStarted" and e.data["step"] == "d" for e in events), "d waits for its dependencies"
        release.set()
        worker.join(20)
    assert result[0].status == "succeeded"
    assert Gate.peak[0] == 3
    order = [e.data["step"] for e in events if e.name == "StepStarted"]
    assert order[-1] == "d" and sorted(order[:3]) == ["a", "b", "c"]


def test_busy_type_waits_instead_of_failing(tmp_path: Path, transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    release = threading.Event()
    with Embodiment("robot", mesh=mesh, transport=transport, rules=rules_file(tmp_path, PARALLEL),
                    competencies=[Gate("only", release)]):
        events = collect(client, component="execution")
        result: list[Any] = []
        worker = threading.Thread(target=lambda: result.append(client.act("robot", "Do", timeout=20)))
        worker.start()
        wait_for(lambda: any(e.name == "StepWaiting" for e in events), 10, "steps wait for the one busy Gate")
        release.set()
        worker.join(20)
    assert result[0].status == "succeeded"
    assert [e.data["competency"] for e in events if e.name == "StepSucceeded"] == ["only"] * 4


def test_busy_wait_is_bounded_by_the_plan_deadline(tmp_path: Path, transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    release = threading.Event()
    try:
        with Embodiment("robot", mesh=mesh, transport=transport, rules=rules_file(tmp_path, PARALLEL),
                        competencies=[Gate("only", release)]):
            report = client.act("robot", "Do", deadline=0.3, timeout=20)
    finally:
        release.set()
    assert report.status == "failed" and "deadline of 0.3 s passed" in report.reason


def test_cancel_mid_plan_stops_running_competencies(tmp_path: Path, transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    release = threading.Event()
    gates = [Gate(f"g{i}", release) for i in range(3)]
    with Embodiment("robot", mesh=mesh, transport=transport, rules=rules_file(tmp_path, PARALLEL), competencies=gates):
        events = collect(client, component="*")
        result: list[Any] = []
        worker = threading.Thread(target=lambda: result.append(client.act("robot", "Do", action_id="job-1", timeout=20)))
        worker.start()
        wait_for(lambda: len(Gate.running) == 3, 10, "three running")
        assert client.cancel("robot", "job-1").status == "accepted"
        worker.join(20)
        assert not Gate.running, "every competency stopped"
        again = client.cancel("robot", "job-1")
        assert again.status == "rejected" and "job-1" in again.reason
    assert result[0].status == "cancelled" and result[0].action_id == "job-1"
    heard_end(events, "job-1")
    names = [e.name for e in events]
    assert names.count("StepCancelled") == 3
    assert names.index("PlanCancelled") > max(i for i, n in enumerate(names) if n == "StepCancelled"), "reported once all stopped"
    assert "ActionCancelled" in names and "StepStarted" in names


SPECIFIC = """
<Rule><MindAction Name="Go"><Parameter No="1" Value="*"/><Parameter No="2" Value="*"/></MindAction>
  <CompetencyExecutionPlan><Competency ID="1" Type="Gate"><CompetencyParameter Name="ok" Value="yes"/></Competency>
  </CompetencyExecutionPlan></Rule>
<Rule><MindAction Name="Go"><Parameter No="1" Value="home"/><Parameter No="2" Value="*"/></MindAction>
  <CompetencyExecutionPlan><Competency ID="1" Type="Gate"><CompetencyParameter Name="ok" Value="$parameter2"/></Competency>
  </CompetencyExecutionPlan></Rule>
<Rule><MindAction Name="Go"><Parameter No="1" Value="home"/><Parameter No="2" Value="no"/></MindAction>
  <CompetencyExecutionPlan><Competency ID="1" Type="Gate"><CompetencyParameter Name="ok" Value="no"/></Competency>
  </CompetencyExecutionPlan></Rule>
"""


def test_most_specific_rule_first_then_fallback_in_order(tmp_path: Path, transport: MemoryTransport, client: MeshClient, mesh: str) -> None:
    release = threading.Event()
    release.set()
    with Embodiment("robot", mesh=mesh, transport=transport, rules=rules_file(tmp_path, SPECIFIC), competencies=[Gate("g", release)]):
        events = collect(client, component="manager")
        report = client.act("robot", "Go", ["home", "no"], timeout=20)
        assert report.status == "succeeded"
        heard_end(events, report.action_id)
        tried = [e.data["rule"].rsplit(":", 1)[1] for e in events if e.name == "ActionAttempt"]
        assert tried == ["9", "6", "3"], "fewest wildcards first, each failure falls back to the next match"
        assert report.rule.endswith(":3")
        events.clear()
        second = client.act("robot", "Go", ["home", "yes"], timeout=20)
        assert second.rule.endswith(":6")
        heard_end(events, second.action_id)
        assert [e.data["rule"].rsplit(":", 1)[1] for e in events if e.name == "ActionAttempt"] == ["6"]


def test_missing_competency_type_fails_the_action_with_reason(tmp_path: Path, transport: MemoryTransport, client: MeshClient,
                                                              mesh: str) -> None:
    rules = rules_file(tmp_path, '<Rule><MindAction Name="Fly"/><CompetencyExecutionPlan><Competency ID="1" Type="Wings"/>'
                                 '</CompetencyExecutionPlan></Rule>')
    with Embodiment("robot", mesh=mesh, transport=transport, rules=rules), \
            pytest.raises(RequestRejected, match="step 1 needs competency type 'Wings', which no competency of this embodiment provides"):
        client.act("robot", "Fly")
