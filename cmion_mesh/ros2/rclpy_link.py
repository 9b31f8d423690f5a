"""The ROS link through rclpy: an rclpy node hosted by the daemon, on the RMW the environment selects.

The only module that imports rclpy (it has no type stubs the project checks: mypy sees it as
``Any``, so the types here are stated locally). With the ``ros2`` extra (``pip install
'cmion-mesh[ros2]'``) that is Fast DDS from the wheels; on a full ROS 2 installation,
``RMW_IMPLEMENTATION`` chooses (``rmw_zenoh_cpp``, ``rmw_cyclonedds_cpp``...), and
``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE`` and the RMW's own variables apply as to any
ROS 2 process. The wheels need ``LD_LIBRARY_PATH`` to reach their libraries: their bootstrap
(a ``.pth`` file) sets it and re-executes the interpreter once at start-up, and child processes
inherit it.

Threads: each link has its own rclpy ``Context`` (its domain; no signal handlers: the daemon owns
its signals) and one executor spun by one thread of its own. Callbacks (messages, feedback, the
server watch) run there and only hand over (the competencies put them on their queues); the
competencies' threads publish, send goals and wait on futures with a deadline, never spinning.
``close`` (idempotent; also the context manager's exit) stops the thread, then destroys the node
and shuts the context down.
"""

from __future__ import annotations

import array
import importlib
import logging
import threading
import uuid
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.action import ActionClient, get_action_server_names_and_types_by_node
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

from cmion_mesh.errors import ConfigError, OutcomeUnknown
from cmion_mesh.ros2.interfaces import split_type
from cmion_mesh.ros2.wire import qualify
from cmion_mesh.transport.base import QueryCancel

log = logging.getLogger(__name__)

#: How often the spinning thread comes back to see whether it must stop (seconds), and how often
#: a waiting competency looks at rclpy's graph (which has no blocking wait across threads).
SPIN_PERIOD = 0.1
POLL_PERIOD = 0.02
#: The node name rmw gives an endpoint whose participant's node list has not arrived.
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"
#: How long to wait for the name of the node behind a ready action server (seconds).
NAMING_WAIT = 2.0


def interface(type_name: str) -> Any:
    """The generated Python class of a ROS 2 type (``test_msgs/action/Fibonacci``), or ``ConfigError``."""
    pkg, kind, name = split_type(type_name)
    try:
        module = importlib.import_module(f"{pkg}.{kind}")
    except ImportError:
        raise ConfigError(f"ROS 2 type {type_name}: no Python package {pkg} here (install its interface package, "
                          f"e.g. ros-kilted-{pkg.replace('_', '-')}, or source the workspace that builds it)") from None
    found = getattr(module, name, None)
    if found is None:
        raise ConfigError(f"ROS 2 type {type_name}: the package {pkg} has no {kind} {name}")
    return found


class _Types:
    """The ``LinkTypes`` of this transport: what the installed interface packages define."""

    def known(self, type_name: str) -> bool:
        try:
            return split_type(type_name)[1] == "msg" and interface(type_name) is not None
        except ConfigError:
            return False

    def known_action(self, type_name: str) -> bool:
        try:
            return split_type(type_name)[1] == "action" and interface(type_name) is not None
        except ConfigError:
            return False

    def string_fields(self, type_name: str) -> list[str]:
        fields: dict[str, str] = interface(type_name).get_fields_and_field_types()
        return [name for name, kind in fields.items() if kind == "string" or kind.startswith("string<")]


TYPES = _Types()


def build(cls: Any, values: dict[str, Any], where: str) -> Any:
    """A message of class ``cls`` from field values (nested dicts for nested messages)."""
    message = cls()
    _fill(message, values, where)
    return message


