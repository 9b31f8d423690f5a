"""A DDS robot as a body: ``Drive`` -> first Twist at a real rclpy node, and goal sent -> goal accepted
by a real rclpy action server, beside the same two over rmw_zenoh, in one run.

Processes (all on loopback): two daemons, ``cmion-mesh up`` of one bench-made embodiment each
(rules ``Drive`` and ``Goal``; the same ``Ros2Velocity`` and ``Ros2Action`` competencies, one
daemon with ``transport=rclpy`` on Fast DDS, on a ROS domain of the run's own with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, the other with ``transport=rmw_zenoh``). The measuring
process is the operator (a ``MeshClient``) and the robot twice over: an rclpy node (its own
context and executor thread: a ``cmd_vel`` subscription and a ``test_msgs/action/Fibonacci``
server that accepts and ends every goal at once) and a raw zenoh session playing an rmw_zenoh node
with the same two entities (liveliness tokens, a subscriber, the send_goal and get_result
queryables). Both ends of each metric are read from one clock; the two ways alternate sample by
sample. Needs the ``ros2-test`` extra (rclpy, Fast DDS, test_msgs); without it, nothing is measured.

Metrics:

* ``rclpy_drive`` / ``zenoh_drive``: ``MeshClient.start_action(Drive 0.1 0 0.05)`` called until
  the first moving Twist is in the robot's subscription callback (the act request, the plan, the
  competency, its wait for the subscriber, one message over DDS or zenoh).
* ``rclpy_goal`` / ``zenoh_goal``: ``MeshClient.start_action(Goal {"order": 1})`` called until the
  server has the goal (its goal callback, or the send_goal query).
"""

from __future__ import annotations

import importlib.util
import json
import os
import queue
import random
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import zenoh

from bench.core import open_session
from bench.daemons import Node, stop_and_report
from bench.harness import loopback_config
from bench.registry import Options, Row, compare
from bench.ros2 import RawRosNode
from bench.stats import summarize
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.procs import unique_mesh
from cmion_mesh.ros2 import wire
from cmion_mesh.ros2.interfaces import Types
from cmion_mesh.transport.zenoh import ZenohTransport
from tests.helpers.ros2_embodiment import DRIVE, GOAL, write_embodiment

ACTION = "test_msgs/action/Fibonacci"
TWIST = "geometry_msgs/msg/Twist"

LABELS = {
    "zenoh_drive": "Drive -> first Twist at the robot, rmw_zenoh (context)",
    "rclpy_drive": "Drive -> first Twist at a real rclpy node, rclpy + Fast DDS",
    "zenoh_goal": "Goal -> goal at the action server, rmw_zenoh (context)",
    "rclpy_goal": "Goal -> goal accepted by a real rclpy action server, rclpy + Fast DDS",
}

LIBRARY = """<?xml version="1.0" encoding="UTF-8"?>
<CompetencyLibrary>
  <Competency ClassName="cmion_mesh.ros2.competencies:Ros2Velocity" ConstructorParameters="{common},rate=20,subscriber_timeout=20" />
  <Competency ClassName="cmion_mesh.ros2.competencies:Ros2Action"
    ConstructorParameters="{common},action=fibonacci,action_type={action},competency_type=RobotGoal,server_timeout=20" />
</CompetencyLibrary>
"""


def log(text: str) -> None:
    print(f"  [ros2_rclpy] {text}", flush=True)


def embodiment(folder: Path, name: str, common: str) -> Path:
    return write_embodiment(folder, name, rules=(DRIVE, GOAL), library=LIBRARY.format(common=common, action=ACTION))


class Arrivals:
    """What the robot got, stamped: moving Twists and goals (``time.perf_counter``)."""

    def __init__(self) -> None:
        self.twists: queue.SimpleQueue[float] = queue.SimpleQueue()
        self.goals: queue.SimpleQueue[float] = queue.SimpleQueue()

    def drain(self) -> None:
        for waiting in (self.twists, self.goals):
            while not waiting.empty():
                waiting.get_nowait()


class RclpyRobot(Arrivals):
    """A real rclpy node in this process: its own context (the run's domain), one executor thread."""

    def __init__(self, domain: int) -> None:
        super().__init__()
        import rclpy
        from geometry_msgs.msg import Twist
        from rclpy.action import ActionServer, GoalResponse
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node as RosNode
        from test_msgs.action import Fibonacci

        self._context = Context()
        rclpy.init(context=self._context, domain_id=domain)
        self.node = RosNode("bench_rclpy_robot", context=self._context)

        def twist(message: Any) -> None:
            if message.linear.x > 0:
                self.twists.put(time.perf_counter())

        def goal(_: Any) -> Any:
            self.goals.put(time.perf_counter())
            return GoalResponse.ACCEPT

        def execute(handle: Any) -> Any:
            handle.succeed()
            return Fibonacci.Result(sequence=[0, 1])

        self.node.create_subscription(Twist, "/cmd_vel", twist, 10)
        self._server = ActionServer(self.node, Fibonacci, "/fibonacci", execute_callback=execute, goal_callback=goal)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="bench-rclpy-robot", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self._context.ok():
            self._executor.spin_once(timeout_sec=0.1)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self._executor.shutdown(timeout_sec=1.0)
        self._server.destroy()
        self.node.destroy_node()
        self._context.try_shutdown()


