"""An idle daemon costs nothing: no thread of it wakes while nothing happens, and it holds few threads.

Real daemons, connected on loopback: ``cmion-mesh up robot`` (the shipped robot: its planner
mind, competencies and a background console, the companion born there) and ``up screen``. Once both
are up and have met, each one's Python threads are read from ``/proc/<pid>/task``: how many, and
how often they were switched in (voluntary and involuntary context switches) over a short window.
The bound is not a timing: before, twenty threads each woke ten times a second (a zenoh channel's
``recv`` looks for Python signals that often), now none should. zenoh's own threads (keeping its
links alive) are left out.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.procs import Daemon
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .conftest import start_daemon

pytestmark = pytest.mark.timeout(120)

#: Python threads an idle daemon holds at most (zenoh's own come on top: a few, and more per link).
MAX_THREADS = 8
#: Wakes of all of an idle daemon's Python threads together, per second, at most (before: about 200).
MAX_WAKES_PER_S = 1.0
WINDOW = 2.0
#: Windows measured at most, until one is quiet.
WINDOWS = 4


def python_threads(pid: int) -> list[str]:
    """The daemon's Python threads (zenoh's, made in Rust, carry names of their own: ``net-0``, ``rx-1``...)."""
    found = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as f:
                if f.read().strip() == "python":
                    found.append(tid)
        except FileNotFoundError:
            continue  # a thread that ended meanwhile
    return found


def wakes(pid: int, tids: list[str]) -> int:
    total = 0
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/status") as f:
                for line in f:
                    if line.startswith(("voluntary_ctxt_switches", "nonvoluntary_ctxt_switches")):
                        total += int(line.split()[1])
        except FileNotFoundError:
            continue
    return total


def test_an_idle_daemon_wakes_no_thread_and_holds_few(mesh: str, tmp_path: Path) -> None:
    daemons: list[Daemon] = []
    try:
        robot, robot_at = start_daemon(mesh, "robot", "robot", "--state-dir", str(tmp_path / "robot"))
        daemons.append(robot)
        screen, screen_at = start_daemon(mesh, "screen", "screen", "--state-dir", str(tmp_path / "screen"),
                                         "--connect", robot_at)
        daemons.append(screen)
        with ZenohTransport(TransportConfig(connect=(robot_at, screen_at), multicast=False)) as t:
            client = MeshClient(t, mesh)
            wait_for(lambda: set(client.describe("robot", timeout=2.0)["alive"]) >= {"robot", "screen"}, 20, "the two met")
            wait_for(lambda: set(client.describe("screen", timeout=2.0)["alive"]) >= {"robot", "screen"}, 20, "the two met")
        # The client has gone; what each daemon does now, it does on its own.
        tids = {d.name: python_threads(d.proc.pid) for d in daemons}
        for daemon in daemons:
            assert len(tids[daemon.name]) <= MAX_THREADS, f"{daemon.name} holds {len(tids[daemon.name])} Python threads while idle"
        # Something that happens in the mesh now and then (the client's leaving, a peer of another
        # test found on the way) wakes a daemon once or twice: what is measured is that it then
        # stays asleep. So a window counts once one is quiet; a thread a timer wakes, wakes in every one.
        windows = []
        for _ in range(WINDOWS):
            before = {d.name: wakes(d.proc.pid, tids[d.name]) for d in daemons}
            threading.Event().wait(WINDOW)  # a window of idleness, measured: nothing to wait for
            woke = {d.name: (wakes(d.proc.pid, tids[d.name]) - before[d.name]) / WINDOW for d in daemons}
            windows.append(woke)
            if all(rate <= MAX_WAKES_PER_S for rate in woke.values()):
                break
        assert all(rate <= MAX_WAKES_PER_S for rate in windows[-1].values()), \
            f"Python threads' wakes per second while idle, in {len(windows)} windows of {WINDOW:g} s: {windows}"
    finally:
        for daemon in daemons:
            daemon.stop()