def _fill(message: Any, values: dict[str, Any], where: str) -> None:
    fields: dict[str, str] = message.get_fields_and_field_types()
    for key, value in values.items():
        if key not in fields:
            raise ConfigError(f"{where} has no field {key} (its fields: {', '.join(fields)})")
        current = getattr(message, key)
        if isinstance(value, dict) and hasattr(current, "get_fields_and_field_types"):
            _fill(current, value, f"{where}.{key}")
            continue
        try:
            setattr(message, key, _coerce(current, value, fields[key]))
        except (TypeError, ValueError, AssertionError) as exc:
            raise ConfigError(f"{where}.{key} ({fields[key]}): {value!r} does not fit ({exc or type(exc).__name__})") from None


def _coerce(current: Any, value: Any, kind: str) -> Any:
    # rclpy's generated setters check types strictly (an int is not a float64): convert what the
    # step parameters and the blackboard give (strings, ints) to the field's own kind.
    if isinstance(current, bool):
        return value.strip().lower() in ("true", "1", "yes") if isinstance(value, str) else bool(value)
    if isinstance(current, int):
        return int(value)
    if isinstance(current, float):
        return float(value)
    if isinstance(current, str):
        return str(value)
    if isinstance(current, (list, array.array)) or hasattr(current, "tolist"):
        items = list(value)
        if "int" in kind:
            return [int(v) for v in items]
        if "float" in kind or "double" in kind:
            return [float(v) for v in items]
        return items
    return value


def _wait(future: Any, timeout: float, cancel: QueryCancel | None = None) -> bool:
    """Wait (on the caller's thread; the executor's thread completes it) until ``future`` is done,
    ``timeout`` passes or ``cancel`` is cancelled; whether it is done."""
    done = threading.Event()
    future.add_done_callback(lambda _: done.set())
    if cancel is not None:
        cancel.on_cancel(done.set)
    done.wait(timeout)
    return bool(future.done())


def _poll(predicate: Callable[[], bool], timeout: float, cancelled: threading.Event) -> bool:
    for _ in range(int(timeout / POLL_PERIOD) + 1):  # bounded: one look per period
        if predicate():
            return True
        if cancelled.wait(POLL_PERIOD):
            return False
    return predicate()


def _uuid_bytes(values: Any) -> bytes:
    return bytes(bytearray(int(v) for v in values))


class RclpyPublisher:
    def __init__(self, link: RclpyLink, topic: str, type_name: str) -> None:
        self._link = link
        self._cls = interface(type_name)
        self.type_name = type_name
        self.name = qualify(topic, link.namespace)
        self._publisher = link.node.create_publisher(self._cls, self.name, 10)

    def publish(self, values: dict[str, Any]) -> None:
        self._publisher.publish(build(self._cls, values, self.type_name))

    def wait_subscribers(self, timeout: float, cancelled: threading.Event) -> bool:
        return _poll(lambda: int(self._publisher.get_subscription_count()) > 0, timeout, cancelled)

    def mismatches(self) -> str:
        found = [f"{info.node_namespace.rstrip('/')}/{info.node_name} uses it as {info.topic_type}"
                 for info in self._link.node.get_subscriptions_info_by_topic(self.name) if info.topic_type != self.type_name]
        return "; ".join(sorted(set(found)))


