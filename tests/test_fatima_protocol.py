"""The FAtiMA connector's pieces: options, line formats, parsing, the failure gate, and the
connector on an in-memory embodiment with the stand-in mind on a real loopback socket (the
cross-process tests are in ``test_fatima.py``)."""

from __future__ import annotations

import socket
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.body.architecture import load_architecture
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.rules import load_rules
from cmion_mesh.errors import ConfigError, MeshError, XmlError
from cmion_mesh.messages import Act, ActionStatus, AddContainer, Event, MindMessage, SetProperty
from cmion_mesh.minds.fatima import connector as fatima
from cmion_mesh.minds.fatima import link as fatima_link
from cmion_mesh.minds.fatima.connector import FAtiMAConnector
from cmion_mesh.minds.fatima.link import FailureGate
from cmion_mesh.minds.fatima.protocol import (
    HANDSHAKE_TIMEOUT,
    Options,
    format_value,
    look_at_line,
    parse_emotional_state,
    parse_handshake,
    parse_options,
    parse_semantic_memory,
    property_changed_line,
)
from cmion_mesh.testing.fatima_peer import Peer, PeerProcess
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

RULES = """<CompetencyManagerRules>
  <Rule><MindAction Name="Express"><Parameter No="1" Value="*"/></MindAction>
    <CompetencyExecutionPlan><Competency ID="1" Type="Animation">
      <CompetencyParameter Name="AnimationName" Value="$parameter1"/></Competency></CompetencyExecutionPlan></Rule>
  <Rule><MindAction Name="GoTo"><Parameter No="1" Value="*"/></MindAction>
    <CompetencyExecutionPlan><Competency ID="1" Type="Navigation">
      <CompetencyParameter Name="Location" Value="$parameter1"/></Competency></CompetencyExecutionPlan></Rule>
</CompetencyManagerRules>
"""


# --- pure functions ---------------------------------------------------------------------------------


def test_options_as_cmion_wrote_them_and_our_extensions() -> None:
    assert parse_options([]) == Options()
    assert parse_options([""]) == Options()
    opts = parse_options(["Modular persistent migrating", "port:0 host:0.0.0.0 name:mind2 stop-wait:2 state-timeout:1.5",
                          "handshake-timeout:0.5"])
    assert (opts.modular, opts.persistent, opts.migrating) == (True, True, True)
    assert (opts.port, opts.host, opts.name, opts.stop_wait, opts.state_timeout) == (0, "0.0.0.0", "mind2", 2.0, 1.5)
    assert (opts.handshake_timeout, Options().handshake_timeout) == (0.5, HANDSHAKE_TIMEOUT)
    assert parse_options(["sleeping"]) == Options()
    for bad, why in (("magic", "unknown option 'magic'"), ("port:99999", "not a TCP port"), ("port:x", "port:x"),
                     ("stop-wait:-1", "0 to 600"), ("name:a/b", "'/'"), ("colour:red", "unknown option"),
                     ("handshake-timeout:0", "above 0"), ("handshake-timeout:nan", "above 0")):
        with pytest.raises(MeshError, match=why):
            parse_options([bad])
    # A migration gives each component 5 s for its section: the connector's own wait must end first.
    assert parse_options(["stop-wait:2 state-timeout:4"]).state_timeout == 4.0  # no migration: no such limit
    with pytest.raises(MeshError, match=r"stop-wait:2 and state-timeout:3 .* add up to 5 s: with 'migrating' .* under the 5 s"):
        parse_options(["migrating stop-wait:2 state-timeout:3"])


def test_values_and_lines_as_cmion_formatted_them() -> None:
    assert [format_value(v) for v in (True, False, None, 3, 0.5, "a b", [1, "x"], "two\nlines")] == [
        "True", "False", "null", "3", "0.5", "a b", '[1,"x"]', "two lines"]
    plain, modular = Options(), Options(modular=True)
    both = Options(modular=True, persistent=True)
    assert property_changed_line("User", "isPresent", True, False, plain) == "PROPERTY-CHANGED User(isPresent) True"
    assert property_changed_line("User", "isPresent", True, True, modular) == "PROPERTY-CHANGED * User(isPresent) True"
    assert property_changed_line("User", "isPresent", True, True, both) == "PROPERTY-CHANGED-PERSISTENT * User(isPresent) True"
    assert property_changed_line("User", "isPresent", False, False, both) == "PROPERTY-CHANGED-NONPERSISTENT * User(isPresent) False"
    props = {"isPresent": {"value": True, "persistent": False}, "isPerson": {"value": True, "persistent": True},
             "said": {"value": "hello there", "persistent": False}}
    assert look_at_line("User", props, False) == "LOOK-AT User isPresent:True isPerson:True said:hello_there"
    assert look_at_line("User", props, True) == "LOOK-AT User NP:isPresent:True P:isPerson:True NP:said:hello_there"
    assert look_at_line("Nobody", {}, True) == "LOOK-AT Nobody"


