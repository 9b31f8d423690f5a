"""Migration end to end: command -> companion awake at the target, for identity documents of
10 KiB, 1 MiB and 10 MiB, beside a raw zenoh transfer of the same bytes plus an fsync of them.

Processes (loopback only): two daemons ``cmion-mesh up`` of the bench embodiment, ``mig-a``
(where the companion ``bench`` is born) and ``mig-b``, each with its migration records in a
temporary ``--state-dir``; ``python -m bench.core serve-raw``; the measuring process, connected
to all three.

The companion's mind (``bench.minds:CarryMind``) carries a blob in one identity section of its
own: a raw message sets it, fresh random bytes, so that the identity document (manifest and
sections) has the size asked for (its actual size, as the source counts it, is in the JSON). The
blob is set afresh before every measured migration (untimed), so every migration sends the whole
document: no section is at the target from an earlier visit. For each size, after warm-up
migrations, every round measures:

* ``raw``: a raw zenoh get whose payload is that many random bytes, to a queryable in another
  process that replies 64 bytes (three per round);
* ``fsync``: writing that many bytes to a new file in a temporary folder and ``os.fsync`` (three
  per round); ``raw + fsync`` pairs them (the baseline);
* ``floor``: the same hop between two bare peers (``bench.floor``: plain Python, zenoh and the
  disk, doing only the messages and durable points any such handshake needs); the migration's
  ratio to it (``migration_<size>_vs_floor``) is what safety and the component model cost, and
  the floor's own ratio to ``raw + fsync`` (``migration_floor_<size>``) is the least any
  handshake of this shape can show on this machine;
* ``migration``: the ``migrate`` request to the embodiment holding the companion -> the
  ``MigrationOccurred`` event of the target (the companion restored and its minds awake there),
  as seen by the measuring process; the companion then goes back the other way next round.
  ``-> released``: until the source's ``MigrationSucceeded`` (the commit acknowledged).

At 10 KiB, each round also migrates a companion ``AGE`` (2000) migrations old between two daemons of
its own (``old-a``, ``old-b``; its state, a chain of custody of that many links, made beforehand):
``migration_10kib_aged``, with its ratio to the young companion's migration of the same round.

Then the return trip of delta migration: a 10 MiB identity whose blob stays as it is while the
mind's own section (10 KiB drawn afresh at every migration) changes; after a trip there and back
(both sides then hold the blob), each round migrates it once more: ``migration_return_10mib_delta``
(command -> awake at target) and ``migration_return_10mib_delta_sent`` (the bytes sent, manifest
and sections, in % of the document's, from the source's ``MigrationSucceeded`` ``transfer``).

Each side's fsync calls per migration are counted by its ledger (``describe``'s ``ledger``: read
before and after each measured migration, untimed): ``migration_fsyncs_source_*`` and
``migration_fsyncs_target_*``, with the last migration's count by kind in the JSON.

Targets (``bench/targets.py``): a small document (10 KiB) under 5 ms median; large ones (1 MiB,
10 MiB) within 3x of raw transfer plus fsync; the delta return under 20 ms, sending under 1 % of
the document.
"""

from __future__ import annotations

import os
import queue
import tempfile
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import zenoh

from bench.core import open_session, raw_keys
from bench.daemons import Node, client_config, stop_and_report
from bench.floor import Floor
from bench.harness import loopback_config, loopback_endpoint, start_child, stop_child
from bench.registry import Options, Row
from bench.stats import summarize
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.messages import Event, Migrate, MindMessage
from cmion_mesh.migration import custody, signing
from cmion_mesh.migration.identity import Identity
from cmion_mesh.migration.ledger import Record, Records
from cmion_mesh.procs import unique_mesh
from cmion_mesh.testing.wait import migrate_once_seen, wait_for
from cmion_mesh.transport.zenoh import ZenohTransport

