"""A competency in a separate process, driven by an embodiment daemon over real zenoh."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import RequestRejected
from cmion_mesh.messages import Event
from cmion_mesh.procs import Daemon, cli_argv
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .conftest import start_daemon

pytestmark = pytest.mark.timeout(90)

RULES = """<CompetencyManagerRules>
<Rule><MindAction Name="Wave"><Parameter No="1" Value="*"/><Parameter No="2" Value="*"/></MindAction>
  <CompetencyExecutionPlan><Competency ID="1" Type="Arm">
    <CompetencyParameter Name="speed" Value="$parameter1"/><CompetencyParameter Name="steps" Value="$parameter2"/>
  </Competency></CompetencyExecutionPlan></Rule>
</CompetencyManagerRules>
"""


@pytest.fixture
def robot(tmp_path: Path, mesh: str) -> Iterator[str]:
    rules = tmp_path / "rules.xml"
    rules.write_text(RULES)
    daemon, endpoint = start_daemon(mesh, "robot", "--rules", str(rules), "--remote-type", "Arm")
    with daemon:
        yield endpoint


@pytest.fixture
def client(robot: str, mesh: str) -> Iterator[MeshClient]:
    with ZenohTransport(TransportConfig(connect=(robot,), multicast=False)) as t:
        c = MeshClient(t, mesh)
        wait_for(lambda: c.read_store("robot", "bb"), 10, "robot reachable")
        yield c


def arm_process(mesh: str, endpoint: str) -> Daemon:
    argv = cli_argv("serve-competency", "tests.helpers.remote_helpers:Arm", "--embodiment", "robot", "--mesh", mesh,
                    "--connect", endpoint, "--no-multicast")
    arm = Daemon(argv, name="arm")
    arm.wait_line("serving embodiment", 20)
    return arm


def test_remote_competency_runs_reports_progress_cancels_and_vanishes(robot: str, client: MeshClient, mesh: str) -> None:
    events: list[Event] = []
    client.events(events.append, embodiment="robot")
    with pytest.raises(RequestRejected, match="needs competency type 'Arm', which no competency of this embodiment provides"):
        client.act("robot", "Wave", ["fast", "1"])

    arm = arm_process(mesh, robot)
    try:
        wait_for(lambda: any(e.name == "CompetencyAppeared" for e in events), 10, "the remote competency is discovered")
        report = client.act("robot", "Wave", ["fast", "3"], timeout=30)
        assert report.status == "succeeded", report
        assert client.get_property("robot", "bb", "", "waved").value == {"speed": "fast", "steps": 3, "by": "Arm"}
        # progress comes from the remote process, the end from the daemon: they may arrive in either order
        wait_for(lambda: [e.data["progress"] for e in events if e.component == "Arm" and e.name == "Progress"][-3:]
                 == [{"step": 1, "of": 3}, {"step": 2, "of": 3}, {"step": 3, "of": 3}], 10, "three progress reports")

        # cancel mid-run
        result: list[Any] = []
        worker = threading.Thread(target=lambda: result.append(client.act("robot", "Wave", ["slow", "400"], action_id="long", timeout=60)))
        worker.start()
        wait_for(lambda: any(e.component == "Arm" and e.name == "Progress" and e.data["progress"]["of"] == 400 for e in events), 10,
                 "long run in progress")
        assert client.cancel("robot", "long").status == "accepted"
        worker.join(30)
        assert result and result[0].status == "cancelled"
        # The daemon ends the action only after the remote side confirmed the cancel, but the two
        # publish from different processes: nothing orders their arrival here.
        wait_for(lambda: any(e.component == "Arm" and e.name == "RunCancelled" for e in events), 10,
                 "the remote side's confirmation of the cancel")

        # the process dies mid-run: the action fails, naming the vanished competency
        result.clear()
        def doomed() -> None:
            result.append(client.act("robot", "Wave", ["slow", "400"], action_id="doomed", timeout=60))

        worker = threading.Thread(target=doomed)
        worker.start()
        wait_for(lambda: sum(1 for e in events if e.name == "Progress" and e.data["run_id"].startswith("doomed")) >= 2, 10,
                 "doomed run going")
        arm.kill()
        worker.join(30)
        assert result and result[0].status == "failed"
        assert "vanished" in result[0].reason, result[0].reason
    finally:
        arm.kill()
    wait_for(lambda: any(e.name == "CompetencyVanished" for e in events), 10, "the proxy is removed")
