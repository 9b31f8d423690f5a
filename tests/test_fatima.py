"""The FAtiMA line protocol with real processes: two daemons, each with ``cmion_mesh.minds.fatima.connector:FAtiMAConnector``,
and the stand-in FAtiMA (``cmion_mesh.testing.fatima_peer``, written from the spec) in processes of
its own over real sockets.

The robot hosts the companion ``spirit`` and runs its connector with ``modular migrating`` (the
plain ``PROPERTY-CHANGED *`` form); the screen is empty and runs ``modular persistent migrating``
(the ``-PERSISTENT``/``P:`` forms). Mind A talks to the robot, mind B to the screen. The tests share
one pair of daemons and one pair of minds, both connected before the first test: connect,
perceive, act, look at, fail without a storm, disconnect and reconnect with nothing left running,
then, in one test since each step starts where the last left the companion, migrate (the state
arrives byte for byte), fail a migration cleanly when the mind does not answer, and keep an
arriving state until a mind connects. Each test stands alone: the two test workers may split the
file, each then with daemons and minds of its own.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import StorageError
from cmion_mesh.messages import ActionStatus, Event, Migrate, SetProperty
from cmion_mesh.minds.fatima import link as fatima_link
from cmion_mesh.minds.fatima.protocol import HANDSHAKE_TIMEOUT
from cmion_mesh.procs import Daemon, cli_argv, free_port, unique_mesh
from cmion_mesh.testing.fatima_peer import PeerProcess
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

pytestmark = pytest.mark.timeout(120)

RULES = """<CompetencyManagerRules>
  <Rule>
    <MindAction Name="TestAction"><Parameter No="1" Value="*"/></MindAction>
    <CompetencyExecutionPlan>
      <Competency ID="1" Type="TestType2"><CompetencyParameter Name="RandomOutName" Value="$parameter1"/></Competency>
      <Competency ID="2" Type="TestType3" Dependency="1"><CompetencyParameter Name="RandomInName" Value="$parameter1"/></Competency>
    </CompetencyExecutionPlan>
  </Rule>
  <Rule>
    <MindAction Name="Express"><Parameter No="1" Value="*"/></MindAction>
    <CompetencyExecutionPlan>
      <Competency ID="1" Type="Animation"><CompetencyParameter Name="AnimationName" Value="$parameter1"/></Competency>
    </CompetencyExecutionPlan>
  </Rule>
  <Rule>
    <MindAction Name="GoTo"><Parameter No="1" Value="*"/></MindAction>
    <CompetencyExecutionPlan>
      <Competency ID="1" Type="Navigation"><CompetencyParameter Name="Location" Value="$parameter1"/></Competency>
    </CompetencyExecutionPlan>
  </Rule>
</CompetencyManagerRules>
"""
LIBRARY = """<CompetencyLibrary>
  <Competency ClassName="cmion_mesh.competencies.cmion_test:TestCompetency2"/>
  <Competency ClassName="cmion_mesh.competencies.cmion_test:TestCompetency3"/>
  <Competency ClassName="cmion_mesh.competencies.spirit:Animation" ConstructorParameters="0"/>
  <Competency ClassName="cmion_mesh.competencies.spirit:Navigation" ConstructorParameters="0.5,Self,60"/>
</CompetencyLibrary>
"""
WORLD = """<WorldModel>
  <Agent Name="UserA"><Property Name="speaksEnglish" Value="True" Type="bool" Persistent="True"/></Agent>
  <Agent Name="Self"><Property Name="location" Value="Home"/></Agent>
  <Object Name="Far"><Property Name="isLocation" Value="True" Type="bool"/></Object>
