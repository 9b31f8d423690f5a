"""A ROS 2 robot as a body: mind action -> Nav2 goal at the robot, and the goal's result -> action succeeded.

Processes (all on loopback): a daemon ``cmion-mesh up ros_robot`` (the shipped embodiment: GoTo is
one ``Ros2Navigation`` step sending a ``nav2_msgs/action/NavigateToPose`` goal over rmw_zenoh);
``python -m bench.core serve-raw`` (a raw zenoh queryable); the measuring process, which is both
the operator (a ``MeshClient`` sending ``GoTo Kitchen``) and the robot: a raw zenoh session playing
a Nav2 node (its liveliness tokens, the ``send_goal`` and ``get_result`` queryables, rmw_zenoh's
keys and attachments), so that both ends of each metric are read from one clock.

Metrics:

* ``ros2_goal``: ``MeshClient.start_action(ros_robot, GoTo, Kitchen)`` called until the
  ``send_goal`` request is in the robot's queryable (the act request, the plan, the competency,
  CDR encoding, one zenoh query).
* ``ros2_result``: the robot's ``get_result`` reply (status SUCCEEDED) sent until the client sees
  the action succeeded (CDR decoding, the blackboard and world-model writes on arrival, the end
  event).
* ``raw_get``: a raw zenoh get round trip between two processes, for context: each metric is a
  little more than one such hop plus the body's work.
"""

from __future__ import annotations

import queue
import tempfile
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import zenoh

from bench.core import RawGet, _drain, open_session
from bench.daemons import Node, stop_and_report
from bench.harness import loopback_config, loopback_endpoint, start_child, stop_child
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.procs import unique_mesh
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.ros2 import wire as ros2
from cmion_mesh.ros2.interfaces import Types
from cmion_mesh.transport.zenoh import ZenohTransport

EMBODIMENT = "ros_robot"
ACTION = "nav2_msgs/action/NavigateToPose"

LABELS = {
    "raw_get": "raw zenoh get, round trip (context)",
    "ros2_goal": "GoTo Kitchen -> NavigateToPose goal received by the ROS 2 node",
    "ros2_result": "goal result sent by the ROS 2 node -> action succeeded at the client",
}


def log(text: str) -> None:
    print(f"  [ros2] {text}", flush=True)


class RawRosNode:
    """A raw zenoh session playing an rmw_zenoh node: its liveliness token, then what is declared on
    it (``serve_action``); ``close`` undeclares all, newest first, and joins the queryables' threads."""

    def __init__(self, session: zenoh.Session, types: Types, domain: int, name: str) -> None:
        self.session, self.types, self.domain, self.name = session, types, domain, name
        self.zid = str(session.zid())
        self._undeclare: list[Any] = [session.liveliness().declare_token(ros2.node_token(domain, self.zid, 0, "", name))]
        self._threads: list[threading.Thread] = []

    def serve_action(self, action_type: str, action_name: str, first_eid: int, send_goal: Callable[[zenoh.Query], None],
                     get_result: Callable[[zenoh.Query], None], threads: str) -> None:
        """The action's send_goal and get_result services (entities ``first_eid`` and the next), each
        a queryable drained by a thread named ``threads``-<service>."""
        for eid, (service, answer) in enumerate((("send_goal", send_goal), ("get_result", get_result)), start=first_eid):
            type_name = f"{action_type}_{'SendGoal' if service == 'send_goal' else 'GetResult'}"
            type_hash = self.types.hash(type_name)
            topic = f"{action_name}/_action/{service}"
            key = ros2.topic_key(self.domain, topic, type_name, type_hash)
            queryable = self.session.declare_queryable(key, zenoh.handlers.FifoChannel(256), complete=True)
            self._undeclare.append(queryable)
            self._threads.append(_drain(f"{threads}-{service}", queryable.handler.recv, answer))
            token = ros2.entity_token(self.domain, self.zid, 0, eid, "SS", "", self.name, topic, type_name, type_hash)
            self._undeclare.append(self.session.liveliness().declare_token(token))

    def reply(self, query: zenoh.Query, type_name: str, values: dict[str, Any]) -> None:
        """``values`` as the service's response, with the request's attachment (rmw_zenoh's sequence number and GID)."""
        attachment = query.attachment
        payload = self.types.encode(f"{type_name}_Response", values)
        query.reply(query.key_expr, payload, attachment=attachment.to_bytes() if attachment is not None else None)

    def close(self) -> None:
        for entity in reversed(self._undeclare):
            entity.undeclare()
        for thread in self._threads:
            thread.join(5.0)


