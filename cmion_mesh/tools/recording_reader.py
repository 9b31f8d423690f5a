"""Reading a recording back (``RecordingReader``: record by record, without its summary, so a
file whose recorder was killed reads up to its last complete chunk) and ``cmion-mesh record info``
(``info``: time span, counts per channel, migrations, embodiments, requests refused, drops;
``format_info`` for people). ``tools/replay.py`` reads recordings with ``RecordingReader`` too.
"""

from __future__ import annotations

import dataclasses
import json
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, DataEnd, Footer, Header, Metadata, Schema, Statistics
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError
from cmion_mesh.tools.recording_format import ANSWER_SCHEMA, EVENT_SCHEMA, LIVELINESS_SCHEMA, PROFILE, event_data

#: Requests not accepted that ``info`` lists (it counts them all).
MAX_REFUSALS_LISTED = 20
#: What a truncated or damaged file raises while it is read: a record cut short (EndOfFile, short
#: reads that ``struct`` cannot unpack), or a chunk cut short (its decompressor's error).
_READ_ERRORS: tuple[type[BaseException], ...] = (McapError, struct.error, ValueError, EOFError, UnicodeDecodeError)
try:
    import zstandard

    _READ_ERRORS += (zstandard.ZstdError,)
except ImportError:  # pragma: no cover - mcap requires it
    pass


@dataclass(frozen=True, slots=True)
class Recorded:
    """One message of a recording: its channel's topic and schema, times (ns) and JSON bytes."""

    topic: str
    schema: str
    log_time: int
    publish_time: int
    data: bytes

    def decoded(self) -> Any:
        return json.loads(self.data)


