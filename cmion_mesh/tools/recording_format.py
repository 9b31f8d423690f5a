"""The channels the mesh is shown on, and their schemas: one place for a recording
(``tools/recording.py`` writes it) and the live Foxglove connection (``tools/foxglove.py``).

One channel per key pattern:

* events: one channel per event key ``cmion/<mesh>/<embodiment>/ev/<component>/<event>``
  (schema ``cmion_mesh.Event``). The migration handshake is here: each side's
  ``MigrationStep`` after every durable record, with ``MigrationStarting``/``Occurred``/
  ``Succeeded``/``Failed``/``Dropped``; so are mind actions (the manager's ``Action*`` events).
* storage changes: one channel per store, ``cmion/<mesh>/<embodiment>/bb/**`` and ``.../wm/**``
  (schema ``cmion_mesh.StorageSample``: the key, the property or container put, or a delete).
* liveliness: one channel per kind of token, ``cmion/<mesh>/@alive/*`` (embodiments),
  ``@claim``, ``@competency``, ``@custody`` (schema ``cmion_mesh.Liveliness``: comings and goings;
  the tokens alive when recording starts come first).
* requests and their outcomes: one channel per request key,
  ``cmion/<mesh>/<embodiment>/@outcome/<component>/<request>`` (schema ``cmion_mesh.RequestAnswered``:
  status, code, reason, sender). Requests are zenoh queries, which a passive subscriber never
  sees; each embodiment publishes how it answered one only while some session subscribes there
  (``requests.Answers``: one attribute read per request otherwise).
* the story as log lines, ``log:cmion/<mesh>`` (Foxglove's well-known schema ``foxglove.Log``,
  which its Log panel shows): embodiments coming and going, who holds which companion, the
  events of migrations, actions and plans, every event that says something failed, requests
  not accepted, samples not understood. Derived from the other channels, never instead of them.
* anything else under the recorded keys, and every payload that does not decode as what its key
  should carry, goes to ``raw:<key pattern>`` (schema ``cmion_mesh.RawSample``: the key and the
  bytes in base64), never lost.

Messages are JSON (``message_encoding`` ``json``) with a JSON Schema each, self-contained (no
``$ref``), ``"type": "object"`` at the root and a ``type`` on every field: what Foxglove's JSON
Schema reader requires (it throws on anything else, and does not follow ``$ref``). A plain value
(an event's ``data``, a property's ``value``), which may be any JSON value, is therefore written
in the one field its kind allows: ``data`` for a map, ``data_number``, ``data_string``,
``data_boolean``, or ``data_json`` (a list, as JSON text); none for null (``plain_fields``;
``plain_value`` reads it back). Files written before this (``FORMAT`` 1: ``data`` and ``value``
as they were, ``$ref`` schemas) read the same (``recorded_event``, ``event_data``).
JSON keeps every plain value a message can carry except non-finite floats (msgspec writes NaN
and infinities as ``null``). ``log_time`` is when the recorder received the message,
``publish_time`` the event's own ``time`` (the publisher's clock).

``PROFILE`` names the files this recorder wrote (the MCAP header's profile).
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import msgspec
from msgspec import UNSET, UnsetType

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.messages import Container, Event, Property, RequestAnswered, decode, decoder
from cmion_mesh.transport.base import BatchHandler, Closeable, LivelinessHandler, Sample, Transport

EVENT_SCHEMA = "cmion_mesh.Event"
STORAGE_SCHEMA = "cmion_mesh.StorageSample"
LIVELINESS_SCHEMA = "cmion_mesh.Liveliness"
RAW_SCHEMA = "cmion_mesh.RawSample"
ANSWER_SCHEMA = "cmion_mesh.RequestAnswered"
#: Foxglove's well-known schema of a log line (foxglove/foxglove-sdk, schemas/jsonschema/Log.json).
LOG_SCHEMA = "foxglove.Log"
#: Liveliness token kinds recorded, each one channel.
TOKEN_KINDS = (keys.ALIVE, keys.CLAIM, keys.COMPETENCY, keys.CUSTODY)
PROFILE = "cmion-mesh"
#: The format of the messages and schemas written (metadata ``cmion-mesh``, ``format``). 1 (no
#: ``format`` said): wire Structs as they are, schemas with ``$ref``; 2: as this module says.
FORMAT = 2


# --- plain values, in the one field their kind allows -----------------------------------------------


def plain_fields(prefix: str, value: Any) -> dict[str, Any]:
    """``value`` as the one field of its kind: ``{prefix: map}``, ``{prefix_number: 3}``... (none
    for null, or a float that is not finite: JSON has no such number)."""
    if value is None:
        return {}
    if isinstance(value, dict):
        return {prefix: value}
    if isinstance(value, bool):
        return {f"{prefix}_boolean": value}
    if isinstance(value, int):
        return {f"{prefix}_number": value}
    if isinstance(value, float):
        return {f"{prefix}_number": value} if math.isfinite(value) else {}
    if isinstance(value, str):
        return {f"{prefix}_string": value}
    return {f"{prefix}_json": _json.encode(value).decode()}


def plain_value(fields: dict[str, Any], prefix: str) -> Any:
    """The value ``plain_fields`` wrote (or, from a file of format 1, ``fields[prefix]`` as it is)."""
    if prefix in fields:
        return fields[prefix]
    for kind in ("number", "string", "boolean"):
        if f"{prefix}_{kind}" in fields:
            return fields[f"{prefix}_{kind}"]
    text = fields.get(f"{prefix}_json")
    return json.loads(text) if isinstance(text, str) else None


def event_data(event: dict[str, Any]) -> Any:
    """The ``data`` of a recorded event as decoded JSON (``Recorded.decoded()``), of either format."""
    return plain_value(event, "data")


# --- the messages of the channels --------------------------------------------------------------------

_Map = dict[str, Any]


class RecordedEvent(msgspec.Struct, frozen=True):
    """An ``Event`` as a channel carries it: its data in the one field of its kind (``plain_fields``)."""

    embodiment: str
    component: str
    name: str
    seq: int = 0
    time: float = 0.0
    data: _Map | UnsetType = UNSET
    data_number: int | float | UnsetType = UNSET
    data_string: str | UnsetType = UNSET
    data_boolean: bool | UnsetType = UNSET
    data_json: str | UnsetType = UNSET


class StoredEntry(msgspec.Struct, frozen=True):
    """A ``Property`` (``value`` in the field of its kind, ``persistent``) or a ``Container`` (``kind``)."""

    type: Literal["property", "container"]
    value: _Map | UnsetType = UNSET
    value_number: int | float | UnsetType = UNSET
    value_string: str | UnsetType = UNSET
    value_boolean: bool | UnsetType = UNSET
    value_json: str | UnsetType = UNSET
    persistent: bool = False
    kind: str = ""


class StorageSample(msgspec.Struct, frozen=True):
    """A storage change as a plain subscriber sees it: ``entry`` put on ``key``, or a delete (no ``entry``)."""

    key: str
    deleted: bool = False
    entry: StoredEntry | UnsetType = UNSET


class Liveliness(msgspec.Struct, frozen=True):
    """A liveliness token appearing (``alive``) or vanishing; ``name`` is the embodiment it is about."""

    key: str
    kind: str
    name: str
    alive: bool


class RawSample(msgspec.Struct, frozen=True):
    """A sample kept as bytes: not a cmion message, or not the one its key should carry (``error``)."""

    key: str
    deleted: bool = False
    payload_base64: Annotated[str, msgspec.Meta(extra_json_schema={"contentEncoding": "base64"})] = ""
    error: str = ""


class LogTime(msgspec.Struct, frozen=True):
    sec: int
    nsec: int


class LogLine(msgspec.Struct, frozen=True):
    """A ``foxglove.Log`` message: ``level`` is one of ``LEVELS``; ``name`` the embodiment it is about."""

    timestamp: LogTime
    level: int
    message: str
    name: str
    file: str = ""
    line: int = 0


#: ``foxglove.Log``'s levels (its enum ``foxglove.LogLevel``).
LEVELS = {"UNKNOWN": 0, "DEBUG": 1, "INFO": 2, "WARNING": 3, "ERROR": 4, "FATAL": 5}
INFO, WARNING, ERROR = LEVELS["INFO"], LEVELS["WARNING"], LEVELS["ERROR"]


# --- the schemas -------------------------------------------------------------------------------------


def _self_contained(schema: dict[str, Any]) -> dict[str, Any]:
    """msgspec's JSON Schema as Foxglove reads it: ``$ref`` replaced by what it names, a ``type``
    on every field (a string enum is a string, a number that may be an integer a number), a
    ``properties`` on every object (a map's keys are free), no ``null`` alternative (an unset
    field is left out of the message, never written null)."""
    defs = schema.get("$defs", {})

    def resolve(node: Any) -> Any:
        if isinstance(node, list):
            return [resolve(item) for item in node]
        if not isinstance(node, dict):
            return node
        if "$ref" in node:
            node = {**defs[node["$ref"].rsplit("/", 1)[-1]], **{k: v for k, v in node.items() if k != "$ref"}}
        node = {k: resolve(v) for k, v in node.items() if k not in ("$defs", "default")}
        alternatives = [a for a in node.pop("anyOf", []) if a.get("type") != "null"]
        if alternatives and all(a.get("type") in ("integer", "number") for a in alternatives):
            node["type"] = "number"
        elif len(alternatives) == 1:
            node.update(alternatives[0])
        elif alternatives:
            raise TypeError(f"no one type fits {alternatives}: Foxglove needs one")
        if "enum" in node and "type" not in node and all(isinstance(v, str) for v in node["enum"]):
            node["type"] = "string"
        if node.get("type") == "object":
            node.setdefault("properties", {})
        return node

    return dict(resolve(schema))


def _schema(kind: Any, title: str) -> bytes:
    schema = _self_contained(msgspec.json.schema(kind))
    schema["title"] = title
    return json.dumps(schema, sort_keys=True).encode()


def _log_schema() -> bytes:
    """``foxglove.Log`` as Foxglove defines it (its level an enum of numbers: ``oneOf`` consts)."""
    schema = _self_contained(msgspec.json.schema(LogLine))
    schema["title"] = LOG_SCHEMA
    schema["description"] = "A log line"
    levels = [{"title": name, "const": value} for name, value in LEVELS.items()]
    schema["properties"]["level"] = {"title": "foxglove.LogLevel", "oneOf": levels}
    schema["required"] = ["timestamp", "level", "message", "name", "file", "line"]
    return json.dumps(schema, sort_keys=True).encode()


#: name -> JSON Schema bytes of every schema a recording uses.
SCHEMAS: dict[str, bytes] = {
    EVENT_SCHEMA: _schema(RecordedEvent, EVENT_SCHEMA),
    STORAGE_SCHEMA: _schema(StorageSample, STORAGE_SCHEMA),
    LIVELINESS_SCHEMA: _schema(Liveliness, LIVELINESS_SCHEMA),
    RAW_SCHEMA: _schema(RawSample, RAW_SCHEMA),
    ANSWER_SCHEMA: _schema(RequestAnswered, ANSWER_SCHEMA),
    LOG_SCHEMA: _log_schema(),
}

_json = msgspec.json.Encoder()
_decode_event = decoder(Event)
_decode_answer = decoder(RequestAnswered)
_Entry = Property | Container


class _EventFields(msgspec.Struct, frozen=True):
    """A recorded event of either format: 1 had ``data`` whatever its kind (and the tag ``type``)."""

    embodiment: str
    component: str
    name: str
    seq: int = 0
    time: float = 0.0
    data: Any = None
    data_number: int | float | None = None
    data_string: str | None = None
    data_boolean: bool | None = None
    data_json: str | None = None


_event_fields = msgspec.json.Decoder(_EventFields)


def recorded_event(data: bytes) -> Event:
    """The ``Event`` a recorded message holds, of either format (``msgspec.DecodeError`` or
    ``ValidationError`` when it holds none; ``ValueError`` when its ``data_json`` is not JSON)."""
    f = _event_fields.decode(data)
    value = f.data
    if value is None:
        value = next((v for v in (f.data_number, f.data_string, f.data_boolean) if v is not None), None)
        if value is None and f.data_json is not None:
            value = json.loads(f.data_json)
    return Event(f.embodiment, f.component, f.name, value, f.seq, f.time)


def record_event(event: Event) -> bytes:
    """The JSON an event channel carries for ``event``."""
    data = event.data
    if data is None or type(data) is dict:  # nearly every event: straight in (the recorder's hot path)
        return _json.encode(RecordedEvent(event.embodiment, event.component, event.name, event.seq, event.time,
                                          UNSET if data is None else data))
    return _json.encode(RecordedEvent(event.embodiment, event.component, event.name, event.seq, event.time,
                                      **plain_fields("data", data)))


# --- what is subscribed to -----------------------------------------------------------------------------


def mesh_filter(mesh: str, pattern: str) -> str:
    """A filter as given on the command line: a key expression relative to ``cmion/<mesh>/``
    (``robot/ev/**``), or absolute when it starts with ``cmion/``."""
    if not pattern or pattern.startswith("/") or pattern.endswith("/"):
        raise ConfigError(f"filter {pattern!r} is not a key expression (e.g. robot/ev/** or */wm/**)")
    return pattern if pattern.startswith(f"{keys.ROOT}/") else f"{keys.mesh_prefix(mesh)}/{pattern}"


def mesh_filters(mesh: str, filters: Sequence[str] = ()) -> list[str]:
    """The key expressions subscribed to: ``filters`` (see ``mesh_filter``), by default the whole
    mesh and its requests' answers (``**`` never matches ``@outcome``, a verbatim chunk)."""
    return [mesh_filter(mesh, f) for f in filters] or [f"{keys.mesh_prefix(mesh)}/**", keys.outcome_pattern(mesh)]


def token_patterns(mesh: str) -> list[str]:
    """The liveliness watched, always: one pattern per kind of token (``TOKEN_KINDS``)."""
    return [f"{keys.mesh_prefix(mesh)}/{kind}/{'*' if kind == keys.ALIVE else '**'}" for kind in TOKEN_KINDS]


def follow(transport: Transport, mesh: str, filters: Sequence[str], on_samples: BatchHandler,
           on_token: LivelinessHandler) -> list[Closeable]:
    """Subscribe to ``filters`` and watch every kind of token of ``mesh``, as the recorder and the live
    Foxglove server both do; what was declared is closed again if a declaration fails."""
    declared: list[Closeable] = []
    try:
        declared.extend(transport.subscribe_batches(pattern, on_samples) for pattern in filters)
        declared.extend(transport.watch_liveliness(pattern, on_token) for pattern in token_patterns(mesh))
    except BaseException:
        for handle in declared:
            handle.close()
        raise
    return declared


# --- where a sample goes --------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Routed:
    """One message as it goes on a channel: the channel's topic and schema, and the JSON bytes."""

    topic: str
    schema: str
    data: bytes
    publish_ns: int = 0


def overflow_topic(routed: Routed, mesh: str) -> str:
    """The channel of a message whose own would be one too many: all events share
    ``cmion/<mesh>/*/ev/**``, every other schema one of its own."""
    if routed.schema == EVENT_SCHEMA:
        return f"{keys.ROOT}/{mesh}/*/{keys.EVENTS}/**"
    if routed.schema == RAW_SCHEMA:
        return f"raw:{keys.ROOT}/{mesh}/**"
    return f"{routed.schema}:{keys.ROOT}/{mesh}/**"


def route(sample: Sample, stamp_ns: int) -> list[Routed]:
    """The messages of a published sample received at ``stamp_ns``: its own, then its log line if
    it has one (never raises: what does not decode goes raw)."""
    key, payload, deleted = sample.key, sample.payload, sample.deleted
    chunks = key.split("/")
    kind = chunks[3] if len(chunks) >= 4 and chunks[0] == keys.ROOT else ""
    try:
        if kind == keys.EVENTS and len(chunks) == 6 and not deleted:
            event = _decode_event(payload, key)
            routed = Routed(key, EVENT_SCHEMA, record_event(event), nanoseconds(event.time))
            line = event_line(event, chunks[1], stamp_ns)
            return [routed] if line is None else [routed, line]
        if kind == keys.OUTCOMES and len(chunks) == 6 and not deleted:
            answer = _decode_answer(payload, key)
            routed = Routed(key, ANSWER_SCHEMA, _json.encode(answer), nanoseconds(answer.time))
            if answer.status == "accepted":
                return [routed]
            sender = f" from {answer.sender}" if answer.sender else ""
            text = f"{answer.component}/{answer.request}{sender}: {answer.status} {answer.code}: {answer.reason}"
            return [routed, _line(chunks[1], answer.embodiment, WARNING, text, routed.publish_ns or stamp_ns)]
        if kind in (keys.BLACKBOARD, keys.WORLD_MODEL):
            topic = "/".join((*chunks[:4], "**"))
            entry: StoredEntry | UnsetType = UNSET
            if not deleted:
                put = decode(payload, _Entry, where=key)
                entry = (StoredEntry("property", persistent=put.persistent, **plain_fields("value", put.value))
                         if isinstance(put, Property) else StoredEntry("container", kind=put.kind))
            return [Routed(topic, STORAGE_SCHEMA, _json.encode(StorageSample(key, deleted, entry)))]
        error = ""
    except MeshError as exc:
        error = str(exc)
    topic = "raw:" + ("/".join((*chunks[:4], "**")) if kind else key)
    routed = Routed(topic, RAW_SCHEMA, _json.encode(RawSample(key, deleted, base64.b64encode(payload).decode(), error)))
    if not error or not kind:
        return [routed]
    return [routed, _line(chunks[1], chunks[2], WARNING, f"not understood: {error}", stamp_ns)]


def route_token(key: str, alive: bool, stamp_ns: int) -> list[Routed]:
    """The messages of a liveliness token appearing or vanishing: its own, then its log line if it has one."""
    chunks = key.split("/")
    kind = chunks[2] if len(chunks) >= 4 else "?"
    name = chunks[3] if len(chunks) >= 4 else ""
    topic = "/".join((*chunks[:3], "*" if kind == keys.ALIVE else "**"))
    routed = Routed(topic, LIVELINESS_SCHEMA, _json.encode(Liveliness(key, kind, name, alive)))
    if kind == keys.ALIVE:
        text = f"{name} is alive" if alive else f"{name} is gone"
    elif kind == keys.CUSTODY and len(chunks) == 6:
        text = f"{name} {'holds' if alive else 'no longer holds'} {chunks[4]} (epoch {chunks[5]})"
    else:
        return [routed]
    return [routed, _line(chunks[1], name, INFO, text, stamp_ns)]


# --- log lines ------------------------------------------------------------------------------------------

#: Components whose every event is a log line: the companion's moves, actions, plans, the body.
STORY_COMPONENTS = frozenset({"migration", "manager", "execution", "embodiment"})
#: Event names that say something is broken (ERROR), and endings of those that say something failed (WARNING).
ERROR_EVENTS = frozenset({"CustodyFork", "CompanionDamaged", "DuplicateEmbodiment", "CompetencyCrashed"})
WARNING_ENDINGS = ("Failed", "Dropped", "NotSent", "Unavailable", "Superseded")
#: Longest message of a log line (an event's data is cut beyond).
MAX_LINE = 500


def event_level(name: str) -> int:
    if name in ERROR_EVENTS:
        return ERROR
    return WARNING if name.endswith(WARNING_ENDINGS) else INFO


def event_line(event: Event, mesh: str, stamp_ns: int) -> Routed | None:
    """The log line of an event, if it is one of the story's (``STORY_COMPONENTS``) or says
    something failed; at the event's own time (else ``stamp_ns``)."""
    level = event_level(event.name)
    if level == INFO and event.component not in STORY_COMPONENTS:
        return None
    data = event.data
    if isinstance(data, dict):
        detail = " ".join(f"{k}={v if isinstance(v, str) else _json.encode(v).decode()}" for k, v in data.items())
    else:
        detail = "" if data is None else _json.encode(data).decode()
    text = f"{event.component} {event.name}" + (f": {detail}" if detail else "")
    return _line(mesh, event.embodiment, level, text, nanoseconds(event.time) or stamp_ns)


def _line(mesh: str, name: str, level: int, text: str, at_ns: int) -> Routed:
    if len(text) > MAX_LINE:
        text = text[: MAX_LINE - 3] + "..."
    line = LogLine(LogTime(at_ns // 1_000_000_000, at_ns % 1_000_000_000), level, text, name)
    return Routed(f"log:{keys.ROOT}/{mesh}", LOG_SCHEMA, _json.encode(line), at_ns)


def nanoseconds(seconds: float) -> int:
    """``seconds`` since the epoch in nanoseconds; 0 for a time that is not one (0, negative, not finite)."""
    return int(seconds * 1e9) if seconds > 0 and math.isfinite(seconds) else 0
