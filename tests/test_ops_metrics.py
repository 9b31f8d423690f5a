"""Metrics and health: real embodiments on the in-memory transport feed ``Metrics``, scraped over real
HTTP and parsed with prometheus_client's own parsers; /healthz flips while the loop is blocked."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from prometheus_client import REGISTRY
from prometheus_client.openmetrics.parser import text_string_to_metric_families as parse_openmetrics
from prometheus_client.parser import text_string_to_metric_families

from cmion_mesh import keys
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError, RequestRejected, WebServerError
from cmion_mesh.messages import Event
from cmion_mesh.ops import metrics as ops_metrics
from cmion_mesh.ops.heartbeat import Heartbeat
from cmion_mesh.ops.metrics import Metrics, MetricsServer
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .helpers.competency_helpers import Stall

pytestmark = pytest.mark.timeout(60)

RULES = """<CompetencyManagerRules>
<Rule><MindAction Name="Nod"/><CompetencyExecutionPlan><Competency ID="a" Type="Nod"/></CompetencyExecutionPlan></Rule>
<Rule><MindAction Name="Shake"/><CompetencyExecutionPlan><Competency ID="a" Type="Shake"/></CompetencyExecutionPlan></Rule>
</CompetencyManagerRules>
"""
Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]


class Nod(Competency):
    type = "Nod"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        return True


class Shake(Competency):
    type = "Shake"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        return ctx.fail("shaking is not possible today")




def get(url: str, accept: str | None = None, host: str | None = None) -> tuple[int, str, str]:
    request = urllib.request.Request(url, headers={k: v for k, v in (("Accept", accept), ("Host", host)) if v})
    try:
        with urllib.request.urlopen(request, timeout=5) as reply:
            return reply.status, reply.headers.get("Content-Type", ""), reply.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers.get("Content-Type", ""), exc.read().decode()


def scrape(server: MetricsServer) -> Samples:
    """Every sample of ``/metrics`` in the Prometheus text format, parsed by prometheus_client."""
    status, content_type, text = get(server.url + "/metrics")
    assert status == 200 and content_type.startswith("text/plain; version=0.0.4"), (status, content_type)
    return {(s.name, frozenset(s.labels.items())): s.value for family in text_string_to_metric_families(text) for s in family.samples}


def value(samples: Samples, name: str, **labels: str) -> float:
    return samples.get((name, frozenset({"embodiment": "robot", **labels}.items())), 0.0)


@pytest.fixture
def bodies(tmp_path: Path, mesh: str) -> Iterator[tuple[Embodiment, Embodiment, MeshClient]]:
    network = MemoryNetwork()
    (tmp_path / "rules.xml").write_text(RULES)
    robot = Embodiment("robot", mesh=mesh, transport=MemoryTransport(network, "robot"), rules=tmp_path / "rules.xml",
                       competencies=[Nod(name="nod"), Shake(name="shake")], state_dir=tmp_path / "robot", companion="spirit")
    kiosk = Embodiment("kiosk", mesh=mesh, transport=MemoryTransport(network, "kiosk"), state_dir=tmp_path / "kiosk")
    client_transport = MemoryTransport(network, "mind")
    try:
        robot.start()
        kiosk.start()
        wait_for(lambda: robot.inhabitant == "spirit", 5, "spirit born on the robot")
        yield robot, kiosk, MeshClient(client_transport, mesh)
    finally:
        for e in (robot, kiosk):
            e.close()
            e.transport.close()
        client_transport.close()


def test_a_scrape_counts_what_the_embodiment_did(bodies: tuple[Embodiment, Embodiment, MeshClient]) -> None:
    robot, kiosk, client = bodies
    with ops_metrics.serve("127.0.0.1:0", robot) as server:
        assert server.url.startswith("http://127.0.0.1:") and server.port > 0
        before = scrape(server)
        assert value(before, "cmion_mesh_actions_total", outcome="succeeded") == 0, "every series is there from the start, at 0"
        assert value(before, "cmion_mesh_companion_hosted") == 1
        wait_for(lambda: value(scrape(server), "cmion_mesh_peers_alive") == 1, 5, "the robot sees the kiosk")

        # Actions: three succeed, one fails in its plan, one is refused before it starts.
        for _ in range(3):
            assert client.act("robot", "Nod", timeout=10).status == "succeeded"
        assert client.act("robot", "Shake", timeout=10).status == "failed"
        with pytest.raises(RequestRejected, match="no rule matches"):
            client.act("robot", "Dance", timeout=10)
        # Requests over the mesh, by code: one accepted write, two refused cancels of actions not running.
        answered = scrape(server)
        client.set_property("robot", keys.BLACKBOARD, "", "mood", "calm")
        for _ in range(2):
            assert client.cancel("robot", "no-such-action").code == "not_found"
        # Events: five raised here, three received from the kiosk.
        heard: list[Event] = []
        robot.sim.on_event(heard.append, embodiment="kiosk", component="probe")
        raised = scrape(server)
        for i in range(5):
            robot.sim.raise_event("probe", "Tick", i)
        for i in range(3):
            kiosk.sim.raise_event("probe", "Tock", i)
        wait_for(lambda: len(heard) == 3, 5, "the kiosk's three events heard by the robot")

        # Migrations: one refused (no such target), one that succeeds; then a custody conflict reported.
        assert robot.migration is not None
        assert robot.migration.start("nowhere").result(10).status == "rejected"
        assert robot.migration.start("kiosk").result(10).status == "accepted"
        # A custody conflict lost, then its end (no other holder left: not a conflict).
        robot.sim.raise_event("migration", "CustodyConflict", {"companion": "spirit", "holders": {"robot": 3, "kiosk": 4},
                                                               "keeper": "kiosk"})
        robot.sim.raise_event("migration", "CustodyConflict", {"companion": "spirit", "holders": {"robot": 5}, "keeper": "robot"})
        wait_for(lambda: value(scrape(server), "cmion_mesh_custody_conflicts_total") == 1, 5, "the conflict counted")
        after = scrape(server)

    assert value(after, "cmion_mesh_actions_total", outcome="succeeded") == 3
    assert value(after, "cmion_mesh_actions_total", outcome="failed") == 2, "a plan that failed and an action refused"
    assert value(after, "cmion_mesh_action_duration_seconds_count", outcome="succeeded") == 3
    assert value(after, "cmion_mesh_action_duration_seconds_count", outcome="failed") == 1, "a refused action has no duration"
    assert value(after, "cmion_mesh_action_duration_seconds_bucket", outcome="succeeded", le="+Inf") == 3

    def delta(name: str, since: Samples = answered, **labels: str) -> float:
        return value(after, name, **labels) - value(since, name, **labels)

    assert delta("cmion_mesh_requests_answered_total", status="accepted", code="") == 1
    assert delta("cmion_mesh_requests_answered_total", status="rejected", code="not_found") == 2
    assert value(answered, "cmion_mesh_requests_answered_total", status="rejected", code="not_found") == 1, "the refused action"
    assert delta("cmion_mesh_events_received_total", since=raised) == 3
    # Raised here since then: the five, the migration's own events and the conflict's two; none is counted twice.
    assert delta("cmion_mesh_events_published_total", since=raised) == robot.sim.events_raised - raised[
        ("cmion_mesh_events_published_total", frozenset({"embodiment": "robot"}.items()))]
    assert delta("cmion_mesh_events_published_total", since=raised) >= 5 + 2 + 2

    assert value(after, "cmion_mesh_migrations_total", role="source", outcome="failed") == 1
    assert value(after, "cmion_mesh_migrations_total", role="source", outcome="succeeded") == 1
    assert value(after, "cmion_mesh_migration_duration_seconds_count", outcome="succeeded") == 1
    assert value(after, "cmion_mesh_migration_duration_seconds_count", outcome="failed") == 0, "refused before it started"
    assert value(after, "cmion_mesh_companion_hosted") == 0, "spirit left for the kiosk"
    assert value(after, "cmion_mesh_custody_conflicts_total") == 1
    assert value(after, "cmion_mesh_request_queue_depth") >= 0 and value(after, "cmion_mesh_loop_updates_total") > 0
    assert ("cmion_mesh_publications_dropped_total", frozenset({"embodiment": "robot"}.items())) in after
    assert not any(family.name.startswith("cmion_mesh") for family in REGISTRY.collect()), "never the global registry"


def test_openmetrics_when_the_scraper_asks_for_it(bodies: tuple[Embodiment, Embodiment, MeshClient]) -> None:
    robot, _, client = bodies
    with ops_metrics.serve("127.0.0.1:0", robot) as server:
        assert client.act("robot", "Nod", timeout=10).status == "succeeded"
        status, content_type, text = get(server.url + "/metrics", accept="application/openmetrics-text; version=1.0.0")
        assert status == 200 and content_type.startswith("application/openmetrics-text"), content_type
        assert text.endswith("# EOF\n")
        families = {f.name: f for f in parse_openmetrics(text)}  # type: ignore[no-untyped-call]
        assert families["cmion_mesh_actions"].type == "counter"
        assert families["cmion_mesh_action_duration_seconds"].type == "histogram"
        assert families["cmion_mesh_request_queue_depth"].type == "gauge"
        succeeded = [s for s in families["cmion_mesh_actions"].samples if s.name == "cmion_mesh_actions_total"
                     and s.labels == {"embodiment": "robot", "outcome": "succeeded"}]
        assert [s.value for s in succeeded] == [1]


def test_healthz_is_unhealthy_while_the_loop_is_blocked(mesh: str) -> None:
    stall = Stall()
    with MemoryTransport(MemoryNetwork(), "robot") as transport, \
            Embodiment("robot", mesh=mesh, transport=transport, components=[stall]) as robot, \
            Heartbeat(robot.sim, 0.05) as heartbeat, \
            MetricsServer("127.0.0.1:0") as server:
        assert get(server.url + "/healthz")[0::2] == (503, "starting: the embodiment has not joined the mesh yet\n")
        assert get(server.url + "/metrics")[0] == 503
        metrics = server.attach(Metrics(robot, heartbeat=heartbeat, stale_after=0.3))
        assert metrics.stale_after == 0.3
        wait_for(lambda: get(server.url + "/healthz")[0::2] == (200, "ok\n"), 5, "healthy once the loop beats")
        try:
            stall.block()
            assert stall.entered.wait(5.0)
            for _ in range(3):
                robot.sim.call(lambda: None)  # work piling up behind the stuck handler
            wait_for(lambda: get(server.url + "/healthz")[0] == 503, 5, "unhealthy while blocked")
            reason = get(server.url + "/healthz")[2]
            assert "update loop has not turned for" in reason, reason
            # The metrics are still served while the loop is stuck: they show the queue growing.
            assert value(scrape(server), "cmion_mesh_request_queue_depth") >= 3
        finally:
            stall.release.set()
        wait_for(lambda: get(server.url + "/healthz")[0] == 200, 5, "healthy again once the loop turns")
        robot.close()
        status, _, reason = get(server.url + "/healthz")
        assert status == 503 and "stopping" in reason, reason
        transport.close()


def test_the_server_refuses_what_it_should(mesh: str) -> None:
    with MetricsServer(":0") as server:
        assert server.host == "127.0.0.1", "loopback unless an address says otherwise"
        assert get(server.url + "/nothing")[0] == 404
        status, _, body = get(server.url + "/healthz", host="attacker.example:80")
        assert status == 403 and "loopback" in body, "a site rebound to 127.0.0.1 reads nothing"
        assert get(server.url + "/healthz", host=f"localhost:{server.port}")[0] == 503
        with pytest.raises(WebServerError, match=f"cannot listen on 127.0.0.1:{server.port}"):
            MetricsServer(f"127.0.0.1:{server.port}")
    server.close()  # idempotent
    for bad in ("example.org:9464", "127.0.0.1:99999", "::1:9464"):
        with pytest.raises(ConfigError, match=r"--metrics: bad metrics address"):
            ops_metrics.parse_address(bad)


def test_codes_from_peers_cannot_grow_the_series() -> None:
    counts = {("accepted", ""): 2, ("rejected", "not_found"): 1, ("rejected", "x" * 50): 4, ("rejected", "y"): 1, ("odd", ""): 1}
    assert ops_metrics.bounded_codes(counts) == {("accepted", ""): 2, ("rejected", "not_found"): 1, ("rejected", "other"): 5,
                                                  ("other", ""): 1}


def test_the_container_probe(mesh: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CMION_MESH_METRICS", raising=False)
    assert ops_metrics.metrics_option(["cmion-mesh", "up", "--metrics", "0.0.0.0:9464"]) == "0.0.0.0:9464"
    assert ops_metrics.metrics_option(["cmion-mesh", "up", "--metrics=:9464"]) == ":9464"
    assert ops_metrics.metrics_option(["cmion-mesh", "up"]) is None
    with MemoryTransport(MemoryNetwork(), "robot") as transport, Embodiment("robot", mesh=mesh, transport=transport) as robot:
        with ops_metrics.serve("127.0.0.1:0", robot) as server:
            wait_for(lambda: ops_metrics.probe(f"127.0.0.1:{server.port}") == 0, 5, "the probe says healthy")
            monkeypatch.setenv("CMION_MESH_METRICS", f"0.0.0.0:{server.port}")
            assert ops_metrics.probe() == 0, "a wildcard address is asked on loopback"
            robot.close()
            assert ops_metrics.probe() == 1
        assert ops_metrics.probe() == 1, "nobody answers"


def test_minds_and_pages_connected_are_read_when_scraped(mesh: str) -> None:
    from websockets.sync.client import connect

    from cmion_mesh.minds.fatima.connector import FAtiMAConnector
    from cmion_mesh.testing.fatima_peer import Peer
    from cmion_mesh.web.body import WebBody

    mind = FAtiMAConnector("persistent", "port:0")
    with WebBody("127.0.0.1:0") as page_body, MemoryTransport(MemoryNetwork(), "robot") as transport, \
            Embodiment("robot", mesh=mesh, transport=transport, components=[page_body, mind]) as robot, \
            ops_metrics.serve("127.0.0.1:0", robot) as server:
        wait_for(lambda: mind.listener is not None, 5, "the connector listening")
        assert mind.listener is not None
        idle = scrape(server)
        assert value(idle, "cmion_mesh_mind_connected", mind="fatima", protocol="fatima") == 0
        assert value(idle, "cmion_mesh_web_pages_open", component="web") == 0
        with Peer("127.0.0.1", mind.listener.port) as peer, \
                connect(f"ws://127.0.0.1:{page_body.port}/ws", open_timeout=5) as page:
            peer.connect()
            page.recv(timeout=5)
            wait_for(lambda: value(scrape(server), "cmion_mesh_mind_connected", mind="fatima", protocol="fatima") == 1, 5,
                     "the mind connected")
            wait_for(lambda: value(scrape(server), "cmion_mesh_web_pages_open", component="web") == 1, 5, "the page open")
        wait_for(lambda: value(scrape(server), "cmion_mesh_web_pages_open", component="web") == 0, 5, "the page closed")
        wait_for(lambda: value(scrape(server), "cmion_mesh_mind_connected", mind="fatima", protocol="fatima") == 0, 5,
                 "the mind gone")


def test_the_containerfile_health_check_as_written(mesh: str) -> None:
    text = (Path(__file__).resolve().parents[1] / "Containerfile").read_text()
    assert re.search(r"^USER cmion-mesh$", text, re.M) and re.search(r"^VOLUME /state$", text, re.M)
    assert not re.search(r"^EXPOSE", text, re.M), "zenoh's ports are chosen when run"
    found = re.search(r"^HEALTHCHECK .*?CMD (\[.*\])$", text, re.M | re.S)
    assert found, "a HEALTHCHECK in exec form"
    command = json.loads(found.group(1))
    assert command[0] == "python"

    def check(address: str | None) -> subprocess.CompletedProcess[str]:
        env = {k: v for k, v in os.environ.items() if k != "CMION_MESH_METRICS"} | ({"CMION_MESH_METRICS": address} if address else {})
        return subprocess.run([sys.executable, *command[1:]], env=env, capture_output=True, text=True, timeout=30, check=False)

    with MemoryTransport(MemoryNetwork(), "robot") as transport, Embodiment("robot", mesh=mesh, transport=transport) as robot, \
            ops_metrics.serve("127.0.0.1:0", robot) as server:
        wait_for(lambda: get(server.url + "/healthz")[0] == 200, 5, "healthy")
        assert check(f"0.0.0.0:{server.port}").returncode == 0
        robot.close()
        done = check(f"0.0.0.0:{server.port}")
        assert done.returncode == 1 and "503" in done.stdout and "stopping" in done.stdout, done
