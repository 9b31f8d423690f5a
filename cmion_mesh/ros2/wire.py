"""ROS 2 over rmw_zenoh (ROS 2 Jazzy): the wire format, and a mesh-side ROS 2 node.

rmw_zenoh maps ROS 2 onto plain zenoh, so a cmion-mesh session can talk to ROS 2 nodes with no
ROS installation, no DDS and no bridge process. What goes on the wire (rmw_zenoh's
``docs/design.md``, ``liveliness_utils.cpp``, ``attachment_helpers.cpp``):

* **Data keys**: ``<domain>/<fully qualified name without the outer "/">/<DDS type>/<type hash>``,
  e.g. ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...``. Services use the service's
  type and hash (not its Request's); an action is three services (``<action>/_action/send_goal``,
  ``cancel_goal``, ``get_result``) and two topics (``feedback``, ``status``).
* **Type hashes** (RIHS01) and **payloads** (CDR): ``ros2/interfaces.py``.
* **Attachments** (required: rmw_zenoh drops a sample without one): int64 sequence number, int64
  source time (ns), one byte GID length (16), the 16-byte GID; a service reply carries its
  request's sequence number and the client's GID.
* **Liveliness tokens** (the ROS graph: ``ros2 node list`` reads them):
  ``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>`` for a node, and
  ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<MP|MS|SS|SC>/<enclave>/<namespace>/<node>/<name>/<DDS type>/<hash>/<qos>``
  for its entities, ``/`` in a name written ``%`` (the root namespace and no enclave are ``%``).

Here: names, keys, liveliness tokens and attachments, and the mesh-side node (``Node``: its
publishers, subscriptions, service and action clients, and the ``Graph`` of entities it sees).
The types, their hashes and CDR: ``ros2/interfaces.py``. Only these two modules know the format;
the competencies (``ros2/competencies.py``) use ``Node``.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import math
import os
import string
import struct
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy

from cmion_mesh.errors import ConfigError, OutcomeUnknown, ProtocolError
from cmion_mesh.ros2.interfaces import Types, split_type
from cmion_mesh.transport.base import Closeable, QueryCancel, Sample, Transport

log = logging.getLogger(__name__)

ADMIN_SPACE = "@ros2_lv"
#: rmw_zenoh's compact QoS for the default profile (reliable, volatile, keep last 10).
DEFAULT_QOS = "::,10:,:,:,,"
#: An action's status topic: transient local, keep last 1.
STATUS_QOS = ":1:,1:,:,:,,"
GID_SIZE = 16
#: Seconds between two reports (log line, ``on_malformed``) of malformed messages on one
#: subscription: a robot publishing a mismatched topic at 50 Hz must not flood the log.
MALFORMED_EVERY = 10.0
_ATTACHMENT = struct.Struct("<qqB")

# action_msgs/msg/GoalStatus
STATUS_UNKNOWN, STATUS_ACCEPTED, STATUS_EXECUTING, STATUS_CANCELING = 0, 1, 2, 3
STATUS_SUCCEEDED, STATUS_CANCELED, STATUS_ABORTED = 4, 5, 6
STATUS_NAMES = {0: "unknown", 1: "accepted", 2: "executing", 3: "canceling", 4: "succeeded", 5: "canceled", 6: "aborted"}

# --- names, keys, tokens -----------------------------------------------------------------------

_NAME_CHARS = frozenset(string.ascii_letters + string.digits + "_")


def qualify(name: str, namespace: str = "") -> str:
    """The fully qualified name of ``name`` in ``namespace`` (``odom`` in ``/robot1``: ``/robot1/odom``);
    an absolute name stays as it is. ``ConfigError`` for a name ROS 2 would refuse."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    full = name if name.startswith("/") else f"{ns}/{name}"
    parts = full.strip("/").split("/")
    # design.ros2.org "Topic and Service name mapping": ASCII alphanumerics and _, tokens that do
    # not start with a digit, no repeated _, no trailing /. A name ROS 2 refuses never matches.
    if (not name or name.endswith("/") or "__" in full
            or any(not p or not set(p) <= _NAME_CHARS or p[0].isdigit() for p in parts)):
        raise ConfigError(f"invalid ROS 2 name {name!r} (namespace {namespace!r}): use ASCII letters, digits, _ and /, "
                          "without a repeated _ or a trailing /")
    return "/" + "/".join(parts)


