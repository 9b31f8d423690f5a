"""docs/tutorial.md runs: its commands (examples/blink/tutorial.sh, which the tutorial quotes) run
here as a person runs them, each in its own process over real zenoh: two daemons built from the
example's files, the example competency and mind as remote processes, a refused mind name, and a
migration. The one change to what a person types: every command that joins a mesh gets this
test's mesh, loopback endpoints and no multicast (and each daemon a state folder under tmp), so
that the run meets nothing else."""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
from contextlib import ExitStack
from pathlib import Path

import pytest

from cmion_mesh.procs import Daemon, cli_argv, free_port
from cmion_mesh.testing.wait import wait_for
from tests.helpers.tutorial import ROOT, script_regions

pytestmark = pytest.mark.timeout(180)

#: The script's regions in order, and what each is: "setup" (cd, export), "once" (commands that
#: end, each must succeed), "terminal" (one command that runs until stopped), "fails" (exit 1),
#: "refused" (exit 2); "launch" (the launch file: its own test, below).
STEPS = {
    "setup": "setup", "validate": "once", "terminal-lamp": "terminal", "act-lamp": "once", "act-fails": "fails",
    "terminal-desk": "terminal", "terminal-competency": "terminal", "act-desk": "once", "mind-clash": "refused",
    "terminal-mind": "terminal", "watch": "once", "migrate": "once", "migrate-back": "once",
    "terminal-launch": "launch",
}
#: Verbs that take no mesh options.
OFFLINE = {"validate"}


