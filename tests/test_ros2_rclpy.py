"""DDS robots as bodies: the ROS 2 competencies over an rclpy node, against real rclpy processes.

Separate processes: a daemon (``cmion-mesh up`` of a small embodiment whose library says
``transport=rclpy``) hosting an rclpy node, and a robot of real rclpy nodes
(``tests/helpers/rclpy_robot.py``), both on Fast DDS from the ``ros2`` extra's wheels, loopback
only (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``), on a ROS domain of their own per test. The
same rules and competency classes, with ``transport=rmw_zenoh``, then pass against the rmw_zenoh
stand-in robot (``tests/helpers/ros2_robot_standin.py``).
"""

from __future__ import annotations

import itertools
import json
import random
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy", reason="rclpy is not installed (the ros2 extra: pip install 'cmion-mesh[ros2]')")
pytest.importorskip("test_msgs", reason="test_msgs is not installed (the ros2 extra: pip install 'cmion-mesh[ros2]')")

from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.procs import Daemon, cli_argv
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.testing.wait import wait_for
from tests.helpers.mesh_setups import blackboard, body_and_client
from tests.helpers.robot_procs import RclpyRobot, Standin
from tests.helpers.ros2_embodiment import DRIVE, FIBONACCI_FROM, GOAL, SAY, write_embodiment

pytestmark = pytest.mark.timeout(120)
BODY = "dds_robot"

# The same rules for both transports (tests/helpers/ros2_embodiment.py): Say and Drive as the
# shipped ros_robot has them, and a goal of whatever action the library's RobotGoal competency
# serves (a JSON object of goal fields, or the Fibonacci order from the blackboard).
LIBRARY = """<?xml version="1.0" encoding="UTF-8"?>
<CompetencyLibrary>
  <Competency ClassName="cmion_mesh.ros2.competencies:Ros2Velocity" ConstructorParameters="{common},rate=20,subscriber_timeout=20" />
  <Competency ClassName="cmion_mesh.ros2.competencies:Ros2Speech" ConstructorParameters="{common},subscriber_timeout=20" />
  <Competency ClassName="cmion_mesh.ros2.competencies:Ros2SensorBridge" ConstructorParameters="{common},sensor.{sensor},interval=0.5" />
  <Competency ClassName="cmion_mesh.ros2.competencies:Ros2Action"
              ConstructorParameters="{common},competency_type=RobotGoal,{action},bb=goal,feedback_interval=0,server_timeout=20" />
  <Competency ClassName="cmion_mesh.competencies.spirit:LanguageGeneration" ConstructorParameters="0.02,Self" />
</CompetencyLibrary>
"""


def embodiment(folder: Path, *, common: str, sensor: str, action: str) -> Path:
    return write_embodiment(folder, BODY, rules=(SAY, DRIVE, GOAL, FIBONACCI_FROM),
                            library=LIBRARY.format(common=common, sensor=sensor, action=action),
                            world=(embodiment_dir("ros_robot") / "WorldModel.xml").read_text()).parent


@pytest.fixture
def ros_domain(monkeypatch: pytest.MonkeyPatch) -> int:
    """A ROS domain of this test's own, loopback only, for every process it starts."""
    domain = random.SystemRandom().randrange(1, 102)  # below 102: its ports stay under the ephemeral range
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.delenv("ROS_STATIC_PEERS", raising=False)
    monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)  # the wheels' Fast DDS
    return domain


@contextmanager
def body_client(tmp_path: Path, common: str, sensor: str, action: str) -> Iterator[tuple[Daemon, str, MeshClient]]:
    with body_and_client(BODY, str(embodiment(tmp_path / BODY, common=common, sensor=sensor, action=action))) as started:
        yield started


@pytest.fixture
def dds_body(tmp_path: Path, ros_domain: int) -> Iterator[tuple[Daemon, str, MeshClient]]:
    with body_client(tmp_path, f"transport=rclpy,domain={ros_domain}", "battery=battery sensor_msgs/msg/BatteryState",
                     "action=fibonacci,action_type=test_msgs/action/Fibonacci") as body:
        yield body


def bb(client: MeshClient, path: str) -> Any:
    return blackboard(client, BODY, path)


