"""What a body can do, as tools: the abilities a language-model mind or an MCP client is offered.

A rules file says which mind actions a body accepts (``Say * *``, ``GoTo *``...). Today's agent
frameworks call functions with named, typed arguments and a description, so each action name and
parameter count becomes one ``Ability``:

* its **parameters** are named from the rule's comment when that starts with the action's form
  (``<!-- GoTo <location>: drive there ... -->``, how CMION's and this project's files document
  their rules), else from the step parameter fed by exactly ``$parameterN`` (``Location`` ->
  ``location``), else ``parameterN``;
* a parameter every rule of the ability fixes to a literal offers those literals as its
  **choices** (an enum); one any rule leaves ``*`` takes any text;
* its **description** is the rules' comments, else what the plan runs;
* its **tool** name fits the common function-name grammar (``^[A-Za-z0-9_-]{1,64}$``), unique in
  the body; the action's own name may be anything CMION allowed.

Pure: a ``RuleSet`` in, plain data out (``to_json``/``from_json`` carry abilities in ``describe``
so a client in another process builds the same tools).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import Any

import msgspec

from cmion_mesh.body.rules import WILDCARD, Rule, RuleSet
from cmion_mesh.errors import InvalidArguments

__all__ = ["Ability", "Parameter", "abilities"]

_TOOL_CHARACTERS = re.compile(r"[^A-Za-z0-9_-]")
_MAX_TOOL = 64
_MAX_DESCRIPTION = 1024
# ``Name <a> <b>`` at the start of a comment: the parameters' names as the author wrote them.
_FORM = re.compile(r"^\s*(?P<name>\S+)(?P<params>(?:\s+<[^<>]+>)*)")
_ANGLED = re.compile(r"<([^<>]+)>")
_PARAMETER_TOKEN = re.compile(r"^\$parameter(\d+)$")


class Parameter(msgspec.Struct, frozen=True):
    """One positional parameter of an action, named; ``choices`` empty means any text."""

    name: str
    choices: tuple[str, ...] = ()


class Ability(msgspec.Struct, frozen=True):
    """One action of a body with a given parameter count, as a callable tool."""

    tool: str
    action: str
    parameters: tuple[Parameter, ...]
    description: str
    patterns: tuple[str, ...] = ()

    def input_schema(self) -> dict[str, Any]:
        """JSON Schema of the tool's arguments (an object of strings, every parameter required)."""
        properties: dict[str, Any] = {}
        for p in self.parameters:
            prop: dict[str, Any] = {"type": "string"}
            if p.choices:
                prop["enum"] = list(p.choices)
            properties[p.name] = prop
        return {"type": "object", "properties": properties, "required": [p.name for p in self.parameters],
                "additionalProperties": False}

    def positional(self, arguments: Mapping[str, Any] | None) -> tuple[str, ...]:
        """The action's parameters in order, from a tool call's named ``arguments``.

        ``InvalidArguments`` names what is missing, unknown or outside its choices. Numbers and
        booleans are taken as their text (models send ``3`` for ``"3"``); anything else is refused.
        """
        given = dict(arguments or {})
        known = {p.name for p in self.parameters}
        unknown = sorted(set(given) - known)
        if unknown:
            raise InvalidArguments(f"{self.tool}: unknown argument(s) {', '.join(unknown)}; it takes {self._signature()}")
        values: list[str] = []
        for p in self.parameters:
            if p.name not in given:
                raise InvalidArguments(f"{self.tool}: argument {p.name!r} is missing; it takes {self._signature()}")
            value = given[p.name]
            if isinstance(value, bool):
                text = "true" if value else "false"
            elif isinstance(value, (str, int, float)):
                text = str(value)
            else:
                raise InvalidArguments(f"{self.tool}: argument {p.name!r} must be text, not {type(value).__name__}")
            if p.choices and text not in p.choices:
                raise InvalidArguments(f"{self.tool}: argument {p.name!r} is {text!r}; one of {', '.join(p.choices)}")
            values.append(text)
        return tuple(values)

    def _signature(self) -> str:
        return f"({', '.join(p.name for p in self.parameters)})" if self.parameters else "no arguments"

    def to_json(self) -> dict[str, Any]:
        return {
            "tool": self.tool,
            "action": self.action,
            "parameters": [{"name": p.name, "choices": list(p.choices)} for p in self.parameters],
            "description": self.description,
            "patterns": list(self.patterns),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Ability:
        """The ability ``to_json`` gave (from another process: ``InvalidArguments`` when malformed)."""
        try:
            return cls(
                tool=str(data["tool"]),
                action=str(data["action"]),
                parameters=tuple(Parameter(str(p["name"]), tuple(str(c) for c in p.get("choices") or ())) for p in data["parameters"]),
                description=str(data.get("description") or ""),
                patterns=tuple(str(p) for p in data.get("patterns") or ()),
            )
        except (KeyError, TypeError, AttributeError) as exc:
            raise InvalidArguments(f"malformed ability description: {exc!r}") from None


def abilities(rules: RuleSet | None) -> list[Ability]:
    """Every action of ``rules`` as an ability, in file order of each action's first rule.

    Rules named ``*`` (any action) offer no tool of their own: a tool needs a name.
    """
    if rules is None:
        return []
    groups: dict[tuple[str, int], list[Rule]] = {}
    for rule in rules.rules:
        if rule.name != WILDCARD:
            groups.setdefault((rule.name, len(rule.parameters)), []).append(rule)
    arities: dict[str, int] = {}
    for name, _ in groups:
        arities[name] = arities.get(name, 0) + 1
    used: set[str] = set()
    out: list[Ability] = []
    for (name, count), group in groups.items():
        base = name if arities[name] == 1 else f"{name}_{count}"
        out.append(Ability(
            tool=_unique(_tool_name(base), used),
            action=name,
            parameters=tuple(_parameter(group, i) for i in range(count)),
            description=_description(group),
            patterns=tuple(dict.fromkeys(r.describe() for r in group)),
        ))
    return out


def _tool_name(text: str) -> str:
    cleaned = _TOOL_CHARACTERS.sub("_", text)[:_MAX_TOOL]
    return cleaned or "action"


def _unique(name: str, used: set[str]) -> str:
    candidate = name
    for n in range(2, 2 + len(used) + 1):  # bounded: at most one clash per name already used
        if candidate not in used:
            break
        suffix = f"_{n}"
        candidate = name[: _MAX_TOOL - len(suffix)] + suffix
    used.add(candidate)
    return candidate


def _parameter(group: Sequence[Rule], index: int) -> Parameter:
    literals = [r.parameters[index] for r in group]
    choices = () if WILDCARD in literals else tuple(dict.fromkeys(literals))
    return Parameter(_parameter_name(group, index), choices)


def _parameter_name(group: Sequence[Rule], index: int) -> str:
    for rule in group:
        named = _comment_names(rule)
        if named is not None and index < len(named):
            return named[index]
    for rule in group:
        for plan in rule.plans:
            for step in plan.steps:
                for pname, value in step.parameters:
                    match = _PARAMETER_TOKEN.match(value)
                    if match and int(match.group(1)) == index + 1:
                        return _identifier(pname[:1].lower() + pname[1:])
    return f"parameter{index + 1}"


def _comment_names(rule: Rule) -> list[str] | None:
    """The parameters' names a rule's comment gives (``Say <speechAct> <addressee>: ...``), when
    the comment starts with this action's name followed by exactly as many ``<names>``."""
    match = _FORM.match(rule.description)
    if match is None or match.group("name").rstrip(":") != rule.name:
        return None
    names = [_identifier(n) for n in _ANGLED.findall(match.group("params"))]
    return names if len(names) == len(rule.parameters) else None


def _identifier(text: str) -> str:
    cleaned = _TOOL_CHARACTERS.sub("_", text.strip())[:_MAX_TOOL]
    return cleaned or "parameter"


def _description(group: Sequence[Rule]) -> str:
    comments = list(dict.fromkeys(r.description for r in group if r.description))
    if comments:
        text = " ".join(comments)
    else:
        plans = [" then ".join(dict.fromkeys(s.type for s in plan.topological_order())) or "nothing" for r in group for plan in r.plans]
        text = f"{group[0].name}: runs " + "; or else ".join(dict.fromkeys(plans))
    return text if len(text) <= _MAX_DESCRIPTION else text[: _MAX_DESCRIPTION - 1] + "…"
