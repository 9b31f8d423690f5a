"""Competency manager rules: which competency execution plans can realise an action sent by a mind.

Vocabulary (CMION 2011, ``CompetencyManagerRules.dtd``):

* a **mind action** is what a mind asks the body to do: a name, positional string parameters and
  the acting subject (``MindAction``);
* a **rule** pairs a mind-action *pattern* with one or more competency execution **plans**; the
  pattern's name and each parameter are a literal or ``*`` (anything), and a rule matches only
  actions with exactly as many parameters as it lists;
* a **plan** is a set of **steps** (``<Competency>``): each names a competency *type* from the
  competency library, run parameters, and the IDs of steps it waits for.  Steps whose
  dependencies have all succeeded run in parallel; at least one step has no dependency.

Specificity: ``RuleSet.candidates`` returns every matching rule, fewest wildcards first (a
``Name="*"`` counts as one wildcard, like a ``*`` parameter; ``Subject`` does not count), ties in
file order.  The execution system tries the first candidate's plans and, when a plan fails, falls
back to the next plan of the same rule, then to the next candidate, until one succeeds or all
have failed.

Substitution (``substitute``), done when a step *starts*, so blackboard and world-model values
are those current at that moment, not at action arrival:

* ``$subject``, ``$action`` - the action's subject and name;
* ``$parameterN`` - the action's N-th parameter (from 1); ``$parameter1`` never touches
  ``$parameter10``;
* ``$BB(name)`` - a blackboard value; ``name`` may be a ``container/property`` path and may not
  contain parentheses;
* ``$WM(entity.property)`` - a world-model value; the *first* dot separates entity from property,
  so entity names cannot contain a dot there (property names may); ``$WM(entity/property)`` is
  the same, its dots literal (``keys.store_path``: the grammar of every world-model path).

A value that is exactly one token yields the looked-up value with its own type (an ``int`` from
the blackboard stays an ``int``); otherwise each token is replaced by ``str(value)`` in one pass,
so text coming from a substitution is never itself substituted.  Other ``$`` text is left alone.

Differences from CMION 2011:

* a rule may hold several alternative plans, tried in file order (the DTD allows one);
* ``MindAction/@Subject`` (optional) restricts a rule to one subject;
* ``$BB(...)`` and ``$WM(...)`` tokens are new;
* files are checked when loaded, not when an action first needs them: parameter numbers must run
  1..n, step IDs must be unique, dependencies must exist and be acyclic, and no step may use a
  ``$parameterN`` the rule can never supply.  Each fault is a ``ConfigError`` naming file and line.
  A step whose competency type nothing provides is not one of them: CMION loaded such a rule and
  the action failed when it ran, and so it is here (``validate`` and ``up`` warn, ``type_problems``;
  the manager fails the action with the same words, ``missing_types``);
* a plan with no steps is allowed (the DTD says ``Competency*``) and trivially succeeds;
* ``Rule.index`` counts from 0, so ``ruleset.rules[rule.index] is rule``.
"""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Callable, Collection, Iterable
from typing import Any

import msgspec
from lxml import etree

from cmion_mesh import keys, xmlsafe
from cmion_mesh.errors import ConfigError, InvalidName, PlanError, StorageError
from cmion_mesh.mind import MindAction

__all__ = [
    "SCHEMA",
    "WILDCARD",
    "Plan",
    "Rule",
    "RuleSet",
    "Step",
    "load_rules",
    "missing_types",
    "needs",
    "parse_rules",
    "substitute",
    "substitute_step",
]

SCHEMA = "CompetencyManagerRules.xsd"
WILDCARD = "*"

# One alternation so a single left-to-right pass finds every token and nothing is substituted twice.
# The look-aheads make tokens exact: ``$parameter1`` must not eat the prefix of ``$parameter10``, nor
# ``$subject`` the prefix of ``$subjects``.
_TOKEN = re.compile(
    r"\$(?:"
    r"(?P<word>subject|action)(?![A-Za-z0-9_])"
    r"|parameter(?P<index>\d+)(?!\d)"
    r"|BB\((?P<bb>[^()]*)\)"
    r"|WM\((?P<wm>[^()]*)\)"
    r")"
)
# Openers of the bracketed tokens: one left over after tokenising is an unterminated or nested
# token, which would otherwise silently reach the competency as literal text.
_OPENER = re.compile(r"\$(?:BB|WM)\(")


