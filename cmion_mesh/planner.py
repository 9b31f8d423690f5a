"""The reference mind: a small goal-driven planner whose whole state is plain data.

**Facts** are world-model facts, ``(entity, property, value)`` triples such as
``("Guest", "greeted", True)``. The mind keeps a *belief base* (entity -> {property: value}), fed
by world-model perceptions and by the effects of its own actions when they succeed.

**Operators** say what an action does: the mind action to send (name, parameters, subject),
preconditions and effects, and a cost. Any string may hold variables, ``?name``:

* in preconditions a variable binds to whatever the beliefs hold (an entity, a property name or
  a value); a precondition whose value is ``None`` holds when the property is absent (or None);
* a variable the preconditions leave unbound (e.g. ``?place`` in ``GoTo ?place``) ranges over
  the entities of the belief base and the strings named in the goal;
* an effect whose value is ``None`` deletes the property.

A variable standing alone keeps its bound value's type (``"?v"`` -> ``True``); inside longer text
it is replaced by the value's text (``"greet ?who"`` -> ``"greet Guest"``).

**Goals** are facts to achieve with a priority (higher first). Achieved goals move to the
``achieved`` list; a *persistent* goal stays pending as a maintenance goal and is pursued again
whenever its facts stop holding.

**Planning** is uniform-cost search over belief states, bounded by depth and by expanded states:
an unsolvable goal ends as a ``goal_unreachable`` episode, never a hang. The mind sends one
action at a time; after each success it checks that the rest of the plan still reaches the goal
from what it now believes, and replans if not. A failed step is banned for the goal for a few
planning attempts so the next plan tries something else; after ``max_failures`` failures the goal
is abandoned.

The spec (JSON, or the same structure as Python data)::

    {
      "operators": [
        {"name": "walk", "action": "GoTo", "parameters": ["?place"],
         "preconditions": [["Robot", "at", "?from"], ["?place", "room", true]],
         "effects": [["Robot", "at", "?place"]], "cost": 1},
        {"name": "greet", "action": "Greet", "parameters": ["?who"],
         "preconditions": [["Robot", "at", "?p"], ["?who", "at", "?p"]],
         "effects": [["?who", "greeted", true]]}
      ],
      "goals": [{"name": "greet guest", "facts": [["Guest", "greeted", true]], "priority": 5}],
      "triggers": [{"when": ["Command", "greet", "?who"],
                    "goal": {"name": "greet ?who", "facts": [["?who", "greeted", true]], "priority": 5}}],
      "emotion": {"decay": 0.9, "appraisals": {"action_failed": {"valence": -0.2, "arousal": 0.2}}},
      "limits": {"max_depth": 8, "max_expanded": 5000, "max_generated": 200000, "max_failures": 3,
                 "ban_attempts": 3, "max_actions": 50, "memory": 500, "retry_delay": 1.0}
    }

All callbacks run on the simulation's update loop; call ``replace_beliefs`` and ``restore`` there
too once the mind is attached (``sim.call``).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import heapq
import itertools
import logging
import os
import re
import time
from collections import deque
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.messages import ActionReport, check_value
from cmion_mesh.mind import Mind
from cmion_mesh.rules import MindAction

__all__ = [
    "DEFAULT_APPRAISALS",
    "EmotionConfig",
    "Fact",
    "Goal",
    "Limits",
    "Operator",
    "PlanResult",
    "PlannerMind",
    "PlannerSpec",
    "Step",
    "Trigger",
    "find_plan",
    "goals_from_data",
    "holds",
    "is_var",
    "load_operators",
    "load_spec",
    "match",
    "operators_from_data",
    "spec_from_data",
    "substitute",
]

log = logging.getLogger(__name__)

Fact = tuple[str, str, Any]
Beliefs = dict[str, dict[str, Any]]

_VAR = re.compile(r"\?[A-Za-z_][A-Za-z0-9_]*")
STATE_VERSION = 1


# --- variables and values ------------------------------------------------------------------------


def is_var(term: Any) -> bool:
    return isinstance(term, str) and "?" in term and _is_var_text(term)


@functools.lru_cache(maxsize=4096)  # the search asks about the same few terms again and again
def _is_var_text(term: str) -> bool:
    return _VAR.fullmatch(term) is not None


def _text(value: Any) -> str:
    if isinstance(value, str):
        return value
    if value is None:
        return ""
    if isinstance(value, (bool, int, float)):
        return str(value)
    return msgspec.json.encode(value).decode()


def substitute(term: Any, bindings: Mapping[str, Any]) -> Any:
    """``term`` with its bound variables replaced; unbound ones are left as they are."""
    if isinstance(term, str):
        if "?" not in term:
            return term
        if term in bindings and _is_var_text(term):
            return bindings[term]
        return _VAR.sub(lambda m: _text(bindings[m.group()]) if m.group() in bindings else m.group(), term)
    if isinstance(term, list):
        return [substitute(t, bindings) for t in term]
    if isinstance(term, tuple):
        return tuple(substitute(t, bindings) for t in term)
    if isinstance(term, dict):
        return {k: substitute(v, bindings) for k, v in term.items()}
    return term


def _same(a: Any, b: Any) -> bool:
    # True == 1 in Python, but a world model that says True does not say 1.
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    return bool(a == b)


def _value_key(value: Any) -> Any:
    """A hashable stand-in for a value, equal exactly when ``_same`` says the values are."""
    if value is None:
        return ("none",)
    if isinstance(value, bool):
        return ("bool", value)
    if isinstance(value, (int, float)):
        return ("num", value)
    if isinstance(value, str):
        return ("str", value)
    return ("json", msgspec.json.encode(value, order="sorted"))


def _bindings_text(bindings: Mapping[str, Any]) -> str:
    return msgspec.json.encode(dict(bindings), order="sorted").decode()


# --- operators, goals, triggers --------------------------------------------------------------------


@dataclass(frozen=True)
class Operator:
    """What one mind action does to the world, in the planner's terms."""

    name: str
    action: str
    parameters: tuple[str, ...] = ()
    preconditions: tuple[Fact, ...] = ()
    effects: tuple[Fact, ...] = ()
    cost: float = 1.0
    subject: str = ""
    #: Its effects become persistent beliefs: the companion's own memory, kept across migration
    #: (e.g. "Guest greeted"), where plain effects are body knowledge the next world model replaces.
    remember: bool = False

    @functools.cached_property
    def variables(self) -> tuple[str, ...]:
        """Every variable it mentions, in order of first mention (searched for on every expansion)."""
        found: dict[str, None] = {}
        for term in _flatten((self.action, self.parameters, self.subject, self.preconditions, self.effects)):
            if isinstance(term, str):
                for m in _VAR.finditer(term):
                    found.setdefault(m.group(), None)
        return tuple(found)

    def to_data(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "action": self.action,
            "parameters": list(self.parameters),
            "subject": self.subject,
            "preconditions": [list(f) for f in self.preconditions],
            "effects": [list(f) for f in self.effects],
            "cost": self.cost,
            "remember": self.remember,
        }