class ZenohRobot(Arrivals, RawRosNode):
    """A raw zenoh session as an rmw_zenoh node: a cmd_vel subscriber and a Fibonacci server."""

    def __init__(self, session: zenoh.Session, types: Types, domain: int = 0, name: str = "bench_zenoh_robot") -> None:
        Arrivals.__init__(self)
        RawRosNode.__init__(self, session, types, domain, name)
        types.find_action(ACTION)
        twist_hash = types.hash(TWIST)
        self._undeclare.append(session.declare_subscriber(wire.topic_key(domain, "/cmd_vel", TWIST, twist_hash), self._on_twist))
        self._undeclare.append(session.liveliness().declare_token(
            wire.entity_token(domain, self.zid, 0, 1, "MS", "", name, "/cmd_vel", TWIST, twist_hash)))
        self.serve_action(ACTION, "/fibonacci", 2, self._send_goal, self._get_result, "bench-zenoh-robot")

    def _on_twist(self, sample: zenoh.Sample) -> None:
        if self.types.decode(TWIST, sample.payload.to_bytes()).linear.x > 0:
            self.twists.put(time.perf_counter())

    def _send_goal(self, query: zenoh.Query) -> None:
        self.goals.put(time.perf_counter())
        with query:
            self.reply(query, f"{ACTION}_SendGoal", {"accepted": True})

    def _get_result(self, query: zenoh.Query) -> None:
        with query:
            self.reply(query, f"{ACTION}_GetResult", {"status": wire.STATUS_SUCCEEDED, "result": {"sequence": [0, 1]}})


def once(client: MeshClient, embodiment_name: str, robot: Arrivals, action: str, parameters: list[str]) -> float:
    """One action: act called -> the robot's first arrival of its kind, in seconds."""
    robot.drain()
    arrivals = robot.twists if action == "Drive" else robot.goals
    t0 = time.perf_counter()
    with client.start_action(embodiment_name, action, parameters) as run:
        arrived = arrivals.get(timeout=30.0)
        report = run.wait(30.0)
    if report.status != "succeeded":
        raise MeshError(f"{action} on {embodiment_name} ended {report.status}: {report.reason}")
    return arrived - t0


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    if importlib.util.find_spec("rclpy") is None or importlib.util.find_spec("test_msgs") is None:
        log("rclpy or test_msgs is not installed (pip install -e '.[ros2-test]'): nothing measured")
        return []
    mesh = unique_mesh("bench")
    domain = random.SystemRandom().randrange(1, 102)  # a domain of this run's own; its ports stay below the ephemeral range
    ros_env = {"ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    os.environ.update(ros_env)  # this process's own rclpy node, too
    samples = max(20, options.samples // 40)  # a Drive lasts 50 ms and more: a fortieth of the round trips' samples
    warmup = max(5, options.warmup // 40)
    started = time.monotonic()
    pooled: dict[str, list[float]] = {metric: [] for metric in LABELS}
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-ros2-rclpy-")))
        nodes: dict[str, Node] = {}
        for way, transport, dom in (("rclpy", "rclpy", domain), ("zenoh", "rmw_zenoh", 0)):
            config = embodiment(tmp / way / "config", f"{way}_robot", f"transport={transport},domain={dom}")
            nodes[way] = Node(f"{way}_robot", mesh, tmp / way, architecture=str(config), extra_env=ros_env,
                              connect=tuple(n.listen for n in nodes.values()))
        for node in nodes.values():
            node.start()
        stack.callback(stop_and_report, list(nodes.values()), log)
        for node in nodes.values():
            node.wait_up(60.0)
        log(f"daemons up after {time.monotonic() - started:.2f} s (mesh {mesh}, ROS domain {domain})")
        rclpy_robot = RclpyRobot(domain)
        stack.callback(rclpy_robot.close)
        robot_session = open_session(loopback_config(connect=nodes["zenoh"].listen))
        stack.callback(robot_session.close)
        zenoh_robot = ZenohRobot(robot_session, Types())
        stack.callback(zenoh_robot.close)
        transport = stack.enter_context(ZenohTransport(loopback_config(connect=nodes["rclpy"].listen)))
        client = stack.enter_context(MeshClient(transport, mesh))
        robots: dict[str, Arrivals] = {"rclpy": rclpy_robot, "zenoh": zenoh_robot}
        for way in robots:
            client.join(f"{way}_robot", timeout=30.0)
        goal = [json.dumps({"order": 1})]
        for _ in range(warmup):
            for way, robot in robots.items():
                once(client, f"{way}_robot", robot, "Drive", ["0.1", "0", "0.05"])
                once(client, f"{way}_robot", robot, "Goal", goal)
        for _ in range(samples):
            for way, robot in robots.items():
                pooled[f"{way}_drive"].append(once(client, f"{way}_robot", robot, "Drive", ["0.1", "0", "0.05"]))
                pooled[f"{way}_goal"].append(once(client, f"{way}_robot", robot, "Goal", goal))
        log(f"measured {samples} of each in {time.monotonic() - started:.1f} s")
    rows = [Row(m, LABELS[m], summarize(pooled[m])) for m in LABELS]
    compare(rows, {"rclpy_drive": "zenoh_drive", "rclpy_goal": "zenoh_goal"}, None)
    return rows
