"""The stand-in ROS 2 robot (tests/helpers/ros2_robot_standin.py) against the facts of rmw_zenoh it claims.

One stand-in process on a loopback endpoint; the test process talks to it over a plain zenoh
session with hand-written CDR, so that what is checked here is the wire format, not the
stand-in's own encoder. The type hashes are checked against real ROS 2 constants.
"""

from __future__ import annotations

import json
import queue
import struct
import sys
import time
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh
import zenoh.ext

from cmion_mesh.procs import Daemon, free_port
from tests.helpers import ros2_robot_standin as standin

DOMAIN = 7
NS = "robot1"
SEND_GOAL = ("7/robot1/navigate_to_pose/_action/send_goal/nav2_msgs::action::dds_::NavigateToPose_SendGoal_/"
             "RIHS01_a4fcb3bee1bf32e21a0e541a943b221aa0826996e2c98f079b47022b256f48b5")
GET_RESULT = ("7/robot1/navigate_to_pose/_action/get_result/nav2_msgs::action::dds_::NavigateToPose_GetResult_/"
              "RIHS01_c407920357d566771e8882b4ef4d1f1a84ee922d609920ccd57faa6d6e391dc5")
FEEDBACK = ("7/robot1/navigate_to_pose/_action/feedback/nav2_msgs::action::dds_::NavigateToPose_FeedbackMessage_/"
            "RIHS01_9d1f6fa2eb975ce733b419ac2e97b134d8ff92b6478b6559feed9a50bdfd82b3")
STATUS = ("7/robot1/navigate_to_pose/_action/status/action_msgs::msg::dds_::GoalStatusArray_/"
          "RIHS01_6c1684b00f177d37438febe6e709fc4e2b0d4248dca4854946f9ed8b30cda83e")
CMD_VEL = "7/robot1/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
SPEECH = "7/robot1/speech/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
CLIENT_GID = bytes(range(100, 116))


def test_computed_type_hashes_equal_the_real_ros2_constants() -> None:
    for name, expected in standin.KNOWN_HASHES.items():
        assert standin.type_hash(name) == expected, name


def attachment(sequence: int, gid: bytes = CLIENT_GID) -> bytes:
    # rmw_zenoh design.md: int64 sequence number, int64 timestamp, GID length byte, GID
    return struct.pack("<qq", sequence, time.time_ns()) + bytes([len(gid)]) + gid


def cdr_string(s: str, offset: int) -> tuple[bytes, int]:
    """A CDR string starting at ``offset`` (relative to after the encapsulation header)."""
    pad = b"\x00" * (-offset % 4)
    data = s.encode() + b"\x00"
    out = pad + struct.pack("<I", len(data)) + data
    return out, offset + len(out)


def send_goal_request(goal_id: bytes, frame: str, xyz: tuple[float, float, float], bt: str) -> bytes:
    body = goal_id + struct.pack("<iI", 12, 34)               # UUID, header.stamp (offset 16 -> 24)
    frame_bytes, off = cdr_string(frame, len(body))
    body += frame_bytes
    body += b"\x00" * (-off % 8)                               # float64 alignment
    body += struct.pack("<7d", *xyz, 0.0, 0.0, 0.0, 1.0)
    bt_bytes, _ = cdr_string(bt, len(body))
    return b"\x00\x01\x00\x00" + body + bt_bytes


class Standin:
    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.proc = Daemon([sys.executable, "-m", "tests.helpers.ros2_robot_standin", "--listen", self.endpoint, "--domain", str(DOMAIN),
                            "--namespace", NS, "--feedback", "2", "--feedback-interval", "0.02"], name="standin", stdin=True)
        ready = self.event("ready", 20)
        self.zid = ready["zid"]

    def event(self, kind: str, timeout: float = 10.0, **first: Any) -> dict[str, Any]:
        """The first event of ``kind`` whose leading fields are ``first`` (the stand-in prints them in order)."""
        return dict(json.loads(self.proc.wait_line(json.dumps({"event": kind, **first})[:-1], timeout)))


@pytest.fixture(scope="module")
def robot() -> Iterator[Standin]:
    s = Standin()
    try:
        yield s
    finally:
        s.proc.stop()


@pytest.fixture(scope="module")
def session(robot: Standin) -> Iterator[zenoh.Session]:
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("connect/endpoints", json.dumps([robot.endpoint]))
    s = zenoh.open(config)
    try:
        yield s
    finally:
        s.close()  # type: ignore[no-untyped-call]


def tokens(session: zenoh.Session, robot: Standin) -> list[str]:
    """The stand-in's liveliness tokens, once they (and so its declarations) have reached us."""
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        found = [str(r.ok.key_expr) for r in session.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=2) if r.ok]
        mine = [k for k in found if k.split("/")[2] == robot.zid]
        if len(mine) >= 8:
            return mine
    raise TimeoutError(f"tokens of {robot.zid} not all seen: {found}")


