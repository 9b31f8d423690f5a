"""CMION's agent-mind line protocol, pure: the connector's options and FAtiMA's lines, written and read.

Nothing here touches a socket or the update loop (``link`` carries the lines, ``connector`` acts on
them); see ``docs/fatima.md`` for the conversation these lines make up.

**Options** (words of the constructor parameters, separated by spaces or commas, any order):
CMION's ``modular`` (FAtiMA-Modular: ``PROPERTY-CHANGED * e(p) v``; without it the old
``PROPERTY-CHANGED e(p) v``), ``persistent`` (``PROPERTY-CHANGED-PERSISTENT``/``-NONPERSISTENT``
with ``modular``, and ``P:``/``NP:`` pairs in ``LOOK-AT``), ``migrating`` (the mind's state
migrates) and ``sleeping`` (accepted; the migration manager decides when the mind sleeps). Our
extensions: ``port:N`` (default 46874, or ``CMION_MESH_FATIMA_PORT`` when set; ``port:0`` takes a free port, written to the blackboard as
``<name>/port``), ``host:ADDR`` (default 127.0.0.1; ``host:0.0.0.0`` for every interface),
``name:N`` (the component's name, default ``fatima``), ``stop-wait:S`` (seconds between ``CMD Stop``
and ``CMD GET-STATE``, default 0.5; CMION waited 2), ``state-timeout:S`` (how long FAtiMA may
take to answer ``GET-STATE``/``SET-STATE``, default 4; with ``migrating``, the two must add up to
less than the migration's ``SECTION_DEADLINE``) and ``handshake-timeout:S`` (how long a new
connection may take to send its handshake, default 5). An unknown word is a configuration error.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import msgspec

from cmion_mesh import keys, xmlsafe
from cmion_mesh.errors import MeshError, ProtocolError
from cmion_mesh.migration.outgoing import SECTION_DEADLINE

DEFAULT_PORT = 46874
#: The port a connector listens on when its parameters name none (instead of ``DEFAULT_PORT``).
PORT_VARIABLE = "CMION_MESH_FATIMA_PORT"
DEFAULT_HOST = "127.0.0.1"
#: Longest line accepted from the mind (a STATE line of CMION's minds is 34-46 k characters).
MAX_LINE = 16 * 1024 * 1024
#: Seconds a new connection has to send its handshake (its first line), by default (option
#: ``handshake-timeout:S``): beyond, it is closed. Until its handshake a connection is only pending:
#: it never holds the mind's place, so one that sends a few bytes and stops keeps nobody out.
HANDSHAKE_TIMEOUT = 5.0
#: Sent as the body stops: FAtiMA compares the command with "Save" (CMION sent "SAVE", which it ignored).
SAVE_COMMAND = "CMD Save"
#: Subjects in the semantic memory that CMION did not copy into the world model.
_NOT_ENTITIES = frozenset({"ProbBias", "IOS", "IOF", "ActionContext", ""})

#: An action as the mind names it: its name and its parameters (what a retry repeats exactly).
ActionKey = tuple[str, tuple[str, ...]]


# --- options ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Options:
    modular: bool = False
    persistent: bool = False
    migrating: bool = False
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    name: str = "fatima"
    stop_wait: float = 0.5
    state_timeout: float = 4.0
    handshake_timeout: float = HANDSHAKE_TIMEOUT


_FLAGS = ("modular", "persistent", "migrating", "sleeping")


def parse_options(parameters: Sequence[str]) -> Options:
    """CMION's option words plus our ``key:value`` extensions; ``MeshError`` naming a bad word."""
    flags: set[str] = set()
    values: dict[str, Any] = {}
    for word in " ".join(parameters).replace(",", " ").split():
        key, sep, raw = word.partition(":")
        key = key.lower()
        if not sep:
            if key not in _FLAGS:
                raise MeshError(f"unknown option {word!r} of the FAtiMA connector (known: {', '.join(_FLAGS)}, port:N, host:ADDR, "
                                "name:N, stop-wait:S, state-timeout:S, handshake-timeout:S)")
            flags.add(key)
            continue
        try:
            if key == "port":
                port = int(raw)
                if not 0 <= port <= 65535:
                    raise ValueError("not a TCP port")
                values["port"] = port
            elif key == "host":
                if not raw:
                    raise ValueError("empty")
                values["host"] = raw
            elif key == "name":
                values["name"] = keys.check_name(raw, "component")
            elif key in ("stop-wait", "state-timeout"):
                seconds = float(raw)
                if not 0.0 <= seconds <= 600.0:
                    raise ValueError("not a number of seconds from 0 to 600")
                values[key.replace("-", "_")] = seconds
            elif key == "handshake-timeout":
                seconds = float(raw)
                if not 0.0 < seconds <= 600.0:  # 0 would close every connection before its handshake
                    raise ValueError("not a number of seconds above 0, up to 600")
                values["handshake_timeout"] = seconds
            else:
                raise ValueError("unknown option")
        except ValueError as exc:
            raise MeshError(f"option {word!r} of the FAtiMA connector: {exc}") from None
    if "port" not in values and os.environ.get(PORT_VARIABLE, "").strip():
        # CMION's files leave the port to the code (46874): two embodiments on one machine need another.
        raw = os.environ[PORT_VARIABLE].strip()
        if not raw.isdigit() or int(raw) > 65535:
            raise MeshError(f"{PORT_VARIABLE}={raw!r} is not a TCP port")
        values["port"] = int(raw)
    options = Options(modular="modular" in flags, persistent="persistent" in flags, migrating="migrating" in flags, **values)
    if options.migrating and options.stop_wait + options.state_timeout >= SECTION_DEADLINE:
        # Past the migration manager's deadline the migration is abandoned with a vaguer reason
        # ("components ... did not give their sections") while the connector still waits.
        raise MeshError(f"options stop-wait:{options.stop_wait:g} and state-timeout:{options.state_timeout:g} of the FAtiMA "
                        f"connector add up to {options.stop_wait + options.state_timeout:g} s: with 'migrating' they must stay "
                        f"under the {SECTION_DEADLINE:g} s a migration gives each component for its section")
    return options


