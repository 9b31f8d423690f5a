"""The ledger: one append per durable step, torn tails ignored, compaction, records of older versions migrated.

Pure file work in one process, and migrations between two embodiments on the in-memory transport
(compaction at every step, fsyncs counted). The kill -9 crash points inside the ledger are
``test_ledger_crash``'s (real processes).
"""

from __future__ import annotations

import gc
import json
from collections.abc import Iterator
from pathlib import Path

import msgspec
import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError
from cmion_mesh.messages import MindMessage
from cmion_mesh.migration import crash, custody, signing
from cmion_mesh.migration.identity import Identity
from cmion_mesh.migration.journal import BOUND_ENV, HEADER, LOG
from cmion_mesh.migration.ledger import Record, Records, read_ledger
from cmion_mesh.migration.sections import FSYNCS
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .helpers.memory_bodies import body, close, ready_to_migrate, robot_and_screen
from .helpers.remote_helpers import Diary

pytestmark = pytest.mark.timeout(120)


def born(records: Records, companion: str = "spirit") -> tuple[Record, bytes, bytes]:
    """A companion born in ``records``: its active record, document and custody key."""
    packed = Identity(companion, 1, {"mind": {"entries": ["met Ada"]}}).pack_sections()
    private = signing.new_key()
    chain = [custody.birth(companion, "robot", private, packed.manifest)]
    record = records.put(Record(companion, "active", 1, chain=chain, public_key=signing.encode_public(chain[0].public_key)),
                         document=packed.manifest, sections=packed.data, key=private)
    return record, packed.manifest, private


class Killed(BaseException):
    """Stands for SIGKILL at a crash point, in one process."""


