"""``cmion-mesh up`` run for months (docs/deploy.md), as real daemons in their own processes on
loopback: sd_notify to a unix datagram socket the test binds as systemd would, metrics scraped
after an action and a migration, a settings file with the command line over it, JSON log lines,
start-up errors as one line and exit code 2 with nothing left behind, and ``service unit``."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ExitCode
from cmion_mesh.procs import Daemon, cli_argv, free_port
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .helpers.notify import NotifySocket

pytestmark = pytest.mark.timeout(90)

Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]


@pytest.fixture
def systemd() -> Iterator[NotifySocket]:
    got = NotifySocket()
    yield got
    got.close()


def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def up(*args: str, env: dict[str, str] | None = None, name: str = "up") -> Daemon:
    return Daemon(cli_argv("up", *args), env=env, name=name)


def run_up(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cli_argv("up", *args), capture_output=True, text=True, timeout=60, env={**os.environ, **(env or {})})


def test_up_under_systemd_is_ready_once_it_holds_its_name_pings_the_watchdog_and_says_stopping(
        systemd: NotifySocket, tmp_path: Path, mesh: str) -> None:
    robot_at = endpoint()
    with up("robot", "--mesh", mesh, "--listen", robot_at, "--no-multicast", "--state-dir", str(tmp_path / "robot"),
            env=systemd.env(), name="robot") as robot:
        ready = systemd.until("READY=1", 30)
        assert ready == [["READY=1", f"STATUS=embodiment 'robot' up in mesh {mesh!r}"]], "READY=1 is the first thing said"
        # A second robot is refused its name: it never says it is ready, and leaves no state folder behind.
        twin_systemd = NotifySocket()
        try:
            twin = run_up("robot", "--mesh", mesh, "--connect", robot_at, "--listen", endpoint(), "--no-multicast",
                          "--state-dir", str(tmp_path / "twin" / "robot"), env=twin_systemd.env())
            assert twin.returncode == ExitCode.FAILED and "embodiment 'robot' is already alive" in twin.stderr, twin
            assert twin_systemd.pending() == [], "refused: never ready"
        finally:
            twin_systemd.close()
        assert not (tmp_path / "twin").exists(), "a refused daemon leaves no state folder (nor lock) behind"
        # The update loop turns: the watchdog is pinged (every 0.5 s for WATCHDOG_USEC=1 s).
        systemd.until("WATCHDOG=1", 10)
        systemd.until("WATCHDOG=1", 10)
        assert robot.stop(signal.SIGTERM, grace=30) == 0
    stopping = systemd.until("STOPPING=1", 5)
    assert all(fields == ["WATCHDOG=1"] for fields in stopping[:-1]), stopping
    assert any("stopped cleanly" in line for line in robot.lines), robot.lines


def scrape(url: str) -> Samples:
    with urllib.request.urlopen(url + "/metrics", timeout=5) as reply:
        assert reply.status == 200
        text = reply.read().decode()
    return {(s.name, frozenset(s.labels.items())): s.value for family in text_string_to_metric_families(text) for s in family.samples}


def value(samples: Samples, name: str, embodiment: str, **labels: str) -> float:
    return samples.get((name, frozenset({"embodiment": embodiment, **labels}.items())), 0.0)


def test_a_daemon_from_a_settings_file_is_scraped_after_an_act_and_a_migration_and_logs_json(tmp_path: Path, mesh: str) -> None:
    robot_at, screen_at = endpoint(), endpoint()
    robot_metrics, screen_metrics = free_port(), free_port()
    etc = tmp_path / "etc"
    etc.mkdir()
    settings = etc / "robot.toml"
    settings.write_text(f'architecture = "robot"\nname = "robot"\nmesh = "not-this-one"\nlisten = ["{robot_at}"]\n'
                        f'connect = ["{screen_at}"]\nmulticast = false\nstate-dir = "state"\nlog-format = "json"\n'
                        f'log-file = "robot.log"\nmetrics = "127.0.0.1:{robot_metrics}"\n')
    with up("screen", "--mesh", mesh, "--listen", screen_at, "--no-multicast", "--state-dir", str(tmp_path / "screen"),
            "--metrics", f"127.0.0.1:{screen_metrics}", name="screen") as screen, \
            up("--settings", str(settings), "--mesh", mesh, name="robot") as robot:
        screen.wait_line("up in mesh", 30)
        robot.wait_line("up in mesh", 30)
        assert (etc / "state" / "daemon.lock").is_file(), "a relative path is the settings file's folder's"
        with ZenohTransport(TransportConfig(connect=(robot_at,), multicast=False)) as transport, \
                MeshClient(transport, mesh) as client:  # the flag's mesh, not the file's
            client.join("robot", timeout=10)
            client.join("screen", timeout=10)
            wait_for(lambda: client.describe("robot", timeout=5).get("inhabitant") == "spirit", 20, "spirit born on the robot")
            assert client.act("robot", "GoTo", ["Kitchen"], timeout=30).status == "succeeded"
            client.migrate("spirit", "screen", timeout=30)
            robot_seen = scrape(f"http://127.0.0.1:{robot_metrics}")
            screen_seen = scrape(f"http://127.0.0.1:{screen_metrics}")
        with urllib.request.urlopen(f"http://127.0.0.1:{robot_metrics}/healthz", timeout=5) as reply:
            assert (reply.status, reply.read()) == (200, b"ok\n")
    assert robot.proc.returncode == 0 and screen.proc.returncode == 0
    assert value(robot_seen, "cmion_mesh_actions_total", "robot", outcome="succeeded") == 1
    assert value(robot_seen, "cmion_mesh_migrations_total", "robot", role="source", outcome="succeeded") == 1
    assert value(robot_seen, "cmion_mesh_migration_duration_seconds_count", "robot", outcome="succeeded") == 1
    assert value(robot_seen, "cmion_mesh_companion_hosted", "robot") == 0
    assert value(screen_seen, "cmion_mesh_migrations_total", "screen", role="target", outcome="arrived") == 1
    assert value(screen_seen, "cmion_mesh_companion_hosted", "screen") == 1
    assert value(robot_seen, "cmion_mesh_peers_alive", "robot") == 1
    # The log file: one JSON object per line, the daemon's own lines among them.
    records = [json.loads(line) for line in (etc / "robot.log").read_text().splitlines()]
    assert records and all({"ts", "level", "logger", "msg"} <= set(r) for r in records)
    said = {r["msg"]: r for r in records if r["logger"] == "cmion_mesh.cli.daemon"}
    assert said["settings read"]["file"] == str(settings)
    assert said["metrics served"]["url"] == f"http://127.0.0.1:{robot_metrics}/metrics"
    assert (said["embodiment up"]["mesh"], said["embodiment up"]["embodiment"], said["embodiment up"]["companion"]) == \
        (mesh, "robot", "spirit")
    assert said["embodiment stopping"]["signal"] == "SIGTERM" and "embodiment stopped cleanly" in said
    assert not any(line.startswith("{") for line in robot.lines), "the log lines went to the file, not to the console"


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A loopback port someone else listens on."""
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        yield other.getsockname()[1]