# --- the protocol's lines (pure functions) ---------------------------------------------------------


def format_value(value: Any) -> str:
    """A world-model value as CMION wrote it: ``True``/``False`` for booleans, JSON for structures;
    never a line break (a value must not end the line)."""
    if isinstance(value, bool):
        text = "True" if value else "False"
    elif value is None:
        text = "null"
    elif isinstance(value, str):
        text = value
    elif isinstance(value, (int, float)):
        text = repr(value)
    else:
        text = msgspec.json.encode(value).decode()
    return text.replace("\r", " ").replace("\n", " ") if ("\n" in text or "\r" in text) else text


def _token(text: str) -> str:
    """One space-free token (``LOOK-AT`` pairs are split on spaces by the mind)."""
    return "_".join(text.split()) if any(c.isspace() for c in text) else text


def action_text(name: str, parameters: Iterable[str]) -> str:
    return " ".join((name, *parameters))


def property_changed_line(entity: str, name: str, value: Any, persistent: bool, options: Options) -> str:
    if not options.modular:
        return f"PROPERTY-CHANGED {entity}({name}) {format_value(value)}"
    command = "PROPERTY-CHANGED"
    if options.persistent:
        command += "-PERSISTENT" if persistent else "-NONPERSISTENT"
    return f"{command} * {entity}({name}) {format_value(value)}"


def look_at_line(entity: str, properties: Mapping[str, Any], persistent_pairs: bool) -> str:
    """``LOOK-AT e p:v ...`` from a ``Store.tree`` node's ``properties`` ({name: {value, persistent}})."""
    parts = [f"LOOK-AT {entity}"]
    for name, prop in properties.items():
        value = prop.get("value") if isinstance(prop, Mapping) else prop
        mark = ("P:" if isinstance(prop, Mapping) and prop.get("persistent") else "NP:") if persistent_pairs else ""
        parts.append(f"{mark}{_token(name)}:{_token(format_value(value))}")
    return " ".join(parts)


@dataclass(frozen=True)
class Handshake:
    agent: str
    role: str
    display_name: str
    properties: dict[str, str]


#: First words of the mind's other lines: a first line starting with one is not a handshake.
_NOT_AGENT_NAMES = frozenset({"look-at", "CANCEL-ACTION", "STATE", "STATE-SET", "PROPERTY-CHANGED"})


def parse_handshake(line: str) -> Handshake:
    """``<agentName> <role> <displayName> k:v ...``; ``ProtocolError`` saying what is wrong otherwise."""

    def bad(why: str) -> ProtocolError:
        return ProtocolError(f"the first line must be the handshake '<agentName> <role> <displayName> k:v ...': {why}; "
                             f"got {line[:120]!r}")

    tokens = line.split()
    if len(tokens) < 3:
        raise bad(f"{len(tokens)} word(s), not at least 3")
    agent, role, display = tokens[:3]
    if agent in _NOT_AGENT_NAMES or agent.startswith("<"):
        raise bad(f"{agent!r} starts another message of the protocol")
    if not keys.is_name(agent):
        raise bad(f"agent name {agent!r} is not a valid name (no / * $ # ? nor a leading @)")
    for what, word in (("agent name", agent), ("role", role), ("display name", display)):
        if ":" in word:
            raise bad(f"the {what} {word!r} is a k:v pair (a name is missing)")
    properties: dict[str, str] = {}
    for pair in tokens[3:]:
        name, sep, value = pair.partition(":")
        if not sep or not keys.is_name(name):
            raise bad(f"{pair!r} is not a property 'name:value' with a valid name")
        properties[name] = value
    return Handshake(agent, role, display, properties)


def parse_emotional_state(line: str, where: str) -> dict[str, Any]:
    """``{"mood": float or text, "emotions": [attributes of each Emotion element]}``; ``XmlError``."""
    root = xmlsafe.loads(line.encode("utf-8"), None, name=where, max_bytes=MAX_LINE).getroot()
    mood_text = root.findtext("Mood")
    mood: Any = None
    if mood_text is not None:
        try:
            mood = float(mood_text)
        except ValueError:
            mood = mood_text.strip()
    emotions = [dict(el.attrib) for el in root.iter("Emotion")]
    return {"mood": mood, "emotions": emotions}


def parse_semantic_memory(line: str, agent: str, where: str) -> list[tuple[str, str, str, bool]]:
    """``(entity, property, value, persistent)`` of each ``<Property name="E(p)" .../>``, ``SELF``
    read as ``agent``, FAtiMA's own bookkeeping (``ProbBias``, ``IOS``, ``IOF``, ``ActionContext``)
    left out, as CMION did; ``XmlError`` if the line is not XML."""
    root = xmlsafe.loads(line.encode("utf-8"), None, name=where, max_bytes=MAX_LINE).getroot()
    found = []
    for el in root.iter("Property"):
        full = el.get("name", "")
        owner, sep, rest = full.partition("(")
        if not sep or not rest.endswith(")") or owner in _NOT_ENTITIES:
            continue
        found.append((agent if owner == "SELF" else owner, rest[:-1], el.get("value", ""),
                      el.get("persistent", "false").strip().lower() == "true"))
    return found

