"""Crash safety inside the ledger, with real processes: kill -9 in the middle of an append (a torn
entry) and during a compaction, at each step of the handshake; restart; exactly one inhabited.

As ``test_migration_crash``, whose harness this reuses: each embodiment is a daemon in its own
process with its own state folder; ``CMION_MESH_CRASH_AT`` names a crash point of the ledger
(``migration.crash``), the daemon SIGKILLs itself there, is restarted on the same state, and the
mesh must settle with the companion inhabiting exactly one embodiment, its memory unchanged.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.messages import Migrate, MindMessage
from cmion_mesh.migration.journal import BOUND_ENV, LOG
from cmion_mesh.migration.ledger import read_ledger
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .helpers.remote_helpers import Node
from .test_migration_crash import crash_while_migrating, inhabitants, node_pair, settle

pytestmark = pytest.mark.timeout(180)

CASES = [
    # A torn entry is no step: the state before it is the durable one. Torn at prepared, that is
    # the companion as it was born: what its mind learnt since lived in memory only (the identity
    # is stored at a clean stop or a migration), so it resumes as it was last stored.
    ("ledger:torn:prepared", "robot", "robot"),
    ("ledger:torn:handed", "robot", "robot"),       # never handed: the source aborts and resumes
    ("ledger:torn:released", "robot", "screen"),    # still handed: the restarted source commits again
    ("ledger:torn:incoming", "screen", ("robot", "screen")),  # never incoming: the source's retry decides
    ("ledger:torn:active", "screen", "screen"),     # still incoming: the source's commit retry activates it
    # A compaction cut short leaves the old log, or the new one, each whole (compacted at every entry).
    ("ledger:compacting:handed", "robot", "screen"),
    ("ledger:compacted:handed", "robot", "screen"),
    ("ledger:compacting:active", "screen", "screen"),
    ("ledger:compacting:released", "robot", "screen"),  # the compaction that takes the former host's key away
]


@pytest.fixture
def nodes(tmp_path: Path, mesh: str) -> Iterator[tuple[Node, Node]]:
    with node_pair(tmp_path, mesh, {BOUND_ENV: "1"}) as pair:  # a compaction after every entry appended
        yield pair


@pytest.mark.parametrize(("crash_at", "side_name", "home"), CASES)
def test_kill_inside_the_ledger_at_each_step(nodes: tuple[Node, Node], mesh: str, crash_at: str, side_name: str,
                                             home: str | tuple[str, ...]) -> None:
    robot, screen = nodes
    side = robot if side_name == "robot" else screen
    notes = ["met Ada", f"crash at {crash_at}"]
    durable = [] if crash_at == "ledger:torn:prepared" else notes  # its identity as it was last made durable
    crash_while_migrating(nodes, mesh, crash_at, side, notes, home, durable)
    dead = side.history[-2].proc.pid
    leftovers = [p.name for p in side.state.iterdir() if p.name.startswith(f".{LOG}.{dead}.")]
    assert not leftovers, f"the compaction's temporary file is swept at the restart: {leftovers}"


def test_a_restart_after_a_torn_entry_goes_on_appending(nodes: tuple[Node, Node], mesh: str) -> None:
    """The torn tail is cut off at the restart: the next migrations append after the state before it."""
    robot, screen = nodes
    robot.start()
    screen.start("ledger:torn:active")
    with ZenohTransport(TransportConfig(connect=(robot.endpoint, screen.endpoint), multicast=False)) as t:
        client = MeshClient(t, mesh)
        wait_for(lambda: inhabitants(client) == {"robot": "spirit", "screen": None}, 30, "spirit born on the robot")
        client.request("robot", "mind", "message", MindMessage({"note": "met Ada"}))
        assert client.request("robot", "migration", "migrate", Migrate("spirit", "screen")).status == "accepted"
        assert screen.died() == -9
        screen.start()
        settle(client, "screen", ["met Ada"])
        client.request("screen", "mind", "message", MindMessage({"note": "on the screen"}))
        wait_for(lambda: read_ledger(robot.state).records["spirit"].state == "released", 30, "the robot released it")
        client.migrate("spirit", "robot", timeout=30)
        settle(client, "robot", ["met Ada", "on the screen"])
        assert screen.daemon is not None
        screen.daemon.stop()
        screen.start()
        settle(client, "robot", ["met Ada", "on the screen"])