class Step(msgspec.Struct, frozen=True):
    """One ``<Competency>`` of a plan; ``parameters`` are (Name, Value) pairs in file order."""

    id: str
    type: str
    dependencies: tuple[str, ...]
    parameters: tuple[tuple[str, str], ...]
    line: int


class Plan(msgspec.Struct, frozen=True):
    """A competency execution plan: steps forming a dependency DAG (checked on load)."""

    steps: tuple[Step, ...]
    line: int

    def roots(self) -> tuple[Step, ...]:
        """Steps with no dependency, in file order: they start as soon as the plan does."""
        return tuple(s for s in self.steps if not s.dependencies)

    def step(self, id: str) -> Step:
        """The step with ID ``id``; ``KeyError`` if the plan has none."""
        for s in self.steps:
            if s.id == id:
                return s
        raise KeyError(id)

    def topological_order(self) -> tuple[Step, ...]:
        """Every step after all of its dependencies; among steps ready together, file order.

        ``PlanError`` if the plan has a cycle or an unknown dependency (only possible for a plan
        built by hand: loaded plans are checked).
        """
        by_id = {s.id: s for s in self.steps}
        waiting: dict[str, set[str]] = {}
        for s in self.steps:
            unknown = [d for d in s.dependencies if d not in by_id]
            if unknown:
                raise PlanError(f"step {s.id} depends on unknown step {unknown[0]}")
            waiting[s.id] = set(s.dependencies)
        order: list[Step] = []
        done: set[str] = set()
        while len(order) < len(self.steps):
            ready = [s for s in self.steps if s.id not in done and not waiting[s.id] - done]
            if not ready:
                left = [s.id for s in self.steps if s.id not in done]
                raise PlanError(f"dependency cycle among steps {', '.join(left)}")
            order.extend(ready)
            done.update(s.id for s in ready)
        return tuple(order)


class Rule(msgspec.Struct, frozen=True):
    """A mind-action pattern and its alternative plans.  ``index`` is the file position, from 0."""

    index: int
    name: str
    parameters: tuple[str, ...]
    subject: str | None
    plans: tuple[Plan, ...]
    path: str
    line: int
    # The XML comment just before the rule (how CMION's files document a rule), whitespace folded:
    # what a language-model mind or an MCP client is told the action does (``body/abilities.py``).
    description: str = ""

    @property
    def wildcards(self) -> int:
        """How many ``*`` the pattern has (name and parameters): fewer means more specific."""
        return (self.name == WILDCARD) + sum(p == WILDCARD for p in self.parameters)

    def matches(self, action: MindAction) -> bool:
        """True if ``action`` fits the pattern; the parameter count must be equal (CMION)."""
        if self.name not in (WILDCARD, action.name):
            return False
        if len(self.parameters) != len(action.parameters):
            return False
        if any(p not in (WILDCARD, a) for p, a in zip(self.parameters, action.parameters, strict=True)):
            return False
        return self.subject is None or self.subject in (WILDCARD, action.subject)

    def describe(self) -> str:
        """The pattern as text, e.g. ``"TestAction *"`` or ``"Talk * * (subject Greta)"``."""
        return _describe(self.name, self.parameters, self.subject)


