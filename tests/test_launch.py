"""``cmion-mesh launch``: the file checked with its lines, the Spirit of the Building started as three
daemons that find each other, and every child stopped: on SIGINT, on a failure, and when the
launcher itself is SIGKILLed."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from cmion_mesh import procs
from cmion_mesh.cli.main import main
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError
from cmion_mesh.procs import Daemon, cli_argv
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.tools import launch
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

pytestmark = pytest.mark.timeout(120)
BODIES = {"robot", "screen", "phone"}


def running(pid: int) -> bool:
    """Whether ``pid`` is a live process (a zombie left for a reaper is not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return any(running(int(p.name)) for p in Path("/proc").glob("[0-9]*") if _pgid(p) == pgid)


def _pgid(proc: Path) -> int | None:
    try:
        return int((proc / "stat").read_text().rsplit(")", 1)[1].split()[2])
    except (OSError, ValueError, IndexError):
        return None


def started_pids(lines: list[str]) -> dict[str, int]:
    found = (re.search(r"started (\S+) \(pid (\d+)\)", line) for line in lines)
    return {m.group(1): int(m.group(2)) for m in found if m}


def test_a_bad_file_is_refused_with_every_problem_by_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.launch.toml"
    bad.write_text('[launch]\non_failure = "explode"\n\n[[embodiment]]\nname = "robot"\nconfg = "robot"\n\n'
                   '[[process]]\nname = "a"\ncommand = ["true"]\nafter = ["robott"]\n')
    with pytest.raises(ConfigError) as caught:
        launch.load(bad)
    text = str(caught.value)
    assert f"{bad}:2: [launch]: 'on_failure' must be one of stop_all, continue, restart, not 'explode'" in text
    assert f"{bad}:6: [[embodiment]] #1: unknown key 'confg' (did you mean 'config'?)" in text
    assert f"{bad}:11: [[process]] 'a': after 'robott': no process of that name (did you mean 'robot'?)" in text
    broken = tmp_path / "broken.toml"
    broken.write_text('[launch]\nmesh = "x\n')
    assert main(["launch", str(broken)]) == 2
    assert f"{broken}:2: not valid TOML" in capsys.readouterr().err
    # the shipped file checks, and says what it would run
    assert main(["launch", "spirit", "--check", "--json", "--mesh", "checked"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert [p["name"] for p in plan["processes"]] == ["robot", "screen", "phone"]
    assert all(p["command"][:2] == ["cmion-mesh", "up"] and "checked" in p["command"] for p in plan["processes"])


ONE_PROCESS = '[[process]]\nname = "p"\ncommand = ["true"]\n'


@pytest.mark.parametrize(("text", "line", "says"), [
    ("x = " + "[" * 100_000 + "]" * 100_000 + "\n", 1, "too deep for a launch file: arrays or inline tables nested more than"),
    (ONE_PROCESS + "x = " + "{a = " * 50_000 + "1" + "}" * 50_000 + "\n", 4, "too deep for a launch file: arrays or inline"),
    ("[launch]\nmesh" + ".a" * 100_000 + " = 1\n" + ONE_PROCESS, 2, "too deep for a launch file: a dotted key of more than"),
    ("[" + ".".join(["a"] * 100_000) + "]\n", 1, "too deep for a launch file: a dotted key of more than"),
], ids=["arrays", "inline-tables", "dotted-key", "table-header"])
def test_a_file_nested_too_deep_exits_2_naming_the_file_and_line(tmp_path: Path, text: str, line: int, says: str) -> None:
    """Python's TOML reader recursed to a RecursionError (an internal error, exit 1), or took
    minutes over a long dotted key; the launcher says what is wrong with the file instead."""
    file = tmp_path / "deep.launch.toml"
    file.write_text(text)
    result = subprocess.run(cli_argv("launch", str(file)), capture_output=True, text=True, timeout=60)
    assert (result.returncode, result.stdout) == (2, ""), result.stderr[-400:]
    assert result.stderr.startswith(f"error: {file}:{line}: {says}") and result.stderr.count("\n") == 1, result.stderr[-400:]


def test_a_long_chain_of_after_is_ordered_not_recursed(tmp_path: Path) -> None:
    """Each process after the next one: the order was found by recursion, one level per process."""
    file = tmp_path / "chain.launch.toml"
    count = 3000
    file.write_text("".join(f'[[process]]\nname = "p{i}"\ncommand = ["true"]\nafter = ["p{i + 1}"]\n\n' for i in range(count))
                    + f'[[process]]\nname = "p{count}"\ncommand = ["true"]\n')
    result = subprocess.run(cli_argv("launch", str(file), "--check", "--json"), capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr[-400:]
    names = [p["name"] for p in json.loads(result.stdout)["processes"]]
    assert names == [f"p{i}" for i in range(count, -1, -1)]  # each after the one it waits for


@pytest.mark.parametrize(("content", "line", "says"), [
    (b'[launch]\nmesh = "caf\xe9"\n' + ONE_PROCESS.encode(), 2, "not UTF-8 (byte 0xe9: invalid continuation byte)"),
    (b'[launch]\nmesh = "x\n', 2, "not valid TOML: Illegal character"),
    (b'[launch]\nrestarts = "3"\n' + ONE_PROCESS.encode(), 2, "[launch]: 'restarts' must be a whole number >= 0, not str '3'"),
    (b'[launch]\nstop_timeout = inf\n' + ONE_PROCESS.encode(), 2, "[launch]: 'stop_timeout' must be a positive number of seconds"),
    (b'[launch]\nready_timeout = 1e300\n' + ONE_PROCESS.encode(), 2, "[launch]: 'ready_timeout' must be a positive number"),
    (b'[launch]\nwat = 1\n' + ONE_PROCESS.encode(), 2, "[launch]: unknown key 'wat'"),
    (b'[[process]]\nname = "p"\ncommand = ["echo", "a\\u0000b"]\n', 3, "[[process]] #1: 'command' must be a list of strings (without NUL"),
    (b'[[process]]\nname = "p"\ncommand = ["true"]\nenv = { "A=B" = "x" }\n', 4,
     "[[process]] #1: 'env' must be a table of strings (names without '='"),
    (b'[[process]]\nname = "p"\ncommand = ["true"]\ncwd = "\\u0000"\n', 4,
     "[[process]] #1: 'cwd' must be a string (without NUL characters)"),
    (b"# " + b"x" * launch.MAX_FILE + b"\n" + ONE_PROCESS.encode(), None, "the launch file is larger than 1024 KiB"),
], ids=["not-utf8", "toml-syntax", "wrong-type", "infinite-timeout", "huge-timeout", "unknown-key", "nul-in-command",
        "env-name", "nul-in-cwd", "too-large"])
def test_every_kind_of_bad_file_exits_2_with_one_line_naming_it(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                 content: bytes, line: int | None, says: str) -> None:
    file = tmp_path / "bad.launch.toml"
    file.write_bytes(content)
    assert main(["launch", str(file)]) == 2
    captured = capsys.readouterr()
    where = f"{file}:{line}" if line is not None else f"{file}"
    assert captured.out == "" and captured.err.startswith(f"error: {where}: {says}") and captured.err.count("\n") == 1, captured.err


def test_a_launch_file_that_cannot_be_read_exits_2_naming_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    too_long = str(tmp_path / ("x" * 5000))
    assert main(["launch", too_long]) == 2
    assert capsys.readouterr().err == f"error: {too_long}: cannot read the launch file: File name too long\n"
    with pytest.raises(ConfigError, match=r"^.*: cannot read the launch file: Is a directory$"):
        launch.load(tmp_path)  # a folder where the file should be (the CLI names it as no launch file at all)


def test_spirit_starts_three_daemons_that_find_each_other_and_sigint_stops_them_all(mesh: str) -> None:
    with Daemon(cli_argv("launch", "spirit", "--mesh", mesh), name="launch") as launcher:
        for body in BODIES:
            launcher.wait_line(f"{body} is ready", 60)
        pids = started_pids(launcher.lines)
        assert set(pids) == BODIES
        endpoints = tuple(sorted({m for line in launcher.lines for m in re.findall(r"--listen (tcp/127\.0\.0\.1:\d+)", line)}))
        assert len(endpoints) == 3
        assert any(line.startswith("robot  | ") for line in launcher.lines), "each line prefixed with its process's name"
        with ZenohTransport(TransportConfig(connect=endpoints, multicast=False)) as transport, MeshClient(transport, mesh) as client:
            for body in BODIES:
                client.join(body, timeout=30)
            wait_for(lambda: all(set(client.describe(b, timeout=2).get("alive", ())) >= BODIES for b in BODIES), 30,
                     "each of the three daemons sees the other two")
        net = ["--mesh", mesh, "--no-multicast", *(x for e in endpoints for x in ("--connect", e))]
        tokens = subprocess.run(cli_argv("echo", "@alive/*", "--count", "3", "--json", *net), capture_output=True, text=True,
                                timeout=60)
        assert tokens.returncode == 0, tokens.stderr
        assert {json.loads(line)["key"] for line in tokens.stdout.splitlines()} == {f"cmion/{mesh}/@alive/{b}" for b in BODIES}
        # what the launcher tells the user to run reaches the mesh
        told = launcher.wait_line("all ready; reach this mesh with: cmion-mesh peers ", 30).split("cmion-mesh peers ", 1)[1]
        peers = subprocess.run(cli_argv("peers", "--json", *told.split()), capture_output=True, text=True, timeout=60)
        assert peers.returncode == 0, peers.stderr
        assert {p["name"] for p in json.loads(peers.stdout)} == BODIES
        launcher.proc.send_signal(signal.SIGINT)
        assert launcher.proc.wait(60) == 0, launcher.lines
    assert any("all stopped (robot exit code 0, screen exit code 0, phone exit code 0)" in line for line in launcher.lines)
    for name, pid in pids.items():
        assert not running(pid) and not group_alive(pid), f"{name} (pid {pid}) outlived the launcher"


def test_a_failure_stops_everything_even_a_child_that_ignores_sigint(tmp_path: Path) -> None:
    file = tmp_path / "fail.launch.toml"
    file.write_text('[launch]\nstop_timeout = 1\n\n[[process]]\nname = "sleeper"\ncommand = ["sleep", "300"]\n\n'
                    '[[process]]\nname = "stubborn"\nready = "ignoring"\ncommand = ["python3", "-c", '
                    '"import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); print(\'ignoring\', flush=True); '
                    'time.sleep(300)"]\n\n[[process]]\nname = "failer"\nafter = ["stubborn"]\ncommand = ["sh", "-c", "exit 3"]\n')
    result = subprocess.run(cli_argv("launch", str(file)), capture_output=True, text=True, timeout=60)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "failer exited with exit code 3: stopping everything" in result.stderr
    assert "stubborn did not stop within 1 s: killed" in result.stderr
    pids = started_pids(result.stdout.splitlines())
    assert set(pids) == {"sleeper", "stubborn", "failer"}
    assert not any(running(pid) for pid in pids.values())
    file.write_text('[launch]\non_failure = "restart"\nrestarts = 1\n\n[[process]]\nname = "failer"\ncommand = ["sh", "-c", "exit 4"]\n')
    result = subprocess.run(cli_argv("launch", str(file)), capture_output=True, text=True, timeout=60)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "failer exited with exit code 4: restarting in 1 s (restart 1 of 1)" in result.stderr
    assert "failer exited with exit code 4 after 1 restarts: stopping everything" in result.stderr
    assert len(started_pids(result.stdout.splitlines())) == 1 and result.stdout.count("started failer") == 2


def test_a_sigkilled_launcher_leaves_no_child(tmp_path: Path) -> None:
    file = tmp_path / "sleep.launch.toml"
    file.write_text('[[process]]\nname = "sleeper"\ncommand = ["sleep", "300"]\n')
    with Daemon(cli_argv("launch", str(file)), name="launch") as launcher:
        line = launcher.wait_line("started sleeper", 30)
        pid = int(re.search(r"pid (\d+)", line).group(1))  # type: ignore[union-attr]
        assert running(pid)
        launcher.kill()  # SIGKILL: no cleanup runs in the launcher
    wait_for(lambda: not running(pid), 10, f"the sleeper (pid {pid}) ended with its launcher")


def test_a_sigkilled_demo_style_parent_leaves_no_daemon() -> None:
    """``procs.Daemon(die_with_parent=True)``, as the demo starts its daemons: they go with their parent."""
    parent_code = ("import sys; from cmion_mesh.procs import Daemon\n"
                   "d = Daemon(['sleep', '300'], name='sleeper', die_with_parent=True)\n"
                   "print(d.proc.pid, flush=True); sys.stdin.read()")
    with Daemon([sys.executable, "-c", parent_code], name="parent", stdin=True) as parent:
        pid = int(parent.wait_line("", 30))  # its first line: the daemon's pid
        assert running(pid)
        parent.kill()
    wait_for(lambda: not running(pid), 10, f"the parent's daemon (pid {pid}) ended with it")


def test_free_ports_come_from_below_the_range_outgoing_connections_take() -> None:
    """A port handed to a daemon about to listen must not be one that any outgoing connection can
    take before the daemon binds it (a test's daemon then failed: "Address already in use")."""
    floor = procs.ephemeral_floor()
    if floor <= procs.PORTS_FROM:
        pytest.skip(f"no room below this kernel's ephemeral range (from {floor})")
    ports = [procs.free_port() for _ in range(50)]
    assert len(set(ports)) == 50, "never the same port twice"
    assert all(procs.PORTS_FROM <= port < floor for port in ports), (floor, ports)
