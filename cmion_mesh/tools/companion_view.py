"""What an MCP client is offered of a companion, decided from plain data (``describe``, events).

The companion lives in one body at a time; its **tools** are that body's abilities
(``body/abilities.py``: one tool per action its rules accept, named and typed), plus the
companion's own ``migrate`` (to the embodiments its policy accepts, among those alive) and
``peers``. The body's built-in ``Migrate <target>`` ability is the same deed as ``migrate`` and is
not offered twice. Its **resources** are the world model and the blackboard of the body it lives
in now, under URIs that name the companion, not the body: a client that subscribed keeps
following the companion across migrations (each one is an update of both, and a change of the
list, whose titles name the new body).

Pure: no I/O, no SDK types; ``tools/mcp_server.py`` turns these into the protocol's messages.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Literal
from urllib.parse import quote

from cmion_mesh import keys
from cmion_mesh.body.abilities import Ability
from cmion_mesh.errors import InvalidArguments, MeshError

__all__ = [
    "MIGRATE",
    "PEERS",
    "ResourceSpec",
    "ToolSpec",
    "companion_resources",
    "companion_tools",
    "progress_message",
    "store_document",
]

MIGRATE = "migrate"
PEERS = "peers"
#: What each resource of a companion holds: (URI tail, store, title).
STORES: tuple[tuple[str, str, str], ...] = (("world-model", keys.WORLD_MODEL, "world model"),
                                            ("blackboard", keys.BLACKBOARD, "blackboard"))
ToolKind = Literal["action", "migrate", "peers"]


@dataclass(frozen=True, slots=True)
class ToolSpec:
    """One tool as offered: ``ability`` set for a body's action."""

    name: str
    description: str
    input_schema: dict[str, Any]
    kind: ToolKind
    read_only: bool
    ability: Ability | None = None

    def arguments(self, given: Mapping[str, Any] | None) -> tuple[str, ...]:
        """The positional parameters of a call (``InvalidArguments`` naming what is wrong)."""
        if self.ability is not None:
            return self.ability.positional(given)
        if self.kind == MIGRATE:
            target = (given or {}).get("target")
            unknown = sorted(set(given or {}) - {"target"})
            if unknown:
                raise InvalidArguments(f"migrate: unknown argument(s) {', '.join(unknown)}; it takes (target)")
            if not isinstance(target, str) or not target:
                raise InvalidArguments("migrate: argument 'target' (an embodiment's name) is missing")
            choices = self.input_schema["properties"]["target"].get("enum")
            if choices is not None and target not in choices:
                raise InvalidArguments(f"migrate: {target!r} is not an embodiment the companion may move to now; "
                                       f"one of {', '.join(choices) or '(none)'}")
            return (target,)
        if given:
            raise InvalidArguments(f"{self.name}: takes no arguments")
        return ()


@dataclass(frozen=True, slots=True)
class ResourceSpec:
    uri: str
    name: str
    title: str
    description: str
    store: str
    embodiment: str


def resource_uri(companion: str, tail: str) -> str:
    return f"cmion-mesh://{quote(companion, safe='')}/{tail}"


def companion_tools(companion: str, description: Mapping[str, Any], *, alive: Iterable[str],
                    policy: Iterable[str] | None) -> list[ToolSpec]:
    """The tools of ``companion`` living in the body ``description`` describes.

    ``alive``: the embodiments alive now; ``policy``: the embodiments the companion accepts (None:
    any). Abilities that cannot be read (an older daemon, a malformed entry) are left out, never
    guessed. Names stay unique: an ability named like a companion tool gets a suffix.
    """
    host = str(description.get("name") or "")
    targets = sorted(set(alive) - {host} if policy is None else (set(alive) & set(policy)) - {host})
    tools = [
        ToolSpec(MIGRATE, f"Move {companion}, with its memory, from the body it lives in now ({host}) to another embodiment; "
                 "it then has that body's tools. Targets: the embodiments alive that its policy accepts.",
                 {"type": "object", "properties": {"target": {"type": "string", "enum": targets,
                                                              "description": "the embodiment to move to"}},
                  "required": ["target"], "additionalProperties": False}, "migrate", read_only=False),
        ToolSpec(PEERS, "The embodiments alive in the mesh: who lives where, and what each body can do.",
                 {"type": "object", "properties": {}, "additionalProperties": False}, "peers", read_only=True),
    ]
    used = {t.name.lower() for t in tools}
    for raw in description.get("abilities") or ():
        try:
            ability = Ability.from_json(raw)
        except MeshError:
            continue
        if ability.action == "Migrate" and len(ability.parameters) == 1:
            continue  # the built-in rule: ``migrate`` does it, with its targets listed
        name = ability.tool
        for n in range(1, 100):  # bounded: a handful of companion tools can clash
            if name.lower() not in used:
                break
            name = f"{ability.tool[:58]}_body{n if n > 1 else ''}"
        used.add(name.lower())
        patterns = "; ".join(ability.patterns)
        text = f"{ability.description} (an action of {host}: {patterns})" if patterns else ability.description
        tools.append(ToolSpec(name, text, ability.input_schema(), "action", read_only=False, ability=ability))
    return tools


def companion_resources(companion: str, host: str | None) -> list[ResourceSpec]:
    """The world model and blackboard of the body ``companion`` lives in (none while it is nowhere)."""
    if not host:
        return []
    return [ResourceSpec(resource_uri(companion, tail), tail, f"{companion}'s {label} (on {host})",
                         f"The {label} of {host}, the body {companion} lives in now, as JSON "
                         f"(path -> value). It follows {companion} when it migrates.", store, host)
            for tail, store, label in STORES]


def store_document(embodiment: str, store: str, entries: Mapping[str, Any], prefix: str) -> str:
    """A store's entries (``MeshClient.read_store``: key -> Property or Container) as one JSON text:
    ``{"embodiment", "store", "entries": {path: value}}``, a container's value ``{"container": kind}``."""
    out: dict[str, Any] = {}
    for key in sorted(entries):
        if not key.startswith(prefix + "/"):
            continue
        entry = entries[key]
        path = key[len(prefix) + 1:]
        value = getattr(entry, "value", None)
        kind = getattr(entry, "kind", None)
        out[path] = {"container": kind} if kind is not None and not hasattr(entry, "value") else value
    return json.dumps({"embodiment": embodiment, "store": store, "entries": out}, sort_keys=True, default=str)


def progress_message(event_name: str, component: str, data: Mapping[str, Any]) -> str | None:
    """A line for a progress notification from one event of an action's run (None: not worth one)."""
    if event_name == "Progress":
        progress = data.get("progress")
        if isinstance(progress, Mapping) and "step" in progress and "steps" in progress:
            where = f" to {progress['location']}" if "location" in progress else ""
            return f"{component}: step {progress['step']} of {progress['steps']}{where}"
        return f"{component}: {json.dumps(progress, default=str)}"
    if event_name in ("StepStarted", "StepSucceeded", "StepFailed", "StepCancelled"):
        what = str(data.get("type") or data.get("step") or "step")
        verb = {"StepStarted": "started", "StepSucceeded": "done", "StepFailed": "failed", "StepCancelled": "cancelled"}
        reason = f": {data['reason']}" if event_name == "StepFailed" and data.get("reason") else ""
        return f"{what} {verb[event_name]}{reason}"
    return None


def belongs_to(action_id: str, data: Any) -> bool:
    """Whether an event's data is about the run of action ``action_id`` (the manager names each
    attempt's plan run ``<action_id>#<n>``, and each step run below it)."""
    return isinstance(data, Mapping) and str(data.get("run_id", "")).startswith(f"{action_id}#")
