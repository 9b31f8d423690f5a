"""The reference planner's spec: operators, goals, triggers, emotion and limits, as validated Structs.

**Facts** are world-model facts, ``(entity, property, value)`` triples such as
``("Guest", "greeted", True)``.

**Operators** say what a mind action does: the action to send (name, parameters, subject),
preconditions and effects, and a cost. Any string may hold variables, ``?name``:

* in preconditions a variable binds to whatever the beliefs hold (an entity, a property name or
  a value); a precondition whose value is ``None`` holds when the property is absent (or None);
* a variable the preconditions leave unbound (e.g. ``?place`` in ``GoTo ?place``) ranges over
  the entities of the belief base and the strings named in the goal;
* an effect whose value is ``None`` deletes the property.

A variable standing alone keeps its bound value's type (``"?v"`` -> ``True``); inside longer text
it is replaced by the value's text (``"greet ?who"`` -> ``"greet Guest"``).

**Goals** are facts to achieve with a priority (higher first); a *persistent* goal is a
maintenance goal, pursued again whenever its facts stop holding. **Triggers** add a goal when a
world-model fact is set. The spec (JSON, or the same structure as Python data)::

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
                 "ban_attempts": 3, "max_actions": 50, "memory": 500, "retry_delay": 1.0},
      "invitations": {"follow": true, "accept_from": ["screen", "phone"], "action": "Migrate"}
    }

Each part is one frozen msgspec Struct: the same object is read from the file, checked (a check
that msgspec's types cannot say lives in ``__post_init__``, so it holds however the object is
made), used by the mind and written back into its state with ``msgspec.to_builtins``.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import msgspec

from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import check_value

__all__ = [
    "DEFAULT_APPRAISALS",
    "VARIABLE",
    "Appraisal",
    "EmotionConfig",
    "Fact",
    "Goal",
    "InvitationPolicy",
    "Limits",
    "Operator",
    "PlannerSpec",
    "Trigger",
    "goals_from_data",
    "is_var",
    "is_var_text",
    "load_operators",
    "load_spec",
    "operators_from_data",
    "read_json",
    "spec_from_data",
    "to_plain",
]

Fact = tuple[str, str, Any]

VARIABLE = re.compile(r"\?[A-Za-z_][A-Za-z0-9_]*")
#: Largest spec file read.
MAX_SPEC_BYTES = 16 * 1024 * 1024


def is_var(term: Any) -> bool:
    return isinstance(term, str) and "?" in term and is_var_text(term)


@functools.lru_cache(maxsize=4096)  # the search asks about the same few terms again and again
def is_var_text(term: str) -> bool:
    return VARIABLE.fullmatch(term) is not None


def _check_facts(facts: Sequence[Fact], where: str) -> None:
    for entity, prop, value in facts:
        if not entity or not prop:
            raise ValueError(f"{where}: fact {[entity, prop, value]!r} has an empty entity or property")
        try:
            check_value(value)
        except ValueError as exc:
            raise ValueError(f"{where}: fact {[entity, prop, value]!r}: {exc}") from None


def _flatten(term: Any) -> Iterator[Any]:
    if isinstance(term, (list, tuple)):
        for t in term:
            yield from _flatten(t)
    elif isinstance(term, dict):
        for t in term.values():
            yield from _flatten(t)
    else:
        yield term


class Operator(msgspec.Struct, frozen=True, forbid_unknown_fields=True, dict=True):
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

    def __post_init__(self) -> None:
        where = f"operator {self.name!r}"
        if not self.name or not self.action:
            raise ValueError(f"{where}: name and action must not be empty")
        if self.cost < 0:
            raise ValueError(f"{where}: cost {float(self.cost)} is negative")
        _check_facts(self.preconditions, where)
        _check_facts(self.effects, where)

    @functools.cached_property
    def variables(self) -> tuple[str, ...]:
        """Every variable it mentions, in order of first mention (searched for on every expansion)."""
        found: dict[str, None] = {}
        for term in _flatten((self.action, self.parameters, self.subject, self.preconditions, self.effects)):
            if isinstance(term, str):
                for m in VARIABLE.finditer(term):
                    found.setdefault(m.group(), None)
        return tuple(found)


class Goal(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Facts to achieve. Variables in its facts are existential: any binding that holds will do."""

    name: str
    facts: tuple[Fact, ...]
    priority: float = 0.0
    persistent: bool = False

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("a goal has an empty name")
        if not self.facts:
            raise ValueError(f"goal {self.name!r} has no facts")
        _check_facts(self.facts, f"goal {self.name!r}")