@pytest.mark.parametrize("problem", ["state-folder", "metrics-port", "web-port", "zenoh-port", "settings-file"])
def test_what_up_cannot_start_with_is_one_line_exit_2_and_nothing_left(problem: str, taken_port: int, tmp_path: Path,
                                                                       mesh: str) -> None:
    state = tmp_path / "state" / "robot"
    args = ["robot", "--mesh", mesh, "--no-multicast", "--state-dir", str(state)]
    settings = tmp_path / "robot.toml"
    settings.write_text('name = "robot"\nlog-level = "loud"\n')
    args, says = {
        "state-folder": (["robot", "--mesh", mesh, "--no-multicast", "--state-dir", "/proc/forbidden"],
                         "error: state folder /proc/forbidden cannot be made: No such file or directory"),
        "metrics-port": ([*args, "--metrics", f"127.0.0.1:{taken_port}"],
                         f"error: metrics server cannot listen on 127.0.0.1:{taken_port}: Address already in use"),
        "web-port": ([*args, "--web", f"127.0.0.1:{taken_port}"],
                     f"error: web server cannot listen on http://127.0.0.1:{taken_port}: Address already in use"),
        "zenoh-port": ([*args, "--listen", f"tcp/127.0.0.1:{taken_port}"],
                       f"error: zenoh cannot listen on tcp/127.0.0.1:{taken_port}: Address already in use"),
        "settings-file": ([*args, "--settings", str(settings)],
                          f"error: {settings}:2: 'log-level' must be one of debug, info, warning, error, not str 'loud'"),
    }[problem]
    done = run_up(*args)
    assert (done.returncode, done.stderr, done.stdout) == (ExitCode.USAGE, says + "\n", ""), done
    assert not (tmp_path / "state").exists(), "nothing left behind"


def test_service_unit_prints_a_unit_systemd_accepts(tmp_path: Path) -> None:
    done = subprocess.run(cli_argv("service", "unit", "robot", "--mesh", "home", "--metrics", "127.0.0.1:9464"),
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stderr == "", done
    exec_start = next(line for line in done.stdout.splitlines() if line.startswith("ExecStart="))
    assert exec_start.endswith(" up --name robot --settings /etc/cmion-mesh/robot.toml --state-dir %S/cmion-mesh/robot "
                               "--mesh home --metrics 127.0.0.1:9464"), exec_start
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd is not installed: systemd-analyze verify is not available")
    path = tmp_path / "cmion-mesh-robot.service"
    path.write_text(done.stdout)
    verified = subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True, text=True, timeout=60, check=False)
    said = [line for line in (verified.stdout + verified.stderr).splitlines() if path.name in line]
    assert (verified.returncode, said) == (0, []), verified


def test_service_unit_names_what_it_refuses() -> None:
    done = subprocess.run(cli_argv("service", "unit", "no/such", "--settings", "relative.toml"), capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == ExitCode.USAGE and done.stderr.count("\n") == 1 and "no/such" in done.stderr, done
