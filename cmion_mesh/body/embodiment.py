"""An embodiment: one zenoh session, one update loop, the stores, execution system and competency manager.

The daemon (``cmion-mesh up``) runs one of these per device; tests and tools can run one in a
process of their own. A context manager; ``close`` is idempotent and stops everything it started.

With ``join`` (what the daemon passes) it first claims its name in the mesh and refuses to start
when a live embodiment holds it (``claim.NameClaim``), and a companion it would give birth to
is not born when a live embodiment already hosts it. With a ``state_dir`` it holds that folder
(``statedir.StateLock``): two daemons never share one.

Other embodiments joining and leaving the mesh are log lines at info (``peer <name> joined`` /
``peer <name> left``, field ``peer``), through throttles keyed by the peer: a peer whose token
comes and goes many times a second writes a line and a count per window, not a line each time.
"""

from __future__ import annotations

import logging
import os
import platform
import threading
import time
from collections.abc import Iterable
from typing import Any

import msgspec

from cmion_mesh import __version__, keys, logs
from cmion_mesh.body.abilities import abilities
from cmion_mesh.body.architecture import embodiment_name, load_architecture
from cmion_mesh.body.execution import ExecutionSystem
from cmion_mesh.body.library import load_library, table_for_library
from cmion_mesh.body.manager import CompetencyManager
from cmion_mesh.body.rules import Plan, Rule, RuleSet, Step, load_rules
from cmion_mesh.body.standin import StandIn
from cmion_mesh.body.standin import summary as standin_summary
from cmion_mesh.body.validate import check_embodiment
from cmion_mesh.claim import Joining, NameClaim, claim_name
from cmion_mesh.client import MeshClient
from cmion_mesh.competency import Competency
from cmion_mesh.errors import MeshError
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import Code, Describe, Event, RemoteAction
from cmion_mesh.migration.devices import DeviceTable, birth, with_table_endpoints
from cmion_mesh.migration.invitation import Invitations
from cmion_mesh.migration.manager import MigrationCompetency, MigrationManager
from cmion_mesh.mind import Mind, MindAction, remote_action_problem
from cmion_mesh.presence import Presence
from cmion_mesh.requests import IncomingRequest
from cmion_mesh.statedir import StateLock
from cmion_mesh.storage import Blackboard, WorldModel
from cmion_mesh.transport.base import Closeable, Transport, TransportConfig

