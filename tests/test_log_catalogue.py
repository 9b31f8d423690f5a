"""The catalogue of log lines (docs/deploy.md, "Logs"), in one process: a migration's every step on
both sides, an action's end, refusals bounded under a flood, a web page and a FAtiMA mind coming and
going, a certificate about to expire; each parsed back from the text and the JSON format, and none
holding a secret. The same lines from daemons in their own processes: ``test_log_daemons.py``."""

from __future__ import annotations

import base64
import datetime as dt
import json
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from websockets.sync.client import connect

from cmion_mesh import keys, logs
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.rules import load_rules
from cmion_mesh.client import MeshClient
from cmion_mesh.messages import Act, MindMessage
from cmion_mesh.migration.ledger import read_ledger
from cmion_mesh.minds.fatima.connector import FAtiMAConnector
from cmion_mesh.presence import Presence
from cmion_mesh.requests import send_request
from cmion_mesh.testing.fatima_peer import Peer
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport import certs, security
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport
from cmion_mesh.web.body import WebBody

from .helpers.memory_bodies import body
from .test_logs import parse_text, strict_json

pytestmark = pytest.mark.timeout(60)

FORMATS = ("text", "json")


class LogFile:
    """The process's log, configured as a daemon's (``logs.configure``) into a file, read back parsed."""

    def __init__(self, path: Path, fmt: str) -> None:
        self.path, self.fmt = path, fmt

    def lines(self) -> list[dict[str, Any]]:
        logs.shutdown()  # the throttles' counts too
        text = self.path.read_text(encoding="utf-8") if self.path.exists() else ""
        parse = parse_text if self.fmt == "text" else strict_json
        return [parse(line) for line in text.splitlines() if line and not line.startswith((" ", "Traceback"))]

    def raw(self) -> str:
        logs.shutdown()
        return self.path.read_bytes().decode("utf-8", "replace")

    def where(self, **wanted: Any) -> list[dict[str, Any]]:
        """The lines whose fields have every value given (``msg__startswith`` for a message's start)."""
        out = []
        for line in self.lines():
            start = wanted.get("msg__startswith")
            if start is not None and not str(line.get("msg", "")).startswith(start):
                continue
            if all(line.get(k) == v for k, v in wanted.items() if k != "msg__startswith"):
                out.append(line)
        return out