def test_handshake_and_xml_lines() -> None:
    hello = parse_handshake("SpiritOfTheBuilding TestAgent Spirit role:TestAgent isTestMind:True url:http://x empty:")
    assert (hello.agent, hello.role, hello.display_name) == ("SpiritOfTheBuilding", "TestAgent", "Spirit")
    assert hello.properties == {"role": "TestAgent", "isTestMind": "True", "url": "http://x", "empty": ""}
    assert parse_handshake("Spirit TestAgent Spirit").properties == {}
    # Per the spec, and with the reason: a mind that skipped its handshake, or a malformed one.
    for bad, why in (("Spirit TestAgent", "2 word"), ("look-at Spirit now", "'look-at' starts another message"),
                     ("<EmotionalState><Mood>0</Mood> a b", "starts another message"), ("STATE-SET a b", "another message"),
                     ("Spi/rit TestAgent Spirit", "not a valid name"), ("Spirit role:TestAgent Spirit", "role 'role:TestAgent'"),
                     ("Spirit TestAgent Spirit role:A odd", "'odd' is not a property"),
                     ("Spirit TestAgent Spirit :x", "':x' is not a property")):
        with pytest.raises(MeshError, match=f"handshake.*{why}"):
            parse_handshake(bad)
    state = parse_emotional_state('<EmotionalState><Mood>-0.5</Mood><Emotion type="DISTRESS" intensity="1"/></EmotionalState>', "m")
    assert state == {"mood": -0.5, "emotions": [{"type": "DISTRESS", "intensity": "1"}]}
    memory = ('<SemanticMemory><STM><Property persistent="true" name="ProbBias(TestAction1)" value="0.0"/>'
              '<Property persistent="true" name="SELF(mood)" value="ok"/><Property persistent="false" name="User(isPresent)" value="True"/>'
              '<Property persistent="false" name="ActionContext()" value=""/></STM><LTM><Property persistent="true" '
              'name="Cup(isObject)" value="True"/></LTM></SemanticMemory>')
    assert parse_semantic_memory(memory, "Spirit", "m") == [
        ("Spirit", "mood", "ok", True), ("User", "isPresent", "True", False), ("Cup", "isObject", "True", True)]
    with pytest.raises(XmlError, match=r"the mind at 1\.2\.3\.4"):
        parse_semantic_memory("<SemanticMemory><STM>", "Spirit", "the mind at 1.2.3.4")
    with pytest.raises(XmlError):
        parse_emotional_state('<!DOCTYPE x [<!ENTITY a "b">]><EmotionalState>&a;</EmotionalState>', "m")


def test_failure_gate_holds_then_backs_off() -> None:
    now = [100.0]
    gate = FailureGate(first=2.0, most=5.0, clock=lambda: now[0])
    key = ("greet", ("User",))
    assert gate.held(key) is None
    gate.failed(key, "no rule")
    now[0] += 0.25
    held = gate.held(key)
    assert held is not None and held.retries == 1 and held.reason == "no rule"
    now[0] += 1.8  # past the first window: the rules run again
    assert gate.held(key) is None
    assert gate.failed(key, "still no rule").hold == 4.0
    assert gate.failed(key, "again").hold == 5.0  # at most HOLD_MOST
    assert gate.held_retries == 1
    gate.succeeded(key)
    assert gate.held(key) is None and gate.get(key) is None