class RecordingReader:
    """Reads a recording from its start, record by record, without its summary: a file whose
    recorder was killed reads up to its last complete chunk (``truncated`` says so once read).
    A context manager; ``close`` is idempotent."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._stream: IO[bytes] = open(self.path, "rb")  # noqa: SIM115  (closed by close())
        except OSError as exc:
            raise ConfigError(f"cannot open recording: {exc.strerror}", path=str(self.path)) from None
        self.header: Header | None = None
        self.metadata: list[tuple[str, dict[str, str]]] = []
        self.truncated = False
        self.complete = False
        self.error = ""
        self._data_end = False
        self.statistics: Statistics | None = None
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        self._stream.close()

    def messages(self) -> Iterator[Recorded]:
        """Every message, in the order written (that of arrival at the recorder)."""
        reader = StreamReader(self._stream, skip_magic=False)
        records = reader.records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except _READ_ERRORS as exc:
                if self.header is None and not isinstance(exc, EndOfFile):
                    raise ConfigError(f"not an MCAP recording ({exc or type(exc).__name__})", path=str(self.path)) from None
                self.truncated = True
                self.error = str(exc) or type(exc).__name__
                return
            if isinstance(record, McapMessage):
                channel = self._channels.get(record.channel_id)
                if channel is None:
                    continue
                schema = self._schemas.get(channel.schema_id)
                yield Recorded(channel.topic, schema.name if schema else "", record.log_time, record.publish_time, record.data)
            elif isinstance(record, Channel):
                self._channels[record.id] = record
            elif isinstance(record, Schema):
                self._schemas[record.id] = record
            elif isinstance(record, Metadata):
                self.metadata.append((record.name, dict(record.metadata)))
            elif isinstance(record, Header):
                self.header = record
            elif isinstance(record, Statistics):
                self.statistics = record
            elif isinstance(record, DataEnd):
                self._data_end = True
            elif isinstance(record, Footer):
                # A recorder's finished file names its summary; an open end (a killed recorder's) does not.
                own = self.header is not None and self.header.profile == PROFILE
                self.complete = self._data_end and (record.summary_start != 0 or not own)
                return


@dataclass
class Migration:
    """One migration attempt as the recording shows it."""

    companion: str
    attempt: str
    source: str = ""
    target: str = ""
    steps: list[str] = field(default_factory=list)
    outcome: str = ""


def info(path: str | Path) -> dict[str, Any]:
    """A summary of a recording: time span, counts per channel, migrations, embodiments, drops,
    and whether it was truncated (its recorder killed: read up to its last complete chunk)."""
    counts: dict[str, int] = {}
    first = last = 0
    embodiments: set[str] = set()
    migrations: dict[str, Migration] = {}
    answers: dict[str, int] = {}
    refusals: list[dict[str, str]] = []
    with RecordingReader(path) as reader:
        for message in reader.messages():
            counts[message.topic] = counts.get(message.topic, 0) + 1
            first = message.log_time if not first else min(first, message.log_time)
            last = max(last, message.log_time)
            if message.schema == LIVELINESS_SCHEMA and message.topic.endswith(f"/{keys.ALIVE}/*"):
                embodiments.add(message.decoded().get("name", ""))
            elif message.schema == EVENT_SCHEMA:
                _follow_migration(message, migrations, embodiments)
            elif message.schema == ANSWER_SCHEMA:
                answer = message.decoded()
                status = str(answer.get("status"))
                answers[status] = answers.get(status, 0) + 1
                if status != "accepted" and len(refusals) < MAX_REFUSALS_LISTED:
                    refusals.append({k: str(answer.get(k, "")) for k in ("embodiment", "component", "request", "sender",
                                                                         "status", "code", "reason")})
        meta = reader.metadata
        truncated, error = reader.truncated or not reader.complete, reader.error
    start = dict(next((m for n, m in meta if n == "cmion-mesh"), {}))
    end = dict(next((m for n, m in reversed(meta) if n == "cmion-mesh.end"), {}))
    drops = [int(m.get("dropped", "0")) for n, m in meta if n in ("cmion-mesh.drops", "cmion-mesh.end")]
    described = {n.split(":", 1)[1]: m for n, m in meta if n.startswith("embodiment:")}
    embodiments |= set(described)
    embodiments.discard("")
    return {
        "file": str(path),
        "mesh": start.get("mesh", ""),
        "started": start.get("started", ""),
        "ended": end.get("ended", ""),
        "duration": (last - first) / 1e9 if last else 0.0,
        "messages": sum(counts.values()),
        "channels": dict(sorted(counts.items())),
        "embodiments": sorted(embodiments),
        # Values that were not strings are kept as JSON: an embodiment nobody inhabits says "null".
        "described": {name: {k: "" if (v := described[name].get(k, "")) == "null" else v
                             for k in ("version", "host", "pid", "inhabitant")}
                      for name in sorted(described)},
        "migrations": [dataclasses.asdict(m) for m in migrations.values()],
        "requests": dict(sorted(answers.items())),
        "refused": refusals,
        "dropped": max(drops, default=0),
        "truncated": truncated,
        "truncation": error or ("no end: the recorder did not close the file" if truncated else ""),
    }


def _follow_migration(message: Recorded, migrations: dict[str, Migration], embodiments: set[str]) -> None:
    name = message.topic.rsplit("/", 1)[-1]
    if not name.startswith("Migration"):
        return
    try:
        event = message.decoded()
    except ValueError:
        return
    if not isinstance(event, dict):
        return
    embodiments.add(str(event.get("embodiment", "")))
    data = event_data(event)
    if not isinstance(data, dict):
        return
    attempt = str(data.get("attempt", ""))
    if not attempt:
        return
    where = str(event.get("embodiment", ""))
    migration = migrations.setdefault(attempt, Migration(str(data.get("companion", "")), attempt))
    if name == "MigrationStarting":
        migration.source, migration.target = where, str(data.get("target", ""))
    elif name == "MigrationStep":
        migration.steps.append(f"{where}:{data.get('step')}")
        if data.get("step") in ("prepared", "handed") and not migration.source:
            migration.source, migration.target = where, str(data.get("peer", ""))
    elif name in ("MigrationSucceeded", "MigrationFailed", "MigrationDropped"):
        migration.outcome = name.removeprefix("Migration").lower()


def format_info(summary: dict[str, Any]) -> str:
    """``info`` for people."""
    lines = [f"{summary['file']}: mesh {summary['mesh'] or '?'}, {summary['messages']} messages over {summary['duration']:.2f} s"
             + (f" (started {summary['started']})" if summary["started"] else "")]
    if summary["truncated"]:
        lines.append(f"TRUNCATED: {summary['truncation']} (read up to the last complete chunk)")
    if summary["dropped"]:
        lines.append(f"DROPPED: {summary['dropped']} samples the recorder could not keep up with")
    lines.append(f"embodiments: {', '.join(summary['embodiments']) or 'none'}")
    for name, d in summary["described"].items():
        lines.append(f"  {name}: version {d['version'] or '?'}, host {d['host'] or '?'}, pid {d['pid'] or '?'}, "
                     f"inhabitant {d['inhabitant'] or '-'}")
    lines.append(f"migrations: {len(summary['migrations'])}")
    for m in summary["migrations"]:
        lines.append(f"  {m['companion']} {m['source'] or '?'} -> {m['target'] or '?'} ({m['attempt']}): "
                     f"{' '.join(m['steps']) or 'no step'}; {m['outcome'] or 'no end recorded'}")
    if summary["requests"]:
        counts = ", ".join(f"{n} {status}" for status, n in summary["requests"].items())
        lines.append(f"requests answered: {sum(summary['requests'].values())} ({counts})")
        for r in summary["refused"]:
            lines.append(f"  {r['embodiment']} {r['component']}/{r['request']}{' from ' + r['sender'] if r['sender'] else ''}: "
                         f"{r['status']} {r['code']}: {r['reason']}")
    lines.append("channels:")
    width = max((len(t) for t in summary["channels"]), default=0)
    for topic, count in summary["channels"].items():
        lines.append(f"  {topic:<{width}}  {count}")
    return "\n".join(lines)