@pytest.fixture(params=FORMATS)
def log_file(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[LogFile]:
    path = tmp_path / "daemon.log"
    logs.configure("info", request.param, path)
    try:
        yield LogFile(path, request.param)
    finally:
        logs.unconfigure()


def number(value: Any) -> float:
    assert isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value >= 0, value
    return float(value)


def secrets_of(state: Path) -> list[str]:
    """Every custody private key kept in a state folder, in the forms a line could hold it."""
    found = []
    for raw in read_ledger(state).keys.values():
        found += [raw.hex(), base64.b64encode(raw).decode(), base64.urlsafe_b64encode(raw).decode().rstrip("=")]
        found += [line.strip() for line in raw.decode("ascii", "replace").splitlines() if len(line.strip()) >= 16]
    return [s for s in found if len(s) >= 16]


def test_a_migration_and_the_action_that_moves_it_back_are_one_line_a_step(
        log_file: LogFile, network: MemoryNetwork, mesh: str, tmp_path: Path) -> None:
    robot = body(network, mesh, "robot", tmp_path, companion="spirit").start()
    screen = body(network, mesh, "screen", tmp_path).start()
    keys_seen: list[str] = []
    try:
        with MemoryTransport(network, "cli") as t:
            client = MeshClient(t, mesh)
            wait_for(lambda: robot.inhabitant == "spirit", 5, "spirit born on the robot")
            keys_seen += secrets_of(tmp_path / "robot")
            client.request("robot", "mind", "message", MindMessage({"note": "met Ada"}))
            assert client.migrate("spirit", "screen", timeout=20)["epoch"] == 2
            keys_seen += secrets_of(tmp_path / "screen")
            report = client.act("screen", "Migrate", ["robot"], timeout=20)
            assert report.status == "succeeded", report
            wait_for(lambda: robot.inhabitant == "spirit", 5, "back on the robot")
            keys_seen += secrets_of(tmp_path / "robot")
    finally:
        for e in (robot, screen):
            e.close()
            e.transport.close()

    born = log_file.where(step="born")
    assert [(b["msg"], b["companion"], b["epoch"], b["logger"]) for b in born] == [
        ("companion spirit born here", "spirit", 1, "cmion_mesh.migration.manager")]
    there = log_file.where(step="started", peer="screen")
    assert len(there) == 1 and there[0]["msg"] == "migration of spirit to screen started" and there[0]["epoch"] == 1
    attempt = there[0]["attempt"]
    steps = [line for line in log_file.lines() if line.get("attempt") == attempt]
    order = [s["step"] for s in steps]
    # The source's prepared is written beside the prepare: it and the target's incoming may come in either order.
    assert order[0] == "started" and set(order[1:3]) == {"prepared", "incoming"}, steps
    assert order[3:] == ["handed", "active", "released"], steps
    assert {s["companion"] for s in steps} == {"spirit"} and all(s["level"] == "INFO" for s in steps)
    by_step = {s["step"]: s for s in steps}
    # Who is on the other side, from each side: the target on the source's lines, the source on the target's.
    assert {k: by_step[k]["peer"] for k in by_step} == {"started": "screen", "prepared": "screen", "handed": "screen",
                                                        "released": "screen", "incoming": "robot", "active": "robot"}
    assert {k: by_step[k]["logger"] for k in by_step} == {
        "started": "cmion_mesh.migration.outgoing", "prepared": "cmion_mesh.migration.outgoing",
        "handed": "cmion_mesh.migration.outgoing", "released": "cmion_mesh.migration.outgoing",
        "incoming": "cmion_mesh.migration.incoming", "active": "cmion_mesh.migration.incoming"}
    assert by_step["active"]["msg"] == "companion spirit arrived from robot" and by_step["active"]["epoch"] == 2
    assert by_step["released"]["msg"] == "companion spirit left for screen" and by_step["released"]["epoch"] == 2
    assert number(by_step["released"]["duration_s"]) < 20 and number(by_step["active"]["duration_s"]) < 20
    assert by_step["handed"]["msg"] == "companion spirit handed to screen"

    # Back, through the Migrate action: its handshake the same way, then the action's end.
    back = log_file.where(step="started", peer="robot")
    assert len(back) == 1
    order = [s["step"] for s in log_file.lines() if s.get("attempt") == back[0]["attempt"]]
    assert order[0] == "started" and set(order[1:3]) == {"prepared", "incoming"}, order
    assert order[3:] == ["handed", "active", "released"], order
    ends = log_file.where(action="Migrate")
    assert len(ends) == 1, ends
    end = ends[0]
    assert end["msg"] == "action Migrate succeeded" and end["outcome"] == "succeeded" and end["logger"] == "cmion_mesh.body.manager"
    assert end["rule"] == "<built-in>:0" and end["attempts"] == 1 and end["action_id"] == report.action_id
    assert number(end["duration_s"]) < 20 and end["reason"] is None
    # Peers: each saw the other (and the client's session is no embodiment).
    assert {(p["msg"], p["peer"]) for p in log_file.where(msg__startswith="peer ")} >= {
        ("peer screen joined", "screen"), ("peer robot joined", "robot")}

    text = log_file.raw()
    assert keys_seen and not [s for s in keys_seen if s in text], "a custody private key reached the log"


def test_the_embodiments_alive_before_a_listener_came_are_told_to_it(network: MemoryNetwork, mesh: str) -> None:
    # An embodiment starts listening to its presence just after opening it: the peers the watch
    # delivers in between would otherwise never be logged as joined.
    with MemoryTransport(network, "robot") as robot, MemoryTransport(network, "screen") as screen:
        token = robot.declare_token(keys.alive_key(mesh, "robot"))
        presence = Presence(screen, mesh)
        try:
            wait_for(lambda: presence.alive() == {"robot"}, 5, "robot seen alive")
            told: list[tuple[str, bool]] = []
            with presence.listen(lambda name, alive: told.append((name, alive)), replay=True):
                assert told == [("robot", True)]
                token.close()
                wait_for(lambda: told == [("robot", True), ("robot", False)], 5, "robot seen leaving")
        finally:
            presence.close()
            token.close()


def test_an_action_and_the_actions_refused_at_once_end_in_one_line_and_a_count(log_file: LogFile, tmp_path: Path,
                                                                              network: MemoryNetwork, mesh: str) -> None:
    from cmion_mesh.competencies.spirit import Animation

    (tmp_path / "rules.xml").write_text(
        "<CompetencyManagerRules><Rule><MindAction Name=\"Express\"><Parameter No=\"1\" Value=\"*\"/></MindAction>"
        "<CompetencyExecutionPlan><Competency ID=\"1\" Type=\"Animation\"><CompetencyParameter Name=\"AnimationName\" "
        "Value=\"$parameter1\"/></Competency></CompetencyExecutionPlan></Rule></CompetencyManagerRules>")
    with MemoryTransport(network, "robot") as transport, Embodiment(
            "robot", mesh=mesh, transport=transport, rules=load_rules(tmp_path / "rules.xml"),
            competencies=[Animation("0")]) as robot, MemoryTransport(network, "cli") as t:
        client = MeshClient(t, mesh)
        assert client.act("robot", "Express", ["joy"], timeout=10).status == "succeeded"
        for _ in range(50):  # no rule: refused at once, every time, from the mesh
            assert client.request("robot", "manager", "act", Act("Fly", ["away"])).status == "rejected"
        robot.sim.request("manager", "act", Act("Fly", ["home"])).result(5)  # and from a mind of its own
    ok = log_file.where(action="Express")
    assert len(ok) == 1 and ok[0]["outcome"] == "succeeded" and ok[0]["rule"] == f"{tmp_path / 'rules.xml'}:1"
    # 51 failures at once: the first line, then one count (a peer can send those as fast as it likes).
    fly = log_file.where(action="Fly")
    assert [(f["msg"], f["outcome"], f["rule"]) for f in fly] == [("action Fly failed", "failed", None)]
    assert "no rule matches" in fly[0]["reason"]
    counted = log_file.where(msg__startswith="50 more actions failed at once from Fly in the last ")
    assert len(counted) == 1 and counted[0]["count"] == 50
    refused = log_file.where(msg="refused manager/act from (unnamed)")
    assert len(refused) == 1 and refused[0]["code"] == "not_found" and refused[0]["sender"] is None
    assert refused[0]["component"] == "manager" and refused[0]["request"] == "act" and "Fly" in refused[0]["reason"]


def flood_total(lines: list[dict[str, Any]], first: Callable[[dict[str, Any]], bool]) -> int:
    return sum(line["count"] if " more refused requests from " in line["msg"] else 1 for line in lines
               if first(line) or " more refused requests from " in line["msg"])


@pytest.mark.parametrize("senders", [1, 200])
def test_a_flood_of_refused_requests_writes_a_bounded_number_of_lines(log_file: LogFile, network: MemoryNetwork, mesh: str,
                                                                     tmp_path: Path, senders: int) -> None:
    count = 2000
    began = time.monotonic()
    with body(network, mesh, "robot", tmp_path) as robot, MemoryTransport(network, "cli") as t:
        for i in range(count):
            sender = f"phone{i % senders}"
            key = keys.request_key(mesh, "robot", "migration", "nosuch", sender)
            outcome = send_request(t, key, MindMessage({}), timeout=5)
            assert outcome.status == "rejected" and outcome.code == "unknown_request"
        assert robot.sim.answered()[("rejected", "unknown_request")] == count  # every one counted
    windows = (time.monotonic() - began) // logs.WINDOW + 1
    lines = [line for line in log_file.lines() if line["logger"] == "cmion_mesh.requests"]
    budget = min(senders, logs.BUDGET)
    assert len(lines) <= windows * (2 * budget + 1), [line["msg"] for line in lines]
    firsts = [line for line in lines if line["msg"].startswith("refused migration/nosuch from ")]
    assert firsts and all(f["code"] == "unknown_request" and f["request"] == "nosuch" and f["sender"] == f["msg"].split()[-1]
                          for f in firsts)
    assert flood_total(lines, lambda line: line in firsts) == count  # every refusal is in a line or a count
    if senders == 1 and windows == 1:
        assert [line["msg"] for line in lines] == ["refused migration/nosuch from phone0",
                                                   lines[1]["msg"]] and lines[1]["count"] == count - 1


def test_a_web_page_connecting_and_leaving_is_a_line_each_without_its_key(log_file: LogFile, transport: MemoryTransport,
                                                                         mesh: str) -> None:
    secret = "page-key-that-must-never-be-logged"
    with WebBody("127.0.0.1:0", key=secret) as page, Embodiment("screen", mesh=mesh, transport=transport) as screen:
        screen.add(page)
        with connect(page.url.replace("http", "ws") + f"/ws?key={secret}") as ws:
            assert json.loads(ws.recv(timeout=10))["type"] == "access"
        wait_for(lambda: log_file.where(msg="web page disconnected from web"), 10, "the page's end logged")
    connected = log_file.where(msg="web page connected to web")
    assert len(connected) == 1 and connected[0]["acts"] is True and connected[0]["pages"] == 1
    assert connected[0]["body"] == "web" and connected[0]["client"].startswith("127.0.0.1:")
    left = log_file.where(msg="web page disconnected from web")[0]
    assert left["pages"] == 0 and number(left["duration_s"]) < 10
    assert secret not in log_file.raw()


def test_a_fatima_mind_connecting_and_leaving_is_a_line_each(log_file: LogFile, transport: MemoryTransport) -> None:
    mind = FAtiMAConnector("port:0")
    with Embodiment("robot", transport=transport, components=[mind]):
        wait_for(lambda: mind.listener is not None, 5, "listening")
        assert mind.listener is not None
        with Peer("127.0.0.1", mind.listener.port, agent="Spirit") as peer:
            peer.connect()
            peer.wait_for(lambda line: line == "OK")
            wait_for(lambda: log_file.where(agent="Spirit", level="INFO"), 10, "the mind's arrival logged")
            peer.disconnect()
            wait_for(lambda: log_file.where(agent="Spirit", level="WARNING"), 10, "the mind's end logged")
    came = log_file.where(agent="Spirit", level="INFO")[0]
    assert came["msg"] == f"FAtiMA mind Spirit at {came['peer']} connected to fatima" and came["peer"].startswith("127.0.0.1:")
    assert came["mind"] == "fatima" and came["agent"] == "Spirit" and came["role"] == "TestAgent" and came["level"] == "INFO"
    went = log_file.where(agent="Spirit", level="WARNING")[0]
    assert went["msg"].startswith(f"FAtiMA mind Spirit at {came['peer']} disconnected from fatima") and went["cancelled"] == 0
    assert went["peer"] == came["peer"] and number(went["duration_s"]) < 10 and went["reason"]


def test_a_certificate_about_to_expire_is_a_warning_naming_it(log_file: LogFile, tmp_path: Path) -> None:
    folder = tmp_path / "pki"
    certs.init(folder)
    certs.issue(folder, "robot", days=12)
    certs.issue(folder, "screen")
    security.load_credentials(folder, "robot")
    security.load_credentials(folder, "screen")
    lines = log_file.where(logger="cmion_mesh.transport.security")
    assert len(lines) == 1, lines
    line = lines[0]
    assert line["level"] == "WARNING" and line["msg"].startswith(("certificate of robot expires in 11 days (",
                                                                  "certificate of robot expires in 12 days ("))
    expires = (dt.datetime.now(dt.UTC) + dt.timedelta(days=12)).date()
    assert line["identity"] == "robot" and line["cert"] == str(folder / "robot.pem") and line["days_left"] in (11, 12)
    assert abs((dt.date.fromisoformat(line["expires"]) - expires).days) <= 1
    private = (folder / "robot.key").read_text()
    assert "PRIVATE" in private and private.splitlines()[1] not in log_file.raw()