class Nav2Node(RawRosNode):
    """The measuring process as a Nav2 node: goals are accepted and succeed at once; the moment each
    send_goal request arrives and each result is sent is recorded (``time.perf_counter``)."""

    def __init__(self, session: zenoh.Session, types: Types, domain: int = 0, name: str = "bench_nav2") -> None:
        super().__init__(session, types, domain, name)
        self.goals: queue.SimpleQueue[float] = queue.SimpleQueue()
        self.results: queue.SimpleQueue[float] = queue.SimpleQueue()
        self.serve_action(ACTION, "/navigate_to_pose", 1, self._send_goal, self._get_result, "bench-nav2")

    def _send_goal(self, query: zenoh.Query) -> None:
        self.goals.put(time.perf_counter())
        with query:
            self.reply(query, f"{ACTION}_SendGoal", {"accepted": True})

    def _get_result(self, query: zenoh.Query) -> None:
        with query:
            self.results.put(time.perf_counter())
            self.reply(query, f"{ACTION}_GetResult", {"status": ros2.STATUS_SUCCEEDED})


def goto_once(client: MeshClient, robot: Nav2Node) -> tuple[float, float]:
    """One GoTo Kitchen: (act -> goal received, result sent -> succeeded seen), in seconds."""
    t0 = time.perf_counter()
    with client.start_action(EMBODIMENT, "GoTo", ["Kitchen"]) as run:
        goal_at = robot.goals.get(timeout=30.0)
        report = run.wait(30.0)
        done = time.perf_counter()
    if report.status != "succeeded":
        raise MeshError(f"GoTo Kitchen ended {report.status}: {report.reason}")
    return goal_at - t0, done - robot.results.get(timeout=1.0)


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    mesh = unique_mesh("bench")
    raw_ep = loopback_endpoint()
    samples = max(50, options.samples // 10)  # an action is ~ms; a tenth of the round-trip probes' samples
    warmup = max(10, options.warmup // 10)
    started = time.monotonic()
    goal: list[float] = []
    result: list[float] = []
    raw: list[float] = []
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-ros2-")))
        raw_child = start_child("bench.core", "serve-raw", "--listen", raw_ep, "--tag", mesh, name="serve-raw")
        stack.callback(stop_child, raw_child)
        node = Node(EMBODIMENT, mesh, tmp / EMBODIMENT, architecture=str(embodiment_dir(EMBODIMENT) / "ArchitectureConfiguration.xml"))
        node.start()
        stack.callback(stop_and_report, [node], log)
        raw_child.wait_line("ready", 30.0)
        node.wait_up(60.0)
        log(f"daemon and raw peer up after {time.monotonic() - started:.2f} s (mesh {mesh})")
        raw_session = open_session(loopback_config(connect=raw_ep))
        stack.callback(raw_session.close)
        robot_session = open_session(loopback_config(connect=node.listen))
        stack.callback(robot_session.close)
        robot = Nav2Node(robot_session, Types())
        stack.callback(robot.close)
        transport = stack.enter_context(ZenohTransport(loopback_config(connect=node.listen)))
        client = stack.enter_context(MeshClient(transport, mesh))
        client.join(EMBODIMENT, timeout=30.0)
        raw_get = RawGet(raw_session, mesh)
        raw_get.contact()
        for _ in range(warmup):
            goto_once(client, robot)
        for _ in range(samples):
            t0 = time.perf_counter()
            raw_get.once()
            raw.append(time.perf_counter() - t0)
            to_goal, to_end = goto_once(client, robot)
            goal.append(to_goal)
            result.append(to_end)
        log(f"measured {samples} GoTo actions in {time.monotonic() - started:.1f} s")
    pooled = {"raw_get": raw, "ros2_goal": goal, "ros2_result": result}
    rows = [Row(m, LABELS[m], summarize(pooled[m])) for m in LABELS]
    compare(rows, {"ros2_goal": "raw_get", "ros2_result": "raw_get"}, None)
    return rows
