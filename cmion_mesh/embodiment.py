"""An embodiment: one zenoh session, one update loop, the stores, execution system and competency manager.

The daemon (``cmion-mesh up``) runs one of these per device; tests and tools can run one in a
process of their own. A context manager; ``close`` is idempotent and stops everything it started.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable

from cmion_mesh import keys
from cmion_mesh.competency import Competency, load_library
from cmion_mesh.execution import ExecutionSystem
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.manager import CompetencyManager
from cmion_mesh.rules import RuleSet, load_rules
from cmion_mesh.storage import Blackboard, WorldModel
from cmion_mesh.transport import Closeable, Transport, TransportConfig


class Embodiment:
    def __init__(
        self,
        name: str,
        *,
        mesh: str = keys.DEFAULT_MESH,
        transport: Transport | None = None,
        transport_config: TransportConfig | None = None,
        world_model_init: str | os.PathLike[str] | None = None,
        rules: str | os.PathLike[str] | RuleSet | None = None,
        library: str | os.PathLike[str] | None = None,
        competencies: Iterable[Competency] = (),
    ) -> None:
        self.name = keys.check_name(name, "embodiment")
        self.mesh = keys.check_name(mesh, "mesh")
        self.started_at = time.time()
        self._owns_transport = transport is None
        if transport is None:
            from cmion_mesh.zenoh_transport import ZenohTransport

            transport = ZenohTransport(transport_config)
        self.transport: Transport = transport
        self._token: Closeable | None = None
        self.sim = Simulation(self.transport, mesh=self.mesh, embodiment=self.name)
        try:
            self.blackboard = Blackboard()
            self.world_model = WorldModel()
            if world_model_init is not None:
                self.world_model.load_init(world_model_init)
            self.sim.add(self.blackboard)
            self.sim.add(self.world_model)
            loaded = list(competencies)
            if library is not None:
                loaded += load_library(library)
            self.execution = ExecutionSystem(loaded)
            ruleset = rules if isinstance(rules, RuleSet) or rules is None else load_rules(rules)
            self.rules = ruleset if ruleset is not None else RuleSet((), "<no rules>")
            self.sim.add(self.execution)
            self.manager = CompetencyManager(self.rules, self.execution)
            self.sim.add(self.manager)
        except BaseException:
            self.close()
            raise

    def add(self, component: Component) -> Component:
        return self.sim.add(component)

    def start(self) -> Embodiment:
        self.sim.start()
        if self._token is None:
            self._token = self.transport.declare_token(keys.alive_key(self.mesh, self.name))
        return self

    def __enter__(self) -> Embodiment:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        token, self._token = self._token, None
        if token is not None:
            token.close()
        self.sim.close()
        if self._owns_transport:
            self.transport.close()
