"""Competencies that drive a ROS 2 robot over rmw_zenoh (``cmion_mesh/ros2/wire.py`` is the wire).

The daemon's own zenoh session is a ROS 2 node (``cmion_<embodiment>`` unless ``node=`` says
otherwise): no ROS installation, no DDS, no bridge process. Every parameter is ``name=value`` in
the library's ``ConstructorParameters``; each competency takes ``domain`` (default
``$ROS_DOMAIN_ID``, else 0), ``namespace`` (default the root) and ``node``; competencies with the
same three share one node.

* ``Ros2Navigation`` (type ``Navigation``): run parameter ``Location``; sends a
  ``nav2_msgs/action/NavigateToPose`` goal (``action=navigate_to_pose``, ``frame=map``,
  ``behavior_tree=``) to the pose of the location: ``place.<Name>=x y yaw`` (metres, radians),
  else the world model's ``<Name>.x``, ``.y`` and ``.yaw``. Writes BB ``navigation/target``,
  ``navigation/state`` (moving, arrived, stopped, failed) and ``navigation/feedback`` (at most
  every ``feedback_interval`` s), WM ``Self.location`` on success. A cancel sends ``cancel_goal``
  and waits (``cancel_timeout``) for the goal to end; the action's result decides success; a
  server whose liveliness goes fails the run naming its node; ``server_timeout`` bounds the
  wait for a server, ``goal_timeout`` the goal's acceptance, ``timeout`` the whole trip.
* ``Ros2Velocity`` (type ``Velocity``): run parameters ``Linear`` (m/s), ``Angular`` (rad/s),
  ``Duration`` (s); publishes ``geometry_msgs/msg/Twist`` on ``topic=cmd_vel`` at ``rate=10``
  Hz for the duration (at most ``max_duration=10``; speeds clipped to ``max_linear=0.5`` and
  ``max_angular=1.0``), then a zero Twist; a cancel publishes the zero Twist at once.
* ``Ros2Speech`` (type ``SpeechSynthesis``): run parameter ``TextInName`` (a BB name, as the
  simulated one) or ``Text``; publishes ``std_msgs/msg/String`` (``type=``, its field
  ``field=data``) on ``topic=speech``; writes BB ``speech/last``, WM ``Self.lastUtterance`` and
  raises ``Spoke``.
* ``Ros2SensorBridge`` (background, type ``Ros2Sensors``): ``sensor.<alias>=<topic> <type>``
  (as many as wanted); writes each topic's latest message to BB ``<container>/<alias>``
  (``container=ros2``), or with ``store=worldmodel`` to the property ``<alias>`` of the WM
  entity ``<container>``, at most every ``interval=0.5`` s (the last one is never lost, only the
  ones between).

The publishing competencies wait (``subscriber_timeout=2`` s) for a subscriber on the robot and
fail naming the topic when there is none: a message nobody receives is not success. A message
from the robot that is not valid CDR of its type is refused and logged, naming the topic and the
node; a malformed reply to a navigation goal fails the run with that reason.
"""

from __future__ import annotations

import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

from cmion_mesh import keys
from cmion_mesh.competencies.common import SELF, bb_set, parse_seconds, quietly, text_parameter, wm_set
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.ion import Simulation
from cmion_mesh.ros2 import wire as ros2
from cmion_mesh.ros2.interfaces import Types, plain, split_type
from cmion_mesh.transport.base import QueryCancel

__all__ = ["Ros2Competency", "Ros2Navigation", "Ros2SensorBridge", "Ros2Speech", "Ros2Velocity"]

log = logging.getLogger(__name__)

# --- one node per (transport, domain, namespace, name), shared by the competencies --------------

_nodes: dict[tuple[int, int, str, str], tuple[ros2.Node, int]] = {}
_nodes_lock = threading.Lock()
_types: Types | None = None


def _shared_types() -> Types:
    global _types
    with _nodes_lock:
        if _types is None:
            _types = Types()
        return _types


def _acquire(sim: Simulation, domain: int, namespace: str, name: str) -> ros2.Node:
    types = _shared_types()
    key = (id(sim.transport), domain, namespace, name)
    with _nodes_lock:
        found = _nodes.get(key)
        if found is None:
            node = ros2.Node(sim.transport, name, domain=domain, namespace=namespace, types=types)
            _nodes[key] = (node, 1)
            return node
        _nodes[key] = (found[0], found[1] + 1)
        return found[0]


