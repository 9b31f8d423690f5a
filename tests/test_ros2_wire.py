"""The ROS 2 wire format (rmw_zenoh, Jazzy) against the examples of rmw_zenoh's design.md and
REP 2011's hashes: keys, liveliness tokens, attachments, type hashes, CDR; and the competency
library's parameters. No network here (tests/test_ros2_robot.py drives a stand-in robot)."""

from __future__ import annotations

import threading

import pytest

from cmion_mesh.errors import ConfigError, ProtocolError
from cmion_mesh.ros2 import wire as ros2
from cmion_mesh.ros2.competencies import Ros2Navigation, Ros2SensorBridge, Ros2Speech, Ros2Velocity
from cmion_mesh.ros2.interfaces import Types, plain
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import Sample
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"


@pytest.fixture(scope="module")
def types() -> Types:
    found = Types()
    found.register_service("example_interfaces/srv/AddTwoInts", "int64 a\nint64 b", "int64 sum")
    return found


def test_type_hashes_are_rosidl_ones(types: Types) -> None:
    assert types.hash("std_msgs/msg/String") == STRING_HASH
    assert types.hash("geometry_msgs/msg/Twist") == "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
    # A service's hash covers request, response and the synthesized event (whose ServiceEventInfo
    # has a char[16], a uint8[16] in rosidl's description).
    assert types.hash("example_interfaces/srv/AddTwoInts") == ADD_TWO_INTS_HASH
    assert types.hash("service_msgs/msg/ServiceEventInfo") == "RIHS01_41bcbbe07a75c9b52bc96bfd5c24d7f0fc0a08c0cb7921b3373c5732345a6f45"
    for name in ("nav2_msgs/action/NavigateToPose_SendGoal", "nav2_msgs/action/NavigateToPose_GetResult",
                 "nav2_msgs/action/NavigateToPose_FeedbackMessage", "action_msgs/srv/CancelGoal"):
        assert types.hash(name).startswith("RIHS01_") and len(types.hash(name)) == 7 + 64


def test_data_keys_match_the_design_examples(types: Types) -> None:
    assert ros2.topic_key(0, ros2.qualify("chatter"), "std_msgs/msg/String", STRING_HASH) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert ros2.topic_key(0, ros2.qualify("chatter", "/robot1"), "std_msgs/msg/String", STRING_HASH) == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert ros2.topic_key(2, "/add_two_ints", "example_interfaces/srv/AddTwoInts", types.hash("example_interfaces/srv/AddTwoInts")) == \
        f"2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}"