def dds_type(type_name: str) -> str:
    """``std_msgs/msg/String`` -> ``std_msgs::msg::dds_::String_`` (the name rmw_zenoh keys carry)."""
    pkg, kind, name = split_type(type_name)
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type(dds: str) -> str:
    """The inverse of ``dds_type``; a name of another form is returned as it is."""
    parts = dds.split("::")
    if len(parts) == 4 and parts[2] == "dds_" and parts[3].endswith("_"):
        return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"
    return dds


def mangle(name: str) -> str:
    return name.replace("/", "%") if name else "%"


def demangle(chunk: str) -> str:
    return "" if chunk == "%" else chunk.replace("%", "/")


def topic_key(domain: int, name: str, type_name: str, type_hash: str) -> str:
    return f"{domain}/{name.strip('/')}/{dds_type(type_name)}/{type_hash}"


def node_token(domain: int, zid: str, nid: int, namespace: str, node: str) -> str:
    ns = "/" + namespace.strip("/") if namespace.strip("/") else "/"
    return f"{ADMIN_SPACE}/{domain}/{zid}/{nid}/{nid}/NN/%/{mangle(ns)}/{node}"


def entity_token(domain: int, zid: str, nid: int, eid: int, kind: str, namespace: str, node: str,
                 name: str, type_name: str, type_hash: str, qos: str = DEFAULT_QOS) -> str:
    if kind not in ("MP", "MS", "SS", "SC"):
        raise ValueError(f"entity kind {kind!r}")
    ns = "/" + namespace.strip("/") if namespace.strip("/") else "/"
    return (f"{ADMIN_SPACE}/{domain}/{zid}/{nid}/{eid}/{kind}/%/{mangle(ns)}/{node}/"
            f"{mangle(name)}/{dds_type(type_name)}/{type_hash}/{qos}")


class Entity(NamedTuple):
    """One liveliness token of the ROS graph, parsed."""

    domain: int
    zid: str
    nid: str
    eid: str
    kind: str  # NN, MP, MS, SS, SC
    namespace: str  # "/" for the root
    node: str
    name: str = ""  # the topic or service, fully qualified
    type: str = ""  # the ROS type name (pkg/msg/Name)
    type_hash: str = ""

    @property
    def node_path(self) -> str:
        return f"{self.namespace.rstrip('/')}/{self.node}"