def _release(node: ros2.Node) -> None:
    with _nodes_lock:
        for key, (held, count) in list(_nodes.items()):
            if held is node:
                if count > 1:
                    _nodes[key] = (held, count - 1)
                    return
                del _nodes[key]
                break
    node.close()


def _number(value: Any, what: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{what}: {value!r} is not a number") from None
    if not math.isfinite(number):
        raise ConfigError(f"{what}: {value!r} is not a finite number")
    return number


class Ros2Competency(Competency):
    """Base: ``name=value`` parameters, and the shared ROS 2 node (made when the embodiment starts
    the competency, withdrawn when it stops it)."""

    #: The parameter names a subclass takes besides domain, namespace and node, with defaults.
    defaults: ClassVar[dict[str, str]] = {}
    #: Parameter name prefixes taking any suffix (``place.``, ``sensor.``).
    prefixes: ClassVar[tuple[str, ...]] = ()

    def __init__(self, *parameters: str, name: str | None = None) -> None:
        super().__init__(*parameters, name=name)
        label = type(self).__name__
        options: dict[str, str] = {}
        for item in parameters:
            if not item.strip():
                continue
            key, sep, value = item.partition("=")
            key = key.strip()
            if not sep:
                raise ConfigError(f"{label}: parameter {item!r} is not name=value")
            if key not in self.defaults and key not in ("domain", "namespace", "node") and not key.startswith(self.prefixes):
                known = sorted([*self.defaults, "domain", "namespace", "node", *(p + "NAME" for p in self.prefixes)])
                raise ConfigError(f"{label}: unknown parameter {key!r} (known: {', '.join(known)})")
            if key in options:
                raise ConfigError(f"{label}: parameter {key!r} given twice")
            options[key] = value.strip()
        self.options = {**self.defaults, **options}
        domain = options.get("domain", os.environ.get("ROS_DOMAIN_ID", "0") or "0")
        try:
            self.domain = int(domain)
        except ValueError:
            raise ConfigError(f"{label}: domain {domain!r} is not a ROS 2 domain id (0..232)") from None
        if not 0 <= self.domain <= 232:
            raise ConfigError(f"{label}: domain {self.domain} out of range (0..232)")
        self.namespace = options.get("namespace", "")
        if self.namespace.strip("/"):
            try:
                ros2.qualify("x", self.namespace)
            except ConfigError:
                raise ConfigError(f"{label}: invalid ROS 2 namespace {self.namespace!r}: use letters, digits, _ and /") from None
        self.node_name = options.get("node", "")
        self.node: ros2.Node | None = None

    def check_type(self, type_name: str, what: str) -> str:
        """``type_name`` if it is a ROS 2 type this library knows; else ``ConfigError`` (at load
        time, so that the library file's line is named, not a failure when the daemon starts)."""
        if split_type(type_name)[1] == "action" and _shared_types().known(f"{type_name}_SendGoal"):
            raise ConfigError(f"{type(self).__name__}: {what} {type_name!r} is an action, not a message type")
        if not _shared_types().known(type_name):
            raise ConfigError(f"{type(self).__name__}: {what} {type_name!r} is not a ROS 2 Jazzy type known here "
                              "(std_msgs, geometry_msgs, nav_msgs, sensor_msgs... and nav2_msgs/action/NavigateToPose)")
        return type_name

    def seconds(self, key: str) -> float:
        return parse_seconds(self.options[key], f"{type(self).__name__}: {key}")

    def start(self, sim: Simulation) -> None:
        if self.node is None:
            name = self.node_name or "cmion_" + "".join(c if c.isalnum() else "_" for c in sim.embodiment)
            self.node = _acquire(sim, self.domain, self.namespace, name)
            self.declare(self.node)
        super().start(sim)

    def declare(self, node: ros2.Node) -> None:
        """Declare the publishers, subscriptions and clients this competency uses."""

    def stop(self, timeout: float = 10.0) -> None:
        super().stop(timeout)
        node, self.node = self.node, None
        if node is not None:
            _release(node)

    def wait_subscriber(self, ctx: RunContext, publisher: ros2.Publisher) -> bool:
        """Wait for a subscriber of ``publisher``'s topic, type and type hash (one of another type
        or definition never receives these messages); False (with the reason) if none came."""
        node = publisher.node
        timeout = self.seconds("subscriber_timeout")
        if node.graph.wait_for(lambda: bool(node.subscribers(publisher)), timeout, ctx.cancelled):
            return True
        if ctx.cancelled.is_set():
            return False
        others = ros2.describe_mismatches([e for e in node.graph.subscribers(publisher.name) if e.zid != node.zid],
                                          publisher.type_name, publisher.type_hash)
        return ctx.fail(f"no ROS 2 node subscribes to {publisher.name} ({publisher.type_name}) on domain {node.domain} "
                        f"within {timeout:g} s" + (f": {others}" if others else ""))


# --- navigation ------------------------------------------------------------------------------------


class Ros2Navigation(Ros2Competency):
    type = "Navigation"
    defaults: ClassVar[dict[str, str]] = {
        "action": "navigate_to_pose", "action_type": "nav2_msgs/action/NavigateToPose", "frame": "map",
        "behavior_tree": "", "agent": SELF, "server_timeout": "5", "goal_timeout": "5", "timeout": "600",
        "cancel_timeout": "5", "feedback_interval": "0.2",
    }
    prefixes = ("place.",)

    def __init__(self, *parameters: str, name: str | None = None) -> None:
        super().__init__(*parameters, name=name)
        for key in ("server_timeout", "goal_timeout", "timeout", "cancel_timeout", "feedback_interval"):
            self.seconds(key)
        self.agent = keys.check_name(self.options["agent"], "Ros2Navigation: agent")
        self.check_type(self.options["action_type"] + "_SendGoal", "action_type (its SendGoal service)")
        ros2.qualify(self.options["action"], self.namespace)
        self.places: dict[str, tuple[float, float, float]] = {}
        for key, value in self.options.items():
            if key.startswith("place."):
                place = key[len("place."):]
                numbers = value.split()
                if len(numbers) not in (2, 3):
                    raise ConfigError(f"Ros2Navigation: {key}={value!r}: give x y [yaw] (metres, radians)")
                x, y, *rest = (_number(n, f"Ros2Navigation: {key}") for n in numbers)
                self.places[place] = (x, y, rest[0] if rest else 0.0)
        self.client: ros2.ActionClient | None = None
        self._events: queue.SimpleQueue[tuple[str, Any]] | None = None

    def declare(self, node: ros2.Node) -> None:
        self.client = node.action_client(self.options["action"], self.options["action_type"])

    def _interrupt(self) -> None:
        events = self._events
        if events is not None:
            events.put(("cancel", None))

    def _pose(self, ctx: RunContext, target: str) -> tuple[float, float, float] | None:
        if target in self.places:
            return self.places[target]
        if not keys.is_name(target):
            return None
        x, y = ctx.wm_get(target, "x"), ctx.wm_get(target, "y")
        if x is None or y is None:
            return None
        try:
            return (_number(x, f"{target}.x"), _number(y, f"{target}.y"), _number(ctx.wm_get(target, "yaw", 0.0), f"{target}.yaw"))
        except ConfigError:
            return None

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        target = text_parameter(parameters, "Location")
        if not target:
            return ctx.fail("Ros2Navigation needs a Location parameter")
        pose = self._pose(ctx, target)
        if pose is None:
            known = sorted(self.places)
            return ctx.fail(f"no pose for {target!r}: give place.{target}=x y yaw in the competency library or "
                            f"{target}.x and {target}.y in the world model" + (f" (places: {', '.join(known)})" if known else ""))
        client = self.client
        assert client is not None and self.node is not None
        graph = self.node.graph
        server_timeout = self.seconds("server_timeout")
        if not graph.wait_for(lambda: bool(client.servers()), server_timeout, ctx.cancelled):
            if ctx.cancelled.is_set():
                return False
            others = client.send_goal.mismatches()
            return ctx.fail(f"no ROS 2 node serves the action {client.name} ({client.type_name}) on domain "
                            f"{self.node.domain} within {server_timeout:g} s" + (f": {others}" if others else ""))
        who = ros2.describe_peers(client.servers())
        events: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._events = events
        if ctx.cancelled.is_set():
            return False
        goal_id = client.new_goal_id()

        def on_change(entity: ros2.Entity, alive: bool) -> None:
            if not alive and entity.kind == "SS" and entity.name == client.send_goal.name and not client.servers():
                events.put(("vanished", entity))

        unwatch = graph.watch(on_change)
        unfollow = client.follow(goal_id, lambda feedback: events.put(("feedback", feedback)),
                                 lambda reason: events.put(("malformed", reason)))
        try:
            bb_set(ctx, "navigation/target", target)
            bb_set(ctx, "navigation/state", "moving")
            x, y, yaw = pose
            goal = {"pose": {"header": {"frame_id": self.options["frame"]},
                             "pose": {"position": {"x": x, "y": y}, "orientation": ros2.yaw_quaternion(yaw)}},
                    "behavior_tree": self.options["behavior_tree"]}
            try:
                accepted = client.send(goal_id, goal, timeout=self.seconds("goal_timeout"))
            except MeshError as exc:
                return self._failed(ctx, f"the goal to {target} was not sent: {exc}")
            if not accepted:
                return self._failed(ctx, f"{who} rejected the goal to {target}")
            return self._follow(ctx, client, goal_id, target, who, events)
        finally:
            unwatch()
            unfollow()
            self._events = None

    def _failed(self, ctx: RunContext, reason: str, state: str = "failed") -> bool:
        quietly("navigation state", bb_set, ctx, "navigation/state", state)
        return ctx.fail(reason)

    def _follow(self, ctx: RunContext, client: ros2.ActionClient, goal_id: bytes, target: str, who: str,
                events: queue.SimpleQueue[tuple[str, Any]]) -> bool:
        timeout = self.seconds("timeout")

        stop_waiting = QueryCancel()

        def wait_result() -> None:
            try:
                events.put(("result", client.result(goal_id, timeout=timeout, cancel=stop_waiting)))
            except MeshError as exc:
                events.put(("error", exc))

        # get_result is answered when the goal ends: a call of its own, so that feedback, a
        # cancel and the server's departure are seen meanwhile; whatever ends the run ends it.
        waiter = threading.Thread(target=wait_result, name=f"{self.name}-result", daemon=True)
        waiter.start()
        try:
            return self._wait(ctx, client, goal_id, target, who, events, timeout)
        finally:
            stop_waiting.cancel()
            waiter.join(5.0)

    def _wait(self, ctx: RunContext, client: ros2.ActionClient, goal_id: bytes, target: str, who: str,
              events: queue.SimpleQueue[tuple[str, Any]], timeout: float) -> bool:
        interval = self.seconds("feedback_interval")
        last_feedback = -math.inf
        # The newest feedback that came within ``interval`` of the last one written: written when
        # its turn comes or the goal ends, so the blackboard never keeps an older one than the robot sent.
        pending: Any = None
        deadline = time.monotonic() + timeout
        cancel_deadline: float | None = None
        if ctx.cancelled.is_set():
            events.put(("cancel", None))
        while True:
            end = cancel_deadline if cancel_deadline is not None else deadline
            wake = end if pending is None else min(end, last_feedback + interval)
            try:
                kind, value = events.get(timeout=max(0.0, wake - time.monotonic()))
            except queue.Empty:
                if pending is not None and time.monotonic() < end:
                    self._feedback(ctx, pending)
                    last_feedback, pending = time.monotonic(), None
                    continue
                if cancel_deadline is not None:
                    return self._failed(ctx, f"{who} did not end the goal to {target} within "
                                             f"{self.seconds('cancel_timeout'):g} s of its cancel", "stopped")
                quietly("cancel on timeout", client.cancel, goal_id, self.seconds("cancel_timeout"))
                return self._failed(ctx, f"the goal to {target} did not end within {timeout:g} s (cancelled)")
            if kind != "feedback" and pending is not None:
                self._feedback(ctx, pending)
                pending = None
            if kind == "feedback":
                now = time.monotonic()
                if now - last_feedback >= interval:
                    self._feedback(ctx, value)
                    last_feedback, pending = now, None
                else:
                    pending = value
            elif kind == "malformed":
                log.debug("%s: %s", self.name, value)  # the node has logged it
            elif kind == "cancel":
                if cancel_deadline is None:
                    cancel_deadline = time.monotonic() + self.seconds("cancel_timeout")
                    try:
                        code = client.cancel(goal_id, self.seconds("cancel_timeout"))
                        if code != 0:
                            log.info("%s: cancel_goal answered %d", self.name, code)
                    except MeshError as exc:
                        return self._failed(ctx, f"cancelling the goal to {target}: {exc}", "stopped")
            elif kind == "vanished":
                return self._failed(ctx, f"the ROS 2 {who} serving {client.name} left (its liveliness token is gone) "
                                         f"while going to {target}")
            elif kind == "error":
                # A server that leaves ends the pending get_result query before its token's
                # removal may be heard: say which it was.
                if self.node is not None and self.node.graph.wait_for(lambda: not client.servers(), 1.0):
                    events.put(("vanished", None))
                    continue
                return self._failed(ctx, f"the result of the goal to {target}: {value}")
            elif kind == "result":
                status, result = value
                return self._ended(ctx, target, who, status, result, cancelled=cancel_deadline is not None)

    def _feedback(self, ctx: RunContext, feedback: Any) -> None:
        position = feedback.current_pose.pose.position
        summary = {"distance_remaining": plain(float(feedback.distance_remaining)),
                   "x": plain(float(position.x)), "y": plain(float(position.y)),
                   "number_of_recoveries": int(feedback.number_of_recoveries),
                   "estimated_time_remaining": feedback.estimated_time_remaining.sec
                   + feedback.estimated_time_remaining.nanosec / 1e9}
        quietly("navigation feedback", bb_set, ctx, "navigation/feedback", summary)
        quietly("progress", ctx.progress, summary)

    def _ended(self, ctx: RunContext, target: str, who: str, status: int, result: Any, *, cancelled: bool) -> bool:
        if status == ros2.STATUS_SUCCEEDED and not cancelled:
            bb_set(ctx, "navigation/state", "arrived")
            wm_set(ctx, self.agent, "location", target)
            return True
        name = ros2.STATUS_NAMES.get(status, str(status))
        detail = ""
        code, message = getattr(result, "error_code", 0), getattr(result, "error_msg", "")
        if code or message:
            detail = f" (error {code}{': ' + message if message else ''})"
        return self._failed(ctx, f"{who} ended the goal to {target}: {name}{detail}", "stopped" if cancelled else "failed")


# --- velocity ------------------------------------------------------------------------------------


class Ros2Velocity(Ros2Competency):
    type = "Velocity"
    defaults: ClassVar[dict[str, str]] = {
        "topic": "cmd_vel", "rate": "10", "max_duration": "10", "max_linear": "0.5", "max_angular": "1.0",
        "subscriber_timeout": "2",
    }

    def __init__(self, *parameters: str, name: str | None = None) -> None:
        super().__init__(*parameters, name=name)
        self.rate = _number(self.options["rate"], "Ros2Velocity: rate")
        if not 0 < self.rate <= 1000:
            raise ConfigError(f"Ros2Velocity: rate {self.rate:g} Hz out of range (0..1000]")
        for key in ("max_duration", "max_linear", "max_angular", "subscriber_timeout"):
            self.seconds(key)  # non-negative finite numbers
        ros2.qualify(self.options["topic"], self.namespace)
        self.publisher: ros2.Publisher | None = None
        self._wake = threading.Event()

    def declare(self, node: ros2.Node) -> None:
        self.publisher = node.publisher(self.options["topic"], "geometry_msgs/msg/Twist")

    def _interrupt(self) -> None:
        self._wake.set()

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        publisher = self.publisher
        assert publisher is not None
        try:
            linear = _number(parameters.get("Linear", 0), "Linear")
            angular = _number(parameters.get("Angular", 0), "Angular")
            duration = _number(parameters.get("Duration", 1), "Duration")
        except ConfigError as exc:
            return ctx.fail(str(exc))
        if duration < 0:
            return ctx.fail(f"Duration {duration:g} s is negative")
        duration = min(duration, self.seconds("max_duration"))
        limit_linear, limit_angular = self.seconds("max_linear"), self.seconds("max_angular")
        linear = max(-limit_linear, min(limit_linear, linear))
        angular = max(-limit_angular, min(limit_angular, angular))
        if not self.wait_subscriber(ctx, publisher):
            return False
        moving = {"linear": {"x": linear}, "angular": {"z": angular}}
        end = time.monotonic() + duration
        period = 1.0 / self.rate
        self._wake.clear()
        try:
            for _ in range(int(duration * self.rate) + 2):  # bounded: one per period, plus the first
                if ctx.cancelled.is_set() or time.monotonic() >= end:
                    break
                publisher.publish(moving)
                self._wake.wait(max(0.0, min(period, end - time.monotonic())))
        finally:
            # Stop the robot whatever ended the run: the duration, a cancel, a failure.
            quietly("zero Twist", publisher.publish, {})
        return not ctx.cancelled.is_set()


# --- speech --------------------------------------------------------------------------------------


class Ros2Speech(Ros2Competency):
    type = "SpeechSynthesis"
    defaults: ClassVar[dict[str, str]] = {
        "topic": "speech", "type": "std_msgs/msg/String", "field": "data", "agent": SELF, "subscriber_timeout": "2",
    }

    def __init__(self, *parameters: str, name: str | None = None) -> None:
        super().__init__(*parameters, name=name)
        self.agent = keys.check_name(self.options["agent"], "Ros2Speech: agent")
        self.check_type(self.options["type"], "type")
        strings = _shared_types().string_fields(self.options["type"])
        if self.options["field"] not in strings:
            raise ConfigError(f"Ros2Speech: field {self.options['field']!r} is not a string field of {self.options['type']} "
                              f"(its string fields: {', '.join(strings) or 'none'})")
        ros2.qualify(self.options["topic"], self.namespace)
        self.seconds("subscriber_timeout")
        self.publisher: ros2.Publisher | None = None

    def declare(self, node: ros2.Node) -> None:
        self.publisher = node.publisher(self.options["topic"], self.options["type"])

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        publisher = self.publisher
        assert publisher is not None
        text = text_parameter(parameters, "Text")
        source = text_parameter(parameters, "TextInName")
        if not text and source:
            value = ctx.bb_get(source)
            text = "" if value is None else str(value).strip()
            if not text:
                return ctx.fail(f"nothing to say: no text on the blackboard under {source!r}")
        if not text:
            return ctx.fail("Ros2Speech needs a Text or a TextInName parameter")
        if not self.wait_subscriber(ctx, publisher):
            return False
        publisher.publish({self.options["field"]: text})
        bb_set(ctx, "speech/last", text)
        wm_set(ctx, self.agent, "lastUtterance", text)
        ctx.raise_event("Spoke", {"text": text, "topic": publisher.name})
        return True


# --- sensors -------------------------------------------------------------------------------------


class Ros2SensorBridge(Ros2Competency):
    type = "Ros2Sensors"
    background = True
    defaults: ClassVar[dict[str, str]] = {"interval": "0.5", "container": "ros2", "store": "blackboard"}
    prefixes = ("sensor.",)

    def __init__(self, *parameters: str, name: str | None = None) -> None:
        super().__init__(*parameters, name=name)
        self.interval = self.seconds("interval")
        self.container = keys.check_name(self.options["container"], "Ros2SensorBridge: container")
        self.store = self.options["store"]
        if self.store not in ("blackboard", "worldmodel"):
            raise ConfigError(f"Ros2SensorBridge: store {self.store!r} (blackboard or worldmodel)")
        self.sensors: dict[str, tuple[str, str]] = {}
        for key, value in self.options.items():
            if key.startswith("sensor."):
                alias = keys.check_name(key[len("sensor."):], "Ros2SensorBridge: sensor alias")
                parts = value.split()
                if len(parts) != 2:
                    raise ConfigError(f"Ros2SensorBridge: {key}={value!r}: give the topic and its type (odom nav_msgs/msg/Odometry)")
                ros2.qualify(parts[0], self.namespace)
                self.sensors[alias] = (parts[0], self.check_type(parts[1], f"{key}: type"))
        self._wake = threading.Event()
        self._latest: dict[str, Any] = {}
        self._lock = threading.Lock()

    def declare(self, node: ros2.Node) -> None:
        for alias, (topic, type_name) in self.sensors.items():
            node.subscribe(topic, type_name, self._arrival(alias), on_malformed=self._malformed)

    def _arrival(self, alias: str) -> Callable[[Any], None]:
        def arrived(message: Any) -> None:
            with self._lock:
                self._latest[alias] = message
            self._wake.set()

        return arrived

    def _malformed(self, reason: str) -> None:
        try:
            self.sim.raise_event(self.name, "MalformedMessage", {"reason": reason})
        except MeshError:
            pass  # stopping

    def _interrupt(self) -> None:
        self._wake.set()

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        written: dict[str, float] = {}
        while not ctx.cancelled.is_set():
            self._wake.wait()
            self._wake.clear()
            if ctx.cancelled.is_set():
                break
            now = time.monotonic()
            with self._lock:
                due = {a: m for a, m in self._latest.items() if now - written.get(a, -math.inf) >= self.interval}
                for alias in due:
                    del self._latest[alias]
                waiting = bool(self._latest)
            for alias, message in due.items():
                written[alias] = now
                if self.store == "blackboard":
                    quietly(f"sensor {alias}", bb_set, ctx, f"{self.container}/{alias}", plain(message))
                else:
                    quietly(f"sensor {alias}", wm_set, ctx, self.container, alias, plain(message))
            if waiting:
                # Something arrived too soon after its last write: come back when it is due.
                if not ctx.wait(self.interval):
                    break
                self._wake.set()
        return True
