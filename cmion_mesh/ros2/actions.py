"""ROS 2 action competencies: Nav2's ``NavigateToPose`` (``Ros2Navigation``) and any action by name
(``Ros2Action``), over either ROS link (``ros2/link.py``), with one goal-following loop.

* ``Ros2Navigation`` (type ``Navigation``): run parameter ``Location``; a
  ``nav2_msgs/action/NavigateToPose`` goal (``action=navigate_to_pose``, ``frame=map``,
  ``behavior_tree=``) to the pose of the location: ``place.<Name>=x y yaw`` (metres, radians),
  else the world model's ``<Name>.x``, ``.y`` and ``.yaw``. BB ``navigation/target``,
  ``navigation/state`` (moving, arrived, stopped, failed) and ``navigation/feedback`` (at most
  every ``feedback_interval`` s), WM ``<agent>.location`` on success.
* ``Ros2Action`` (type ``competency_type``, default ``RosAction``): ``action=<name>``,
  ``action_type=<pkg/action/Name>``; the goal's fields come from ``goal.<field>=value`` in the
  library, then from the step's parameters: ``goal=<JSON object of fields>``, ``<field>=value``
  (a dotted path for a nested field, values as JSON when they parse so: ``5``, ``0.5``, ``true``,
  ``[1, 2]``) and ``<field>InName=<BB name>`` (the blackboard's value). BB ``<bb>/state`` (active, succeeded,
  canceled, aborted, failed, stopped), ``<bb>/feedback`` (the latest feedback, at most every
  ``feedback_interval`` s) and ``<bb>/result`` (the result, whatever the status), ``bb``
  defaulting to the action's last name.

Both: a cancel sends ``cancel_goal`` and waits (``cancel_timeout``) for the goal to end; the
action's status decides success; a server that leaves fails the run naming its node;
``server_timeout`` bounds the wait for a server, ``goal_timeout`` the goal's acceptance,
``timeout`` the whole goal.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from typing import Any, ClassVar

from cmion_mesh import keys
from cmion_mesh.competencies.common import SELF, bb_set, quietly, text_parameter, wm_set
from cmion_mesh.competency import RunContext
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.ros2 import wire
from cmion_mesh.ros2.base import Ros2Competency, number
from cmion_mesh.ros2.interfaces import plain
from cmion_mesh.ros2.link import LinkActionClient, RosLink
from cmion_mesh.transport.base import QueryCancel

__all__ = ["Ros2Action", "Ros2GoalCompetency", "Ros2Navigation"]

log = logging.getLogger(__name__)

Events = queue.SimpleQueue[tuple[str, Any]]

TIMEOUTS = {"server_timeout": "5", "goal_timeout": "5", "timeout": "600", "cancel_timeout": "5", "feedback_interval": "0.2"}


class Ros2GoalCompetency(Ros2Competency):
    """One goal per run: wait for a server, send, follow (feedback, cancel, the server leaving),
    and end on the result. Subclasses say what the goal is and what the blackboard shows."""

    def __init__(self, *parameters: str, name: str | None = None) -> None:
        super().__init__(*parameters, name=name)
        for key in TIMEOUTS:
            self.seconds(key)
        wire.qualify(self.options["action"], self.namespace)
        self.check_action(self.options["action_type"], "action_type")
        self.client: LinkActionClient | None = None
        self._events: Events | None = None

    def declare(self, link: RosLink) -> None:
        self.client = link.action_client(self.options["action"], self.options["action_type"])

    def _interrupt(self) -> None:
        events = self._events
        if events is not None:
            events.put(("cancel", None))

    # --- what a subclass says --------------------------------------------------------------------

    def goal(self, parameters: dict[str, Any], ctx: RunContext) -> tuple[str, dict[str, Any]] | str:
        """(what the goal is for messages, e.g. ``to Kitchen``; its fields), or why there is none."""
        raise NotImplementedError

    def state(self, ctx: RunContext, state: str) -> None:
        """Show the goal's state (moving, arrived, stopped, failed...) on the blackboard."""

    def started(self, ctx: RunContext, subject: str) -> None:
        """The goal is about to be sent."""

    def feedback(self, ctx: RunContext, feedback: Any) -> None:
        quietly("progress", ctx.progress, plain(feedback))

    def ended(self, ctx: RunContext, status: int, result: Any, *, cancelled: bool) -> None:
        """The goal ended with ``status`` (before success or failure is decided)."""

    def failure_detail(self, result: Any) -> str:
        return ""

    # --- the loop ------------------------------------------------------------------------------------

    def _failed(self, ctx: RunContext, reason: str, state: str = "failed") -> bool:
        quietly("goal state", self.state, ctx, state)
        return ctx.fail(reason)

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        planned = self.goal(parameters, ctx)
        if isinstance(planned, str):
            return ctx.fail(planned)
        subject, goal = planned
        client, link = self.client, self.link
        assert client is not None and link is not None
        server_timeout = self.seconds("server_timeout")
        if not client.wait_server(server_timeout, ctx.cancelled):
            if ctx.cancelled.is_set():
                return False
            others = client.mismatches()
            return ctx.fail(f"no ROS 2 node serves the action {client.name} ({client.type_name}) on domain "
                            f"{link.domain} within {server_timeout:g} s" + (f": {others}" if others else ""))
        who = client.who()
        events: Events = queue.SimpleQueue()
        self._events = events
        if ctx.cancelled.is_set():
            return False
        goal_id = client.new_goal_id()
        unwatch = client.watch_servers(lambda: events.put(("vanished", None)))
        unfollow = client.follow(goal_id, lambda feedback: events.put(("feedback", feedback)),
                                 lambda reason: events.put(("malformed", reason)))
        try:
            self.started(ctx, subject)
            try:
                accepted = client.send(goal_id, goal, timeout=self.seconds("goal_timeout"))
            except MeshError as exc:
                return self._failed(ctx, f"the goal {subject} was not sent: {exc}")
            if not accepted:
                return self._failed(ctx, f"{who} rejected the goal {subject}")
            return self._follow(ctx, client, goal_id, subject, who, events)
        finally:
            unwatch()
            unfollow()
            self._events = None

    def _follow(self, ctx: RunContext, client: LinkActionClient, goal_id: bytes, subject: str, who: str, events: Events) -> bool:
        timeout = self.seconds("timeout")
        stop_waiting = QueryCancel()

        def wait_result() -> None:
            try:
                events.put(("result", client.result(goal_id, timeout=timeout, cancel=stop_waiting)))
            except MeshError as exc:
                events.put(("error", exc))

        # The result is answered when the goal ends: a call of its own, so that feedback, a cancel
        # and the server's departure are seen meanwhile; whatever ends the run ends it.
        waiter = threading.Thread(target=wait_result, name=f"{self.name}-result", daemon=True)
        waiter.start()
        try:
            return self._wait(ctx, client, goal_id, subject, who, events, timeout)
        finally:
            stop_waiting.cancel()
            waiter.join(5.0)

    def _wait(self, ctx: RunContext, client: LinkActionClient, goal_id: bytes, subject: str, who: str,
              events: Events, timeout: float) -> bool:
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
                    self.feedback(ctx, pending)
                    last_feedback, pending = time.monotonic(), None
                    continue
                if cancel_deadline is not None:
                    return self._failed(ctx, f"{who} did not end the goal {subject} within "
                                             f"{self.seconds('cancel_timeout'):g} s of its cancel", "stopped")
                quietly("cancel on timeout", client.cancel, goal_id, self.seconds("cancel_timeout"))
                return self._failed(ctx, f"the goal {subject} did not end within {timeout:g} s (cancelled)")
            if kind != "feedback" and pending is not None:
                self.feedback(ctx, pending)
                pending = None
            if kind == "feedback":
                now = time.monotonic()
                if now - last_feedback >= interval:
                    self.feedback(ctx, value)
                    last_feedback, pending = now, None
                else:
                    pending = value
            elif kind == "malformed":
                log.debug("%s: %s", self.name, value)  # the link has logged it
            elif kind == "cancel":
                if cancel_deadline is None:
                    cancel_deadline = time.monotonic() + self.seconds("cancel_timeout")
                    try:
                        code = client.cancel(goal_id, self.seconds("cancel_timeout"))
                        if code != 0:
                            log.info("%s: cancel_goal answered %d", self.name, code)
                    except MeshError as exc:
                        return self._failed(ctx, f"cancelling the goal {subject}: {exc}", "stopped")
            elif kind == "vanished":
                return self._failed(ctx, f"the ROS 2 {who} serving {client.name} left (it is gone from the ROS graph) "
                                         f"during the goal {subject}")
            elif kind == "error":
                # A server that leaves may end the pending result call before its departure is
                # seen in the graph: say which it was.
                if self._gone(client, ctx):
                    events.put(("vanished", None))
                    continue
                return self._failed(ctx, f"the result of the goal {subject}: {value}")
            elif kind == "result":
                status, result = value
                cancelled = cancel_deadline is not None
                self.ended(ctx, status, result, cancelled=cancelled)
                if status == wire.STATUS_SUCCEEDED and not cancelled:
                    return True
                name = wire.STATUS_NAMES.get(status, str(status))
                return self._failed(ctx, f"{who} ended the goal {subject}: {name}{self.failure_detail(result)}",
                                    "stopped" if cancelled else "failed")

    @staticmethod
    def _gone(client: LinkActionClient, ctx: RunContext) -> bool:
        gone = threading.Event()
        for _ in range(50):  # bounded: a second
            if not client.has_servers():
                return True
            if ctx.cancelled.is_set() or gone.wait(0.02):
                return False
        return False


