"""CMION's demonstration minds (``cmion.level3.supersimplemind``), as ``Mind`` subclasses.

They take CMION's constructor parameters (none), so a configuration naming the Java connectors
runs them through a port map. Their actions are CMION's: ``TestAction test`` and ``Migration
<device>`` (CMION's rules map ``Migration *`` to the ``Migration`` competency with ``DeviceName``).
Their subject is CMION's agent name, ``SimpleMind``.

* ``SuperSimpleMind``: when it wakes, sends ``TestAction test``; sends it again after a failure
  (``RETRY_DELAY`` later: CMION resent at once, a storm when the action cannot succeed); a
  world-model property named ``cancel`` that changes cancels it.
* ``SuperSimpleMigratingMind``: when it wakes, migrates to ``B``; once arrived there, migrates
  back to ``A`` ``BACK_DELAY`` seconds later. Its state, the ``mindstate`` section, is CMION's
  ``{"goal": "Migrate Mind"}``.
* ``SuperSimpleMigratingByInviteMind``: follows invitations (``MigrationInvitation <embodiment>``
  -> ``Migration <embodiment>``); when an entity is added to the world model of the embodiment it
  sits in while that one is empty (its mind asleep), it raises ``InviteMigration``, so that the
  embodiment invites the companion (``invitation``). Its state is a ``mindstate`` section too.

Minds sleep where no companion lives: the migrating ones wake where the companion is.
"""

from __future__ import annotations

import logging
from typing import Any

from cmion_mesh import keys
from cmion_mesh.errors import MeshError
from cmion_mesh.ion import Simulation
from cmion_mesh.messages import ActionReport, Event
from cmion_mesh.migration.invitation import INVITATION_ACTION, INVITE_EVENT
from cmion_mesh.mind import Mind, MindAction, storage_change

log = logging.getLogger(__name__)

#: CMION's agent name for these minds: the subject of their actions.
AGENT_NAME = "SimpleMind"
#: CMION's migration action (``CompManagerRulesMigrationTest``: ``Migration *`` -> ``Migration``/``DeviceName``).
MIGRATION_ACTION = "Migration"
#: Seconds before SuperSimpleMind sends its action again after a failure.
RETRY_DELAY = 1.0
#: Seconds SuperSimpleMigratingMind stays on ``B`` before migrating back (CMION's 5 s).
BACK_DELAY = 5.0
#: The section CMION's migrating minds filled (``getMessageTag``), and what it held.
MIND_STATE = "mindstate"
MIND_GOAL = "Migrate Mind"


class _SimpleMind(Mind):
    """What the three share: one action at a time, sent with CMION's agent name as subject."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.executing: str | None = None  # the action in flight

    def _send(self, action: str, *parameters: str) -> None:
        try:
            self.executing = self.act(action, parameters, AGENT_NAME)
        except MeshError as exc:  # asleep meanwhile
            log.info("mind %s did not send %s: %s", self.name, action, exc)

    def _ended(self, report: ActionReport) -> bool:
        if report.action_id != self.executing:
            return False
        self.executing = None
        return True

    def on_action_succeeded(self, report: ActionReport) -> None:
        self._ended(report)

    def on_action_failed(self, report: ActionReport) -> None:
        self._ended(report)

    def on_action_cancelled(self, report: ActionReport) -> None:
        self._ended(report)


class SuperSimpleMind(_SimpleMind):
    """Sends ``TestAction test`` when it wakes, and again after each failure."""

    def __init__(self, name: str = "mind") -> None:
        super().__init__(name)

    def on_start(self) -> None:
        if self.awake:
            self.on_wake()

    def on_wake(self) -> None:
        if self.executing is None:
            self._send("TestAction", "test")

    def on_action_failed(self, report: ActionReport) -> None:
        if self._ended(report) and self.awake:
            self.sim.call_later(RETRY_DELAY, self._retry)

    def _retry(self) -> None:
        if self.awake and self.executing is None:
            self._send("TestAction", "test")

    def on_property_changed(self, entity: str, name: str, value: Any, persistent: bool) -> None:
        if name == "cancel" and self.executing is not None:
            self.cancel(self.executing)


class SuperSimpleMigratingMind(_SimpleMind):
    """Migrates to ``B`` when it wakes; arrived there, back to ``A`` ``BACK_DELAY`` seconds later."""

    def __init__(self, name: str = MIND_STATE, there: str = "B", back: str = "A") -> None:
        super().__init__(name)
        self.there, self.back = there, back
        self.goal: str | None = None  # the goal it arrived with, None before any migration

    def on_start(self) -> None:
        if self.awake:
            self.on_wake()

    def on_wake(self) -> None:
        if self.executing is not None:
            return
        here = self.sim.embodiment
        if self.goal is None and here != self.there:
            self._send(MIGRATION_ACTION, self.there)
        elif self.goal is not None and here == self.there:
            self.sim.call_later(BACK_DELAY, self._migrate_back)

    def _migrate_back(self) -> None:
        if self.awake and self.executing is None and self.sim.embodiment != self.back:
            self._send(MIGRATION_ACTION, self.back)

    def state(self) -> dict[str, Any]:
        return {"goal": MIND_GOAL}

    def restore(self, state: dict[str, Any]) -> None:
        goal = state.get("goal")
        self.goal = goal if isinstance(goal, str) else ""
        log.info("mind %s arrived with goal %r", self.name, self.goal)


class SuperSimpleMigratingByInviteMind(_SimpleMind):
    """Follows invitations; where it sleeps (no companion), invites when an entity appears."""

    def __init__(self, name: str = MIND_STATE) -> None:
        super().__init__(name)
        self.goal: str | None = None

    def attach(self, sim: Simulation) -> None:
        super().attach(sim)
        # The base class hands world-model changes to an awake mind only; this one must see
        # entities appear where it sleeps, for that is when it invites.
        sim.on_event(self._entity_seen, component=keys.WORLD_MODEL)

    def _entity_seen(self, event: Event) -> None:
        change = None if self.awake else storage_change(event)
        if change is not None and change.op == "add_container" and change.container == "":
            log.info("mind %s: entity %r added while the companion is elsewhere: inviting it", self.name, change.name)
            self.raise_event(INVITE_EVENT, {"entity": change.name})

    def on_remote_action(self, action: MindAction) -> None:
        if action.name != INVITATION_ACTION:
            return
        where = action.subject or (action.parameters[0] if action.parameters else "")
        if where and self.executing is None:
            self._send(MIGRATION_ACTION, where)

    def state(self) -> dict[str, Any]:
        return {"goal": MIND_GOAL}

    def restore(self, state: dict[str, Any]) -> None:
        goal = state.get("goal")
        self.goal = goal if isinstance(goal, str) else ""
