"""The planner mind's state as plain data: what migrates with the companion, and how it is read back.

``dump_state`` writes everything a planner mind is as one JSON-serialisable dict; ``load_state``
makes a mind what such a dict describes (``PlannerMind.state`` and ``restore`` are these two). The
fields they read and write are ``PlannerFields``; what the mind keeps only while it runs (goals
waiting to be searched again, what was last reported) is not part of the state.
"""

from __future__ import annotations

import copy
from collections import deque
from typing import Any, Protocol

import msgspec

from cmion_mesh.messages import Act
from cmion_mesh.minds.planner.search import Beliefs, GroundedOperator
from cmion_mesh.minds.planner.spec import (
    EmotionConfig,
    Goal,
    InvitationPolicy,
    Limits,
    Operator,
    Trigger,
    goals_from_data,
    operators_from_data,
    spec_from_data,
    to_plain,
)

STATE_VERSION = 1


class PlannerFields(Protocol):
    """The fields of a planner mind that its state is made of (and ``Mind.pending``, whose entry for
    an action in flight a restore drops)."""

    operators: tuple[Operator, ...]
    triggers: tuple[Trigger, ...]
    emotion_config: EmotionConfig
    limits: Limits
    invitations: InvitationPolicy
    pending_goals: list[Goal]
    satisfied: set[str]
    achieved: list[dict[str, Any]]
    abandoned: list[dict[str, Any]]
    plan: list[GroundedOperator]
    plan_goal: str | None
    in_flight: str | None
    beliefs: Beliefs
    persistent: set[tuple[str, str]]
    memory: deque[dict[str, Any]]
    emotion: dict[str, float]
    failures: dict[str, int]
    actions_spent: dict[str, int]
    bans: dict[str, dict[str, int]]
    pending: dict[str, Act]


def dump_state(mind: PlannerFields) -> dict[str, Any]:
    """Everything the mind is, as one JSON-serialisable dict (``load_state`` takes it back).

    Keys: ``version``; ``spec`` (operators, triggers, emotion, limits and invitations settings); ``goals``
    (``pending`` - goal maps plus ``satisfied`` for persistent goals - ``achieved`` and
    ``abandoned``, each with ``time`` and maybe ``reason``); ``plan`` (``goal`` and ``steps``:
    operator, bindings, action, parameters, subject - the first is the one in flight);
    ``in_flight`` (action id or None); ``beliefs`` (entity -> property -> value);
    ``persistent`` ([entity, property] pairs); ``memory`` (episodes: time, kind, details);
    ``emotion`` (valence, arousal); ``failures`` and ``actions_spent`` per pending goal;
    ``bans`` (goal -> failed step key -> planning attempts it is still avoided for).
    """
    return {
        "version": STATE_VERSION,
        "spec": {
            "operators": [to_plain(op) for op in mind.operators],
            "triggers": [to_plain(t) for t in mind.triggers],
            "emotion": to_plain(mind.emotion_config),
            "limits": to_plain(mind.limits),
            "invitations": to_plain(mind.invitations),
        },
        "goals": {
            "pending": [{**to_plain(g), "satisfied": g.name in mind.satisfied} for g in mind.pending_goals],
            "achieved": copy.deepcopy(mind.achieved),
            "abandoned": copy.deepcopy(mind.abandoned),
        },
        "plan": {"goal": mind.plan_goal, "steps": [s.to_data() for s in mind.plan]},
        "in_flight": mind.in_flight,
        "beliefs": copy.deepcopy(mind.beliefs),
        "persistent": [list(k) for k in sorted(mind.persistent)],
        "memory": copy.deepcopy(list(mind.memory)),
        "emotion": dict(mind.emotion),
        "failures": dict(mind.failures),
        "actions_spent": dict(mind.actions_spent),
        "bans": {g: dict(b) for g, b in mind.bans.items()},
    }


def load_state(mind: PlannerFields, state: dict[str, Any]) -> None:
    """Make ``mind`` what ``state`` describes. An action that was in flight is dropped with the plan
    it belonged to (it ran on another body). ``KeyError``, ``TypeError``, ``ValueError`` or
    ``msgspec.ValidationError`` on a state that is not one of this version (its spec, goals and
    plan are read before anything is set)."""
    if state.get("version") != STATE_VERSION:
        raise ValueError(f"state version {state.get('version')!r}, expected {STATE_VERSION}")
    spec = state["spec"]
    operators = operators_from_data(spec["operators"])
    triggers = spec_from_data({"triggers": spec["triggers"]}).triggers
    emotion = msgspec.convert(spec["emotion"], EmotionConfig)
    limits = msgspec.convert(spec["limits"], Limits)
    invitations = msgspec.convert(spec["invitations"], InvitationPolicy) if "invitations" in spec else mind.invitations
    pending = [dict(g) for g in state["goals"]["pending"]]
    satisfied = {str(g["name"]) for g in pending if g.pop("satisfied", False)}
    goals = goals_from_data(pending)
    by_name = {op.name: op for op in operators}
    plan = [GroundedOperator(by_name[s["operator"]], dict(s["bindings"])) for s in state["plan"]["steps"]]

    if mind.in_flight is not None:
        mind.pending.pop(mind.in_flight, None)
    mind.operators, mind.triggers, mind.emotion_config, mind.limits = tuple(operators), triggers, emotion, limits
    mind.invitations = invitations
    mind.pending_goals, mind.satisfied = goals, satisfied
    mind.achieved = copy.deepcopy(list(state["goals"]["achieved"]))
    mind.abandoned = copy.deepcopy(list(state["goals"]["abandoned"]))
    mind.plan, mind.plan_goal = plan, state["plan"]["goal"]
    mind.in_flight = None
    if state["in_flight"] is not None:
        mind.plan, mind.plan_goal = [], None
    mind.beliefs = {str(e): dict(p) for e, p in copy.deepcopy(state["beliefs"]).items()}
    mind.persistent = {(str(e), str(p)) for e, p in state["persistent"]}
    mind.memory = deque(copy.deepcopy(list(state["memory"])), maxlen=limits.memory)
    mind.emotion = {"valence": float(state["emotion"]["valence"]), "arousal": float(state["emotion"]["arousal"])}
    mind.failures = {str(k): int(v) for k, v in state["failures"].items()}
    mind.actions_spent = {str(k): int(v) for k, v in state["actions_spent"].items()}
    mind.bans = {str(g): {str(k): int(n) for k, n in b.items()} for g, b in state["bans"].items()}