class RuleSet(msgspec.Struct, frozen=True):
    """The rules of one file, in file order."""

    rules: tuple[Rule, ...]
    path: str

    def candidates(self, action: MindAction) -> list[Rule]:
        """Every rule matching ``action``, most specific (fewest wildcards) first, ties in file order."""
        return sorted((r for r in self.rules if r.matches(action)), key=lambda r: (r.wildcards, r.index))

    def actions(self) -> list[str]:
        """The action patterns covered, for discovery: e.g. ``["TestAction test", "TestAction *"]``.

        File order, each pattern once.
        """
        return list(dict.fromkeys(r.describe() for r in self.rules))

    def why_no_match(self, action: MindAction) -> str:
        """Why no rule matches ``action``: what the rules of that name accept (``*`` = anything), or
        the action names there are, with a ``did you mean``."""
        same = list(dict.fromkeys(r.describe() for r in self.rules if r.name in (action.name, WILDCARD)))
        if same:
            return f"the rules accept: {'; '.join(same)}"
        names = sorted({r.name for r in self.rules})
        close = difflib.get_close_matches(action.name, names, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        return f"no rule is named {action.name!r} (actions: {', '.join(names) or 'none'}){hint}"

    def types(self) -> set[str]:
        """Every competency type some step uses."""
        return {s.type for r in self.rules for p in r.plans for s in p.steps}

    def check_types(self, available: Collection[str]) -> None:
        """``ConfigError`` at the first step (file order) whose type no competency in ``available``
        provides. ``validate`` and ``up`` do not refuse such a rule (CMION loaded it, and the action
        failed when it ran): they warn with ``type_problems``; this is for code that wants the refusal."""
        problems = self.type_problems(available)
        if problems:
            raise problems[0]

    def type_problems(self, available: Collection[str]) -> list[ConfigError]:
        """Every step (file order) whose type no competency in ``available`` provides, at its line,
        naming the rule and the closest available types (a misspelling, most often): the words of
        the action's failure when it runs (``missing_types``)."""
        return [
            ConfigError(f"rule {rule.describe()!r}, plan {number}: {needs(s, available)}", path=self.path, line=s.line)
            for rule in self.rules for number, plan in enumerate(rule.plans, start=1) for s in plan.steps if s.type not in available
        ]

    def type_lines(self) -> dict[str, list[int]]:
        """Each competency type some step uses, with the lines of those steps (file order)."""
        lines: dict[str, list[int]] = {}
        for rule in self.rules:
            for plan in rule.plans:
                for s in plan.steps:
                    lines.setdefault(s.type, []).append(s.line)
        return lines


def needs(step: Step, available: Collection[str]) -> str:
    """Why ``step`` cannot run here, with the closest of the ``available`` types."""
    close = difflib.get_close_matches(step.type, sorted(set(available)), n=3)
    closest = f" (closest: {', '.join(repr(c) for c in close)})" if close else ""
    return f"step {step.id} needs competency type {step.type!r}, which no competency of this embodiment provides{closest}"


def missing_types(plan: Plan, available: Collection[str]) -> str | None:
    """Why ``plan`` cannot run with the competency types ``available`` (each missing type once, at
    its first step), or None when it can."""
    first: dict[str, Step] = {}
    for s in plan.steps:
        if s.type not in available:
            first.setdefault(s.type, s)
    return "; ".join(needs(s, available) for s in first.values()) or None


# --- loading --------------------------------------------------------------------------------------


def load_rules(path: str | os.PathLike[str], problems: list[ConfigError] | None = None) -> RuleSet:
    """Read, schema-check and semantically check a competency manager rules file.

    With ``problems``, a rule at fault is left out and its error appended there, so that every
    faulty rule is reported in one run (the schema was checked by the caller, ``validate``)."""
    name = os.fspath(path)
    return _parse(xmlsafe.load(name, SCHEMA, comments=True), name, problems)


def parse_rules(tree: etree._ElementTree, path: str, problems: list[ConfigError] | None = None) -> RuleSet:
    """Check an already parsed rules document (schema, then semantics); ``path`` names it in errors.
    ``problems``: as for ``load_rules``."""
    xmlsafe.validate(tree, SCHEMA, path)
    return _parse(tree, path, problems)


def _line(element: etree._Element) -> int:
    return xmlsafe.sourceline(element) or 0


def _children(element: etree._Element, tag: str) -> list[etree._Element]:
    return [c for c in element if c.tag == tag]


def _attr(element: etree._Element, name: str, path: str) -> str:
    value = element.get(name)
    if value is None:  # the schema requires it; kept for trees that bypass validation
        raise ConfigError(f"<{element.tag}> lacks attribute {name}", path=path, line=_line(element))
    return value


def _describe(name: str, parameters: Iterable[str], subject: str | None) -> str:
    def shown(text: str) -> str:
        # Quote only what would make the space-separated form ambiguous.
        return f'"{text}"' if not text or any(c.isspace() for c in text) or '"' in text else text

    text = " ".join([shown(name), *(shown(p) for p in parameters)])
    return text if subject is None else f"{text} (subject {shown(subject)})"


def _parse(tree: etree._ElementTree, path: str, problems: list[ConfigError] | None = None) -> RuleSet:
    root = tree.getroot()
    if root.tag != "CompetencyManagerRules":
        raise ConfigError(f"root element is <{root.tag}>, expected <CompetencyManagerRules>", path=path, line=_line(root))
    rules: list[Rule] = []
    for element in _children(root, "Rule"):
        try:
            rules.append(_parse_rule(len(rules), element, path))
        except ConfigError as exc:
            if problems is None:
                raise
            problems.append(exc)
    return RuleSet(tuple(rules), path)


def _parse_rule(index: int, element: etree._Element, path: str) -> Rule:
    actions = _children(element, "MindAction")
    if len(actions) != 1:
        raise ConfigError("<Rule> needs exactly one <MindAction>", path=path, line=_line(element))
    action = actions[0]
    name = _attr(action, "Name", path)
    if not name:
        raise ConfigError("MindAction Name is empty; use * to match any action", path=path, line=_line(action))
    subject = action.get("Subject")
    parameters = _parse_parameters(action, f"MindAction {name!r}", path)
    label = f"rule {_describe(name, parameters, subject)!r}"
    plan_elements = _children(element, "CompetencyExecutionPlan")
    if not plan_elements:
        raise ConfigError(f"{label} has no <CompetencyExecutionPlan>", path=path, line=_line(element))
    plans = tuple(
        _parse_plan(plan, f"{label}, plan {number}", len(parameters), path) for number, plan in enumerate(plan_elements, start=1)
    )
    return Rule(index, name, parameters, subject, plans, path, _line(element), _comment_before(element))


def _comment_before(element: etree._Element) -> str:
    """The text of the comment right before ``element`` (only whitespace between), folded to one line."""
    previous = element.getprevious()
    if not isinstance(previous, etree._Comment):
        return ""
    return " ".join((previous.text or "").split())


def _parse_parameters(action: etree._Element, label: str, path: str) -> tuple[str, ...]:
    elements = _children(action, "Parameter")
    count = len(elements)
    by_number: dict[int, tuple[str, int]] = {}
    for p in elements:
        raw = _attr(p, "No", path)
        line = _line(p)
        try:
            number = int(raw.strip())
        except ValueError:
            raise ConfigError(f"{label}: Parameter No {raw!r} is not a whole number", path=path, line=line) from None
        if number in by_number:
            raise ConfigError(f"{label}: Parameter No {number} already used at line {by_number[number][1]}", path=path, line=line)
        by_number[number] = (_attr(p, "Value", path), line)
    # With the numbers distinct, they are exactly 1..n iff none lies outside that range.
    for p in elements:
        number = int(_attr(p, "No", path).strip())
        if not 1 <= number <= count:
            raise ConfigError(
                f"{label}: Parameter No {number} is out of range: the action has {count} parameter(s), numbered 1..{count} with no gaps",
                path=path,
                line=_line(p),
            )
    return tuple(by_number[n][0] for n in range(1, count + 1))


def _parse_plan(element: etree._Element, label: str, parameter_count: int, path: str) -> Plan:
    steps: list[Step] = []
    seen: dict[str, int] = {}
    for c in _children(element, "Competency"):
        line = _line(c)
        step_id = _attr(c, "ID", path)
        if not step_id or step_id != step_id.strip() or "," in step_id:
            raise ConfigError(
                f"{label}: step ID {step_id!r} cannot be referenced by a Dependency list (empty, padded or containing a comma)",
                path=path,
                line=line,
            )
        if step_id in seen:
            raise ConfigError(f"{label}: step ID {step_id} already used at line {seen[step_id]}", path=path, line=line)
        seen[step_id] = line
        step_type = _attr(c, "Type", path)
        if not step_type.strip():
            raise ConfigError(f"{label}: step {step_id} has an empty Type", path=path, line=line)
        steps.append(
            Step(
                step_id,
                step_type,
                _parse_dependencies(c.get("Dependency", ""), f"{label}: step {step_id}", path, line),
                _parse_step_parameters(c, f"{label}: step {step_id}", parameter_count, path),
                line,
            )
        )
    plan = Plan(tuple(steps), _line(element))
    _check_graph(plan, label, path)
    return plan


def _parse_dependencies(raw: str, label: str, path: str, line: int) -> tuple[str, ...]:
    if not raw.strip():
        return ()
    items = [item.strip() for item in raw.split(",")]
    if "" in items:
        raise ConfigError(f"{label}: Dependency {raw!r} has an empty item", path=path, line=line)
    # A repeated ID is harmless (waiting twice for one step is waiting once).
    return tuple(dict.fromkeys(items))


def _parse_step_parameters(element: etree._Element, label: str, parameter_count: int, path: str) -> tuple[tuple[str, str], ...]:
    pairs: list[tuple[str, str]] = []
    seen: dict[str, int] = {}
    for p in _children(element, "CompetencyParameter"):
        line = _line(p)
        name = _attr(p, "Name", path)
        value = _attr(p, "Value", path)
        if name in seen:
            # Run parameters become a dict: a second value would silently replace the first.
            raise ConfigError(f"{label}: parameter {name!r} already given at line {seen[name]}", path=path, line=line)
        seen[name] = line
        problem = _token_problem(value, parameter_count)
        if problem is not None:
            raise ConfigError(f"{label}: parameter {name!r}: {problem}", path=path, line=line)
        pairs.append((name, value))
    return tuple(pairs)


def _token_problem(value: str, parameter_count: int) -> str | None:
    """Why a value's tokens could never be substituted, or ``None`` if they all can."""
    rest: list[str] = []
    end = 0
    for match in _TOKEN.finditer(value):
        rest.append(value[end : match.start()])
        end = match.end()
        token = match.group(0)
        index, bb, wm = match.group("index"), match.group("bb"), match.group("wm")
        if index is not None and not 1 <= int(index) <= parameter_count:
            if parameter_count == 0:
                usable = "it has none"
            elif parameter_count == 1:
                usable = "only $parameter1 exists"
            else:
                usable = f"$parameter1..$parameter{parameter_count} exist"
            return f"{token} can never be substituted: the rule's action has {parameter_count} parameter(s), {usable}"
        if bb is not None and not bb.strip():
            return f"{token} names no blackboard property"
        if wm is not None and _split_wm(wm) is None:
            return f"{token} must be $WM(entity.property)"
    rest.append(value[end:])
    leftover = _OPENER.search("".join(rest))
    if leftover is not None:
        return f"unterminated or nested {leftover.group(0)}...) in {value!r}; names may not contain parentheses"
    return None


def _split_wm(inner: str) -> tuple[str, str] | None:
    """``(container, property)`` of a ``$WM(...)`` path, as every read and write of the world model
    takes it (``keys.store_path``); None unless it names a property of an entity."""
    try:
        container, name = keys.property_path(keys.WORLD_MODEL, inner)
    except InvalidName:
        return None
    return (container, name) if container else None


def _check_graph(plan: Plan, label: str, path: str) -> None:
    """Dependencies exist, none is a self-dependency, and there is no cycle (hence a root exists)."""
    by_id = {s.id: s for s in plan.steps}
    for s in plan.steps:
        for d in s.dependencies:
            if d == s.id:
                raise ConfigError(f"{label}: step {s.id} depends on itself", path=path, line=s.line)
            if d not in by_id:
                known = ", ".join(by_id)
                raise ConfigError(f"{label}: step {s.id} depends on unknown step {d} (steps: {known})", path=path, line=s.line)
    cycle = _find_cycle(plan)
    if cycle is not None:
        # Start the named cycle at its member earliest in the file, so the message and line are stable.
        position = {s.id: i for i, s in enumerate(plan.steps)}
        ring = cycle[:-1]
        start = min(range(len(ring)), key=lambda i: position[ring[i]])
        ring = ring[start:] + ring[:start]
        shown = " -> ".join([*ring, ring[0]])
        prefix = "" if plan.roots() else "no step without dependencies; "
        raise ConfigError(
            f"{label}: {prefix}dependency cycle {shown} (each step waits for the next)",
            path=path,
            line=by_id[ring[0]].line,
        )


def _find_cycle(plan: Plan) -> list[str] | None:
    """A dependency cycle as IDs with the first repeated at the end, or ``None``; iterative DFS."""
    deps = {s.id: s.dependencies for s in plan.steps}
    state: dict[str, int] = {}  # absent: unvisited, 1: on the current path, 2: finished
    for start in deps:
        if start in state:
            continue
        stack: list[tuple[str, int]] = [(start, 0)]
        trail = [start]
        state[start] = 1
        while stack:
            node, i = stack[-1]
            if i < len(deps[node]):
                stack[-1] = (node, i + 1)
                nxt = deps[node][i]
                if state.get(nxt) == 1:
                    return [*trail[trail.index(nxt) :], nxt]
                if nxt not in state:
                    state[nxt] = 1
                    stack.append((nxt, 0))
                    trail.append(nxt)
            else:
                state[node] = 2
                stack.pop()
                trail.pop()
    return None


# --- substitution ---------------------------------------------------------------------------------


def substitute(value: str, action: MindAction, *, bb: Callable[[str], Any], wm: Callable[[str, str], Any]) -> Any:
    """``value`` with its ``$`` tokens replaced (see the module docstring).

    ``bb(name)`` reads the blackboard, ``wm(entity, property)`` the world model; either raising
    ``LookupError`` (``KeyError``...) or ``StorageError`` becomes a ``PlanError`` naming the token,
    as does a ``$parameterN`` the action does not have.
    """

    def lookup(match: re.Match[str]) -> Any:
        token = match.group(0)
        word, index, bb_name, wm_inner = match.group("word", "index", "bb", "wm")
        if word == "subject":
            return action.subject
        if word == "action":
            return action.name
        try:
            if index is not None:
                number = int(index)
                if not 1 <= number <= len(action.parameters):
                    raise PlanError(f"{token}: action {action.name!r} has {len(action.parameters)} parameter(s)")
                return action.parameters[number - 1]
            if bb_name is not None:
                return bb(bb_name)
            parts = _split_wm(wm_inner)
            if parts is None:
                raise PlanError(f"{token}: must be $WM(entity.property)")
            return wm(*parts)
        except (LookupError, StorageError) as exc:
            raise PlanError(f"{token}: no value ({_reason(exc)})") from exc

    whole = _TOKEN.fullmatch(value)
    if whole is not None:
        return lookup(whole)
    return _TOKEN.sub(lambda m: str(lookup(m)), value)


def _reason(exc: BaseException) -> str:
    # str(KeyError('x')) is "'x'", which reads as noise; name the missing key instead.
    if isinstance(exc, KeyError) and len(exc.args) == 1:
        return f"{type(exc).__name__}: {exc.args[0]!r} not found"
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def substitute_step(
    step: Step, action: MindAction, *, bb: Callable[[str], Any], wm: Callable[[str, str], Any]
) -> dict[str, Any]:
    """The run parameters of ``step`` for ``action``, substituted now; ``PlanError`` names step and token."""
    result: dict[str, Any] = {}
    for name, value in step.parameters:
        try:
            result[name] = substitute(value, action, bb=bb, wm=wm)
        except PlanError as exc:
            raise PlanError(f"step {step.id} ({step.type}), parameter {name!r}: {exc}") from exc
    return result
