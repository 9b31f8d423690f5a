"""The ros2-CLI habits against real daemons (robot, screen, phone in processes of their own): ``peers
NAME``, ``keys``, ``pub`` and ``call``, shell completion with live names through argcomplete's own
protocol, and the paper cuts: ``demo --web``'s attach commands, ``up`` saying where a FAtiMA mind
connects, ``doctor`` naming TLS-only peers."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shlex
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.cli import main as cli
from cmion_mesh.client import MeshClient
from cmion_mesh.messages import Event, encode
from cmion_mesh.procs import Daemon, cli_argv, free_port, unique_mesh
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.tools.demo import Scenario, attach_commands, start_bodies, stop_bodies
from cmion_mesh.transport.base import Sample, TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport
from tests.test_fatima import write_config

pytestmark = pytest.mark.timeout(240)


@pytest.fixture(scope="module")
def bodies(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Scenario]:
    scenario = start_bodies(unique_mesh("habits"), tmp_path_factory.mktemp("bodies"))
    try:
        yield scenario
    finally:
        stop_bodies(scenario)


def net(s: Scenario) -> list[str]:
    """Reach the mesh through the robot's endpoint only: the others are found from there."""
    return ["--mesh", s.mesh, "--no-multicast", "--connect", s.endpoints["robot"]]


def run_cli(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(args))
    return code, out.getvalue(), err.getvalue()


def real_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cli_argv(*args), capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL,
                          env={**os.environ, **(env or {})})


@contextlib.contextmanager
def client_of(s: Scenario) -> Iterator[MeshClient]:
    with ZenohTransport(TransportConfig(connect=(s.endpoints["robot"],), multicast=False)) as t, MeshClient(t, s.mesh) as c:
        yield c


def test_peers_name_says_everything_describe_knows(bodies: Scenario) -> None:
    done = real_cli("peers", "robot", *net(bodies))
    assert done.returncode == 0, done.stderr
    fields = dict(line.split(":", 1) for line in done.stdout.splitlines() if line[:1] != " ")
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    assert fields["embodiment"] == "robot" and fields["inhabitant"] == "spirit" and fields["mesh"] == bodies.mesh
    assert "GoTo *" in fields["actions"] and "Navigation" in fields["competency types"]
    assert set(fields["sees alive"].split(", ")) == {"phone", "robot", "screen"}
    with client_of(bodies) as client:
        client.join("robot")
        described = client.describe("robot")
    assert fields["zenoh id"] == described["zenoh_id"] and fields["pid"] == str(described["pid"])
    typo = real_cli("peers", "robt", *net(bodies), "--timeout", "2")
    assert typo.returncode == 1 and "did you mean 'robot'?" in typo.stderr

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    # The table wraps to the terminal instead of cutting: every action whole, at 80 columns too.
    screen = Terminal()
    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(screen):
        patch.setenv("COLUMNS", "80")
        assert cli.main(["peers", *net(bodies)]) == 0
    table = screen.getvalue()
    assert all(len(line) <= 80 for line in table.splitlines()) and len(table.splitlines()) > 4, table
    flat = " ".join(table.split())
    for action in described["actions"]:
        assert action in flat, (action, table)
    # Into a pipe: one line a row, whole.
    piped = real_cli("peers", *net(bodies)).stdout.splitlines()
    assert len(piped) == 4 and all(action in piped[[r.split()[0] for r in piped].index("robot")] for action in described["actions"])