def test_the_standin_speaks_rmw_zenoh(robot: Standin, session: zenoh.Session) -> None:
    # Liveliness tokens as rmw_zenoh's liveliness_utils.cpp builds them
    found = tokens(session, robot)
    prefix = f"@ros2_lv/{DOMAIN}/{robot.zid}/0"
    assert f"{prefix}/0/NN/%/%robot1/standin_robot" in found
    by_topic = {k.split("/")[9]: k.split("/") for k in found if len(k.split("/")) == 13}
    send_goal = by_topic["%robot1%navigate_to_pose%_action%send_goal"]
    assert send_goal[5] == "SS" and "/".join(send_goal[10:12]) == "/".join(SEND_GOAL.split("/")[-2:])
    assert send_goal[12] == "::,10:,:,:,,"
    status = by_topic["%robot1%navigate_to_pose%_action%status"]
    assert status[5] == "MP" and status[10] == "action_msgs::msg::dds_::GoalStatusArray_" and status[12] == ":1:,1:,:,:,,"
    cmd_vel = by_topic["%robot1%cmd_vel"]
    assert cmd_vel[5] == "MS" and "/".join(cmd_vel[10:12]) == "/".join(CMD_VEL.split("/")[-2:])
    assert len({k.split("/")[4] for k in found}) == len(found), "entity ids are unique"

    # A node token of another session is reported, and its end too. Declared after the feedback
    # subscriber: once the stand-in sees the token, it has the subscriber too (one ordered link).
    feedback: queue.SimpleQueue[zenoh.Sample] = queue.SimpleQueue()
    feedback_sub = session.declare_subscriber(FEEDBACK, feedback.put)
    token = session.liveliness().declare_token(f"@ros2_lv/{DOMAIN}/{session.zid()}/0/0/NN/%/%/mesh_body")
    seen = robot.event("node_seen", name="mesh_body")
    assert (seen["namespace"], seen["zid"]) == ("/", str(session.zid()))
    token.undeclare()  # type: ignore[no-untyped-call]
    robot.event("node_gone", name="mesh_body")

    # send_goal: accepted, and the reply carries the request's sequence number and client GID
    goal_id = bytes(range(16))
    replies = list(session.get(SEND_GOAL, payload=send_goal_request(goal_id, "map", (1.5, -2.0, 0.0), "bt.xml"),
                               attachment=attachment(41), target=zenoh.QueryTarget.ALL_COMPLETE, timeout=10))
    assert len(replies) == 1 and replies[0].ok is not None, replies
    reply = replies[0].ok
    assert reply.payload.to_bytes()[:5] == b"\x00\x01\x00\x00\x01"         # header, accepted = true
    assert reply.attachment is not None
    att = reply.attachment.to_bytes()
    assert struct.unpack_from("<q", att)[0] == 41 and att[16] == 16 and att[17:] == CLIENT_GID
    goal = robot.event("goal", goal_id=goal_id.hex())
    assert (goal["frame_id"], goal["x"], goal["y"], goal["qw"], goal["behavior_tree"]) == ("map", 1.5, -2.0, 1.0, "bt.xml")

    # get_result: answered once the goal succeeded (status 4), with the right sequence number
    replies = list(session.get(GET_RESULT, payload=b"\x00\x01\x00\x00" + goal_id, attachment=attachment(42),
                               target=zenoh.QueryTarget.ALL_COMPLETE, timeout=10))
    assert len(replies) == 1 and replies[0].ok is not None, replies
    assert replies[0].ok.attachment is not None
    assert struct.unpack_from("<q", replies[0].ok.attachment.to_bytes())[0] == 42
    assert replies[0].ok.payload.to_bytes()[4] == 4
    assert robot.event("result", goal_id=goal_id.hex())["status"] == 4
    sample = feedback.get(timeout=10)
    assert sample.payload.to_bytes()[4:20] == goal_id                              # FeedbackMessage.goal_id
    assert sample.attachment is not None and len(sample.attachment.to_bytes()) == 33
    feedback_sub.undeclare()  # type: ignore[no-untyped-call]

    # status is transient local: a subscriber arriving now still gets the last GoalStatusArray
    statuses: queue.SimpleQueue[zenoh.Sample] = queue.SimpleQueue()
    late = zenoh.ext.declare_advanced_subscriber(
        session, STATUS, statuses.put, history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
    last = statuses.get(timeout=10).payload.to_bytes()
    assert last[4:8] == b"\x01\x00\x00\x00" and last[8:24] == goal_id and last[-1] == 4  # one goal, SUCCEEDED
    late.undeclare()  # type: ignore[no-untyped-call]

    # cmd_vel: a Twist published with an rmw_zenoh attachment becomes a cmd_vel event
    twist = b"\x00\x01\x00\x00" + struct.pack("<6d", 0.5, 0.0, 0.0, 0.0, 0.0, -0.25)
    session.put(CMD_VEL, twist, attachment=attachment(1))
    assert robot.event("cmd_vel") == {"event": "cmd_vel", "linear": [0.5, 0.0, 0.0], "angular": [0.0, 0.0, -0.25]}

    # speech: a std_msgs/String
    text, _ = cdr_string("hello, robot", 0)
    session.put(SPEECH, b"\x00\x01\x00\x00" + text, attachment=attachment(1))
    assert robot.event("speech")["data"] == "hello, robot"

    # A malformed Twist is reported, and the stand-in goes on
    session.put(CMD_VEL, b"\x00\x01\x00\x00\x01\x02", attachment=attachment(2))
    assert "truncated" in robot.event("error")["what"]

    # "exit" on stdin: a clean shutdown
    robot.proc.send("exit")
    assert robot.proc.proc.wait(15) == 0
