"""``cmion-mesh replay``: a recording's events published again, into a mesh, at their timing.

So that a mind or a monitor can be tested against a real session: each recorded event is
published on its key with the mesh name rewritten (``cmion/<recorded>/robot/ev/...`` becomes
``cmion/<target>/robot/ev/...``), its fields as recorded (embodiment, component, name, seq, time,
data), in the order recorded, spaced as recorded divided by ``rate`` (0 or infinity: as fast as
the mesh takes them, blocking congestion control). Storage samples, liveliness and raw samples
are not replayed: a replayed token or property would claim a body that is not there.

Join, then publish: before the first event, replay waits (within ``join_timeout``) for a
subscriber matching it to be known to its session (and for ``wait_for`` embodiments to be alive):
published before the mesh knows of it, an event reaches nobody. Zenoh says only whether *some*
subscriber matches: the first one known may be a daemon next door while a monitor's subscription
is still on its way (it comes over its own link, found by gossip), so replay then waits
``SETTLE`` more before the first event. Every wait ends at once when ``stop`` is set (Ctrl-C).
"""

from __future__ import annotations

import functools
import math
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import msgspec

from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.messages import encode
from cmion_mesh.tools.recording_format import EVENT_SCHEMA, recorded_event
from cmion_mesh.tools.recording_reader import Recorded, RecordingReader

#: Longest single sleep between two events: a stop request is seen within it.
SLEEP_SLICE = 0.25
#: After a first subscriber is known, how long the others' subscriptions have to arrive (they
#: come a few milliseconds apart on one host: this leaves room for a LAN).
SETTLE = 0.25

#: What a recorded event that is not one raises (``recording_format.recorded_event``).
_UNDECODABLE = (msgspec.DecodeError, msgspec.ValidationError, ValueError)


@dataclass
class ReplayStats:
    published: int = 0
    undecodable: int = 0
    truncated: bool = False
    listened: bool = True
    seconds: float = 0.0


def _relative(pattern: str) -> list[str]:
    """A filter as chunks of the key below ``cmion/<mesh>/`` (an absolute filter's mesh is dropped:
    it selects in the recording, whose mesh the replay rewrites anyway)."""
    chunks = pattern.split("/")
    if pattern.startswith(f"{keys.ROOT}/") and len(chunks) > 2:
        chunks = chunks[2:]
    if not pattern or "" in chunks:
        raise ConfigError(f"filter {pattern!r} is not a key expression (e.g. robot/ev/** or */ev/migration/*)")
    return chunks


def events(reader: RecordingReader, filters: Sequence[str] = ()) -> Iterator[tuple[Recorded, list[str]]]:
    """The recorded events selected by ``filters`` (any matching; none: all), each with its key's
    chunks below ``cmion/<mesh>/``."""
    patterns = [_relative(f) for f in filters]
    for message in reader.messages():
        if message.schema != EVENT_SCHEMA:
            continue
        if "*" in message.topic:
            # The overflow channel (a file with more event keys than ``record.MAX_CHANNELS``): its
            # topic is a pattern, each event's key is made of its own fields.
            try:
                fields = recorded_event(message.data)
            except _UNDECODABLE:
                continue
            rest = [fields.embodiment, keys.EVENTS, fields.component, fields.name]
            if not all(keys.is_name(chunk) for chunk in rest):
                continue
        else:
            rest = message.topic.split("/")[2:]
        if patterns and not any(keys.matches_chunks(p, rest) for p in patterns):
            continue
        yield message, rest


def _alive(client: MeshClient, name: str) -> Callable[[float], bool]:
    return lambda seconds: client.presence.wait(lambda names: name in names, seconds)


def _until(ready: Callable[[float], bool], timeout: float, stop: threading.Event) -> bool | None:
    """``ready(seconds)`` called for slices of ``timeout`` until it is True (True), ``stop`` is set
    (None: Ctrl-C is not kept waiting for the whole join) or ``timeout`` has passed (False). A
    ``ready`` that answers at once is asked again a slice later, not in a busy loop."""
    deadline = time.monotonic() + timeout
    for _ in range(1_000_000):  # bounded: each round waits a slice of what is left
        began = time.monotonic()
        part = max(0.0, min(deadline - began, SLEEP_SLICE))
        if ready(part):
            return True
        if stop.wait(max(0.0, part - (time.monotonic() - began))):
            return None
        if time.monotonic() >= deadline:
            return False
    return False


def replay(
    client: MeshClient, path: str | Path, *, rate: float = 1.0, filters: Sequence[str] = (), join_timeout: float = 5.0,
    wait_for: Sequence[str] = (), stop: threading.Event | None = None, warn: Callable[[str], None] | None = None,
) -> ReplayStats:
    """Publish the events of the recording at ``path`` into ``client``'s mesh (see the module doc)."""
    if rate < 0 or math.isnan(rate):
        raise ConfigError(f"rate {rate!r} must be 0 (as fast as possible) or more")
    fast = rate == 0 or math.isinf(rate)
    stop = stop or threading.Event()
    stats = ReplayStats()
    for embodiment in wait_for:
        alive = _until(_alive(client, embodiment), join_timeout, stop)
        if alive is None:
            return stats
        if not alive:
            raise client.not_alive(embodiment, join_timeout)
    started = time.monotonic()
    first_log: int | None = None
    transport = client.transport
    with RecordingReader(path) as reader:
        for message, rest in events(reader, filters):
            if stop.is_set():
                break
            try:
                event = recorded_event(message.data)
            except _UNDECODABLE:
                stats.undecodable += 1
                continue
            key = "/".join((keys.ROOT, client.mesh, *rest))
            if first_log is None:
                listened = _until(functools.partial(transport.wait_subscribers, key), join_timeout, stop)
                if listened is None or (listened and stop.wait(SETTLE)):
                    break
                stats.listened = listened
                if not stats.listened and warn is not None:
                    warn(f"replay: nobody in mesh {client.mesh!r} subscribes to {key} (waited {join_timeout:g} s); "
                         "publishing anyway")
                first_log, started = message.log_time, time.monotonic()
            if not fast:
                due = started + (message.log_time - first_log) / 1e9 / rate
                for _ in range(1_000_000):  # bounded: each round sleeps a slice of what is left
                    left = due - time.monotonic()
                    if left <= 0 or stop.wait(min(left, SLEEP_SLICE)):
                        break
                if stop.is_set():
                    break
            try:
                transport.publish(key, encode(event))
            except MeshError as exc:
                raise MeshError(f"replay of {message.topic} (recorded at {message.log_time} ns) into mesh "
                                f"{client.mesh!r}: {exc}") from None
            stats.published += 1
        else:  # read to its end (not stopped): whether that end is the file's
            stats.truncated = reader.truncated or not reader.complete
    stats.seconds = time.monotonic() - started
    return stats
