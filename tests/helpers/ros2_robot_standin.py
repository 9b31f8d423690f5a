"""A stand-in ROS 2 robot speaking rmw_zenoh's wire format (ROS 2 Jazzy), for the ROS 2 body's tests.

Run as ``python -m tests.helpers.ros2_robot_standin [options]``; the command line and the JSON lines it
prints are fixed by the stand-in contract (options in ``parse_args`` below). It plays a Nav2 robot:
a node serving the ``navigate_to_pose`` action (nav2_msgs/action/NavigateToPose), subscribing to
``cmd_vel`` (geometry_msgs/msg/Twist) and ``speech`` (std_msgs/msg/String), optionally publishing
``odom`` (nav_msgs/msg/Odometry), and reporting the ROS nodes of other zenoh sessions.

It is written from the specifications, independently of the code under test: it imports only
zenoh and the standard library (CDR by hand with ``struct``, type hashes with ``hashlib``).

What of rmw_zenoh it implements, and where each fact comes from:

* Data key expressions (rmw_zenoh docs/design.md "Topic and Service name mapping to Zenoh key
  expressions"; liveliness_utils.cpp ``TopicInfo``: ``strip_slashes(name)``):
  ``<domain>/<fully qualified name without leading slash>/<DDS type name>/<RIHS01 hash>``, e.g.
  ``0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...``. The DDS type name is
  ``pkg::msg::dds_::Name_``; a service (and an action's service) uses the *service* type name
  (``pkg::srv::dds_::Name_``, the response type's name without ``Response_``:
  rmw_service_data.cpp) and the service type's hash, in the key and in the token alike.
* Liveliness tokens (design.md "Graph Cache"; liveliness_utils.cpp ``Entity::Entity``):
  ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<NN|MP|MS|SS|SC>/<enclave>/<namespace>/<node>`` and, for
  other than nodes, ``/<topic>/<type>/<hash>/<qos>``; enclave, namespace, node and topic names
  are "mangled": every ``/`` becomes ``%`` (so the root namespace is ``%``, ``/cmd_vel`` is
  ``%cmd_vel``). A node token repeats the node id as entity id. ``<zid>`` is the session's zenoh
  id as zenoh prints it. Node and entity ids come from one counter per context (the design.md
  example has a node 0 whose subscription is entity 10); here the node is 0, its entities 1...
* QoS in tokens (liveliness_utils.cpp ``qos_to_keyexpr``): ``rel:dur:hist,depth:dl_s,dl_ns:
  ls_s,ls_ns:liv,lease_s,lease_ns``, each field left empty when equal to rmw_zenoh's default
  (reliable, volatile, keep-last 42, infinite durations, automatic liveliness). So the rclcpp
  default (keep-last 10) is ``::,10:,:,:,,`` (design.md's examples) and an action's status topic
  (transient local, depth 1: rcl_action's status QoS) is ``:1:,1:,:,:,,``.
* Attachments (design.md "Publishers", "Service Clients", "Service Servers";
  attachment_helpers.cpp, zenoh ext serializer): 8 bytes sequence number (int64 LE), 8 bytes source
  timestamp (ns since the epoch, int64 LE), 1 byte GID length (16), 16 bytes GID. A service reply
  carries the *request's* sequence number and client GID: that is how the client matches it
  (rmw_client_data.cpp ``take_response``). rmw_zenoh drops a sample or request without one
  (rmw_subscription_data.cpp, rmw_service_data.cpp); the stand-in reports it as an error.
* Services are queryables declared ``complete`` (design.md "Service Servers"); a request is a
  query whose payload is the CDR request and whose attachment is as above; rmw_zenoh's clients
  ask with target ALL_COMPLETE, no consolidation and no timeout (rmw_client_data.cpp), so a
  get_result may wait as long as the goal runs.
* Actions (ROS 2 design "actions", rcl_action names): services ``<action>/_action/send_goal``,
  ``.../cancel_goal`` (action_msgs/srv/CancelGoal), ``.../get_result``; topics
  ``.../feedback`` (``<Action>_FeedbackMessage``) and ``.../status`` (action_msgs/msg/
  GoalStatusArray). get_result is answered when the goal reaches a terminal state.
* CDR (rmw_zenoh uses Fast CDR, XCDR1 little endian): a 4-byte encapsulation header
  ``00 01 00 00``, then primitives aligned to their size *relative to the end of that header*;
  strings are uint32 length (with the NUL), bytes, NUL; sequences uint32 count then elements;
  fixed arrays (UUID's uint8[16]) are the bare elements.
* RIHS01 type hashes (REP 2011, rosidl_generator_type_description): sha256 of the JSON of the
  type description (type name, fields: name and type id/capacity/string capacity/nested type;
  the referenced types sorted by name; no default values, no constants) with ``", "``/``": "``
  separators. Implemented here from the REP; ``KNOWN_HASHES`` holds real constants of ROS 2
  that the computed ones are checked against (tests/test_ros2_standin.py), each with its origin.
* Messages as in Jazzy: NavigateToPose from navigation2's jazzy branch (goal: PoseStamped pose,
  string behavior_tree; result: uint16 error_code, string error_msg; feedback: PoseStamped
  current_pose, Duration navigation_time, Duration estimated_time_remaining, int16
  number_of_recoveries, float32 distance_remaining); action_msgs GoalInfo/GoalStatus/CancelGoal;
  unique_identifier_msgs/UUID; builtin_interfaces Time/Duration; service_msgs/ServiceEventInfo.

Not reproduced: rmw_zenoh's GIDs are an XXH3-128 of the liveliness key; these are the first 16
bytes of its sha256 (GIDs are opaque to peers). No parameter services, no type description
service, no ``ros_discovery_info``: only the entities listed above.

The status topic is transient local (rcl_action), so, as rmw_publisher_data.cpp does for such
publishers, it is a zenoh advanced publisher with a cache of one sample, publisher detection and
sporadic heartbeats every 500 ms: a late subscriber asking for history gets the last status.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import heapq
import json
import math
import queue
import re
import signal
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh
import zenoh.ext

# --------------------------------------------------------------------------------------------
# Type descriptions and RIHS01 hashes (REP 2011)

# type_description_interfaces/msg/FieldType: the primitive ids; +48 fixed array, +96 bounded
# sequence, +144 unbounded sequence. ``char`` in .msg files is uint8 in IDL.
_PRIMITIVE_IDS = {"int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7, "int64": 8, "uint64": 9,
                  "float32": 10, "float64": 11, "bool": 15, "byte": 16, "string": 17}
_NESTED = 1

# (field name, type, array kind or "", capacity)
Field = tuple[str, str, str, int]
TYPES: dict[str, list[Field]] = {}


def _msg(name: str, *fields: str) -> None:
    """Register ``name`` with fields written as in a .msg file: ``"float64[36] covariance"``."""
    parsed: list[Field] = []
    for text in fields:
        ftype, fname = text.split()
        kind, cap = "", 0
        if ftype.endswith("]"):
            ftype, bracket = ftype[:-1].split("[")
            if bracket.startswith("<="):
                kind, cap = "bounded", int(bracket[2:])
            elif bracket:
                kind, cap = "array", int(bracket)
            else:
                kind = "sequence"
        parsed.append((fname, ftype, kind, cap))
    TYPES[name] = parsed


def _srv(name: str, request: tuple[str, ...], response: tuple[str, ...]) -> None:
    """A service type as rosidl generates it: Request, Response, Event and the service itself."""
    _msg(f"{name}_Request", *request)
    _msg(f"{name}_Response", *response)
    _msg(f"{name}_Event", "service_msgs/msg/ServiceEventInfo info", f"{name}_Request[<=1] request",
         f"{name}_Response[<=1] response")
    _msg(name, f"{name}_Request request_message", f"{name}_Response response_message", f"{name}_Event event_message")


def _action(name: str, goal: tuple[str, ...], result: tuple[str, ...], feedback: tuple[str, ...]) -> None:
    """An action type as rosidl generates it (the implicit Goal/Result/Feedback and services)."""
    _msg(f"{name}_Goal", *goal)
    _msg(f"{name}_Result", *result)
    _msg(f"{name}_Feedback", *feedback)
    uuid = "unique_identifier_msgs/msg/UUID"
    _srv(f"{name}_SendGoal", (f"{uuid} goal_id", f"{name}_Goal goal"), ("bool accepted", "builtin_interfaces/msg/Time stamp"))
    _srv(f"{name}_GetResult", (f"{uuid} goal_id",), ("int8 status", f"{name}_Result result"))
    _msg(f"{name}_FeedbackMessage", f"{uuid} goal_id", f"{name}_Feedback feedback")
    _msg(name, f"{name}_Goal goal", f"{name}_Result result", f"{name}_Feedback feedback",
         f"{name}_SendGoal send_goal_service", f"{name}_GetResult get_result_service",
         f"{name}_FeedbackMessage feedback_message")


_msg("builtin_interfaces/msg/Time", "int32 sec", "uint32 nanosec")
_msg("builtin_interfaces/msg/Duration", "int32 sec", "uint32 nanosec")
_msg("std_msgs/msg/Header", "builtin_interfaces/msg/Time stamp", "string frame_id")
_msg("std_msgs/msg/String", "string data")
_msg("geometry_msgs/msg/Point", "float64 x", "float64 y", "float64 z")
_msg("geometry_msgs/msg/Quaternion", "float64 x", "float64 y", "float64 z", "float64 w")
_msg("geometry_msgs/msg/Vector3", "float64 x", "float64 y", "float64 z")
_msg("geometry_msgs/msg/Pose", "geometry_msgs/msg/Point position", "geometry_msgs/msg/Quaternion orientation")
_msg("geometry_msgs/msg/PoseStamped", "std_msgs/msg/Header header", "geometry_msgs/msg/Pose pose")
_msg("geometry_msgs/msg/Twist", "geometry_msgs/msg/Vector3 linear", "geometry_msgs/msg/Vector3 angular")
_msg("geometry_msgs/msg/PoseWithCovariance", "geometry_msgs/msg/Pose pose", "float64[36] covariance")
_msg("geometry_msgs/msg/TwistWithCovariance", "geometry_msgs/msg/Twist twist", "float64[36] covariance")
_msg("nav_msgs/msg/Odometry", "std_msgs/msg/Header header", "string child_frame_id",
     "geometry_msgs/msg/PoseWithCovariance pose", "geometry_msgs/msg/TwistWithCovariance twist")
_msg("unique_identifier_msgs/msg/UUID", "uint8[16] uuid")
_msg("service_msgs/msg/ServiceEventInfo", "uint8 event_type", "builtin_interfaces/msg/Time stamp", "uint8[16] client_gid",
     "int64 sequence_number")
_msg("action_msgs/msg/GoalInfo", "unique_identifier_msgs/msg/UUID goal_id", "builtin_interfaces/msg/Time stamp")
_msg("action_msgs/msg/GoalStatus", "action_msgs/msg/GoalInfo goal_info", "int8 status")
_msg("action_msgs/msg/GoalStatusArray", "action_msgs/msg/GoalStatus[] status_list")
_srv("action_msgs/srv/CancelGoal", ("action_msgs/msg/GoalInfo goal_info",),
     ("int8 return_code", "action_msgs/msg/GoalInfo[] goals_canceling"))
_srv("example_interfaces/srv/AddTwoInts", ("int64 a", "int64 b"), ("int64 sum",))  # only to check the hashing
_action("nav2_msgs/action/NavigateToPose",
        ("geometry_msgs/msg/PoseStamped pose", "string behavior_tree"),
        ("uint16 error_code", "string error_msg"),
        ("geometry_msgs/msg/PoseStamped current_pose", "builtin_interfaces/msg/Duration navigation_time",
         "builtin_interfaces/msg/Duration estimated_time_remaining", "int16 number_of_recoveries",
         "float32 distance_remaining"))

# Real constants of ROS 2 (Jazzy), to check ``type_hash`` against:
KNOWN_HASHES = {
    # rmw_zenoh docs/design.md, key expression examples
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "example_interfaces/srv/AddTwoInts": "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a",
    # rosidl_generator_c output for nav2_msgs (jazzy definition) committed in a public workspace
    # (AliaksandrNazaruk/ros2_ws build/nav2_msgs/.../navigate_to_pose__description.c), including
    # its EXPECTED_HASH constants of the referenced types
    "nav2_msgs/action/NavigateToPose": "RIHS01_a56dba8a3234a1215e610180dc703ae25bbf406dded8b54887891c9732857eab",
    "nav2_msgs/action/NavigateToPose_SendGoal": "RIHS01_a4fcb3bee1bf32e21a0e541a943b221aa0826996e2c98f079b47022b256f48b5",
    "nav2_msgs/action/NavigateToPose_GetResult": "RIHS01_c407920357d566771e8882b4ef4d1f1a84ee922d609920ccd57faa6d6e391dc5",
    "nav2_msgs/action/NavigateToPose_FeedbackMessage":
        "RIHS01_9d1f6fa2eb975ce733b419ac2e97b134d8ff92b6478b6559feed9a50bdfd82b3",
    "unique_identifier_msgs/msg/UUID": "RIHS01_1b8e8aca958cbea28fe6ef60bf6c19b683c97a9ef60bb34752067d0f2f7ab437",
    "builtin_interfaces/msg/Time": "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197",
    "builtin_interfaces/msg/Duration": "RIHS01_e8d009f659816f758b75334ee1a9ca5b5c0b859843261f14c7f937349599d93b",
    "geometry_msgs/msg/PoseStamped": "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "std_msgs/msg/Header": "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
    "service_msgs/msg/ServiceEventInfo": "RIHS01_41bcbbe07a75c9b52bc96bfd5c24d7f0fc0a08c0cb7921b3373c5732345a6f45",
    # third-party rmw_zenoh clients' constants (two independent code bases agree on the Twist one)
    "geometry_msgs/msg/Twist": "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a",
    "action_msgs/msg/GoalStatusArray": "RIHS01_6c1684b00f177d37438febe6e709fc4e2b0d4248dca4854946f9ed8b30cda83e",
    "nav_msgs/msg/Odometry": "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    # ros2_documentation "Understanding actions": ``ros2 action info --verbose`` output
    "action_msgs/srv/CancelGoal": "RIHS01_573d8b0a534451d7bc2ac8c5ffde8ac14b8593b7001175d0cd6516dcbeb8689a",
}


def _type_json(name: str) -> dict[str, Any]:
    fields = []
    for fname, ftype, kind, cap in TYPES[name]:
        type_id = _PRIMITIVE_IDS.get(ftype, _NESTED) + {"": 0, "array": 48, "bounded": 96, "sequence": 144}[kind]
        fields.append({"name": fname, "type": {"type_id": type_id, "capacity": cap, "string_capacity": 0,
                                              "nested_type_name": "" if ftype in _PRIMITIVE_IDS else ftype}})
    return {"type_name": name, "fields": fields}


def _referenced(name: str, found: set[str]) -> set[str]:
    for _, ftype, _, _ in TYPES[name]:
        if ftype not in _PRIMITIVE_IDS and ftype not in found:
            found.add(ftype)
            _referenced(ftype, found)
    return found


@functools.cache
def type_hash(name: str) -> str:
    """The RIHS01 hash of a registered type (``"pkg/msg/Name"``), computed as REP 2011 says."""
    description = {"type_description": _type_json(name),
                   "referenced_type_descriptions": [_type_json(r) for r in sorted(_referenced(name, set()))]}
    text = json.dumps(description, separators=(", ", ": "), ensure_ascii=True)
    return "RIHS01_" + hashlib.sha256(text.encode()).hexdigest()


def dds_type_name(name: str) -> str:
    """``nav2_msgs/action/NavigateToPose_SendGoal`` -> ``nav2_msgs::action::dds_::NavigateToPose_SendGoal_``."""
    package, kind, short = name.split("/")
    return f"{package}::{kind}::dds_::{short}_"


# --------------------------------------------------------------------------------------------
# CDR (XCDR1, little endian)

CDR_HEADER = b"\x00\x01\x00\x00"


class CdrWriter:
    def __init__(self) -> None:
        self.buf = bytearray()

    def _prim(self, fmt: str, value: Any) -> CdrWriter:
        size = struct.calcsize(fmt)
        self.buf += b"\x00" * (-len(self.buf) % size)
        self.buf += struct.pack("<" + fmt, value)
        return self

    def i8(self, v: int) -> CdrWriter: return self._prim("b", v)
    def u8(self, v: int) -> CdrWriter: return self._prim("B", v)
    def i16(self, v: int) -> CdrWriter: return self._prim("h", v)
    def u16(self, v: int) -> CdrWriter: return self._prim("H", v)
    def i32(self, v: int) -> CdrWriter: return self._prim("i", v)
    def u32(self, v: int) -> CdrWriter: return self._prim("I", v)
    def f32(self, v: float) -> CdrWriter: return self._prim("f", v)
    def f64(self, v: float) -> CdrWriter: return self._prim("d", v)
    def boolean(self, v: bool) -> CdrWriter: return self._prim("B", 1 if v else 0)

    def string(self, s: str) -> CdrWriter:
        data = s.encode() + b"\x00"
        self.u32(len(data))
        self.buf += data
        return self

    def raw(self, data: bytes) -> CdrWriter:
        self.buf += data
        return self

    def bytes(self) -> bytes:
        return CDR_HEADER + bytes(self.buf)


class CdrReader:
    """Reads a CDR payload; ``ValueError`` on anything short, oversized or not little-endian CDR."""

    def __init__(self, payload: bytes) -> None:
        if len(payload) < 4 or payload[:2] != b"\x00\x01":
            raise ValueError(f"not a little-endian CDR payload (header {payload[:4].hex() or 'missing'})")
        self.data = payload[4:]
        self.pos = 0

    def _prim(self, fmt: str) -> Any:
        size = struct.calcsize(fmt)
        self.pos += -self.pos % size
        if self.pos + size > len(self.data):
            raise ValueError(f"truncated CDR: need {size} bytes at offset {self.pos}, have {len(self.data) - self.pos}")
        (value,) = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return value

    def i8(self) -> int: return int(self._prim("b"))
    def u8(self) -> int: return int(self._prim("B"))
    def i16(self) -> int: return int(self._prim("h"))
    def u16(self) -> int: return int(self._prim("H"))
    def i32(self) -> int: return int(self._prim("i"))
    def u32(self) -> int: return int(self._prim("I"))
    def f32(self) -> float: return float(self._prim("f"))
    def f64(self) -> float: return float(self._prim("d"))
    def boolean(self) -> bool: return bool(self._prim("B") != 0)

    def raw(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise ValueError(f"truncated CDR: need {n} bytes at offset {self.pos}, have {len(self.data) - self.pos}")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return bytes(out)

    def string(self) -> str:
        n = self.u32()
        if n == 0 or n > len(self.data) - self.pos:
            raise ValueError(f"bad CDR string length {n} at offset {self.pos}")
        data = self.raw(n)
        if data[-1] != 0:
            raise ValueError("CDR string without its terminating NUL")
        return data[:-1].decode()  # UnicodeDecodeError is a ValueError


def _time_now(w: CdrWriter) -> None:
    ns = time.time_ns()
    w.i32(ns // 1_000_000_000).u32(ns % 1_000_000_000)


def _duration(w: CdrWriter, seconds: float) -> None:
    seconds = max(0.0, seconds)
    w.i32(int(seconds)).u32(int((seconds % 1) * 1e9))


# --------------------------------------------------------------------------------------------
# Attachments, names, tokens

def attachment(sequence: int, gid: bytes) -> bytes:
    return struct.pack("<qqB", sequence, time.time_ns(), len(gid)) + gid


def parse_attachment(raw: bytes | None) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp, GID) of an rmw_zenoh attachment; ``ValueError`` if malformed."""
    if raw is None:
        raise ValueError("no attachment (rmw_zenoh sends sequence number, timestamp and GID)")
    if len(raw) != 33 or raw[16] != 16:
        raise ValueError(f"attachment of {len(raw)} bytes, expected 33 (int64, int64, length 16, 16-byte GID)")
    sequence, stamp = struct.unpack_from("<qq", raw)
    return sequence, stamp, bytes(raw[17:33])


