"""A mind of your own: ``Keeper`` keeps the light, and remembers how many bodies it has lived in.

The same class runs in a daemon (named in an ``ArchitectureConfiguration``) and in a process of
its own (``cmion-mesh serve-mind``).
"""

from __future__ import annotations

from typing import Any

from cmion_mesh import Mind
from cmion_mesh.messages import ActionReport


class Keeper(Mind):
    """Blinks ``times`` times when it starts awake (a mind in a process of its own), and, each time
    its companion arrives in a body, once per body it has lived in so far: that count is its
    memory (``state``), which migration carries from body to body."""

    def __init__(self, times: str = "1", name: str = "keeper") -> None:
        super().__init__(name)
        self.times = times
        self.visits = 0

    def on_start(self) -> None:
        # In a daemon the mind sleeps until its companion lives there; in a process of its own it
        # is awake, and its embodiment is reachable: the action reaches the body.
        if self.awake:
            self.act("Blink", [self.times])

    def on_arrived(self, world_model: dict[str, Any]) -> None:
        self.visits += 1
        self.act("Blink", [str(self.visits)])

    def on_action_succeeded(self, report: ActionReport) -> None:
        self.raise_event("Blinked", {"action": report.name, "parameters": report.parameters, "visits": self.visits})

    def on_action_failed(self, report: ActionReport) -> None:
        self.raise_event("BlinkFailed", {"action": report.name, "reason": report.reason})

    def state(self) -> dict[str, Any]:
        return {"visits": self.visits}

    def restore(self, state: dict[str, Any]) -> None:
        self.visits = int(state.get("visits", 0))
