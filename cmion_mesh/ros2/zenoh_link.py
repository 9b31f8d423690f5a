"""The ROS link over rmw_zenoh's wire format: the daemon's zenoh session is the node (``ros2/wire.py``).

Callbacks come on the transport's worker (liveliness, samples): the competencies hand them over
to their own queues. Types are ROS 2 Jazzy's (``rosbags``), Nav2's NavigateToPose, and any action
whose ``.action`` file is found in an installed ROS share folder (``interfaces.Types.find_action``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from cmion_mesh.ros2 import wire
from cmion_mesh.ros2.interfaces import Types
from cmion_mesh.transport.base import QueryCancel, Transport

_types: Types | None = None
_types_lock = threading.Lock()


def shared_types() -> Types:
    global _types
    with _types_lock:
        if _types is None:
            _types = Types()
        return _types


class ZenohPublisher:
    def __init__(self, publisher: wire.Publisher) -> None:
        self._publisher = publisher
        self.name, self.type_name = publisher.name, publisher.type_name

    def publish(self, values: dict[str, Any]) -> None:
        self._publisher.publish(values)

    def wait_subscribers(self, timeout: float, cancelled: threading.Event) -> bool:
        node = self._publisher.node
        return node.graph.wait_for(lambda: bool(node.subscribers(self._publisher)), timeout, cancelled)

    def mismatches(self) -> str:
        node, publisher = self._publisher.node, self._publisher
        return wire.describe_mismatches([e for e in node.graph.subscribers(publisher.name) if e.zid != node.zid],
                                        publisher.type_name, publisher.type_hash)


class ZenohActionClient:
    def __init__(self, client: wire.ActionClient) -> None:
        self._client = client
        self.name, self.type_name = client.name, client.type_name

    def wait_server(self, timeout: float, cancelled: threading.Event) -> bool:
        return self._client.node.graph.wait_for(lambda: bool(self._client.servers()), timeout, cancelled)

    def mismatches(self) -> str:
        return self._client.send_goal.mismatches()

    def who(self) -> str:
        return wire.describe_peers(self._client.servers())

    def has_servers(self) -> bool:
        return bool(self._client.servers())

    def watch_servers(self, on_gone: Callable[[], None]) -> Callable[[], None]:
        client = self._client

        def on_change(entity: wire.Entity, alive: bool) -> None:
            if not alive and entity.kind == "SS" and entity.name == client.send_goal.name and not client.servers():
                on_gone()

        return client.node.graph.watch(on_change)

    def new_goal_id(self) -> bytes:
        return self._client.new_goal_id()

    def follow(self, goal_id: bytes, on_feedback: Callable[[Any], None], on_malformed: Callable[[str], None]) -> Callable[[], None]:
        return self._client.follow(goal_id, on_feedback, on_malformed)

    def send(self, goal_id: bytes, goal: dict[str, Any], *, timeout: float) -> bool:
        return self._client.send(goal_id, goal, timeout=timeout)

    def result(self, goal_id: bytes, *, timeout: float, cancel: QueryCancel | None = None) -> tuple[int, Any]:
        return self._client.result(goal_id, timeout=timeout, cancel=cancel)

    def cancel(self, goal_id: bytes, timeout: float) -> int:
        return self._client.cancel(goal_id, timeout)


class ZenohLink:
    """A ``wire.Node`` on the daemon's zenoh session, as a ROS link."""

    transport = "rmw_zenoh"

    def __init__(self, session: Transport, name: str, *, domain: int, namespace: str) -> None:
        self.node = wire.Node(session, name, domain=domain, namespace=namespace, types=shared_types())
        self.domain = domain
        self.path = self.node.path

    def publisher(self, topic: str, type_name: str) -> ZenohPublisher:
        return ZenohPublisher(self.node.publisher(topic, type_name))

    def subscribe(self, topic: str, type_name: str, handler: Callable[[Any], None], *,
                  on_malformed: Callable[[str], None] | None = None) -> None:
        self.node.subscribe(topic, type_name, handler, on_malformed=on_malformed)

    def action_client(self, action: str, type_name: str) -> ZenohActionClient:
        shared_types().find_action(type_name)
        return ZenohActionClient(self.node.action_client(action, type_name))

    def __enter__(self) -> ZenohLink:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        self.node.close()