def test_keys_lists_the_keys_that_exist_with_their_kind(bodies: Scenario) -> None:
    stop = threading.Event()

    def publish() -> None:  # an event published while keys looks
        with ZenohTransport(TransportConfig(connect=(bodies.endpoints["phone"],), multicast=False)) as t:
            for n in range(600):  # bounded: at most 30 s
                t.publish(f"cmion/{bodies.mesh}/phone/ev/sensor/Touched", encode(Event("phone", "sensor", "Touched", None, n, 0.0)))
                if stop.wait(0.05):
                    break

    publisher = threading.Thread(target=publish, name="publisher")
    publisher.start()
    try:
        code, out, err = run_cli("keys", *net(bodies), "--watch", "2", "--json")
    finally:
        stop.set()
        publisher.join()
    assert code == 0, err
    found = {entry["key"].split("/", 2)[2]: (entry["kind"], entry["type"]) for entry in json.loads(out)}
    assert found["robot/bb"] == ("bb container", "container")
    assert found["robot/wm/Kitchen"] == ("wm container (object)", "container")
    assert found["robot/wm/Kitchen/isLocation"] == ("wm property", "property")
    assert found["screen/rq/bb/set_property"] == ("request", "set_property")
    assert found["phone/rq/manager/act"] == ("request", "act")
    assert found["robot/rq/migration/prepare/<sender>"] == ("request (per sender)", "migrate_prepare")
    assert found["@alive/screen"][0] == "liveliness: a daemon alive"
    assert found["@custody/robot/spirit/1"][0] == "liveliness: custody of a companion"
    assert found["phone/ev/sensor/Touched"] == ("event", "event")
    # A pattern keeps what matches it; the table names kinds for people.
    code, out, _ = run_cli("keys", "screen/rq/bb/*", *net(bodies), "--watch", "0")
    lines = out.splitlines()
    assert code == 0 and lines[0].split() == ["KEY", "KIND", "TYPE"]
    assert [line.split()[0] for line in lines[1:]] == [f"screen/rq/bb/{r}" for r in
                                                       ("add_container", "remove_container", "remove_property", "set_property")]


def test_pub_reaches_a_subscriber(bodies: Scenario) -> None:
    heard: list[Sample] = []
    with ZenohTransport(TransportConfig(connect=(bodies.endpoints["screen"],), multicast=False)) as t, \
            t.subscribe(f"cmion/{bodies.mesh}/robot/ev/sensor/*", heard.append):
        done = real_cli("pub", "robot/ev/sensor/Touched", '{"where": "head"}', *net(bodies), "--join", "20")
        assert done.returncode == 0 and "published event Touched" in done.stdout, done
        sample = wait_for(lambda: heard[0] if heard else None, 10, "the publication")
    from cmion_mesh.messages import decode

    event = decode(sample.payload, Event)
    assert (event.embodiment, event.component, event.name, event.data) == ("robot", "sensor", "Touched", {"where": "head"})
    bad = real_cli("pub", "robot/x/y", '{"type": "propertee", "value": 1}', *net(bodies))
    assert bad.returncode == 2 and "did you mean 'property'?" in bad.stderr and bad.stderr.count("\n") == 1