class RclpyActionClient:
    def __init__(self, link: RclpyLink, action: str, type_name: str) -> None:
        self._link = link
        self._cls = interface(type_name)
        self.type_name = type_name
        self.name = qualify(action, link.namespace)
        self._client = ActionClient(link.node, self._cls, self.name)
        self._lock = threading.Lock()
        self._handles: dict[bytes, Any] = {}
        self._feedback: dict[bytes, Callable[[Any], None]] = {}

    def _serving(self) -> list[tuple[str, list[str]]]:
        """(node path, the types it serves this action as) for each node serving it."""
        node = self._link.node
        found = []
        for name, namespace in node.get_node_names_and_namespaces():
            try:
                served = get_action_server_names_and_types_by_node(node, name, namespace)
            except Exception:  # the node left between the two calls
                continue
            for action, types in served:
                if action == self.name:
                    found.append((f"{namespace.rstrip('/')}/{name}", list(types)))
        return found

    def wait_server(self, timeout: float, cancelled: threading.Event) -> bool:
        return _poll(lambda: bool(self._client.server_is_ready()), timeout, cancelled)

    def mismatches(self) -> str:
        return "; ".join(f"{path} serves it as {', '.join(types)}" for path, types in self._serving() if self.type_name not in types)

    def who(self) -> str:
        paths: list[str] = []

        def named() -> bool:
            paths[:] = sorted(path for path, types in self._serving() if self.type_name in types)
            return bool(paths)

        # Nodes are announced apart from their endpoints (and after them): a server that is
        # ready may not have its node's name in the graph yet.
        _poll(named, NAMING_WAIT, threading.Event())
        return "node " + ", ".join(paths) if paths else "an unknown server (no node in the graph serves it)"

    def has_servers(self) -> bool:
        return bool(self._client.server_is_ready())

    def watch_servers(self, on_gone: Callable[[], None]) -> Callable[[], None]:
        state = {"ready": self.has_servers()}

        def look() -> None:  # on the executor's thread: look, and hand over
            ready = self.has_servers()
            if state["ready"] and not ready:
                on_gone()
            state["ready"] = ready

        timer = self._link.node.create_timer(SPIN_PERIOD / 2, look)
        return lambda: self._link.destroy_timer(timer)

    def new_goal_id(self) -> bytes:
        return uuid.uuid4().bytes

    def follow(self, goal_id: bytes, on_feedback: Callable[[Any], None], on_malformed: Callable[[str], None]) -> Callable[[], None]:
        del on_malformed  # the RMW refuses what does not deserialize before rclpy sees it
        with self._lock:
            self._feedback[goal_id] = on_feedback

        def stop() -> None:
            with self._lock:
                self._feedback.pop(goal_id, None)
                self._handles.pop(goal_id, None)

        return stop

    def _on_feedback(self, message: Any) -> None:
        with self._lock:
            handler = self._feedback.get(_uuid_bytes(message.goal_id.uuid))
        if handler is not None:
            handler(message.feedback)

    def send(self, goal_id: bytes, goal: dict[str, Any], *, timeout: float) -> bool:
        uuid_type = interface("unique_identifier_msgs/msg/UUID")
        request = build(self._cls.Goal, goal, f"{self.type_name} goal")
        future = self._client.send_goal_async(request, feedback_callback=self._on_feedback, goal_uuid=uuid_type(uuid=list(goal_id)))
        if not _wait(future, timeout):
            future.cancel()
            raise OutcomeUnknown(f"no answer to the goal from the ROS 2 action server of {self.name} within {timeout:g} s")
        handle = future.result()
        if not handle.accepted:
            return False
        with self._lock:
            self._handles[goal_id] = handle
        return True

    def _handle(self, goal_id: bytes) -> Any:
        with self._lock:
            handle = self._handles.get(goal_id)
        if handle is None:
            raise OutcomeUnknown(f"{self.name}: no accepted goal {goal_id.hex()}")
        return handle

    def result(self, goal_id: bytes, *, timeout: float, cancel: QueryCancel | None = None) -> tuple[int, Any]:
        future = self._handle(goal_id).get_result_async()
        if not _wait(future, timeout, cancel):
            raise OutcomeUnknown(f"no result from the ROS 2 action server of {self.name} within {timeout:g} s")
        response = future.result()
        return int(response.status), response.result

    def cancel(self, goal_id: bytes, timeout: float) -> int:
        future = self._handle(goal_id).cancel_goal_async()
        if not _wait(future, timeout):
            raise OutcomeUnknown(f"no answer to the cancel from the ROS 2 action server of {self.name} within {timeout:g} s")
        return int(future.result().return_code)


