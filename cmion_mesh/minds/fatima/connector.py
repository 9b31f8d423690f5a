"""CMION's agent-mind line protocol: the original LIREC mind (FAtiMA, Java) as a companion's mind.

``FAtiMAConnector`` is a ``Mind`` that listens on TCP (CMION's port 46874 by default, on loopback
unless told otherwise) for one FAtiMA connection and translates between FAtiMA's lines and the
embodiment: FAtiMA's actions go to the competency manager's rules, the world model's changes go to
FAtiMA, and around a migration FAtiMA's whole state (an opaque hex string) travels in the
companion's identity document. Name it in an ArchitectureConfiguration as CMION did::

    <ArchitectureComponent ClassName="cmion_mesh.minds.fatima.connector:FAtiMAConnector"
                           ConstructorParameters="modular persistent migrating"/>

Its options are read by ``protocol.parse_options`` and its lines written and read by ``protocol``;
the listener, the one-mind-at-a-time rule, the socket threads and the back-off of failed actions
are ``link``'s. Here: the mind's life cycle, its perceptions and actions, its state around a
migration.

**Held retries.** A retry of an action the ``FailureGate`` holds is answered ``ACTION-FAILED``
after ``HELD_ANSWER_DELAY`` seconds, not by running the rules again, and counted (``held_retries``
in ``connection()``).

**Raw messages** (``{"line": ...}`` to ``.../rq/<name>/message``) go to the mind as they are; as the
daemon stops the mind is sent ``CMD Save`` (FAtiMA compares with ``Save``; CMION's ``SAVE`` was ignored).

**Remote actions** (``RemoteAction`` events, e.g. ``MigrationInvitation <embodiment>``) reach the
mind as CMION's connector sent them before its last revision: ``ACTION-FINISHED <subject> <action>
[params]``, FAtiMA's perception of another agent's action (subject ``World`` when the event names
none). CMION's last revision sent ``CMD GET-PROPERTIES`` instead, so the mind never heard of them.

**Migration** (option ``migrating``): see ``docs/fatima.md``. The source stops the mind, asks for
its state and puts the hex into the mind's section unchanged; if the mind does not answer within
``state-timeout`` the migration is abandoned (the mind is woken: ``CMD Start``); with no mind
connected, one connecting within ``stop-wait`` + ``state-timeout`` is asked, else the migration is
refused (``MindStateUnavailable``): the companion never leaves with an empty mind. The target sends
``CMD SET-STATE``, waits for ``STATE-SET``, then ``CMD Start``, ``ACTION-FINISHED`` for the action
that migrated it (as CMION's ``successMsg``) and ``ACTION-FAILED`` for the others that were running
(cancelled at the source), a ``LOOK-AT`` per entity and ``CMD GET-PROPERTIES``. With no mind
connected when the companion arrives, the state is kept (and carried on, should the companion leave
first) and set in the next mind that connects. Late answers (a ``STATE`` or ``STATE-SET`` whose
request was given up) are logged and ignored.

**Log lines.** A mind connecting is a line at info (``FAtiMA mind <agent> at <address> connected``)
and one whose connection ends, not as the body stops, a line at warning (``FAtiMA mind <agent> at
<address> disconnected``); fields ``mind`` (this connector), ``agent``, ``peer`` (its address), ``role``
when connecting, ``reason``, ``cancelled`` (its running actions) and ``duration_s`` when
disconnecting. Connections refused or closed before a handshake are ``link``'s warnings, a few a
minute per host.
"""

from __future__ import annotations

import functools
import logging
import time
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from cmion_mesh import keys, logs, xmlsafe
from cmion_mesh.body.manager import CompetencyManager
from cmion_mesh.errors import MeshError, XmlError
from cmion_mesh.ion import Simulation
from cmion_mesh.messages import ActionReport, AddContainer, Event, SetProperty
from cmion_mesh.migration.manager import MigrationCompetency, MigrationManager
from cmion_mesh.mind import Mind, MindAction
from cmion_mesh.minds.fatima.link import MAX_HELD, FailureGate, Link, Listener, Switchboard
from cmion_mesh.minds.fatima.protocol import (
    MAX_LINE,
    SAVE_COMMAND,
    ActionKey,
    Handshake,
    action_text,
    format_value,
    look_at_line,
    parse_emotional_state,
    parse_options,
    parse_semantic_memory,
    property_changed_line,
)
from cmion_mesh.storage import Store
from cmion_mesh.timers import Timer