class Ros2Navigation(Ros2GoalCompetency):
    type = "Navigation"
    defaults: ClassVar[dict[str, str]] = {
        "action": "navigate_to_pose", "action_type": "nav2_msgs/action/NavigateToPose", "frame": "map",
        "behavior_tree": "", "agent": SELF, **TIMEOUTS,
    }
    prefixes = ("place.",)

    def __init__(self, *parameters: str, name: str | None = None) -> None:
        super().__init__(*parameters, name=name)
        self.agent = keys.check_name(self.options["agent"], "Ros2Navigation: agent")
        self.places: dict[str, tuple[float, float, float]] = {}
        for key, value in self.options.items():
            if key.startswith("place."):
                place = key[len("place."):]
                numbers = value.split()
                if len(numbers) not in (2, 3):
                    raise ConfigError(f"Ros2Navigation: {key}={value!r}: give x y [yaw] (metres, radians)")
                x, y, *rest = (number(n, f"Ros2Navigation: {key}") for n in numbers)
                self.places[place] = (x, y, rest[0] if rest else 0.0)
        self._target = ""

    def _pose(self, ctx: RunContext, target: str) -> tuple[float, float, float] | None:
        if target in self.places:
            return self.places[target]
        if not keys.is_name(target):
            return None
        x, y = ctx.wm_get(target, "x"), ctx.wm_get(target, "y")
        if x is None or y is None:
            return None
        try:
            return (number(x, f"{target}.x"), number(y, f"{target}.y"), number(ctx.wm_get(target, "yaw", 0.0), f"{target}.yaw"))
        except ConfigError:
            return None

    def goal(self, parameters: dict[str, Any], ctx: RunContext) -> tuple[str, dict[str, Any]] | str:
        target = text_parameter(parameters, "Location")
        if not target:
            return "Ros2Navigation needs a Location parameter"
        pose = self._pose(ctx, target)
        if pose is None:
            known = sorted(self.places)
            return (f"no pose for {target!r}: give place.{target}=x y yaw in the competency library or "
                    f"{target}.x and {target}.y in the world model" + (f" (places: {', '.join(known)})" if known else ""))
        self._target = target
        x, y, yaw = pose
        return f"to {target}", {"pose": {"header": {"frame_id": self.options["frame"]},
                                         "pose": {"position": {"x": x, "y": y}, "orientation": wire.yaw_quaternion(yaw)}},
                                "behavior_tree": self.options["behavior_tree"]}

    def state(self, ctx: RunContext, state: str) -> None:
        bb_set(ctx, "navigation/state", state)

    def started(self, ctx: RunContext, subject: str) -> None:
        bb_set(ctx, "navigation/target", self._target)
        bb_set(ctx, "navigation/state", "moving")

    def feedback(self, ctx: RunContext, feedback: Any) -> None:
        position = feedback.current_pose.pose.position
        summary = {"distance_remaining": plain(float(feedback.distance_remaining)),
                   "x": plain(float(position.x)), "y": plain(float(position.y)),
                   "number_of_recoveries": int(feedback.number_of_recoveries),
                   "estimated_time_remaining": feedback.estimated_time_remaining.sec
                   + feedback.estimated_time_remaining.nanosec / 1e9}
        quietly("navigation feedback", bb_set, ctx, "navigation/feedback", summary)
        quietly("progress", ctx.progress, summary)

    def ended(self, ctx: RunContext, status: int, result: Any, *, cancelled: bool) -> None:
        if status == wire.STATUS_SUCCEEDED and not cancelled:
            bb_set(ctx, "navigation/state", "arrived")
            wm_set(ctx, self.agent, "location", self._target)

    def failure_detail(self, result: Any) -> str:
        code, message = getattr(result, "error_code", 0), getattr(result, "error_msg", "")
        return f" (error {code}{': ' + message if message else ''})" if code or message else ""