def test_architecture_names_the_connector_with_cmion_parameters(tmp_path: Path) -> None:
    for params, expected in (("", Options()), ("modular persistent migrating", Options(True, True, True)),
                             ("migrating,port:0", Options(migrating=True, port=0))):
        config = tmp_path / "ArchitectureConfiguration.xml"
        (tmp_path / "r.xml").write_text("<CompetencyManagerRules/>")
        (tmp_path / "l.xml").write_text("<CompetencyLibrary/>")
        config.write_text('<ArchitectureConfiguration Embodiment="e" CompetencyManagerRulesFile="r.xml" '
                          'CompetencyLibraryConfigurationFile="l.xml">\n'
                          f'  <ArchitectureComponent ClassName="cmion_mesh.minds.fatima.connector:FAtiMAConnector" '
                          f'ConstructorParameters="{params}"/>\n'
                          "</ArchitectureConfiguration>\n")
        (built,) = load_architecture(config).build_components()
        assert isinstance(built, FAtiMAConnector) and built.options == expected and built.listener is None
    config.write_text(config.read_text().replace("migrating,port:0", "migrating wobbly"))
    with pytest.raises(ConfigError, match=r"ArchitectureConfiguration.xml:2: .*unknown option 'wobbly'"):
        load_architecture(config).build_components()


# --- the connector on an in-memory embodiment -------------------------------------------------------


@pytest.fixture
def body(tmp_path: Path) -> Iterator[tuple[Embodiment, FAtiMAConnector]]:
    from cmion_mesh.competencies.spirit import Animation, Navigation

    (tmp_path / "rules.xml").write_text(RULES)
    mind = FAtiMAConnector("persistent", "port:0")  # not modular: CMION's old PROPERTY-CHANGED form
    with MemoryTransport(MemoryNetwork(), "local") as transport, Embodiment(
            "robot", transport=transport, rules=load_rules(tmp_path / "rules.xml"),
            competencies=[Animation("0"), Navigation("0.5", "Self", "60")], components=[mind]) as embodiment:
        embodiment.world_model.apply_now(AddContainer("", "Far", "object"))
        embodiment.world_model.apply_now(SetProperty("Far", "isLocation", True))
        embodiment.world_model.apply_now(AddContainer("", "Self", "agent"))
        wait_for(lambda: mind.listener is not None, 5, "the connector listening")
        yield embodiment, mind


def _peer(mind: FAtiMAConnector, **kwargs: object) -> Peer:
    assert mind.listener is not None
    return Peer("127.0.0.1", mind.listener.port, **kwargs)  # type: ignore[arg-type]


def test_port_zero_cancel_remote_action_and_old_form(body: tuple[Embodiment, FAtiMAConnector]) -> None:
    embodiment, mind = body
    assert mind.listener is not None and mind.listener.port != 0
    assert embodiment.blackboard.get("fatima", "port") == mind.listener.port
    with _peer(mind) as peer:
        peer.connect()
        peer.wait_for(lambda line: line == "ENTITY-ADDED Far")
        embodiment.world_model.apply_now(SetProperty("Far", "visited", False))
        peer.wait_for(lambda line: line == "PROPERTY-CHANGED Far(visited) False")
        peer.send("look-at Far")
        peer.wait_for(lambda line: line == "LOOK-AT Far NP:isLocation:True NP:visited:False")
        peer.send("GoTo Far")
        wait_for(lambda: embodiment.manager.active, 5, "GoTo running")
        peer.send("CANCEL-ACTION GoTo Far")
        wait_for(lambda: not embodiment.manager.active, 5, "GoTo cancelled")
        embodiment.sim.raise_event("invitations", "RemoteAction",
                                   {"name": "MigrationInvitation", "parameters": ["screen"], "subject": "screen"})
        peer.wait_for(lambda line: line == "ACTION-FINISHED screen MigrationInvitation screen")
        assert not any(line.startswith("ACTION-FINISHED Spirit GoTo") for line in peer.received)
        assert embodiment.describe()["mind_connections"]["fatima"]["connected"] is True
        # CMION's raw messages: a line handed to the mind as it is
        outcome = embodiment.sim.request("fatima", "message", MindMessage({"line": "CMD Save"})).result(5)
        assert outcome.status == "accepted", outcome
        peer.wait_for(lambda line: line == "CMD Save")
        bad = embodiment.sim.request("fatima", "message", MindMessage({"line": "two\nlines"})).result(5)
        assert bad.status == "rejected" and "one line of text" in bad.reason


def test_the_mind_is_asked_to_save_as_the_body_stops() -> None:
    mind = FAtiMAConnector("port:0")
    with MemoryTransport(MemoryNetwork(), "local") as transport:
        embodiment = Embodiment("robot", transport=transport, components=[mind]).start()
        try:
            wait_for(lambda: mind.listener is not None, 5, "listening")
            with _peer(mind) as peer:
                peer.connect()
                peer.wait_for(lambda line: line == "OK")
                embodiment.close()
                peer.wait_for(lambda line: line == "CMD Save")
        finally:
            embodiment.close()


