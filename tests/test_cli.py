"""The daemon and the command line, each in separate processes over real zenoh (loopback only)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import OutcomeUnknown
from cmion_mesh.messages import AddContainer, Event, MindMessage, MindState, Sleep, Wake
from cmion_mesh.procs import Daemon, cli_argv, free_port
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .conftest import CMION_2011, start_daemon

pytestmark = pytest.mark.timeout(120)
CMION_TEST = embodiment_dir("cmion_test")


def cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cli_argv(*args), capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL)


def net(mesh: str, endpoint: str) -> list[str]:
    return ["--mesh", mesh, "--connect", endpoint, "--no-multicast"]


@pytest.fixture
def two(mesh: str) -> Iterator[tuple[Daemon, Daemon, str]]:
    """The CMION test embodiment and a second, bare embodiment joined to it."""
    a, endpoint = start_daemon(mesh, "alpha", "--rules", str(CMION_TEST / "CompManagerRulesTest.xml"),
                               "--library", str(CMION_TEST / "CompetencyLibrary.xml"))
    with a:
        b = Daemon(cli_argv("up", "--name", "beta", "--mesh", mesh, "--connect", endpoint, "--no-multicast"), name="beta")
        with b:
            b.wait_line("up in mesh", 20)
            yield a, b, endpoint


def peers(mesh: str, endpoint: str) -> list[dict[str, Any]]:
    result = cli("peers", "--json", "--timeout", "1", *net(mesh, endpoint))
    assert result.returncode == 0, result.stderr
    found: list[dict[str, Any]] = json.loads(result.stdout)
    return found


def test_daemons_find_each_other_and_a_killed_one_vanishes(two: tuple[Daemon, Daemon, str], mesh: str) -> None:
    _, b, endpoint = two
    listing = wait_for(lambda: (p := peers(mesh, endpoint)) and len(p) == 2 and p, 20, "both daemons listed")
    by_name = {p["name"]: p for p in listing}
    assert "TestType4" in by_name["alpha"]["competency_types"]
    assert "TestAction test" in by_name["alpha"]["actions"] and by_name["alpha"]["inhabitant"] is None
    assert by_name["beta"]["competency_types"] == ["Migration"] and by_name["beta"]["version"]
    with ZenohTransport(TransportConfig(connect=(endpoint,), multicast=False)) as t:
        client = MeshClient(t, mesh)
        wait_for(lambda: set(client.embodiments()) == {"alpha", "beta"}, 10, "liveliness of both")
        b.kill()
        wait_for(lambda: client.embodiments() == ["alpha"], 10, "beta vanishes once killed")
    table = cli("peers", *net(mesh, endpoint))
    assert "alpha" in table.stdout and "beta" not in table.stdout and "INHABITANT" in table.stdout


def test_act_cancel_and_events_through_the_cli(two: tuple[Daemon, Daemon, str], mesh: str) -> None:
    _, _, endpoint = two
    follower = Daemon(cli_argv("events", "--follow", "--json", "--embodiment", "alpha", "--component", "manager",
                               "--count", "6", *net(mesh, endpoint)), name="events")
    with follower:
        # the follower's subscription needs a moment to be declared: act until it hears something
        ok = cli("act", "alpha", "TestAction", "test", "--json", *net(mesh, endpoint))
        assert ok.returncode == 0, ok.stderr
        report = json.loads(ok.stdout)
        assert report["status"] == "succeeded" and report["rule"].endswith(":47")
        failed = cli("act", "alpha", "TestAction", "a", "b", *net(mesh, endpoint))
        assert failed.returncode == 1 and "no rule matches action 'TestAction a b'" in failed.stderr
        assert "Traceback" not in failed.stderr and len(failed.stderr.strip().splitlines()) == 1
        wait_for(lambda: cli("act", "alpha", "TestAction2", *net(mesh, endpoint)).returncode == 0 and
                 any("ActionSucceeded" in line for line in follower.lines), 30, "events heard by the follower")
        unknown = cli("cancel", "alpha", "nope", *net(mesh, endpoint))
        assert unknown.returncode == 1 and "no running action with id 'nope'" in unknown.stderr
    events = [json.loads(line) for line in follower.lines if line.startswith("{")]
    assert {e["name"] for e in events} >= {"ActionStarted", "ActionSucceeded"}


def test_bb_and_wm_commands(mesh: str) -> None:
    daemon, endpoint = start_daemon(mesh, "robot", "--world-model", str(CMION_2011 / "worldModelInit.xml"))
    with daemon:
        wait_for(lambda: cli("wm", "get", "robot", "UserA/speaksEnglish", *net(mesh, endpoint)).returncode == 0, 20, "wm answers")
        got = cli("wm", "get", "robot", "UserA/speaksEnglish", "--json", *net(mesh, endpoint))
        assert json.loads(got.stdout) == {f"cmion/{mesh}/robot/wm/UserA/speaksEnglish": {"type": "property", "value": "True",
                                                                                       "persistent": True}}
        assert cli("bb", "set", "robot", "battery", "0.5", "--persistent", *net(mesh, endpoint)).returncode == 0
        tree = cli("bb", "tree", "robot", *net(mesh, endpoint))
        assert "battery" in tree.stdout and "0.5" in tree.stdout and "(persistent)" in tree.stdout
        bad = cli("bb", "set", "robot", "nowhere/x", "1", *net(mesh, endpoint))
        assert bad.returncode == 1 and "no container 'nowhere'" in bad.stderr
        wm_tree = cli("wm", "tree", "robot", *net(mesh, endpoint))
        assert "UserB" in wm_tree.stdout and "[agent]" in wm_tree.stdout


def test_remote_mind_drives_a_daemon(two: tuple[Daemon, Daemon, str], mesh: str) -> None:
    _, _, endpoint = two
    mind = Daemon(cli_argv("serve-mind", "tests.helpers.remote_helpers:EagerMind", "--embodiment", "alpha",
                           "--parameters", "eager,TestAction2", *net(mesh, endpoint)), name="mind")
    with mind, ZenohTransport(TransportConfig(connect=(endpoint,), multicast=False)) as t:
        mind.wait_line("serving embodiment", 20)
        client = MeshClient(t, mesh)
        seen: list[Event] = []
        client.events(seen.append, embodiment="alpha", component="eager")
        # a raw message makes the mind act; the mind learns the outcome and tells us by an event
        def mind_acted() -> bool:
            try:
                asked = client.request("alpha", "eager", "message", MindMessage({"action": "TestAction", "parameters": ["test"]}),
                                       timeout=2)
            except OutcomeUnknown:
                return False  # the mind's queryable is not known to this session yet
            return asked.status == "accepted" and any(e.name == "MindSaw" and e.data["status"] == "succeeded" for e in seen)

        wait_for(mind_acted, 30, "the remote mind's action succeeded")
        # it perceives world-model changes, with the persistent flag
        client.write("alpha", "wm", AddContainer("", "Guest", "agent"))
        client.set_property("alpha", "wm", "Guest", "name", "Ada", persistent=True)
        wait_for(lambda: any(e.name == "MindPerceived" and e.data == {"entity": "Guest", "name": "name", "value": "Ada",
                                                                      "persistent": True} for e in seen), 10, "perception")
        assert client.request("alpha", "eager", "sleep", Sleep()).value == {"awake": False}
        refused = client.request("alpha", "eager", "message", MindMessage({"action": "TestAction2"}))
        assert refused.status == "rejected" and "asleep" in refused.reason
        assert client.request("alpha", "eager", "wake", Wake()).value == {"awake": True}
        assert "TestAction:succeeded" in client.request("alpha", "eager", "state", MindState()).value["outcomes"]


def test_sigterm_stops_the_daemon_cleanly(mesh: str) -> None:
    daemon, _ = start_daemon(mesh, "robot", "--rules", str(CMION_TEST / "CompManagerRulesTest.xml"),
                             "--library", str(CMION_TEST / "CompetencyLibrary.xml"))
    code = daemon.stop(signal.SIGTERM)
    assert code == 0, "\n".join(daemon.lines)
    assert any("stopped cleanly (no thread left)" in line for line in daemon.lines)
    assert daemon.proc.poll() == 0


def test_up_from_an_architecture_configuration(mesh: str) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Daemon(cli_argv("up", str(CMION_TEST / "ArchitectureConfiguration.xml"), "--mesh", mesh, "--listen", endpoint,
                         "--no-multicast"), name="cmion_test") as daemon:
        line = daemon.wait_line("up in mesh", 20)
        assert "'cmion_test'" in line and "7 competencies, 5 rules" in line, "CMION's 6 and 4, plus the built-in Migration"


BROKEN = {
    "cycle.xml": ('<CompetencyManagerRules><Rule><MindAction Name="A"/><CompetencyExecutionPlan>\n'
                  '<Competency ID="1" Type="T" Dependency="2"/>\n<Competency ID="2" Type="T" Dependency="1"/>\n'
                  '</CompetencyExecutionPlan></Rule></CompetencyManagerRules>', "cycle"),
    "unknown_dep.xml": ('<CompetencyManagerRules><Rule><MindAction Name="A"/><CompetencyExecutionPlan>\n'
                        '<Competency ID="1" Type="T" Dependency="9"/>\n</CompetencyExecutionPlan></Rule></CompetencyManagerRules>', "9"),
    "no_type.xml": ('<CompetencyManagerRules><Rule><MindAction Name="A"/><CompetencyExecutionPlan>\n'
                    '<Competency ID="1"/>\n</CompetencyExecutionPlan></Rule></CompetencyManagerRules>', "Type"),
    "bad_library.xml": ('<CompetencyLibrary>\n<Competency ClassName="nowhere.module:X"/>\n</CompetencyLibrary>', "nowhere.module"),
    "bad_wm.xml": ('<WorldModel>\n<Agent Name="a/b"/>\n</WorldModel>', "'a/b'"),
    "xxe.xml": ('<!DOCTYPE WorldModel [<!ENTITY x SYSTEM "file:///etc/passwd">]>\n<WorldModel>&x;</WorldModel>', "DTD subset"),
    "syntax.xml": ('<WorldModel>\n<Agent Name="a">\n</WorldModel>', "syntax"),
    "unknown_kind.xml": ("<Something/>", "unknown document kind"),
}


def test_validate_catches_each_kind_of_broken_file(tmp_path: Path) -> None:
    good = cli("validate", *(str(p) for p in sorted(CMION_TEST.glob("*.xml"))), str(CMION_2011 / "CompManagerRulesExample.xml"))
    assert good.returncode == 0, good.stderr
    assert "ArchitectureConfiguration" in good.stdout
    for name, (text, needle) in BROKEN.items():
        path = tmp_path / name
        path.write_text(text)
        result = cli("validate", str(path))
        assert result.returncode == 1, (name, result.stdout)
        assert f"{path}:" in result.stderr and needle.lower() in result.stderr.lower(), (name, result.stderr)
        assert "Traceback" not in result.stderr
    # an architecture whose rules need a type its library does not provide: loaded, as in CMION (its
    # action fails when it runs), so a warning, and an error with --strict
    arch = tmp_path / "arch"
    arch.mkdir()
    (arch / "rules.xml").write_text('<CompetencyManagerRules><Rule><MindAction Name="Fly"/><CompetencyExecutionPlan>\n'
                                    '<Competency ID="1" Type="Wings"/>\n</CompetencyExecutionPlan></Rule></CompetencyManagerRules>')
    (arch / "lib.xml").write_text("<CompetencyLibrary/>")
    (arch / "ArchitectureConfiguration.xml").write_text(
        '<ArchitectureConfiguration CompetencyManagerRulesFile="rules.xml" CompetencyLibraryConfigurationFile="lib.xml"/>')
    result = cli("validate", str(arch / "ArchitectureConfiguration.xml"))
    assert result.returncode == 0 and "warning: " in result.stderr and "'Wings'" in result.stderr, result.stderr
    assert "rules.xml:2" in result.stderr, result.stderr
    result = cli("validate", "--strict", str(arch / "ArchitectureConfiguration.xml"))
    assert result.returncode == 1 and "error: " in result.stderr and "'Wings'" in result.stderr, result.stderr
    missing = cli("validate", str(tmp_path / "absent.xml"))
    assert missing.returncode == 2 and "absent.xml" in missing.stderr
    assert sys.executable