class Ros2Action(Ros2GoalCompetency):
    type = "RosAction"
    defaults: ClassVar[dict[str, str]] = {"action": "", "action_type": "", "bb": "", "competency_type": "", **TIMEOUTS}
    prefixes = ("goal.",)

    def __init__(self, *parameters: str, name: str | None = None) -> None:
        given = {key.strip(): value for key, _, value in (p.partition("=") for p in parameters)}
        kind = given.get("competency_type", "").strip()
        for required in ("action", "action_type"):
            if not given.get(required, "").strip():
                raise ConfigError(f"Ros2Action: give {required}= (e.g. action=fibonacci, action_type=test_msgs/action/Fibonacci)")
        super().__init__(*parameters, name=name or (keys.check_name(kind, "Ros2Action: competency_type") if kind else None))
        if kind:
            self.type = kind
        action = wire.qualify(self.options["action"], self.namespace)
        self.bb = keys.check_name(self.options["bb"] or action.rsplit("/", 1)[1], "Ros2Action: bb")
        self._ended = False
        self.fixed: dict[str, Any] = {}
        for key, value in self.options.items():
            if key.startswith("goal."):
                _put(self.fixed, key[len("goal."):], _value(value))

    def goal(self, parameters: dict[str, Any], ctx: RunContext) -> tuple[str, dict[str, Any]] | str:
        fields = json.loads(json.dumps(self.fixed))  # a copy of the library's goal fields
        for key, value in parameters.items():
            if key == "goal":
                found = _value(value) if isinstance(value, str) else value
                if not isinstance(found, dict):
                    return f"the goal parameter {value!r} is not a JSON object of goal fields"
                _merge(fields, found)
            elif key.endswith("InName"):
                source = str(value).strip()
                found = ctx.bb_get(source)
                if found is None:
                    return f"no value on the blackboard under {source!r} for the goal field {key[:-len('InName')]}"
                _put(fields, key[: -len("InName")], found)
            else:
                _put(fields, key, _value(value) if isinstance(value, str) else value)
        client = self.client
        return f"on {client.name if client is not None else self.options['action']}", fields

    def state(self, ctx: RunContext, state: str) -> None:
        if not self._ended:  # the goal's own status, once it has one, stays on the blackboard
            bb_set(ctx, f"{self.bb}/state", state)

    def started(self, ctx: RunContext, subject: str) -> None:
        self._ended = False
        bb_set(ctx, f"{self.bb}/state", "active")

    def feedback(self, ctx: RunContext, feedback: Any) -> None:
        summary = plain(feedback)
        quietly("action feedback", bb_set, ctx, f"{self.bb}/feedback", summary)
        quietly("progress", ctx.progress, summary)

    def ended(self, ctx: RunContext, status: int, result: Any, *, cancelled: bool) -> None:
        quietly("action result", bb_set, ctx, f"{self.bb}/result", plain(result))
        quietly("action state", bb_set, ctx, f"{self.bb}/state", wire.STATUS_NAMES.get(status, str(status)))
        self._ended = True


def _value(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        return text


def _merge(fields: dict[str, Any], found: dict[str, Any]) -> None:
    for key, value in found.items():
        if isinstance(value, dict) and isinstance(fields.get(key), dict):
            _merge(fields[key], value)
        else:
            fields[key] = value


def _put(fields: dict[str, Any], path: str, value: Any) -> None:
    *outer, last = path.split(".")
    for part in outer:
        inner = fields.setdefault(part, {})
        if not isinstance(inner, dict):
            raise ConfigError(f"goal field {path}: {part} is not a message")
        fields = inner
    fields[last] = value
