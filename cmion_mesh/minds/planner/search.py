"""The reference planner's search: matching facts against beliefs, and finding a plan. Pure.

Beliefs are ``entity -> {property: value}``; facts and operators are those of ``minds.planner.spec``.
``match`` yields every binding of the variables under which facts hold; ``find_plan`` is a
uniform-cost search over belief states, bounded by depth, expanded states and generated
successors: an unsolvable goal ends with ``found`` False and the reason, never a hang.

Nothing here touches the mesh, a clock or a random source: the same beliefs, facts and operators
always give the same plan.
"""

from __future__ import annotations

import copy
import heapq
import itertools
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import msgspec

from cmion_mesh.minds.planner.spec import VARIABLE, Fact, Operator, is_var_text

__all__ = [
    "Beliefs",
    "GroundedOperator",
    "PlanResult",
    "apply_effects",
    "bind",
    "find_plan",
    "holds",
    "match",
    "plan_works",
    "same_value",
    "text",
]

Beliefs = dict[str, dict[str, Any]]


# --- terms and values ---------------------------------------------------------------------------------


def text(value: Any) -> str:
    """A value as it reads inside a longer string (``"greet ?who"``) or as an action's parameter."""
    if isinstance(value, str):
        return value
    if value is None:
        return ""
    if isinstance(value, (bool, int, float)):
        return str(value)
    return msgspec.json.encode(value).decode()


def bind(term: Any, bindings: Mapping[str, Any]) -> Any:
    """``term`` with its bound variables replaced; unbound ones are left as they are."""
    if isinstance(term, str):
        if "?" not in term:
            return term
        if term in bindings and is_var_text(term):
            return bindings[term]
        return VARIABLE.sub(lambda m: text(bindings[m.group()]) if m.group() in bindings else m.group(), term)
    if isinstance(term, list):
        return [bind(t, bindings) for t in term]
    if isinstance(term, tuple):
        return tuple(bind(t, bindings) for t in term)
    if isinstance(term, dict):
        return {k: bind(v, bindings) for k, v in term.items()}
    return term


def same_value(a: Any, b: Any) -> bool:
    """Equal as beliefs: True == 1 in Python, but a world model that says True does not say 1."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    return bool(a == b)


def _value_key(value: Any) -> Any:
    """A hashable stand-in for a value, equal exactly when ``same_value`` says the values are."""
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


def _ground(fact: Fact, bindings: Mapping[str, Any]) -> Fact:
    entity, prop, value = (bind(t, bindings) for t in fact)
    return (text(entity), text(prop), value)


# --- grounded operators and plans ------------------------------------------------------------------------


@dataclass(frozen=True)
class GroundedOperator:
    """An operator with its variables bound: one action of a plan."""

    operator: Operator
    bindings: dict[str, Any] = field(hash=False)

    @property
    def action(self) -> str:
        return text(bind(self.operator.action, self.bindings))

    @property
    def parameters(self) -> list[str]:
        return [text(bind(p, self.bindings)) for p in self.operator.parameters]

    @property
    def subject(self) -> str:
        return text(bind(self.operator.subject, self.bindings))

    @property
    def key(self) -> str:
        """Identifies the grounded operator, for remembering that it failed."""
        return f"{self.operator.name} {_bindings_text(self.bindings)}"

    def preconditions(self) -> list[Fact]:
        return [_ground(f, self.bindings) for f in self.operator.preconditions]

    def effects(self) -> list[Fact]:
        return [_ground(f, self.bindings) for f in self.operator.effects]

    def describe(self) -> str:
        return " ".join([self.action, *self.parameters])

    def to_data(self) -> dict[str, Any]:
        """Plain data for the mind's state and decisions: the operator by name, bindings and the action."""
        return {"operator": self.operator.name, "bindings": copy.deepcopy(self.bindings),
                "action": self.action, "parameters": self.parameters, "subject": self.subject}


@dataclass
class PlanResult:
    found: bool
    steps: list[GroundedOperator]
    cost: float = 0.0
    expanded: int = 0
    reason: str = ""


# --- matching ------------------------------------------------------------------------------------------


def _term(term: Any, bindings: Mapping[str, Any]) -> tuple[bool, Any]:
    """``(True, var)`` if ``term`` is an unbound variable, else ``(False, its value)``."""
    if isinstance(term, str):
        if "?" not in term:
            return False, term
        if is_var_text(term):
            return (False, bindings[term]) if term in bindings else (True, term)
    return False, bind(term, bindings)


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
            elif props is not None and name in props and same_value(props[name], v):
                yield from match(rest, beliefs, b2)


def holds(facts: Sequence[Fact], beliefs: Mapping[str, Mapping[str, Any]]) -> bool:
    return next(match(facts, beliefs, {}), None) is not None


# --- search --------------------------------------------------------------------------------------------

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
    """The key ``apply_effects(state, effects)`` will have, without building that state."""
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


def apply_effects(state: Mapping[str, Mapping[str, Any]], effects: Iterable[Fact]) -> Beliefs:
    """The beliefs after ``effects`` (a None value deletes); ``state`` itself is left alone."""
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


def _successors(state: Beliefs, operators: Sequence[Operator], constants: Sequence[str]) -> Iterator[GroundedOperator]:
    candidates = list(dict.fromkeys([*(e for e in state if e), *constants]))
    for op in operators:
        variables = op.variables
        for bindings in match(op.preconditions, state, {}):
            free = [v for v in variables if v not in bindings]
            for values in itertools.product(candidates, repeat=len(free)):
                yield GroundedOperator(op, {**bindings, **dict(zip(free, values, strict=True))})


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

    ``banned`` holds ``GroundedOperator.key`` values never to use. Bounded: at most ``max_depth``
    steps and ``max_expanded`` expanded states and ``max_generated`` successors built; ``found``
    False says why in ``reason``.
    """
    ops = list(operators)
    avoid = set(banned)
    start: Beliefs = {e: dict(p) for e, p in beliefs.items()}
    constants = [t for f in facts for t in (f[0], f[2]) if isinstance(t, str) and t and "?" not in t]
    counter = itertools.count()  # ties go first-queued first: fewer steps, then operator order
    start_key = _state_key(start)
    frontier: list[tuple[float, int, StateKey, Beliefs, tuple[GroundedOperator, ...]]] = [(0.0, next(counter), start_key, start, ())]
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
            heapq.heappush(frontier, (new_cost, next(counter), key, apply_effects(state, effects), (*steps, step)))
    if cut:
        return PlanResult(False, [], 0.0, expanded, f"no plan of at most {max_depth} steps")
    return PlanResult(False, [], 0.0, expanded, "no sequence of operators achieves it")


def plan_works(beliefs: Mapping[str, Mapping[str, Any]], steps: Sequence[GroundedOperator], facts: Sequence[Fact]) -> bool:
    """Whether ``steps``, run from ``beliefs``, are each applicable and end with ``facts`` holding."""
    state: Beliefs = {e: dict(p) for e, p in beliefs.items()}
    for step in steps:
        if not holds(step.preconditions(), state):
            return False
        state = apply_effects(state, step.effects())
    return holds(facts, state)
