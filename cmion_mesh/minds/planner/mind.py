"""The reference mind: a small goal-driven planner whose whole state is plain data.

The mind keeps a *belief base* (entity -> {property: value}), fed by world-model perceptions and
by the effects of its own actions when they succeed. Its operators, goals, triggers, emotion and
limits come from a spec (``minds.planner.spec``); plans come from a bounded search (``minds.planner.search``);
its state, what migrates, is written and read by ``minds.planner.state``.

Achieved goals move to the ``achieved`` list; a *persistent* goal stays pending as a maintenance
goal and is pursued again whenever its facts stop holding. An unsolvable goal ends as a
``goal_unreachable`` episode, never a hang. The mind sends one action at a time; after each
success it checks that the rest of the plan still reaches the goal from what it now believes, and
replans if not. A failed step is banned for the goal for a few planning attempts so the next plan
tries something else; after ``max_failures`` failures the goal is abandoned.

All callbacks run on the simulation's update loop; call ``replace_beliefs`` and ``restore`` there
too once the mind is attached (``sim.call``).
"""

from __future__ import annotations

import copy
import logging
import os
import time
from collections import deque
from collections.abc import Mapping, Sequence
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.messages import ActionReport
from cmion_mesh.migration.invitation import INVITATION_ACTION
from cmion_mesh.mind import Mind, MindAction
from cmion_mesh.minds.planner.search import (
    Beliefs,
    GroundedOperator,
    PlanResult,
    bind,
    find_plan,
    holds,
    match,
    plan_works,
    same_value,
    text,
)
from cmion_mesh.minds.planner.spec import (
    EmotionConfig,
    Fact,
    Goal,
    InvitationPolicy,
    Limits,
    Operator,
    PlannerSpec,
    Trigger,
    goals_from_data,
    load_spec,
    operators_from_data,
    read_json,
    spec_from_data,
    to_plain,
)
from cmion_mesh.minds.planner.state import STATE_VERSION, dump_state, load_state
from cmion_mesh.storage import WorldModel

__all__ = ["STATE_VERSION", "PlannerMind"]

log = logging.getLogger(__name__)


def _clamp(x: float) -> float:
    return max(-1.0, min(1.0, x))


