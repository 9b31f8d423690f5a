"""The catalogue of log lines as daemons write it (docs/deploy.md, "Logs"): two ``cmion-mesh up``
in their own processes, a migration's every step on both sides and an action's end in their standard
error, a flood of refused requests bounded, no custody key in any line. Each daemon's log is
configured as ``up`` configures it (info, text lines, standard error); the in-process tests of
both formats are ``test_log_catalogue.py``."""

from __future__ import annotations

import signal
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh import keys, logs
from cmion_mesh.client import MeshClient
from cmion_mesh.messages import MindMessage
from cmion_mesh.procs import Daemon, free_port
from cmion_mesh.requests import send_request
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .helpers.remote_helpers import diary_embodiment_config
from .test_log_catalogue import secrets_of
from .test_logs import TEXT_LINE, parse_text

pytestmark = pytest.mark.timeout(180)

#: ``cmion-mesh up`` with its log configured as the command does (``logs.configure`` with its
#: defaults) whether or not this version's ``up`` configures it itself: then it replaces this.
UP = "import sys; from cmion_mesh import logs; logs.configure(); from cmion_mesh.cli.main import main; sys.exit(main())"


@dataclass
class Up:
    name: str
    port: int
    daemon: Daemon | None = None

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def start(self, mesh: str, folder: Path, peer: str, companion: str | None = None) -> None:
        argv = ["up", str(diary_embodiment_config(folder / self.name, self.name)), "--mesh", mesh, "--listen", self.endpoint,
                "--no-multicast", "--state-dir", str(self.state(folder)), "--connect", peer]
        if companion:
            argv += ["--companion", companion]
        self.daemon = Daemon([sys.executable, "-c", UP, *argv], name=self.name)
        self.daemon.wait_line("up in mesh", 30)

    def state(self, folder: Path) -> Path:
        return folder / f"state-{self.name}"

    def log(self) -> list[dict[str, Any]]:
        """The daemon's log lines so far, parsed (its other output, the lines ``up`` prints, left out)."""
        assert self.daemon is not None
        return [parse_text(line) for line in list(self.daemon.lines) if TEXT_LINE.fullmatch(line)]

    def where(self, **wanted: Any) -> list[dict[str, Any]]:
        return [line for line in self.log() if all(line.get(k) == v for k, v in wanted.items())]

    def stop(self) -> None:
        if self.daemon is not None:
            self.daemon.stop(signal.SIGTERM, grace=20)


@pytest.fixture
def pair(tmp_path: Path, mesh: str) -> Iterator[tuple[Up, Up]]:
    robot, screen = Up("robot", free_port()), Up("screen", free_port())
    try:
        robot.start(mesh, tmp_path, screen.endpoint, companion="spirit")
        screen.start(mesh, tmp_path, robot.endpoint)
        yield robot, screen
    finally:
        for up in (robot, screen):
            if up.daemon is not None:
                up.daemon.kill()


def test_daemons_log_each_step_of_a_migration_each_action_end_and_a_flood_in_bounded_lines(
        pair: tuple[Up, Up], mesh: str, tmp_path: Path) -> None:
    robot, screen = pair
    with ZenohTransport(TransportConfig(connect=(robot.endpoint, screen.endpoint), multicast=False)) as t:
        client = MeshClient(t, mesh)
        client.wait_for_embodiment("robot", timeout=20)
        client.wait_for_embodiment("screen", timeout=20)
        wait_for(lambda: client.describe("robot", timeout=2).get("inhabitant") == "spirit", 20, "spirit born on the robot")
        wait_for(lambda: robot.where(msg="peer screen joined") and screen.where(msg="peer robot joined"), 20, "peers logged")
        assert client.request("robot", "mind", "message", MindMessage({"note": "met Ada"})).status == "accepted"
        assert client.migrate("spirit", "screen", timeout=30)["epoch"] == 2
        report = client.act("screen", "Migrate", ["robot"], timeout=30)
        assert report.status == "succeeded", report
        wait_for(lambda: robot.where(step="active", epoch=3), 20, "spirit back on the robot, logged")

        # A flood: one sender, 2,000 requests no component has.
        began = time.monotonic()
        key = keys.request_key(mesh, "robot", "migration", "nosuch", "phone")
        for _ in range(2000):
            assert send_request(t, key, MindMessage({}), timeout=10).code == "unknown_request"
        flooded = time.monotonic() - began

    # The migration there: the source's steps in the robot's log, the target's in the screen's.
    there = robot.where(step="started", peer="screen")
    assert len(there) == 1 and there[0]["msg"] == "migration of spirit to screen started"
    attempt = there[0]["attempt"]
    source = [line for line in robot.log() if line.get("attempt") == attempt]
    target = [line for line in screen.log() if line.get("attempt") == attempt]
    assert [s["step"] for s in source] == ["started", "prepared", "handed", "released"], source
    assert [s["step"] for s in target] == ["incoming", "active"], target
    assert all(s["peer"] == "screen" and s["companion"] == "spirit" and s["level"] == "INFO" for s in source)
    assert all(s["peer"] == "robot" and s["companion"] == "spirit" for s in target)
    arrived, left = target[-1], source[-1]
    assert arrived["msg"] == "companion spirit arrived from robot" and arrived["epoch"] == 2 and 0 <= arrived["duration_s"] < 30
    assert left["msg"] == "companion spirit left for screen" and left["epoch"] == 2 and 0 <= left["duration_s"] < 30
    # And back, through the action: its steps the other way round, and the action's end on the screen.
    back = screen.where(step="started", peer="robot")
    assert len(back) == 1
    assert [s["step"] for s in screen.log() if s.get("attempt") == back[0]["attempt"]] == ["started", "prepared", "handed", "released"]
    assert [s["step"] for s in robot.log() if s.get("attempt") == back[0]["attempt"]] == ["incoming", "active"]
    end = screen.where(action="Migrate")
    assert len(end) == 1 and end[0]["msg"] == "action Migrate succeeded" and end[0]["outcome"] == "succeeded"
    assert end[0]["rule"] == "<built-in>:0" and end[0]["action_id"] == report.action_id and 0 <= end[0]["duration_s"] < 30

    robot.stop()  # the throttle's last count is written as the daemon stops
    screen.stop()
    refused = [line for line in robot.log() if line["logger"] == "cmion_mesh.requests"]
    windows = flooded // logs.WINDOW + 2
    assert 2 <= len(refused) <= 2 * windows, [line["msg"] for line in refused]
    assert refused[0]["msg"] == "refused migration/nosuch from phone" and refused[0]["code"] == "unknown_request"
    assert refused[0]["sender"] == "phone" and refused[0]["request"] == "nosuch"
    assert sum(line.get("count", 1) for line in refused) == 2000  # every refusal in a line or a count

    everything = "\n".join(robot.daemon.lines if robot.daemon else []) + "\n".join(screen.daemon.lines if screen.daemon else [])
    held = secrets_of(robot.state(tmp_path)) + secrets_of(screen.state(tmp_path))
    assert held and not [s for s in held if s in everything], "a custody private key reached a daemon's output"
