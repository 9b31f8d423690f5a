"""What a target holds for migrations is bounded, against real daemons in separate processes.

A process posing as strangers uploads sections (``have`` then ``migrate_sections``) that never
become a prepare: the section folder stays within its bound while it grows, over-limit uploads are
refused naming their sender, and idle uploads expire (their bytes deleted). A fake source whose
prepare was accepted never commits, aborts or answers: the target drops the attempt at its bound,
counted from the prepare across restarts. After each, the real companion still migrates there.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError, RequestRejected
from cmion_mesh.messages import Code, MigrateAbort, MigrateSections, Outcome, SectionChunk
from cmion_mesh.migration.handshake import have
from cmion_mesh.migration.identity import Identity
from cmion_mesh.migration.ledger import read_ledger
from cmion_mesh.migration.manager import MigrationManager
from cmion_mesh.migration.outgoing import INLINE
from cmion_mesh.procs import free_port
from cmion_mesh.testing.wait import migrate_once_seen, wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.memory import MemoryNetwork
from cmion_mesh.transport.zenoh import ZenohTransport

from .helpers.custody_helpers import Holder
from .helpers.remote_helpers import Node, diary_embodiment_config, screen_in_process

pytestmark = pytest.mark.timeout(180)

MIB = 1024 * 1024
#: The target's bounds in these tests: its section folder, what one sender may upload, idle seconds.
CACHE = 4 * MIB
UPLOAD = 2 * MIB
IDLE = 3.0


@pytest.fixture
def mesh_of_two(tmp_path: Path, mesh: str, request: pytest.FixtureRequest) -> Iterator[tuple[Node, Node, ZenohTransport, MeshClient]]:
    """a (spirit's home) and b (empty, with the environment the test's parameter gives), a client
    joined to both."""
    ports = {"a": free_port(), "b": free_port()}
    env: dict[str, str] = getattr(request, "param", {})
    nodes = [Node(name, mesh, diary_embodiment_config(tmp_path / name, name), tmp_path / f"state-{name}", port,
                  [f"tcp/127.0.0.1:{p}" for n, p in ports.items() if n != name],
                  companion="spirit" if name == "a" else None, env=dict(env) if name == "b" else {})
             for name, port in ports.items()]
    try:
        for node in nodes:
            node.start()
        with ZenohTransport(TransportConfig(connect=tuple(n.endpoint for n in nodes), multicast=False)) as t:
            client = MeshClient(t, mesh)
            wait_for(lambda: client.describe("a", timeout=1.0).get("inhabitant") == "spirit", 30, "spirit born on a")
            client.wait_for_embodiment("b", timeout=20)
            yield nodes[0], nodes[1], t, client
    finally:
        for node in nodes:
            node.stop()


def folder_bytes(state: Path) -> int:
    """Bytes of every file in the section folder, sections being received included."""
    folder = state / "sections"
    total = 0
    for path in folder.iterdir() if folder.exists() else ():
        try:
            total += path.stat().st_size
        except FileNotFoundError:  # a section given its name meanwhile (counted under it, if listed)
            continue
    return total


class Stranger:
    """Offers companions of its own to a target as ``sender``: uploads, prepares."""

    def __init__(self, client: MeshClient, target: str, sender: str) -> None:
        self.client, self.target, self.sender = client, target, sender

    def ask(self, op: str, message: Any) -> Outcome:
        return self.client.request(self.target, "migration", op, message, sender=self.sender, timeout=20)

    def prepare(self, companion: str, attempt: str) -> Outcome:
        """A prepare of a small companion of its own, its sections inside."""
        packed = Identity(companion, 1, {"mind": {"entries": [f"{companion} is not spirit"]}}).pack_sections()
        prepare = Holder(companion, self.sender).prepare(self.target, packed.manifest, attempt)
        return self.ask("prepare", msgspec.structs.replace(prepare, sections=list(packed.data.values())))

    def offer(self, companion: str, size: int, attempt: str) -> tuple[Outcome, Any]:
        """``have`` of a companion of its own whose one section is about ``size`` bytes."""
        packed = Identity(companion, 1, {"blob": f"{companion}-{attempt}-".ljust(size, "z")}).pack_sections()
        prepare = Holder(companion, self.sender).prepare(self.target, packed.manifest, attempt)
        return self.ask("have", have(prepare)), packed

    def upload(self, companion: str, attempt: str, packed: Any, chunk: int = 512 * 1024) -> list[Outcome]:
        """Every section of ``packed`` in chunks; the answers, up to the first refusal."""
        answers = []
        for ref in packed.refs:
            data = packed.data[ref.sha256]
            for offset in range(0, ref.size, chunk):
                piece = SectionChunk(ref.sha256, offset, bytes(data[offset:offset + chunk]))
                answers.append(self.ask("sections", MigrateSections(companion, attempt, self.sender, self.target, [piece])))
                if answers[-1].status != "accepted":
                    return answers
        return answers


ENV = {"CMION_MESH_MAX_CACHE": str(CACHE), "CMION_MESH_MAX_UPLOAD": str(UPLOAD), "CMION_MESH_UPLOAD_IDLE": str(IDLE)}


@pytest.mark.parametrize("mesh_of_two", [ENV], indirect=True)
def test_uploads_that_never_become_a_prepare_are_bounded_and_expire(
        mesh_of_two: tuple[Node, Node, ZenohTransport, MeshClient]) -> None:
    _a, b, _t, client = mesh_of_two
    peak = 0

    def measured() -> None:
        nonlocal peak
        peak = max(peak, folder_bytes(b.state))
        assert peak <= CACHE, f"the section folder of b holds {peak} bytes, over its bound of {CACHE}"

    # One sender, uploads of 1.5 MiB for twelve companions of its own, one after the other, never
    # preparing: each new have ends the sender's previous upload and deletes what it wrote.
    x = Stranger(client, "b", "x")
    for i in range(12):
        answer, packed = x.offer(f"c{i}", 3 * MIB // 2, f"x{i}")
        assert answer.status == "accepted" and answer.value == {"have": []}, answer
        assert all(a.status == "accepted" for a in x.upload(f"c{i}", f"x{i}", packed))
        measured()
    # Its bytes are written beside the answers (a chunk is answered once hashed): held, they are
    # all on disk within moments, and stay until the upload has been idle for IDLE seconds.
    wait_for(lambda: folder_bytes(b.state) >= 3 * MIB // 2, IDLE / 2, "the last upload held, for a prepare that may still come")
    # More than one sender may upload ahead of its prepare: refused before a byte is sent, naming it.
    over, _ = x.offer("big", 3 * MIB, "x-big")
    assert over.status == "rejected" and over.code == Code.INVALID, over
    assert "'x'" in over.reason and f"over the {UPLOAD} one sender may upload" in over.reason, over.reason
    assert "CMION_MESH_MAX_UPLOAD" in over.reason
    # Several senders together: the folder's bound holds as it grows; the chunk over it is refused
    # busy, naming the sender whose chunk it is.
    refused: list[tuple[str, Outcome]] = []
    for name in ("y1", "y2", "y3"):
        y = Stranger(client, "b", name)
        answer, packed = y.offer(f"d-{name}", 3 * MIB // 2, f"{name}-1")
        assert answer.status == "accepted", answer
        answers = y.upload(f"d-{name}", f"{name}-1", packed)
        measured()
        refused += [(name, a) for a in answers if a.status != "accepted"]
    # x's upload and y1's fit (3 MiB); a third 1.5 MiB does not, whether x's has expired meanwhile or not
    assert refused and "y1" not in {name for name, _ in refused}, refused
    for name, answer in refused:
        assert answer.code == Code.BUSY and "section store of 'b' is full" in answer.reason, answer
        assert f"from {name!r} are refused" in answer.reason and "CMION_MESH_MAX_CACHE" in answer.reason, answer.reason
    # Nobody prepares: every upload expires once idle, and its bytes are deleted.
    wait_for(lambda: not list((b.state / "sections").iterdir()), 10 * IDLE, "the idle uploads are deleted, every file")
    # The companion itself still migrates to b, and back.
    migrate_once_seen(client, "spirit", "b")
    wait_for(lambda: client.describe("b", timeout=1.0).get("inhabitant") == "spirit", 30, "spirit on b")
    assert client.migrate("spirit", "a", timeout=30)["target"] == "a"
    assert read_ledger(b.state).records["spirit"].state == "released"


# --- the target's uploads, driven in one process -----------------------------------------------------


@pytest.fixture
def screen(network: MemoryNetwork, mesh: str, tmp_path: Path) -> Iterator[tuple[Embodiment, MeshClient]]:
    with screen_in_process(network, mesh, tmp_path / "screen") as pair:
        yield pair


def test_an_upload_ends_with_its_staging_and_counts_from_its_first_chunk(screen: tuple[Embodiment, MeshClient]) -> None:
    """Replaced by its sender's newer have, or aborted, an upload's sections are deleted, but those
    the newer one holds; bytes being received count in the store's size; a prepare keeps them."""
    body, client = screen
    assert body.migration is not None
    store = body.migration.records.sections

    def ask(op: str, message: Any, sender: str) -> Outcome:
        answer = client.request("screen", "migration", op, message, sender=sender)
        assert answer.status == "accepted", answer
        return answer

    def chunk(packed: Any, component: str, start: int = 0, end: int | None = None) -> SectionChunk:
        ref = next(r for r in packed.refs if r.component == component)
        return SectionChunk(ref.sha256, start, bytes(packed.data[ref.sha256][start:end]))

    packed = Identity("s", 1, {"one": "1" * (INLINE + 10), "two": "2" * (INLINE + 10)}).pack_sections()
    one = next(r for r in packed.refs if r.component == "one")
    robot = Holder("s", "robot")
    prepare = robot.prepare("screen", packed.manifest, "a1")
    assert ask("have", have(prepare), "robot").value == {"have": []}
    ask("sections", MigrateSections("s", "a1", "robot", "screen", [chunk(packed, "one"), chunk(packed, "two", 0, 1000)]), "robot")
    assert store.size == one.size + 1000, "the bytes of a section being received count from its first chunk"
    # The same attempt's have again (as after missing_sections): what the first one stored is held and kept.
    assert ask("have", have(prepare), "robot").value == {"have": [one.sha256]}
    assert store.path(one.sha256).exists() and store.size == one.size
    # A stranger's upload, replaced by its next have, is deleted; aborted, too.
    for i in range(2):
        theirs = Identity(f"t{i}", 1, {"blob": f"t{i}".ljust(INLINE + 10, "t")}).pack_sections()
        stranger = Holder(f"t{i}", "x")
        ask("have", have(stranger.prepare("screen", theirs.manifest, f"t{i}")), "x")
        ask("sections", MigrateSections(f"t{i}", f"t{i}", "x", "screen", [chunk(theirs, "blob")]), "x")
        # Arrived whole and checked: named once synced, beside what comes next.
        wait_for(lambda: store.path(theirs.refs[0].sha256).exists(), 10, "the section named once synced")  # noqa: B023
        if i == 0:
            first = theirs.refs[0].sha256
        else:
            assert not store.path(first).exists(), "replaced by x's next have: deleted"
            ask("abort", MigrateAbort(f"t{i}", 1, f"t{i}"), "x")
            assert not store.path(theirs.refs[0].sha256).exists(), "aborted: deleted"
    assert store.size == one.size
    # The companion's upload goes on and becomes a prepare: its sections stay, named by the record.
    ask("sections", MigrateSections("s", "a1", "robot", "screen", [chunk(packed, "two")]), "robot")
    accepted = ask("prepare", prepare, "robot")
    ask("commit", robot.commit(prepare, accepted), "robot")
    assert body.inhabitant == "s" and body.migration.section("one") == "1" * (INLINE + 10)
    assert body.migration.records.damaged() == {}


