"""The demo's path as a test: three daemons, four hops, the identity checked after each."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import tempfile
from pathlib import Path

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.procs import Daemon, cli_argv
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.tools.demo import GUEST, STATE_PREFIX, Timeline, mind_state, remove_stale_state, run_scenario, start_bodies, stop_bodies
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

pytestmark = pytest.mark.timeout(180)


def test_spirit_of_the_building(tmp_path: Path, mesh: str) -> None:
    lines: list[str] = []
    scenario = start_bodies(mesh, tmp_path)
    try:
        with ZenohTransport(TransportConfig(connect=tuple(scenario.endpoints.values()), multicast=False)) as t:
            client = MeshClient(t, mesh)
            run_scenario(client, scenario, Timeline(lines.append), timeout=90)
            assert [h.embodiment for h in scenario.hops] == ["screen", "phone", "robot"]
            assert [h.epoch for h in scenario.hops] == [2, 3, 4]
            screen, phone, robot = (h.mind for h in scenario.hops)
            # on arrival at the screen it carries the goal, and why it came (the guest is expected)
            assert [g["name"] for g in screen["goals"]["pending"]] == [f"welcome {GUEST}"]
            assert screen["beliefs"][GUEST]["expected"] is True
            assert screen["beliefs"]["Self"]["embodiment"] == "screen", "body knowledge comes from the new world model"
            # at the phone it remembers that the guest was confirmed and welcomed at the screen
            assert phone["beliefs"][GUEST].items() >= {"confirmed": True, "welcomed": True}.items()
            assert phone["beliefs"]["Self"]["embodiment"] == "phone"
            # back home: the whole visit is in its memory, and every earlier memory is kept
            assert robot["beliefs"][GUEST]["accompanied"] is True
            assert robot["goals"]["pending"] == [] or all(g["name"] != f"welcome {GUEST}" for g in robot["goals"]["pending"])
            for earlier, later in ((screen, phone), (phone, robot)):
                assert later["memory"][: len(earlier["memory"])] == earlier["memory"], "memories are carried, never lost"
            final = mind_state(client, "robot")
            assert any(e["kind"] == "goal_achieved" for e in final["memory"])
            inhabitants = {d["name"]: d["inhabitant"] for d in client.describe_all(timeout=1.0)}
            assert inhabitants == {"robot": "spirit", "screen": None, "phone": None}
    finally:
        stop_bodies(scenario)
    assert any("goal 'welcome Guest' achieved" in line for line in lines)


def test_demo_command_runs_and_ends_by_itself_recording_its_mesh(tmp_path: Path) -> None:
    recording = tmp_path / "demo.mcap"
    result = subprocess.run(cli_argv("demo", "--record", str(recording)), capture_output=True, text=True, timeout=150,
                            stdin=subprocess.DEVNULL)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "journey: robot -> screen -> phone -> robot" in result.stdout
    assert result.stdout.rstrip().endswith("done")
    # The recording holds the story the demo told: three migrations, each with its four steps.
    summary = json.loads(subprocess.run(cli_argv("record", "info", str(recording), "--json"), capture_output=True, text=True,
                                        timeout=60, check=True).stdout)
    assert not summary["truncated"] and summary["embodiments"] == ["phone", "robot", "screen"], summary
    hops = [(m["source"], m["target"], m["outcome"], len(m["steps"])) for m in summary["migrations"]]
    assert hops == [("robot", "screen", "succeeded", 4), ("screen", "phone", "succeeded", 4), ("phone", "robot", "succeeded", 4)]
    assert f"recorded {summary['messages']} messages to {recording}" in result.stdout
    # A recording is evidence: a second demo refuses to write over it, before starting anything.
    again = subprocess.run(cli_argv("demo", "--record", str(recording)), capture_output=True, text=True, timeout=60,
                           stdin=subprocess.DEVNULL)
    assert again.returncode == 2 and "exists already" in again.stderr and "starting" not in again.stdout, again


def processes_naming(text: str) -> list[int]:
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if text.encode() in cmdline.read_bytes():
                found.append(int(cmdline.parent.name))
        except OSError:  # gone while we looked
            continue
    return found


def test_a_terminated_demo_stops_its_daemons() -> None:
    """Its daemons run in sessions of their own (a Ctrl-C at the terminal must not reach them
    half-way): SIGTERM to the demo must stop them as Ctrl-C does."""
    demo = Daemon(cli_argv("demo"), name="demo")
    with demo:
        line = demo.wait_line("starting three embodiment daemons", 60)
        mesh = re.search(r"in mesh '([^']+)'", line)
        assert mesh is not None, line
        demo.wait_line("found each other", 60)
        assert len(processes_naming(mesh.group(1))) >= 3
        assert demo.stop(signal.SIGTERM, grace=60) == 143, demo.lines  # not killed: stopped by SIGTERM, as a shell says it
        assert any("stopping the daemons" in seen for seen in demo.lines), demo.lines
    wait_for(lambda: not processes_naming(mesh.group(1)), 30, f"no process left of mesh {mesh.group(1)}")


#: Runs the rest of its command line with SIGINT ignored, as a shell script's background job is.
IGNORING_SIGINT = "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); os.execv(sys.argv[1], sys.argv[1:])"


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_background_web_demo_stops_on_a_signal_while_it_waits_for_the_visitor(sig: signal.Signals) -> None:
    """A background job inherits SIGINT ignored: the demo stops all the same, with the shell's code."""
    argv = cli_argv("demo", "--web")
    demo = Daemon([argv[0], "-c", IGNORING_SIGINT, *argv], name="demo")
    with demo:
        demo.wait_line("say \"I am here\"", 90)  # the story waits for a person at the screen's page
        demo.proc.send_signal(sig)
        demo.wait_line("stopping the daemons", 5)
        assert demo.proc.wait(60) == 128 + sig, demo.lines
        demo.stop()
        assert demo.lines[-1].endswith("] done"), demo.lines


def test_a_killed_web_demo_leaves_no_view_and_its_state_goes_with_the_next_demo(tmp_path: Path) -> None:
    """SIGKILL gives the demo no chance to stop anything: its children must go by themselves (the
    kernel tells them), and its state folder is removed by the next demo."""
    demo = Daemon(cli_argv("demo", "--web"), name="demo")
    with demo:
        line = demo.wait_line("starting three embodiment daemons", 60)
        mesh = re.search(r"in mesh '([^']+)'", line)
        assert mesh is not None, line
        demo.wait_line("view: http", 60)
        assert len(processes_naming(mesh.group(1))) >= 4  # three daemons and the view
        state = list(Path(tempfile.gettempdir()).glob(f"{STATE_PREFIX}{demo.proc.pid}-*"))
        assert len(state) == 1, state
        demo.kill()
    wait_for(lambda: not processes_naming(mesh.group(1)), 30, f"no process left of mesh {mesh.group(1)}")
    assert state[0].is_dir()  # nobody removed it: the demo was killed
    alive = tmp_path / f"{STATE_PREFIX}{os.getpid()}-x"  # a running demo's: kept
    alive.mkdir()
    assert state[0] in remove_stale_state() and not state[0].exists()
    assert remove_stale_state(str(tmp_path)) == [] and alive.is_dir()
