"""The base of the ROS 2 competencies: their ``name=value`` parameters, and the ROS link they share.

Every competency takes ``transport`` (``rmw_zenoh``, the default, or ``rclpy``: ``ros2/link.py``),
``domain`` (default ``$ROS_DOMAIN_ID``, else 0), ``namespace`` (default the root) and ``node``
(default ``cmion_<embodiment>``); competencies naming the same four share one link, made when the
embodiment starts the first of them and closed when it stops the last.
"""

from __future__ import annotations

import math
import os
from typing import Any, ClassVar

from cmion_mesh.competencies.common import parse_seconds
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import ConfigError
from cmion_mesh.ion import Simulation
from cmion_mesh.ros2 import link as links
from cmion_mesh.ros2.interfaces import split_type
from cmion_mesh.ros2.link import LinkPublisher, RosLink
from cmion_mesh.ros2.wire import qualify

COMMON = ("domain", "namespace", "node", "transport")


def number(value: Any, what: str) -> float:
    try:
        found = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{what}: {value!r} is not a number") from None
    if not math.isfinite(found):
        raise ConfigError(f"{what}: {value!r} is not a finite number")
    return found


class Ros2Competency(Competency):
    """Base: ``name=value`` parameters, and the shared ROS link (made when the embodiment starts
    the competency, released when it stops it)."""

    #: The parameter names a subclass takes besides the common ones, with defaults.
    defaults: ClassVar[dict[str, str]] = {}
    #: Parameter name prefixes taking any suffix (``place.``, ``sensor.``, ``goal.``).
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
            if key not in self.defaults and key not in COMMON and not key.startswith(self.prefixes):
                known = sorted([*self.defaults, *COMMON, *(p + "NAME" for p in self.prefixes)])
                raise ConfigError(f"{label}: unknown parameter {key!r} (known: {', '.join(known)})")
            if key in options:
                raise ConfigError(f"{label}: parameter {key!r} given twice")
            options[key] = value.strip()
        self.options = {**self.defaults, **options}
        self.transport = links.check_transport(options.get("transport", "rmw_zenoh"), label)
        self.types = links.types_for(self.transport)
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
                qualify("x", self.namespace)
            except ConfigError:
                raise ConfigError(f"{label}: invalid ROS 2 namespace {self.namespace!r}: use letters, digits, _ and /") from None
        self.node_name = options.get("node", "")
        self.link: RosLink | None = None

    def _unknown(self, what: str, type_name: str) -> ConfigError:
        if self.transport == "rclpy":
            return ConfigError(f"{type(self).__name__}: {what} {type_name!r} is not a ROS 2 type installed here "
                               f"(transport=rclpy finds the interface packages Python can import)")
        return ConfigError(f"{type(self).__name__}: {what} {type_name!r} is not a ROS 2 Jazzy type known here "
                           "(std_msgs, geometry_msgs, nav_msgs, sensor_msgs..., nav2_msgs/action/NavigateToPose, "
                           "and actions whose .action file is in a ROS share folder)")

    def check_type(self, type_name: str, what: str) -> str:
        """``type_name`` if it is a message type this transport knows; else ``ConfigError`` (at load
        time, so that the library file's line is named, not a failure when the daemon starts)."""
        if split_type(type_name)[1] == "action" and self.types.known_action(type_name):
            raise ConfigError(f"{type(self).__name__}: {what} {type_name!r} is an action, not a message type")
        if not self.types.known(type_name):
            raise self._unknown(what, type_name)
        return type_name

    def check_action(self, type_name: str, what: str) -> str:
        if split_type(type_name)[1] != "action":
            raise ConfigError(f"{type(self).__name__}: {what} {type_name!r} is not an action type (package/action/Name)")
        if not self.types.known_action(type_name):
            raise self._unknown(what, type_name)
        return type_name

    def seconds(self, key: str) -> float:
        return parse_seconds(self.options[key], f"{type(self).__name__}: {key}")

    def start(self, sim: Simulation) -> None:
        if self.link is None:
            name = self.node_name or "cmion_" + "".join(c if c.isalnum() else "_" for c in sim.embodiment)
            self.link = links.acquire(self.transport, sim.transport, self.domain, self.namespace, name)
            self.declare(self.link)
        super().start(sim)

    def declare(self, link: RosLink) -> None:
        """Declare the publishers, subscriptions and clients this competency uses."""

    def stop(self, timeout: float = 10.0) -> None:
        super().stop(timeout)
        link, self.link = self.link, None
        if link is not None:
            links.release(link)

    def wait_subscriber(self, ctx: RunContext, publisher: LinkPublisher) -> bool:
        """Wait for a subscriber that receives ``publisher``'s messages (one of another type or
        definition never does); False (with the reason) if none came."""
        timeout = self.seconds("subscriber_timeout")
        if publisher.wait_subscribers(timeout, ctx.cancelled):
            return True
        if ctx.cancelled.is_set():
            return False
        others = publisher.mismatches()
        domain = self.link.domain if self.link is not None else self.domain
        return ctx.fail(f"no ROS 2 node subscribes to {publisher.name} ({publisher.type_name}) on domain {domain} "
                        f"within {timeout:g} s" + (f": {others}" if others else ""))
