"""Test robots in processes of their own, read through the JSON lines they print (``{"event": ...}``).

``Standin``: the rmw_zenoh stand-in (``tests/helpers/ros2_robot_standin.py``), connected to a
daemon. ``RclpyRobot``: real rclpy nodes on Fast DDS (``tests/helpers/rclpy_robot.py``), on the
ROS domain of the environment, announcing a short lease so that its death is seen soon.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Self

from cmion_mesh.procs import Daemon


class RobotProcess:
    """A robot process that prints one JSON line per event; ``event`` waits for one of them."""

    #: how long ``event`` waits by default (seconds)
    wait = 15.0

    def __init__(self, argv: list[str], *, name: str, ready_within: float, env: dict[str, str] | None = None) -> None:
        self.proc = Daemon(argv, name=name, stdin=True, env=env)
        try:
            self.ready = self.event("ready", ready_within)
        except BaseException:
            self.proc.kill()
            raise

    def event(self, kind: str, timeout: float | None = None) -> dict[str, Any]:
        prefix = json.dumps({"event": kind})[:-1]
        return dict(json.loads(self.proc.wait_line(prefix, self.wait if timeout is None else timeout)))

    def events(self, kind: str) -> list[dict[str, Any]]:
        prefix = json.dumps({"event": kind})[:-1]
        return [json.loads(line) for line in list(self.proc.lines) if line.startswith(prefix)]

    def exit(self) -> int:
        if self.proc.proc.poll() is None:
            self.proc.send("exit")
        return self.proc.stop()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_: object) -> None:
        self.exit()


class Standin(RobotProcess):
    """The stand-in robot, connected to the daemon at ``endpoint``."""

    def __init__(self, endpoint: str, *options: str) -> None:
        super().__init__([sys.executable, "-m", "tests.helpers.ros2_robot_standin", "--connect", endpoint, *options],
                         name="standin", ready_within=20)
        self.zid = self.ready["zid"]


# Fast DDS announces a participant's lease: 20 s by default, the time a robot killed without a
# goodbye stays in the graph. The test robot announces 2 s, so that its death is seen soon.
SHORT_LEASE = """<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com"><profiles>
  <participant profile_name="short_lease" is_default_profile="true"><rtps><builtin><discovery_config>
    <leaseDuration><sec>2</sec></leaseDuration><leaseAnnouncement><nanosec>500000000</nanosec></leaseAnnouncement>
  </discovery_config></builtin></rtps></participant>
</profiles></dds>
"""


class RclpyRobot(RobotProcess):
    """The rclpy robot; its Fast DDS profile is written into ``folder``."""

    wait = 20.0

    def __init__(self, folder: Path, *options: str) -> None:
        profile = folder / "short_lease.xml"
        profile.write_text(SHORT_LEASE)
        super().__init__([sys.executable, "-m", "tests.helpers.rclpy_robot", *options], name="rclpy_robot", ready_within=30,
                         env={"FASTDDS_DEFAULT_PROFILES_FILE": str(profile)})
