"""Competencies that drive a ROS 2 robot, over rmw_zenoh's wire format or an rclpy node (``ros2/link.py``).

With ``transport=rmw_zenoh`` (the default) the daemon's own zenoh session is a ROS 2 node
(``cmion_<embodiment>`` unless ``node=`` says otherwise): no ROS installation, no DDS, no bridge
process; with ``transport=rclpy`` an rclpy node hosted by the daemon, on the RMW the environment
selects (Fast DDS with the ``ros2`` extra). Every parameter is ``name=value`` in the library's
``ConstructorParameters``; each competency takes ``transport``, ``domain`` (default
``$ROS_DOMAIN_ID``, else 0), ``namespace`` (default the root) and ``node``; competencies with the
same four share one link (``ros2/base.py``). The action competencies (``Ros2Navigation``, and
``Ros2Action`` for any action type) are in ``ros2/actions.py``, and importable from here.

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
node (rmw_zenoh; over rclpy the RMW refuses it); a malformed reply to a goal fails the run with that reason.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

from cmion_mesh import keys
from cmion_mesh.competencies.common import SELF, bb_set, quietly, text_parameter, wm_set
from cmion_mesh.competency import RunContext
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.ros2.actions import Ros2Action, Ros2Navigation
from cmion_mesh.ros2.base import Ros2Competency, number
from cmion_mesh.ros2.interfaces import plain
from cmion_mesh.ros2.link import LinkPublisher, RosLink
from cmion_mesh.ros2.wire import qualify

__all__ = ["Ros2Action", "Ros2Competency", "Ros2Navigation", "Ros2SensorBridge", "Ros2Speech", "Ros2Velocity"]


# --- velocity ------------------------------------------------------------------------------------


class Ros2Velocity(Ros2Competency):
    type = "Velocity"
    defaults: ClassVar[dict[str, str]] = {
        "topic": "cmd_vel", "rate": "10", "max_duration": "10", "max_linear": "0.5", "max_angular": "1.0",
        "subscriber_timeout": "2",
    }

    def __init__(self, *parameters: str, name: str | None = None) -> None:
        super().__init__(*parameters, name=name)
        self.rate = number(self.options["rate"], "Ros2Velocity: rate")
        if not 0 < self.rate <= 1000:
            raise ConfigError(f"Ros2Velocity: rate {self.rate:g} Hz out of range (0..1000]")
        for key in ("max_duration", "max_linear", "max_angular", "subscriber_timeout"):
            self.seconds(key)  # non-negative finite numbers
        qualify(self.options["topic"], self.namespace)
        self.publisher: LinkPublisher | None = None
        self._wake = threading.Event()

    def declare(self, link: RosLink) -> None:
        self.publisher = link.publisher(self.options["topic"], "geometry_msgs/msg/Twist")

    def _interrupt(self) -> None:
        self._wake.set()

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        publisher = self.publisher
        assert publisher is not None
        try:
            linear = number(parameters.get("Linear", 0), "Linear")
            angular = number(parameters.get("Angular", 0), "Angular")
            duration = number(parameters.get("Duration", 1), "Duration")
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
        strings = self.types.string_fields(self.options["type"])
        if self.options["field"] not in strings:
            raise ConfigError(f"Ros2Speech: field {self.options['field']!r} is not a string field of {self.options['type']} "
                              f"(its string fields: {', '.join(strings) or 'none'})")
        qualify(self.options["topic"], self.namespace)
        self.seconds("subscriber_timeout")
        self.publisher: LinkPublisher | None = None

    def declare(self, link: RosLink) -> None:
        self.publisher = link.publisher(self.options["topic"], self.options["type"])

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
                qualify(parts[0], self.namespace)
                self.sensors[alias] = (parts[0], self.check_type(parts[1], f"{key}: type"))
        self._wake = threading.Event()
        self._latest: dict[str, Any] = {}
        self._lock = threading.Lock()

    def declare(self, link: RosLink) -> None:
        for alias, (topic, type_name) in self.sensors.items():
            link.subscribe(topic, type_name, self._arrival(alias), on_malformed=self._malformed)

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