log = logging.getLogger(__name__)
#: The file in the state folder keeping a store's persistent properties.
PERSISTENT_FILE = "persistent-{store}.json"
#: How long a joining daemon asks the mesh who hosts the companion it would give birth to.
BIRTH_CHECK_TIMEOUT = 2.0


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
        components: Iterable[Component] = (),
        state_dir: str | os.PathLike[str] | None = None,
        companion: str | None = None,
        admit: dict[str, bytes | None] | None = None,
        join: float | None = None,
        joined: Joining | None = None,
        devices: DeviceTable | None = None,
    ) -> None:
        """``join``: claim the name in the mesh first, looking that many seconds for the rest of the
        mesh when nobody answers at once (0 when this session cannot find anyone by itself);
        ``joined``: that claim, already under way on its own session (``claim.Joining``, what the
        daemon passes: it asks the mesh while the daemon loads), whose session this embodiment then owns;
        ``Refused`` if the name is taken or ``state_dir`` is held by another daemon. ``devices``: the
        device table (``devices``) whose embodiments this one takes invitations from and sends its
        own to; its name, endpoints and birth are the caller's to apply (``from_architecture`` does)."""
        self.name = keys.check_name(name, "embodiment")
        self.version = __version__
        self.mesh = keys.check_name(mesh, "mesh")
        self.started_at = time.time()
        self.state_dir = None if state_dir is None else os.fspath(state_dir)
        #: Where the companion this embodiment would have given birth to lives instead (not born here).
        self.companion_elsewhere: str | None = None
        self.devices = devices
        if joined is not None:
            if transport is not None or join is not None:
                raise ValueError("joined brings its own session and claim: give neither transport nor join with it")
            if joined.name != self.name:
                raise ValueError(f"joined claims {joined.name!r}, not {self.name!r}")
            transport = joined.transport
        self._owns_transport = transport is None or joined is not None
        self._token: Closeable | None = None
        self._claim: NameClaim | None = None
        self._state_lock: StateLock | None = None
        self.presence: Presence | None = None
        self._peers: Closeable | None = None
        self._joins = logs.Throttle(log, "joins")
        self._departures = logs.Throttle(log, "departures")
        if transport is None:
            # Imported here for start time: an embodiment on a given transport (the tests' memory
            # transport) never loads zenoh.
            from cmion_mesh.transport.zenoh import ZenohTransport

            transport = ZenohTransport(transport_config)
        self.transport: Transport = transport
        self.sim = Simulation(self.transport, mesh=self.mesh, embodiment=self.name, one_queryable=True)
        try:
            if state_dir is not None:
                self._state_lock = StateLock(state_dir)
            self.presence = Presence(self.transport, self.mesh)
            self._peers = self.presence.listen(self._on_peer, replay=True)  # the peers already known too
            if joined is not None:
                self._claim = joined.result()
            elif join is not None:
                self._claim = claim_name(self.transport, self.mesh, self.name, join)
            if self._claim is not None and companion is not None:
                companion = self._unborn_elsewhere(companion)
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
            self.describer = Describer(self)
            self.sim.add(self.describer)
            extra = list(components)
            self.migration: MigrationManager | None = None
            self.invitations: Invitations | None = None
            if state_dir is not None:
                # Minds start asleep: the migration manager wakes them if a companion lives here.
                for component in extra:
                    if isinstance(component, Mind):
                        component.awake = False
                if "Migration" not in self.execution.types():
                    self.execution.add_competency(MigrationCompetency())
                self.rules = with_migrate_rule(self.rules)
                self.manager.rules = self.rules
            for component in extra:
                self.sim.add(component)
            if state_dir is not None:
                self.blackboard.keep_persistent(os.path.join(state_dir, PERSISTENT_FILE.format(store="blackboard")))
                self.world_model.keep_persistent(os.path.join(state_dir, PERSISTENT_FILE.format(store="world_model")))
                self.migration = MigrationManager(state_dir, companion=companion, admit=admit)
                self.sim.add(self.migration)
                self.sim.on_event(self._carry_persistent, component=self.migration.name)
                self.invitations = Invitations(self.migration, devices, presence=self.presence)
                self.sim.add(self.invitations)
        except BaseException:
            if joined is not None:
                joined.close()  # a claim still being decided ends before its session closes
            self.close()
            raise

    @classmethod
    def from_architecture(
        cls, path: str | os.PathLike[str], *, mesh: str = keys.DEFAULT_MESH, name: str | None = None,
        transport: Transport | None = None, transport_config: TransportConfig | None = None,
        state_dir: str | os.PathLike[str] | None = None, companion: str | None = None,
        admit: dict[str, bytes | None] | None = None, remote_types: Iterable[str] = (),
    ) -> Embodiment:
        """Build an embodiment from a CMION ``ArchitectureConfiguration`` file (see ``architecture``):
        the checks of ``up`` (``validate.check_embodiment``; ``remote_types`` as ``--remote-type``),
        the first error raising; stand-ins for Java classes with no equivalent are logged.

        A device table named by the library's Migration competency (``devices``) gives the name,
        the companion's birth and, where ``transport_config`` leaves them empty, the endpoints;
        the arguments given here win over it."""

        arch = load_architecture(path, name=name)
        table = table_for_library(arch.library) if arch.library is not None else None
        ruleset, competencies = check_embodiment(arch.rules, arch.library, arch.world_model, remote_types=remote_types)
        if transport_config is not None or transport is None:
            transport_config = with_table_endpoints(transport_config or TransportConfig(), table)
        return cls(
            name or embodiment_name(table, arch), mesh=mesh, transport=transport, transport_config=transport_config,
            world_model_init=arch.world_model, rules=ruleset, competencies=competencies, components=arch.build_components(),
            state_dir=state_dir, companion=companion or birth(table, arch.companion),
            admit=arch.admit if admit is None else {**(arch.admit or {}), **admit}, devices=table,
        )

    def add(self, component: Component) -> Component:
        return self.sim.add(component)

    @property
    def minds(self) -> list[Mind]:
        return [c for c in self.sim.components if isinstance(c, Mind)]

    def _unborn_elsewhere(self, companion: str) -> str | None:
        """``companion``, or None when a live embodiment of the mesh already hosts it (never born twice)."""
        with MeshClient(self.transport, self.mesh) as client:
            for found in client.describe_all(timeout=BIRTH_CHECK_TIMEOUT):
                if found.get("inhabitant") == companion and found.get("name") != self.name:
                    self.companion_elsewhere = str(found.get("name"))
                    log.warning("companion %r already lives on %r: it is not born on %r", companion, self.companion_elsewhere, self.name)
                    return None
        return companion

    def _on_peer(self, name: str, alive: bool) -> None:
        # On the transport's worker (the presence watch): a line, nothing that waits.
        if name != self.name:
            if alive:
                self._joins(name, "peer %s joined", name, peer=name)
            else:
                self._departures(name, "peer %s left", name, peer=name)

    def _carry_persistent(self, event: Event) -> None:
        """The world model's persistent properties belong to the companion: packed into its identity
        when it leaves (a section of the world model's name), set here when it arrives."""
        migration, world = self.migration, self.world_model
        if migration is None:
            return
        if event.name == "MigrationStarting":
            try:
                token = migration.wait(world.name)  # on the loop, before the packing starts
            except MeshError:
                return  # the migration ended already
            migration.resolve(token, {"properties": world.persistent_items()})
        elif event.name == "MigrationOccurred":
            section = migration.section(world.name)
            if isinstance(section, dict):
                data = event.data if isinstance(event.data, dict) else {}
                world.restore(section.get("properties"), source=f"the identity of companion {data.get('companion')!r}")

    def _on_duplicate(self, zenoh_ids: list[str]) -> None:
        """Another daemon answers as this embodiment (two parts of a mesh joined): say so loudly."""
        assert self._claim is not None
        keeps = self._claim.keeps_name()
        rule = ("this one is the older and keeps the name" if keeps else
                "the other one is older and keeps the name: stop this one")
        logs.event(log, f"DUPLICATE EMBODIMENT: another daemon named {self.name!r} is in mesh {self.mesh!r} "
                        f"(zenoh id {', '.join(zenoh_ids)}); {rule}", level=logging.ERROR, peer=self.name, zenoh_ids=zenoh_ids,
                   keeps_name=keeps)
        self.sim.raise_event("embodiment", "DuplicateEmbodiment",
                             {"name": self.name, "others": zenoh_ids, "keeps_name": keeps, "rule": rule})

    def describe(self) -> dict[str, Any]:
        """What discovery tells other peers about this embodiment (plain data)."""
        return {
            "name": self.name,
            "alive": sorted(self.presence.alive()) if self.presence is not None else [],
            "host": platform.node(),  # gethostname(), without importing socket at every start
            "pid": os.getpid(),
            "duplicates": self._claim.duplicates() if self._claim is not None else [],
            "mesh": self.mesh,
            "competency_types": sorted({c.type for c in self.execution.competencies if not isinstance(c, StandIn)}),
            "stand_ins": self.standins(),
            "competencies": [c.name for c in self.execution.competencies],
            "actions": self.rules.actions(),
            # The same actions as named, typed, described tools (language-model minds, MCP clients).
            "abilities": [a.to_json() for a in abilities(self.rules)],
            "minds": [m.name for m in self.minds],
            "mind_connections": {m.name: link for m in self.minds if (link := m.connection()) is not None},
            "inhabitant": self.inhabitant,
            # The embodiments the companion living here accepts (its policy section; None: any).
            "policy": self.migration.policy() if self.migration is not None else None,
            "companion_key": self.migration.public_key() if self.migration is not None else None,
            "admits": sorted(self.migration.admit) if self.migration is not None and self.migration.admit is not None else None,
            "damaged": dict(self.migration.damaged) if self.migration is not None else {},
            "custody": self.migration.custody_report() if self.migration is not None else {},
            "migration_transfer": self.migration.last_transfer if self.migration is not None else None,
            "ledger": self.migration.records.stats() if self.migration is not None else None,
            "devices": self.devices.names if self.devices is not None else None,
            "version": self.version,
            "started_at": self.started_at,
            "zenoh_id": self.transport.id,
            "publications_dropped": self.transport.dropped_publications,
        }

    def standins(self) -> list[dict[str, Any]]:
        """What stands in for CMION classes with no cmion-mesh equivalent (reported unavailable)."""
        return standin_summary([*self.sim.components, *self.execution.competencies])

    @property
    def inhabitant(self) -> str | None:
        """The companion living here, or None when empty."""
        return self.migration.inhabitant if self.migration is not None else None

    def start(self) -> Embodiment:
        self.sim.start()
        if self._token is None:
            # Alive only once every component is attached (stores answer reads from then on): a
            # client that sees the token may ask at once.
            attached = threading.Event()
            self.sim.call(attached.set)
            if not attached.wait(30.0):
                raise MeshError(f"embodiment {self.name!r}: the update loop did not start within 30 s")
            self._token = self.transport.declare_token(keys.alive_key(self.mesh, self.name))
            if self._claim is not None:
                self._claim.watch_duplicates(self._on_duplicate)
        self.sim.raise_event("embodiment", "EmbodimentReady", {"name": self.name})
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
        for handle in (self._peers, self._claim, self.presence, self._state_lock):
            if handle is not None:
                handle.close()
        if self._owns_transport:
            self.transport.close()


