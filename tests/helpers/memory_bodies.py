"""Embodiments on the in-memory transport, each with its state folder and a ``Diary``, for logic tests."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .remote_helpers import Diary


def body(network: MemoryNetwork, mesh: str, name: str, state: Path, companion: str | None = None) -> Embodiment:
    """Embodiment ``name`` (not started), its state in ``state``/``name``, its mind a ``Diary``."""
    return Embodiment(name, mesh=mesh, transport=MemoryTransport(network, name), state_dir=state / name,
                      companion=companion, components=[Diary()])


def close(*embodiments: Embodiment) -> None:
    """Each embodiment closed, then its transport (the embodiment does not own it)."""
    for e in embodiments:
        e.close()
        e.transport.close()


@contextlib.contextmanager
def robot_and_screen(network: MemoryNetwork, mesh: str, state: Path, companion: str = "spirit") -> Iterator[tuple[Embodiment, Embodiment]]:
    """The robot (where ``companion`` is born) and the screen, started; both closed at the end."""
    robot = body(network, mesh, "robot", state, companion=companion).start()
    screen = body(network, mesh, "screen", state).start()
    try:
        yield robot, screen
    finally:
        close(robot, screen)


def ready_to_migrate(source: Embodiment, target: Embodiment, companion: str = "spirit") -> None:
    """Wait until ``companion`` lives on ``source`` and ``source`` sees ``target`` alive: a migration
    started before that is refused ("unknown target"), which under load is a race, not a verdict."""
    migration = source.migration
    assert migration is not None and target.migration is not None
    wait_for(lambda: source.inhabitant == companion, 5, f"{companion} living on {source.sim.embodiment}")
    wait_for(lambda: migration.claims.is_alive(target.sim.embodiment), 5,
             f"{source.sim.embodiment} sees {target.sim.embodiment}")