</WorldModel>
"""
#: Every entity of the world model above, as the minds are told about it (agents first).
ENTITIES = ["Self", "UserA", "Far"]


def write_config(folder: Path, name: str, options: str, port: int) -> Path:
    folder.mkdir(parents=True)
    (folder / "rules.xml").write_text(RULES)
    (folder / "library.xml").write_text(LIBRARY)
    (folder / "world.xml").write_text(WORLD)
    config = folder / "ArchitectureConfiguration.xml"
    config.write_text(
        f'<ArchitectureConfiguration Embodiment="{name}" CompetencyManagerRulesFile="rules.xml"'
        ' CompetencyLibraryConfigurationFile="library.xml" WorldModelInitFile="world.xml">\n'
        f'  <ArchitectureComponent ClassName="cmion_mesh.minds.fatima.connector:FAtiMAConnector" ConstructorParameters="{options} '
        f'port:{port}"/>\n'
        "</ArchitectureConfiguration>\n")
    return config


@dataclass
class Mesh:
    mesh: str
    robot: Daemon
    screen: Daemon
    client: MeshClient
    a: PeerProcess  # the mind on the robot
    b: PeerProcess  # the mind on the screen
    state_a: str
    state_b: str
    events: list[Event]

    def running(self, embodiment: str) -> list[str]:
        value = self.client.request(embodiment, "manager", "status", ActionStatus("")).value
        assert isinstance(value, dict)
        return list(value["running"])

    def link(self, embodiment: str) -> dict[str, Any]:
        link = self.client.describe(embodiment)["mind_connections"]["fatima"]
        assert isinstance(link, dict)
        return link

    def bb(self, embodiment: str, container: str, name: str) -> Any:
        """A blackboard value, or None while it is not there."""
        try:
            return self.client.get_property(embodiment, "bb", container, name, timeout=2.0).value
        except StorageError:
            return None

    def inhabitant(self, embodiment: str) -> Any:
        return self.client.describe(embodiment).get("inhabitant")

    def event(self, match: Callable[[Event], bool], what: str) -> Event:
        return wait_for(lambda: next((e for e in list(self.events) if match(e)), None), 15, what)


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Mesh]:
    tmp = tmp_path_factory.mktemp("fatima")
    mesh = unique_mesh()
    zenoh_ports = {"robot": free_port(), "screen": free_port()}
    mind_ports = {"robot": free_port(), "screen": free_port()}
    options = {"robot": "modular migrating stop-wait:0 state-timeout:1",
               "screen": "modular,persistent migrating stop-wait:0 state-timeout:1"}
    daemons: dict[str, Daemon] = {}
    peers: list[PeerProcess] = []
    states = {"robot": os.urandom(17_186).hex(), "screen": os.urandom(20_000).hex()}  # A's is 34,372 characters
    try:
        for name in ("robot", "screen"):
            config = write_config(tmp / name, name, options[name], mind_ports[name])
            other = "screen" if name == "robot" else "robot"
            argv = ["up", str(config), "--mesh", mesh, "--listen", f"tcp/127.0.0.1:{zenoh_ports[name]}", "--no-multicast",
                    "--connect", f"tcp/127.0.0.1:{zenoh_ports[other]}", "--state-dir", str(tmp / f"state-{name}")]
            if name == "robot":
                argv += ["--companion", "spirit"]
            daemons[name] = Daemon(cli_argv(*argv), name=name)
        for daemon in daemons.values():
            daemon.wait_line("up in mesh", 30)
        for name in ("robot", "screen"):
            (tmp / f"state-{name}.hex").write_text(states[name])
        a = PeerProcess(mind_ports["robot"], "--agent", "Spirit", "--prop", "role:TestAgent", "--prop", "isTestMind:True",
                        "--state-file", str(tmp / "state-robot.hex"))
        peers.append(a)
        b = PeerProcess(mind_ports["screen"], "--agent", "Spirit", "--prop", "role:TestAgent", "--state-file",
                        str(tmp / "state-screen.hex"))
        peers.append(b)
        transport = ZenohTransport(TransportConfig(connect=tuple(f"tcp/127.0.0.1:{p}" for p in zenoh_ports.values()),
                                                   multicast=False))
        try:
            client = MeshClient(transport, mesh)
            events: list[Event] = []
            subscription = client.events(events.append, component="*")
            try:
                wait_for(lambda: client.presence.alive() >= {"robot", "screen"}, 20, "both daemons seen")
                a.got("OK", timeout=20)
                b.got("CMD Stop", timeout=20)  # no companion on the screen: its mind sleeps
                yield Mesh(mesh, daemons["robot"], daemons["screen"], client, a, b, states["robot"], states["screen"], events)
            finally:
                subscription.close()
        finally:
            transport.close()
    finally:
        for peer in peers:
            peer.close()
        for daemon in daemons.values():
            daemon.stop()


def test_connects_and_is_told_the_world(world: Mesh) -> None:
    a = world.a
    a.got("OK")
    a.got("CMD GET-PROPERTIES")
    for entity in ENTITIES:
        a.got(f"ENTITY-ADDED {entity}")
    # The mind's own properties make it an agent of the world model (and so a perception).
    a.got("ENTITY-ADDED Spirit")
    a.got("PROPERTY-CHANGED * Spirit(role) TestAgent")
    a.got("PROPERTY-CHANGED * Spirit(isTestMind) True")
    link = wait_for(lambda: (lk := world.link("robot"))["connected"] and lk, 10, "the robot says a mind is connected")
    assert link["agent"] == "Spirit" and link["peer"].startswith("127.0.0.1:")
    assert wait_for(lambda: world.bb("robot", "", "agentName"), 10, "agentName on the blackboard") == "Spirit"
    # The screen's mind connects while no companion lives there: it is told to sleep.
    world.b.got("OK")
    world.b.got("CMD Stop")


def test_perceives_world_model_changes(world: Mesh) -> None:
    start = world.a.mark()
    assert world.client.write("robot", "wm", SetProperty("UserA", "mood", "happy")).status == "accepted"
    world.a.got("PROPERTY-CHANGED * UserA(mood) happy", start=start)
    assert world.client.write("robot", "wm", SetProperty("UserA", "age", 42)).status == "accepted"
    world.a.got("PROPERTY-CHANGED * UserA(age) 42", start=start)


def test_acts_through_the_rules_and_looks_at(world: Mesh) -> None:
    a = world.a
    start = a.mark()
    a.command("act TestAction test")
    done = a.got("ACTION-FINISHED Spirit TestAction test", start=start)
    received = a.received(start)
    assert received.index("ENTITY-ADDED TestUser") < received.index(done)
    assert "PROPERTY-CHANGED * TestUser(test) True" in received
    start = a.mark()
    a.command("send look-at TestUser")
    a.got("LOOK-AT TestUser test:True", start=start)
    a.got("ACTION-FINISHED Spirit look-at TestUser", start=start)
    a.command("send look-at Nobody")
    a.got("LOOK-AT Nobody", start=start)
    a.got("ACTION-FINISHED Spirit look-at Nobody", start=start)


def test_emotional_state_kept_and_bad_xml_survived(world: Mesh) -> None:
    a = world.a
    a.command("emotion 0.75")
    wait_for(lambda: world.bb("robot", "fatima", "mood") == 0.75, 10, "the mood on the blackboard")
    emotions = world.client.get_property("robot", "bb", "fatima", "emotions").value
    assert emotions == [{"type": "JOY", "direction": "User", "intensity": "2.5"}]
    a.command("send <EmotionalState><Mood>0.1</Moo")
    world.robot.wait_line("sent a malformed line", 10)
    assert "127.0.0.1:" in world.robot.wait_line("sent a malformed line", 1), "the log names the peer"
    start = a.mark()
    a.command("act Express nod")
    a.got("ACTION-FINISHED Spirit Express nod", start=start)
    assert world.client.get_property("robot", "bb", "fatima", "mood").value == 0.75


def test_a_failed_action_is_not_a_storm(world: Mesh) -> None:
    a = world.a
    before = world.link("robot")
    start = a.mark()
    a.command("act Dance wildly")  # no rule: fails; the stand-in retries every 250 ms, as FAtiMA does
    failed = [a.got("ACTION-FAILED Spirit Dance wildly", start=start)]
    first = a.mark()
    for _ in range(2):
        a.wait(lambda line: line == "< ACTION-FAILED Spirit Dance wildly", 5, start=a.mark())
    a.command("drop Dance wildly")
    answers = a.received(start).count(failed[0])
    tries = a.sent(start).count("Dance wildly")
    after = world.link("robot")
    # Each try got exactly one answer; the held ones came a second late, so at most about one try a second.
    assert answers == 3 and tries in (3, 4), (answers, tries)
    assert after["held_retries"] - before["held_retries"] >= 2, "the retries were answered from the hold"
    assert after["failures"] - before["failures"] <= 2, "the rules were not run again for each retry"
    assert a.mark() > first


def test_disconnect_cancels_running_actions_and_reconnects(world: Mesh) -> None:
    a = world.a
    a.command("act GoTo Far")  # 30 s of walking
    wait_for(lambda: world.running("robot"), 10, "the GoTo action running")
    a.command("disconnect")
    wait_for(lambda: not world.running("robot"), 10, "no action left running after the mind left")
    line = world.robot.wait_line("disconnected", 10)
    assert "Spirit" in line and "127.0.0.1:" in line, line
    world.event(lambda e: e.name == "MindDisconnected" and e.embodiment == "robot", "MindDisconnected event")
    before = world.link("robot")
    assert before["connected"] is False
    start = a.mark()
    a.command("connect")
    a.got("OK", start=start)
    a.command("act Express wave")
    a.got("ACTION-FINISHED Spirit Express wave", start=start)
    assert world.link("robot")["connections"] == before["connections"] + 1


def test_a_second_mind_is_refused(world: Mesh) -> None:
    with PeerProcess(int(world.link("robot")["listening"].rsplit(":", 1)[1]), "--agent", "Intruder") as intruder:
        intruder.wait(lambda line: line == "# disconnected", 10)
        assert "OK" not in intruder.received()
    assert "refused a connection" in world.robot.wait_line("refused a connection", 5)
    assert world.link("robot")["agent"] == "Spirit"


def closed_by_the_body(sock: socket.socket, timeout: float) -> bool:
    """Whether the body closed ``sock`` within ``timeout`` (it never sends a connection that did not
    handshake anything: the first thing read is the end)."""
    sock.settimeout(timeout)
    try:
        return sock.recv(64) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def test_a_connection_that_never_handshakes_keeps_no_mind_out(tmp_path: Path) -> None:
    """A slowloris (three bytes of a handshake, then nothing) and a crowd of idle sockets, all
    before the mind: the mind still gets through its handshake at once and is served, and every
    one of them is closed within the handshake timeout."""
    mind_port = free_port()
    config = write_config(tmp_path / "robot", "robot", "modular", mind_port)
    robot = Daemon(cli_argv("up", str(config), "--mesh", unique_mesh(), "--listen", f"tcp/127.0.0.1:{free_port()}",
                            "--no-multicast", "--state-dir", str(tmp_path / "state"), "--companion", "spirit"), name="robot")
    idle: list[socket.socket] = []
    try:
        robot.wait_line("up in mesh", 30)
        slow = socket.create_connection(("127.0.0.1", mind_port), timeout=10)
        idle.append(slow)
        slow.sendall(b"Spi")
        for _ in range(3 * fatima_link.MAX_PENDING):
            idle.append(socket.create_connection(("127.0.0.1", mind_port), timeout=10))
        with PeerProcess(mind_port, "--agent", "Spirit", "--prop", "role:TestAgent") as mind:
            mind.got("OK", timeout=HANDSHAKE_TIMEOUT)  # not after the slowloris's time is up: at once
            mind.command("act Express wave")
            mind.got("ACTION-FINISHED Spirit Express wave")
            still_open = [i for i, sock in enumerate(idle) if not closed_by_the_body(sock, HANDSHAKE_TIMEOUT + 10)]
            assert still_open == [], f"connections never handshaken still open: {still_open}"
            start = mind.mark()
            mind.command("act Express nod")  # served still, once they are gone
            mind.got("ACTION-FINISHED Spirit Express nod", start=start)
        robot.wait_line("before its handshake", 5)
    finally:
        for sock in idle:
            sock.close()
        robot.stop()


def test_migrations(world: Mesh) -> None:
    migrates_with_its_state_byte_for_byte(world)  # robot -> screen
    migration_fails_cleanly_when_the_mind_keeps_its_state(world)  # screen -> robot, refused
    an_arriving_state_waits_for_a_mind(world)  # screen -> robot


def migrates_with_its_state_byte_for_byte(world: Mesh) -> None:
    a, b = world.a, world.b
    start_a, start_b = a.mark(), b.mark()
    a.command("act GoTo Far")  # 30 s of walking, cut short by the companion leaving
    wait_for(lambda: world.running("robot"), 10, "the GoTo action running")
    a.command("act Migrate screen")
    a.got("CMD Stop", start=start_a)
    a.got("CMD GET-STATE", start=start_a)
    line = b.wait(lambda out: out.startswith("< CMD SET-STATE "), 15, start=start_b)
    assert line[len("< CMD SET-STATE "):] == world.state_a, "the opaque state arrives unchanged"
    b.got("CMD Start", start=start_b)
    b.got("ACTION-FINISHED Spirit Migrate screen", start=start_b)  # the action that moved it ends where it arrived
    b.got("ACTION-FAILED Spirit GoTo Far", start=start_b)  # the others did not: the mind retries them if it will
    b.got("CMD GET-PROPERTIES", start=start_b)
    received = b.received(start_b)
    assert "ACTION-FINISHED Spirit GoTo Far" not in received
    assert received.index("ACTION-FINISHED Spirit Migrate screen") < received.index("ACTION-FAILED Spirit GoTo Far")
    order = [received.index(line[2:]), received.index("CMD Start")]
    for entity in [*ENTITIES, "Spirit"]:
        look = next(r for r in received if r.startswith(f"LOOK-AT {entity}"))
        order += [received.index(look), received.index(f"ACTION-FINISHED Spirit look-at {entity}")]
    order.append(received.index("CMD GET-PROPERTIES"))
    assert order[:2] == sorted(order[:2]) and max(order[:2]) < min(order[2:-1]) < order[-1], received
    assert "LOOK-AT UserA P:speaksEnglish:True" in received  # the screen runs with `persistent`
    assert "STATE-SET" in b.sent(start_b)
    # The persistent facts of the world model came with the companion (its role, from its semantic memory).
    b.got("PROPERTY-CHANGED-PERSISTENT * Spirit(role) TestAgent", start=start_b)
    assert wait_for(lambda: world.inhabitant("screen") == "spirit", 10, "spirit on the screen")
    assert world.inhabitant("robot") is None
    # Nothing works on the robot any more for the companion that left.
    wait_for(lambda: not world.running("robot"), 10, "the GoTo action cancelled on the robot")


def migration_fails_cleanly_when_the_mind_keeps_its_state(world: Mesh) -> None:
    b = world.b
    b.command("mute-state")
    start = b.mark()
    outcome = world.client.request("screen", "migration", "migrate", Migrate("spirit", "robot"))
    assert outcome.status == "accepted", outcome
    b.got("CMD GET-STATE", start=start)
    b.got("CMD Start", start=start)  # abandoned: the mind is woken
    failed = world.event(lambda e: e.name == "MigrationFailed" and e.embodiment == "screen", "MigrationFailed")
    assert isinstance(failed.data, dict) and "did not answer GET-STATE" in failed.data["reason"]
    assert world.inhabitant("screen") == "spirit"
    b.command("answer-state")


def an_arriving_state_waits_for_a_mind(world: Mesh) -> None:
    a, b = world.a, world.b
    a.command("disconnect")
    wait_for(lambda: not world.link("robot")["connected"], 10, "the robot's mind gone")
    start_b = b.mark()
    outcome = world.client.request("screen", "migration", "migrate", Migrate("spirit", "robot"))
    assert outcome.status == "accepted", outcome
    b.got("CMD GET-STATE", start=start_b)
    wait_for(lambda: world.inhabitant("robot") == "spirit", 15, "spirit back on the robot")
    start_a = a.mark()
    a.command("connect")
    a.got("OK", start=start_a)
    line = a.wait(lambda out: out.startswith("< CMD SET-STATE "), 10, start=start_a)
    assert line[len("< CMD SET-STATE "):] == world.state_b
    a.got("CMD Start", start=start_a)
    a.wait(lambda out: out.startswith("< LOOK-AT UserA speaksEnglish:True"), start=start_a)
    a.got("CMD GET-PROPERTIES", start=start_a)
