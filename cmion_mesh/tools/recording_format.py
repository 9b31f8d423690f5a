"""What a recording holds (``tools/recording.py`` writes it): its channels, the schemas of their
messages, and which channel each sample goes to.

What is recorded, one MCAP channel per key pattern:

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
* anything else under the recorded keys, and every payload that does not decode as what its key
  should carry, goes to ``raw:<key pattern>`` (schema ``cmion_mesh.RawSample``: the key and the
  bytes in base64), never lost.

Messages are JSON (``message_encoding`` ``json``) with a JSON Schema generated from the wire
Structs, so any reader shows their fields; JSON keeps every plain value a message can carry
except non-finite floats (msgspec writes NaN and infinities as ``null``). ``log_time`` is when the
recorder received the message, ``publish_time`` the event's own ``time`` (the publisher's clock).

``PROFILE`` names the files this recorder wrote (the MCAP header's profile).
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.messages import Container, Event, Property, RequestAnswered, decode, decoder
from cmion_mesh.transport.base import Sample

EVENT_SCHEMA = "cmion_mesh.Event"
STORAGE_SCHEMA = "cmion_mesh.StorageSample"
LIVELINESS_SCHEMA = "cmion_mesh.Liveliness"
RAW_SCHEMA = "cmion_mesh.RawSample"
ANSWER_SCHEMA = "cmion_mesh.RequestAnswered"
#: Liveliness token kinds recorded, each one channel.
TOKEN_KINDS = (keys.ALIVE, keys.CLAIM, keys.COMPETENCY, keys.CUSTODY)
PROFILE = "cmion-mesh"


class StorageSample(msgspec.Struct, frozen=True):
    """A storage change as a plain subscriber sees it: ``entry`` put on ``key``, or a delete."""

    key: str
    deleted: bool = False
    entry: Property | Container | None = None


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
    payload_base64: str = ""
    error: str = ""


def _schema(kind: Any, title: str) -> bytes:
    schema = msgspec.json.schema(kind)
    schema.setdefault("title", title)
    return json.dumps(schema, sort_keys=True).encode()


#: name -> JSON Schema bytes of every schema a recording uses.
SCHEMAS: dict[str, bytes] = {
    EVENT_SCHEMA: _schema(Event, EVENT_SCHEMA),
    STORAGE_SCHEMA: _schema(StorageSample, STORAGE_SCHEMA),
    LIVELINESS_SCHEMA: _schema(Liveliness, LIVELINESS_SCHEMA),
    RAW_SCHEMA: _schema(RawSample, RAW_SCHEMA),
    ANSWER_SCHEMA: _schema(RequestAnswered, ANSWER_SCHEMA),
}

_json = msgspec.json.Encoder()
_decode_event = decoder(Event)
_decode_answer = decoder(RequestAnswered)
_Entry = Property | Container


def mesh_filter(mesh: str, pattern: str) -> str:
    """A filter as given on the command line: a key expression relative to ``cmion/<mesh>/``
    (``robot/ev/**``), or absolute when it starts with ``cmion/``."""
    if not pattern or pattern.startswith("/") or pattern.endswith("/"):
        raise ConfigError(f"filter {pattern!r} is not a key expression (e.g. robot/ev/** or */wm/**)")
    return pattern if pattern.startswith(f"{keys.ROOT}/") else f"{keys.mesh_prefix(mesh)}/{pattern}"


# --- where a sample goes --------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Routed:
    """One sample as it goes into the file: its channel's topic and schema, and the JSON bytes."""

    topic: str
    schema: str
    data: bytes
    publish_ns: int = 0


def route(sample: Sample) -> Routed:
    """The channel and message of a published sample (never raises: what does not decode goes raw)."""
    key, payload, deleted = sample.key, sample.payload, sample.deleted
    chunks = key.split("/")
    kind = chunks[3] if len(chunks) >= 4 and chunks[0] == keys.ROOT else ""
    try:
        if kind == keys.EVENTS and len(chunks) == 6 and not deleted:
            event = _decode_event(payload, key)
            return Routed(key, EVENT_SCHEMA, _json.encode(event), int(event.time * 1e9) if event.time > 0 else 0)
        if kind == keys.OUTCOMES and len(chunks) == 6 and not deleted:
            answer = _decode_answer(payload, key)
            return Routed(key, ANSWER_SCHEMA, _json.encode(answer), int(answer.time * 1e9) if answer.time > 0 else 0)
        if kind in (keys.BLACKBOARD, keys.WORLD_MODEL):
            topic = "/".join((*chunks[:4], "**"))
            entry = None if deleted else decode(payload, _Entry, where=key)
            return Routed(topic, STORAGE_SCHEMA, _json.encode(StorageSample(key, deleted, entry)))
        error = ""
    except MeshError as exc:
        error = str(exc)
    topic = "raw:" + ("/".join((*chunks[:4], "**")) if kind else key)
    return Routed(topic, RAW_SCHEMA, _json.encode(RawSample(key, deleted, base64.b64encode(payload).decode(), error)))


def route_token(key: str, alive: bool) -> Routed:
    chunks = key.split("/")
    kind = chunks[2] if len(chunks) >= 4 else "?"
    topic = "/".join((*chunks[:3], "*" if kind == keys.ALIVE else "**"))
    return Routed(topic, LIVELINESS_SCHEMA, _json.encode(Liveliness(key, kind, chunks[3] if len(chunks) >= 4 else "", alive)))