def mangle(name: str) -> str:
    return name.replace("/", "%")


QOS_DEFAULT = "::,10:,:,:,,"           # reliable, volatile, keep last 10 (rclcpp and services default)
QOS_STATUS = ":1:,1:,:,:,,"            # transient local, keep last 1 (rcl_action status)
STATUS_NAMES = {1: "ACCEPTED", 2: "EXECUTING", 3: "CANCELING", 4: "SUCCEEDED", 5: "CANCELED", 6: "ABORTED"}
SUCCEEDED, CANCELED, ABORTED = 4, 5, 6


@dataclass
class Entity:
    kind: str              # MP MS SS SC
    topic: str             # fully qualified ROS name, e.g. /navigate_to_pose/_action/send_goal
    type_name: str         # pkg/kind/Name, of the message or service
    qos: str = QOS_DEFAULT
    eid: int = 0
    sequence: int = 0
    gid: bytes = b""
    key: str = ""          # the data key expression
    token_key: str = ""    # the liveliness token


def emit(event: str, **fields: Any) -> None:
    with _print_lock:
        print(json.dumps({"event": event, **fields}), flush=True)


_print_lock = threading.Lock()


# --------------------------------------------------------------------------------------------
# The robot

@dataclass
class Goal:
    goal_id: bytes
    frame_id: str
    target: tuple[float, float, float]
    accepted_ns: int
    status: int = 1
    start: float = field(default_factory=time.monotonic)
    feedback_sent: int = 0
    result_queries: list[tuple[Any, int, bytes]] = field(default_factory=list)