class Tutorial:
    """Runs the script's command lines: ``cd`` and ``export`` change where and with what the next
    ones run; ``cmion-mesh VERB ...`` runs this installation's command line."""

    def __init__(self, mesh: str, state: Path, stack: ExitStack) -> None:
        self.mesh = mesh
        self.state = state
        self.stack = stack
        self.cwd = Path.cwd()
        self.env: dict[str, str] = {}
        self.endpoints: list[str] = []

    def setup(self, line: str) -> None:
        words = shlex.split(line)
        if words[0] == "cd":
            self.cwd = (ROOT / words[1]).resolve()  # the tutorial starts at the repository's root
        elif words[0] == "export":
            name, _, value = words[1].partition("=")
            value = value.replace("$PWD", str(self.cwd))
            # and this worktree's package, which a person has installed
            self.env[name] = os.pathsep.join((value, os.environ.get(name, str(ROOT))))
        else:
            raise AssertionError(f"tutorial.sh: not a setup line: {line!r}")

    def argv(self, line: str) -> list[str]:
        words = shlex.split(line)
        assert words[0] == "cmion-mesh", f"tutorial.sh: not a cmion-mesh command: {line!r}"
        verb = words[1]
        if verb in OFFLINE:
            return cli_argv(*words[1:])
        if verb == "launch":
            return cli_argv(*words[1:], "--mesh", self.mesh)  # the file says loopback: it meets nothing else
        net = ["--mesh", self.mesh, "--no-multicast", *(x for e in self.endpoints for x in ("--connect", e))]
        if verb == "up":
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            name = Path(words[2]).name
            net += ["--listen", endpoint, "--state-dir", str(self.state / name)]
            self.endpoints.append(endpoint)
        return cli_argv(*words[1:], *net)

    def once(self, line: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(self.argv(line), cwd=self.cwd, env={**os.environ, **self.env}, capture_output=True, text=True,
                              timeout=60, stdin=subprocess.DEVNULL)

    def succeeds(self, line: str) -> str:
        done = self.once(line)
        assert done.returncode == 0, f"{line}: exit {done.returncode}: {done.stderr}"
        return done.stdout

    def terminal(self, line: str) -> Daemon:
        words = shlex.split(line)
        process = self.stack.enter_context(Daemon(self.argv(line), env=self.env, cwd=self.cwd, name=words[1]))
        process.wait_line({"up": "up in mesh", "launch": "all ready"}.get(words[1], "serving embodiment"), 30)
        return process


def light_last(tutorial: Tutorial, line: str) -> str:
    """The value ``bb get`` prints (``light/last  = 3``), or "" while there is none."""
    done = tutorial.once(line)
    return done.stdout.rpartition("=")[2].strip() if done.returncode == 0 else ""


def test_the_tutorial_runs_as_written(mesh: str, tmp_path: Path) -> None:
    steps = script_regions()
    assert list(steps) == list(STEPS), "tutorial.sh's regions changed: say here how each runs"
    with ExitStack() as stack:
        tutorial = Tutorial(mesh, tmp_path, stack)
        for line in steps["setup"]:
            tutorial.setup(line)

        (validate,) = steps["validate"]
        tutorial.succeeds(validate)

        # The lamp: the example's library, rules and mind in one daemon; the companion is born there.
        (lamp,) = steps["terminal-lamp"]
        tutorial.terminal(lamp)
        act, show = steps["act-lamp"]
        tutorial.succeeds(act)
        assert light_last(tutorial, show) == "2"
        (bad,) = steps["act-fails"]
        failed = tutorial.once(bad)
        assert failed.returncode == 1 and "Blink: Times must be 1 to 20, not 99" in failed.stdout + failed.stderr

        # The desk: the rules and the mind, its Light served by the example competency in a process of its own.
        (desk,) = steps["terminal-desk"]
        tutorial.terminal(desk)
        (competency,) = steps["terminal-competency"]
        tutorial.terminal(competency)
        (act_desk,) = steps["act-desk"]
        # until the desk has seen the remote competency's token (a person types slower than that)
        wait_for(lambda: tutorial.once(act_desk).returncode == 0, 30, "the desk blinks with the remote competency")

        # A remote mind under the desk's own mind's name is refused, in one line naming both.
        (clash,) = steps["mind-clash"]
        refused = tutorial.once(clash)
        assert refused.returncode == 2, refused.stdout + refused.stderr
        assert refused.stderr.strip().splitlines() == [
            "error: embodiment 'desk' already has a mind named 'keeper': give this mind another name (serve-mind --name NAME)"]

        # Under its own name it serves, and the action of its on_start reaches the body: its first act succeeds.
        (mind,) = steps["terminal-mind"]
        watcher = tutorial.terminal(mind)
        (watch,) = steps["watch"]
        wait_for(lambda: light_last(tutorial, watch) == "4", 30, "the remote mind's first action (Blink 4) ran on the desk")
        assert not any("fail" in line.lower() for line in watcher.lines), watcher.lines

        # The companion moves to the desk; its mind remembers it has lived in one body before: Blink 2.
        migrate, show_desk = steps["migrate"]
        tutorial.succeeds(migrate)
        wait_for(lambda: light_last(tutorial, show_desk) == "2", 30, "the keeper's arrival blink on the desk")
        # and back: its third body, three blinks
        back, show_lamp = steps["migrate-back"]
        tutorial.succeeds(back)
        wait_for(lambda: light_last(tutorial, show_lamp) == "3", 30, "the keeper's arrival blink back on the lamp")


def test_a_remote_mind_started_before_its_embodiment_acts_once_it_is_there(mesh: str, tmp_path: Path) -> None:
    """The mind's ``on_start`` waits until its embodiment is reachable: its first ``act`` succeeds
    (it used to run at once, and its action reached nobody)."""
    examples = ROOT / "examples"
    env = {"PYTHONPATH": os.pathsep.join((str(examples), os.environ.get("PYTHONPATH", str(ROOT))))}
    competency_at, mind_at, desk_at = (f"tcp/127.0.0.1:{free_port()}" for _ in range(3))
    net = ["--mesh", mesh, "--no-multicast"]
    with ExitStack() as stack:
        def start(*argv: str, name: str) -> Daemon:
            return stack.enter_context(Daemon(cli_argv(*argv, *net), env=env, cwd=examples, name=name))

        competency = start("serve-competency", "blink.competency:Blink", "--embodiment", "desk", "--listen", competency_at, name="light")
        competency.wait_line("serving embodiment", 30)
        mind = start("serve-mind", "blink.mind:Keeper", "--embodiment", "desk", "--name", "watcher", "--parameters", "4",
                     "--listen", mind_at, "--connect", competency_at, name="watcher")
        mind.wait_line("this mind starts once it is", 30)
        desk = start("up", "blink/desk", "--remote-type", "Light", "--state-dir", str(tmp_path / "desk"), "--listen", desk_at,
                     "--connect", competency_at, "--connect", mind_at, name="desk")
        desk.wait_line("up in mesh", 30)
        mind.wait_line("mind 'watcher' serving embodiment 'desk'", 30)

        def last() -> str:
            done = subprocess.run(cli_argv("bb", "get", "desk", "light/last", *net, "--connect", desk_at), capture_output=True,
                                  text=True, timeout=60, stdin=subprocess.DEVNULL)
            return done.stdout.rpartition("=")[2].strip() if done.returncode == 0 else ""

        wait_for(lambda: last() == "4", 30, "the watcher's first action (Blink 4) ran on the desk")


def test_the_launch_file_starts_it_all(mesh: str, tmp_path: Path) -> None:
    """``launch blink/blink.launch.toml``: the lamp, the desk, its Light and the watcher, in order;
    the options it prints reach them."""
    steps = script_regions()
    with ExitStack() as stack:
        tutorial = Tutorial(mesh, tmp_path, stack)
        for line in steps["setup"]:
            tutorial.setup(line)
        tutorial.env["XDG_STATE_HOME"] = str(tmp_path)  # the daemons' default state folders
        (launch,) = steps["terminal-launch"]
        launcher = tutorial.terminal(launch)
        reach = shlex.split(launcher.wait_line("all ready", 1).partition("cmion-mesh peers ")[2])
        assert reach[:2] == ["--mesh", mesh] and "--no-multicast" in reach

        def last(embodiment: str) -> str:
            done = subprocess.run(cli_argv("bb", "get", embodiment, "light/last", *reach), capture_output=True, text=True,
                                  timeout=60, stdin=subprocess.DEVNULL)
            return done.stdout.rpartition("=")[2].strip() if done.returncode == 0 else ""

        wait_for(lambda: last("desk") == "4", 30, "the watcher's first action (Blink 4) ran on the desk")
        assert last("lamp") == "1"  # the keeper's blink when its companion was born there
        assert launcher.stop(signal.SIGINT) == 0, launcher.lines[-20:]