COMPANION = "bench"
A, B = "mig-a", "mig-b"
KIB = 1024
SIZES = (10 * KIB, 1024 * KIB, 10 * 1024 * KIB)
SMALL_LIMIT_MS = 5.0
LARGE_TARGET = 3.0
DELTA_LIMIT_MS = 20.0
DELTA_SENT_LIMIT = 1.0  # % of the document
DELTA_SCRATCH = 10 * KIB
#: Links in the chain of custody of the aged companion (``aged``): that many migrations old.
AGE = 2000
#: bytes of the document that are not the blob (the manifest, the mind's section): subtracted from the blob
OVERHEAD = 600


def size_name(size: int) -> str:
    return f"{size // (1024 * KIB)} MiB" if size >= 1024 * KIB else f"{size // KIB} KiB"


def log(text: str) -> None:
    print(f"  [migration] {text}", flush=True)


def two_daemons(stack: ExitStack, mesh: str, tmp: Path, names: tuple[str, str], *, companion: str | None = None,
                launcher: tuple[str, ...] | None = None, report: Callable[[str], None] = log) -> tuple[dict[str, Node], MeshClient]:
    """Two daemons (the second connected to the first), up, and a client that sees both and the
    companion living on the first: born there (``companion``) or resumed from its state folder.
    Everything started is stopped by ``stack``."""
    first, second = names
    a = Node(first, mesh, tmp / first, companion=companion, launcher=launcher)
    b = Node(second, mesh, tmp / second, connect=(a.listen,), launcher=launcher)
    nodes = {first: a, second: b}
    for node in nodes.values():
        node.start()
    stack.callback(stop_and_report, list(nodes.values()), report)
    for node in nodes.values():
        node.wait_up(60.0)
    transport = ZenohTransport(client_config(a.listen, b.listen))
    stack.callback(transport.close)
    client = MeshClient(transport, mesh)
    for name in nodes:
        client.wait_for_embodiment(name, timeout=20.0)
    wait_for(lambda: client.describe(first, timeout=2.0).get("inhabitant") == COMPANION, 20.0, f"{COMPANION} living on {first}")
    return nodes, client


class Migrations:
    """Drives the companion between two daemons and times each hop from the measuring process."""

    def __init__(self, client: MeshClient, nodes: dict[str, Node]) -> None:
        self.client = client
        self.nodes = nodes
        self.pair = tuple(nodes)  # the embodiment it starts on, then the other
        self.home = self.pair[0]
        self.events: queue.SimpleQueue[tuple[float, Event]] = queue.SimpleQueue()
        self.transfer: dict[str, int] = {}
        #: fsyncs of the last migration, from each side's ledger counters (``describe``'s ``ledger``)
        self.fsyncs: dict[str, dict[str, int]] = {}
        self.subscription = client.events(self._on_event, component="migration")

    def _on_event(self, event: Event) -> None:
        self.events.put((time.perf_counter(), event))

    def close(self) -> None:
        self.subscription.close()

    @property
    def other(self) -> str:
        return self.pair[1] if self.home == self.pair[0] else self.pair[0]

    def tell_mind(self, args: dict[str, int]) -> None:
        outcome = self.client.request(self.home, "mind", "message", MindMessage(dict(args)), timeout=30.0)
        if outcome.status != "accepted":
            raise MeshError(f"the companion's mind on {self.home} refused {args}: {outcome.reason}")

    def once(self, timeout: float = 60.0) -> tuple[float, float]:
        """One migration home -> other: (to MigrationOccurred at the target, to MigrationSucceeded).
        ``transfer`` then holds the source's count of bytes sent and of the document."""
        while not self.events.empty():
            self.events.get_nowait()
        source, target = self.home, self.other
        counted = {name: self.fsync_counts(name) for name in (source, target)}
        t0 = time.perf_counter()
        outcome = self.client.request(source, "migration", "migrate", Migrate(COMPANION, target), timeout=timeout)
        if outcome.status != "accepted":
            raise MeshError(f"migrate {source} -> {target} refused: {outcome.reason}")
        occurred = succeeded = 0.0
        deadline = time.monotonic() + timeout
        seen: list[str] = []
        while True:
            try:
                if time.monotonic() > deadline:
                    raise queue.Empty
                at, event = self.events.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                raise MeshError(f"migration {source} -> {target}: no end within {timeout:g} s; {self.diagnose(seen)}") from None
            seen.append(f"{event.embodiment}:{event.name}")
            data = event.data if isinstance(event.data, dict) else {}
            if data.get("companion") != COMPANION:
                continue
            if event.name == "MigrationOccurred" and event.embodiment == target:
                occurred = at
            elif event.name == "MigrationFailed" and event.embodiment == source:
                raise MeshError(f"migration {source} -> {target} failed: {data.get('reason')}")
            elif event.name == "MigrationSucceeded" and event.embodiment == source:
                succeeded = at  # may arrive before the target's event: they come from two processes
                transfer = data.get("transfer")
                self.transfer = dict(transfer) if isinstance(transfer, dict) else {}
            if occurred and succeeded:
                self.home = target
                for side, name in (("source", source), ("target", target)):
                    after = self.fsync_counts(name)
                    self.fsyncs[side] = {kind: after.get(kind, 0) - counted[name].get(kind, 0) for kind in after}
                return occurred - t0, succeeded - t0

    def fsync_counts(self, name: str) -> dict[str, int]:
        """The daemon's fsyncs so far, by kind (untimed: before and after a measured migration)."""
        ledger = self.client.describe(name, timeout=10.0).get("ledger") or {}
        fsyncs = ledger.get("fsyncs") if isinstance(ledger, dict) else None
        return {str(k): int(v) for k, v in fsyncs.items()} if isinstance(fsyncs, dict) else {}

    def diagnose(self, seen: list[str]) -> str:
        """What the daemons say after a migration did not end: for the error message."""
        parts = [f"events seen: {seen}"]
        for name, node in self.nodes.items():
            try:
                inhabitant = self.client.describe(name, timeout=2.0).get("inhabitant")
            except MeshError as exc:
                inhabitant = f"? ({exc})"
            tail = " | ".join(node.daemon.lines[-5:]) if node.daemon is not None else ""
            parts.append(f"{name}: inhabitant {inhabitant}; output: {tail}")
        return "; ".join(parts)

    def document_size(self) -> int:
        """The last migration's document (manifest and sections), as its source counted it."""
        return int(self.transfer.get("total", 0))


