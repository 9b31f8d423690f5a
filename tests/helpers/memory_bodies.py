"""Embodiments on the in-memory transport, each with its state folder and a ``Diary``, for logic tests."""

from __future__ import annotations

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


def ready_to_migrate(source: Embodiment, target: Embodiment, companion: str = "spirit") -> None:
    """Wait until ``companion`` lives on ``source`` and ``source`` sees ``target`` alive: a migration
    started before that is refused ("unknown target"), which under load is a race, not a verdict."""
    migration = source.migration
    assert migration is not None and target.migration is not None
    wait_for(lambda: source.inhabitant == companion, 5, f"{companion} living on {source.sim.embodiment}")
    wait_for(lambda: migration.claims.is_alive(target.sim.embodiment), 5,
             f"{source.sim.embodiment} sees {target.sim.embodiment}")
