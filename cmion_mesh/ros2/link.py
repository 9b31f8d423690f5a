"""The "ROS link": what the ROS 2 competencies need from a robot, whichever way they reach it.

Two implementations, chosen by the library's ``transport=`` parameter:

* ``rmw_zenoh`` (``ros2/zenoh_link.py``): the daemon's own zenoh session is the ROS 2 node and
  speaks rmw_zenoh's wire format (``ros2/wire.py``); nothing of ROS is installed.
* ``rclpy`` (``ros2/rclpy_link.py``): an rclpy node hosted by the daemon, on whatever RMW the
  environment selects (Fast DDS from the ``ros2`` extra's wheels, rmw_zenoh on a full ROS
  installation); rclpy's executor runs on a thread of its own and hands every callback over.

The competencies (``ros2/competencies.py``, ``ros2/actions.py``) are written once against the
protocols below; messages reach them as objects with attributes (``feedback.current_pose``),
which ``interfaces.plain`` turns into blackboard values, and go out as dicts of field values.
One link per (transport, zenoh session, domain, namespace, node name), shared by the
competencies that name the same ones, closed when the last of them stops.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Protocol

from cmion_mesh.errors import ConfigError
from cmion_mesh.transport.base import QueryCancel, Transport

TRANSPORTS = ("rmw_zenoh", "rclpy")
EXTRA_HINT = "pip install 'cmion-mesh[ros2]' (the rclpy wheels), or source a ROS 2 installation"


class LinkPublisher(Protocol):
    name: str  # fully qualified
    type_name: str

    def publish(self, values: dict[str, Any]) -> None:
        """One message from field values (missing fields take their defaults)."""

    def wait_subscribers(self, timeout: float, cancelled: threading.Event) -> bool:
        """Wait until a subscriber that receives these messages is there; False if none came."""

    def mismatches(self) -> str:
        """The subscribers of this topic that never receive these messages (another type or
        definition), described for a failure's reason; empty when there are none."""


class LinkActionClient(Protocol):
    name: str  # the action's fully qualified name
    type_name: str

    def wait_server(self, timeout: float, cancelled: threading.Event) -> bool:
        """Wait until a server of this action, type and definition is there."""

    def mismatches(self) -> str:
        """The servers of this action of another type or definition, described."""

    def who(self) -> str:
        """``node /fibonacci_server (...)``: the nodes serving this action now, for messages."""

    def has_servers(self) -> bool: ...

    def watch_servers(self, on_gone: Callable[[], None]) -> Callable[[], None]:
        """Call ``on_gone`` (from the link's thread: hand over) when the last server leaves;
        the returned function stops watching."""

    def new_goal_id(self) -> bytes: ...

    def follow(self, goal_id: bytes, on_feedback: Callable[[Any], None], on_malformed: Callable[[str], None]) -> Callable[[], None]:
        """Route one goal's feedback to ``on_feedback`` (from the link's thread: hand over) until
        the returned function is called."""

    def send(self, goal_id: bytes, goal: dict[str, Any], *, timeout: float) -> bool:
        """Send a goal; whether the server accepted it. ``OutcomeUnknown`` when nobody answered."""

    def result(self, goal_id: bytes, *, timeout: float, cancel: QueryCancel | None = None) -> tuple[int, Any]:
        """Wait for the goal's end: (action_msgs GoalStatus, result message). ``cancel`` stops
        waiting (``OutcomeUnknown``)."""

    def cancel(self, goal_id: bytes, timeout: float) -> int:
        """Ask the server to cancel a goal; CancelGoal's return code (0: it is canceling)."""


class RosLink(Protocol):
    transport: str  # "rmw_zenoh" or "rclpy"
    domain: int
    path: str  # the node's fully qualified name

    def publisher(self, topic: str, type_name: str) -> LinkPublisher: ...

    def subscribe(self, topic: str, type_name: str, handler: Callable[[Any], None], *,
                  on_malformed: Callable[[str], None] | None = None) -> None:
        """``handler(message)`` for each message (from the link's thread: hand over)."""

    def action_client(self, action: str, type_name: str) -> LinkActionClient: ...

    def close(self) -> None: ...


class LinkTypes(Protocol):
    """What a competency checks when its library is loaded (so the library file's line is named)."""

    def known(self, type_name: str) -> bool: ...

    def known_action(self, type_name: str) -> bool: ...

    def string_fields(self, type_name: str) -> list[str]: ...


def check_transport(value: str, label: str) -> str:
    if value not in TRANSPORTS:
        raise ConfigError(f"{label}: transport {value!r} (one of: {', '.join(TRANSPORTS)})")
    if value == "rclpy":
        import importlib.util

        if importlib.util.find_spec("rclpy") is None:
            raise ConfigError(f"{label}: transport=rclpy needs rclpy: {EXTRA_HINT}")
    return value


def types_for(transport: str) -> LinkTypes:
    if transport == "rclpy":
        from cmion_mesh.ros2 import rclpy_link

        return rclpy_link.TYPES
    from cmion_mesh.ros2 import zenoh_link

    return zenoh_link.shared_types()


# --- one link per (transport, session, domain, namespace, name), shared ---------------------------

_links: dict[tuple[str, int, int, str, str], tuple[RosLink, int]] = {}
_lock = threading.Lock()


def acquire(transport: str, session: Transport, domain: int, namespace: str, name: str) -> RosLink:
    key = (transport, id(session) if transport == "rmw_zenoh" else 0, domain, namespace, name)
    with _lock:
        found = _links.get(key)
        if found is not None:
            _links[key] = (found[0], found[1] + 1)
            return found[0]
        link: RosLink
        if transport == "rclpy":
            from cmion_mesh.ros2 import rclpy_link

            link = rclpy_link.RclpyLink(name, domain=domain, namespace=namespace)
        else:
            from cmion_mesh.ros2 import zenoh_link

            link = zenoh_link.ZenohLink(session, name, domain=domain, namespace=namespace)
        _links[key] = (link, 1)
        return link


def release(link: RosLink) -> None:
    with _lock:
        for key, (held, count) in list(_links.items()):
            if held is link:
                if count > 1:
                    _links[key] = (held, count - 1)
                    return
                del _links[key]
                break
    link.close()