def _flatten(term: Any) -> Iterator[Any]:
    if isinstance(term, (list, tuple)):
        for t in term:
            yield from _flatten(t)
    elif isinstance(term, dict):
        for t in term.values():
            yield from _flatten(t)
    else:
        yield term


@dataclass(frozen=True)
class Goal:
    """Facts to achieve. Variables in its facts are existential: any binding that holds will do."""

    name: str
    facts: tuple[Fact, ...]
    priority: float = 0.0
    persistent: bool = False

    def to_data(self) -> dict[str, Any]:
        return {"name": self.name, "facts": [list(f) for f in self.facts], "priority": self.priority,
                "persistent": self.persistent}


@dataclass(frozen=True)
class Trigger:
    """A world-model fact that, when set, adds a goal (``goal`` is goal data; ``?vars`` come from the fact)."""

    when: Fact
    goal: dict[str, Any] = field(hash=False)
    #: Facts the mind learns when the trigger fires (``?vars`` filled in), kept as its own
    #: persistent beliefs, e.g. "Guest is expected": the reason for the goal travels with it.
    believe: tuple[Fact, ...] = ()

    def to_data(self) -> dict[str, Any]:
        return {"when": list(self.when), "goal": copy.deepcopy(self.goal), "believe": [list(f) for f in self.believe]}