@pytest.fixture
def killed_at(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    def die(point: str) -> None:
        raise Killed(point)

    monkeypatch.setattr(crash, "die", die)
    yield


def test_a_torn_last_entry_cut_at_every_byte_is_ignored_and_the_state_before_it_read(tmp_path: Path) -> None:
    folder = tmp_path / "state"
    records = Records(folder)
    active, document, key = born(records)
    before = (folder / LOG).read_bytes()
    prepared = records.put(msgspec.structs.replace(active, state="prepared", seq=1, attempt="a1", peer="screen"))
    records.close()
    whole = (folder / LOG).read_bytes()
    assert whole.startswith(before) and len(whole) > len(before) + HEADER.size
    for cut in range(len(before), len(whole)):
        torn = tmp_path / f"torn-{cut}"
        torn.mkdir()
        (torn / LOG).write_bytes(whole[:cut])
        again = Records(torn)
        assert again.get("spirit") == active, f"cut at byte {cut}"
        assert again.document("spirit") == document and again.key("spirit") == key
        again.close()
        assert (torn / LOG).read_bytes() == before, "the torn tail is cut off when the ledger is opened"
    # whole, the entry is read
    assert Records(folder).get("spirit") == prepared


def test_a_torn_tail_is_cut_off_and_the_next_step_appended_after_the_state_before_it(tmp_path: Path) -> None:
    folder = tmp_path / "state"
    records = Records(folder)
    active, _document, _key = born(records)
    records.close()
    with open(folder / LOG, "ab") as f:
        f.write(b"CMLJ\x10\x00")  # a header cut short
    records = Records(folder)
    handed = records.put(msgspec.structs.replace(active, state="prepared", seq=1, attempt="a1", peer="screen"))
    records.close()
    assert Records(folder).get("spirit") == handed


def test_damage_before_intact_entries_is_refused_naming_the_file_and_the_offset(tmp_path: Path) -> None:
    folder = tmp_path / "state"
    records = Records(folder)
    active, _document, _key = born(records)
    records.put(msgspec.structs.replace(active, state="prepared", seq=1, attempt="a1", peer="screen"))
    records.close()
    data = bytearray((folder / LOG).read_bytes())
    data[HEADER.size + 3] ^= 0xFF  # inside the first entry's payload
    (folder / LOG).write_bytes(bytes(data))
    with pytest.raises(ConfigError) as refused:
        Records(folder)
    assert str(folder / LOG) in str(refused.value) and "damaged at byte 0" in str(refused.value)


def test_each_step_is_one_append_and_one_fdatasync(tmp_path: Path) -> None:
    records = Records(tmp_path / "state", bound=1 << 30)
    active, _document, _key = born(records)
    before = FSYNCS.snapshot()
    for state, seq in (("prepared", 1), ("handed", 1)):
        records.put(msgspec.structs.replace(active, state=state, seq=seq, attempt="a1", peer="screen"))
    after = FSYNCS.snapshot()
    assert after["append"] - before["append"] == 2
    assert after["total"] - before["total"] == 2, "no temporary file, no rename, no folder fsync"
    assert records.journal.appends == 3


def aged(records: Records, links: int) -> tuple[Record, bytes]:
    """A companion born in ``records`` whose chain of custody has ``links`` links (as after that
    many migrations), active here: its record and the custody key of its last link."""
    active, document, key = born(records)
    chain = list(active.chain)
    for epoch in range(2, links + 1):
        following = signing.new_key()
        chain.append(custody.hand_on(key, "spirit", epoch, "robot" if epoch % 2 else "screen", signing.public_of(following),
                                     f"a{epoch}", custody.digest(document)))
        key = following
    record = records.put(msgspec.structs.replace(active, epoch=links, chain=chain), document=document, key=key)
    return record, key


def test_an_entry_keeps_the_chain_written_before_it_and_carries_only_its_new_links(tmp_path: Path) -> None:
    """A chain gains a link a migration and is the same at most steps: an entry written whole at
    every step grew with the companion's age (a 1000-link chain is about 170 KiB)."""
    folder = tmp_path / "state"
    records = Records(folder, bound=1 << 30)
    active, key = aged(records, 600)
    steps = [msgspec.structs.replace(active, state="prepared", seq=1, attempt="a601", peer="screen"),
             msgspec.structs.replace(active, state="handed", seq=1, attempt="a601", peer="screen")]
    link = custody.hand_on(key, "spirit", 601, "screen", signing.public_of(signing.new_key()), "a601", custody.digest(b"d"))
    steps.append(msgspec.structs.replace(active, state="active", epoch=601, chain=[*active.chain, link]))
    for step in steps:
        size = (folder / LOG).stat().st_size
        written = records.put(step)
        assert (folder / LOG).stat().st_size - size < 1024, f"{step.state}: the entry carries the whole chain"
    assert written.chain == [*active.chain, link]
    records.close()
    assert read_ledger(folder).records["spirit"].chain == written.chain, "tools read it whole too"
    again = Records(folder, bound=1)  # the next step compacts: chains are written whole then
    assert again.get("spirit") == written, "read at start, each entry's chain is whole again"
    assert len(again.get("spirit").chain) == 601  # type: ignore[union-attr]
    again.put(msgspec.structs.replace(written, peer="x"))
    assert again.journal.compactions == 1
    again.close()
    assert Records(folder).get("spirit").chain == written.chain  # type: ignore[union-attr]


def test_an_entry_that_keeps_links_the_entries_before_it_lack_is_refused_naming_the_file(tmp_path: Path) -> None:
    folder = tmp_path / "state"
    records = Records(folder, bound=1 << 30)
    active, _key = aged(records, 5)
    records.put(msgspec.structs.replace(active, state="prepared", seq=1, attempt="a6", peer="screen"))
    records.close()
    data = (folder / LOG).read_bytes()
    first = HEADER.size + HEADER.unpack_from(data)[1]
    second = first + HEADER.size + HEADER.unpack_from(data, first)[1]
    (folder / LOG).write_bytes(data[:first] + data[second:])  # the entry of the aged chain taken out
    with pytest.raises(ConfigError) as refused:
        Records(folder)
    assert str(folder / LOG) in str(refused.value) and "keeps 5 links" in str(refused.value)


def test_compaction_keeps_the_state_and_bounds_the_log(tmp_path: Path) -> None:
    folder = tmp_path / "state"
    records = Records(folder, bound=4096)
    active, document, key = born(records)
    record = active
    for i in range(200):
        record = records.put(msgspec.structs.replace(record, peer=f"peer-{i}"))
        assert (folder / LOG).stat().st_size <= 4096 + 2048
    assert records.journal.compactions > 0
    records.close()
    again = Records(folder)
    assert again.get("spirit") == record and again.document("spirit") == document and again.key("spirit") == key


def test_a_custody_key_leaves_the_disk_with_the_companion(tmp_path: Path) -> None:
    folder = tmp_path / "state"
    records = Records(folder, bound=1 << 30)
    active, _document, key = born(records)
    assert key in (folder / LOG).read_bytes()
    records.put(msgspec.structs.replace(active, state="released", seq=1, attempt="a1", peer="screen"))
    assert key not in (folder / LOG).read_bytes(), "compacted at once: the former host's key is gone from the log"
    assert records.key("spirit") is None and read_ledger(folder).keys == {}


@pytest.mark.parametrize("point", ["ledger:torn:prepared", "ledger:compacting:prepared", "ledger:compacted:prepared"])
def test_a_crash_inside_the_ledger_leaves_the_state_before_or_after_the_step(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, killed_at: None, point: str) -> None:
    folder = tmp_path / "state"
    records = Records(folder, bound=1)  # compacted after every entry
    active, document, key = born(records)
    prepared = msgspec.structs.replace(active, state="prepared", seq=1, attempt="a1", peer="screen")
    monkeypatch.setenv(crash.CRASH_ENV, point)
    with pytest.raises(Killed):
        records.put(prepared)
    monkeypatch.delenv(crash.CRASH_ENV)
    records.journal.close()  # the process is gone: its descriptor with it
    again = Records(folder)
    got = again.get("spirit")
    assert got is not None
    expected = "active" if point.startswith("ledger:torn") else "prepared"
    assert got.state == expected and again.document("spirit") == document and again.key("spirit") == key


def test_records_of_an_older_version_are_migrated_once(tmp_path: Path) -> None:
    folder = tmp_path / "state"
    folder.mkdir()
    packed = Identity("spirit", 1, {"mind": {"entries": ["met Ada"]}}).pack_sections()
    private = signing.new_key()
    chain = [custody.birth("spirit", "robot", private, packed.manifest)]
    digest = custody.digest(packed.manifest).hex()
    record = Record("spirit", "active", 1, chain=chain, public_key=signing.encode_public(chain[0].public_key),
                    document=digest, seal=custody.sign_seal(private, "spirit", packed.manifest))
    (folder / "spirit.record.json").write_bytes(msgspec.json.encode(record))
    (folder / f"spirit.{digest}.identity.xml").write_bytes(packed.manifest)
    (folder / "spirit.key").write_bytes(private)
    (folder / "old.record.json").write_text(json.dumps({"companion": "old", "state": "dropped", "epoch": 3}))
    records = Records(folder)
    records.sections.write(packed.data)
    assert records.get("spirit") == record and records.key("spirit") == private
    assert records.get("old") is not None and records.get("old").epoch == 3  # type: ignore[union-attr]
    assert records.identity("spirit") == Identity("spirit", 1, {"mind": {"entries": ["met Ada"]}}, 2)
    records.put(msgspec.structs.replace(record, seq=2), document=packed.manifest)  # the companion moves on
    records.close()
    assert sorted(p.name for p in folder.iterdir() if p.name != "sections") == [LOG]
    again = Records(folder)
    assert again.get("spirit") is not None and again.get("spirit").seq == 2  # type: ignore[union-attr]
    assert again.key("spirit") == private and again.document("spirit") == packed.manifest


def test_a_migration_interrupted_after_the_ledger_was_written_keeps_the_ledger(tmp_path: Path) -> None:
    folder = tmp_path / "state"
    records = Records(folder)
    active, _document, _key = born(records)
    records.close()
    stale = msgspec.structs.replace(active, epoch=1, state="dropped")
    (folder / "spirit.record.json").write_bytes(msgspec.json.encode(stale))  # left behind by the crash
    again = Records(folder)
    assert again.get("spirit") == active and not (folder / "spirit.record.json").exists()


# --- migrations with the ledger compacted at every step ----------------------------------------------


def test_compaction_under_running_migrations_loses_nothing(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(BOUND_ENV, "1")  # every entry appended is followed by a compaction
    notes = ["met Ada"] + [f"hop {i}" for i in range(6)]
    with MemoryTransport(network, "cli") as t:
        client = MeshClient(t, mesh)
        robot = body(network, mesh, "robot", tmp_path, companion="spirit").start()
        screen = body(network, mesh, "screen", tmp_path).start()
        try:
            wait_for(lambda: robot.inhabitant == "spirit", 5, "spirit born on the robot")
            client.request("robot", "mind", "message", MindMessage({"note": notes[0]}))
            home, other = "robot", "screen"
            for note in notes[1:]:
                client.migrate("spirit", other, timeout=20)
                home, other = other, home
                assert client.request(home, "mind", "message", MindMessage({"note": note})).status == "accepted"
            hosts = {e.sim.embodiment: e.inhabitant for e in (robot, screen)}
            assert hosts == {home: "spirit", other: None}
            stats = robot.migration.records.stats() if robot.migration is not None else {}
            assert int(stats["compactions"]) >= len(notes)  # type: ignore[call-overload]
        finally:
            close(robot, screen)
        states = {name: read_ledger(tmp_path / name).records["spirit"].state for name in ("robot", "screen")}
        assert states == {home: "active", other: "released"}
        robot = body(network, mesh, "robot", tmp_path).start()
        screen = body(network, mesh, "screen", tmp_path).start()
        try:
            wait_for(lambda: {e.sim.embodiment: e.inhabitant for e in (robot, screen)} == {home: "spirit", other: None}, 5,
                     "exactly one host after a restart")
            mind = (robot if home == "robot" else screen).minds[0]
            assert isinstance(mind, Diary) and mind.entries == notes
        finally:
            close(robot, screen)


def test_an_attempt_decided_is_held_by_none_of_its_deadlines(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                             client: MeshClient) -> None:
    """Each prepare arms the deadline of its attempt (a minute): were the timers to hold its record,
    every attempt of the last minute would stay in memory with its chain of custody (hundreds of
    them, each as long as the companion is old, when migrations follow one another)."""
    with robot_and_screen(network, mesh, tmp_path) as (robot, screen):
        home, other = robot, screen
        for _ in range(8):
            ready_to_migrate(home, other)
            client.migrate("spirit", other.sim.embodiment, timeout=20)
            home, other = other, home
        wait_for(lambda: home.inhabitant == "spirit", 5, "the last migration over")
        gc.collect()
        incoming = [o for o in gc.get_objects() if isinstance(o, Record) and o.state == "incoming"]
        assert len(incoming) <= 1, f"{len(incoming)} incoming records still held (8 attempts decided)"


def test_a_migration_is_one_append_a_step_on_each_side(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                      client: MeshClient) -> None:
    with robot_and_screen(network, mesh, tmp_path) as (robot, screen):
        ready_to_migrate(robot, screen)
        assert robot.migration is not None and screen.migration is not None
        appends = robot.migration.records.journal.appends, screen.migration.records.journal.appends
        client.migrate("spirit", "screen", timeout=20)
        wait_for(lambda: robot.migration is not None and robot.migration.records.get("spirit") is not None
                 and robot.migration.records.get("spirit").state == "released", 5, "released")  # type: ignore[union-attr]
        assert robot.migration.records.journal.appends - appends[0] == 3, "prepared, handed, released"
        assert screen.migration.records.journal.appends - appends[1] == 2, "incoming, active"


@pytest.fixture
def client(network: MemoryNetwork, mesh: str) -> Iterator[MeshClient]:
    with MemoryTransport(network, "cli") as t:
        yield MeshClient(t, mesh)


def test_an_append_that_fails_leaves_nothing_of_itself_and_the_next_one_follows(tmp_path: Path,
                                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    from cmion_mesh.migration import journal

    folder = tmp_path / "state"
    records = Records(folder, bound=1 << 30)
    active, _document, _key = born(records)
    size = (folder / LOG).stat().st_size

    def full(_fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(journal.os, "fdatasync", full)
    with pytest.raises(OSError):
        records.put(msgspec.structs.replace(active, state="prepared", seq=1, attempt="a1", peer="screen"))
    monkeypatch.undo()
    assert (folder / LOG).stat().st_size == size, "the failed entry is cut off at once"
    handed = records.put(msgspec.structs.replace(active, state="prepared", seq=1, attempt="a2", peer="screen"))
    records.close()
    assert Records(folder).get("spirit") == handed


def test_small_sections_are_durable_in_their_entry_and_rewritten_if_their_file_was_lost(tmp_path: Path) -> None:
    folder = tmp_path / "state"
    records = Records(folder, bound=1 << 30)
    active, _document, _key = born(records)
    grown = Identity("spirit", 1, {"mind": {"entries": ["met Ada", "and Bob"]}}).pack_sections()
    before = FSYNCS.snapshot()
    kept = records.put(active, document=grown.manifest, sections=grown.data)
    after = FSYNCS.snapshot()
    assert after["total"] - before["total"] == 1, "one append makes the sections and the record durable"
    records.close()
    for digest in grown.data:  # a power cut after the unsynced write: the files are gone or empty
        (folder / "sections" / digest).write_bytes(b"")
    again = Records(folder)
    assert again.get("spirit") == kept
    assert again.identity("spirit") == Identity("spirit", 1, {"mind": {"entries": ["met Ada", "and Bob"]}}, 2)
    assert again.damaged() == {}


def test_a_compaction_syncs_the_sections_first_and_carries_them_no_more(tmp_path: Path) -> None:
    folder = tmp_path / "state"
    records = Records(folder, bound=50_000)  # the entry below is past it: compacted right after
    active, _document, _key = born(records)
    grown = Identity("spirit", 1, {"mind": {"entries": ["x" * 100_000]}}).pack_sections()
    before = FSYNCS.snapshot()
    records.put(active, document=grown.manifest, sections=grown.data)
    after = FSYNCS.snapshot()
    assert after["file"] - before["file"] >= len(grown.data) and after["compact"] - before["compact"] == 1
    assert (folder / LOG).stat().st_size < 10_000, "the sections are in their synced files now, not in the ledger"
    records.close()
    again = Records(folder)
    assert again.identity("spirit") == Identity("spirit", 1, {"mind": {"entries": ["x" * 100_000]}}, 2)