def test_drive_say_and_a_sensor_reach_a_real_rclpy_robot(dds_body: tuple[Daemon, str, MeshClient], tmp_path: Path) -> None:
    daemon, _, client = dds_body
    with RclpyRobot(tmp_path, "--battery-hz", "20") as robot:
        # Drive: Twists on /cmd_vel for the duration, then a zero Twist, last.
        assert client.act(BODY, "Drive", ["0.2", "0.5", "0.3"], timeout=60).status == "succeeded"
        assert robot.event("cmd_vel")["linear"] == [0.2, 0.0, 0.0]
        assert robot.events("cmd_vel")[0]["angular"] == [0.0, 0.0, 0.5]
        stopped = {"event": "cmd_vel", "linear": [0.0, 0.0, 0.0], "angular": [0.0, 0.0, 0.0]}
        assert wait_for(lambda: robot.events("cmd_vel")[-1] == stopped, 10, "a zero Twist last")
        # Say: the composed sentence on /speech.
        assert client.act(BODY, "Say", ["greeting", "Alice"], timeout=60).status == "succeeded"
        assert "Alice" in robot.event("speech")["data"]
        # The battery reaches the blackboard at the configured rate: the robot publishes 20 a
        # second, numbered; the bridge writes at most one every 0.5 s, so ten or so apart.
        written: list[float] = []
        selector = f"cmion/{client.mesh}/{BODY}/{keys.BLACKBOARD}/ros2/battery"
        with client.watch(selector, lambda _, entry: written.append(entry.value["percentage"]) if entry is not None else None):
            wait_for(lambda: len(written) >= 5, 20, "five battery writes")
        steps = [b - a for a, b in itertools.pairwise(written)]
        assert all(step >= 5 for step in steps), written
        assert set(bb(client, "ros2/battery")) >= {"voltage", "percentage", "header"}
        assert bb(client, "ros2/battery")["voltage"] == 12.0
    # The daemon stops its rclpy node with itself: nothing left running.
    assert daemon.stop() == 0
    assert any("stopped cleanly (no thread left)" in line for line in daemon.lines), daemon.lines[-5:]


def test_a_fibonacci_action_server_driven_by_the_generic_action_competency(dds_body: tuple[Daemon, str, MeshClient],
                                                                             tmp_path: Path) -> None:
    _, _, client = dds_body
    with RclpyRobot(tmp_path, "--feedback-interval", "0.02") as robot:
        updates: list[Any] = []
        selector = f"cmion/{client.mesh}/{BODY}/{keys.BLACKBOARD}/goal/feedback"
        with client.watch(selector, lambda _, entry: updates.append(entry.value) if entry is not None else None):
            report = client.act(BODY, "Goal", [json.dumps({"order": 6})], timeout=60)
        assert report.status == "succeeded", report
        assert robot.event("goal")["order"] == 6
        assert bb(client, "goal/result") == {"sequence": [0, 1, 1, 2, 3, 5, 8]}
        assert bb(client, "goal/state") == "succeeded"
        assert updates and updates[-1] == {"sequence": [0, 1, 1, 2, 3, 5, 8]}, updates  # the last feedback is kept
        # A goal field from the blackboard.
        client.set_property(BODY, keys.BLACKBOARD, "fib", "order", 4, create=True)
        assert client.act(BODY, "FibonacciFrom", ["fib/order"], timeout=60).status == "succeeded"
        assert robot.events("goal")[-1]["order"] == 4
        assert bb(client, "goal/result") == {"sequence": [0, 1, 1, 2, 3]}
        # A field the action does not have fails the run, naming it.
        report = client.act(BODY, "Goal", [json.dumps({"length": 3})], timeout=60)
        assert report.status == "failed" and "has no field length" in report.reason, report


def test_cancel_and_a_server_killed_mid_goal(dds_body: tuple[Daemon, str, MeshClient], tmp_path: Path) -> None:
    daemon, _, client = dds_body
    with RclpyRobot(tmp_path, "--hang") as robot:
        with client.start_action(BODY, "Goal", [json.dumps({"order": 3})]) as run:
            robot.event("goal")
            client.cancel(BODY, run.action_id)
            report = run.wait(30)
        assert report.status == "cancelled", report
        robot.event("cancel")
        assert robot.event("result")["status"] == "canceled"
        assert wait_for(lambda: bb(client, "goal/state") == "canceled", 10, "the goal's state")

        # Drive stops the robot on cancel: a zero Twist, long before its 5 s are over.
        with client.start_action(BODY, "Drive", ["0.3", "0", "5"]) as run:
            assert robot.event("cmd_vel")["linear"] == [0.3, 0.0, 0.0]
            client.cancel(BODY, run.action_id)
            assert run.wait(30).status == "cancelled"
        assert wait_for(lambda: robot.events("cmd_vel")[-1]["linear"] == [0.0, 0.0, 0.0], 10, "a zero Twist last")

        # The robot's process killed mid-goal (no goodbye): the run fails naming its node.
        with client.start_action(BODY, "Goal", [json.dumps({"order": 3})]) as run:
            wait_for(lambda: len(robot.events("goal")) == 2, 20, "the second goal")
            robot.proc.kill()
            report = run.wait(60)
        assert report.status == "failed", report
        assert "/rclpy_robot" in report.reason and "left" in report.reason, report.reason
        assert daemon.proc.poll() is None


