"""ROS 2 interfaces (messages, services, actions) as rmw_zenoh puts them on the wire: their RIHS01
type hashes and their CDR payloads (``ros2/wire.py`` has the keys, tokens and attachments).

* **Type hashes**: REP 2011's RIHS01 (SHA-256 of the type description); services are described
  as ``request_message``, ``response_message`` and ``event_message`` (``<Name>_Event``: ``info``
  and request and response as sequences of at most one). A ``.msg`` ``char`` is ``uint8`` there.
* **Payloads**: CDR with its 4-byte encapsulation header (little endian written, either read).

CDR and the type descriptions come from ``rosbags`` (its ROS 2 Jazzy type store: the standard
messages, and the Nav2 and action types registered here from their ``.msg``/``.action`` text);
this module adds what rosbags has no notion of: services and actions as rmw_zenoh names and hashes
them. ``plain`` turns a message into blackboard values.
"""

from __future__ import annotations

import array
import copy
import math
import os
import sys
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from cmion_mesh.errors import ConfigError, ProtocolError


def split_type(type_name: str) -> tuple[str, str, str]:
    parts = type_name.split("/")
    if len(parts) != 3 or not all(parts) or parts[1] not in ("msg", "srv", "action"):
        raise ConfigError(f"invalid ROS 2 type name {type_name!r} (expected package/msg/Name)")
    return parts[0], parts[1], parts[2]


ACTION_MSGS_CANCEL_GOAL = (
    "action_msgs/srv/CancelGoal",
    "action_msgs/msg/GoalInfo goal_info",
    "int8 ERROR_NONE=0\nint8 ERROR_REJECTED=1\nint8 ERROR_UNKNOWN_GOAL_ID=2\nint8 ERROR_GOAL_TERMINATED=3\n"
    "int8 return_code\naction_msgs/msg/GoalInfo[] goals_canceling",
)

#: nav2_msgs/action/NavigateToPose as in Nav2 for ROS 2 Jazzy.
NAVIGATE_TO_POSE = (
    "nav2_msgs/action/NavigateToPose",
    "geometry_msgs/msg/PoseStamped pose\nstring behavior_tree",
    "uint16 NONE=0\nuint16 UNKNOWN=9000\nuint16 FAILED_TO_LOAD_BEHAVIOR_TREE=9001\nuint16 TF_ERROR=9002\n"
    "uint16 TIMEOUT=9003\nuint16 error_code\nstring error_msg",
    "geometry_msgs/msg/PoseStamped current_pose\nbuiltin_interfaces/msg/Duration navigation_time\n"
    "builtin_interfaces/msg/Duration estimated_time_remaining\nint16 number_of_recoveries\nfloat32 distance_remaining",
)


def _rename(desc: Any, fix: Callable[[str], str]) -> Any:
    if desc[0] == Nodetype.NAME:
        return (desc[0], fix(desc[1]))
    if desc[0] in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return (desc[0], (_rename(desc[1][0], fix), desc[1][1]))
    return desc


def _as_uint8(desc: Any) -> Any:
    if desc[0] == Nodetype.BASE and desc[1][0] == "char":
        return (desc[0], ("uint8", desc[1][1]))
    if desc[0] in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return (desc[0], (_as_uint8(desc[1][0]), desc[1][1]))
    return desc


