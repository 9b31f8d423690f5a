"""A competency the test drives, and a stepped simulation's update pump."""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from typing import Any

from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.ion import Component, Simulation

_CANCEL = object()


class Scripted(Competency):
    """A competency whose every run ends when the test says how (``finish``, which may be said
    ahead: verdicts are taken in order), or when it is cancelled."""

    def __init__(self, name: str, type: str = "Walk") -> None:
        super().__init__(name=name, type=type)
        self.parameters: list[dict[str, Any]] = []
        self._verdicts: queue.SimpleQueue[object] = queue.SimpleQueue()

    def finish(self, ok: bool = True, reason: str = "") -> None:
        self._verdicts.put((ok, reason))

    def _interrupt(self) -> None:
        self._verdicts.put(_CANCEL)

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        self.parameters.append(dict(parameters))
        while True:
            verdict = self._verdicts.get(timeout=20)
            if ctx.cancelled.is_set():
                return False
            if verdict is _CANCEL:
                continue  # left by the cancel of an earlier run
            assert isinstance(verdict, tuple)
            ok, reason = verdict
            return bool(ok) or ctx.fail(reason)


def pump(sim: Simulation, until: Callable[[], object], what: str, timeout: float = 10.0) -> None:
    """Run updates of a stepped ``sim`` until ``until()`` holds, for at most ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not until():
        assert time.monotonic() < deadline, f"{what}: not within {timeout:g} s"
        sim.run_once(0.05)


class Stall(Component):
    """Blocks the update loop on purpose until released: a handler stuck in the loop (``block``)."""

    def __init__(self) -> None:
        super().__init__("stall")
        self.entered = threading.Event()
        self.release = threading.Event()

    def block(self) -> None:
        self.sim.call(self._wait)

    def _wait(self) -> None:
        self.entered.set()
        self.release.wait(30.0)  # bounded: released by the test (or its end)