def test_liveliness_tokens_match_the_design_examples() -> None:
    zid = "aac3178e146ba6f1fc6e6a4085e77f21"
    assert ros2.node_token(2, zid, 0, "", "listener") == f"@ros2_lv/2/{zid}/0/0/NN/%/%/listener"
    token = ros2.entity_token(2, zid, 0, 10, "MS", "/", "listener", "/chatter", "std_msgs/msg/String", STRING_HASH)
    assert token == f"@ros2_lv/2/{zid}/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,"
    server = ("@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/%add_two_ints/"
              f"example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}/::,10:,:,:,,")
    parsed = ros2.parse_token(server)
    assert parsed == ros2.Entity(2, "f9980ee0495eaafb3e38f0d19e2eae12", "0", "10", "SS", "/", "add_two_ints_server",
                                 "/add_two_ints", "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH)
    assert parsed.node_path == "/add_two_ints_server"
    assert ros2.parse_token(ros2.node_token(0, zid, 3, "/robot1", "nav")) == ros2.Entity(0, zid, "3", "3", "NN", "/robot1", "nav")
    for junk in ("@ros2_lv/x/1/2/3/NN/%/%/n", "@ros2_lv/0/z/0/0/XX/%/%/n", "cmion/m/e", "@ros2_lv/0/z/0/1/MP/%/%/n"):
        assert ros2.parse_token(junk) is None


def test_names() -> None:
    assert ros2.qualify("/odom", "/ns") == "/odom"
    assert ros2.qualify("scan", "robot1/") == "/robot1/scan"
    assert ros2.dds_type("nav2_msgs/action/NavigateToPose_SendGoal") == "nav2_msgs::action::dds_::NavigateToPose_SendGoal_"
    assert ros2.ros_type("nav2_msgs::action::dds_::NavigateToPose_SendGoal_") == "nav2_msgs/action/NavigateToPose_SendGoal"
    for bad in ("", "a//b", "9lives", "bad-name", "speech/", "navigate__to_pose", "caf\u00e9"):
        with pytest.raises(ConfigError):
            ros2.qualify(bad)
    with pytest.raises(ConfigError, match="type name"):
        ros2.dds_type("std_msgs/String")


def test_attachments() -> None:
    gid = bytes(range(16))
    data = ros2.encode_attachment(7, gid, timestamp_ns=123)
    assert len(data) == 33 and data[16] == 16
    assert ros2.decode_attachment(data) == ros2.Attachment(7, 123, gid)
    for bad in (None, b"", data[:-1], data[:16] + b"\x08" + data[17:]):
        with pytest.raises(ProtocolError):
            ros2.decode_attachment(bad)


def test_cdr_round_trips_and_refuses_malformed(types: Types) -> None:
    assert types.encode("std_msgs/msg/String", {"data": "hi"})[:11] == bytes.fromhex("00010000030000006869 00".replace(" ", ""))
    goal_id = bytes(range(16))
    request = {"goal_id": {"uuid": list(goal_id)},
               "goal": {"pose": {"header": {"frame_id": "map"},
                                 "pose": {"position": {"x": 4.0, "y": 2.5}, "orientation": ros2.yaw_quaternion(1.5708)}}}}
    data = types.encode("nav2_msgs/action/NavigateToPose_SendGoal_Request", request)
    back = plain(types.decode("nav2_msgs/action/NavigateToPose_SendGoal_Request", data))
    assert back["goal_id"]["uuid"] == list(goal_id)
    assert back["goal"]["pose"]["header"]["frame_id"] == "map"
    assert back["goal"]["pose"]["pose"]["position"] == {"x": 4.0, "y": 2.5, "z": 0.0}
    assert back["goal"]["pose"]["pose"]["orientation"]["w"] == pytest.approx(0.7071, abs=1e-3)
    for cut in (0, 3, 4, 20, len(data) - 8):
        with pytest.raises(ProtocolError, match="malformed CDR for nav2_msgs/action/NavigateToPose_SendGoal_Request"):
            types.decode("nav2_msgs/action/NavigateToPose_SendGoal_Request", data[:cut])
    with pytest.raises(ConfigError, match="no field"):
        types.encode("geometry_msgs/msg/Twist", {"linaer": {}})


def test_attachments_travel_only_to_subscriptions_that_ask() -> None:
    with MemoryTransport(MemoryNetwork()) as transport:
        got: dict[str, Sample] = {}
        both = threading.Event()

        def keep(name: str):  # type: ignore[no-untyped-def]
            def handler(sample: Sample) -> None:
                got[name] = sample
                if len(got) == 2:
                    both.set()
            return handler

        transport.subscribe("0/x", keep("plain"))
        transport.subscribe("0/x", keep("attached"), attachments=True)
        transport.publish("0/x", b"p", attachment=b"a")
        assert both.wait(5)
        assert got["attached"].attachment == b"a" and got["plain"].attachment is None


def test_competency_parameters() -> None:
    nav = Ros2Navigation("action=navigate_to_pose", "place.Kitchen=4 2.5 1.57", "place.Lab=1 2", "domain=3")
    assert nav.places == {"Kitchen": (4.0, 2.5, 1.57), "Lab": (1.0, 2.0, 0.0)} and nav.domain == 3
    with pytest.raises(ConfigError, match="unknown parameter 'acton'"):
        Ros2Navigation("acton=x")
    with pytest.raises(ConfigError, match="x y"):
        Ros2Navigation("place.Kitchen=4")
    with pytest.raises(ConfigError, match="domain"):
        Ros2Velocity("domain=300")
    with pytest.raises(ConfigError, match="rate"):
        Ros2Velocity("rate=0")
    bridge = Ros2SensorBridge("sensor.odom=odom nav_msgs/msg/Odometry", "interval=0.1")
    assert bridge.sensors == {"odom": ("odom", "nav_msgs/msg/Odometry")}
    with pytest.raises(ConfigError, match="topic and its type"):
        Ros2SensorBridge("sensor.odom=odom")
    with pytest.raises(ConfigError, match="not a ROS 2 Jazzy type known here"):
        Ros2SensorBridge("sensor.people=people my_msgs/msg/People")
    with pytest.raises(ConfigError, match="type name"):
        Ros2SensorBridge("sensor.odom=odom Odometry")
    with pytest.raises(ConfigError, match="invalid ROS 2 name"):
        Ros2Velocity("topic=cmd-vel")
    with pytest.raises(ConfigError, match=r"Ros2Velocity: invalid ROS 2 namespace '/robot 1'"):
        Ros2Velocity("namespace=/robot 1")
    with pytest.raises(ConfigError, match="'nav2_msgs/action/NavigateToPose' is an action, not a message type"):
        Ros2SensorBridge("sensor.nav=navigate_to_pose nav2_msgs/action/NavigateToPose")
    with pytest.raises(ConfigError, match="blackboard or worldmodel"):
        Ros2SensorBridge("store=disk")
    # The speech field is checked when the library loads, not when the robot is told to speak.
    assert Ros2Speech("type=std_msgs/msg/Header", "field=frame_id").options["field"] == "frame_id"
    with pytest.raises(ConfigError, match=r"field 'text' is not a string field of std_msgs/msg/String \(its string fields: data\)"):
        Ros2Speech("field=text")
    with pytest.raises(ConfigError, match="field 'linear' is not a string field of geometry_msgs/msg/Twist"):
        Ros2Speech("type=geometry_msgs/msg/Twist", "field=linear")


def test_a_query_ends_when_cancelled() -> None:
    """A get that nobody answers yet (a ROS 2 action's result) ends when its caller cancels it."""
    from cmion_mesh.transport.base import IncomingQuery, QueryCancel

    held: list[IncomingQuery] = []
    arrived = threading.Event()

    def hold(query: IncomingQuery) -> None:
        held.append(query)  # answered only when the test says so: never, here
        arrived.set()

    with MemoryTransport(MemoryNetwork()) as transport:
        transport.declare_queryable("0/result", hold)
        cancel = QueryCancel()
        out: list[object] = []
        waiter = threading.Thread(target=lambda: out.append(transport.get("0/result", b"", timeout=60, cancel=cancel)))
        waiter.start()
        assert arrived.wait(5)
        cancel.cancel()
        waiter.join(5)
        assert not waiter.is_alive() and out == [[]]
        held[0].finish()
        cancel.cancel()  # twice: harmless


def test_malformed_messages_are_reported_without_flooding(monkeypatch: pytest.MonkeyPatch) -> None:
    """A robot publishing a topic the mesh cannot decode, at sensor rate: the first refusal is
    reported at once, the next ones at most every MALFORMED_EVERY seconds, counted."""
    twist = "geometry_msgs/msg/Twist"
    with MemoryTransport(MemoryNetwork()) as transport, ros2.Node(transport, "n") as node:
        reports: list[str] = []
        good: list[object] = []
        node.subscribe("cmd_vel", twist, good.append, on_malformed=reports.append)
        key = ros2.topic_key(0, "/cmd_vel", twist, node.types.hash(twist))
        for _ in range(50):
            transport.publish(key, b"\x00\x01\x00\x00short", attachment=ros2.encode_attachment(1, bytes(16)))
        transport.publish(key, node.types.encode(twist, {"linear": {"x": 1.0}}), attachment=ros2.encode_attachment(2, bytes(16)))
        wait_for(lambda: len(good) == 1, 10, "the good message after the bad ones")
        assert len(reports) == 1 and "refused a message on /cmd_vel" in reports[0] and "more refused" not in reports[0]
        monkeypatch.setattr(ros2, "MALFORMED_EVERY", 0.0)
        transport.publish(key, b"", attachment=ros2.encode_attachment(3, bytes(16)))
        wait_for(lambda: len(reports) == 2, 10, "the next report")
        # the next report counts the 49 held back since the first
        assert reports[1].endswith("(49 more refused since the last report)"), reports[1]


def test_an_action_loaded_from_its_action_file_has_the_installed_type_hashes() -> None:
    """An action outside rosbags' store (test_msgs' Fibonacci) loads from its .action file in a ROS
    share folder, for the rmw_zenoh way; its hashes are those rosidl wrote beside it."""
    import json
    import sys
    from pathlib import Path

    share = Path(sys.prefix) / "share" / "test_msgs" / "action"
    if not (share / "Fibonacci.json").is_file():
        pytest.skip("test_msgs is not installed (the ros2 extra: pip install 'cmion-mesh[ros2]')")
    installed = {h["type_name"]: h["hash_string"] for h in json.loads((share / "Fibonacci.json").read_text())["type_hashes"]}
    types = Types()
    assert not types.known("test_msgs/action/Fibonacci_SendGoal")
    assert types.known_action("test_msgs/action/Fibonacci")
    for part in ("SendGoal", "GetResult", "FeedbackMessage", "Goal", "Result", "Feedback"):
        name = f"test_msgs/action/Fibonacci_{part}"
        assert types.hash(name) == installed[name], name
    assert not types.known_action("test_msgs/action/NoSuchAction")


def test_generic_action_parameters() -> None:
    from cmion_mesh.ros2.competencies import Ros2Action

    nav = Ros2Action("action=navigate_to_pose", "action_type=nav2_msgs/action/NavigateToPose", "competency_type=Dock",
                     "goal.pose.header.frame_id=map", "goal.behavior_tree=\"\"")
    assert (nav.type, nav.name, nav.bb) == ("Dock", "Dock", "navigate_to_pose")
    assert nav.fixed == {"pose": {"header": {"frame_id": "map"}}, "behavior_tree": ""}
    with pytest.raises(ConfigError, match="give action="):
        Ros2Action("action_type=nav2_msgs/action/NavigateToPose")
    with pytest.raises(ConfigError, match="not an action type"):
        Ros2Action("action=x", "action_type=std_msgs/msg/String")
    with pytest.raises(ConfigError, match="not a ROS 2 Jazzy type known here"):
        Ros2Action("action=x", "action_type=my_msgs/action/Nothing")
    with pytest.raises(ConfigError, match=r"transport 'dds' \(one of: rmw_zenoh, rclpy\)"):
        Ros2Action("action=x", "action_type=nav2_msgs/action/NavigateToPose", "transport=dds")