def _lines_until(lines: Any, last: Callable[[bytes], bool], limit: int = 200) -> list[bytes]:
    """Lines read from a socket file up to the first for which ``last`` is true (bounded)."""
    got = [lines.readline()]
    while got[-1] != b"" and not last(got[-1]) and len(got) < limit:
        got.append(lines.readline())
    assert got[-1] != b"" and last(got[-1]), got
    return got


def test_crlf_lines_and_a_bad_handshake(body: tuple[Embodiment, FAtiMAConnector], caplog: pytest.LogCaptureFixture) -> None:
    _, mind = body
    assert mind.listener is not None
    with socket.create_connection(("127.0.0.1", mind.listener.port), timeout=5) as sock:
        sock.sendall(b"Lonely\r\n")
        assert sock.recv(100) == b""  # closed: no OK
    wait_for(lambda: "bad handshake" in caplog.text, 5, "the refusal logged")
    assert "127.0.0.1:" in caplog.text
    with socket.create_connection(("127.0.0.1", mind.listener.port), timeout=5) as sock, sock.makefile("rb") as lines:
        sock.sendall(b"Spirit Role Spirit\r\nExpress nod\r\n")
        got = [lines.readline()]
        while got[-1] not in (b"", b"ACTION-FINISHED Spirit Express nod\n") and len(got) < 20:
            got.append(lines.readline())
        assert got[0] == b"OK\n" and got[-1] == b"ACTION-FINISHED Spirit Express nod\n", got


def test_a_line_not_utf8_is_dropped_and_a_cut_line_logged(body: tuple[Embodiment, FAtiMAConnector],
                                                          caplog: pytest.LogCaptureFixture) -> None:
    _, mind = body
    assert mind.listener is not None
    with socket.create_connection(("127.0.0.1", mind.listener.port), timeout=10) as sock, sock.makefile("rb") as lines:
        peer = f"127.0.0.1:{sock.getsockname()[1]}"
        sock.sendall(b"Spirit Role Spirit\nExpress caf\xe9\nExpress nod\n")
        got = _lines_until(lines, lambda line: line.startswith(b"ACTION-FINISHED Spirit Express"))
        assert got[-1] == b"ACTION-FINISHED Spirit Express nod\n", got  # the bad line never became an action
        assert not any(b"caf" in line for line in got)
        sock.sendall(b"Express unfinish")  # then the mind goes, inside a line
        sock.shutdown(socket.SHUT_WR)
        wait_for(lambda: "ended inside a line" in caplog.text, 5, "the cut line logged")
    dropped = next(r.getMessage() for r in caplog.records if "not UTF-8" in r.getMessage())
    assert peer in dropped and "caf\\xe9" in dropped, dropped
    cut = next(r.getMessage() for r in caplog.records if "ended inside a line" in r.getMessage())
    assert peer in cut and "16 byte(s)" in cut and "Express unfinish" in cut, cut