class PlannerMind(Mind):
    """A goal-driven mind: plans over its beliefs, one action in flight at a time.

    ``operators`` is a list of ``Operator`` (or operator maps), or - as the daemon passes
    constructor parameters from XML as strings - the path of a JSON spec file whose goals,
    triggers, emotion and limits are taken too (``"mind,spec.json"``; a lone ``"spec.json"`` in
    the name's place works too). ``goals`` likewise: ``Goal``s, goal maps, or a JSON file holding
    a list of goals (or a spec's ``goals``). Keyword arguments override the spec's settings.
    """

    def __init__(
        self,
        name: str = "mind",
        operators: str | os.PathLike[str] | Sequence[Operator | Mapping[str, Any]] = (),
        goals: str | os.PathLike[str] | Sequence[Goal | Mapping[str, Any]] = (),
        *,
        triggers: Sequence[Trigger | Mapping[str, Any]] = (),
        emotion: EmotionConfig | None = None,
        limits: Limits | None = None,
        invitations: InvitationPolicy | None = None,
        awake: bool = True,
        seed_beliefs: bool = True,
    ) -> None:
        if name.strip().lower().endswith(".json") and not operators:
            # ConstructorParameters="spec.json": the spec came first and the name was left out.
            operators, name = name.strip(), "mind"
        super().__init__(name, awake=awake)
        spec = PlannerSpec()
        if isinstance(operators, (str, os.PathLike)):
            if os.fspath(operators).strip():
                spec = load_spec(os.fspath(operators).strip())
            op_list = list(spec.operators)
        else:
            op_list = operators_from_data(list(operators))
        goal_list = list(spec.goals)
        if isinstance(goals, (str, os.PathLike)):
            goal_file = os.fspath(goals).strip()
            if goal_file:
                data = read_json(goal_file)
                if isinstance(data, dict):
                    goal_list += spec_from_data(data, path=goal_file).goals
                elif isinstance(data, list):
                    goal_list += goals_from_data(data, path=goal_file)
                else:
                    raise ConfigError("a goals file holds a list of goals or a spec", path=goal_file)
        else:
            goal_list += goals_from_data(list(goals))
        self.operators: tuple[Operator, ...] = tuple(op_list)
        self.triggers: tuple[Trigger, ...] = (*spec.triggers, *spec_from_data({"triggers": list(triggers)}).triggers)
        self.emotion_config: EmotionConfig = emotion or spec.emotion or EmotionConfig()
        self.limits: Limits = limits or spec.limits or Limits()
        self.invitations: InvitationPolicy = invitations or spec.invitations or InvitationPolicy()
        self.seed_beliefs = seed_beliefs

        self.beliefs: Beliefs = {}
        self.persistent: set[tuple[str, str]] = set()
        self.pending_goals: list[Goal] = []
        self.satisfied: set[str] = set()  # persistent goals whose facts hold now
        self.achieved: list[dict[str, Any]] = []
        self.abandoned: list[dict[str, Any]] = []
        self.plan: list[GroundedOperator] = []
        self.plan_goal: str | None = None
        self.in_flight: str | None = None
        self.memory: deque[dict[str, Any]] = deque(maxlen=self.limits.memory)
        self.emotion: dict[str, float] = {"valence": 0.0, "arousal": 0.0}
        self.failures: dict[str, int] = {}
        self.actions_spent: dict[str, int] = {}
        self.bans: dict[str, dict[str, int]] = {}  # goal -> step key -> planning attempts left
        # Runtime only, not in state (a restored mind simply searches again): goals whose search
        # failed -> (when, whether beliefs changed since).
        self._blocked: dict[str, tuple[float, bool]] = {}
        self._retry_armed = False
        self._unreachable: dict[str, str] = {}  # goal -> the reason last reported
        self._thinking = False
        for goal in goal_list:
            self._add_goal(goal, source="spec", quiet=True)

    # --- life cycle -----------------------------------------------------------------------------

    def on_start(self) -> None:
        if self.seed_beliefs:
            wm = self.sim.components_by_name().get(keys.WORLD_MODEL)
            if isinstance(wm, WorldModel):
                self.replace_beliefs(wm.tree())
        log.info("mind %s starts with %d operators, %d goals, %d believed entities", self.name, len(self.operators),
                 len(self.pending_goals), len(self.beliefs))
        self._think()

    def on_sleep(self) -> None:
        log.info("mind %s sleeps (action in flight: %s)", self.name, self.in_flight)

    def on_wake(self) -> None:
        log.info("mind %s wakes", self.name)
        self._feel()
        # Think in the next update, not now: migration wakes a restored mind and hands it the new
        # body's world model (``on_arrived``) in one go, and acting before that would act on
        # beliefs about the old body.
        self._think_soon()

    def on_arrived(self, world_model: dict[str, Any]) -> None:
        """Restored on a new body: its world model replaces what was believed about the old one."""
        self.replace_beliefs(world_model)

    def _think_soon(self) -> None:
        if self._sim is not None:
            self._sim.post(self._think)

    # --- perceptions ----------------------------------------------------------------------------

    def on_entity_added(self, name: str, kind: str) -> None:
        if name not in self.beliefs:
            self.beliefs[name] = {}
            self._remember("perceived", {"op": "entity_added", "entity": name, "kind": kind})
            self._beliefs_changed()

    def on_entity_removed(self, name: str, kind: str) -> None:
        removed = [e for e in self.beliefs if e == name or e.startswith(name + "/")]
        for e in removed:
            del self.beliefs[e]
        self.persistent = {k for k in self.persistent if k[0] not in removed}
        if removed:
            self._remember("perceived", {"op": "entity_removed", "entity": name, "kind": kind})
            self._beliefs_changed()

    def on_property_changed(self, entity: str, name: str, value: Any, persistent: bool) -> None:
        if not entity:
            return  # properties of the world model's root describe no entity
        props = self.beliefs.setdefault(entity, {})
        changed = name not in props or not same_value(props[name], value)
        props[name] = value
        if persistent:
            self.persistent.add((entity, name))
        else:
            self.persistent.discard((entity, name))
        if changed:
            self._remember("perceived", {"op": "property_changed", "entity": entity, "property": name, "value": value})
        # A trigger fires on every write, even an unchanged value: a repeated command is a new request.
        for trigger in self.triggers:
            self._fire(trigger, (entity, name, value))
        if changed:
            self._beliefs_changed()
        else:
            self._think()

    def on_property_removed(self, entity: str, name: str, persistent: bool) -> None:
        props = self.beliefs.get(entity)
        self.persistent.discard((entity, name))
        if props is not None and name in props:
            del props[name]
            self._remember("perceived", {"op": "property_removed", "entity": entity, "property": name})
            self._beliefs_changed()

    def on_remote_action(self, action: MindAction) -> None:
        self._remember("remote_action", {"name": action.name, "parameters": list(action.parameters), "subject": action.subject})
        if action.name == INVITATION_ACTION:
            self._consider_invitation(action.subject or (action.parameters[0] if action.parameters else ""))

    def _consider_invitation(self, inviter: str) -> None:
        """Follow a migration invitation as the spec's ``invitations`` policy says: only when idle."""
        reason = self.invitation_refusal(inviter)
        action_id = None
        if not reason:
            try:
                action_id = self.act(self.invitations.action, [inviter])
            except MeshError as exc:
                reason = str(exc)
        if action_id is None:
            self._remember("invitation_declined", {"inviter": inviter, "reason": reason})
            self._decide("invitation_declined", inviter=inviter, reason=reason)
            return
        self.in_flight = action_id
        self.plan, self.plan_goal = [], None
        self._remember("invitation_followed", {"inviter": inviter, "action_id": action_id})
        self._decide("invitation_followed", inviter=inviter, action=self.invitations.action, action_id=action_id)

    def invitation_refusal(self, inviter: str) -> str:
        """Why the policy declines an invitation from ``inviter`` now ("" if it follows it)."""
        policy = self.invitations
        if not policy.follow:
            return "the spec does not follow invitations"
        if not inviter:
            return "no inviter named"
        if policy.accept_from is not None and inviter not in policy.accept_from:
            return f"{inviter!r} is not among {list(policy.accept_from)}"
        if self.in_flight is not None:
            return f"busy: action {self.in_flight} in flight"
        unmet = [g.name for g in self.pending_goals if g.name not in self.satisfied]
        return f"busy: goal {unmet[0]!r} is not achieved" if unmet else ""

    def on_message(self, data: dict[str, Any]) -> None:
        """``{"goal": {...}}`` or ``{"goals": [...]}`` adds goals; ``{"drop_goal": name}`` drops one."""
        self._remember("message", copy.deepcopy(data))
        goals: list[Any] = []
        if isinstance(data.get("goal"), dict):
            goals.append(data["goal"])
        if isinstance(data.get("goals"), list):
            goals += data["goals"]
        for raw in goals:
            try:
                goal = goals_from_data([raw])[0]
            except ConfigError as exc:
                log.warning("mind %s ignored a goal in a message: %s", self.name, exc)
                continue
            self._add_goal(goal, source="message")
        if isinstance(data.get("drop_goal"), str):
            self.drop_goal(data["drop_goal"])
        self._think()

    def _fire(self, trigger: Trigger, fact: Fact) -> None:
        bindings = next(match([trigger.when], {fact[0]: {fact[1]: fact[2]}}, {}), None)
        if bindings is None:
            return
        try:
            goal = goals_from_data([bind(trigger.goal, bindings)])[0]
        except ConfigError as exc:
            log.warning("mind %s: trigger %r made no goal: %s", self.name, list(trigger.when), exc)
            return
        for entity, prop, value in bind([list(f) for f in trigger.believe], bindings):
            self.beliefs.setdefault(str(entity), {})[str(prop)] = value
            self.persistent.add((str(entity), str(prop)))
        self._add_goal(goal, source=f"trigger {text(list(fact))}")

    # --- goals ----------------------------------------------------------------------------------

    def add_goal(self, goal: Goal | Mapping[str, Any]) -> bool:
        """Add a goal (on the loop); False if a pending goal already has its name."""
        added = self._add_goal(goal if isinstance(goal, Goal) else goals_from_data([goal])[0], source="api")
        self._think()
        return added

    def drop_goal(self, name: str) -> bool:
        before = len(self.pending_goals)
        self.pending_goals = [g for g in self.pending_goals if g.name != name]
        if len(self.pending_goals) == before:
            return False
        self._forget_goal(name)
        self._remember("goal_dropped", {"goal": name})
        self._decide("goal_dropped", goal=name)
        return True

    def _add_goal(self, goal: Goal, *, source: str, quiet: bool = False) -> bool:
        if any(g.name == goal.name for g in self.pending_goals):
            return False
        self.pending_goals.append(goal)
        if not quiet:
            self._remember("goal_added", {"goal": goal.name, "source": source})
            self._decide("goal_added", goal=goal.name, source=source, facts=[list(f) for f in goal.facts],
                         priority=goal.priority)
        return True

    def _forget_goal(self, name: str) -> None:
        self.satisfied.discard(name)
        self.failures.pop(name, None)
        self.actions_spent.pop(name, None)
        self.bans.pop(name, None)
        self._blocked.pop(name, None)
        self._unreachable.pop(name, None)
        if self.plan_goal == name:
            # A step in flight stays so that its effects are still believed when it succeeds.
            self.plan, self.plan_goal = (self.plan[:1] if self.in_flight else []), None

    def _finish(self, goal: Goal, outcome: str, reason: str = "") -> None:
        self.pending_goals = [g for g in self.pending_goals if g.name != goal.name]
        self._forget_goal(goal.name)
        record = {**to_plain(goal), "time": time.time()}
        if reason:
            record["reason"] = reason
        target = self.achieved if outcome == "goal_achieved" else self.abandoned
        target.append(record)
        del target[:-100]  # the episodes keep the story; these lists are for quick look-up
        self._remember(outcome, {"goal": goal.name, **({"reason": reason} if reason else {})})
        self._decide(outcome, goal=goal.name, reason=reason)

    # --- beliefs --------------------------------------------------------------------------------

    def replace_beliefs(self, world_model_tree: Mapping[str, Any]) -> None:
        """Replace embodiment-specific knowledge with a world model's contents (``WorldModel.tree()``).

        Persistent beliefs (the companion's own knowledge) are kept, and win over the new world
        model's value for the same property; everything else comes from the tree.
        """
        kept = {(e, p): self.beliefs[e][p] for e, p in self.persistent if p in self.beliefs.get(e, {})}
        beliefs: Beliefs = {}
        persistent: set[tuple[str, str]] = set(kept)

        def walk(node: Mapping[str, Any], path: str) -> None:
            for child, sub in node.get("children", {}).items():
                entity = f"{path}/{child}" if path else child
                props = beliefs.setdefault(entity, {})
                for prop, entry in sub.get("properties", {}).items():
                    props[prop] = entry.get("value")
                    if entry.get("persistent"):
                        persistent.add((entity, prop))
                walk(sub, entity)

        walk(world_model_tree, "")
        for (e, p), v in kept.items():
            beliefs.setdefault(e, {})[p] = v
        self.beliefs, self.persistent = beliefs, persistent
        self._beliefs_changed()

    def _beliefs_changed(self) -> None:
        self._blocked = {g: (t, True) for g, (t, _) in self._blocked.items()}
        self._think()

    def _retry_due(self) -> None:
        self._retry_armed = False
        self._think()

    # --- deciding and acting --------------------------------------------------------------------

    def _think(self) -> None:
        if self._sim is None or not self.awake or self.in_flight is not None or self._thinking:
            return
        self._thinking = True
        try:
            self._think_once()
        finally:
            self._thinking = False

    def _think_once(self) -> None:
        self._check_goals()
        # Each pass either acts, or takes a goal out of the running: bounded by the goal count.
        for _ in range(len(self.pending_goals) + 1):
            goal = self.top_goal()
            if goal is None:
                if self.plan:
                    self.plan, self.plan_goal = [], None
                return
            if self.plan_goal == goal.name and self.plan and plan_works(self.beliefs, self.plan, goal.facts):
                if self._act(goal, self.plan[0]):
                    return
                continue
            if self.plan:
                self._decide("replan", goal=goal.name, previous_goal=self.plan_goal,
                             reason="the world changed" if self.plan_goal == goal.name else "a goal came first")
            self.plan, self.plan_goal = [], None
            result = self._plan_for(goal)
            if not result.found:
                self._blocked[goal.name] = (time.monotonic(), False)
                # Reported once per cause: perceptions replan it, and memory must not fill with repeats.
                if self._unreachable.get(goal.name) != result.reason:
                    self._unreachable[goal.name] = result.reason
                    self._remember("goal_unreachable", {"goal": goal.name, "reason": result.reason, "expanded": result.expanded})
                    self._decide("goal_unreachable", goal=goal.name, reason=result.reason, expanded=result.expanded)
                continue
            self._unreachable.pop(goal.name, None)
            self._blocked.pop(goal.name, None)
            if not result.steps:  # holds already (only if a variable binding changed under us)
                self._check_goals()
                continue
            self.plan, self.plan_goal = result.steps, goal.name
            self._decide("plan", goal=goal.name, cost=result.cost, expanded=result.expanded,
                         steps=[s.to_data() for s in result.steps])
            if self._act(goal, self.plan[0]):
                return

    def _check_goals(self) -> None:
        for goal in list(self.pending_goals):
            if holds(goal.facts, self.beliefs):
                if not goal.persistent:
                    self._finish(goal, "goal_achieved")
                elif goal.name not in self.satisfied:
                    self.satisfied.add(goal.name)
                    self.failures.pop(goal.name, None)
                    self.actions_spent.pop(goal.name, None)
                    self.bans.pop(goal.name, None)
                    self._remember("goal_achieved", {"goal": goal.name, "persistent": True})
                    self._decide("goal_achieved", goal=goal.name, persistent=True)
            else:
                self.satisfied.discard(goal.name)

    def top_goal(self) -> Goal | None:
        """The goal to pursue now: the first of the highest priority among the pending goals that
        do not hold and are not waiting to be searched again (for those, a retry is armed)."""
        now = time.monotonic()
        wait = None
        ready = []
        for g in self.pending_goals:
            if g.name in self.satisfied:
                continue
            blocked = self._blocked.get(g.name)
            if blocked is not None:
                since, changed = blocked
                left = since + self.limits.retry_delay - now
                if not changed:
                    continue
                if left > 0:
                    wait = left if wait is None else min(wait, left)
                    continue
            ready.append(g)
        if wait is not None and not self._retry_armed and self._sim is not None:
            self._retry_armed = True
            self.sim.call_later(wait, self._retry_due)
        return max(ready, key=lambda g: g.priority, default=None)  # max keeps the first of equals

    def _plan_for(self, goal: Goal) -> PlanResult:
        bans = self.bans.get(goal.name, {})
        result = find_plan(self.beliefs, goal.facts, self.operators, banned=bans,
                           max_depth=self.limits.max_depth, max_expanded=self.limits.max_expanded,
                           max_generated=self.limits.max_generated)
        if not result.found and bans:
            # Every way left has failed recently: rather than stall, try them again (the failure
            # count still grows, so the goal is abandoned if they keep failing).
            retry = find_plan(self.beliefs, goal.facts, self.operators,
                              max_depth=self.limits.max_depth, max_expanded=self.limits.max_expanded,
                              max_generated=self.limits.max_generated)
            if retry.found:
                log.info("mind %s: every untried way to %r is gone; retrying steps that failed", self.name, goal.name)
                self.bans.pop(goal.name, None)
                return retry
        if bans:
            left = {k: n - 1 for k, n in bans.items() if n > 1}
            if left:
                self.bans[goal.name] = left
            else:
                self.bans.pop(goal.name, None)
        return result

    def _act(self, goal: Goal, step: GroundedOperator) -> bool:
        """Send ``step``; False if the goal was abandoned instead and another may be pursued."""
        spent = self.actions_spent.get(goal.name, 0)
        if spent >= self.limits.max_actions:
            self._finish(goal, "goal_abandoned", f"{spent} actions did not achieve it")
            return False
        try:
            action_id = self.act(step.action, step.parameters, step.subject)
        except MeshError as exc:
            log.warning("mind %s could not send %s: %s", self.name, step.describe(), exc)
            return True
        self.in_flight = action_id
        self.actions_spent[goal.name] = spent + 1
        log.debug("mind %s acts for %r: %s (%s)", self.name, goal.name, step.describe(), action_id)  # the action's end is the body's line
        self._decide("act", goal=goal.name, action_id=action_id, step=step.to_data())
        return True

    # --- outcomes -------------------------------------------------------------------------------

    def on_action_succeeded(self, report: ActionReport) -> None:
        if report.action_id != self.in_flight:
            return
        self.in_flight = None
        step = self.plan.pop(0) if self.plan else None
        if step is not None:
            for entity, prop, value in step.effects():
                props = self.beliefs.setdefault(entity, {})
                if value is None:
                    props.pop(prop, None)
                    self.persistent.discard((entity, prop))
                else:
                    props[prop] = value
                    if step.operator.remember:
                        self.persistent.add((entity, prop))
        self._remember("action_succeeded", {"action_id": report.action_id, "action": report.name,
                                            "parameters": list(report.parameters), "goal": self.plan_goal,
                                            "operator": step.operator.name if step else None})
        self._beliefs_changed()

    def on_action_failed(self, report: ActionReport) -> None:
        self._action_ended(report, "action_failed")

    def on_action_cancelled(self, report: ActionReport) -> None:
        # Counted like a failure: a mind that ignored cancels would resend the action forever.
        self._action_ended(report, "action_cancelled")

    def _action_ended(self, report: ActionReport, kind: str) -> None:
        if report.action_id != self.in_flight:
            return
        self.in_flight = None
        step = self.plan[0] if self.plan else None
        goal_name = self.plan_goal
        self.plan, self.plan_goal = [], None
        self._remember(kind, {"action_id": report.action_id, "action": report.name, "parameters": list(report.parameters),
                              "reason": report.reason, "goal": goal_name, "operator": step.operator.name if step else None})
        goal = next((g for g in self.pending_goals if g.name == goal_name), None)
        if goal is not None:
            count = self.failures.get(goal.name, 0) + 1
            self.failures[goal.name] = count
            if step is not None:
                self.bans.setdefault(goal.name, {})[step.key] = self.limits.ban_attempts
            log.info("mind %s: %s %s (%s); failure %d of %d for %r", self.name, report.name, kind.split("_")[1],
                     report.reason, count, self.limits.max_failures, goal.name)
            if count >= self.limits.max_failures:
                self._finish(goal, "goal_abandoned", f"{count} failures, the last: {report.reason}")
            else:
                self._decide("replan", goal=goal.name, reason=f"{report.name} {kind.split('_')[1]}: {report.reason}",
                             avoiding=step.key if step else None)
        self._think()

    # --- memory, emotion, events ----------------------------------------------------------------

    def _remember(self, kind: str, details: dict[str, Any]) -> None:
        self.memory.append({"time": time.time(), "kind": kind, "details": details})
        nudge = self.emotion_config.appraisals.get(kind)
        if nudge is not None:
            decay = self.emotion_config.decay
            before = self.emotion
            self.emotion = {"valence": round(_clamp(self.emotion["valence"] * decay + nudge.valence), 6),
                            "arousal": round(_clamp(self.emotion["arousal"] * decay + nudge.arousal), 6)}
            if self.emotion != before:
                self._feel()

    def _feel(self) -> None:
        """Say how the mind feels (an ``Emotion`` event): a body shows it, a face among others."""
        if self._sim is not None and not self._sim.closed and self.awake:
            try:
                self.raise_event("Emotion", {"mind": self.name, **self.emotion})
            except (MeshError, ValueError) as exc:
                log.warning("mind %s could not raise Emotion: %s", self.name, exc)

    def _decide(self, decision: str, **data: Any) -> None:
        log.info("mind %s: %s %s", self.name, decision, data)
        if self._sim is not None and not self._sim.closed:
            try:
                self.raise_event("MindDecision", {"mind": self.name, "decision": decision, **data})
            except (MeshError, ValueError) as exc:
                log.warning("mind %s could not raise MindDecision: %s", self.name, exc)

    # --- migration --------------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """Everything the mind is, as one JSON-serialisable dict (``restore`` takes it back; the keys
        are ``state.dump_state``'s)."""
        return dump_state(self)

    def restore(self, state: dict[str, Any]) -> None:
        """Become the mind ``state`` describes. An action that was in flight is dropped with the plan
        it belonged to (it ran on another body); planning resumes on the loop when awake.
        Otherwise ``state()`` afterwards equals ``state``."""
        try:
            load_state(self, state)
        except (KeyError, TypeError, ValueError, msgspec.ValidationError) as exc:
            raise ConfigError(f"mind {self.name!r}: unusable state: {exc!r}") from None
        self._blocked, self._unreachable = {}, {}
        self._think_soon()