def test_bad_bounds_in_the_environment_are_named(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    for variable, value in (("CMION_MESH_MAX_CACHE", "lots"), ("CMION_MESH_MAX_UPLOAD", "0"), ("CMION_MESH_UPLOAD_IDLE", "-1"),
                            ("CMION_MESH_INCOMING_TIMEOUT", "soon")):
        with monkeypatch.context() as m:
            m.setenv(variable, value)
            with pytest.raises(ConfigError, match=rf"{variable}='{value}': not a number of (bytes|seconds) between"):
                MigrationManager(tmp_path / "state")


BOUND = 6.0


def b_record(b: Node, companion: str) -> dict[str, Any] | None:
    """b's record of ``companion``, read as a file (a live daemon's folder is never tidied by a test)."""
    record = read_ledger(b.state).records.get(companion)
    return None if record is None else msgspec.to_builtins(record)


def dropped(b: Node, companion: str) -> bool:
    record = b_record(b, companion)
    return record is not None and record["state"] == "dropped"


@pytest.mark.parametrize("mesh_of_two", [{"CMION_MESH_INCOMING_TIMEOUT": str(BOUND)}], indirect=True)
def test_a_prepare_never_committed_is_dropped_at_its_bound_across_restarts(
        mesh_of_two: tuple[Node, Node, ZenohTransport, MeshClient], mesh: str) -> None:
    _a, b, _t, client = mesh_of_two

    def occupy(companion: str) -> float:
        """A fake source's prepare, accepted by b; then the fake source is gone (it never commits,
        aborts or answers b's questions). The prepare's durable time."""
        with ZenohTransport(TransportConfig(connect=(b.endpoint,), multicast=False)) as fake_t:
            fake = MeshClient(fake_t, mesh)
            fake.wait_for_embodiment("b", timeout=20)
            answer = Stranger(fake, "b", "x").prepare(companion, f"{companion}-1")
            assert answer.status == "accepted", answer
        record = b_record(b, companion)
        assert record is not None and record["state"] == "incoming" and record["peer"] == "x", record
        assert record["since"] > 0
        return float(record["since"])

    def restart_b() -> None:
        assert b.daemon is not None
        b.daemon.kill()
        b.start()

    # Restarted in between: still occupied, then dropped at the bound.
    occupy("x1")
    with pytest.raises(RequestRejected, match="occupied by companion 'x1'"):
        migrate_once_seen(client, "spirit", "b")
    restart_b()
    record = b_record(b, "x1")
    assert record is not None and record["state"] in ("incoming", "dropped")
    wait_for(lambda: dropped(b, "x1"), BOUND + 30, "b drops the attempt nobody commits")
    # Down past the bound: dropped as b starts, the bound counted from the prepare, not from the start.
    since = occupy("x2")
    assert b.daemon is not None
    b.daemon.kill()
    wait_for(lambda: time.time() > since + BOUND, BOUND + 10, "the attempt's bound passes while b is down")
    b.start()
    wait_for(lambda: dropped(b, "x2"), BOUND / 2, "b drops the attempt whose bound passed, as it starts")
    # b is free again: the companion itself migrates there.
    client.wait_for_embodiment("b", timeout=20)
    assert migrate_once_seen(client, "spirit", "b")["target"] == "b"
    wait_for(lambda: client.describe("b", timeout=1.0).get("inhabitant") == "spirit", 30, "spirit lives on b")
