"""Migration logic in one process (in-memory transport): handshake, sections, refusals, records."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError, NotAlive, RequestRejected
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import Event, MigrateAbort, MigrateCommit, MigratePrepare, MigrateStatus, MindMessage, Outcome, SetPolicy
from cmion_mesh.migration import custody, signing
from cmion_mesh.migration.identity import Identity, unpack
from cmion_mesh.migration.ledger import Records
from cmion_mesh.migration.manager import MigrationManager
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .helpers.custody_helpers import Holder
from .helpers.memory_bodies import body, close, ready_to_migrate, robot_and_screen
from .helpers.remote_helpers import Diary

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def client(network: MemoryNetwork, mesh: str) -> Iterator[MeshClient]:
    with MemoryTransport(network, "cli") as t:
        yield MeshClient(t, mesh)


def test_companion_moves_with_its_memory_and_sections(network: MemoryNetwork, mesh: str, tmp_path: Path, client: MeshClient) -> None:
    with robot_and_screen(network, mesh, tmp_path) as (robot, screen):
        wait_for(lambda: robot.inhabitant == "spirit", 5, "spirit born on the robot")
        assert screen.inhabitant is None
        robot_mind, screen_mind = robot.minds[0], screen.minds[0]
        wait_for(lambda: robot_mind.awake and not screen_mind.awake, 5, "only the inhabited mind is awake")
        client.request("robot", "mind", "message", _note("met Ada"))
        result = client.migrate("spirit", "screen", timeout=20)
        assert result["source"] == "robot" and result["epoch"] == 2
        assert screen.inhabitant == "spirit" and robot.inhabitant is None
        assert screen_mind.awake and not robot_mind.awake
        assert screen_mind.entries == ["met Ada"] and screen_mind.arrivals == ["robot", "screen"]
        assert Records(tmp_path / "robot").get("spirit").state == "released"
        assert Records(tmp_path / "screen").get("spirit").state == "active"
        assert Records(tmp_path / "screen").get("spirit").epoch == 2
        # and back, through a mind action handled by the built-in Migrate rule
        client.request("screen", "mind", "message", _note("at the entrance"))
        report = client.act("screen", "Migrate", ["robot"], timeout=20)
        assert report.status == "succeeded", report
        wait_for(lambda: robot.inhabitant == "spirit", 5, "back on the robot")
        assert robot_mind.entries == ["met Ada", "at the entrance"] and robot_mind.awake


def test_a_source_knows_its_targets_claims_without_asking(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                          client: MeshClient) -> None:
    # The target's token while it receives the companion is no claim, and the one after the commit
    # is backed by the link the source signed: asking for them (a chain request, a signature and its
    # check on both sides) in the middle of every migration cost both daemons time for nothing.
    asked: list[tuple[str, str]] = []
    with robot_and_screen(network, mesh, tmp_path) as (robot, screen):
        for embodiment in (robot, screen):
            assert embodiment.migration is not None
            claims = embodiment.migration.claims
            answer = claims.on_chain
            claims.on_chain = lambda request, msg, answer=answer, me=embodiment.name: (  # type: ignore[method-assign]
                asked.append((me, request.requester)), answer(request, msg))
        wait_for(lambda: robot.inhabitant == "spirit", 5, "spirit born on the robot")
        wait_for(lambda: screen.migration is not None and screen.migration.claims.backed("spirit") != [], 5,
                 "the screen checked the robot's claim (a stranger's: asked)")
        asked.clear()
        ready_to_migrate(robot, screen)
        client.migrate("spirit", "screen", timeout=20)
        assert robot.migration is not None and screen.migration is not None
        wait_for(lambda: [c.holder for c in robot.migration.claims.backed("spirit")] == ["screen"], 5,  # type: ignore[union-attr]
                 "the robot backs the screen's claim")
        backed = robot.migration.claims.backed("spirit")[0]
        assert list(backed.chain) == Records(tmp_path / "screen").get("spirit").chain  # what the screen holds, link for link
        assert client.migrate("spirit", "robot", timeout=20)["source"] == "screen"
        wait_for(lambda: [c.holder for c in screen.migration.claims.backed("spirit")] == ["robot"], 5,  # type: ignore[union-attr]
                 "the screen backs the robot's claim")
        assert asked == [], f"chain requests between the two ends of a migration: {asked}"


def test_a_target_that_cannot_record_active_never_runs_the_companion(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                                     client: MeshClient) -> None:
    # ``active`` is durable before the companion wakes at the target: woken first, a write that
    # failed would leave it running there on a record still incoming, which the source then
    # aborts, and resumes: two hosts.
    with robot_and_screen(network, mesh, tmp_path) as (robot, screen):
        assert robot.migration is not None and screen.migration is not None
        ready_to_migrate(robot, screen)
        records = screen.migration.records
        put = records.put

        def full(record: Any, *args: Any, **kwargs: Any) -> Any:
            if record.state == "active":
                raise OSError(28, "No space left on device")
            return put(record, *args, **kwargs)

        records.put = full  # type: ignore[method-assign]
        with pytest.raises(MeshError):
            client.migrate("spirit", "screen", timeout=20)
        wait_for(lambda: robot.inhabitant == "spirit", 20, "spirit back on the robot")
        screen_mind = screen.minds[0]
        assert screen.inhabitant is None and screen.migration.identity is None
        assert not screen_mind.awake and screen_mind.arrivals == [], "the companion never ran on the screen"


class Badge(Component):
    """A component that gives its section straight from the ``MigrationStarting`` handler."""

    def __init__(self) -> None:
        super().__init__("badge")
        self.received: list[Any] = []

    def attach(self, sim: Simulation) -> None:
        sim.on_event(self._on_migration, component="migration")

    def _on_migration(self, event: Event) -> None:
        migration = self.sim.component("migration")
        assert isinstance(migration, MigrationManager)
        if event.name == "MigrationStarting":
            migration.contribute(self.name, {"visits": 1 + len(self.received)})
        elif event.name == "MigrationOccurred":
            self.received.append(migration.section(self.name))


def test_a_section_contributed_from_the_starting_handler_travels(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                                 client: MeshClient) -> None:
    robot = Embodiment("robot", mesh=mesh, transport=MemoryTransport(network, "robot"), state_dir=tmp_path / "robot",
                       companion="spirit", components=[Badge()]).start()
    screen_badge = Badge()
    screen = Embodiment("screen", mesh=mesh, transport=MemoryTransport(network, "screen"), state_dir=tmp_path / "screen",
                        components=[screen_badge]).start()
    try:
        wait_for(lambda: robot.inhabitant == "spirit", 5, "spirit born on the robot")
        client.migrate("spirit", "screen", timeout=20)
        wait_for(lambda: screen_badge.received, 5, "the badge's section at the screen")
        assert screen_badge.received == [{"visits": 1}]
    finally:
        close(robot, screen)


class Photo(Component):
    """Gives a large section, new at every migration (an image taken just before leaving)."""

    def __init__(self) -> None:
        super().__init__("photo")
        self.taken = 0

    def attach(self, sim: Simulation) -> None:
        sim.on_event(self._on_migration, component="migration", event="MigrationStarting")

    def _on_migration(self, event: Event) -> None:
        migration = self.sim.component("migration")
        assert isinstance(migration, MigrationManager)
        self.taken += 1
        migration.contribute(self.name, str(self.taken) * 300_000)


def test_a_new_large_section_follows_the_have_without_waiting_for_its_answer(
        network: MemoryNetwork, mesh: str, tmp_path: Path, client: MeshClient) -> None:
    # No target can hold a section new at the source: it goes right behind the have, before its
    # answer is waited for (a round trip less).
    robot = Embodiment("robot", mesh=mesh, transport=MemoryTransport(network, "robot"), state_dir=tmp_path / "robot",
                       companion="spirit", components=[Photo()]).start()
    screen = Embodiment("screen", mesh=mesh, transport=MemoryTransport(network, "screen"), state_dir=tmp_path / "screen",
                        components=[Photo()]).start()
    order: list[str] = []
    try:
        assert robot.migration is not None and screen.migration is not None
        uploads = screen.migration.uploads
        on_sections = uploads.on_sections
        uploads.on_sections = lambda request, msg: (order.append("screen takes sections"),  # type: ignore[method-assign]
                                                    on_sections(request, msg))
        ask_later = robot.migration.ask_later

        def asked(peer: str, op: str, message: Any) -> Any:
            answer = ask_later(peer, op, message)
            return lambda: (order.append(f"robot waits for the {op} answer"), answer())[1]

        robot.migration.ask_later = asked  # type: ignore[method-assign]
        ready_to_migrate(robot, screen)
        client.migrate("spirit", "screen", timeout=20)
        assert order == ["screen takes sections", "robot waits for the have answer"], order
        assert screen.migration.section("photo") == "1" * 300_000
    finally:
        close(robot, screen)


def test_refusals_leave_the_companion_running_at_the_source(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                            client: MeshClient) -> None:
    robot = body(network, mesh, "robot", tmp_path, companion="spirit").start()
    phone = body(network, mesh, "phone", tmp_path, companion="other").start()
    try:
        wait_for(lambda: robot.inhabitant == "spirit" and phone.inhabitant == "other", 5, "both born")
        with pytest.raises(RequestRejected, match="occupied by companion 'other'"):
            client.migrate("spirit", "phone", timeout=20)
        with pytest.raises(NotAlive, match=r"'nowhere' is not alive in mesh .* \(alive: phone, robot\)"):
            client.migrate("spirit", "nowhere", timeout=20)
        assert robot.inhabitant == "spirit" and robot.minds[0].awake
        assert Records(tmp_path / "robot").get("spirit").state == "active"
    finally:
        close(robot, phone)


def handshake(client: MeshClient, op: str, message: Any, sender: str = "robot") -> Outcome:
    """A handshake message to the screen, on the per-sender key of ``sender``."""
    return client.request("screen", "migration", op, message, sender=sender)


def test_invalid_document_and_stale_or_duplicate_messages(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                          client: MeshClient) -> None:
    screen = body(network, mesh, "screen", tmp_path).start()
    try:
        wait_for(lambda: screen.sim.updates > 0, 5, "screen up")
        hostile = b'<!DOCTYPE Identity [<!ENTITY x SYSTEM "file:///etc/passwd">]><Identity SchemaVersion="1" Companion="s" Epoch="1"/>'
        bad = handshake(client, "prepare", Holder("s", "robot").prepare("screen", hostile, "a1"))
        assert bad.status == "rejected" and "internal DTD subset" in bad.reason and "identity of s from robot" in bad.reason
        huge = b"<Identity" + b" " * (50 * 1024 * 1024) + b"/>"
        too_big = handshake(client, "prepare", Holder("s", "robot").prepare("screen", huge, "a0"))
        assert too_big.status == "rejected"
        doc = Identity("s", 4, {"mind": {"entries": []}, "face": {"smile": 0.7}}).pack()
        robot = Holder("s", "robot", 4)
        prepare = robot.prepare("screen", doc, "a2")
        ok = handshake(client, "prepare", prepare)
        again = handshake(client, "prepare", prepare)
        assert ok.status == again.status == "accepted", "a duplicated prepare gets the same answer"
        assert ok.value == again.value and set(ok.value) == {"state", "custody_key"}
        stale = handshake(client, "commit", MigrateCommit("s", 4, "old-attempt", "robot", "screen", b""))
        assert stale.status == "rejected" and "old-attempt" in stale.reason
        forged = handshake(client, "commit", Holder("s", "robot", 4).commit(prepare, ok))
        assert forged.status == "rejected" and "not by its holder's custody key" in forged.reason
        assert screen.inhabitant is None
        commit = robot.commit(prepare, ok)
        assert handshake(client, "commit", commit).status == "accepted"
        assert handshake(client, "commit", commit).status == "accepted", "duplicate commit: same answer"
        assert screen.inhabitant == "s"
        older = handshake(client, "prepare", Holder("s", "robot", 3).prepare("screen", doc, "a3"))
        assert older.status == "rejected" and "holds 's' itself" in older.reason
        # the unknown "face" section is kept and carried on
        kept = unpack(Records(tmp_path / "screen").document("s") or b"")
        assert kept.sections["face"] == {"smile": 0.7}
        status = handshake(client, "status", MigrateStatus("s", "zzz"))
        assert status.value == {"state": "aborted"}
    finally:
        close(screen)


def test_custody_checks_come_before_any_xml(network: MemoryNetwork, mesh: str, tmp_path: Path, client: MeshClient) -> None:
    screen = body(network, mesh, "screen", tmp_path).start()
    doc = Identity("s", 1, {"mind": {"entries": ["x"]}}).pack()

    def prepare(message: MigratePrepare) -> Outcome:
        return handshake(client, "prepare", message)

    try:
        wait_for(lambda: screen.sim.updates > 0, 5, "screen up")
        robot = Holder("s", "robot")
        unsigned = prepare(msgspec.structs.replace(robot.prepare("screen", doc, "a1"), proof=b""))
        assert unsigned.status == "rejected" and "bad signature on the offer" in unsigned.reason
        no_chain = prepare(msgspec.structs.replace(robot.prepare("screen", doc, "a1"), chain=custody.encode_chain([])))
        assert "no chain of custody" in no_chain.reason
        redirected = robot.prepare("phone", doc, "a1")
        assert "this is 'screen', not 'phone'" in prepare(redirected).reason
        redirected = msgspec.structs.replace(redirected, target="screen")
        assert "bad signature on the offer" in prepare(redirected).reason
        altered = msgspec.structs.replace(robot.prepare("screen", doc, "a1"), document=doc.replace(b'"x"', b'"y"'))
        assert "bad signature on the offer" in prepare(altered).reason
        by_another = Holder("s", "robot", chain=robot.chain)  # the chain, but not its holder's key
        assert "bad signature on the offer" in prepare(by_another.prepare("screen", doc, "a1")).reason
        # an offer that is aborted pins nothing: another companion of the same name may come next
        assert prepare(robot.prepare("screen", doc, "a1")).status == "accepted"
        assert handshake(client, "abort", MigrateAbort("s", 1, "a1")).status == "accepted"
        assert Records(tmp_path / "screen").get("s").public_key == ""
        other = Holder("s", "robot")
        first = other.prepare("screen", doc, "a2", seq=9)
        answer = prepare(first)
        assert answer.status == "accepted", answer
        assert handshake(client, "commit", other.commit(first, answer)).status == "accepted"
        assert Records(tmp_path / "screen").get("s").public_key == signing.encode_public(other.identity_key), "pinned at the commit"
        assert screen.inhabitant == "s"
    finally:
        close(screen)


def test_handshake_senders_are_known_from_their_keys(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                     client: MeshClient) -> None:
    screen = body(network, mesh, "screen", tmp_path).start()
    doc = Identity("s", 1, {}).pack()
    robot = Holder("s", "robot")
    try:
        wait_for(lambda: screen.sim.updates > 0, 5, "screen up")
        message = robot.prepare("screen", doc, "a1")
        sender_less = client.request("screen", "migration", "prepare", message)
        assert sender_less.status == "rejected" and "prepare/<sender>" in sender_less.reason
        spoofed = handshake(client, "prepare", message, sender="phone")
        assert spoofed.status == "rejected" and "on behalf of 'robot'" in spoofed.reason
        answer = handshake(client, "prepare", message)
        assert answer.status == "accepted"
        assert handshake(client, "abort", MigrateAbort("s", 1, "a1"), sender="phone").status == "rejected"
        assert handshake(client, "status", MigrateStatus("s", "a1"), sender="phone").status == "rejected"
        commit = robot.commit(message, answer)
        spoofed_commit = msgspec.structs.replace(commit, source="phone")
        assert handshake(client, "commit", spoofed_commit, sender="phone").status == "rejected"
        assert screen.inhabitant is None
        assert handshake(client, "commit", commit).status == "accepted"
        assert screen.inhabitant == "s"
    finally:
        close(screen)


def test_admission_policy_and_companion_policy(network: MemoryNetwork, mesh: str, tmp_path: Path, client: MeshClient) -> None:
    robot = body(network, mesh, "robot", tmp_path, companion="spirit").start()
    kiosk = Embodiment("kiosk", mesh=mesh, transport=MemoryTransport(network, "kiosk"), state_dir=tmp_path / "kiosk",
                       components=[Diary()], admit={"someone-else": None}).start()
    screen = body(network, mesh, "screen", tmp_path).start()
    try:
        wait_for(lambda: robot.inhabitant == "spirit", 5, "spirit born")
        with pytest.raises(RequestRejected, match="admission: companion 'spirit' may not enter 'kiosk'"):
            client.migrate("spirit", "kiosk", timeout=20)
        assert robot.inhabitant == "spirit" and robot.minds[0].awake
        # the companion's own policy: it accepts only the robot and the phone, and carries that along
        client.set_policy("spirit", ["robot", "phone"])
        with pytest.raises(RequestRejected, match="does not accept embodiment 'screen'"):
            client.migrate("spirit", "screen", timeout=20)
        assert robot.inhabitant == "spirit"
        bad = client.request("robot", "migration", "policy", MindMessage({"accepts": "screen"}))
        assert bad.status == "rejected" and "Invalid value 'mind_message'" in bad.reason
        empty = client.request("robot", "migration", "policy", SetPolicy(["a/b"]))
        assert empty.status == "rejected" and "'a/b'" in empty.reason
        client.set_policy("spirit", None)
        client.migrate("spirit", "screen", timeout=20)
        assert screen.inhabitant == "spirit"
    finally:
        close(robot, kiosk, screen)


def _note(text: str) -> Any:
    return MindMessage({"note": text})


def test_several_companions_and_an_emptied_body_taken_by_another(network: MemoryNetwork, mesh: str, tmp_path: Path,
                                                                 client: MeshClient) -> None:
    robot = body(network, mesh, "robot", tmp_path, companion="spirit").start()
    phone = body(network, mesh, "phone", tmp_path, companion="buddy").start()
    screen = body(network, mesh, "screen", tmp_path).start()
    try:
        wait_for(lambda: robot.inhabitant == "spirit" and phone.inhabitant == "buddy", 5, "two companions born")
        client.migrate("spirit", "screen", timeout=20)
        assert robot.inhabitant is None and screen.inhabitant == "spirit"
        client.migrate("buddy", "robot", timeout=20)  # the body spirit left is free for another companion
        homes = {e.name: e.inhabitant for e in (robot, phone, screen)}
        assert homes == {"robot": "buddy", "phone": None, "screen": "spirit"}
        with pytest.raises(RequestRejected, match="occupied by companion 'spirit'"):
            client.migrate("buddy", "screen", timeout=20)
    finally:
        close(robot, phone, screen)
