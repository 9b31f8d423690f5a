"""A ROS 2 robot made of real rclpy nodes (the ``ros2`` extra's wheels), for the tests and the bench.

Not a stand-in: rclpy on the RMW the environment selects (Fast DDS from the wheels), in a process
of its own, on the domain of ``ROS_DOMAIN_ID`` (loopback only with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``). One node, ``/rclpy_robot``:

* subscribes to ``/cmd_vel`` (geometry_msgs/Twist) and ``/speech`` (std_msgs/String), printing
  each message received as a JSON line (``{"event": "cmd_vel", ...}``, ``{"event": "speech", ...}``);
* publishes ``/battery`` (sensor_msgs/BatteryState) at ``--battery-hz``, its ``percentage`` the
  message's number (0, 1, 2...), so that a reader can tell which messages it got;
* serves ``/fibonacci`` (test_msgs/action/Fibonacci): one feedback per number every
  ``--feedback-interval`` s, then the sequence; ``--hang`` never ends a goal (until cancelled).
  Prints ``goal`` (order, goal id), ``cancel`` and ``result`` lines.

Prints ``{"event": "ready"}`` once its entities exist; ``exit`` on standard input stops it.
``python -m tests.helpers.rclpy_robot --battery-hz 20``.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from typing import Any

import rclpy
from geometry_msgs.msg import Twist
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import BatteryState
from std_msgs.msg import String
from test_msgs.action import Fibonacci

_print_lock = threading.Lock()


def emit(event: str, **fields: Any) -> None:
    with _print_lock:
        print(json.dumps({"event": event, **fields}), flush=True)


class Robot:
    def __init__(self, node: Node, args: argparse.Namespace) -> None:
        self.node, self.args = node, args
        self.stopping = threading.Event()
        group = ReentrantCallbackGroup()
        node.create_subscription(Twist, "/cmd_vel", self.on_twist, 10)
        node.create_subscription(String, "/speech", lambda m: emit("speech", data=m.data), 10)
        self.battery = node.create_publisher(BatteryState, "/battery", 10)
        self.count = 0
        if args.battery_hz > 0:
            node.create_timer(1.0 / args.battery_hz, self.publish_battery)
        ActionServer(node, Fibonacci, "/fibonacci", execute_callback=self.execute, goal_callback=self.on_goal,
                     cancel_callback=self.on_cancel, callback_group=group)

    def on_twist(self, message: Twist) -> None:
        emit("cmd_vel", linear=[message.linear.x, message.linear.y, message.linear.z],
             angular=[message.angular.x, message.angular.y, message.angular.z])

    def publish_battery(self) -> None:
        self.battery.publish(BatteryState(percentage=float(self.count), voltage=12.0))
        self.count += 1

    def on_goal(self, request: Any) -> GoalResponse:
        emit("goal", order=int(request.order), received=time.perf_counter())
        return GoalResponse.ACCEPT

    def on_cancel(self, handle: Any) -> CancelResponse:
        emit("cancel", goal_id=bytes(handle.goal_id.uuid).hex())
        return CancelResponse.ACCEPT

    def execute(self, handle: Any) -> Any:
        sequence = [0, 1]
        steps = 100_000 if self.args.hang else max(0, int(handle.request.order) - 1)
        for i in range(steps):  # bounded: the order, or (hanging) until cancelled or stopped
            if handle.is_cancel_requested:
                handle.canceled()
                emit("result", status="canceled")
                return Fibonacci.Result(sequence=sequence)
            if self.stopping.wait(self.args.feedback_interval):
                break
            if not self.args.hang:
                sequence.append(sequence[i] + sequence[i + 1])
            handle.publish_feedback(Fibonacci.Feedback(sequence=sequence))
        handle.succeed()
        emit("result", status="succeeded", sequence=sequence)
        return Fibonacci.Result(sequence=sequence)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--battery-hz", type=float, default=0.0)
    parser.add_argument("--feedback-interval", type=float, default=0.05)
    parser.add_argument("--hang", action="store_true", help="goals never end unless cancelled")
    args = parser.parse_args(argv)
    context = Context()
    rclpy.init(context=context)
    node = Node("rclpy_robot", context=context)
    robot = Robot(node, args)
    executor = MultiThreadedExecutor(num_threads=4, context=context)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    emit("ready")
    for line in sys.stdin:  # bounded by the parent: it closes the pipe or says exit
        if line.strip() == "exit":
            break
    robot.stopping.set()
    executor.shutdown(timeout_sec=2.0)
    node.destroy_node()
    context.try_shutdown()
    spinner.join(5.0)
    emit("stopped", battery_sent=robot.count)
    return 0


if __name__ == "__main__":
    sys.exit(main())