class Types:
    """ROS 2 Jazzy types by name: CDR encoding and decoding, and their RIHS01 hashes."""

    def __init__(self) -> None:
        self._store = get_typestore(Stores.ROS2_JAZZY)
        self._hashes: dict[str, str] = {}
        self._services: set[str] = set()
        self._lock = threading.Lock()
        self.register_service(*ACTION_MSGS_CANCEL_GOAL)
        self.register_action(*NAVIGATE_TO_POSE)

    def known(self, type_name: str) -> bool:
        return type_name in self._store.fielddefs or type_name in self._services

    def known_action(self, type_name: str) -> bool:
        """Whether ``type_name`` is an action known here, after looking for its ``.action`` file."""
        try:
            return self.find_action(type_name)
        except ConfigError:
            return False

    def find_action(self, type_name: str) -> bool:
        """Register the action ``type_name`` from its ``.action`` file in a ROS share folder
        (``$AMENT_PREFIX_PATH``'s, this Python's, as the ``ros2`` extra's wheels install them),
        unless it is known already; whether it is known now."""
        if self.known(f"{type_name}_SendGoal"):
            return True
        pkg, kind, name = split_type(type_name)
        if kind != "action":
            return False
        prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p] + [sys.prefix]
        for prefix in prefixes:
            path = Path(prefix) / "share" / pkg / "action" / f"{name}.action"
            if path.is_file():
                parts = path.read_text(encoding="utf-8").split("\n---")
                if len(parts) != 3:
                    raise ConfigError(f"{path}: an action definition has three parts separated by ---, not {len(parts)}")
                goal, result, feedback = (part.lstrip("-").strip("\n") for part in parts)
                self.register_action(type_name, goal, result, feedback)
                return True
        return False

    def string_fields(self, type_name: str) -> list[str]:
        """The names of the string fields of a message type (``data`` for ``std_msgs/msg/String``)."""
        with self._lock:
            if type_name not in self._store.fielddefs:
                raise ConfigError(f"unknown ROS 2 type {type_name!r}")
            _, fields = self._store.fielddefs[type_name]
        return [name for name, desc in fields if desc[0] == Nodetype.BASE and desc[1][0] == "string"]

    def register_messages(self, definitions: Iterable[tuple[str, str]]) -> None:
        """Register message types from ``.msg`` text (``pkg/msg/Name`` or ``pkg/srv/Name_Request``...)."""
        found: dict[str, Any] = {}
        for name, text in definitions:
            split_type(name)
            try:
                found.update(get_types_from_msg(text, name))
            except Exception as exc:  # rosbags' parser raises its own exception types
                raise ConfigError(f"ROS 2 type {name}: cannot parse its definition: {exc}") from None

        # rosbags files anything outside msg/ and action/ under msg/: put srv types back in place.
        def fix(n: str) -> str:
            return n.replace("/srv/msg/", "/srv/")

        fixed = {fix(k): (consts, [(f, _rename(d, fix)) for f, d in fields]) for k, (consts, fields) in found.items()}
        with self._lock:
            try:
                self._store.register(fixed)
            except Exception as exc:
                raise ConfigError(f"ROS 2 types {sorted(fixed)}: {exc}") from None
            self._hashes.clear()

    def register_service(self, name: str, request: str, response: str) -> None:
        """A service from the two halves of its ``.srv`` text, with the ``_Event`` type and the
        description its hash is taken from."""
        self.register_messages([
            (f"{name}_Request", request),
            (f"{name}_Response", response),
            (f"{name}_Event", f"service_msgs/msg/ServiceEventInfo info\n{name}_Request[<=1] request\n{name}_Response[<=1] response"),
            (name, f"{name}_Request request_message\n{name}_Response response_message\n{name}_Event event_message"),
        ])
        self._services.add(name)

    def register_action(self, name: str, goal: str, result: str, feedback: str) -> None:
        """An action from the three parts of its ``.action`` text: its goal, result and feedback
        messages, its send_goal and get_result services and its feedback message, as rosidl
        generates them."""
        self.register_messages([(f"{name}_Goal", goal), (f"{name}_Result", result), (f"{name}_Feedback", feedback),
                                (f"{name}_FeedbackMessage", f"unique_identifier_msgs/msg/UUID goal_id\n{name}_Feedback feedback")])
        self.register_service(f"{name}_SendGoal", f"unique_identifier_msgs/msg/UUID goal_id\n{name}_Goal goal",
                              "bool accepted\nbuiltin_interfaces/msg/Time stamp")
        self.register_service(f"{name}_GetResult", "unique_identifier_msgs/msg/UUID goal_id", f"int8 status\n{name}_Result result")

    def hash(self, type_name: str) -> str:
        """The RIHS01 hash of a message or service type."""
        with self._lock:
            found = self._hashes.get(type_name)
            if found is not None:
                return found
            if type_name not in self._store.fielddefs:
                raise ConfigError(f"unknown ROS 2 type {type_name!r}")
            # The type description has rosidl's field types, where a .msg char is a uint8.
            hashing = copy.copy(self._store)
            hashing.fielddefs = {k: (c, [(f, _as_uint8(d)) for f, d in fields]) for k, (c, fields) in self._store.fielddefs.items()}
            found = hashing.hash_rihs01(type_name)
            self._hashes[type_name] = found
            return found

    def encode(self, type_name: str, values: Any) -> bytes:
        """CDR (little endian, with its header) of ``values``: a message object, or a dict whose
        missing fields take their defaults."""
        message = values if not isinstance(values, dict) else self.build(type_name, values)
        return bytes(self._store.serialize_cdr(message, type_name))

    def decode(self, type_name: str, data: bytes) -> Any:
        """The message ``data`` holds; ``ProtocolError`` saying why it is not one."""
        try:
            return self._store.deserialize_cdr(data, type_name)
        except Exception as exc:  # rosbags raises struct.error, IndexError, its own errors...
            raise ProtocolError(f"malformed CDR for {type_name} ({len(data)} bytes): {type(exc).__name__}: {exc}") from None

    def build(self, type_name: str, values: dict[str, Any] | None = None) -> Any:
        """A message object from a dict (nested dicts for nested messages), defaults for the rest."""
        values = values or {}
        if type_name not in self._store.fielddefs:
            raise ConfigError(f"unknown ROS 2 type {type_name!r}")
        _, fields = self._store.fielddefs[type_name]
        unknown = set(values) - {f for f, _ in fields}
        if unknown:
            raise ConfigError(f"{type_name} has no field {', '.join(sorted(unknown))}")
        cls = self._store.types[type_name]
        return cls(**{f: self._value(desc, values.get(f), f"{type_name}.{f}") for f, desc in fields})

    def _value(self, desc: Any, value: Any, where: str) -> Any:
        kind, rest = desc
        if kind == Nodetype.BASE:
            base = rest[0]
            if base == "string":
                return "" if value is None else str(value)
            if base == "bool":
                return bool(value)
            if base in ("float32", "float64"):
                return 0.0 if value is None else float(value)
            return 0 if value is None else int(value)
        if kind == Nodetype.NAME:
            if value is not None and not isinstance(value, dict):
                return value
            return self.build(rest, value)
        inner, count = rest
        if inner[0] == Nodetype.BASE and inner[1][0] not in ("string", "bool"):
            dtype = numpy.dtype({"char": "uint8", "byte": "uint8", "float32": "float32", "float64": "float64"}.get(
                inner[1][0], inner[1][0]))
            items = numpy.zeros(count if kind == Nodetype.ARRAY else 0, dtype=dtype) if value is None else numpy.asarray(value, dtype=dtype)
            if kind == Nodetype.ARRAY and len(items) != count:
                raise ConfigError(f"{where}: {count} values needed, {len(items)} given")
            return items
        listed = [self._value(inner, v, where) for v in (value or [])]
        if kind == Nodetype.ARRAY and not listed:
            listed = [self._value(inner, None, where) for _ in range(count)]
        return listed


def plain(message: Any, *, limit: int = 64) -> Any:
    """A message (of rosbags or of rclpy) as plain values for the blackboard (dicts, lists, numbers, strings); sequences
    longer than ``limit`` are cut to it (a laser scan is not a blackboard value)."""
    if isinstance(message, (numpy.ndarray, array.array)):
        return [plain(v) for v in message.tolist()[:limit]]
    if isinstance(message, bytes):
        return list(message[:limit])
    if isinstance(message, (list, tuple)):
        return [plain(v) for v in message[:limit]]
    if isinstance(message, float):
        return message if math.isfinite(message) else None
    if isinstance(message, (str, int, bool)) or message is None:
        return message
    if isinstance(message, (numpy.integer, numpy.floating)):
        return plain(message.item())
    fields = getattr(message, "__dataclass_fields__", None)
    if fields is None:
        # An rclpy message (``ros2/rclpy_link.py``): its generated class lists its fields.
        listed = getattr(message, "get_fields_and_field_types", None)
        if not callable(listed):
            return str(message)
        fields = listed()
    return {name: plain(getattr(message, name)) for name in fields if not name.startswith("__")}
