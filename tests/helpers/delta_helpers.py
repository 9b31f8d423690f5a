"""A mind for the delta-migration tests, hosted by daemons (importable as ``tests.helpers.delta_helpers``)."""

from __future__ import annotations

import base64
import hashlib
import random
from pathlib import Path
from typing import Any

from cmion_mesh.ion import Simulation
from cmion_mesh.messages import Event
from cmion_mesh.migration.manager import MigrationManager
from cmion_mesh.mind import Mind

from .remote_helpers import diary_embodiment_config


def blob_text(size: int, seed: int) -> str:
    """``size`` characters of incompressible text, the same for the same seed."""
    return base64.b64encode(random.Random(seed).randbytes(size * 3 // 4 + 3)).decode()[:size]


class Carrier(Mind):
    """A mind whose notes live in its own section and whose blob (``{"blob": size, "seed": n}``) is
    a section of its own, ``carrier-blob``: unchanged from one migration to the next unless set
    again. Its state says the blob's SHA-256, so a test can check it arrived whole."""

    def __init__(self, name: str = "carrier") -> None:
        super().__init__(name)
        self.notes: list[str] = []
        self.blob = ""

    @property
    def blob_section(self) -> str:
        return f"{self.name}-blob"

    def attach(self, sim: Simulation) -> None:
        super().attach(sim)
        sim.on_event(self._starting, component="migration", event="MigrationStarting")

    def _manager(self) -> MigrationManager | None:
        manager = self.sim.components_by_name().get("migration")
        return manager if isinstance(manager, MigrationManager) else None

    def _starting(self, event: Event) -> None:
        manager = self._manager()
        if manager is not None:
            manager.contribute(self.blob_section, self.blob)

    def on_message(self, data: dict[str, Any]) -> None:
        if "note" in data:
            self.notes.append(str(data["note"]))
        if "blob" in data:
            self.blob = blob_text(int(data["blob"]), int(data.get("seed", 0)))

    def on_arrived(self, world_model: dict[str, Any]) -> None:
        manager = self._manager()
        carried = manager.section(self.blob_section) if manager is not None else None
        if isinstance(carried, str):
            self.blob = carried

    def state(self) -> dict[str, Any]:
        return {"notes": list(self.notes), "blob_sha256": hashlib.sha256(self.blob.encode()).hexdigest(),
                "blob_size": len(self.blob)}

    def restore(self, state: dict[str, Any]) -> None:
        self.notes = list(state.get("notes", []))


def carrier_config(folder: Path, name: str) -> Path:
    """An ArchitectureConfiguration for ``name`` with CMION's test rules and library and a Carrier mind."""
    return diary_embodiment_config(folder, name, mind="tests.helpers.delta_helpers:Carrier")