def test_call_sends_a_typed_request_and_decodes_its_answer(bodies: Scenario) -> None:
    done = real_cli("call", "screen/rq/bb/set_property", '{"container": "", "name": "habit", "value": [1, 2]}', *net(bodies), "--json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["status"] == "accepted"
    with client_of(bodies) as client:
        client.join("screen")
        assert client.get_property("screen", "bb", "", "habit").value == [1, 2]
    described = real_cli("call", "robot/rq/embodiment/describe", *net(bodies))
    assert described.returncode == 0 and described.stdout.startswith("accepted\n")
    assert json.loads(described.stdout.split("\n", 1)[1])["name"] == "robot"
    refused = real_cli("call", "screen/rq/bb/remove_property", '{"container": "", "name": "nothing"}', *net(bodies))
    assert refused.returncode == 1 and refused.stdout.startswith("rejected (not_found)")
    typo = real_cli("call", "screen/rq/bb/set_propert", "{}", *net(bodies))
    assert typo.returncode == 2 and "did you mean 'set_property'?" in typo.stderr
    malformed = real_cli("call", "screen/rq/bb/set_property", '{"container": "", "nam": "x"}', *net(bodies))
    assert malformed.returncode == 2 and "missing required field `name`" in malformed.stderr


def complete(line: str, tmp_path: Path, point: int | None = None) -> list[str]:
    """What the shell would offer for ``line`` with the cursor at ``point`` (default: its end),
    through argcomplete's protocol, as bash asks it."""
    out = tmp_path / "completions"
    env = {**os.environ, "_ARGCOMPLETE": "1", "COMP_LINE": line, "COMP_POINT": str(len(line) if point is None else point),
           "_ARGCOMPLETE_IFS": "\n",
           "_ARGCOMPLETE_STDOUT_FILENAME": str(out)}
    done = subprocess.run([sys.executable, "-m", "cmion_mesh.cli"], env=env, capture_output=True, text=True, timeout=30,
                          stdin=subprocess.DEVNULL)
    assert done.returncode == 0, done.stderr
    return sorted(word.strip() for word in out.read_text().split("\n") if word.strip())


def test_completion_offers_live_names(bodies: Scenario, tmp_path: Path) -> None:
    mesh = " ".join(shlex.quote(a) for a in net(bodies))
    assert complete("cmion-mesh pe", tmp_path) == ["peers"]
    assert complete("cmion-mesh peers --js", tmp_path) == ["--json"]
    assert {"phone", "robot", "screen"} <= set(complete(f"cmion-mesh act {mesh} ", tmp_path))
    assert complete(f"cmion-mesh act {mesh} robot G", tmp_path) == ["GoTo", "Greet"]
    assert complete(f"cmion-mesh migrate {mesh} s", tmp_path) == ["spirit"]
    assert complete(f"cmion-mesh migrate spirit {mesh} --to p", tmp_path) == ["phone"]
    assert complete(f"cmion-mesh peers {mesh} sc", tmp_path) == ["screen"]
    assert complete("cmion-mesh record i", tmp_path) == ["info"]
    # A mesh nobody answers for: no names, and the shell gets its answer (bounded join).
    nobody = f"cmion-mesh act --mesh {bodies.mesh} --no-multicast --connect tcp/127.0.0.1:{free_port()} r"
    assert complete(nobody, tmp_path) == []



def test_completion_reads_the_mesh_options_after_the_cursor_and_offers_store_paths(bodies: Scenario, tmp_path: Path) -> None:
    mesh = " ".join(shlex.quote(a) for a in net(bodies))
    before = "cmion-mesh act robot G"
    assert complete(f"{before} {mesh}", tmp_path, point=len(before)) == ["GoTo", "Greet"]
    with client_of(bodies) as client:
        client.join("robot")
        stored = client.lookup("robot", "wm", "", below=True)
    prefix = f"cmion/{bodies.mesh}/robot/wm/"
    paths = sorted(k.removeprefix(prefix) for k in stored if k.startswith(prefix))
    assert paths, "the robot's world model holds something to complete"
    offered = [w for w in complete(f"cmion-mesh wm get {mesh} robot ", tmp_path) if not w.startswith("-")]
    assert offered == paths and "README.md" not in offered, offered  # the store's paths, never the folder's files
    assert complete(f"cmion-mesh wm get {mesh} robot {paths[0][:2]}", tmp_path) == [p for p in paths if p.startswith(paths[0][:2])]
    # a new entity's name: nothing but options
    assert not [w for w in complete(f"cmion-mesh wm add {mesh} robot ", tmp_path) if not w.startswith("-")]


def test_demo_web_prints_commands_that_attach_to_its_mesh(bodies: Scenario, tmp_path: Path) -> None:
    lines = attach_commands(bodies.mesh, bodies.endpoints["robot"], foxglove=True)
    without = attach_commands(bodies.mesh, bodies.endpoints["robot"], foxglove=False)
    assert not [line for line in without if line.strip().startswith("cmion-mesh foxglove")]
    assert any("pip install 'cmion-mesh[foxglove]'" in line for line in without), without
    assert any(line.endswith("-o attach-2.mcap") for line in attach_commands("m", "tcp/127.0.0.1:1", recording="x/attach.mcap"))
    commands = {shlex.split(line)[1]: shlex.split(line)[2:] for line in lines if line.strip().startswith("cmion-mesh")}
    assert set(commands) == {"record", "view", "foxglove", "peers"}
    for argv in commands.values():
        assert argv[argv.index("--mesh") + 1] == bodies.mesh and argv[argv.index("--connect") + 1] == bodies.endpoints["robot"]
    peers = real_cli("peers", *commands["peers"], "--json")
    assert sorted(p["name"] for p in json.loads(peers.stdout)) == ["phone", "robot", "screen"]
    record = commands["record"]
    assert record[record.index("-o") + 1] == "attach.mcap"  # not demo.mcap, which `demo --web --record demo.mcap` writes
    record[record.index("-o") + 1] = str(tmp_path / "attach.mcap")
    with Daemon(cli_argv("record", *record, "--duration", "1"), name="record") as recorder:
        assert "alive: phone, robot, screen" in recorder.wait_line("recording mesh", 30)
        recorder.wait_line("recorded", 30)


def test_up_says_where_a_fatima_mind_connects(tmp_path: Path) -> None:
    mind_port = free_port()
    config = write_config(tmp_path / "robot", "robot", "modular", mind_port)
    with Daemon(cli_argv("up", str(config), "--mesh", unique_mesh(), "--listen", f"tcp/127.0.0.1:{free_port()}",
                         "--no-multicast", "--state-dir", str(tmp_path / "state")), name="robot") as robot:
        robot.wait_line("up in mesh", 30)
        line = robot.wait_line("connector", 1)
    assert f"fatima connector 'fatima' of 'robot' listening at 127.0.0.1:{mind_port}" in line, line


def test_doctor_says_when_the_peers_speak_tls_only(tmp_path: Path) -> None:
    pki = tmp_path / "pki"
    for argv in (["init", str(pki)], ["issue", str(pki), "robot"]):
        assert run_cli("certs", *argv)[0] == 0
    mesh, endpoint = unique_mesh(), f"tcp/127.0.0.1:{free_port()}"
    with Daemon(cli_argv("up", "robot", "--name", "robot", "--mesh", mesh, "--listen", endpoint, "--no-multicast",
                         "--certs", str(pki), "--state-dir", str(tmp_path / "state")), name="robot") as robot:
        robot.wait_line("up in mesh", 30)
        doctor = real_cli("doctor", "--mesh", mesh, "--no-multicast", "--connect", endpoint, "--timeout", "1", "--json")
    assert doctor.returncode == 1
    report: dict[str, Any] = json.loads(doctor.stdout)
    assert f"{endpoint} speaks TLS only" in " ".join(report["problems"]), report["problems"]
    assert any("--certs DIR" in hint for hint in report["hints"]), report["hints"]


def test_commands_that_need_embodiments_look_for_join_seconds_and_say_so() -> None:
    """--join is how long to look for the embodiments; --timeout waits for the outcome after."""
    nobody = ("--mesh", unique_mesh(), "--no-multicast", "--connect", f"tcp/127.0.0.1:{free_port()}", "--join", "1")
    for argv in (["invite", "screen", "--timeout", "2"], ["custody", "resolve", "spirit", "--keep", "robot", "--timeout", "3"]):
        done = real_cli(*argv, *nobody)
        assert done.returncode == 1 and "no embodiment at all found within 1 s" in done.stderr, (argv, done.stderr)
    migrate = real_cli("migrate", "spirit", "--to", "screen", "--timeout", "3", *nobody)
    assert migrate.returncode == 1 and "hosts companion 'spirit'" in migrate.stderr, migrate.stderr


def test_keys_hints_doctor_only_when_no_embodiment_was_reached(bodies: Scenario) -> None:
    idle = real_cli("keys", "robot/nothing/**", *net(bodies), "--watch", "0")
    assert idle.returncode == 0 and "no key matching" in idle.stdout and "doctor" not in idle.stdout, idle.stdout
    nobody = real_cli("keys", "--mesh", unique_mesh(), "--no-multicast", "--connect", f"tcp/127.0.0.1:{free_port()}",
                      "--watch", "0", "--timeout", "1")
    assert "try `cmion-mesh doctor`" in nobody.stdout, nobody.stdout


def test_act_json_prints_the_refusal_on_stdout_too(bodies: Scenario) -> None:
    refused = real_cli("act", "robot", "NoSuchAction", *net(bodies), "--json", "--id", "a1")
    assert refused.returncode == 1 and refused.stderr.count("\n") == 1, refused.stderr
    outcome = json.loads(refused.stdout)
    assert outcome["action_id"] == "a1" and outcome["status"] == "rejected" and outcome["reason"], outcome


def test_a_reader_that_leaves_gets_no_error_line() -> None:
    """`cmion-mesh ... | head`: the reader closes the pipe; the command stops quietly."""
    proc = subprocess.Popen(cli_argv("service", "unit", "robot"), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            stdin=subprocess.DEVNULL)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # gone before the command writes (it is still importing)
    err = proc.stderr.read().decode()
    assert proc.wait(30) == 141 and err == "", err