class Describer(Component):
    """The embodiment's own requests: ``.../rq/embodiment/describe`` for discovery, and
    ``.../rq/embodiment/remote_action``: another agent's action, which the embodiment perceives as
    its ``RemoteAction`` event (CMION's RemoteActionSimulator; ``cmion-mesh remote-action``).
    Accepted with ``{"minds": [...]}``, the minds of this process awake to perceive it (a mind in
    another process perceives it too); rejected ``invalid`` when minds could not be told it."""

    requests = {"describe": Describe, "remote_action": RemoteAction}
    built_by_embodiment = True

    def __init__(self, embodiment: Embodiment) -> None:
        super().__init__("embodiment")
        self.embodiment = embodiment

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        description: dict[str, Any] | None = None
        for request in batch:
            match request.payload:
                case RemoteAction() as action:
                    problem = remote_action_problem(action)
                    if problem:
                        request.reject(problem, Code.INVALID)
                        continue
                    self.raise_event("RemoteAction", msgspec.to_builtins(action))
                    request.accept({"minds": sorted(m.name for m in self.embodiment.minds if m.awake)})
                case _:
                    if description is None:
                        description = self.embodiment.describe()
                    request.accept(description)


def with_migrate_rule(rules: RuleSet) -> RuleSet:
    """Add the built-in rule ``Migrate <target>`` -> one ``Migration`` step, unless the rules have one."""
    if rules.candidates(MindAction("Migrate", ("somewhere",))):
        return rules
    step = Step("1", "Migration", (), (("target", "$parameter1"),), 0)
    rule = Rule(len(rules.rules), "Migrate", ("*",), None, (Plan((step,), 0),), "<built-in>", 0,
                "Migrate <target>: move the companion, with its memory, to the embodiment named target "
                "(one its migration policy accepts); it then lives in that body, with that body's abilities.")
    return RuleSet((*rules.rules, rule), rules.path)
