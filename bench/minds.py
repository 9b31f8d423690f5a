"""Minds for the benchmark embodiment; a daemon builds them from its ArchitectureConfiguration.

* ``TimingMind`` (component ``timer``): told by a raw message ``{"action", "count", "tag"}``, it
  sends that action ``count`` times back to back, each from the handler of the previous one's
  end, and times ``act()`` -> ``on_action_succeeded`` in the daemon's own process. The samples
  come back as its event ``Measured`` ``{"tag", "samples"}`` (seconds), or ``{"tag", "error"}``.
* ``CarryMind`` (component ``mind``): a companion's mind that carries a blob (message
  ``{"size": N}`` sets it to N fresh random characters) and the list of embodiments it arrived
  on, so that the identity document has the size a benchmark asks for and a soak can check where
  it has been. The blob is a section of its own, ``<mind>-blob`` (contributed when
  ``MigrationStarting`` is raised, read back with ``section()`` on arrival): it is unchanged from
  one migration to the next unless a message sets it again, so a return trip sends only the
  mind's own section. That section also carries ``{"scratch": N}`` characters drawn afresh at
  every migration (the "one changed section" of the return benchmark).
"""

from __future__ import annotations

import base64
import os
import time
from typing import Any

from cmion_mesh.ion import Simulation
from cmion_mesh.messages import ActionReport, Event
from cmion_mesh.migration.manager import MigrationManager
from cmion_mesh.mind import Mind


class TimingMind(Mind):
    def __init__(self, name: str = "timer") -> None:
        super().__init__(name)
        self.tag = ""
        self.action = ""
        self.remaining = 0
        self.samples: list[float] = []
        self.t_sent = 0.0

    def on_message(self, data: dict[str, Any]) -> None:
        self.tag = str(data.get("tag", ""))
        self.action = str(data.get("action", "One"))
        self.remaining = max(1, int(data.get("count", 1)))
        self.samples = []
        self._send()

    def _send(self) -> None:
        self.t_sent = time.perf_counter()
        self.act(self.action)

    def on_action_succeeded(self, report: ActionReport) -> None:
        now = time.perf_counter()
        if self.remaining <= 0:
            return
        self.samples.append(now - self.t_sent)
        self.remaining -= 1
        if self.remaining:
            self._send()
        else:
            self.raise_event("Measured", {"tag": self.tag, "samples": self.samples})

    def on_action_failed(self, report: ActionReport) -> None:
        self.remaining = 0
        self.raise_event("Measured", {"tag": self.tag, "error": f"{report.name} failed: {report.reason}"})


def blob(size: int) -> str:
    """``size`` characters of incompressible base64 text (JSON and XML carry it unescaped)."""
    return base64.b64encode(os.urandom(size * 3 // 4 + 3)).decode()[:size] if size > 0 else ""


class CarryMind(Mind):
    def __init__(self, name: str = "mind", size: str = "0") -> None:
        super().__init__(name)
        self.blob = blob(int(size))
        self.scratch = 0
        self.arrivals: list[str] = []

    @property
    def blob_section(self) -> str:
        return f"{self.name}-blob"

    def attach(self, sim: Simulation) -> None:
        super().attach(sim)
        sim.on_event(self._migration_starting, component="migration", event="MigrationStarting")

    def _migration(self) -> MigrationManager | None:
        manager = self.sim.components_by_name().get("migration")
        return manager if isinstance(manager, MigrationManager) else None

    def _migration_starting(self, event: Event) -> None:
        manager = self._migration()
        if manager is not None:
            manager.contribute(self.blob_section, self.blob)

    def on_message(self, data: dict[str, Any]) -> None:
        if "size" in data:
            self.blob = blob(int(data["size"]))
        if "scratch" in data:
            self.scratch = max(0, int(data["scratch"]))

    def on_arrived(self, world_model: dict[str, Any]) -> None:
        manager = self._migration()
        if manager is not None:
            carried = manager.section(self.blob_section)
            if isinstance(carried, str):
                self.blob = carried
        self.arrivals.append(self.sim.embodiment)

    def state(self) -> dict[str, Any]:
        return {"scratch": blob(self.scratch), "scratch_size": self.scratch, "arrivals": list(self.arrivals)}

    def restore(self, state: dict[str, Any]) -> None:
        self.scratch = int(state.get("scratch_size", 0))
        self.arrivals = [str(a) for a in state.get("arrivals", [])]
