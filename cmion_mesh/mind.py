"""The agent mind interface (CMION's ``AgentMindConnector``).

A ``Mind`` is an ION component that drives the body and perceives it:

* **to the body**: ``act(name, parameters, subject)`` sends a mind action to the competency
  manager and returns its id; ``cancel(action_id)`` stops it;
* **from the body**, each on the update loop, one at a time: the outcome of every action it sent
  (``on_action_succeeded`` / ``failed`` / ``cancelled``), world-model changes (``on_entity_added``,
  ``on_entity_removed``, ``on_property_changed``, ``on_property_removed``, with the persistent
  flag), remote actions (actions of other agents, raised as ``RemoteAction`` events by any
  component) and raw messages (``.../rq/<mind>/message``);
* ``sleep`` / ``wake`` (requests ``.../rq/<mind>/sleep`` and ``wake``: ``Sleep``, ``Wake``): an
  asleep mind perceives nothing and its ``act`` is refused; ``on_sleep`` / ``on_wake`` tell it;
* ``state`` (``MindState``) answers ``state()``; ``message`` (``MindMessage``) hands its data to
  ``on_message`` (refused while asleep);
* **to the world**: ``wm_add`` / ``wm_remove`` / ``wm_set`` write the world model (an entity and
  its properties, as a sensor would); they never wait (a mind runs on the update loop, where the
  store answers): each returns the outcome's future, and ``on_outcome`` runs on the loop.

A remote action comes from any component's ``RemoteAction`` event whose data is a
``messages.RemoteAction`` (or a map of its fields): a sensor's competency (``RunContext.remote_action``),
an invitation, or a person (``cmion-mesh remote-action``: the request ``.../rq/embodiment/remote_action``).

The same class runs inside the daemon (named in the architecture config) or in another process
(``body.remote_mind.serve_mind``, ``cmion-mesh serve-mind``): there its simulation carries the
embodiment's name, so its requests and subscriptions travel over zenoh, and it is added
(``on_start`` runs) once its embodiment is reachable. The key-space protocol is therefore only:
requests ``.../rq/manager/act|cancel``, events ``.../ev/manager/Action*`` and ``.../ev/wm/*``,
events ``.../ev/*/RemoteAction``, and the mind's own ``.../rq/<mind>/sleep|wake|message|state``. Any
zenoh client can be a mind. Several minds may drive one body, each under a name of its own.

``state()`` / ``restore()`` hold the mind's plain-data state, which migration packs.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import MeshError, RequestRejected
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import (
    Act,
    ActionReport,
    AddEntity,
    CancelAction,
    Code,
    Event,
    MindMessage,
    MindState,
    Outcome,
    RemoteAction,
    RemoveContainer,
    SetProperty,
    Sleep,
    StorageChange,
    StorageWrite,
    Wake,
    tag,
)
from cmion_mesh.requests import IncomingRequest

log = logging.getLogger(__name__)


class MindAction(msgspec.Struct, frozen=True):
    """An action sent by a mind for execution."""

    name: str
    parameters: tuple[str, ...] = ()
    subject: str = ""

    def __post_init__(self) -> None:
        # Accept a list from callers but keep the instance hashable and immutable.
        if not isinstance(self.parameters, tuple):
            msgspec.structs.force_setattr(self, "parameters", tuple(self.parameters))

    def describe(self) -> str:
        """The action as one line of text: its name and parameters (as events and reasons show it)."""
        return " ".join((self.name, *self.parameters))


#: Most parameters a remote action carries.
MAX_REMOTE_PARAMETERS = 64


def remote_action_problem(action: RemoteAction) -> str:
    """Why ``action`` cannot be perceived as it is, or "" when it can: its name, each parameter and
    its subject ("" allowed) are words (no white space), as minds' line protocols (FAtiMA's) carry
    them, split on spaces."""
    if len(action.parameters) > MAX_REMOTE_PARAMETERS:
        return f"remote action {action.name[:40]!r} has {len(action.parameters)} parameters, more than {MAX_REMOTE_PARAMETERS}"
    for what, word in (("name", action.name), *(("parameter", p) for p in action.parameters), ("subject", action.subject)):
        if not word and what == "subject":
            continue
        if not word or len(word) > keys.MAX_NAME or any(c.isspace() or ord(c) < 32 for c in word):
            return (f"remote action {what} {word[:40]!r} must be one word of 1 to {keys.MAX_NAME} characters, "
                    "without white space (minds split actions on spaces)")
    return ""


class Mind(Component):
    requests = {"sleep": Sleep, "wake": Wake, "message": MindMessage, "state": MindState}

    def __init__(self, name: str = "mind", *, awake: bool = True) -> None:
        super().__init__(name)
        self.awake = awake
        self._ids = itertools.count(1)
        self.pending: dict[str, Act] = {}

    # --- wiring -------------------------------------------------------------------------------

    def attach(self, sim: Simulation) -> None:
        sim.on_event(self._manager_event, component="manager")
        sim.on_event(self._world_event, component=keys.WORLD_MODEL)
        sim.on_event(self._remote_action, event="RemoteAction")
        self.on_start()

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        for request in batch:
            match request.payload:
                case Sleep():
                    self.sleep()
                    request.accept({"awake": self.awake})
                case Wake():
                    self.wake()
                    request.accept({"awake": self.awake})
                case MindState():
                    request.accept(self.state())
                case MindMessage() if not self.awake:
                    request.reject(f"mind {self.name!r} is asleep", Code.BUSY)
                case MindMessage(data=data):
                    self._message(request, data)

    def _message(self, request: IncomingRequest, data: dict[str, Any]) -> None:
        # Answered here, one message at a time: a message the mind refuses (or fails on) must not
        # take the other requests of its update down with it, as it would if it reached the loop.
        try:
            self.on_message(data)
        except RequestRejected as exc:
            request.answer(Outcome("rejected", exc.reason or str(exc), code=exc.code or Code.INVALID))
        except MeshError as exc:
            request.reject(str(exc), Code.INVALID)
        except Exception as exc:
            log.exception("mind %s failed on a message", self.name)
            request.reject(f"mind {self.name!r} failed on a message: {type(exc).__name__}: {exc}", Code.HANDLER_FAILED)
        else:
            request.accept()

    def sleep(self) -> None:
        if self.awake:
            self.awake = False
            self.raise_event("MindAsleep", {"mind": self.name})
            self.on_sleep()

    def wake(self) -> None:
        if not self.awake:
            self.awake = True
            self.raise_event("MindAwake", {"mind": self.name})
            self.on_wake()

    # --- to the body --------------------------------------------------------------------------

    def act(self, name: str, parameters: list[str] | tuple[str, ...] = (), subject: str = "", *, deadline: float = 0.0) -> str:
        """Send an action; returns its id. Its end arrives as ``on_action_*``. Refused while asleep."""
        if not self.awake:
            raise MeshError(f"mind {self.name!r} is asleep: action {name!r} not sent")
        action_id = f"{self.name}-{self.sim.transport.id[:6]}-{next(self._ids)}"
        act = Act(name, list(parameters), subject, action_id, deadline)
        self.pending[action_id] = act
        self.sim.request("manager", "act", act, on_outcome=lambda outcome: self._act_answered(act, outcome))
        return action_id

    def cancel(self, action_id: str) -> None:
        self.sim.request("manager", "cancel", CancelAction(action_id))

    # --- to the world model (never waiting: see the module's doc) -----------------------------

    def wm_add(self, entity: str, properties: Mapping[str, Any] | None = None, *, kind: str = "agent",
               persistent: bool = False, on_outcome: Callable[[Outcome], None] | None = None) -> Future[Outcome]:
        """Add the entity ``entity`` (``agent`` or ``object``) with ``properties``, in one write."""
        return self._write_world(AddEntity(entity, kind, dict(properties or {}), persistent), on_outcome)

    def wm_remove(self, entity: str, on_outcome: Callable[[Outcome], None] | None = None) -> Future[Outcome]:
        return self._write_world(RemoveContainer("", entity), on_outcome)

    def wm_set(self, entity: str, prop: str, value: Any, *, persistent: bool = False,
               on_outcome: Callable[[Outcome], None] | None = None) -> Future[Outcome]:
        return self._write_world(SetProperty(entity, prop, value, persistent), on_outcome)

    def _write_world(self, write: StorageWrite, on_outcome: Callable[[Outcome], None] | None) -> Future[Outcome]:
        return self.sim.request(keys.WORLD_MODEL, tag(type(write)), write, on_outcome=on_outcome)

    def _act_answered(self, act: Act, outcome: Outcome) -> None:
        if outcome.status != "accepted" and self.pending.pop(act.action_id, None) is not None:
            # Refused (no rule...) or unknown: the mind learns it as a failure with the reason.
            self.on_action_failed(ActionReport(act.action_id, act.name, list(act.parameters), act.subject, "failed", outcome.reason))

    # --- from the body ------------------------------------------------------------------------

    def _manager_event(self, event: Event) -> None:
        data = event.data if isinstance(event.data, dict) else {}
        if data.get("action_id") not in self.pending:
            return
        report = msgspec.convert(data, ActionReport)
        if event.name == "ActionSucceeded":
            self.pending.pop(report.action_id, None)
            self.on_action_succeeded(report)
        elif event.name == "ActionFailed":
            self.pending.pop(report.action_id, None)
            self.on_action_failed(report)
        elif event.name == "ActionCancelled":
            self.pending.pop(report.action_id, None)
            self.on_action_cancelled(report)

    def _world_event(self, event: Event) -> None:
        change = storage_change(event) if self.awake else None
        if change is None:
            return
        if change.op == "add_container" and change.container == "":
            self.on_entity_added(change.name, change.kind)
        elif change.op == "remove_container" and change.container == "":
            self.on_entity_removed(change.name, change.kind)
        elif change.op == "set_property":
            self.on_property_changed(change.container, change.name, change.value, change.persistent)
        elif change.op == "remove_property":
            self.on_property_removed(change.container, change.name, change.persistent)

    def _remote_action(self, event: Event) -> None:
        if not self.awake or not isinstance(event.data, dict):
            return
        data = event.data
        self.on_remote_action(MindAction(str(data.get("name", "")), tuple(str(p) for p in data.get("parameters", ())),
                                         str(data.get("subject", ""))))

    # --- to override --------------------------------------------------------------------------

    def on_start(self) -> None:
        """Once, when the mind can reach its body: added to a daemon, or, in a process of its own,
        once its embodiment is alive (``body.remote_mind``). A daemon's minds are asleep then
        (``act`` is refused) until their companion lives there: see ``on_arrived``."""
    def on_action_succeeded(self, report: ActionReport) -> None: ...
    def on_action_failed(self, report: ActionReport) -> None: ...
    def on_action_cancelled(self, report: ActionReport) -> None: ...
    def on_entity_added(self, name: str, kind: str) -> None: ...
    def on_entity_removed(self, name: str, kind: str) -> None: ...
    def on_property_changed(self, entity: str, name: str, value: Any, persistent: bool) -> None: ...
    def on_property_removed(self, entity: str, name: str, persistent: bool) -> None: ...
    def on_remote_action(self, action: MindAction) -> None: ...
    def on_message(self, data: dict[str, Any]) -> None: ...
    def on_sleep(self) -> None: ...
    def on_wake(self) -> None: ...

    def on_arrived(self, world_model: dict[str, Any]) -> None:
        """The companion (re)started on this embodiment, its state restored and the mind awake:
        replace embodiment-specific knowledge with this world model (``Store.tree()`` form)."""

    def connection(self) -> dict[str, Any] | None:
        """How a mind outside this process is linked to its connector (a socket's peer...), for the
        embodiment's description; None for a mind that is its own component."""
        return None

    def state(self) -> dict[str, Any]:
        """Plain data that migration carries; minds with memory override this and ``restore``."""
        return {}

    def restore(self, state: dict[str, Any]) -> None: ...


def storage_change(event: Event) -> StorageChange | None:
    """The change a store's event reports, or None when its data is not one."""
    try:
        return msgspec.convert(event.data, StorageChange)
    except msgspec.ValidationError:
        return None
