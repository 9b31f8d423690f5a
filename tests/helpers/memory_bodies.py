"""Embodiments on the in-memory transport, each with its state folder and a ``Diary``, for logic tests."""

from __future__ import annotations

from pathlib import Path

from cmion_mesh.body.embodiment import Embodiment
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