def parse_token(key: str) -> Entity | None:
    """The entity a ``@ros2_lv`` token names, or None for one that is not of that form."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or any(not p for p in parts):
        return None
    kind = parts[5]
    try:
        domain = int(parts[1])
    except ValueError:
        return None
    if kind == "NN":
        return Entity(domain, parts[2], parts[3], parts[4], kind, demangle(parts[7]) or "/", parts[8])
    if kind not in ("MP", "MS", "SS", "SC") or len(parts) < 13:
        return None
    return Entity(domain, parts[2], parts[3], parts[4], kind, demangle(parts[7]) or "/", parts[8],
                  demangle(parts[9]), ros_type(parts[10]), parts[11])


# --- attachments -------------------------------------------------------------------------------


class Attachment(NamedTuple):
    sequence: int
    timestamp_ns: int
    gid: bytes


def encode_attachment(sequence: int, gid: bytes, timestamp_ns: int | None = None) -> bytes:
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, not {len(gid)}")
    stamp = time.time_ns() if timestamp_ns is None else timestamp_ns
    return _ATTACHMENT.pack(sequence, stamp, GID_SIZE) + gid


def decode_attachment(data: bytes | None) -> Attachment:
    """The attachment of a sample or reply; ``ProtocolError`` when missing or malformed."""
    if data is None:
        raise ProtocolError("no rmw_zenoh attachment")
    if len(data) != _ATTACHMENT.size + GID_SIZE:
        raise ProtocolError(f"rmw_zenoh attachment of {len(data)} bytes (expected {_ATTACHMENT.size + GID_SIZE})")
    sequence, stamp, size = _ATTACHMENT.unpack_from(data)
    if size != GID_SIZE:
        raise ProtocolError(f"rmw_zenoh attachment with a GID of {size} bytes")
    return Attachment(sequence, stamp, bytes(data[_ATTACHMENT.size:]))


def gid_of(token: str) -> bytes:
    """A 16-byte GID for the entity of ``token``: unique per token, stable for its life (rmw_zenoh
    hashes the token too; peers only compare GIDs, they never recompute them)."""
    return hashlib.sha256(token.encode()).digest()[:GID_SIZE]


# --- the mesh side of the ROS graph --------------------------------------------------------------

_ids = itertools.count(int.from_bytes(os.urandom(2), "big"))


class Graph:
    """The ROS graph of one domain as liveliness tokens show it; ``wait_for`` blocks until a
    predicate over it holds, ``watch`` tells a function (on the transport's worker) of each change."""

    def __init__(self, transport: Transport, domain: int) -> None:
        self.domain = domain
        self._entities: dict[str, Entity] = {}
        self._changed = threading.Condition()
        self._watchers: list[Callable[[Entity, bool], None]] = []
        self._handle = transport.watch_liveliness(f"{ADMIN_SPACE}/{domain}/**", self._on_token)

    def _on_token(self, key: str, alive: bool) -> None:
        entity = parse_token(key)
        if entity is None:
            return
        with self._changed:
            if alive:
                self._entities[key] = entity
            else:
                self._entities.pop(key, None)
            watchers = list(self._watchers)
            self._changed.notify_all()
        for watcher in watchers:
            try:
                watcher(entity, alive)
            except Exception:
                log.exception("ROS graph watcher failed")

    def entities(self) -> list[Entity]:
        with self._changed:
            return list(self._entities.values())

    def servers(self, service: str, type_name: str | None = None, type_hash: str | None = None) -> list[Entity]:
        """The servers of ``service``; with ``type_name`` and ``type_hash``, only those of that type
        and definition (rmw_zenoh's keys carry the hash: a server of another one never answers)."""
        return [e for e in self.entities() if e.kind == "SS" and e.name == service and (type_name is None or e.type == type_name)
                and (type_hash is None or e.type_hash == type_hash)]

    def subscribers(self, topic: str, type_name: str | None = None, type_hash: str | None = None) -> list[Entity]:
        """The subscriptions of ``topic`` (of that type and definition, when given)."""
        return [e for e in self.entities() if e.kind == "MS" and e.name == topic and (type_name is None or e.type == type_name)
                and (type_hash is None or e.type_hash == type_hash)]

    def publishers(self, topic: str) -> list[Entity]:
        return [e for e in self.entities() if e.kind == "MP" and e.name == topic]

    def nodes(self) -> list[Entity]:
        return [e for e in self.entities() if e.kind == "NN"]

    def wait_for(self, predicate: Callable[[], bool], timeout: float, cancelled: threading.Event | None = None) -> bool:
        deadline = time.monotonic() + timeout
        with self._changed:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0 or (cancelled is not None and cancelled.is_set()):
                    return False
                self._changed.wait(min(left, 0.1) if cancelled is not None else left)
        return True

    def watch(self, watcher: Callable[[Entity, bool], None]) -> Callable[[], None]:
        with self._changed:
            self._watchers.append(watcher)

        def unwatch() -> None:
            with self._changed:
                if watcher in self._watchers:
                    self._watchers.remove(watcher)

        return unwatch

    def close(self) -> None:
        self._handle.close()


def describe_mismatches(entities: list[Entity], type_name: str, type_hash: str) -> str:
    """What other type or definition the nodes behind ``entities`` use, for messages: a robot on
    another release (or a topic of another type) is visible in the graph but never matches."""
    found = []
    for e in sorted(entities, key=lambda e: (e.node_path, e.zid)):
        if e.type != type_name:
            found.append(f"{e.node_path} (zenoh {e.zid}) uses it as {e.type}")
        elif e.type_hash != type_hash:
            found.append(f"{e.node_path} (zenoh {e.zid}) has another definition of {e.type} ({e.type_hash}, here {type_hash})")
    return "; ".join(dict.fromkeys(found))


def describe_peers(entities: list[Entity]) -> str:
    """``node /standin_robot (zenoh 1a2b...)`` for the nodes behind some entities, for messages."""
    named = sorted({f"{e.node_path} (zenoh {e.zid})" for e in entities})
    return "node " + ", ".join(named) if named else "an unknown peer (no ROS 2 node announces it)"


class Node:
    """A ROS 2 node on the mesh side: its liveliness token and those of its publishers,
    subscriptions and clients, so that ``ros2 node list`` and ``ros2 topic list`` on the robot see
    it; and the publishing, subscribing and calling that go with them.

    A context manager; ``close`` withdraws every token and subscription (idempotent).
    """

    def __init__(self, transport: Transport, name: str, *, domain: int = 0, namespace: str = "", types: Types | None = None) -> None:
        if not name or not all(c.isalnum() or c == "_" for c in name) or name[0].isdigit():
            raise ConfigError(f"invalid ROS 2 node name {name!r}: use letters, digits and _")
        if not 0 <= domain <= 232:
            raise ConfigError(f"ROS 2 domain id {domain} out of range (0..232)")
        self.transport = transport
        self.name = name
        self.domain = domain
        self.namespace = qualify("x", namespace)[: -len("/x")] or "/"
        self.types = types or Types()
        self.zid = transport.id
        self.nid = next(_ids)
        self._handles: list[Closeable] = []
        self._lock = threading.Lock()
        self._closed = False
        self.graph = Graph(transport, domain)
        self._handles.append(transport.declare_token(node_token(domain, self.zid, self.nid, self.namespace, name)))

    @property
    def path(self) -> str:
        return f"{self.namespace.rstrip('/')}/{self.name}"

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def qualify(self, name: str) -> str:
        return qualify(name, self.namespace)

    def _declare(self, kind: str, name: str, type_name: str, qos: str = DEFAULT_QOS) -> tuple[str, str]:
        """Declare an entity's token; (its data key, its token). The key ends with the type hash."""
        if not self.types.known(type_name):
            raise ConfigError(f"unknown ROS 2 type {type_name!r} for {name}")
        type_hash = self.types.hash(type_name)
        token = entity_token(self.domain, self.zid, self.nid, next(_ids), kind, self.namespace, self.name, name, type_name, type_hash, qos)
        handle = self.transport.declare_token(token)
        with self._lock:
            self._handles.append(handle)
        return topic_key(self.domain, name, type_name, type_hash), token

    def publisher(self, topic: str, type_name: str, qos: str = DEFAULT_QOS) -> Publisher:
        name = self.qualify(topic)
        key, token = self._declare("MP", name, type_name, qos)
        return Publisher(self, name, type_name, key, gid_of(token))

    def subscribers(self, publisher: Publisher) -> list[Entity]:
        """The subscriptions of other sessions that receive what ``publisher`` publishes: same topic,
        type and type hash (a subscriber of another type or definition has another key)."""
        return [e for e in self.graph.subscribers(publisher.name, publisher.type_name, publisher.type_hash) if e.zid != self.zid]

    def subscribe(self, topic: str, type_name: str, handler: Callable[[Any], None], *, qos: str = DEFAULT_QOS,
                  on_malformed: Callable[[str], None] | None = None) -> Closeable:
        """``handler(message)`` for each message on ``topic``, on the transport's worker thread. A
        sample that is not a ``type_name`` is refused: logged, naming the topic and the node(s)
        publishing it, and passed to ``on_malformed`` (the first at once, then at most one every
        ``MALFORMED_EVERY`` seconds, saying how many were refused meanwhile); the subscription goes on."""
        name = self.qualify(topic)
        key, _ = self._declare("MS", name, type_name, qos)
        gate = threading.Lock()
        refused = {"last": -math.inf, "since": 0}

        def each(sample: Sample) -> None:
            try:
                message = self.types.decode(type_name, sample.payload)
            except ProtocolError as exc:
                now = time.monotonic()
                with gate:
                    if now - refused["last"] < MALFORMED_EVERY:
                        refused["since"] += 1
                        return
                    since, refused["since"], refused["last"] = int(refused["since"]), 0, now
                reason = f"refused a message on {name} from {describe_peers(self.graph.publishers(name))}: {exc}"
                if since:
                    reason += f" ({since} more refused since the last report)"
                log.warning("%s", reason)
                if on_malformed is not None:
                    on_malformed(reason)
                return
            handler(message)

        handle = self.transport.subscribe(key, each, attachments=True)
        with self._lock:
            self._handles.append(handle)
        return handle

    def client(self, service: str, type_name: str) -> Client:
        name = self.qualify(service)
        key, token = self._declare("SC", name, type_name)
        return Client(self, name, type_name, key, gid_of(token))

    def action_client(self, action: str, type_name: str) -> ActionClient:
        return ActionClient(self, action, type_name)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            handles, self._handles = self._handles, []
        for handle in reversed(handles):
            handle.close()
        self.graph.close()


class Publisher:
    def __init__(self, node: Node, name: str, type_name: str, key: str, gid: bytes) -> None:
        self.node, self.name, self.type_name, self.key, self.gid = node, name, type_name, key, gid
        self.type_hash = key.rsplit("/", 1)[1]
        self._sequence = itertools.count(1)

    def publish(self, values: Any) -> None:
        payload = self.node.types.encode(self.type_name, values)
        self.node.transport.publish(self.key, payload, attachment=encode_attachment(next(self._sequence), self.gid))


class Client:
    """A ROS 2 service client: ``call`` sends a request and returns the response."""

    def __init__(self, node: Node, name: str, type_name: str, key: str, gid: bytes) -> None:
        self.node, self.name, self.type_name, self.key, self.gid = node, name, type_name, key, gid
        self.type_hash = key.rsplit("/", 1)[1]
        self._sequence = itertools.count(1)

    def servers(self) -> list[Entity]:
        """The servers that answer this client: same service, type and type hash."""
        return self.node.graph.servers(self.name, self.type_name, self.type_hash)

    def mismatches(self) -> str:
        """The servers of this service that never answer it (another type or definition), described."""
        return describe_mismatches(self.node.graph.servers(self.name), self.type_name, self.type_hash)

    def call(self, request: Any, *, timeout: float, cancel: QueryCancel | None = None) -> Any:
        """The response to ``request``. ``OutcomeUnknown`` when no server answered in ``timeout``
        (or before ``cancel``);
        ``ProtocolError`` (naming the service and the node that answered) for a reply that is not
        a response, or an error reply."""
        sequence = next(self._sequence)
        payload = self.node.types.encode(f"{self.type_name}_Request", request)
        replies = self.node.transport.get(self.key, payload, timeout=timeout, attachment=encode_attachment(sequence, self.gid),
                                          cancel=cancel)
        if not replies:
            raise OutcomeUnknown(f"no answer from the ROS 2 service {self.name} within {timeout:g} s "
                                 f"(servers: {describe_peers(self.servers()) if self.servers() else 'none'})")
        reply = replies[0]
        who = describe_peers(self.servers())
        if not reply.ok:
            raise ProtocolError(f"{self.name}: error reply from {who}: {reply.payload[:200]!r}")
        try:
            attached = decode_attachment(reply.attachment)
        except ProtocolError as exc:
            log.debug("%s: reply from %s: %s", self.name, who, exc)
        else:
            if attached.sequence != sequence:
                raise ProtocolError(f"{self.name}: reply from {who} answers request {attached.sequence}, not {sequence}")
        try:
            return self.node.types.decode(f"{self.type_name}_Response", reply.payload)
        except ProtocolError as exc:
            raise ProtocolError(f"{self.name}: refused the reply from {who}: {exc}") from None


class ActionClient:
    """A ROS 2 action client over rmw_zenoh: three service clients and two subscriptions under
    ``<action>/_action/``, as rclcpp's action client declares them."""

    def __init__(self, node: Node, action: str, type_name: str) -> None:
        self.node = node
        self.type_name = type_name
        self.name = node.qualify(action)
        base = f"{self.name}/_action"
        self.send_goal = node.client(f"{base}/send_goal", f"{type_name}_SendGoal")
        self.get_result = node.client(f"{base}/get_result", f"{type_name}_GetResult")
        self.cancel_goal = node.client(f"{base}/cancel_goal", "action_msgs/srv/CancelGoal")
        self._feedback: dict[bytes, Callable[[Any], None]] = {}
        self._malformed: dict[bytes, Callable[[str], None]] = {}
        self._lock = threading.Lock()
        node.subscribe(f"{base}/feedback", f"{type_name}_FeedbackMessage", self._on_feedback, on_malformed=self._on_malformed)
        node.subscribe(f"{base}/status", "action_msgs/msg/GoalStatusArray", lambda _: None, qos=STATUS_QOS)

    def servers(self) -> list[Entity]:
        return self.send_goal.servers()

    def follow(self, goal_id: bytes, on_feedback: Callable[[Any], None], on_malformed: Callable[[str], None]) -> Callable[[], None]:
        """Route the feedback of one goal to ``on_feedback`` (and malformed feedback to
        ``on_malformed``) until the returned function is called."""
        with self._lock:
            self._feedback[goal_id] = on_feedback
            self._malformed[goal_id] = on_malformed

        def stop() -> None:
            with self._lock:
                self._feedback.pop(goal_id, None)
                self._malformed.pop(goal_id, None)

        return stop

    def _on_feedback(self, message: Any) -> None:
        goal_id = bytes(numpy.asarray(message.goal_id.uuid, dtype=numpy.uint8).tobytes())
        with self._lock:
            handler = self._feedback.get(goal_id)
        if handler is not None:
            handler(message.feedback)

    def _on_malformed(self, reason: str) -> None:
        with self._lock:
            handlers = list(self._malformed.values())
        for handler in handlers:
            handler(reason)

    @staticmethod
    def new_goal_id() -> bytes:
        return uuid.uuid4().bytes

    def uuid(self, goal_id: bytes) -> dict[str, Any]:
        return {"uuid": numpy.frombuffer(goal_id, dtype=numpy.uint8).copy()}

    def send(self, goal_id: bytes, goal: dict[str, Any], *, timeout: float) -> bool:
        """Send a goal; whether the server accepted it."""
        response = self.send_goal.call({"goal_id": self.uuid(goal_id), "goal": goal}, timeout=timeout)
        return bool(response.accepted)

    def result(self, goal_id: bytes, *, timeout: float, cancel: QueryCancel | None = None) -> tuple[int, Any]:
        """Wait for the goal's end: (GoalStatus, result message); ``cancel`` stops waiting."""
        response = self.get_result.call({"goal_id": self.uuid(goal_id)}, timeout=timeout, cancel=cancel)
        return int(response.status), response.result

    def cancel(self, goal_id: bytes, timeout: float) -> int:
        """Ask the server to cancel a goal; CancelGoal's return code (0: it is canceling)."""
        response = self.cancel_goal.call({"goal_info": {"goal_id": self.uuid(goal_id)}}, timeout=timeout)
        return int(response.return_code)


def yaw_quaternion(yaw: float) -> dict[str, float]:
    """The orientation of a planar heading (radians) as a quaternion."""
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2.0), "w": math.cos(yaw / 2.0)}
