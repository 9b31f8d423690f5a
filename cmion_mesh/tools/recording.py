"""``cmion-mesh record``: everything a mesh says, written to an MCAP file.

MCAP (https://mcap.dev) is the open log format of robotics: Foxglove, the ``mcap`` command line
and any MCAP reader open these files. What goes in them (one channel per key pattern, JSON
messages with self-contained JSON Schemas that Foxglove reads, log lines as ``foxglove.Log``):
``tools/recording_format.py``, shared with the live Foxglove connection; reading them back and
``record info``: ``tools/recording_reader.py``. Here: the ``Recorder`` and the file it writes.

Bounded memory: the subscriptions' workers hand samples to a bounded inbox; the writer thread
drains it into MCAP chunks of ``CHUNK_SIZE``, and writes the chunk in progress out at least every
``FLUSH_INTERVAL``, so a killed recorder loses at most that much. After each write the file gets a
provisional end (``DataEnd``, a ``Footer`` naming no summary, the magic), which the next write
overwrites: a killed recorder's file is a valid MCAP file without a summary, which every reader
opens (``make_reader(f).iter_messages()`` too), unless it was killed in the middle of a write. If the writer falls behind and
the inbox is full, samples are dropped and counted, never silently: on stderr, and in the file
(metadata ``cmion-mesh.drops``, and ``cmion-mesh.end``).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import struct
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.opcode import Opcode
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from cmion_mesh import __version__, keys
from cmion_mesh.errors import ConfigError, MeshError, ProtocolError
from cmion_mesh.messages import Event, decoder
from cmion_mesh.tools.recording_format import (
    EVENT_SCHEMA,
    FORMAT,
    PROFILE,
    SCHEMAS,
    Routed,
    event_line,
    follow,
    mesh_filters,
    nanoseconds,
    overflow_topic,
    record_event,
    route,
    route_token,
)
from cmion_mesh.transport.base import Closeable, Sample, Transport

#: Uncompressed bytes of a chunk before it is compressed and written.
CHUNK_SIZE = 256 * 1024
#: Longest a received message stays in the chunk in progress before it reaches the file.
FLUSH_INTERVAL = 0.5
#: Samples and bytes waiting for the writer beyond which new ones are dropped (and counted).
MAX_QUEUED_SAMPLES = 100_000
MAX_QUEUED_BYTES = 64 * 1024 * 1024
#: Channels in one file; events on keys beyond it share the overflow channel ``cmion/<mesh>/*/ev/**``
#: (``recording_format.overflow_topic``).
MAX_CHANNELS = 4096
#: Most often a drop is reported on stderr.
DROP_REPORT_INTERVAL = 1.0

#: The end a file gets after each write, until the next one overwrites it: ``DataEnd`` (no CRC),
#: a ``Footer`` with no summary, the magic. A finished file's footer names its summary.
OPEN_END = struct.pack("<BQI", Opcode.DATA_END, 4, 0) + struct.pack("<BQQQI", Opcode.FOOTER, 20, 0, 0, 0) + MCAP0_MAGIC

_decode_event = decoder(Event)


# --- the inbox between the subscriptions and the writer -------------------------------------------


class Inbox:
    """Items waiting for the writer (or the live server's worker), bounded in samples and bytes;
    what does not fit is counted (``dropped``)."""

    def __init__(self, max_samples: int, max_bytes: int) -> None:
        self._items: deque[tuple[int, int, Any]] = deque()
        self._cond = threading.Condition()
        self._samples = 0
        self._bytes = 0
        self._max_samples = max_samples
        self._max_bytes = max_bytes
        self.dropped = 0
        self.closed = False

    def put(self, item: Any, samples: int, size: int) -> bool:
        with self._cond:
            if self.closed:
                return False
            if samples and (self._samples + samples > self._max_samples or self._bytes + size > self._max_bytes):
                self.dropped += samples
                return False
            self._samples += samples
            self._bytes += size
            self._items.append((samples, size, item))
            self._cond.notify()
            return True

    # The transport's workers hand over here: stamp and queue, nothing more (the recorder and the live
    # Foxglove server both subscribe with these two).

    def put_samples(self, batch: list[Sample]) -> None:
        self.put((time.time_ns(), batch), len(batch), sum(len(s.payload) + len(s.key) for s in batch))

    def put_token(self, key: str, alive: bool) -> None:
        self.put((time.time_ns(), (key, alive)), 1, len(key))

    def take(self, timeout: float) -> list[Any]:
        """Everything waiting (at once), or what arrives within ``timeout``; [] when nothing did."""
        with self._cond:
            if not self._items and not self.closed:
                self._cond.wait(max(0.0, timeout))
            items = list(self._items)
            self._items.clear()
            self._samples = 0
            self._bytes = 0
        return [item for _, _, item in items]

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()


# --- the file writer --------------------------------------------------------------------------------


def part_path(output: Path, index: int, split: bool) -> Path:
    """The file of part ``index``: ``output`` itself unless the recording is split (``name-0001.mcap``)."""
    return output.with_name(f"{output.stem}-{index:04d}{output.suffix or '.mcap'}") if split else output


class _Part:
    """One MCAP file being written: its writer, schemas and channels."""

    def __init__(self, path: Path, meta: dict[str, dict[str, str]], *, exclusive: bool = False) -> None:
        self.path = path
        self.started = time.monotonic()
        if path.is_dir():
            raise ConfigError("is a folder: name the recording's file (-o FOLDER/name.mcap)", path=str(path))
        try:
            self._stream: IO[bytes] = open(path, "xb" if exclusive else "wb")  # noqa: SIM115  (closed by close())
        except FileExistsError:
            raise ConfigError("exists already: not overwritten (another name, or --force)", path=str(path)) from None
        except OSError as exc:
            raise ConfigError(f"cannot write the recording: {exc.strerror}", path=str(path)) from None
        self.writer = Writer(self._stream, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        self.writer.start(profile=PROFILE, library=f"cmion-mesh {__version__}")
        self._schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.messages = 0
        self.pending = 0
        self.closed = False
        for name, data in meta.items():
            self.writer.add_metadata(name, data)
        self._end_at = -1
        self._open_end()  # the header on disk at once: a recorder killed now leaves a file that opens

    def channel(self, topic: str, schema: str) -> int:
        channel = self.channels.get(topic)
        if channel is None:
            schema_id = self._schemas.get(schema)
            if schema_id is None:
                schema_id = self._schemas[schema] = self.writer.register_schema(schema, "jsonschema", SCHEMAS[schema])
            channel = self.channels[topic] = self.writer.register_channel(topic, "json", schema_id)
        return channel

    def add(self, routed: Routed, log_ns: int, mesh: str) -> None:
        topic = routed.topic
        if topic not in self.channels and len(self.channels) >= MAX_CHANNELS:
            topic = overflow_topic(routed, mesh)
        self.messages += 1
        self.pending += 1
        self.writer.add_message(self.channel(topic, routed.schema), log_ns, routed.data, routed.publish_ns or log_ns, self.messages)

    def flush(self) -> None:
        if self.pending:
            self.writer.flush()  # type: ignore[no-untyped-call]
            self.pending = 0
        self._open_end()  # after metadata (drops, descriptions) written since, too

    def wrote(self) -> None:
        """After a batch: if a full chunk went out, the open end after it (else nothing)."""
        if self._stream.tell() != self._end_at:
            self._open_end()

    def _open_end(self) -> None:
        """Write what was written since the last time, then ``OPEN_END`` after it, and go back to
        where it starts: the next record overwrites it (nothing to do when nothing was written)."""
        self._stream.flush()
        at = self._stream.tell()
        if at == self._end_at:
            return
        self._stream.write(OPEN_END)
        self._stream.flush()
        self._stream.seek(at)
        self._end_at = at

    def size(self) -> int:
        return self._stream.tell()

    def close(self, end: dict[str, str]) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.writer.add_metadata("cmion-mesh.end", end)
            self.writer.finish()  # type: ignore[no-untyped-call]
            self._stream.truncate()  # nothing of an open end after the real one
        finally:
            self._stream.close()


@dataclass
class RecorderStats:
    """What a recorder wrote: ``messages`` in its files (what ``record info`` counts: log lines
    too), the ``samples`` (and liveliness changes) they came of, samples dropped, the files."""

    messages: int = 0
    samples: int = 0
    dropped: int = 0
    files: list[str] = field(default_factory=list)
    embodiments: set[str] = field(default_factory=set)


class Recorder:
    """Records ``mesh`` through ``transport`` into ``output`` from construction until ``close()``
    (idempotent; a context manager). ``filters``: key expressions (see ``mesh_filter``) of the
    publications recorded, default the whole mesh and its requests' answers (``@outcome``);
    liveliness is always recorded.
    ``split_bytes``/``split_seconds``: start a new file (``name-0001.mcap``...) past that size or age."""

    def __init__(
        self, transport: Transport, mesh: str, output: str | Path, *, filters: Sequence[str] = (),
        split_bytes: int = 0, split_seconds: float = 0.0, flush_interval: float = FLUSH_INTERVAL,
        max_queued: int = MAX_QUEUED_SAMPLES, report: Callable[[str], None] | None = None, overwrite: bool = True,
    ) -> None:
        self.mesh = keys.check_name(mesh, "mesh")
        self.output = Path(output)
        self.filters = mesh_filters(mesh, filters)
        self.split_bytes = split_bytes
        self.split_seconds = split_seconds
        self.flush_interval = flush_interval
        self.stats = RecorderStats()
        self._report = report or (lambda text: print(text, file=sys.stderr, flush=True))
        self._inbox = Inbox(max_queued, MAX_QUEUED_BYTES)
        self._split = bool(split_bytes or split_seconds)
        self._split_due = False  # the part is full or old: the next thing written starts a new one
        self._alive: set[str] = set()
        # Custody tokens seen (embodiment -> companion -> epoch): who inhabits what when a part starts.
        self._custody: dict[str, dict[str, str]] = {}
        self._custody_seen = False
        self._meta: dict[str, dict[str, str]] = {"cmion-mesh": {
            "mesh": self.mesh, "filters": " ".join(self.filters), "recorder": f"cmion-mesh {__version__}", "format": str(FORMAT),
            "host": socket.gethostname(), "pid": str(os.getpid()), "started": _iso(time.time()),
        }}
        self._lock = threading.Lock()
        self._closed = False
        self._error: BaseException | None = None
        self._exclusive = not overwrite
        self._part = _Part(part_path(self.output, 0, self._split), self._meta_for(0), exclusive=self._exclusive)
        self.stats.files.append(str(self._part.path))
        self._writer = threading.Thread(target=self._run, name="record-writer", daemon=True)
        self._writer.start()
        self._subscriptions: list[Closeable] = []
        try:
            self._subscriptions = follow(transport, mesh, self.filters, self._inbox.put_samples, self._inbox.put_token)
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Recorder:
        return self

    @property
    def dropped(self) -> int:
        """Samples dropped so far because the writer fell behind."""
        return self._inbox.dropped

    def __exit__(self, *_: object) -> None:
        self.close()

    def describe(self, descriptions: Iterable[dict[str, Any]]) -> None:
        """Write what the embodiments said of themselves (``MeshClient.describe_all``) as metadata
        ``embodiment`` records, one each, in this file and every later part."""
        for description in descriptions:
            name = str(description.get("name", "?"))
            record = {k: v if isinstance(v, str) else json.dumps(v, sort_keys=True) for k, v in description.items()}
            self._inbox.put((0, ("meta", f"embodiment:{name}", record)), 0, 0)

    # --- the writer thread ------------------------------------------------------------------------

    def _meta_for(self, index: int) -> dict[str, dict[str, str]]:
        meta = {name: dict(value) for name, value in self._meta.items()}
        meta["cmion-mesh"]["part"] = str(index)
        if index:  # each part says when it started; the recording's own start stays beside it
            meta["cmion-mesh"]["recording_started"] = meta["cmion-mesh"]["started"]
            meta["cmion-mesh"]["started"] = _iso(time.time())
        meta["cmion-mesh"]["alive_at_start"] = ",".join(sorted(self._alive))
        if index and self._custody_seen:
            # Each part stands alone: who held which companion when it started, not when the
            # recording did (the descriptions are from then: their inhabitants are brought up to date).
            meta["cmion-mesh"]["custody_at_start"] = ",".join(
                f"{embodiment}:{companion}@{epoch}" for embodiment, held in sorted(self._custody.items())
                for companion, epoch in sorted(held.items()))
            for name, record in meta.items():
                if name.startswith("embodiment:"):
                    held = sorted(self._custody.get(name.split(":", 1)[1], {}))
                    record["inhabitant"] = ",".join(held) if held else "null"
        return meta

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as exc:  # a full disk or a bad path: said on close, recording stops
            self._error = exc
            self._inbox.close()
            self._report(f"recorder: writing {self._part.path} failed: {exc}; recording stopped")

    def _loop(self) -> None:
        next_flush = time.monotonic() + self.flush_interval
        reported_drops = 0
        last_report = 0.0
        while True:
            items = self._inbox.take(next_flush - time.monotonic())
            if items and self._split_due:
                self._split_due = False
                self._next_part()
            for stamp, item in items:
                self._write(stamp, item)
            self._part.wrote()
            now = time.monotonic()
            if now >= next_flush or self._inbox.closed:
                dropped = self._inbox.dropped
                if dropped != reported_drops and (now - last_report >= DROP_REPORT_INTERVAL or self._inbox.closed):
                    self._report(f"recorder: {dropped - reported_drops} samples dropped (the writer fell behind; "
                                 f"{dropped} in all)")
                    self._part.writer.add_metadata("cmion-mesh.drops", {"dropped": str(dropped), "at": _iso(time.time())})
                    reported_drops, last_report = dropped, now
                self.stats.dropped = dropped
                self._part.flush()
                next_flush = now + self.flush_interval
                # Only a message fills a part: its header and metadata alone pass a small split size,
                # and a part that waited long for its first message is old, yet it holds none.
                if self._split and not self._split_due and self._part.messages and (
                        (self.split_bytes and self._part.size() >= self.split_bytes)
                        or (self.split_seconds and now - self._part.started >= self.split_seconds)):
                    self._split_due = True  # not now: an idle mesh would leave a trail of empty files
            if self._inbox.closed and not items:
                return

    def _write(self, stamp: int, item: Any) -> None:
        if isinstance(item, list):
            self._write_samples(stamp, item)
            return
        if item[0] == "meta":
            _, name, record = item
            self._meta[name] = record
            self._part.writer.add_metadata(name, record)
            return
        key, alive = item
        chunks = key.split("/")
        if chunks[2:3] == [keys.ALIVE]:
            name = key.rsplit("/", 1)[-1]
            self.stats.embodiments.add(name)
            (self._alive.add if alive else self._alive.discard)(name)
        elif chunks[2:3] == [keys.CUSTODY] and len(chunks) == 6:
            self._custody_seen = True
            held = self._custody.setdefault(chunks[3], {})
            if alive:
                held[chunks[4]] = chunks[5]
            elif held.get(chunks[4]) == chunks[5]:
                del held[chunks[4]]
        routed = route_token(key, alive, stamp)
        for message in routed:
            self._part.add(message, stamp, self.mesh)
        self.stats.samples += 1
        self.stats.messages += len(routed)

    def _write_samples(self, stamp: int, batch: list[Sample]) -> None:
        # The hot path: an event on a key whose channel this file has (its topic is the key itself;
        # no other channel's topic is a concrete key) goes straight in (its log line, if it has one,
        # after it); the rest through ``route``.
        part = self._part
        channels = part.channels
        add = part.writer.add_message
        mesh = self.mesh
        written = part.messages
        for sample in batch:
            key, payload, deleted = sample.key, sample.payload, sample.deleted
            channel = channels.get(key)
            if channel is not None and not deleted:
                try:
                    event = _decode_event(payload, key)
                except ProtocolError:
                    pass  # to ``route``: kept raw, with the error
                else:
                    part.messages += 1
                    part.pending += 1
                    add(channel, stamp, record_event(event), nanoseconds(event.time) or stamp, part.messages)
                    line = event_line(event, mesh, stamp)
                    if line is not None:
                        part.add(line, stamp, mesh)
                    continue
            for routed in route(sample, stamp):
                if routed.schema == EVENT_SCHEMA:
                    self.stats.embodiments.add(key.split("/")[2])
                part.add(routed, stamp, mesh)
        self.stats.samples += len(batch)
        self.stats.messages += part.messages - written

    def _end_record(self) -> dict[str, str]:
        return {"messages": str(self._part.messages), "dropped": str(self._inbox.dropped), "ended": _iso(time.time()),
                "embodiments": ",".join(sorted(self.stats.embodiments))}

    def _next_part(self) -> None:
        self._part.close(self._end_record())
        index = len(self.stats.files)
        self._part = _Part(part_path(self.output, index, True), self._meta_for(index), exclusive=self._exclusive)
        self.stats.files.append(str(self._part.path))

    def close(self) -> None:
        """Stop recording: close the subscriptions, write what is waiting and the file's summary."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for subscription in self._subscriptions:
            subscription.close()
        self._inbox.close()
        self._writer.join()
        self.stats.dropped = self._inbox.dropped
        if self._error is None:
            self._part.close(self._end_record())
        else:
            with contextlib.suppress(OSError, ValueError):
                self._part._stream.close()
            raise MeshError(f"recording to {self._part.path} failed: {self._error}") from None


def _iso(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t * 1000) % 1000:03d}Z"


def parse_size(text: str) -> int:
    """``100M``, ``1.5G``, ``64k`` or a plain number of bytes."""
    units = {"k": 1024, "m": 1024**2, "g": 1024**3}
    raw = text.strip().lower().removesuffix("b").removesuffix("i")
    try:
        value = float(raw[:-1]) * units[raw[-1]] if raw and raw[-1] in units else float(raw)
    except ValueError:
        raise ConfigError(f"size {text!r} is not a size (e.g. 100M, 1G, 65536)") from None
    if value <= 0:
        raise ConfigError(f"size {text!r} must be more than 0")
    return int(value)