class Trigger(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A world-model fact that, when set, adds a goal (``goal`` is goal data; ``?vars`` come from the fact)."""

    when: Fact
    goal: dict[str, Any]
    #: Facts the mind learns when the trigger fires (``?vars`` filled in), kept as its own
    #: persistent beliefs, e.g. "Guest is expected": the reason for the goal travels with it.
    believe: tuple[Fact, ...] = ()

    def __post_init__(self) -> None:
        _check_facts([self.when], "trigger")
        where = f"trigger {list(self.when)!r}"
        # The template must already read as a goal; substitution only fills in values.
        try:
            msgspec.convert(self.goal, Goal)
            check_value(self.goal)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        _check_facts(self.believe, "trigger belief")


class Appraisal(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """How one kind of episode nudges the emotion."""

    valence: float = 0.0
    arousal: float = 0.0


#: Nudges per kind of episode; kinds not listed leave the emotion alone.
DEFAULT_APPRAISALS: dict[str, Appraisal] = {
    "action_succeeded": Appraisal(0.1, 0.05),
    "action_failed": Appraisal(-0.2, 0.2),
    "action_cancelled": Appraisal(-0.1, 0.1),
    "goal_achieved": Appraisal(0.4, -0.1),
    "goal_abandoned": Appraisal(-0.4, 0.2),
    "goal_unreachable": Appraisal(-0.15, 0.1),
}


class EmotionConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """``appraisals`` given here replace the defaults of their kinds; the others stay."""

    decay: float = 0.9
    appraisals: dict[str, Appraisal] = {}

    def __post_init__(self) -> None:
        if not 0.0 <= self.decay <= 1.0:
            raise ValueError(f"emotion decay {self.decay} is not within [0, 1]")
        msgspec.structs.force_setattr(self, "appraisals", dict(sorted({**DEFAULT_APPRAISALS, **self.appraisals}.items())))


class Limits(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
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

    def __post_init__(self) -> None:
        for name in self.__struct_fields__:
            value = getattr(self, name)
            least = 0 if name == "retry_delay" else 1
            if value < least:
                raise ValueError(f"limit {name} must be at least {least}, not {value}")


class InvitationPolicy(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Whether the mind takes up migration invitations (the remote action ``MigrationInvitation
    <embodiment>``, see ``invitation``): with ``follow``, from the embodiments in ``accept_from``
    (null: any), by sending ``action <embodiment>`` (the built-in ``Migrate`` rule), but only when
    idle: no action in flight and no goal left to achieve. Otherwise it is declined (remembered,
    and a ``MindDecision``)."""

    follow: bool = False
    accept_from: tuple[str, ...] | None = None
    action: str = "Migrate"

    def __post_init__(self) -> None:
        if not self.action:
            raise ValueError("invitations: action must not be empty")


def _unique(operators: Sequence[Operator]) -> None:
    seen: set[str] = set()
    for op in operators:
        if op.name in seen:
            raise ValueError(f"two operators are named {op.name!r}")
        seen.add(op.name)


class PlannerSpec(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    operators: tuple[Operator, ...] = ()
    goals: tuple[Goal, ...] = ()
    triggers: tuple[Trigger, ...] = ()
    emotion: EmotionConfig | None = None
    limits: Limits | None = None
    invitations: InvitationPolicy | None = None
    description: str = ""

    def __post_init__(self) -> None:
        _unique(self.operators)


def to_plain(part: msgspec.Struct) -> Any:
    """A part of the spec as plain data (maps and lists, as JSON has them), e.g. for the mind's state."""
    return msgspec.msgpack.decode(msgspec.msgpack.encode(part))


def _convert(data: Any, kind: Any, what: str, path: str | None) -> Any:
    try:
        return msgspec.convert(data, kind)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{what}: {exc}", path=path) from None


def operators_from_data(data: Sequence[Mapping[str, Any] | Operator], *, path: str | None = None) -> list[Operator]:
    """Operators from plain data (a list of operator maps); ``ConfigError`` names the fault."""
    operators: list[Operator] = _convert(list(data), list[Operator], "operators", path)
    try:
        _unique(operators)
    except ValueError as exc:
        raise ConfigError(str(exc), path=path) from None
    return operators


def goals_from_data(data: Sequence[Mapping[str, Any] | Goal], *, path: str | None = None) -> list[Goal]:
    goals: list[Goal] = _convert(list(data), list[Goal], "goals", path)
    return goals


def spec_from_data(data: Mapping[str, Any] | Sequence[Mapping[str, Any]], *, path: str | None = None) -> PlannerSpec:
    """A whole spec from plain data; a bare list is read as the operators alone."""
    if not isinstance(data, Mapping):
        return PlannerSpec(operators=tuple(operators_from_data(data, path=path)))
    spec: PlannerSpec = _convert(dict(data), PlannerSpec, "planner spec", path)
    return spec


def read_json(path: str | os.PathLike[str]) -> Any:
    """A JSON file's data; ``ConfigError`` naming the file if it is unreadable, too big or not JSON."""
    name = os.fspath(path)
    try:
        with open(name, "rb") as f:
            raw = f.read(MAX_SPEC_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"cannot read planner spec: {exc.strerror or exc}", path=name) from None
    if len(raw) > MAX_SPEC_BYTES:
        raise ConfigError("planner spec is larger than 16 MiB", path=name)
    try:
        return msgspec.json.decode(raw)
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise ConfigError(f"not JSON: {exc}", path=name) from None


def load_spec(path: str | os.PathLike[str]) -> PlannerSpec:
    """Read a JSON spec file: ``{"operators", "goals", "triggers", "emotion", "limits"}`` or a bare operator list."""
    data = read_json(path)
    if not isinstance(data, (dict, list)):
        raise ConfigError("a planner spec is a JSON object or a list of operators", path=os.fspath(path))
    return spec_from_data(data, path=os.fspath(path))


def load_operators(path: str | os.PathLike[str]) -> list[Operator]:
    """The operators of a JSON spec file (a whole spec or a bare list)."""
    return list(load_spec(path).operators)
