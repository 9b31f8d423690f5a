"""Delta migration: sections stored and named by their hash, only the missing ones cross the network.

The network tests run two daemons (``cmion-mesh up``) in processes of their own, on loopback, each
with its own state folder, the companion's mind a ``tests.helpers.delta_helpers:Carrier`` whose blob is a
section of its own. Their state folders are read directly (never through ``Records``, which would
tidy a live daemon's folder). The in-process tests drive a target's migration component with a
holder played by the test (``custody_helpers.Holder``) over the in-memory transport.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError, RequestRejected
from cmion_mesh.messages import Code, MigrateAbort, MigrateSections, MindMessage, MindState, Outcome, SectionChunk
from cmion_mesh.migration import identity, sections, uploads
from cmion_mesh.migration.handshake import have
from cmion_mesh.migration.identity import Identity, SectionMemo, SectionRef, max_section, read_manifest
from cmion_mesh.migration.ledger import Record, Records, read_ledger
from cmion_mesh.migration.outgoing import INLINE
from cmion_mesh.migration.sections import SectionStore
from cmion_mesh.procs import free_port
from cmion_mesh.testing.wait import migrate_once_seen, wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.memory import MemoryNetwork
from cmion_mesh.transport.zenoh import ZenohTransport

from .helpers import delta_helpers, remote_helpers
from .helpers.custody_helpers import Holder
from .helpers.delta_helpers import carrier_config
from .helpers.remote_helpers import screen_in_process

pytestmark = pytest.mark.timeout(180)

COMPANION = "spirit"
MIB = 1024 * 1024


# --- real daemons ---------------------------------------------------------------------------------


class Node(remote_helpers.Node):
    """A daemon of the test mesh whose state folder the tests read."""

    # The state folder, read as files.

    def record(self) -> Record:
        return read_ledger(self.state).records[COMPANION]

    def manifest_bytes(self) -> bytes:
        return read_ledger(self.state).documents[COMPANION]

    def refs(self) -> tuple[SectionRef, ...]:
        return read_manifest(self.manifest_bytes()).refs

    def cached(self) -> set[str]:
        folder = self.state / "sections"
        return {p.name for p in folder.iterdir() if not p.name.startswith(".")} if folder.exists() else set()

    def section_file(self, component: str) -> Path:
        ref = next(r for r in self.refs() if r.component == component)
        return self.state / "sections" / ref.sha256


@pytest.fixture
def two(tmp_path: Path, mesh: str, request: pytest.FixtureRequest) -> Iterator[tuple[Node, Node, MeshClient]]:
    """robot (the companion's home) and screen up, a client joined to both, spirit living on the robot.
    Parametrized indirectly, the parameter is extra environment for the screen's daemon."""
    screen_env: dict[str, str] = getattr(request, "param", {})
    ports = {"robot": free_port(), "screen": free_port()}
    nodes = [Node(name, mesh, carrier_config(tmp_path / name, name), tmp_path / f"state-{name}", port,
                  [f"tcp/127.0.0.1:{p}" for n, p in ports.items() if n != name],
                  companion=COMPANION if name == "robot" else None,
                  env=dict(screen_env) if name == "screen" else {})
             for name, port in ports.items()]
    try:
        for node in nodes:
            node.start()
        with ZenohTransport(TransportConfig(connect=tuple(n.endpoint for n in nodes), multicast=False)) as t:
            client = MeshClient(t, mesh)
            wait_for(lambda: client.describe("robot", timeout=1.0).get("inhabitant") == COMPANION, 30, "spirit born on the robot")
            client.wait_for_embodiment("screen", timeout=20)
            yield nodes[0], nodes[1], client
    finally:
        for node in nodes:
            node.stop()


def tell(client: MeshClient, embodiment: str, data: dict[str, Any]) -> None:
    outcome = client.request(embodiment, "carrier", "message", MindMessage(data), timeout=30)
    assert outcome.status == "accepted", outcome


def state(client: MeshClient, embodiment: str) -> dict[str, Any]:
    value = client.request(embodiment, "carrier", "state", MindState(), timeout=30).value
    assert isinstance(value, dict)
    return value


def blob_sha(size: int, seed: int) -> str:
    return hashlib.sha256(delta_helpers.blob_text(size, seed).encode()).hexdigest()


def test_a_return_trip_sends_only_the_manifest_and_the_changed_sections(two: tuple[Node, Node, MeshClient]) -> None:
    robot, _screen, client = two
    size = 2 * MIB  # over INLINE: the target is asked what it holds
    assert size > INLINE
    tell(client, "robot", {"note": "met Ada", "blob": size, "seed": 7})
    there = migrate_once_seen(client, COMPANION, "screen")
    assert there["transfer"]["sent"] >= size, "first visit: everything crosses"
    assert there["transfer"]["sent"] <= there["transfer"]["total"]
    assert client.describe("robot")["migration_transfer"] == there["transfer"]
    tell(client, "screen", {"note": "at the entrance"})  # the mind's section changes; the blob does not
    held = robot.cached()
    back = client.migrate(COMPANION, "robot", timeout=60)

    manifest = robot.manifest_bytes()
    refs = robot.refs()
    blob = next(r for r in refs if r.component == "carrier-blob")
    assert blob.sha256 in held, "the blob the robot had when it left is the one that came back"
    changed = [r for r in refs if r.sha256 not in held]
    assert changed and blob not in changed
    assert back["transfer"]["sent"] == len(manifest) + sum(r.size for r in changed), back["transfer"]
    assert back["transfer"]["sent"] < back["transfer"]["total"] / 20
    # Byte-identical: the manifest is the one the screen signed (its custody link names its hash), and
    # every section the manifest names is here under its hash.
    assert robot.record().state == "active"
    assert robot.record().chain[-1].document_sha256 == hashlib.sha256(manifest).digest()
    for ref in refs:
        data = (robot.state / "sections" / ref.sha256).read_bytes()
        assert len(data) == ref.size and hashlib.sha256(data).hexdigest() == ref.sha256
    mind = state(client, "robot")
    assert mind["notes"] == ["met Ada", "at the entrance"] and mind["blob_sha256"] == blob_sha(size, 7)


def test_a_corrupted_or_missing_cached_section_is_fetched_again(two: tuple[Node, Node, MeshClient]) -> None:
    robot, screen, client = two
    size = 2 * MIB
    tell(client, "robot", {"note": "met Ada", "blob": size, "seed": 3})
    migrate_once_seen(client, COMPANION, "screen")
    # The robot keeps the blob it sent (no record names it now): alter it at rest, same size.
    cached = robot.state / "sections" / screen.section_file("carrier-blob").name
    data = bytearray(cached.read_bytes())
    data[len(data) // 2] ^= 0xFF
    cached.write_bytes(bytes(data))
    back = client.migrate(COMPANION, "robot", timeout=60)
    assert back["transfer"]["sent"] > size, "the altered section was sent again"
    assert hashlib.sha256(cached.read_bytes()).hexdigest() == cached.name, "and stored whole"
    assert state(client, "robot")["blob_sha256"] == blob_sha(size, 3)
    # The screen keeps the blob too: remove it; the next visit sends it again.
    gone = screen.state / "sections" / cached.name
    assert gone.exists()
    gone.unlink()
    again = client.migrate(COMPANION, "screen", timeout=60)
    assert again["transfer"]["sent"] > size, "the missing section was sent again"
    assert hashlib.sha256(gone.read_bytes()).hexdigest() == gone.name
    assert state(client, "screen")["blob_sha256"] == blob_sha(size, 3)
    assert state(client, "screen")["notes"] == ["met Ada"]


def test_a_10_mib_section_migrates(two: tuple[Node, Node, MeshClient]) -> None:
    _robot, screen, client = two
    size = 10 * MIB + 123
    tell(client, "robot", {"blob": size, "seed": 11})
    result = migrate_once_seen(client, COMPANION, "screen")
    blob = next(r for r in screen.refs() if r.component == "carrier-blob")
    assert blob.size > size, "one section holds the whole blob"
    assert result["transfer"]["total"] > size
    assert state(client, "screen")["blob_sha256"] == blob_sha(size, 11)


@pytest.mark.parametrize("two", [{"CMION_MESH_MAX_SECTION": str(MIB)}], indirect=True)
def test_a_section_over_the_targets_limit_is_refused_naming_it(two: tuple[Node, Node, MeshClient]) -> None:
    _robot, screen, client = two
    tell(client, "robot", {"note": "met Ada", "blob": 2 * MIB, "seed": 5})
    with pytest.raises(RequestRejected) as refused:
        migrate_once_seen(client, COMPANION, "screen")
    reason = refused.value.reason
    size = len(msgspec.msgpack.encode(delta_helpers.blob_text(2 * MIB, 5)))
    assert f"section 'carrier-blob' of 'spirit' is {size} bytes" in reason, reason
    assert f"the most a section may hold here is {MIB} (CMION_MESH_MAX_SECTION)" in reason, reason
    wait_for(lambda: client.describe("robot", timeout=1.0).get("inhabitant") == COMPANION, 20, "spirit stays on the robot")
    assert state(client, "robot")["notes"] == ["met Ada"]
    assert not screen.cached(), "nothing of it was stored at the screen"


# --- the target, driven in one process --------------------------------------------------------------


@pytest.fixture
def screen(network: MemoryNetwork, mesh: str, tmp_path: Path) -> Iterator[tuple[Embodiment, MeshClient]]:
    with screen_in_process(network, mesh, tmp_path / "screen") as pair:
        yield pair


def to_screen(client: MeshClient, op: str, message: Any, sender: str = "robot") -> Outcome:
    return client.request("screen", "migration", op, message, sender=sender)


def test_the_target_asks_for_what_it_lacks_and_checks_every_chunk(screen: tuple[Embodiment, MeshClient], tmp_path: Path) -> None:
    body, client = screen
    packed = Identity("s", 1, {"mind": {"entries": ["x"]}, "big": "b" * (INLINE + 10)}).pack_sections()
    big = next(r for r in packed.refs if r.component == "big")
    small = next(r for r in packed.refs if r.component == "mind")
    robot = Holder("s", "robot")
    prepare = robot.prepare("screen", packed.manifest, "a1")
    # A prepare whose sections the target lacks: refused missing_sections, naming them; nothing written.
    lacking = to_screen(client, "prepare", prepare)
    assert lacking.status == "rejected" and lacking.code == Code.MISSING_SECTIONS
    assert sorted(lacking.value["missing"]) == sorted([big.sha256, small.sha256])
    assert "'big'" in lacking.reason and "'mind'" in lacking.reason
    assert body.migration is not None and body.migration.records.get("s") is None
    # Sections without a have first are refused; after it, chunks must come in order and hash right.
    chunk = SectionChunk(big.sha256, 0, packed.data[big.sha256][:1000])
    alone = to_screen(client, "sections", MigrateSections("s", "a1", "robot", "screen", [chunk]))
    assert alone.status == "rejected" and alone.code == Code.NOT_FOUND and "have" in alone.reason
    asked = to_screen(client, "have", have(prepare))
    assert asked.status == "accepted" and asked.value == {"have": []}
    spoofed = to_screen(client, "sections", MigrateSections("s", "a1", "robot", "screen", [chunk]), sender="phone")
    assert spoofed.status == "rejected" and "on behalf of 'robot'" in spoofed.reason
    wrong = bytes(b ^ 1 for b in packed.data[big.sha256])
    bad = to_screen(client, "sections", MigrateSections("s", "a1", "robot", "screen", [SectionChunk(big.sha256, 0, wrong)]))
    assert bad.status == "rejected" and "hash" in bad.reason and "'big'" in bad.reason
    data = packed.data[big.sha256]
    ahead = SectionChunk(big.sha256, 100_000, data[100_000:200_000])  # chunks may come in any order
    assert to_screen(client, "sections", MigrateSections("s", "a1", "robot", "screen", [ahead])).status == "accepted"
    across = SectionChunk(big.sha256, 150_000, data[150_000:250_000])
    overlapping = to_screen(client, "sections", MigrateSections("s", "a1", "robot", "screen", [across]))
    assert overlapping.status == "rejected" and "overlaps" in overlapping.reason and "'big'" in overlapping.reason
    past = to_screen(client, "sections", MigrateSections("s", "a1", "robot", "screen", [SectionChunk(big.sha256, len(data), b"x")]))
    assert past.status == "rejected" and "runs past" in past.reason
    stranger = to_screen(client, "sections", MigrateSections("s", "a1", "robot", "screen", [SectionChunk("0" * 64, 0, b"x")]))
    assert stranger.status == "rejected" and "not in the manifest" in stranger.reason
    for offset in range(0, len(data), 100_000):
        piece = SectionChunk(big.sha256, offset, data[offset:offset + 100_000])
        answer = to_screen(client, "sections", MigrateSections("s", "a1", "robot", "screen", [piece]))
        assert answer.status == "accepted", answer
    assert answer.value == {"stored": [big.sha256]}
    # The small one travels inside the prepare; now it is accepted, and the companion commits. The
    # section's fsync runs beside the prepare's way: it is on the disk, under its name, once the
    # prepare is recorded (incoming).
    with_small = msgspec.structs.replace(prepare, sections=[packed.data[small.sha256]])
    accepted = to_screen(client, "prepare", with_small)
    assert accepted.status == "accepted", accepted
    stored = body.migration.records.sections.path(big.sha256)
    assert hashlib.sha256(stored.read_bytes()).hexdigest() == big.sha256
    assert to_screen(client, "commit", robot.commit(prepare, accepted)).status == "accepted"
    assert body.inhabitant == "s" and body.migration.section("big") == "b" * (INLINE + 10)


def test_a_section_that_cannot_be_synced_refuses_the_prepare_and_records_nothing(
        screen: tuple[Embodiment, MeshClient], monkeypatch: pytest.MonkeyPatch) -> None:
    # A chunk's answer says the section arrived whole and right; its fsync runs beside the prepare's
    # way, and the prepare records incoming only once it is durable: a sync that fails refuses it.
    # Two sections complete in one request: the first failing, the second is still settled (its
    # file and writer thread ended: a thread left running fails the test).
    body, client = screen
    packed = Identity("s", 1, {"big": "b" * (INLINE + 10), "also": "a" * (INLINE + 10)}).pack_sections()
    prepare = Holder("s", "robot").prepare("screen", packed.manifest, "a1")
    assert to_screen(client, "have", have(prepare)).status == "accepted"

    fsync_file = sections.fsync_file

    def full(fd: int, kind: str = "file") -> None:  # the section's own fsync fails; folders sync
        if kind == "file":
            raise OSError(28, "No space left on device")
        fsync_file(fd, kind)

    monkeypatch.setattr(sections, "fsync_file", full)
    chunks = [SectionChunk(ref.sha256, 0, packed.data[ref.sha256]) for ref in packed.refs]
    answer = to_screen(client, "sections", MigrateSections("s", "a1", "robot", "screen", chunks))
    assert answer.status == "accepted" and answer.value == {"stored": sorted(ref.sha256 for ref in packed.refs)}
    refused = to_screen(client, "prepare", prepare)
    assert refused.status == "rejected" and "could not be stored: No space left on device" in refused.reason
    assert body.migration is not None and body.migration.records.get("s") is None
    assert body.migration.uploads.staged("a1", "robot") is None, "the upload ended: its sections are sent again"


def decodes_by_the_prepare(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The components whose sections the prepare decodes itself, from now on."""
    decoded: list[str] = []
    decode = identity.decode_section

    def counted(ref: SectionRef, data: Any, *, name: str = "<identity>") -> Any:
        decoded.append(ref.component)
        return decode(ref, data, name=name)

    monkeypatch.setattr(identity, "decode_section", counted)
    return decoded


def upload_and_commit(client: MeshClient, value: str) -> None:
    """Companion ``s`` with one section ``big`` (``value``) from robot: have, one chunk, prepare, commit."""
    packed = Identity("s", 1, {"big": value}).pack_sections()
    big = packed.refs[0]
    robot = Holder("s", "robot")
    prepare = robot.prepare("screen", packed.manifest, "a1")
    assert to_screen(client, "have", have(prepare)).status == "accepted"
    chunk = SectionChunk(big.sha256, 0, packed.data[big.sha256])
    assert to_screen(client, "sections", MigrateSections("s", "a1", "robot", "screen", [chunk])).status == "accepted"
    accepted = to_screen(client, "prepare", prepare)
    assert accepted.status == "accepted", accepted
    assert to_screen(client, "commit", robot.commit(prepare, accepted)).status == "accepted"


def test_a_section_received_in_chunks_is_decoded_beside_its_sync_not_by_the_prepare(
        screen: tuple[Embodiment, MeshClient], monkeypatch: pytest.MonkeyPatch) -> None:
    # Megabytes decoded on the loop held the prepare's answer: the upload decodes what it completed
    # on a handshake thread, and the prepare takes the value. Bytes that hash right but are not plain
    # data are still refused by the prepare, naming the section.
    body, client = screen
    decoded_by_the_prepare = decodes_by_the_prepare(monkeypatch)
    value = "b" * (INLINE + 10)
    big = Identity("s", 1, {"big": value}).pack_sections().refs[0]
    bad = b"\xc1" * big.size  # never valid MessagePack
    digest = hashlib.sha256(bad).hexdigest()
    manifest = Identity("t", 1, {"big": value}).pack_sections().manifest.replace(big.sha256.encode(), digest.encode())
    offer = Holder("t", "robot").prepare("screen", manifest, "b1")
    asked = to_screen(client, "have", have(offer))
    assert asked.status == "accepted", asked
    taken = to_screen(client, "sections", MigrateSections("t", "b1", "robot", "screen", [SectionChunk(digest, 0, bad)]))
    assert taken.status == "accepted", "whole and hashing right"
    refused = to_screen(client, "prepare", offer)
    assert refused.status == "rejected" and "section 'big': not plain msgpack data" in refused.reason
    assert body.migration is not None and body.migration.records.get("t") is None
    decoded_by_the_prepare.clear()

    upload_and_commit(client, value)
    assert decoded_by_the_prepare == []
    assert body.inhabitant == "s" and body.migration.section("big") == value


def test_past_its_bound_an_upload_leaves_the_decoding_to_the_prepare(
        screen: tuple[Embodiment, MeshClient], monkeypatch: pytest.MonkeyPatch) -> None:
    # Values decoded ahead are held beside their bytes until the prepare: a sender that never
    # prepares would cost twice what it sent. Past DECODE_AHEAD, the prepare decodes.
    body, client = screen
    monkeypatch.setattr(uploads, "DECODE_AHEAD", INLINE)
    decoded_by_the_prepare = decodes_by_the_prepare(monkeypatch)
    value = "b" * (INLINE + 10)
    upload_and_commit(client, value)
    assert decoded_by_the_prepare == ["big"]
    assert body.migration is not None and body.migration.section("big") == value


def test_a_stranger_cannot_fill_the_disk_with_sections(screen: tuple[Embodiment, MeshClient], monkeypatch: pytest.MonkeyPatch) -> None:
    body, client = screen
    assert body.migration is not None
    store = body.migration.records.sections
    monkeypatch.setattr(store, "max_cache", 2 * MIB)
    # An offer whose sections would not fit in the cache is refused before a byte of them is sent.
    huge = Identity("x0", 1, {"a": "a" * (3 * MIB)}).pack_sections()
    holder = Holder("x0", "x")
    refused = to_screen(client, "have", have(holder.prepare("screen", huge.manifest, "h0")), sender="x")
    assert refused.status == "rejected" and "section cache" in refused.reason
    # First-contact prepares of many companions with their sections inside, each aborted: the cache stays bounded.
    for i in range(12):
        packed = Identity(f"x{i + 1}", 1, {"mind": {"blob": f"{i}" * (200 * 1024)}}).pack_sections()
        stranger = Holder(f"x{i + 1}", "x")
        prepare = stranger.prepare("screen", packed.manifest, f"p{i}")
        answer = to_screen(client, "prepare", msgspec.structs.replace(prepare, sections=list(packed.data.values())), sender="x")
        if answer.status == "accepted":
            assert to_screen(client, "abort", MigrateAbort(f"x{i + 1}", 1, f"p{i}"), sender="x").status == "accepted"
    assert store.size <= store.max_cache
    assert sum(p.stat().st_size for p in store.dir.iterdir()) <= store.max_cache


# --- the store and the format ------------------------------------------------------------------------


def test_a_chunk_received_is_hashed_while_its_write_goes_on_and_is_synced_before_it_is_named(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The loop takes the next chunk (or another request) while a chunk is written: ``add`` waits
    # for neither the hash nor the disk. The last chunk's answer says the bytes are whole and hash
    # right (``finish``) while the device may still be writing them; settling (on a handshake
    # thread, before the prepare records incoming) waits for those writes, then syncs and names it.
    store = SectionStore(tmp_path / "sections")
    data = bytes(range(256)) * 64
    ref = SectionRef("blob", hashlib.sha256(data).hexdigest(), len(data))
    incoming = store.receive(ref)
    gate, written = threading.Event(), threading.Event()
    pwrite = os.pwrite

    def held(fd: int, chunk: Any, offset: int) -> int:
        gate.wait(10.0)
        done = pwrite(fd, chunk, offset)
        written.set()
        return done

    monkeypatch.setattr(os, "pwrite", held)
    half = len(data) // 2
    assert incoming.add(half, data[half:]) == "" and incoming.add(0, data[:half]) == ""
    assert not written.is_set() and incoming.complete, "both chunks taken, neither written yet"
    assert incoming.finish(settle=False) == "" and incoming.data == data, "checked while the writes wait"
    settled = threading.Thread(target=incoming.settle)
    settled.start()
    try:
        assert not store.path(ref.sha256).exists(), "not named before its bytes are written"
    finally:
        gate.set()
        settled.join(10.0)
    assert store.path(ref.sha256).read_bytes() == data


def test_a_chunk_that_cannot_be_written_fails_the_section_and_leaves_nothing(tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    store = SectionStore(tmp_path / "sections")
    data = b"x" * 1000
    ref = SectionRef("blob", hashlib.sha256(data).hexdigest(), len(data))
    incoming = store.receive(ref)

    def full(fd: int, chunk: Any, offset: int) -> int:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "pwrite", full)
    assert incoming.add(0, data) == ""
    with pytest.raises(OSError, match="No space left"):
        incoming.finish()
    assert not store.path(ref.sha256).exists() and list(store.dir.iterdir()) == [], "no name, no temporary file"




def test_sections_are_checked_on_every_read_and_the_cache_evicts_the_oldest_unnamed(tmp_path: Path) -> None:
    store = SectionStore(tmp_path / "sections", max_cache=300)
    assert not store.dir.exists(), "made at the first write"
    data = {hashlib.sha256(bytes([i]) * 100).hexdigest(): bytes([i]) * 100 for i in range(3)}
    refs = [SectionRef(f"c{i}", digest, 100) for i, digest in enumerate(data)]
    assert store.write(data) == list(data) and store.write(data) == [], "written once"
    assert oct(store.dir.stat().st_mode & 0o777) == "0o700"
    assert all(oct(store.path(r.sha256).stat().st_mode & 0o777) == "0o600" for r in refs)
    assert store.read(refs[0]) == bytes([0]) * 100
    store.path(refs[1].sha256).write_bytes(bytes([9]) * 100)
    with pytest.raises(ConfigError, match=rf"{refs[1].sha256}: section 'c1' was altered at rest"):
        store.read(refs[1])
    with pytest.raises(ConfigError, match="altered at rest"):  # compared with bytes known to hash right
        store.read(refs[1], known=bytes([1]) * 100)
    assert store.read(refs[0], known=bytes([0]) * 100) == bytes([0]) * 100
    store.path(refs[2].sha256).unlink()
    found, errors = store.read_many(refs)
    assert set(found) == {refs[0].sha256} and "missing" in errors[refs[2].sha256]
    # Over the bound, the least recently used sections that nothing names or pins go first.
    store.write(data)  # the missing one again
    more = {hashlib.sha256(b"m" * 100).hexdigest(): b"m" * 100}
    store.pin("staging", more)
    store.write(more)
    removed = store.evict(keep={refs[0].sha256})
    assert len(removed) == 1 and removed[0] in {refs[1].sha256, refs[2].sha256}
    assert store.size == 300 and store.path(refs[0].sha256).exists() and store.path(next(iter(more))).exists()


def test_a_version_1_identity_at_rest_still_loads_and_is_rewritten_as_version_2(tmp_path: Path) -> None:
    old = Identity(COMPANION, 3, {"mind": {"entries": ["met Ada"]}, "face": {"smile": 0.5}})
    stored = Records(tmp_path)
    stored.put(Record(COMPANION, "active", 3), document=old.pack())
    assert b'SchemaVersion="1"' in (stored.document(COMPANION) or b"")
    assert stored.identity(COMPANION) == old
    packed = old.pack_sections()
    assert b'SchemaVersion="2"' in packed.manifest and b"met Ada" not in packed.manifest
    again = Records(tmp_path)
    record = again.get(COMPANION)
    assert record is not None
    again.put(record, document=packed.manifest, sections=packed.data)
    assert Records(tmp_path).identity(COMPANION) == Identity(COMPANION, 3, old.sections, 2)
    assert Records(tmp_path).damaged() == {}


def test_an_unchanged_section_is_neither_encoded_nor_hashed_again() -> None:
    memo = SectionMemo()
    blob = "z" * 100_000
    first = Identity("s", 1, {"blob": blob, "mind": {"n": 1}}).pack_sections(memo)
    again = Identity("s", 1, {"blob": blob, "mind": {"n": 2}}).pack_sections(memo)
    sha = next(r.sha256 for r in first.refs if r.component == "blob")
    assert again.data[sha] is first.data[sha], "the very same string: its bytes are reused"
    joined = "".join(["z" * 50_000, "z" * 50_000])  # equal, another object: encoded, its hash kept
    copy = Identity("s", 1, {"blob": joined, "mind": {"n": 2}}).pack_sections(memo)
    assert copy.manifest == again.manifest and copy.data[sha] == first.data[sha]
    assert memo.held()[sha] == first.data[sha]
    arrived = read_manifest(again.manifest).identity(again.data, memo.values())
    assert arrived.sections["blob"] is joined, "a string held here already is not decoded again"
    assert arrived.sections["mind"] == {"n": 2}


def test_manifest_faults_are_named(monkeypatch: pytest.MonkeyPatch) -> None:
    packed = Identity("s", 1, {"mind": [1, 2]}).pack_sections()
    ref = packed.refs[0]
    with pytest.raises(identity.MissingSections, match=r"<net>: sections not at hand: 'mind'") as missing:
        identity.unpack(packed.manifest, name="<net>")
    assert missing.value.missing == [ref]
    inline = packed.manifest.replace(b"/>", b">[1]</Section>", 1)
    with pytest.raises(ConfigError, match="names its bytes by Sha256 and Size and holds no text"):
        read_manifest(inline)
    v1 = packed.manifest.replace(b'SchemaVersion="2"', b'SchemaVersion="1"')
    with pytest.raises(ConfigError, match="Sha256 and Size belong to SchemaVersion 2"):
        read_manifest(v1)
    with pytest.raises(ConfigError, match=r"section 'mind' .* is 5 bytes, the manifest says 3"):
        identity.unpack(packed.manifest, sections={ref.sha256: b"\x93\x01\x02\x03\x04"[:5]})
    with pytest.raises(ConfigError, match="not plain msgpack data"):
        identity.unpack(packed.manifest, sections={ref.sha256: b"\xc4\x01x"})
    monkeypatch.setenv("CMION_MESH_MAX_SECTION", "2")
    with pytest.raises(ConfigError, match=r"section 'mind' of 's' is 3 bytes; the most a section may hold here is 2"):
        read_manifest(packed.manifest)
    with pytest.raises(ValueError, match=r"section 'mind' of 's' is 3 bytes; the most a section may hold is 2 \(CMION_MESH_MAX_SECTION\)"):
        Identity("s", 1, {"mind": [1, 2]}).pack_sections()
    monkeypatch.setenv("CMION_MESH_MAX_SECTION", "lots")
    with pytest.raises(ConfigError, match="CMION_MESH_MAX_SECTION='lots': not a number of bytes"):
        max_section()
    monkeypatch.delenv("CMION_MESH_MAX_SECTION")
    assert max_section() == identity.MAX_SECTION == 256 * MIB
    assert sections.MAX_CACHE == 1024 * MIB