#: Nudges (valence, arousal) per kind of episode; kinds not listed leave the emotion alone.
DEFAULT_APPRAISALS: dict[str, tuple[float, float]] = {
    "action_succeeded": (0.1, 0.05),
    "action_failed": (-0.2, 0.2),
    "action_cancelled": (-0.1, 0.1),
    "goal_achieved": (0.4, -0.1),
    "goal_abandoned": (-0.4, 0.2),
    "goal_unreachable": (-0.15, 0.1),
}


@dataclass(frozen=True)
class EmotionConfig:
    decay: float = 0.9
    appraisals: dict[str, tuple[float, float]] = field(default_factory=lambda: dict(DEFAULT_APPRAISALS), hash=False)

    def to_data(self) -> dict[str, Any]:
        return {"decay": self.decay,
                "appraisals": {k: {"valence": v, "arousal": a} for k, (v, a) in sorted(self.appraisals.items())}}


@dataclass(frozen=True)
class Limits:
    max_depth: int = 8  # steps in one plan
    max_expanded: int = 5000  # belief states expanded by one search
    max_generated: int = 200_000  # successors built by one search (free variables multiply them)
    max_failures: int = 3  # failed actions before a goal is abandoned
    ban_attempts: int = 3  # planning attempts a failed step is avoided for
    max_actions: int = 50  # actions spent on one goal before it is abandoned (a world that never agrees)
    memory: int = 500  # episodes remembered
    # Seconds before a goal that could not be planned for is searched again, even if beliefs
    # change sooner: a sensor writing the world model ten times a second must not keep the update
    # loop busy re-proving that the goal is out of reach.
    retry_delay: float = 1.0

    def to_data(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class PlannerSpec:
    operators: tuple[Operator, ...] = ()
    goals: tuple[Goal, ...] = ()
    triggers: tuple[Trigger, ...] = ()
    emotion: EmotionConfig | None = None
    limits: Limits | None = None


# The wire shapes of the spec: msgspec checks them and names the offending path.

_FactData = tuple[str, str, Any]


class _OperatorData(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    action: str
    parameters: list[str] = []
    subject: str = ""
    preconditions: list[_FactData] = []
    effects: list[_FactData] = []
    cost: float = 1.0
    remember: bool = False


class _GoalData(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    facts: list[_FactData]
    priority: float = 0.0
    persistent: bool = False


class _TriggerData(msgspec.Struct, forbid_unknown_fields=True):
    when: _FactData
    goal: dict[str, Any]
    believe: list[_FactData] = []


class _AppraisalData(msgspec.Struct, forbid_unknown_fields=True):
    valence: float = 0.0
    arousal: float = 0.0


class _EmotionData(msgspec.Struct, forbid_unknown_fields=True):
    decay: float = 0.9
    appraisals: dict[str, _AppraisalData] = {}


class _LimitsData(msgspec.Struct, forbid_unknown_fields=True):
    max_depth: int = 8
    max_expanded: int = 5000
    max_generated: int = 200_000
    max_failures: int = 3
    ban_attempts: int = 3
    max_actions: int = 50
    memory: int = 500
    retry_delay: float = 1.0


class _SpecData(msgspec.Struct, forbid_unknown_fields=True):
    operators: list[_OperatorData] = []
    goals: list[_GoalData] = []
    triggers: list[_TriggerData] = []
    emotion: _EmotionData | None = None
    limits: _LimitsData | None = None
    description: str = ""


def _convert(data: Any, kind: Any, what: str, path: str | None) -> Any:
    try:
        return msgspec.convert(data, kind)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{what}: {exc}", path=path) from None


def _fact(raw: Sequence[Any], where: str, path: str | None) -> Fact:
    entity, prop, value = raw
    if not entity or not prop:
        raise ConfigError(f"{where}: fact {list(raw)!r} has an empty entity or property", path=path)
    try:
        check_value(value)
    except ValueError as exc:
        raise ConfigError(f"{where}: fact {list(raw)!r}: {exc}", path=path) from None
    return (entity, prop, value)


def _operator(d: _OperatorData, path: str | None) -> Operator:
    where = f"operator {d.name!r}"
    if not d.name or not d.action:
        raise ConfigError(f"{where}: name and action must not be empty", path=path)
    if d.cost < 0:
        raise ConfigError(f"{where}: cost {d.cost} is negative", path=path)
    return Operator(d.name, d.action, tuple(d.parameters), tuple(_fact(f, where, path) for f in d.preconditions),
                    tuple(_fact(f, where, path) for f in d.effects), float(d.cost), d.subject, d.remember)


def _goal(d: _GoalData, path: str | None) -> Goal:
    where = f"goal {d.name!r}"
    if not d.name:
        raise ConfigError("a goal has an empty name", path=path)
    if not d.facts:
        raise ConfigError(f"{where} has no facts", path=path)
    return Goal(d.name, tuple(_fact(f, where, path) for f in d.facts), float(d.priority), d.persistent)


def _trigger(d: _TriggerData, path: str | None) -> Trigger:
    when = _fact(d.when, "trigger", path)
    # The template must already read as a goal; substitution only fills in values.
    _goal(_convert(d.goal, _GoalData, f"trigger {list(when)!r}", path), path)
    try:
        check_value(d.goal)
    except ValueError as exc:
        raise ConfigError(f"trigger {list(when)!r}: {exc}", path=path) from None
    return Trigger(when, dict(d.goal), tuple(_fact(f, "trigger belief", path) for f in d.believe))


def _emotion(d: _EmotionData, path: str | None) -> EmotionConfig:
    if not 0.0 <= d.decay <= 1.0:
        raise ConfigError(f"emotion decay {d.decay} is not within [0, 1]", path=path)
    appraisals = dict(DEFAULT_APPRAISALS)
    appraisals.update({k: (a.valence, a.arousal) for k, a in d.appraisals.items()})
    return EmotionConfig(d.decay, appraisals)


def _limits(d: _LimitsData, path: str | None) -> Limits:
    values: dict[str, Any] = msgspec.structs.asdict(d)
    for name, value in values.items():
        least = 0 if name == "retry_delay" else 1
        if value < least:
            raise ConfigError(f"limit {name} must be at least {least}, not {value}", path=path)
    return Limits(**values)


def _unique_operators(operators: Iterable[Operator], path: str | None) -> tuple[Operator, ...]:
    seen: set[str] = set()
    for op in operators:
        if op.name in seen:
            raise ConfigError(f"two operators are named {op.name!r}", path=path)
        seen.add(op.name)
    return tuple(operators)


def operators_from_data(data: Sequence[Mapping[str, Any]], *, path: str | None = None) -> list[Operator]:
    """Operators from plain data (a list of operator maps); ``ConfigError`` names the fault."""
    parsed = _convert(list(data), list[_OperatorData], "operators", path)
    return list(_unique_operators([_operator(d, path) for d in parsed], path))


def goals_from_data(data: Sequence[Mapping[str, Any]], *, path: str | None = None) -> list[Goal]:
    parsed = _convert(list(data), list[_GoalData], "goals", path)
    return [_goal(d, path) for d in parsed]


def spec_from_data(data: Mapping[str, Any] | Sequence[Mapping[str, Any]], *, path: str | None = None) -> PlannerSpec:
    """A whole spec from plain data; a bare list is read as the operators alone."""
    if not isinstance(data, Mapping):
        return PlannerSpec(operators=tuple(operators_from_data(data, path=path)))
    d: _SpecData = _convert(dict(data), _SpecData, "planner spec", path)
    return PlannerSpec(
        operators=_unique_operators([_operator(o, path) for o in d.operators], path),
        goals=tuple(_goal(g, path) for g in d.goals),
        triggers=tuple(_trigger(t, path) for t in d.triggers),
        emotion=None if d.emotion is None else _emotion(d.emotion, path),
        limits=None if d.limits is None else _limits(d.limits, path),
    )


def _read_json(path: str | os.PathLike[str]) -> Any:
    name = os.fspath(path)
    try:
        with open(name, "rb") as f:
            raw = f.read(16 * 1024 * 1024 + 1)
    except OSError as exc:
        raise ConfigError(f"cannot read planner spec: {exc.strerror or exc}", path=name) from None
    if len(raw) > 16 * 1024 * 1024:
        raise ConfigError("planner spec is larger than 16 MiB", path=name)
    try:
        return msgspec.json.decode(raw)
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise ConfigError(f"not JSON: {exc}", path=name) from None


def load_spec(path: str | os.PathLike[str]) -> PlannerSpec:
    """Read a JSON spec file: ``{"operators", "goals", "triggers", "emotion", "limits"}`` or a bare operator list."""
    data = _read_json(path)
    if not isinstance(data, (dict, list)):
        raise ConfigError("a planner spec is a JSON object or a list of operators", path=os.fspath(path))
    return spec_from_data(data, path=os.fspath(path))


def load_operators(path: str | os.PathLike[str]) -> list[Operator]:
    """The operators of a JSON spec file (a whole spec or a bare list)."""
    return list(load_spec(path).operators)


# --- planning --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Step:
    """An operator with its variables bound: one action of a plan."""

    operator: Operator
    bindings: dict[str, Any] = field(hash=False)

    @property
    def action(self) -> str:
        return _text(substitute(self.operator.action, self.bindings))

    @property
    def parameters(self) -> list[str]:
        return [_text(substitute(p, self.bindings)) for p in self.operator.parameters]

    @property
    def subject(self) -> str:
        return _text(substitute(self.operator.subject, self.bindings))

    @property
    def key(self) -> str:
        """Identifies the grounded step, for remembering that it failed."""
        return f"{self.operator.name} {_bindings_text(self.bindings)}"

    def preconditions(self) -> list[Fact]:
        return [_ground(f, self.bindings) for f in self.operator.preconditions]

    def effects(self) -> list[Fact]:
        return [_ground(f, self.bindings) for f in self.operator.effects]

    def describe(self) -> str:
        return " ".join([self.action, *self.parameters])

    def to_data(self) -> dict[str, Any]:
        return {"operator": self.operator.name, "bindings": copy.deepcopy(self.bindings), "action": self.action,
                "parameters": self.parameters, "subject": self.subject}


def _ground(fact: Fact, bindings: Mapping[str, Any]) -> Fact:
    entity, prop, value = (substitute(t, bindings) for t in fact)
    return (_text(entity), _text(prop), value)


@dataclass
class PlanResult:
    found: bool
    steps: list[Step]
    cost: float = 0.0
    expanded: int = 0
    reason: str = ""


def _term(term: Any, bindings: Mapping[str, Any]) -> tuple[bool, Any]:
    """``(True, var)`` if ``term`` is an unbound variable, else ``(False, its value)``."""
    if isinstance(term, str):
        if "?" not in term:
            return False, term
        if _is_var_text(term):
            return (False, bindings[term]) if term in bindings else (True, term)
    return False, substitute(term, bindings)


def match(facts: Sequence[Fact], beliefs: Mapping[str, Mapping[str, Any]], bindings: Mapping[str, Any]) -> Iterator[dict[str, Any]]:
    """Every extension of ``bindings`` under which all ``facts`` hold in ``beliefs``."""
    if not facts:
        yield dict(bindings)
        return
    (entity, prop, value), rest = facts[0], facts[1:]
    free, ent = _term(entity, bindings)
    entities = list(beliefs) if free else [ent] if isinstance(ent, str) else []
    for e in entities:
        b1 = {**bindings, ent: e} if free else bindings
        props = beliefs.get(e)
        free_p, p = _term(prop, b1)
        names = list(props or ()) if free_p else [p] if isinstance(p, str) else []
        for name in names:
            b2 = {**b1, p: name} if free_p else b1
            free_v, v = _term(value, b2)
            if free_v:
                if props is not None and name in props:
                    yield from match(rest, beliefs, {**b2, v: props[name]})
            elif v is None:
                if props is None:
                    if not free:  # an unknown entity holds no property at all
                        yield from match(rest, beliefs, b2)
                elif props.get(name) is None:
                    yield from match(rest, beliefs, b2)
            elif props is not None and name in props and _same(props[name], v):
                yield from match(rest, beliefs, b2)


def holds(facts: Sequence[Fact], beliefs: Mapping[str, Mapping[str, Any]]) -> bool:
    return next(match(facts, beliefs, {}), None) is not None


# States are keyed by two order-free sums of fact hashes (XOR and addition), updated from an
# operator's effects alone: building a successor's key costs as much as its effects, not as much as
# the world, so duplicates are dropped before they are copied. Two 64-bit sums colliding by chance
# is not a practical concern.
StateKey = tuple[int, int]
_MASK = (1 << 64) - 1
_ABSENT = object()


def _fact_hash(entity: str, prop: str, value: Any) -> int:
    return hash((entity, prop, _value_key(value))) & _MASK


def _entity_hash(entity: str) -> int:
    return hash((entity,)) & _MASK


def _state_key(state: Mapping[str, Mapping[str, Any]]) -> StateKey:
    x = total = 0
    for e, props in state.items():
        h = _entity_hash(e)
        x, total = x ^ h, total + h
        for p, v in props.items():
            h = _fact_hash(e, p, v)
            x, total = x ^ h, total + h
    return x, total & _MASK


def _key_after(state: Mapping[str, Mapping[str, Any]], key: StateKey, effects: Iterable[Fact]) -> StateKey:
    """The key ``_apply(state, effects)`` will have, without building that state."""
    x, total = key
    now: dict[tuple[str, str], Any] = {}
    added: set[str] = set()
    for entity, prop, value in effects:
        props = state.get(entity)
        if props is None and entity not in added:
            h = _entity_hash(entity)
            x, total = x ^ h, total + h
            added.add(entity)
        old = now.get((entity, prop), _ABSENT if props is None else props.get(prop, _ABSENT))
        if old is not _ABSENT:
            h = _fact_hash(entity, prop, old)
            x, total = x ^ h, total - h
        if value is not None:
            h = _fact_hash(entity, prop, value)
            x, total = x ^ h, total + h
        now[(entity, prop)] = _ABSENT if value is None else value
    return x, total & _MASK


def _apply(state: Mapping[str, Mapping[str, Any]], effects: Iterable[Fact]) -> Beliefs:
    # Copy only the entities an effect touches: states share the rest.
    new: dict[str, Any] = dict(state)
    copied: set[str] = set()
    for entity, prop, value in effects:
        if entity not in copied:
            new[entity] = dict(new.get(entity, {}))
            copied.add(entity)
        if value is None:
            new[entity].pop(prop, None)
        else:
            new[entity][prop] = value
    return new


def _successors(state: Beliefs, operators: Sequence[Operator], constants: Sequence[str]) -> Iterator[Step]:
    candidates = list(dict.fromkeys([*(e for e in state if e), *constants]))
    for op in operators:
        variables = op.variables
        for bindings in match(op.preconditions, state, {}):
            free = [v for v in variables if v not in bindings]
            for values in itertools.product(candidates, repeat=len(free)):
                yield Step(op, {**bindings, **dict(zip(free, values, strict=True))})


def find_plan(
    beliefs: Mapping[str, Mapping[str, Any]],
    facts: Sequence[Fact],
    operators: Iterable[Operator],
    *,
    banned: Iterable[str] = (),
    max_depth: int = 8,
    max_expanded: int = 5000,
    max_generated: int = 200_000,
) -> PlanResult:
    """The cheapest sequence of operators that makes ``facts`` hold, by uniform-cost search.

    ``banned`` holds ``Step.key`` values never to use. Bounded: at most ``max_depth`` steps and
    ``max_expanded`` expanded states and ``max_generated`` successors built; ``found`` False says
    why in ``reason``.
    """
    ops = list(operators)
    avoid = set(banned)
    start: Beliefs = {e: dict(p) for e, p in beliefs.items()}
    constants = [t for f in facts for t in (f[0], f[2]) if isinstance(t, str) and t and "?" not in t]
    counter = itertools.count()  # ties go first-queued first: fewer steps, then operator order
    start_key = _state_key(start)
    frontier: list[tuple[float, int, StateKey, Beliefs, tuple[Step, ...]]] = [(0.0, next(counter), start_key, start, ())]
    best: dict[StateKey, float] = {start_key: 0.0}
    expanded = generated = 0
    cut = False
    while frontier:
        cost, _, state_key, state, steps = heapq.heappop(frontier)
        if best[state_key] < cost:
            continue  # a cheaper way here was queued after this entry
        if holds(facts, state):
            return PlanResult(True, list(steps), cost, expanded)
        if expanded >= max_expanded:
            return PlanResult(False, [], 0.0, expanded, f"search gave up after expanding {expanded} states")
        expanded += 1
        if len(steps) >= max_depth:
            cut = True
            continue
        for step in _successors(state, ops, constants):
            if avoid and step.key in avoid:
                continue
            generated += 1
            if generated > max_generated:
                return PlanResult(False, [], 0.0, expanded, f"search gave up after trying {max_generated} steps")
            effects = step.effects()
            key = _key_after(state, state_key, effects)
            new_cost = cost + step.operator.cost
            if key in best and best[key] <= new_cost:
                continue
            best[key] = new_cost
            heapq.heappush(frontier, (new_cost, next(counter), key, _apply(state, effects), (*steps, step)))
    if cut:
        return PlanResult(False, [], 0.0, expanded, f"no plan of at most {max_depth} steps")
    return PlanResult(False, [], 0.0, expanded, "no sequence of operators achieves it")


def _plan_works(beliefs: Mapping[str, Mapping[str, Any]], steps: Sequence[Step], facts: Sequence[Fact]) -> bool:
    """Whether ``steps``, run from ``beliefs``, are each applicable and end with ``facts`` holding."""
    state: Beliefs = {e: dict(p) for e, p in beliefs.items()}
    for step in steps:
        if not holds(step.preconditions(), state):
            return False
        state = _apply(state, step.effects())
    return holds(facts, state)


# --- the mind --------------------------------------------------------------------------------------


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
            op_list = [o if isinstance(o, Operator) else operators_from_data([o])[0] for o in operators]
        goal_list = list(spec.goals)
        if isinstance(goals, (str, os.PathLike)):
            goal_file = os.fspath(goals).strip()
            if goal_file:
                data = _read_json(goal_file)
                if isinstance(data, dict):
                    goal_list += spec_from_data(data, path=goal_file).goals
                elif isinstance(data, list):
                    goal_list += goals_from_data(data, path=goal_file)
                else:
                    raise ConfigError("a goals file holds a list of goals or a spec", path=goal_file)
        else:
            goal_list += [g if isinstance(g, Goal) else goals_from_data([g])[0] for g in goals]
        trigger_list = list(spec.triggers)
        for t in triggers:
            trigger_list += [t] if isinstance(t, Trigger) else spec_from_data({"triggers": [t]}).triggers
        self.operators: tuple[Operator, ...] = _unique_operators(op_list, None)
        self.triggers: tuple[Trigger, ...] = tuple(trigger_list)
        self.emotion_config: EmotionConfig = emotion or spec.emotion or EmotionConfig()
        self.limits: Limits = limits or spec.limits or Limits()
        self.seed_beliefs = seed_beliefs

        self.beliefs: Beliefs = {}
        self.persistent: set[tuple[str, str]] = set()
        self.pending_goals: list[Goal] = []
        self.satisfied: set[str] = set()  # persistent goals whose facts hold now
        self.achieved: list[dict[str, Any]] = []
        self.abandoned: list[dict[str, Any]] = []
        self.plan: list[Step] = []
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
            from cmion_mesh.storage import WorldModel

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
        # Think in the next update, not now: migration wakes a restored mind and hands it the new
        # body's world model (``on_arrived``) in one go, and acting before that would act on
        # beliefs about the old body.
        self._think_soon()

    def on_arrived(self, world_model: dict[str, Any]) -> None:
        """Restored on a new body: its world model replaces what was believed about the old one."""
        self.replace_beliefs(world_model)

    def _think_soon(self) -> None:
        if self._sim is not None and not self._sim.closed:
            try:
                self._sim.call(self._think)
            except MeshError:
                pass  # closing: nothing left to do

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
        changed = name not in props or not _same(props[name], value)
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
            goal = goals_from_data([substitute(trigger.goal, bindings)])[0]
        except ConfigError as exc:
            log.warning("mind %s: trigger %r made no goal: %s", self.name, list(trigger.when), exc)
            return
        for entity, prop, value in substitute([list(f) for f in trigger.believe], bindings):
            self.beliefs.setdefault(str(entity), {})[str(prop)] = value
            self.persistent.add((str(entity), str(prop)))
        self._add_goal(goal, source=f"trigger {_text(list(fact))}")

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
        record = {**goal.to_data(), "time": time.time()}
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
            goal = self._top_goal()
            if goal is None:
                if self.plan:
                    self.plan, self.plan_goal = [], None
                return
            if self.plan_goal == goal.name and self.plan and _plan_works(self.beliefs, self.plan, goal.facts):
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

    def _top_goal(self) -> Goal | None:
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

    def _act(self, goal: Goal, step: Step) -> bool:
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
        log.info("mind %s acts for %r: %s (%s)", self.name, goal.name, step.describe(), action_id)
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
            self.emotion = {"valence": round(_clamp(self.emotion["valence"] * decay + nudge[0]), 6),
                            "arousal": round(_clamp(self.emotion["arousal"] * decay + nudge[1]), 6)}

    def _decide(self, decision: str, **data: Any) -> None:
        log.info("mind %s: %s %s", self.name, decision, data)
        if self._sim is not None and not self._sim.closed:
            try:
                self.raise_event("MindDecision", {"mind": self.name, "decision": decision, **data})
            except (MeshError, ValueError) as exc:
                log.warning("mind %s could not raise MindDecision: %s", self.name, exc)

    # --- migration --------------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """Everything the mind is, as one JSON-serialisable dict (``restore`` takes it back).

        Keys: ``version``; ``spec`` (operators, triggers, emotion and limits settings); ``goals``
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
                "operators": [op.to_data() for op in self.operators],
                "triggers": [t.to_data() for t in self.triggers],
                "emotion": self.emotion_config.to_data(),
                "limits": self.limits.to_data(),
            },
            "goals": {
                "pending": [{**g.to_data(), "satisfied": g.name in self.satisfied} for g in self.pending_goals],
                "achieved": copy.deepcopy(self.achieved),
                "abandoned": copy.deepcopy(self.abandoned),
            },
            "plan": {"goal": self.plan_goal, "steps": [s.to_data() for s in self.plan]},
            "in_flight": self.in_flight,
            "beliefs": copy.deepcopy(self.beliefs),
            "persistent": [list(k) for k in sorted(self.persistent)],
            "memory": copy.deepcopy(list(self.memory)),
            "emotion": dict(self.emotion),
            "failures": dict(self.failures),
            "actions_spent": dict(self.actions_spent),
            "bans": {g: dict(b) for g, b in self.bans.items()},
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Become the mind ``state`` describes. An action that was in flight is dropped with the
        plan it belonged to (it ran on another body); planning resumes on the loop when awake.
        Otherwise ``state()`` afterwards equals ``state``."""
        try:
            self._restore(state)
        except (KeyError, TypeError, ValueError, msgspec.ValidationError) as exc:
            raise ConfigError(f"mind {self.name!r}: unusable state: {exc!r}") from None
        self._think_soon()

    def _restore(self, state: dict[str, Any]) -> None:
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"state version {state.get('version')!r}, expected {STATE_VERSION}")
        spec = state["spec"]
        operators = operators_from_data(spec["operators"])
        triggers = spec_from_data({"triggers": spec["triggers"]}).triggers
        emotion = _emotion(msgspec.convert(spec["emotion"], _EmotionData), None)
        limits = _limits(msgspec.convert(spec["limits"], _LimitsData), None)
        pending = [dict(g) for g in state["goals"]["pending"]]
        satisfied = {str(g["name"]) for g in pending if g.pop("satisfied", False)}
        goals = goals_from_data(pending)
        by_name = {op.name: op for op in operators}
        plan = [Step(by_name[s["operator"]], dict(s["bindings"])) for s in state["plan"]["steps"]]

        if self.in_flight is not None:
            self.pending.pop(self.in_flight, None)
        self.operators, self.triggers, self.emotion_config, self.limits = tuple(operators), triggers, emotion, limits
        self.pending_goals, self.satisfied = goals, satisfied
        self.achieved = copy.deepcopy(list(state["goals"]["achieved"]))
        self.abandoned = copy.deepcopy(list(state["goals"]["abandoned"]))
        self.plan, self.plan_goal = plan, state["plan"]["goal"]
        self.in_flight = None
        if state["in_flight"] is not None:
            self.plan, self.plan_goal = [], None
        self.beliefs = {str(e): dict(p) for e, p in copy.deepcopy(state["beliefs"]).items()}
        self.persistent = {(str(e), str(p)) for e, p in state["persistent"]}
        self.memory = deque(copy.deepcopy(list(state["memory"])), maxlen=limits.memory)
        self.emotion = {"valence": float(state["emotion"]["valence"]), "arousal": float(state["emotion"]["arousal"])}
        self.failures = {str(k): int(v) for k, v in state["failures"].items()}
        self.actions_spent = {str(k): int(v) for k, v in state["actions_spent"].items()}
        self.bans = {str(g): {str(k): int(n) for k, n in b.items()} for g, b in state["bans"].items()}
        self._blocked, self._unreachable = {}, {}