def test_refused_connections_are_logged_once_a_while(body: tuple[Embodiment, FAtiMAConnector], caplog: pytest.LogCaptureFixture,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    _, mind = body
    assert mind.listener is not None
    monkeypatch.setattr(fatima_link, "REFUSED_LOG_INTERVAL", 3600.0)

    def refused() -> None:
        with socket.create_connection(("127.0.0.1", mind.listener.port), timeout=5) as sock:  # type: ignore[union-attr]
            assert sock.recv(100) == b""  # closed at once: logged (or counted) before

    def warnings() -> list[str]:
        return [r.getMessage() for r in caplog.records if "refused a connection" in r.getMessage()]

    with _peer(mind) as peer:
        peer.connect()
        peer.wait_for(lambda line: line == "OK")
        for _ in range(3):
            refused()
        assert len(warnings()) == 1 and "more from" not in warnings()[0], warnings()
        monkeypatch.setattr(fatima_link, "REFUSED_LOG_INTERVAL", 0.0)
        refused()
        assert len(warnings()) == 2 and "(2 more from 127.0.0.1 refused unlogged" in warnings()[1], warnings()


def test_a_connection_without_a_handshake_is_closed_in_time(caplog: pytest.LogCaptureFixture) -> None:
    mind = FAtiMAConnector("port:0", "handshake-timeout:0.5")
    with MemoryTransport(MemoryNetwork(), "local") as transport, Embodiment("robot", transport=transport, components=[mind]):
        wait_for(lambda: mind.listener is not None, 5, "the connector listening")
        listener = mind.listener
        assert listener is not None
        with socket.create_connection(("127.0.0.1", listener.port), timeout=10) as slow:
            slow.sendall(b"Spi")  # three bytes of a handshake, then nothing
            assert slow.recv(100) == b""  # closed by the body (else the 10 s timeout fails the test)
        wait_for(lambda: "before its handshake: no handshake within 0.5 s" in caplog.text, 5, "the deadline logged")
        assert mind.connection()["pending"] == 0
        with _peer(mind) as peer:
            peer.connect()
            peer.wait_for(lambda line: line == "OK")


def test_pending_connections_are_bounded_and_the_newest_gets_through(caplog: pytest.LogCaptureFixture) -> None:
    mind = FAtiMAConnector("port:0", "handshake-timeout:60")  # no deadline passes here: the bound alone acts
    with MemoryTransport(MemoryNetwork(), "local") as transport, Embodiment("robot", transport=transport, components=[mind]):
        wait_for(lambda: mind.listener is not None, 5, "the connector listening")
        listener = mind.listener
        assert listener is not None
        # More idle connections than may wait: the oldest are closed at once, the others wait.
        extra = 3
        idle = [socket.create_connection(("127.0.0.1", listener.port), timeout=10) for _ in range(fatima_link.MAX_PENDING + extra)]
        try:
            for sock in idle[:extra]:
                sock.settimeout(10)
                assert sock.recv(100) == b""
            wait_for(lambda: mind.connection()["pending"] == fatima_link.MAX_PENDING, 5, "the newest waiting for their handshakes")
            with _peer(mind) as peer:  # the mind is the newest: it gets through, and the rest are closed
                peer.connect()
                peer.wait_for(lambda line: line == "OK")
                for sock in idle[extra:]:
                    sock.settimeout(10)
                    assert sock.recv(100) == b""
                assert mind.connection()["pending"] == 0 and mind.connection()["agent"] == "Spirit"
        finally:
            for sock in idle:
                sock.close()
    assert "newer connections wait for theirs" in caplog.text


def test_a_flooding_mind_is_held_back_and_the_body_keeps_working(body: tuple[Embodiment, FAtiMAConnector]) -> None:
    embodiment, mind = body
    assert mind.listener is not None
    with PeerProcess(mind.listener.port) as peer:
        peer.got("OK")
        link = wait_for(lambda: mind.link if mind.link is not None and mind.link.handshaken else None, 5, "the link")
        peer.command("quiet")  # the peer answers, keeps nothing (a flood's answers are many)
        peer.wait(lambda line: line == "# quiet")
        peer.command("flood-reading look-at Far")  # at most 10,000 look-ats ahead of the answers read
        # The reader stops at the bound of lines in flight: TCP holds the mind back from there on.
        wait_for(lambda: link.peak_in_flight >= fatima_link.MAX_IN_FLIGHT, 20, "the flood reaching the bound")
        waiting: list[int] = []

        def written() -> bool:
            waiting.append(embodiment.sim.queued())
            return bool(embodiment.blackboard.get("animation", "last") == "flood-proof")

        act = embodiment.sim.request("manager", "act", Act("Express", ["flood-proof"])).result(20)
        assert act.status == "accepted", act
        wait_for(written, 30, "the competency's blackboard write, during the flood")
        assert not any(line.startswith("# flood ended") for line in peer.lines), "the flood went on meanwhile"
        peer.command("stop-flood")
        ended = peer.wait(lambda line: line.startswith("# flood ended"), 20)
        assert ended.endswith("(stopped)"), ended  # the connection held all along
        flooded = int(ended.split()[4])
        assert flooded > 10 * fatima_link.MAX_IN_FLIGHT, ended
    # What the daemon held for it stayed bounded, whatever the flood's length.
    assert link.peak_in_flight == fatima_link.MAX_IN_FLIGHT
    assert max(waiting) <= fatima_link.MAX_IN_FLIGHT + 16, max(waiting)
    assert link.peak_queued <= fatima_link.MAX_QUEUED


def test_a_mind_that_does_not_read_is_disconnected(body: tuple[Embodiment, FAtiMAConnector],
                                                   caplog: pytest.LogCaptureFixture) -> None:
    embodiment, mind = body
    assert mind.listener is not None
    embodiment.world_model.apply_now(SetProperty("Far", "description", "x" * 65536))  # each look-at: a 64 KB answer
    gone: list[Event] = []
    embodiment.sim.on_event(gone.append, component="fatima", event="MindDisconnected")
    with PeerProcess(mind.listener.port) as peer:
        peer.got("OK")
        link = wait_for(lambda: mind.link if mind.link is not None and mind.link.handshaken else None, 5, "the link")
        peer.command("stop-reading")
        peer.wait(lambda line: line == "# stopped reading")
        peer.command("flood look-at Far")
        event = wait_for(lambda: gone[0] if gone else None, 60, "the mind disconnected")
        assert isinstance(event.data, dict) and event.data["reason"].startswith("mind is not reading"), event.data
        peer.wait(lambda line: line.startswith("# flood ended"), 20)
    logged = next(r.getMessage() for r in caplog.records if "mind is not reading" in r.getMessage())
    assert link.peer in logged and "connection closed" in logged, logged
    assert fatima_link.MAX_QUEUED < link.peak_queued <= fatima_link.MAX_QUEUED + 70_000, link.peak_queued  # at most one line beyond
    with _peer(mind) as again:  # and the next mind is welcome
        again.connect()
        again.wait_for(lambda line: line == "OK")


def test_an_overlong_line_closes_the_connection(body: tuple[Embodiment, FAtiMAConnector], caplog: pytest.LogCaptureFixture,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    _, mind = body
    monkeypatch.setattr(fatima_link, "MAX_LINE", 1000)
    with _peer(mind) as peer:
        peer.connect()
        peer.wait_for(lambda line: line == "OK")
        peer.send("x" * 5000)
        wait_for(lambda: "longer than 1000 bytes" in caplog.text, 5, "the refusal logged")
        wait_for(lambda: not mind.connection()["connected"], 5, "the link dropped")
    assert "127.0.0.1:" in caplog.text


def test_a_taken_port_is_reported(caplog: pytest.LogCaptureFixture) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        mind = FAtiMAConnector(f"port:{port}")
        with MemoryTransport(MemoryNetwork(), "local") as transport, Embodiment("robot", transport=transport, components=[mind]):
            wait_for(lambda: f"cannot listen on 127.0.0.1:{port}" in caplog.text, 5, "the failure logged")
        assert mind.listener is None and mind.connection()["listening"] is None


def test_held_retries_are_counted(body: tuple[Embodiment, FAtiMAConnector], monkeypatch: pytest.MonkeyPatch) -> None:
    embodiment, mind = body
    monkeypatch.setattr(fatima, "HELD_ANSWER_DELAY", 0.05)
    with _peer(mind, retry_interval=0.01) as peer:
        peer.connect()
        peer.wait_for(lambda line: line == "OK")
        peer.act("Fly away")
        wait_for(lambda: peer.received.count("ACTION-FAILED Spirit Fly away") >= 5, 5, "five answers")
        peer.drop("Fly away")
    link = mind.connection()
    assert link["failures"] == 1 and link["held_retries"] >= 4, link
    value = embodiment.sim.request("manager", "status", ActionStatus("")).result(5).value
    assert value == {"running": []}


def test_the_minds_own_properties_are_told_once(body: tuple[Embodiment, FAtiMAConnector]) -> None:
    embodiment, mind = body
    with _peer(mind) as peer:
        for connection in range(2):  # the first connection, and a reconnection (the properties known)
            start = len(peer.received)
            peer.connect()
            peer.wait_for(lambda line: line == "CMD GET-PROPERTIES", start=start)
            wait_for(lambda: peer.sent[-1].startswith("<SemanticMemory>"), 5, "its semantic memory sent")
            peer.send("look-at Far")  # once answered, the semantic memory before it was read, its writes queued
            peer.wait_for(lambda line: line == "ACTION-FINISHED Spirit look-at Far", start=start)
            # A write queued after those: once it is told, every change before it has been told too.
            assert embodiment.sim.request("wm", "set_property", SetProperty("Far", "marker", connection)).result(5).status == "accepted"
            peer.wait_for(lambda line: line == f"PROPERTY-CHANGED Far(marker) {connection}", start=start)  # noqa: B023
            role = embodiment.world_model.tree()["children"]["Spirit"]["properties"]["role"]
            assert role == {"value": "TestAgent", "persistent": True}, role  # as its semantic memory said
            told = peer.received[start:]
            assert told.count("PROPERTY-CHANGED Spirit(role) TestAgent") == 1, told
            assert told.count("PROPERTY-CHANGED Spirit(isTestMind) True") == 1, told
            peer.disconnect()
            wait_for(lambda: not mind.connection()["connected"], 5, "the mind gone")


# --- migrations that fail, on in-memory embodiments --------------------------------------------------


@pytest.fixture
def two(request: pytest.FixtureRequest, tmp_path: Path, mesh: str) -> Iterator[tuple[Embodiment, FAtiMAConnector, list[Any]]]:
    """The robot hosting spirit with a FAtiMA connector; a kiosk that admits only someone else.
    (Parametrized indirectly: the connector's state-timeout, default 2.)"""
    network = MemoryNetwork()
    mind = FAtiMAConnector(f"modular migrating port:0 stop-wait:0 state-timeout:{getattr(request, 'param', 2)}")
    robot = Embodiment("robot", mesh=mesh, transport=MemoryTransport(network, "robot"), state_dir=tmp_path / "robot",
                       companion="spirit", components=[mind])
    kiosk = Embodiment("kiosk", mesh=mesh, transport=MemoryTransport(network, "kiosk"), state_dir=tmp_path / "kiosk",
                       admit={"someone-else": None})
    failures: list[Any] = []
    try:
        robot.start()
        kiosk.start()
        robot.sim.on_event(lambda e: failures.append(e.data), component="migration", event="MigrationFailed")
        wait_for(lambda: robot.inhabitant == "spirit" and mind.listener is not None and mind.awake, 5, "spirit awake on the robot")
        yield robot, mind, failures
    finally:
        for e in (robot, kiosk):
            e.close()
            e.transport.close()


def test_a_refused_migration_leaves_the_mind_its_state(two: tuple[Embodiment, FAtiMAConnector, list[Any]]) -> None:
    robot, mind, failures = two
    with _peer(mind, state="cafe0123") as peer:
        peer.connect()
        peer.wait_for(lambda line: line == "OK")
        wait_for(lambda: robot.presence is not None and "kiosk" in robot.presence.alive(), 5, "the robot sees the kiosk")
        peer.act("Migrate kiosk")
        peer.wait_for(lambda line: line == "ACTION-FAILED Spirit Migrate kiosk")
        peer.drop("Migrate kiosk")
        received = peer.received
        assert received.index("CMD Stop") < received.index("CMD GET-STATE") < received.index("CMD Start")
        assert not any(line.startswith("CMD SET-STATE") for line in received), "the mind kept its own state"
        assert "ACTION-FINISHED Spirit Migrate kiosk" not in received
        assert failures and "may not enter 'kiosk'" in str(failures[0])
    assert robot.inhabitant == "spirit" and mind.awake


def test_a_mind_leaving_while_asked_for_its_state_ends_the_migration(two: tuple[Embodiment, FAtiMAConnector, list[Any]]) -> None:
    robot, mind, failures = two
    with _peer(mind, answer_state=False) as peer:
        peer.connect()
        peer.wait_for(lambda line: line == "OK")
        wait_for(lambda: robot.presence is not None and "kiosk" in robot.presence.alive(), 5, "the robot sees the kiosk")
        assert robot.migration is not None
        robot.migration.start("kiosk")
        peer.wait_for(lambda line: line == "CMD GET-STATE")
        peer.disconnect()
        wait_for(lambda: failures, 1.5, "the migration abandoned before the state timeout")
    assert "disconnected" in str(failures[0]) and robot.inhabitant == "spirit"


def test_the_stand_in_reads_its_options() -> None:
    from cmion_mesh.testing import fatima_peer

    args = fatima_peer.parse_args(["--port", "5", "--prop", "a:1", "--prop", "b:2", "--mute-state", "--retry-interval", "0.5"])
    assert (args.port, args.prop, args.mute_state, args.retry_interval, args.host) == (5, ["a:1", "b:2"], True, 0.5, "127.0.0.1")
    for bad in (["--port"], ["--port", "x"], ["--colour", "red"], ["stray"]):
        with pytest.raises(SystemExit, match=r"usage|not a number"):
            fatima_peer.parse_args(bad)


def test_no_mind_no_migration(two: tuple[Embodiment, FAtiMAConnector, list[Any]], caplog: pytest.LogCaptureFixture) -> None:
    robot, _, failures = two
    unavailable: list[Event] = []
    robot.sim.on_event(unavailable.append, component="fatima", event="MindStateUnavailable")
    wait_for(lambda: robot.presence is not None and "kiosk" in robot.presence.alive(), 5, "the robot sees the kiosk")
    assert robot.migration is not None
    outcome = robot.migration.start("kiosk").result(10)
    # The companion does not leave with an empty mind: the migration is refused, naming the connector.
    assert outcome.status == "rejected" and "no FAtiMA mind is connected to connector 'fatima'" in outcome.reason, outcome
    assert failures and "no FAtiMA mind is connected to connector 'fatima'" in str(failures[0])
    wait_for(lambda: unavailable, 5, "MindStateUnavailable raised")
    assert isinstance(unavailable[0].data, dict) and unavailable[0].data["mind"] == "fatima"
    assert "no FAtiMA mind is connected to connector 'fatima'" in caplog.text
    assert robot.inhabitant == "spirit"


@pytest.mark.parametrize("two", [4], indirect=True)
def test_a_mind_connecting_while_the_companion_leaves_gives_its_state(two: tuple[Embodiment, FAtiMAConnector, list[Any]],
                                                                      caplog: pytest.LogCaptureFixture) -> None:
    robot, mind, _ = two
    wait_for(lambda: robot.presence is not None and "kiosk" in robot.presence.alive(), 5, "the robot sees the kiosk")
    assert robot.migration is not None
    future = robot.migration.start("kiosk")
    wait_for(lambda: "starts leaving with no FAtiMA mind connected" in caplog.text, 5, "the connector waiting for a mind")
    with _peer(mind, state="cafe0123") as peer:
        peer.connect()
        outcome = future.result(10)
        received = peer.received
        assert received.index("OK") < received.index("CMD Stop") < received.index("CMD GET-STATE"), received
        # Its state was packed: the kiosk's refusal is the end of it, not the connector's.
        assert outcome.status == "rejected" and "may not enter 'kiosk'" in outcome.reason, outcome
        peer.wait_for(lambda line: line == "CMD Start")  # resumed here, its mind woken
    assert robot.inhabitant == "spirit"


def test_a_late_state_set_is_not_taken_for_a_later_one(caplog: pytest.LogCaptureFixture) -> None:
    mind = FAtiMAConnector("migrating port:0 stop-wait:0 state-timeout:0.5")
    with MemoryTransport(MemoryNetwork(), "local") as transport, Embodiment("robot", transport=transport, components=[mind]):
        wait_for(lambda: mind.listener is not None, 5, "listening")
        assert mind.listener is not None
        with socket.create_connection(("127.0.0.1", mind.listener.port), timeout=10) as sock, sock.makefile("rb") as lines:
            sock.sendall(b"Spirit Role Spirit\n")
            _lines_until(lines, lambda line: line == b"ENTITY-ADDED Spirit\n")
            mind.sim.call(lambda: mind.restore({"state": "aa01", "agent": "Spirit"}))
            _lines_until(lines, lambda line: line == b"CMD SET-STATE aa01\n")
            # No answer within state-timeout: the mind is started anyway, the state kept.
            _lines_until(lines, lambda line: line == b"CMD Start\n")
            mind.sim.call(lambda: mind.restore({"state": "bb02", "agent": "Spirit"}))
            _lines_until(lines, lambda line: line == b"CMD SET-STATE bb02\n")
            sock.sendall(b"STATE-SET\nlook-at Nobody\n")  # the late answer to the first
            got = _lines_until(lines, lambda line: line == b"ACTION-FINISHED Spirit look-at Nobody\n")
            assert b"CMD Start\n" not in got, got  # not taken for the second's answer
            assert mind.state()["state"] == "bb02", "the second state is still awaited, kept"
            late = next(r.getMessage() for r in caplog.records if "late" in r.getMessage())
            assert "SET-STATE #1 late (#2 is awaited): ignored" in late and "127.0.0.1:" in late, late
            sock.sendall(b"STATE-SET\n")
            _lines_until(lines, lambda line: line == b"CMD Start\n")
            wait_for(lambda: mind.state() == {}, 5, "the second state confirmed")