log = logging.getLogger(__name__)

#: Seconds before a held retry of a failed action is answered ``ACTION-FAILED``.
HELD_ANSWER_DELAY = 1.0


# --- the connector -----------------------------------------------------------------------------------


@dataclass
class _Running:
    key: ActionKey
    link: Link


@dataclass
class _Outgoing:
    """The source's side of a migration while the mind's state is asked for."""

    token: Any
    link: Link | None  # None: no mind was connected as the migration started; the next one is asked
    timer: Timer | None = None
    asked: bool = False  # CMD GET-STATE went out: a STATE before it answered an older request


@dataclass
class _Arrival:
    """The target's side: a state to set in the mind, then its new world to tell it."""

    state: dict[str, Any]
    link: Link | None = None  # the mind it was sent to, awaiting STATE-SET
    sent: int = 0  # which of that link's SET-STATEs it was (its STATE-SET is the answer of that number)
    timer: Timer | None = None
    awake: bool = False
    world: dict[str, Any] | None = None


class FAtiMAConnector(Mind):
    """CMION's ``FAtiMAConnector``: the FAtiMA mind over the agent-mind line protocol (see the module)."""

    def __init__(self, *parameters: str) -> None:
        self.options = parse_options(parameters)
        super().__init__(self.options.name)
        self.gate = FailureGate()
        self.switchboard = Switchboard(self.name, self.options.handshake_timeout, on_mind=self._mind_connected,
                                       on_line=self._on_line, on_lost=self._disconnected)
        self._running: dict[str, _Running] = {}
        self._outgoing: _Outgoing | None = None
        self._given: tuple[Link, str] | None = None  # the mind that gave its state to a migration, and the state
        self._arrival: _Arrival | None = None
        self._held_timers: dict[ActionKey, Timer] = {}
        self._counts = {"actions": 0, "failures": 0}
        self._properties_due = False
        # Facts the mind's semantic memory wrote into the world model: their change events are not
        # told back to the mind, which knows them ({(entity, property): (value as told, persistent)}).
        self._told: OrderedDict[tuple[str, str], tuple[str, bool]] = OrderedDict()

    @property
    def listener(self) -> Listener | None:
        return self.switchboard.listener

    @property
    def link(self) -> Link | None:
        """The connected mind (loop)."""
        return self.switchboard.link

    # --- life cycle (loop) --------------------------------------------------------------------------

    def attach(self, sim: Simulation) -> None:
        if not isinstance(sim.components_by_name().get(keys.WORLD_MODEL), Store):
            log.warning("FAtiMA connector %r runs without the embodiment's world model (outside its daemon?): look-at "
                        "answers name no properties and the mind does not migrate", self.name)
        sim.on_event(self._migration_event, component="migration")
        self._blackboard(AddContainer("", self.name, "mind"))
        try:
            listener = self.switchboard.listen(sim, self.options.host, self.options.port)
        except MeshError as exc:
            log.error("FAtiMA connector %r: %s: no FAtiMA mind can connect", self.name, exc)
            self.raise_event("MindServerFailed", {"mind": self.name, "reason": str(exc)})
        else:
            self._blackboard(SetProperty(self.name, "port", listener.port))
            self._blackboard(SetProperty(self.name, "connected", False))
        super().attach(sim)

    def detach(self) -> None:
        self.switchboard.close(farewell=SAVE_COMMAND)  # the body stops: the mind keeps what it learnt in its files

    def connection(self) -> dict[str, Any]:
        """For the embodiment's description: where it listens, which mind is connected, the counts."""
        link = self.link
        return {"protocol": "fatima", "listening": self.listener.address if self.listener is not None else None,
                "connected": link is not None and link.handshaken, "peer": link.peer if link is not None else None,
                "agent": link.agent if link is not None else None, "held_retries": self.gate.held_retries,
                "lines_in_flight": link.in_flight if link is not None else 0,
                "bytes_queued": link.queued if link is not None else 0, "pending": self.switchboard.pending(),
                **self._counts, "connections": self.switchboard.connections}

    # --- the mind comes and goes (loop) -------------------------------------------------------------

    def _mind_connected(self, link: Link, hello: Handshake) -> None:
        """``link`` completed its handshake, was answered ``OK`` and is the mind now."""
        # The mind's own properties make it an agent of the world model, as in CMION. A property
        # there already keeps its persistence (its semantic memory said which): otherwise it would
        # flip with every connection, and each flip is told to the mind again.
        self._world(AddContainer("", hello.agent, "agent"))
        known = self._world_tree().get("children", {}).get(hello.agent, {}).get("properties", {})
        for name, value in hello.properties.items():
            current = known.get(name)
            self._world(SetProperty(hello.agent, name, value, bool(isinstance(current, dict) and current.get("persistent"))))
        self.sim.request(keys.BLACKBOARD, "set_property", SetProperty("", "agentName", hello.agent))
        facts: dict[str, Any] = {"connected": True, "peer": link.peer, "agent": hello.agent, "role": hello.role,
                                 "display_name": hello.display_name}
        for fact, value in facts.items():
            self._blackboard(SetProperty(self.name, fact, value))
        self.raise_event("MindConnected", {"mind": self.name, "agent": hello.agent, "peer": link.peer, "role": hello.role})
        logs.event(log, f"FAtiMA mind {hello.agent} at {link.peer} connected to {self.name}", mind=self.name, agent=hello.agent,
                   peer=link.peer, role=hello.role)
        if self._arrival is not None and self.options.migrating:
            self._set_state(link)
        elif not self.awake:
            link.send("CMD Stop")
            outgoing = self._outgoing
            if outgoing is not None and outgoing.link is None:  # a migration waits for a mind to ask
                outgoing.link = link
                self.sim.call_later(self.options.stop_wait, functools.partial(self._ask_state, outgoing))
        else:
            link.send("CMD GET-PROPERTIES")
            for entity in self._entities(self._world_tree()):
                link.send(f"ENTITY-ADDED {entity}")

    def _disconnected(self, link: Link, why: str) -> None:
        """The mind's connection ended (not as the body stops)."""
        logs.event(log, f"FAtiMA mind {link.agent} at {link.peer} disconnected from {self.name} ({why}); its {len(self._running)} running "
                        "action(s) are cancelled", level=logging.WARNING, mind=self.name, agent=link.agent, peer=link.peer,
                   reason=why, cancelled=len(self._running), duration_s=round(time.time() - link.connected_at, 3))
        self.raise_event("MindDisconnected", {"mind": self.name, "agent": link.agent, "peer": link.peer, "reason": why})
        self._blackboard(SetProperty(self.name, "connected", False))
        for action_id in list(self._running):
            self.cancel(action_id)
        self._running.clear()
        for timer in self._held_timers.values():
            timer.cancel()
        self._held_timers.clear()
        self.gate.clear()
        self._told.clear()
        if self._outgoing is not None and self._outgoing.link is link:
            self._state_overdue(self._outgoing, f"disconnected ({why}) while its state was asked for")
        if self._arrival is not None and self._arrival.link is link:
            self._unwait_arrival()
            self._arrival.link = None  # kept: set in the next mind that connects

    # --- lines from the mind (loop) -----------------------------------------------------------------

    def _on_line(self, link: Link, line: str) -> None:
        head, _, rest = line.strip().partition(" ")
        where = f"FAtiMA mind {link.agent} at {link.peer}"
        if head == "look-at":
            self._look_at(link, rest.split()[0] if rest.split() else "")
        elif head == "STATE":
            self._state_received(link, rest.strip())
        elif head == "STATE-SET":
            self._state_set_answer(link)
        elif head == "CANCEL-ACTION":
            self._cancel_action(rest.split())
        elif head.startswith("<"):
            self._xml(link, line.strip(), where)
        elif head.startswith("PROPERTY-CHANGED") or head == "":
            pass  # the mind does not change the world by itself (CMION ignored these too)
        else:
            self._action(link, head, tuple(rest.split()))

    def _look_at(self, link: Link, entity: str) -> None:
        if not entity:
            log.warning("FAtiMA mind %s at %s: 'look-at' without an entity ignored", link.agent, link.peer)
            return
        self._send_look_at(link, entity, self._world_tree())

    def _send_look_at(self, link: Link, entity: str, tree: Mapping[str, Any]) -> None:
        node = tree.get("children", {}).get(entity)
        link.send(look_at_line(entity, node.get("properties", {}) if isinstance(node, dict) else {}, self.options.persistent))
        link.send(f"ACTION-FINISHED {link.agent} look-at {entity}")

    def _xml(self, link: Link, line: str, where: str) -> None:
        try:
            if line.startswith("<EmotionalState"):
                state = parse_emotional_state(line, where)
                self._blackboard(SetProperty(self.name, "EmotionalState", line))
                self._blackboard(SetProperty(self.name, "mood", state["mood"]))
                self._blackboard(SetProperty(self.name, "emotions", state["emotions"]))
                self.sim.request(keys.BLACKBOARD, "set_property", SetProperty("", "FatimaMood", format_value(state["mood"])))
            elif line.startswith("<SemanticMemory"):
                self._semantic_memory(link, parse_semantic_memory(line, link.agent, where))
            elif line.startswith("<MemoryResult"):
                xmlsafe.loads(line.encode("utf-8"), None, name=where, max_bytes=MAX_LINE)
                self._blackboard(SetProperty(self.name, "MemoryResult", line))
            # <Relations ...> and other reports: not used by a single-agent body (CMION ignored them)
        except XmlError as exc:
            log.warning("%s sent a malformed line, ignored: %s", where, exc)

    def _semantic_memory(self, link: Link, facts: list[tuple[str, str, str, bool]]) -> None:
        """Keep the mind's knowledge on the blackboard, and copy it into the world model as CMION did
        (only what differs, so an unchanged fact is not told back to the mind)."""
        self._blackboard(SetProperty(self.name, "SemanticMemory",
                                     [{"name": f"{e}({p})", "value": v, "persistent": pers} for e, p, v, pers in facts]))
        tree = self._world_tree()
        children = tree.get("children", {})
        added: set[str] = set()
        for entity, name, value, persistent in facts:
            if not (keys.is_name(entity) and keys.is_name(name)):
                continue
            node = children.get(entity)
            if node is None and entity not in added:
                kind = "object" if any(e == entity and p == "isObject" and v.lower() == "true" for e, p, v, _ in facts) else "agent"
                self._world(AddContainer("", entity, kind))
                added.add(entity)
            current = node.get("properties", {}).get(name) if isinstance(node, dict) else None
            if isinstance(current, dict) and format_value(current.get("value")) == value and bool(current.get("persistent")) == persistent:
                continue
            self._told[(entity, name)] = (value, persistent)
            self._told.move_to_end((entity, name))
            while len(self._told) > MAX_HELD:
                self._told.popitem(last=False)
            self._world(SetProperty(entity, name, value, persistent))

    # --- actions --------------------------------------------------------------------------------------

    def _action(self, link: Link, name: str, parameters: tuple[str, ...]) -> None:
        key: ActionKey = (name, parameters)
        held = self.gate.held(key)
        if held is not None:
            if not held.answering:
                held.answering = True
                self._held_timers[key] = self.sim.call_later(HELD_ANSWER_DELAY, functools.partial(self._answer_held, link, key))
            return
        self._counts["actions"] += 1
        try:
            action_id = self.act(name, parameters, link.agent)
        except MeshError as exc:
            self._failed(link, key, str(exc))
            return
        self._running[action_id] = _Running(key, link)

    def _answer_held(self, link: Link, key: ActionKey) -> None:
        self._held_timers.pop(key, None)
        failure = self.gate.get(key)
        if failure is not None:
            failure.answering = False
        if link is self.link and link.open:
            link.send(f"ACTION-FAILED {link.agent} {action_text(*key)}")

    def _failed(self, link: Link, key: ActionKey, reason: str) -> None:
        previous = self.gate.get(key)
        retried = previous.retries if previous is not None else 0
        failure = self.gate.failed(key, reason)
        self._counts["failures"] += 1
        log.info("FAtiMA action %r of %s failed (%s); retries held for %.0f s%s", action_text(*key), link.agent, reason,
                 failure.hold, f" ({retried} retries answered since the last run)" if retried else "")
        if link is self.link and link.open:
            link.send(f"ACTION-FAILED {link.agent} {action_text(*key)}")

    def _cancel_action(self, tokens: list[str]) -> None:
        if not tokens:
            return
        key: ActionKey = (tokens[0], tuple(tokens[1:]))
        exact = [i for i, r in self._running.items() if r.key == key]
        named = [i for i, r in self._running.items() if r.key[0] == key[0]]
        chosen = exact or named[-1:]
        for action_id in chosen:
            self.cancel(action_id)

    def on_action_succeeded(self, report: ActionReport) -> None:
        running = self._running.pop(report.action_id, None)
        if running is None:
            return
        self.gate.succeeded(running.key)
        link = running.link
        if link is self.link and link.open:
            link.send(f"ACTION-FINISHED {link.agent} {action_text(*running.key)}")

    def on_action_failed(self, report: ActionReport) -> None:
        running = self._running.pop(report.action_id, None)
        if running is not None:
            self._failed(running.link, running.key, report.reason or "failed")

    def on_action_cancelled(self, report: ActionReport) -> None:
        # FAtiMA takes no feedback on a cancellation (CMION sent none).
        self._running.pop(report.action_id, None)

    def on_remote_action(self, action: MindAction) -> None:
        link = self._ready()
        if link is not None:
            link.send(f"ACTION-FINISHED {action.subject or 'World'} {action_text(action.name, action.parameters)}")

    # --- perceptions (loop) -------------------------------------------------------------------------

    def _ready(self) -> Link | None:
        link = self.link
        return link if link is not None and link.handshaken and link.open else None

    def on_entity_added(self, name: str, kind: str) -> None:
        link = self._ready()
        if link is not None:
            link.send(f"ENTITY-ADDED {name}")

    def on_entity_removed(self, name: str, kind: str) -> None:
        link = self._ready()
        if link is not None:
            link.send(f"ENTITY-REMOVED {name}")

    def on_property_changed(self, entity: str, name: str, value: Any, persistent: bool) -> None:
        if self._told and self._told.pop((entity, name), None) == (format_value(value), persistent):
            return  # the mind's own semantic memory wrote it: it knows
        link = self._ready()
        if link is not None and entity and "/" not in entity:  # entities are the world model's top level
            link.send(property_changed_line(entity, name, value, persistent, self.options))

    def on_property_removed(self, entity: str, name: str, persistent: bool) -> None:
        link = self._ready()
        if link is not None and entity and "/" not in entity:
            link.send(f"PROPERTY-REMOVED {entity} {name}")

    # --- sleep, wake, migration (loop) --------------------------------------------------------------

    def on_sleep(self) -> None:
        link = self._ready()
        if link is not None:
            link.send("CMD Stop")

    def on_wake(self) -> None:
        arrival = self._arrival
        if arrival is not None and arrival.link is not None:
            arrival.awake = True  # CMD Start once the state is set
            return
        link = self._ready()
        if link is not None:
            link.send("CMD Start")
            self._properties_due = True  # unless on_arrived, which follows a wake on arrival, asks first
            self.sim.call(functools.partial(self._ask_properties, link))

    def _ask_properties(self, link: Link) -> None:
        if self._properties_due and link is self._ready():
            link.send("CMD GET-PROPERTIES")
        self._properties_due = False

    def on_message(self, data: dict[str, Any]) -> None:
        """A raw message ``{"line": "..."}`` is sent to the mind as it is (CMION's raw messages)."""
        line = data.get("line")
        link = self._ready()
        if not isinstance(line, str) or "\n" in line or "\r" in line:
            raise MeshError(f"mind {self.name!r} takes a raw message {{'line': 'one line of text'}}, not {str(data)[:80]}")
        if link is None:
            raise MeshError(f"no FAtiMA mind is connected to {self.name!r}")
        link.send(line)

    def on_arrived(self, world_model: dict[str, Any]) -> None:
        arrival = self._arrival
        if arrival is not None and arrival.link is not None:
            arrival.world = world_model
            return
        link = self._ready()
        if link is not None:
            self._tell_world(link, world_model)

    def _tell_world(self, link: Link, tree: Mapping[str, Any]) -> None:
        for entity in self._entities(tree):
            self._send_look_at(link, entity, tree)
        link.send("CMD GET-PROPERTIES")
        self._properties_due = False

    def _migration_event(self, event: Event) -> None:
        if event.name == "MigrationStarting":
            self._migration_starting()
        elif event.name in ("MigrationFailed", "MigrationSucceeded") and self._outgoing is not None:
            outgoing, self._outgoing = self._outgoing, None
            if outgoing.timer is not None:
                outgoing.timer.cancel()
        if event.name == "MigrationSucceeded":  # the companion left: a state kept for it left with it
            self._unwait_arrival()
            self._arrival = None
            self._companion_left()

    def _companion_left(self) -> None:
        """The mind's actions went with the companion (told to its mind where it arrived): those still
        running here are cancelled, nothing more about them is told to the mind left behind."""
        migrating = set(self._actions_running(MigrationCompetency.type))
        for action_id in list(self._running):
            if action_id not in migrating:  # the Migrate action ends by itself, with the migration
                self.cancel(action_id)
        self._running.clear()

    def _migration_starting(self) -> None:
        manager = self._migration()
        if not self.options.migrating or manager is None:
            return
        link = self._ready()
        if link is None and self._arrival is not None:
            return  # the state kept for the next mind is carried by state()
        try:
            token = manager.wait(self.name)
        except MeshError:
            return  # the migration ended already
        outgoing = _Outgoing(token, link)
        self._outgoing = outgoing
        wait = self.options.stop_wait + self.options.state_timeout
        if link is None:
            # Leaving without it would carry an empty mind: a mind connecting meanwhile is asked instead.
            log.warning("FAtiMA connector %r: the companion starts leaving with no FAtiMA mind connected; a mind that "
                        "connects within %g s is asked for its state, else the migration is refused", self.name, wait)
        else:
            # CMD Stop went out as the mind was put to sleep; give FAtiMA's cycle a moment to end.
            self.sim.call_later(self.options.stop_wait, functools.partial(self._ask_state, outgoing))
        outgoing.timer = self.sim.call_later(wait, functools.partial(self._state_overdue, outgoing))

    def _ask_state(self, outgoing: _Outgoing) -> None:
        link = outgoing.link
        if self._outgoing is outgoing and link is not None and link.open:
            outgoing.asked = True
            link.send("CMD GET-STATE")

    def _state_overdue(self, outgoing: _Outgoing, why: str = "") -> None:
        if self._outgoing is not outgoing:
            return
        self._outgoing = None
        if outgoing.timer is not None:
            outgoing.timer.cancel()
        link = outgoing.link
        wait = self.options.stop_wait + self.options.state_timeout
        if link is None:
            listening = self.listener.address if self.listener is not None else "no address (it could not listen)"
            reason = (f"no FAtiMA mind is connected to connector {self.name!r} (listening on {listening}) to give the "
                      f"companion's mind state; none connected within {wait:g} s")
        else:
            reason = (f"the FAtiMA mind {link.agent} at {link.peer} (connector {self.name!r}) "
                      f"{why or f'did not answer GET-STATE within {self.options.state_timeout:g} s'}")
        log.error("%s: the migration is refused", reason)
        self.raise_event("MindStateUnavailable", {"mind": self.name, "agent": link.agent if link is not None else "",
                                                  "peer": link.peer if link is not None else "", "reason": reason})
        manager = self._migration()
        if manager is not None:
            manager.refuse(outgoing.token, reason)

    def _state_received(self, link: Link, hex_state: str) -> None:
        outgoing = self._outgoing
        if outgoing is None or outgoing.link is not link or not outgoing.asked:
            # A late answer to a GET-STATE whose migration was abandoned: an older state than the mind's.
            log.warning("FAtiMA mind %s at %s sent a STATE nobody asked for (late, or before CMD GET-STATE): ignored",
                        link.agent, link.peer)
            return
        if not hex_state or any(c.isspace() for c in hex_state):
            self._state_overdue(outgoing, "answered GET-STATE with no state (or more than one token)")
            return
        self._outgoing = None
        if outgoing.timer is not None:
            outgoing.timer.cancel()
        self._given = (link, hex_state)
        # The Migrate action succeeds where the companion arrives (CMION's successMsg); the others
        # end here with the companion, so the mind is told they failed and retries those it still wants.
        migrating = set(self._actions_running(MigrationCompetency.type))
        finished: list[str] = []
        failed: list[str] = []
        for action_id, running in self._running.items():
            if running.link is link:
                (finished if action_id in migrating else failed).append(action_text(*running.key))
        manager = self._migration()
        if manager is not None:
            manager.resolve(outgoing.token, {
                "state": hex_state, "agent": link.agent, "from": self.sim.embodiment,
                "finished": [f"ACTION-FINISHED {link.agent} {text}" for text in finished],
                "failed": [f"ACTION-FAILED {link.agent} {text}" for text in failed]})

    def _actions_running(self, competency_type: str) -> list[str]:
        manager = self.sim.components_by_name().get("manager")
        return manager.actions_running(competency_type) if isinstance(manager, CompetencyManager) else []

    def state(self) -> dict[str, Any]:
        """A state that arrived and is not yet set in a mind (carried on if the companion leaves first)."""
        return dict(self._arrival.state) if self._arrival is not None else {}

    def restore(self, state: dict[str, Any]) -> None:
        if not self.options.migrating or not isinstance(state.get("state"), str):
            return
        if state.get("from") == self.sim.embodiment:
            # Resumed here after a migration failed past its packing: the document holds the state
            # this embodiment's mind gave, and its actions did not end.
            given = self._given
            if given is not None and given[0] is self._ready() and given[1] == state["state"]:
                return  # the mind that gave it is still here, holding it
            state = {**state, "finished": [], "failed": []}
        self._unwait_arrival()
        self._arrival = _Arrival(dict(state))
        link = self._ready()
        if link is not None:
            self._set_state(link)
        else:
            log.warning("FAtiMA connector %r: the companion's mind state arrived with no FAtiMA mind connected; it is set "
                        "in the next one that connects", self.name)

    def _set_state(self, link: Link) -> None:
        arrival = self._arrival
        assert arrival is not None
        arrival.link = link
        link.set_states_sent += 1
        arrival.sent = link.set_states_sent
        arrival.awake = arrival.awake or self.awake
        link.send(f"CMD SET-STATE {arrival.state['state']}")
        arrival.timer = self.sim.call_later(self.options.state_timeout, functools.partial(self._set_overdue, arrival))

    def _set_overdue(self, arrival: _Arrival) -> None:
        if self._arrival is arrival and arrival.link is not None:
            log.error("FAtiMA mind %s at %s did not answer SET-STATE within %g s: started anyway", arrival.link.agent,
                      arrival.link.peer, self.options.state_timeout)
            self._state_set(arrival.link, confirmed=False)

    def _state_set_answer(self, link: Link) -> None:
        """A ``STATE-SET`` line: the mind answers SET-STATEs in order, so it is the answer to the
        next one of this link; one whose arrival timed out, or was replaced, is ignored."""
        link.set_states_answered += 1
        answer = link.set_states_answered
        arrival = self._arrival
        if arrival is not None and arrival.link is link and arrival.sent == answer:
            self._state_set(link)
            return
        awaited = f"#{arrival.sent} is awaited" if arrival is not None and arrival.link is link else "none is awaited"
        log.warning("FAtiMA mind %s at %s answered SET-STATE #%d late (%s): ignored, the state kept as it is",
                    link.agent, link.peer, answer, awaited)

    def _state_set(self, link: Link, *, confirmed: bool = True) -> None:
        arrival = self._arrival
        if arrival is None or arrival.link is not link:
            return
        self._unwait_arrival()
        if confirmed:
            self._arrival = None
        else:
            arrival.link = None  # kept: set again in the next mind that connects
        if not (arrival.awake or self.awake):
            link.send("CMD Stop")
            return
        link.send("CMD Start")
        for name in ("finished", "failed"):
            lines = arrival.state.get(name)
            for line in lines if isinstance(lines, list) else []:
                if isinstance(line, str) and line.startswith("ACTION-") and "\n" not in line:
                    link.send(line)
        self._tell_world(link, arrival.world if arrival.world is not None else self._world_tree())

    def _unwait_arrival(self) -> None:
        arrival = self._arrival
        if arrival is not None and arrival.timer is not None:
            arrival.timer.cancel()
            arrival.timer = None

    def _migration(self) -> MigrationManager | None:
        manager = self.sim.components_by_name().get("migration")
        return manager if isinstance(manager, MigrationManager) else None

    # --- stores ---------------------------------------------------------------------------------------

    def _blackboard(self, write: SetProperty | AddContainer) -> None:
        self.sim.request(keys.BLACKBOARD, "set_property" if isinstance(write, SetProperty) else "add_container", write)

    def _world(self, write: SetProperty | AddContainer) -> None:
        self.sim.request(keys.WORLD_MODEL, "set_property" if isinstance(write, SetProperty) else "add_container", write)

    def _world_tree(self) -> dict[str, Any]:
        store = self.sim.components_by_name().get(keys.WORLD_MODEL)
        return store.tree() if isinstance(store, Store) else {}

    @staticmethod
    def _entities(tree: Mapping[str, Any]) -> list[str]:
        """Agents first, then objects, as CMION told them."""
        children = tree.get("children", {})
        return sorted(children, key=lambda n: (children[n].get("kind") != "agent", n))
