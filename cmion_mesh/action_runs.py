"""A mind action on its way, as a client follows it: ``ActionRun`` waits for one action's report,
``ActionWatch`` is the one subscription to an embodiment's action ends that hands each end to its
run. ``MeshClient.start_action`` and ``act`` make them; ``watch_actions`` keeps the watches."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Protocol

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import OutcomeUnknown, ProtocolError, Vanished
from cmion_mesh.messages import ActionReport, ActionStatus, Event, Message, Outcome, decode
from cmion_mesh.presence import Presence
from cmion_mesh.transport.base import Handle, Sample, Transport

ACTION_END_EVENTS = frozenset({"ActionSucceeded", "ActionFailed", "ActionCancelled"})


class ActionClient(Protocol):
    """What a run and a watch use of the client that follows them (``MeshClient``)."""

    @property
    def mesh(self) -> str: ...

    @property
    def transport(self) -> Transport: ...

    @property
    def presence(self) -> Presence: ...

    def request(self, embodiment: str, component: str, name: str, payload: Message, *, timeout: float = ...,
                sender: str | None = ...) -> Outcome: ...

    def _follow(self, embodiment: str, run: ActionRun | None) -> ActionWatch: ...

    def _forget(self, watch: ActionWatch) -> None: ...


class ActionWatch(Handle):
    """One subscription to an embodiment's action end events, handing each to the ``ActionRun`` of
    its action id (``MeshClient.watch_actions``). Close it (idempotent) to stop following."""

    def __init__(self, client: ActionClient, embodiment: str) -> None:
        self.client = client
        self.embodiment = embodiment
        self.closed = False
        self._runs: dict[str, ActionRun] = {}
        self._lock = threading.Lock()
        self._ends = tuple(keys.event_key(client.mesh, embodiment, "manager", name) for name in ACTION_END_EVENTS)
        # The manager's other events (started, attempt) are skipped by key, never decoded.
        self._events = client.transport.subscribe_batches(keys.event_pattern(client.mesh, embodiment, "manager", "*"),
                                                          self._on_samples)

    @property
    def busy(self) -> bool:
        """Whether an action is in flight on it."""
        with self._lock:
            return bool(self._runs)

    def _add(self, run: ActionRun) -> None:
        with self._lock:
            self._runs[run.action_id] = run

    def _remove(self, run: ActionRun) -> None:
        with self._lock:
            if self._runs.get(run.action_id) is run:
                del self._runs[run.action_id]

    def _on_samples(self, batch: list[Sample]) -> None:
        for key, payload, deleted, _ in batch:
            if deleted or key not in self._ends:
                continue
            try:
                event = decode(payload, Event, where=key)
                if not isinstance(event.data, dict):
                    continue
                with self._lock:
                    run = self._runs.get(str(event.data.get("action_id")))
                if run is not None:
                    run._end(msgspec.convert(event.data, ActionReport))
            except (ProtocolError, msgspec.ValidationError):
                continue  # not a manager's report (another program on the same keys)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.client._forget(self)
        self._events.close()


class ActionRun(Handle):
    """A mind action on its way: ``wait`` for its report. Follows the manager's end events (through
    the client's ``watch_actions``) and the embodiment's liveliness; close it (idempotent) to stop
    following."""

    def __init__(self, client: ActionClient, embodiment: str, action_id: str, on_end: Callable[[], None] | None) -> None:
        self.client = client
        self.embodiment = embodiment
        self.action_id = action_id
        self.report: ActionReport | None = None
        self.vanished = False
        self.ended = threading.Event()
        self._on_end = on_end
        self._started = time.monotonic()
        self._watch = client._follow(embodiment, self)
        self._presence = client.presence.listen(self._on_presence)
        if embodiment not in client.presence.alive():
            self._end(None)

    def __enter__(self) -> ActionRun:
        return self

    def _on_presence(self, name: str, alive: bool) -> None:
        if name == self.embodiment and not alive:
            self._end(None)

    def _end(self, report: ActionReport | None) -> None:
        if self.ended.is_set():
            return
        if report is None:
            self.vanished = True
        else:
            self.report = report
        self.ended.set()
        if self._on_end is not None:
            self._on_end()

    def wait(self, timeout: float) -> ActionReport:
        """The final report, once the action ends (see ``result``)."""
        self.ended.wait(timeout)
        return self.result(timeout)

    def result(self, waited: float) -> ActionReport:
        """The final report: ``Vanished`` if the embodiment left first; when no end was heard (after
        ``waited`` seconds) the manager is asked, since an end event may be missed, and
        ``OutcomeUnknown`` if the action is still running."""
        key = keys.request_key(self.client.mesh, self.embodiment, "manager", "act")
        if self.report is not None:
            return self.report
        if self.vanished:
            raise Vanished(f"{self.embodiment} left the mesh {time.monotonic() - self._started:.1f} s into action "
                           f"{self.action_id}: its outcome is unknown", key=key)
        status = self.client.request(self.embodiment, "manager", "status", ActionStatus(self.action_id))
        if status.status == "accepted" and isinstance(status.value, dict) and status.value.get("status") != "running":
            report: ActionReport = msgspec.convert(status.value, ActionReport)
            return report
        raise OutcomeUnknown(f"action {self.action_id} on {self.embodiment}: no end heard within {waited:g} s", key=key)

    def close(self) -> None:
        self._presence.close()
        self._watch._remove(self)


__all__ = ["ACTION_END_EVENTS", "ActionClient", "ActionRun", "ActionWatch"]
