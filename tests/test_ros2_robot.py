"""A ROS 2 robot as a body: ``cmion-mesh up ros_robot`` against a stand-in ROS 2 robot.

Separate processes over real zenoh on loopback: one ``ros_robot`` daemon for the module, and a
stand-in robot (tests/helpers/ros2_robot_standin.py: rmw_zenoh's wire format written independently of
cmion_mesh/ros2/wire.py and interfaces.py) started per behaviour it must show (succeeding, hanging, malformed), each
connecting to the daemon. The test process sends mind actions with a ``MeshClient`` and reads
what the stand-in received from its JSON lines.
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from typing import Any

import pytest

from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.procs import Daemon, cli_argv, free_port
from cmion_mesh.testing.wait import wait_for
from tests.conftest import start_daemon
from tests.helpers.mesh_setups import blackboard, body_and_client
from tests.helpers.robot_procs import Standin

pytestmark = pytest.mark.timeout(120)
BODY = "ros_robot"


@pytest.fixture(scope="module")
def body() -> Iterator[tuple[Daemon, str, MeshClient]]:
    with body_and_client(BODY, BODY) as started:
        yield started


def bb(client: MeshClient, path: str) -> Any:
    return blackboard(client, BODY, path)


def test_goto_reaches_nav2_as_a_goal_with_feedback_and_result(body: tuple[Daemon, str, MeshClient]) -> None:
    _, endpoint, client = body
    robot_endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Standin(endpoint, "--listen", robot_endpoint, "--feedback", "3", "--feedback-interval", "0.05", "--odom-hz", "20") as robot:
        # The daemon's node is in the robot's ROS graph (what `ros2 node list` reads).
        seen = robot.event("node_seen")
        assert seen["name"] == f"cmion_{BODY}" and seen["namespace"] == "/"
        # ...and `doctor` sees both nodes, on domain 0 (connected to both, as to a robot's router).
        doctor = subprocess.run(cli_argv("doctor", "--mesh", client.mesh, "--connect", endpoint, "--connect", robot_endpoint,
                                         "--no-multicast", "--json"),
                                capture_output=True, text=True, timeout=60, check=False)
        nodes = json.loads(doctor.stdout)["ros2"]
        assert any(n.startswith("/standin_robot ") for n in nodes["0"]), nodes
        assert any(n.startswith(f"/cmion_{BODY} ") for n in nodes["0"]), nodes

        report = client.act(BODY, "GoTo", ["Kitchen"], timeout=60)
        assert report.status == "succeeded", report.reason
        goal = robot.event("goal")
        # WorldModel.xml: Kitchen at x 4.0, y 2.5, yaw 1.5708 in the map frame.
        assert goal["frame_id"] == "map" and (goal["x"], goal["y"], goal["z"]) == (4.0, 2.5, 0.0)
        assert goal["qz"] == pytest.approx(0.7071, abs=1e-3) and goal["qw"] == pytest.approx(0.7071, abs=1e-3)
        assert robot.event("result")["status"] == 4
        feedback = bb(client, "navigation/feedback")
        assert feedback is not None and set(feedback) >= {"distance_remaining", "x", "y"}
        # The robot's three feedbacks come 0.05 s apart, within feedback_interval (0.2 s): the
        # blackboard still ends with the last one (at the goal), not the first one written.
        assert (feedback["distance_remaining"], feedback["x"], feedback["y"]) == (0.0, 4.0, 2.5), feedback
        assert bb(client, "navigation/state") == "arrived"
        assert client.get_property(BODY, keys.WORLD_MODEL, "Self", "location").value == "Kitchen"

        # Drive: Twist on cmd_vel for a bounded time, then a zero Twist.
        assert client.act(BODY, "Drive", ["0.2", "0.5", "0.3"], timeout=30).status == "succeeded"
        assert robot.event("cmd_vel")["linear"] == [0.2, 0.0, 0.0]
        stopped = {"event": "cmd_vel", "linear": [0, 0, 0], "angular": [0, 0, 0]}
        assert wait_for(lambda: stopped in robot.events("cmd_vel"), 10, "a zero Twist")
        # Say: the composed sentence on the speech topic.
        assert client.act(BODY, "Say", ["greeting", "Alice"], timeout=30).status == "succeeded"
        assert "Alice" in robot.event("speech")["data"]
        # Odometry reaches the blackboard (rate-limited).
        assert wait_for(lambda: isinstance(bb(client, "ros2/odom"), dict), 15, "odometry on the blackboard")
        assert set(bb(client, "ros2/odom")) >= {"header", "pose", "twist"}


def test_cancel_vanish_and_malformed(body: tuple[Daemon, str, MeshClient]) -> None:
    daemon, endpoint, client = body
    with Standin(endpoint, "--nav", "hang") as robot:
        # Cancel: the mind's cancel reaches the robot as an action cancel.
        with client.start_action(BODY, "GoTo", ["Lab"]) as run:
            goal = robot.event("goal")
            client.cancel(BODY, run.action_id)
            report = run.wait(30)
        assert report.status == "cancelled", report
        assert robot.event("cancel")["goal_id"] == goal["goal_id"]
        assert bb(client, "navigation/state") == "stopped"

        # Drive stops the robot on cancel: a zero Twist, long before its 5 s are over.
        with client.start_action(BODY, "Drive", ["0.3", "0", "5"]) as run:
            assert robot.event("cmd_vel")["linear"] == [0.3, 0.0, 0.0]
            client.cancel(BODY, run.action_id)
            assert run.wait(30).status == "cancelled"
        assert wait_for(lambda: robot.events("cmd_vel")[-1]["linear"] == [0, 0, 0], 10, "a zero Twist last")

        # A robot node that vanishes mid-goal fails the action, naming it.
        with client.start_action(BODY, "GoTo", ["Office"]) as run:
            wait_for(lambda: len(robot.events("goal")) == 2, 15, "the second goal")
            assert robot.exit() == 0
            report = run.wait(30)
        assert report.status == "failed"
        assert "/standin_robot" in report.reason and "left" in report.reason, report.reason

    # Malformed CDR from the robot: refused and logged naming the topic and the node; the daemon goes on.
    with Standin(endpoint, "--malformed", "--odom-hz", "20") as robot:
        report = client.act(BODY, "GoTo", ["Kitchen"], timeout=60)
        assert report.status == "failed" and "malformed CDR" in report.reason and "/standin_robot" in report.reason, report.reason
        daemon.wait_line("refused a message on /odom from node /standin_robot", 15)
        assert daemon.proc.poll() is None
        assert client.act(BODY, "Express", ["nod"], timeout=30).status == "succeeded"


def test_the_companion_migrates_into_the_ros_robot_and_out(body: tuple[Daemon, str, MeshClient]) -> None:
    _, endpoint, client = body
    robot, _ = start_daemon(client.mesh, "robot", "robot", "--connect", endpoint)  # the companion is born there
    with robot, Standin(endpoint) as standin:
        client.join("robot", timeout=20)
        assert client.migrate("spirit", BODY, timeout=60)["target"] == BODY
        assert client.describe(BODY)["inhabitant"] == "spirit"
        assert client.act(BODY, "GoTo", ["Lab"], timeout=60).status == "succeeded"
        assert (standin.event("goal")["x"], standin.event("goal")["y"]) == (6.5, -2.0)
        assert client.migrate("spirit", "robot", timeout=60)["target"] == "robot"
        assert client.describe("robot")["inhabitant"] == "spirit"