class RclpyLink:
    """An rclpy node with its own context (``domain``) and its own spinning thread."""

    transport = "rclpy"

    def __init__(self, name: str, *, domain: int, namespace: str = "") -> None:
        self.domain = domain
        self.namespace = "/" + namespace.strip("/")
        self._context = Context()
        rclpy.init(context=self._context, domain_id=domain)
        try:
            # No parameter services, no rosout: the same face as the rmw_zenoh node, and fewer
            # endpoints for discovery to announce.
            self.node = Node(name, namespace=self.namespace, context=self._context, start_parameter_services=False,
                             enable_rosout=False)
            self._executor = SingleThreadedExecutor(context=self._context)
            self._executor.add_node(self.node)
        except Exception as exc:
            self._context.try_shutdown()
            raise ConfigError(f"ROS 2 node {name!r} (namespace {namespace!r}, domain {domain}): {exc}") from None
        self.path = str(self.node.get_fully_qualified_name())
        self._lock = threading.Lock()
        self._closed = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name=f"rclpy-{name}", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self._context.ok():
            try:
                self._executor.spin_once(timeout_sec=SPIN_PERIOD)
            except Exception:  # a callback's failure must not end the node
                if self._stop.is_set() or not self._context.ok():
                    break
                log.exception("rclpy node %s: a callback failed", self.path)

    def publisher(self, topic: str, type_name: str) -> RclpyPublisher:
        return RclpyPublisher(self, topic, type_name)

    def subscribe(self, topic: str, type_name: str, handler: Callable[[Any], None], *,
                  on_malformed: Callable[[str], None] | None = None) -> None:
        del on_malformed  # the RMW refuses what does not deserialize before rclpy sees it
        # Best effort: it matches publishers of either reliability (a robot's sensors are often
        # best effort, which a reliable subscription never hears), and only the latest counts.
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.node.create_subscription(interface(type_name), qualify(topic, self.namespace), handler, qos)

    def action_client(self, action: str, type_name: str) -> RclpyActionClient:
        return RclpyActionClient(self, action, type_name)

    def destroy_timer(self, timer: Any) -> None:
        with self._lock:
            if self._closed:
                return
        self.node.destroy_timer(timer)

    def graph(self) -> dict[str, Any]:
        """The ROS graph this node sees: nodes, topics (with their types), actions."""
        from rclpy.action import get_action_names_and_types

        nodes = sorted(f"{ns.rstrip('/')}/{n}" for n, ns in self.node.get_node_names_and_namespaces()
                       if f"{ns.rstrip('/')}/{n}" != self.path)
        topics = {name: list(types) for name, types in self.node.get_topic_names_and_types() if "/_action/" not in name}
        actions = {name: list(types) for name, types in get_action_names_and_types(self.node)}
        return {"domain": self.domain, "rmw": str(rclpy.get_rmw_implementation_identifier()), "nodes": nodes, "topics": topics,
                "actions": actions}

    def unnamed(self) -> bool:
        """Whether an endpoint in the graph belongs to a node whose name has not arrived yet."""
        for topic, _ in self.node.get_topic_names_and_types():
            infos = [*self.node.get_publishers_info_by_topic(topic), *self.node.get_subscriptions_info_by_topic(topic)]
            if any(info.node_name == UNKNOWN_NODE for info in infos):
                return True
        return False

    def __enter__(self) -> RclpyLink:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._stop.set()
        self._thread.join(5.0)
        try:
            self._executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        finally:
            self._context.try_shutdown()


def graph(domain: int, timeout: float, quiet: float = 3.5) -> dict[str, Any]:
    """The ROS graph of ``domain`` as a fresh rclpy node sees it: once it shows a node and has not
    changed for ``quiet`` seconds (discovery has no "done"; a participant missed at first is heard
    at its next announcement, every 3 s with Fast DDS's defaults), or after ``timeout`` seconds."""
    with RclpyLink(f"cmion_doctor_{uuid.uuid4().hex[:8]}", domain=domain) as link:
        pause = threading.Event()
        seen, still = link.graph(), 0.0
        for _ in range(int(timeout / SPIN_PERIOD)):  # bounded: one look per period
            pause.wait(SPIN_PERIOD)
            now = link.graph()
            still = still + SPIN_PERIOD if now == seen else 0.0
            seen = now
            # An empty graph may be one not yet discovered; an endpoint whose node is not named yet
            # is a participant whose node list has not arrived (it may take a heartbeat, seconds).
            if still >= quiet and seen["nodes"] and not link.unnamed():
                break
        return seen