def test_doctor_lists_the_ros2_graph_seen_through_rclpy(dds_body: tuple[Daemon, str, MeshClient], tmp_path: Path,
                                                        ros_domain: int) -> None:
    _, endpoint, client = dds_body
    with RclpyRobot(tmp_path):
        out = subprocess.run(cli_argv("doctor", "--mesh", client.mesh, "--connect", endpoint, "--no-multicast", "--json"),
                             capture_output=True, text=True, timeout=60, check=False)
        graph = json.loads(out.stdout)["ros2_rclpy"]
    assert graph["domain"] == ros_domain and graph["rmw"] == "rmw_fastrtps_cpp", graph
    assert "/rclpy_robot" in graph["nodes"] and "/cmion_dds_robot" in graph["nodes"], graph
    assert graph["actions"]["/fibonacci"] == ["test_msgs/action/Fibonacci"], graph
    assert graph["topics"]["/cmd_vel"] == ["geometry_msgs/msg/Twist"], graph


def test_the_same_rules_and_competencies_over_rmw_zenoh_against_the_standin(tmp_path: Path, ros_domain: int) -> None:
    """The rmw_zenoh way, with the same rules file and competency classes (only ``transport``
    differs): the stand-in robot serves Nav2's NavigateToPose, which the generic competency drives."""
    del ros_domain  # the stand-in speaks rmw_zenoh on domain 0
    with body_client(tmp_path, "transport=rmw_zenoh,domain=0", "odom=odom nav_msgs/msg/Odometry",
                     "action=navigate_to_pose,action_type=nav2_msgs/action/NavigateToPose") as (_, endpoint, client), \
            Standin(endpoint, "--odom-hz", "20", "--feedback", "2", "--feedback-interval", "0.05") as robot:
        assert client.act(BODY, "Drive", ["0.2", "0.5", "0.3"], timeout=60).status == "succeeded"
        assert robot.event("cmd_vel")["linear"] == [0.2, 0.0, 0.0]
        stopped = {"event": "cmd_vel", "linear": [0, 0, 0], "angular": [0, 0, 0]}
        assert wait_for(lambda: robot.events("cmd_vel")[-1] == stopped, 10, "a zero Twist last")
        assert client.act(BODY, "Say", ["greeting", "Alice"], timeout=60).status == "succeeded"
        assert "Alice" in robot.event("speech")["data"]
        assert wait_for(lambda: isinstance(bb(client, "ros2/odom"), dict), 15, "odometry on the blackboard")
        goal = {"pose": {"header": {"frame_id": "map"}, "pose": {"position": {"x": 4.0, "y": 2.5}}}}
        report = client.act(BODY, "Goal", [json.dumps(goal)], timeout=60)
        assert report.status == "succeeded", report
        assert (robot.event("goal")["x"], robot.event("goal")["y"]) == (4.0, 2.5)
        assert bb(client, "goal/state") == "succeeded" and bb(client, "goal/result")["error_code"] == 0
        assert set(bb(client, "goal/feedback")) >= {"current_pose", "distance_remaining"}


def test_the_rclpy_link_stops_cleanly_and_its_close_is_idempotent(ros_domain: int) -> None:
    import threading

    from cmion_mesh.ros2.rclpy_link import RclpyLink

    with RclpyLink("cmion_link_test", domain=ros_domain) as link:
        assert link.path == "/cmion_link_test"
        spinning = [t for t in threading.enumerate() if t.name == "rclpy-cmion_link_test"]
        assert len(spinning) == 1 and spinning[0].is_alive()
        link.publisher("cmd_vel", "geometry_msgs/msg/Twist").publish({"linear": {"x": 0.1}})
    link.close()  # twice: harmless
    assert not spinning[0].is_alive()
    assert not link.node.context.ok()