class StandinRobot:
    """The node, its entities and one worker thread that does everything zenoh callbacks hand it."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        ns = "/" + args.namespace.strip("/") if args.namespace.strip("/") else "/"
        self.namespace = ns
        self.inbox: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self.stop = threading.Event()
        self.goals: dict[bytes, Goal] = {}
        self.timers: list[tuple[float, int, str, Any]] = []
        self._timer_seq = 0
        self.declared: list[Any] = []
        self.seen: dict[str, tuple[str, str, str]] = {}
        config = zenoh.Config()
        config.insert_json5("mode", '"peer"')
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("connect/endpoints", json.dumps(list(args.connect or [])))
        config.insert_json5("listen/endpoints", json.dumps([args.listen] if args.listen else []))
        self.session = zenoh.open(config)
        self.zid = str(self.session.info.zid())
        self.worker = threading.Thread(target=self._work, name="standin-worker")

    def fqn(self, name: str) -> str:
        if name.startswith("/"):
            return name
        return (self.namespace.rstrip("/") + "/" + name) if self.namespace != "/" else "/" + name

    def token_prefix(self, eid: int, kind: str) -> str:
        return f"@ros2_lv/{self.args.domain}/{self.zid}/0/{eid}/{kind}/%/{mangle(self.namespace)}/{mangle(self.args.node_name)}"

    def _entity(self, entity: Entity, eid: int) -> Entity:
        entity.eid = eid
        entity.key = f"{self.args.domain}/{entity.topic.strip('/')}/{dds_type_name(entity.type_name)}/{type_hash(entity.type_name)}"
        entity.token_key = (f"{self.token_prefix(eid, entity.kind)}/{mangle(entity.topic)}/"
                            f"{dds_type_name(entity.type_name)}/{type_hash(entity.type_name)}/{entity.qos}")
        entity.gid = hashlib.sha256(entity.token_key.encode()).digest()[:16]
        return entity

    def open(self) -> None:
        args = self.args
        action = self.fqn(args.action_name) + "/_action"
        nav = "nav2_msgs/action/NavigateToPose"
        specs = [
            ("send_goal", Entity("SS", f"{action}/send_goal", f"{nav}_SendGoal")),
            ("cancel_goal", Entity("SS", f"{action}/cancel_goal", "action_msgs/srv/CancelGoal")),
            ("get_result", Entity("SS", f"{action}/get_result", f"{nav}_GetResult")),
            ("feedback", Entity("MP", f"{action}/feedback", f"{nav}_FeedbackMessage")),
            ("status", Entity("MP", f"{action}/status", "action_msgs/msg/GoalStatusArray", QOS_STATUS)),
            ("cmd_vel", Entity("MS", self.fqn(args.cmd_vel_topic), "geometry_msgs/msg/Twist")),
            ("speech", Entity("MS", self.fqn(args.speech_topic), "std_msgs/msg/String")),
        ]
        if args.odom_hz > 0:
            specs.append(("odom", Entity("MP", self.fqn("odom"), "nav_msgs/msg/Odometry")))
        self.entities = {name: self._entity(e, i + 1) for i, (name, e) in enumerate(specs)}
        self.publishers: dict[str, Any] = {}
        liveliness = self.session.liveliness()
        self.declared.append(liveliness.declare_subscriber(
            f"@ros2_lv/{self.args.domain}/**", self._to_inbox("liveliness"), history=True))
        self.declared.append(liveliness.declare_token(self.token_prefix(0, "NN")))
        for name, e in self.entities.items():
            if e.kind == "SS":
                self.declared.append(self.session.declare_queryable(e.key, self._to_inbox(name), complete=True))
            elif e.kind == "MS":
                self.declared.append(self.session.declare_subscriber(e.key, self._to_inbox(name)))
            elif e.qos == QOS_STATUS:
                # rmw_publisher_data.cpp: a transient-local publisher is an advanced publisher with a
                # cache of ``depth`` samples, publisher detection and (reliable) sporadic heartbeats.
                self.publishers[name] = zenoh.ext.declare_advanced_publisher(
                    self.session, e.key, cache=zenoh.ext.CacheConfig(1), publisher_detection=True,
                    sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=0.5))
                self.declared.append(self.publishers[name])
            else:
                self.publishers[name] = self.session.declare_publisher(e.key)
                self.declared.append(self.publishers[name])
            self.declared.append(liveliness.declare_token(e.token_key))
        if args.odom_hz > 0:
            self._schedule(0.0, "odom", None)
        self.worker.start()
        emit("ready", zid=self.zid)

    def _to_inbox(self, name: str) -> Callable[[Any], None]:
        """A zenoh callback that only queues: the worker does the work (callbacks never block)."""
        return lambda item: self.inbox.put((name, item))

    def close(self) -> None:
        self.stop.set()
        if self.worker.is_alive():
            self.worker.join(10)
        for goal in self.goals.values():
            for query, _, _ in goal.result_queries:
                self._drop(query)
        for thing in reversed(self.declared):
            try:
                thing.undeclare()
            except Exception:  # shutting down: an entity already gone is fine
                pass
        self.declared.clear()
        if not self.session.is_closed():
            self.session.close()  # type: ignore[no-untyped-call]

    def __enter__(self) -> StandinRobot:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    # -- the worker ---------------------------------------------------------------------------

    def _schedule(self, delay: float, what: str, data: Any) -> None:
        self._timer_seq += 1
        heapq.heappush(self.timers, (time.monotonic() + delay, self._timer_seq, what, data))

    def _work(self) -> None:
        handlers: dict[str, Callable[[Any], None]] = {
            "liveliness": self._on_liveliness, "send_goal": self._on_send_goal, "cancel_goal": self._on_cancel,
            "get_result": self._on_get_result, "cmd_vel": self._on_cmd_vel, "speech": self._on_speech,
        }
        deadline = time.monotonic() + self.args.max_seconds
        while not self.stop.is_set() and time.monotonic() < deadline:
            wait = 0.1 if not self.timers else min(0.1, max(0.0, self.timers[0][0] - time.monotonic()))
            try:
                what, data = self.inbox.get(timeout=wait)
            except queue.Empty:
                pass
            else:
                self._guard(what, handlers[what], data)
            while self.timers and self.timers[0][0] <= time.monotonic():
                _, _, what, data = heapq.heappop(self.timers)
                self._guard(what, self._on_odom if what == "odom" else self._on_step, data)
        self.stop.set()

    def _guard(self, what: str, handler: Callable[[Any], None], data: Any) -> None:
        """Run one handler; whatever it cannot decode becomes an error event, never a crash."""
        try:
            handler(data)
        except Exception as exc:  # the contract: report, never crash
            key = getattr(data, "key_expr", "")
            emit("error", what=f"{what} {key}: {exc}")
            if isinstance(data, zenoh.Query):
                self._drop(data)

    @staticmethod
    def _drop(query: Any) -> None:
        try:
            query.drop()
        except Exception:  # an already finalized query
            pass

    def _publish(self, name: str, payload: bytes) -> None:
        entity = self.entities[name]
        entity.sequence += 1
        self.publishers[name].put(payload, attachment=attachment(entity.sequence, entity.gid))

    def _reply(self, name: str, query: Any, sequence: int, client_gid: bytes, payload: bytes) -> None:
        """Answer a service request: the reply carries the request's sequence number and client GID."""
        query.reply(self.entities[name].key, payload, attachment=attachment(sequence, client_gid))
        self._drop(query)

    # -- graph --------------------------------------------------------------------------------

    def _on_liveliness(self, sample: Any) -> None:
        key = str(sample.key_expr)
        parts = key.split("/")
        if len(parts) < 9 or parts[0] != "@ros2_lv" or parts[5] not in ("NN", "MP", "MS", "SS", "SC") or "" in parts:
            raise ValueError(f"not an rmw_zenoh liveliness token: {key}")
        if parts[5] != "NN" or parts[2] == self.zid:
            return
        node = (parts[8].replace("%", "/"), parts[7].replace("%", "/"), parts[2])
        if sample.kind == zenoh.SampleKind.PUT:
            self.seen[key] = node
            emit("node_seen", name=node[0], namespace=node[1], zid=node[2])
        elif self.seen.pop(key, None) is not None:
            emit("node_gone", name=node[0], namespace=node[1], zid=node[2])

    # -- topics -------------------------------------------------------------------------------

    def _sample_payload(self, sample: Any) -> bytes:
        parse_attachment(sample.attachment.to_bytes() if sample.attachment is not None else None)
        return bytes(sample.payload.to_bytes())

    def _on_cmd_vel(self, sample: Any) -> None:
        r = CdrReader(self._sample_payload(sample))
        linear = [r.f64(), r.f64(), r.f64()]
        angular = [r.f64(), r.f64(), r.f64()]
        emit("cmd_vel", linear=linear, angular=angular)

    def _on_speech(self, sample: Any) -> None:
        emit("speech", data=CdrReader(self._sample_payload(sample)).string())

    def _on_odom(self, _: Any) -> None:
        w = CdrWriter()
        _time_now(w)
        w.string("odom").string("base_link")
        for v in (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0):
            w.f64(v)
        for _i in range(36):
            w.f64(0.0)
        for _i in range(6 + 36):
            w.f64(0.0)
        payload = w.bytes()
        self._publish("odom", payload[: len(payload) // 2] if self.args.malformed else payload)
        self._schedule(1.0 / self.args.odom_hz, "odom", None)

    # -- the action ---------------------------------------------------------------------------

    def _request(self, query: Any) -> tuple[CdrReader, int, bytes]:
        sequence, _, gid = parse_attachment(query.attachment.to_bytes() if query.attachment is not None else None)
        if query.payload is None:
            raise ValueError("request without a payload")
        return CdrReader(bytes(query.payload.to_bytes())), sequence, gid

    def _on_send_goal(self, query: Any) -> None:
        r, sequence, gid = self._request(query)
        goal_id = r.raw(16)
        r.i32(), r.u32()                                   # header.stamp
        frame_id = r.string()
        position = (r.f64(), r.f64(), r.f64())
        orientation = (r.f64(), r.f64(), r.f64(), r.f64())
        behavior_tree = r.string()
        goal = Goal(goal_id, frame_id, position, time.time_ns())
        self.goals[goal_id] = goal
        w = CdrWriter().boolean(True)
        w.i32(goal.accepted_ns // 1_000_000_000).u32(goal.accepted_ns % 1_000_000_000)
        payload = w.bytes()
        self._reply("send_goal", query, sequence, gid, payload[:5] if self.args.malformed else payload)
        emit("goal", goal_id=goal_id.hex(), frame_id=frame_id, x=position[0], y=position[1], z=position[2],
             qx=orientation[0], qy=orientation[1], qz=orientation[2], qw=orientation[3], behavior_tree=behavior_tree)
        self._publish_status()
        self._schedule(self.args.feedback_interval, "step", goal_id)

    def _on_step(self, goal_id: bytes) -> None:
        goal = self.goals.get(goal_id)
        if goal is None or goal.status >= SUCCEEDED or goal.status == 3:
            return
        if goal.status == 1:               # ACCEPTED -> EXECUTING, as rclcpp_action's execute()
            goal.status = 2
            self._publish_status()
        if goal.feedback_sent < self.args.feedback:
            goal.feedback_sent += 1
            self._send_feedback(goal)
            self._schedule(self.args.feedback_interval, "step", goal_id)
        elif self.args.nav == "succeed":
            self._finish(goal, SUCCEEDED)
        elif self.args.nav == "abort":
            self._finish(goal, ABORTED)
        # hang: stays executing until cancelled

    def _send_feedback(self, goal: Goal) -> None:
        left = 1.0 - goal.feedback_sent / max(1, self.args.feedback)
        w = CdrWriter().raw(goal.goal_id)
        _time_now(w)
        w.string(goal.frame_id)
        for v in (goal.target[0] * (1 - left), goal.target[1] * (1 - left), goal.target[2] * (1 - left), 0.0, 0.0, 0.0, 1.0):
            w.f64(v)
        _duration(w, time.monotonic() - goal.start)
        _duration(w, left * self.args.feedback * self.args.feedback_interval)
        w.i16(0)
        w.f32(left * math.dist((0.0, 0.0, 0.0), goal.target))
        payload = w.bytes()
        self._publish("feedback", payload[: len(payload) // 2] if self.args.malformed else payload)

    def _result_payload(self, goal: Goal) -> bytes:
        code, message = (9000, "aborted: the stand-in robot was told to (--nav abort)") if goal.status == ABORTED else (0, "")
        return CdrWriter().i8(goal.status).u16(code).string(message).bytes()

    def _finish(self, goal: Goal, status: int) -> None:
        goal.status = status
        emit("result", goal_id=goal.goal_id.hex(), status=status)
        self._publish_status()
        for query, sequence, gid in goal.result_queries:
            self._reply("get_result", query, sequence, gid, self._result_payload(goal))
        goal.result_queries.clear()

    def _publish_status(self) -> None:
        w = CdrWriter().u32(len(self.goals))
        for goal in self.goals.values():
            w.raw(goal.goal_id)
            w.i32(goal.accepted_ns // 1_000_000_000).u32(goal.accepted_ns % 1_000_000_000)
            w.i8(goal.status)
        self._publish("status", w.bytes())

    def _on_get_result(self, query: Any) -> None:
        r, sequence, gid = self._request(query)
        goal_id = r.raw(16)
        goal = self.goals.get(goal_id)
        if goal is None:  # rcl_action answers an unknown goal with status UNKNOWN (0) and an empty result
            self._reply("get_result", query, sequence, gid, CdrWriter().i8(0).u16(0).string("").bytes())
        elif goal.status >= SUCCEEDED:
            self._reply("get_result", query, sequence, gid, self._result_payload(goal))
        else:
            goal.result_queries.append((query, sequence, gid))

    def _on_cancel(self, query: Any) -> None:
        r, sequence, gid = self._request(query)
        goal_id = r.raw(16)
        stamp = (r.i32(), r.u32())
        every = goal_id == bytes(16)
        stamp_ns = stamp[0] * 1_000_000_000 + stamp[1]
        # action_msgs/srv/CancelGoal.srv: zero id and stamp: all goals; a stamp: also every goal
        # accepted at or before it; an id: that goal.
        chosen = [g for g in self.goals.values()
                  if g.goal_id == goal_id or (every and stamp_ns == 0) or (stamp_ns and g.accepted_ns <= stamp_ns)]
        canceling = [g for g in chosen if g.status < SUCCEEDED]
        if canceling:
            code = 0                       # ERROR_NONE
        elif not every and all(g.goal_id != goal_id for g in chosen):
            code = 2                       # ERROR_UNKNOWN_GOAL_ID
        elif not every:
            code = 3                       # ERROR_GOAL_TERMINATED
        else:
            code = 1                       # ERROR_REJECTED
        w = CdrWriter().i8(code).u32(len(canceling))
        for g in canceling:                # GoalInfo[] goals_canceling
            w.raw(g.goal_id).i32(g.accepted_ns // 1_000_000_000).u32(g.accepted_ns % 1_000_000_000)
        self._reply("cancel_goal", query, sequence, gid, w.bytes())
        for g in canceling:
            emit("cancel", goal_id=g.goal_id.hex())
            g.status = 3
            self._publish_status()
            self._finish(g, CANCELED)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m tests.helpers.ros2_robot_standin", description=__doc__.split("\n")[0])
    p.add_argument("--connect", action="append", default=[], help="zenoh endpoint to connect to (repeatable)")
    p.add_argument("--listen", default=None, help="zenoh endpoint to listen on")
    p.add_argument("--domain", type=int, default=0, help="ROS_DOMAIN_ID")
    p.add_argument("--namespace", default="", help="node namespace (default: root)")
    p.add_argument("--node-name", default="standin_robot")
    p.add_argument("--nav", choices=("succeed", "abort", "hang"), default="succeed")
    p.add_argument("--feedback", type=int, default=3, help="feedback messages before the result")
    p.add_argument("--feedback-interval", type=float, default=0.05)
    p.add_argument("--odom-hz", type=float, default=0.0, help="publish odom at this rate (0: off)")
    p.add_argument("--malformed", action="store_true", help="truncated feedback, odom and send_goal replies")
    p.add_argument("--cmd-vel-topic", default="cmd_vel")
    p.add_argument("--speech-topic", default="speech")
    p.add_argument("--action-name", default="navigate_to_pose")
    p.add_argument("--max-seconds", type=float, default=600.0, help="exit after this long whatever happens")
    args = p.parse_args(argv)
    # ROS names (design.ros2.org "Topic and Service name mapping"): a bad one would make an invalid key.
    name, path = re.compile(r"[A-Za-z_][A-Za-z0-9_]*"), re.compile(r"/?([A-Za-z_][A-Za-z0-9_]*)(/[A-Za-z_][A-Za-z0-9_]*)*")
    if not name.fullmatch(args.node_name):
        p.error(f"--node-name {args.node_name!r} is not a ROS node name")
    for option in ("namespace", "cmd_vel_topic", "speech_topic", "action_name"):
        value = getattr(args, option)
        if not path.fullmatch(value) and not (option == "namespace" and value in ("", "/")):
            p.error(f"--{option.replace('_', '-')} {value!r} is not a ROS name")
    if args.domain < 0:
        p.error("--domain must be >= 0")
    if args.feedback < 0 or args.feedback_interval < 0 or args.odom_hz < 0 or args.odom_hz > 1000:
        p.error("--feedback, --feedback-interval must be >= 0 and --odom-hz within 0..1000")
    return args


def _read_stdin(stop: threading.Event) -> None:
    for line in sys.stdin:
        if line.strip() == "exit":
            break
    stop.set()


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    # A daemon thread: a blocked read of stdin cannot be interrupted, and the process is ending.
    threading.Thread(target=_read_stdin, args=(stop,), name="standin-stdin", daemon=True).start()
    try:
        robot = StandinRobot(args)
    except zenoh.ZError as exc:
        emit("error", what=f"cannot open the zenoh session: {exc}")
        return 2
    with robot:
        robot.open()
        deadline = time.monotonic() + args.max_seconds
        while not stop.is_set() and not robot.stop.is_set() and time.monotonic() < deadline:
            stop.wait(0.2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
