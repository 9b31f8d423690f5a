"""Competencies that tests host in separate processes (importable as ``tests.helpers.remote_helpers``)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.messages import ActionReport
from cmion_mesh.mind import Mind, MindAction
from cmion_mesh.procs import Daemon, cli_argv


class Arm(Competency):
    """Waves for ``steps`` steps of 50 ms, reporting progress; writes the blackboard over the mesh."""

    type = "Arm"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        steps = int(parameters.get("steps", 1))
        for i in range(steps):
            if not ctx.wait(0.05):
                return False
            ctx.progress({"step": i + 1, "of": steps})
        if parameters.get("fail") == "yes":
            return ctx.fail("arm jammed")
        ctx.bb_set("waved", {"speed": parameters.get("speed"), "steps": steps, "by": self.name})
        return True


class EagerMind(Mind):
    """A remote mind for tests: on start (and on every raw message) it sends the action it is given."""

    def __init__(self, name: str = "eager", action: str = "TestAction", *parameters: str) -> None:
        super().__init__(name)
        self.action = action
        self.parameters = parameters
        self.outcomes: list[str] = []

    def on_start(self) -> None:
        self.act(self.action, self.parameters)

    def on_message(self, data: dict[str, Any]) -> None:
        self.act(str(data.get("action", self.action)), tuple(str(p) for p in data.get("parameters", self.parameters)))

    def on_action_succeeded(self, report: ActionReport) -> None:
        self.outcomes.append(f"{report.name}:succeeded")
        self.raise_event("MindSaw", {"action_id": report.action_id, "status": "succeeded", "outcomes": self.outcomes})

    def on_action_failed(self, report: ActionReport) -> None:
        self.outcomes.append(f"{report.name}:failed")
        self.raise_event("MindSaw", {"action_id": report.action_id, "status": "failed", "reason": report.reason, "outcomes": self.outcomes})

    def on_property_changed(self, entity: str, name: str, value: Any, persistent: bool) -> None:
        self.raise_event("MindPerceived", {"entity": entity, "name": name, "value": value, "persistent": persistent})

    def state(self) -> dict[str, Any]:
        return {"outcomes": list(self.outcomes)}


class Perceiver(Mind):
    """A remote mind for tests: tells what it perceives of the world by a ``Perceived`` event each."""

    def __init__(self, name: str = "perceiver") -> None:
        super().__init__(name)

    def on_entity_added(self, name: str, kind: str) -> None:
        self.raise_event("Perceived", {"op": "added", "entity": name, "kind": kind})

    def on_entity_removed(self, name: str, kind: str) -> None:
        self.raise_event("Perceived", {"op": "removed", "entity": name, "kind": kind})

    def on_property_changed(self, entity: str, name: str, value: Any, persistent: bool) -> None:
        self.raise_event("Perceived", {"op": "changed", "entity": entity, "name": name, "value": value})

    def on_remote_action(self, action: MindAction) -> None:
        self.raise_event("Perceived", {"op": "remote", "name": action.name, "parameters": list(action.parameters),
                                       "subject": action.subject})


class Diary(Mind):
    """A mind whose memory is a list of notes (sent as raw messages); it records where it arrived."""

    def __init__(self, name: str = "mind") -> None:
        super().__init__(name)
        self.entries: list[str] = []
        self.arrivals: list[str] = []

    def on_message(self, data: dict[str, Any]) -> None:
        self.entries.append(str(data.get("note")))

    def on_arrived(self, world_model: dict[str, Any]) -> None:
        self.arrivals.append(self.sim.embodiment)

    def state(self) -> dict[str, Any]:
        return {"entries": list(self.entries), "arrivals": list(self.arrivals)}

    def restore(self, state: dict[str, Any]) -> None:
        self.entries = list(state.get("entries", []))
        self.arrivals = list(state.get("arrivals", []))


def diary_embodiment_config(folder: Path, name: str, mind: str = "tests.helpers.remote_helpers:Diary") -> Path:
    """An ArchitectureConfiguration for ``name`` with CMION's test rules and library and a test mind
    (``package.module:Class``, a Diary unless told)."""
    from cmion_mesh.resources import embodiment_dir

    cmion_test = embodiment_dir("cmion_test")
    folder.mkdir(parents=True, exist_ok=True)
    config = folder / "ArchitectureConfiguration.xml"
    config.write_text(
        f'<ArchitectureConfiguration Embodiment="{name}" CompetencyManagerRulesFile="{cmion_test / "CompManagerRulesTest.xml"}"'
        f' CompetencyLibraryConfigurationFile="{cmion_test / "CompetencyLibrary.xml"}">\n'
        f'  <ArchitectureComponent ClassName="{mind}"/>\n'
        "</ArchitectureConfiguration>\n")
    return config


@dataclass
class Node:
    """One daemon of a test mesh, restartable (each run is kept in ``history``; ``stop`` kills them all)."""

    name: str
    mesh: str
    config: Path
    state: Path
    port: int
    peers: list[str]
    companion: str | None = None
    env: dict[str, str] = field(default_factory=dict)
    daemon: Daemon | None = None
    history: list[Daemon] = field(default_factory=list)

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def start(self, crash_at: str = "") -> Node:
        """``crash_at``: the durable record after which the daemon kills itself (``CMION_MESH_CRASH_AT``)."""
        argv = ["up", str(self.config), "--mesh", self.mesh, "--listen", self.endpoint, "--no-multicast", "--state-dir", str(self.state)]
        for peer in self.peers:
            argv += ["--connect", peer]
        if self.companion:
            argv += ["--companion", self.companion]
        self.daemon = Daemon(cli_argv(*argv), env={**self.env, "CMION_MESH_CRASH_AT": crash_at}, name=self.name)
        self.history.append(self.daemon)
        self.daemon.wait_line("up in mesh", 30)
        return self

    def died(self, timeout: float = 30) -> int:
        assert self.daemon is not None
        return self.daemon.proc.wait(timeout)

    def stop(self) -> None:
        for daemon in self.history:
            daemon.kill()


@contextlib.contextmanager
def screen_in_process(network: Any, mesh: str, state: Path) -> Iterator[tuple[Any, Any]]:
    """An embodiment "screen" with a ``Diary`` on the in-memory ``network`` (its state in ``state``), and a
    client beside it: a migration target the test drives message by message."""
    from cmion_mesh.body.embodiment import Embodiment
    from cmion_mesh.client import MeshClient
    from cmion_mesh.testing.wait import wait_for
    from cmion_mesh.transport.memory import MemoryTransport

    body = Embodiment("screen", mesh=mesh, transport=MemoryTransport(network, "screen"), state_dir=state,
                      components=[Diary()]).start()
    try:
        with MemoryTransport(network, "cli") as t:
            client = MeshClient(t, mesh)
            wait_for(lambda: body.sim.updates > 0, 5, "screen up")
            yield body, client
    finally:
        body.close()
        body.transport.close()