class RawTransfer:
    def __init__(self, session: zenoh.Session, tag: str) -> None:
        self.session = session
        self.key = raw_keys(tag)[2]

    def once(self, payload: bytes) -> float:
        t0 = time.perf_counter()
        got = 0
        for reply in self.session.get(self.key, payload=payload, timeout=30.0):
            if reply.ok is not None:
                got += 1
        elapsed = time.perf_counter() - t0
        if got != 1:
            raise MeshError(f"raw transfer of {len(payload)} bytes: {got} replies")
        return elapsed


def fsync_once(folder: Path, payload: bytes, i: int) -> float:
    path = folder / f"fsync-{i}.bin"
    t0 = time.perf_counter()
    with open(path, "wb") as f:
        f.write(payload)
        f.flush()
        os.fsync(f.fileno())
    elapsed = time.perf_counter() - t0
    path.unlink()
    return elapsed


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    rounds = {SIZES[0]: 4, SIZES[1]: 4, SIZES[2]: 2} if options.quick else {SIZES[0]: 12, SIZES[1]: 12, SIZES[2]: 8}
    warmups = 1 if options.quick else 2
    mesh = unique_mesh("bench")
    raw_ep = loopback_endpoint()
    rows: list[Row] = []
    started = time.monotonic()
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-migration-")))
        raw_child = start_child("bench.core", "serve-raw", "--listen", raw_ep, "--tag", mesh, name="serve-raw")
        stack.callback(stop_child, raw_child)
        nodes, client = two_daemons(stack, mesh, tmp, (A, B), companion=COMPANION)
        raw_child.wait_line("ready", 30.0)
        session = open_session(loopback_config(connect=raw_ep))
        stack.callback(session.close)
        for target in (B, A):  # there and back: each daemon has seen the other alive before anything is timed
            migrate_once_seen(client, COMPANION, target)
        mig = Migrations(client, nodes)
        stack.callback(mig.close)
        raw = RawTransfer(session, mesh)
        raw.once(b"x")  # first contact
        old = aged_pair(stack, mesh, tmp, warmups)
        (tmp / "floor").mkdir()
        floor = Floor(f"{mesh}-floor", tmp / "floor")
        stack.callback(floor.close)
        log(f"daemons up after {time.monotonic() - started:.2f} s (mesh {mesh})")
        scratch = tmp / "fsync"
        scratch.mkdir()
        for size in SIZES:
            name = size_name(size)
            payload = os.urandom(size)
            for _ in range(warmups):
                mig.tell_mind({"size": max(0, size - OVERHEAD)})
                mig.once()
                raw.once(payload)
                fsync_once(scratch, payload, 0)
                floor.make(size)
                floor.once()
            samples: dict[str, list[float]] = {"raw": [], "fsync": [], "floor": [], "occurred": [], "released": [], "aged": []}
            sent: list[float] = []
            fsyncs: dict[str, list[float]] = {"source": [], "target": []}
            kinds: dict[str, dict[str, int]] = {}
            for i in range(rounds[size]):
                for j in range(3):
                    samples["raw"].append(raw.once(payload))
                    samples["fsync"].append(fsync_once(scratch, payload, i * 3 + j))
                floor.make(size)
                samples["floor"].append(floor.once())
                mig.tell_mind({"size": max(0, size - OVERHEAD)})  # a fresh blob: nothing of it is at the target
                occurred, released = mig.once()
                samples["occurred"].append(occurred)
                samples["released"].append(released)
                if size == SIZES[0]:  # the same migration of a companion AGE migrations old, in its own pair
                    old.tell_mind({"size": max(0, size - OVERHEAD)})
                    samples["aged"].append(old.once()[0])
                sent.append(mig.transfer.get("sent", 0) / max(1, mig.document_size()))
                for side in fsyncs:
                    fsyncs[side].append(float(mig.fsyncs.get(side, {}).get("total", 0)))
                    kinds[side] = mig.fsyncs.get(side, {})
            doc = mig.document_size()
            extra: dict[str, object] = {"document_bytes": doc, "rounds": rounds[size], "sections": mig.transfer.get("sections"),
                                        "sent_fraction_median": sorted(sent)[len(sent) // 2]}
            log(f"{name}: {rounds[size]} migrations (document {doc} bytes in {mig.transfer.get('sections')} sections, "
                f"the blob in one), {time.monotonic() - started:.1f} s")
            key = name.replace(" ", "").lower()
            both = [r + f for r, f in zip(samples["raw"], samples["fsync"], strict=True)]
            curve = {"curve": "migration_vs_size", "curve_title": "migration vs identity document size",
                     "x_label": "document KiB", "x": round(doc / KIB, 1)}
            base = Row(f"raw_fsync_{key}", f"raw transfer + fsync, {name} (baseline)", summarize(both),
                       extra={**curve, "series": "raw zenoh transfer + fsync"})
            awake, bare = summarize(samples["occurred"]), summarize(samples["floor"])
            occurred_row = Row(f"migration_{key}", f"migration {name}: command -> awake at target", awake,
                               baseline=base.metric, ratio=awake.median_ms / base.summary.median_ms,
                               extra={**extra, **curve, "series": "cmion migration"})
            floor_row = Row(f"migration_floor_{key}", f"bare handshake {name} (bench.floor): command -> awake, the floor", bare,
                            baseline=base.metric, ratio=bare.median_ms / base.summary.median_ms,
                            extra={**curve, "series": "bare handshake (floor)"})
            if size == SIZES[0]:
                occurred_row.limit, occurred_row.strict = SMALL_LIMIT_MS, True
            else:
                occurred_row.target = LARGE_TARGET
            rows += [
                Row(f"raw_{key}", f"raw zenoh get carrying {name}, round trip", summarize(samples["raw"])),
                Row(f"fsync_{key}", f"write + fsync {name} to a new file", summarize(samples["fsync"])),
                base,
                floor_row,
                occurred_row,
                Row(f"migration_{key}_vs_floor", f"migration {name} over the bare handshake", awake,
                    baseline=floor_row.metric, ratio=awake.median_ms / bare.median_ms),
                *([Row(f"migration_{key}_aged", f"migration {name} of a companion {AGE} migrations old: command -> awake",
                       summarize(samples["aged"]), baseline=occurred_row.metric,
                       ratio=summarize(samples["aged"]).median_ms / awake.median_ms, extra={"links": AGE})]
                  if samples["aged"] else []),
                Row(f"migration_released_{key}", f"migration {name}: command -> source released", summarize(samples["released"]),
                    extra=dict(extra)),
                *(Row(f"migration_fsyncs_{side}_{key}", f"migration {name}: fsync calls on the {side} (its ledger's counters)",
                      summarize(fsyncs[side], 1.0), unit="fsyncs", extra={"last_by_kind": kinds.get(side, {})})
                  for side in ("source", "target")),
            ]
        rows += delta_return(mig, rounds[SIZES[-1]] * 2, warmups)
        log(f"measured in {time.monotonic() - started:.1f} s")
    return rows


def aged_state(folder: Path, holder: str, other: str, links: int) -> None:
    """``holder``'s state folder with the companion active there after ``links - 1`` migrations
    between ``other`` and it: a chain of custody that long, signed link by link as handshakes sign."""
    records = Records(folder)
    packed = Identity(COMPANION, links, {}).pack_sections()
    key = signing.new_key()
    chain = [custody.birth(COMPANION, holder if links % 2 else other, key, packed.manifest)]
    for epoch in range(2, links + 1):
        following = signing.new_key()
        chain.append(custody.hand_on(key, COMPANION, epoch, holder if (links - epoch) % 2 == 0 else other,
                                     signing.public_of(following), f"aged-{epoch}", custody.digest(packed.manifest)))
        key = following
    records.put(Record(COMPANION, "active", links, chain=chain, public_key=signing.encode_public(chain[0].public_key)),
                document=packed.manifest, sections=packed.data, key=key)
    records.close()


def aged_pair(stack: ExitStack, mesh: str, tmp: Path, warmups: int) -> Migrations:
    """Two daemons of their own between which the companion, ``AGE`` migrations old (its state
    made beforehand), migrates: warmed up there and back (the other side has verified its chain)."""
    old_a, old_b = "old-a", "old-b"
    aged_state(tmp / old_a / "state", old_a, old_b, AGE)
    nodes, client = two_daemons(stack, mesh, tmp, (old_a, old_b))
    mig = Migrations(client, nodes)
    stack.callback(mig.close)
    for _ in range(max(2, warmups)):
        mig.tell_mind({"size": max(0, SIZES[0] - OVERHEAD)})
        mig.once()
    return mig


def delta_return(mig: Migrations, rounds: int, warmups: int) -> list[Row]:
    """A 10 MiB identity goes back and forth with only its mind's 10 KiB section changed each time."""
    size = SIZES[-1]
    mig.tell_mind({"size": max(0, size - OVERHEAD - DELTA_SCRATCH), "scratch": DELTA_SCRATCH})
    for _ in range(max(2, warmups)):  # there and back: both sides hold the blob from then on
        mig.once()
    times: list[float] = []
    sent: list[float] = []
    for _ in range(rounds):
        occurred, _released = mig.once()
        times.append(occurred)
        sent.append(100.0 * mig.transfer.get("sent", 0) / max(1, mig.document_size()))
    doc = mig.document_size()
    extra: dict[str, object] = {"document_bytes": doc, "rounds": rounds, "changed_section_bytes": DELTA_SCRATCH,
                                "sections": mig.transfer.get("sections"), "last_transfer": dict(mig.transfer)}
    log(f"delta return: {rounds} migrations of a {doc}-byte identity, {mig.transfer.get('sent')} bytes sent the last time")
    mig.tell_mind({"scratch": 0})
    return [
        Row("migration_return_10mib_delta", "return migration, 10 MiB identity, one 10 KiB section changed: command -> awake",
            summarize(times), limit=DELTA_LIMIT_MS, extra=extra),
        Row("migration_return_10mib_delta_sent", "return migration, 10 MiB identity, one 10 KiB section changed: bytes sent",
            summarize(sent, 1.0), unit="%", limit=DELTA_SENT_LIMIT, extra=dict(extra)),
    ]
