"""A robot whose topics or action have another type or definition (another ROS 2 or Nav2 release,
``TwistStamped`` on ``cmd_vel``...): rmw_zenoh's keys carry the type hash, so its nodes never
receive what the mesh publishes nor answer its goals. The ROS 2 competencies must then fail
saying so, not report a success nobody received. In one process, on the in-memory transport: the
"robot" is a second session declaring rmw_zenoh liveliness tokens (tests/test_ros2_robot.py
drives a real stand-in over zenoh)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.ros2 import wire as ros2
from cmion_mesh.ros2.interfaces import Types
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import Sample
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

pytestmark = pytest.mark.timeout(60)
ROS_ROBOT = embodiment_dir("ros_robot")
OTHER_HASH = "RIHS01_" + "ab" * 32
LIBRARY = """<?xml version="1.0" encoding="UTF-8"?>
<CompetencyLibrary>
  <Competency ClassName="cmion_mesh.ros2.competencies:Ros2Navigation" ConstructorParameters="server_timeout=0.5" />
  <Competency ClassName="cmion_mesh.ros2.competencies:Ros2Velocity" ConstructorParameters="subscriber_timeout=0.5" />
  <Competency ClassName="cmion_mesh.ros2.competencies:Ros2Speech" ConstructorParameters="subscriber_timeout=0.5" />
  <Competency ClassName="cmion_mesh.competencies.spirit:LanguageGeneration" ConstructorParameters="0.02,Self" />
  <Competency ClassName="cmion_mesh.competencies.spirit:Animation" ConstructorParameters="0.05,talk,wave,nod" />
</CompetencyLibrary>
"""


class Robot:
    """A session that declares ROS 2 entities as a robot's rmw_zenoh nodes would."""

    def __init__(self, transport: MemoryTransport) -> None:
        self.transport = transport
        self.handles = [transport.declare_token(ros2.node_token(0, transport.id, 1, "/", "robot"))]
        self.eid = 1

    def entity(self, kind: str, name: str, type_name: str, type_hash: str) -> None:
        self.eid += 1
        self.handles.append(self.transport.declare_token(
            ros2.entity_token(0, self.transport.id, 1, self.eid, kind, "/", "robot", name, type_name, type_hash)))


@pytest.fixture
def body(tmp_path: Path, mesh: str) -> Iterator[tuple[MeshClient, Robot, Types]]:
    library = tmp_path / "CompetencyLibrary.xml"
    library.write_text(LIBRARY)
    network = MemoryNetwork()
    with MemoryTransport(network, "daemon") as daemon_side, MemoryTransport(network, "robot") as robot_side, \
            MemoryTransport(network, "tool") as tool_side, \
            Embodiment("ros_robot", mesh=mesh, transport=daemon_side, rules=ROS_ROBOT / "CompetencyManagerRules.xml",
                       library=library, world_model_init=ROS_ROBOT / "WorldModel.xml"):
        yield MeshClient(tool_side, mesh), Robot(robot_side), Types()


def test_a_subscriber_of_another_definition_is_no_subscriber(body: tuple[MeshClient, Robot, Types]) -> None:
    client, robot, types = body
    twist = "geometry_msgs/msg/Twist"
    robot.entity("MS", "/cmd_vel", twist, OTHER_HASH)
    robot.entity("MS", "/speech", "geometry_msgs/msg/Twist", types.hash(twist))
    drive = client.act("ros_robot", "Drive", ["0.2", "0", "0.2"], timeout=20)
    assert drive.status == "failed", drive
    assert "no ROS 2 node subscribes to /cmd_vel" in drive.reason and f"another definition of {twist} ({OTHER_HASH}" in drive.reason
    say = client.act("ros_robot", "Say", ["greeting", "Alice"], timeout=20)
    assert say.status == "failed", say
    assert "no ROS 2 node subscribes to /speech" in say.reason and f"/robot (zenoh {robot.transport.id}) uses it as {twist}" in say.reason

    # The same topic with the right definition: the robot receives the Twists.
    received: list[Sample] = []
    key = ros2.topic_key(0, "/cmd_vel", twist, types.hash(twist))
    robot.handles.append(robot.transport.subscribe(key, received.append, attachments=True))
    robot.entity("MS", "/cmd_vel", twist, types.hash(twist))
    assert client.act("ros_robot", "Drive", ["0.2", "0", "0.2"], timeout=20).status == "succeeded"
    wait_for(lambda: len(received) >= 2, 10, "the Twists at the robot")
    assert types.decode(twist, received[0].payload).linear.x == pytest.approx(0.2)


def test_an_action_server_of_another_definition_is_no_server(body: tuple[MeshClient, Robot, Types]) -> None:
    client, robot, _ = body
    send_goal = "nav2_msgs/action/NavigateToPose_SendGoal"
    robot.entity("SS", "/navigate_to_pose/_action/send_goal", send_goal, OTHER_HASH)
    report = client.act("ros_robot", "GoTo", ["Kitchen"], timeout=20)
    assert report.status == "failed", report
    assert "no ROS 2 node serves the action /navigate_to_pose" in report.reason, report.reason
    assert f"another definition of {send_goal} ({OTHER_HASH}" in report.reason, report.reason
