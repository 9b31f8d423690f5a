"""A mesh client: what tools (the CLI, tests, other programs) use to read, write and watch.

It needs only a transport, not a simulation: no update loop, no components of its own.
"""

from __future__ import annotations

import queue
import threading
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import MeshError, OutcomeUnknown, ProtocolError, RequestRejected, StorageError
from cmion_mesh.ion import DEFAULT_REQUEST_TIMEOUT, require_accepted, send_request
from cmion_mesh.messages import (
    Act,
    ActionReport,
    AddContainer,
    CancelAction,
    Container,
    Event,
    Message,
    Migrate,
    Outcome,
    Property,
    RemoveContainer,
    RemoveProperty,
    Request,
    SetPolicy,
    SetProperty,
    decode,
)
from cmion_mesh.transport import Closeable, Sample, Transport

Entry = Property | Container
ACTION_END_EVENTS = frozenset({"ActionSucceeded", "ActionFailed", "ActionCancelled"})


class MeshClient:
    def __init__(self, transport: Transport, mesh: str = keys.DEFAULT_MESH) -> None:
        self.transport = transport
        self.mesh = keys.check_name(mesh, "mesh")

    # --- storage ------------------------------------------------------------------------------

    def read(self, selector: str, *, timeout: float = 5.0) -> dict[str, Entry]:
        """All properties and containers under a zenoh selector, by key."""
        out: dict[str, Entry] = {}
        for reply in self.transport.get(selector, timeout=timeout):
            if not reply.ok:
                continue
            try:
                out[reply.key] = decode(reply.payload, Entry, where=reply.key)
            except ProtocolError:
                continue  # not a storage entry (another program answering the same keys)
        return dict(sorted(out.items()))

    def read_store(self, embodiment: str, store: str, path: str = "", *, timeout: float = 5.0) -> dict[str, Entry]:
        base = keys.storage_key(self.mesh, embodiment, store, keys.split_path(path))
        return self.read(f"{base}/**", timeout=timeout)

    def get_property(self, embodiment: str, store: str, container: str, name: str, *, timeout: float = 5.0) -> Property:
        key = keys.storage_key(self.mesh, embodiment, store, keys.split_path(container), name)
        for reply in self.transport.get(key, timeout=timeout):
            if reply.ok and reply.key == key:
                entry = decode(reply.payload, Entry, where=key)
                if isinstance(entry, Property):
                    return entry
        raise StorageError(f"no property at {key} (or no store answered)")

    def write(self, embodiment: str, store: str, write: Message, *, timeout: float = DEFAULT_REQUEST_TIMEOUT) -> Outcome:
        """Send one storage write; returns its outcome (accepted, rejected, conflict)."""
        op = {
            SetProperty: "set_property",
            RemoveProperty: "remove_property",
            AddContainer: "add_container",
            RemoveContainer: "remove_container",
        }[type(write)]
        return send_request(self.transport, keys.request_key(self.mesh, embodiment, store, op), write, timeout=timeout)

    def set_property(
        self, embodiment: str, store: str, container: str, name: str, value: Any, *, persistent: bool = False
    ) -> None:
        """Set a property or raise ``RequestRejected`` / ``OutcomeUnknown`` naming the key."""
        key = keys.request_key(self.mesh, embodiment, store, "set_property")
        require_accepted(self.write(embodiment, store, SetProperty(container, name, value, persistent)), key)

    # --- requests and events ------------------------------------------------------------------

    def request(
        self, embodiment: str, component: str, name: str, payload: Message | None = None,
        *, timeout: float = DEFAULT_REQUEST_TIMEOUT, sender: str | None = None,
    ) -> Outcome:
        key = keys.request_key(self.mesh, embodiment, component, name, sender)
        return send_request(self.transport, key, payload if payload is not None else Request(), timeout=timeout)

    def act(
        self, embodiment: str, name: str, parameters: Sequence[str] = (), *, subject: str = "", action_id: str = "",
        timeout: float = 60.0, deadline: float = 0.0,
    ) -> ActionReport:
        """Send a mind action and wait for its end; returns the final report (succeeded/failed/cancelled).

        Raises ``RequestRejected`` if the manager refuses it (no rule, duplicate id) and
        ``OutcomeUnknown`` if nobody answers or the end is not heard within ``timeout``.
        """
        action_id = action_id or f"{self.transport.id[:8]}-{uuid.uuid4().hex[:12]}"
        ended: queue.SimpleQueue[ActionReport] = queue.SimpleQueue()

        def on_event(event: Event) -> None:
            if event.name in ACTION_END_EVENTS and isinstance(event.data, dict) and event.data.get("action_id") == action_id:
                ended.put(msgspec.convert(event.data, ActionReport))

        with self.events(on_event, embodiment=embodiment, component="manager"):
            act = Act(name, list(parameters), subject, action_id, deadline)
            key = keys.request_key(self.mesh, embodiment, "manager", "act")
            outcome = send_request(self.transport, key, act)
            require_accepted(outcome, key)
            try:
                return ended.get(timeout=timeout)
            except queue.Empty:
                pass
        # The end event may have been missed (a link hiccup): the manager remembers recent ends.
        status = self.request(embodiment, "manager", "status", Request({"action_id": action_id}))
        if status.status == "accepted" and isinstance(status.value, dict) and status.value.get("status") != "running":
            report: ActionReport = msgspec.convert(status.value, ActionReport)
            return report
        raise OutcomeUnknown(f"action {action_id} on {embodiment}: no end heard within {timeout:g} s", key=key)

    def cancel(self, embodiment: str, action_id: str) -> Outcome:
        return self.request(embodiment, "manager", "cancel", CancelAction(action_id))

    def find_companion(self, companion: str, *, timeout: float = 2.0) -> str:
        """The embodiment inhabited by ``companion``; ``OutcomeUnknown`` if none says so."""
        for description in self.describe_all(timeout=timeout):
            if description.get("inhabitant") == companion:
                return str(description["name"])
        raise OutcomeUnknown(f"no embodiment in mesh {self.mesh!r} says it hosts companion {companion!r}")

    def migrate(self, companion: str, target: str, *, timeout: float = 60.0) -> dict[str, Any]:
        """Move ``companion`` to ``target``; returns ``{source, target, epoch, attempt}`` once the target committed.

        Raises ``RequestRejected`` with the reason if the migration is refused or fails (the
        companion then keeps running at its source) and ``OutcomeUnknown`` if its end is not heard.
        """
        source = self.find_companion(companion)
        ended: queue.SimpleQueue[Event] = queue.SimpleQueue()

        def on_event(event: Event) -> None:
            if event.name in ("MigrationSucceeded", "MigrationFailed") and isinstance(event.data, dict) \
                    and event.data.get("companion") == companion:
                ended.put(event)

        key = keys.request_key(self.mesh, source, "migration", "migrate")
        with self.events(on_event, embodiment=source, component="migration"):
            started = send_request(self.transport, key, Migrate(companion, target), timeout=timeout)
            require_accepted(started, key)
            try:
                event = ended.get(timeout=timeout)
            except queue.Empty:
                raise OutcomeUnknown(f"migration of {companion} from {source} to {target}: no end heard in {timeout:g} s",
                                     key=key) from None
        data = dict(event.data)
        if event.name == "MigrationFailed":
            raise RequestRejected(f"migration of {companion} to {target} failed: {data.get('reason')}", key=key,
                                  reason=str(data.get("reason")))
        data["source"] = source
        return data

    def set_policy(self, companion: str, accepts: Sequence[str] | None) -> None:
        """Say which embodiments ``companion`` accepts (None: any); it travels with the companion."""
        host = self.find_companion(companion)
        payload = SetPolicy(None if accepts is None else list(accepts))
        require_accepted(self.request(host, "migration", "policy", payload), keys.request_key(self.mesh, host, "migration", "policy"))

    def watch(self, selector: str, handler: Callable[[str, Entry | None], None]) -> Closeable:
        """``handler(key, entry)`` on every change under ``selector``; ``entry`` None when removed."""

        def on_sample(sample: Sample) -> None:
            if sample.deleted:
                handler(sample.key, None)
                return
            try:
                handler(sample.key, decode(sample.payload, Entry, where=sample.key))
            except ProtocolError:
                pass

        return self.transport.subscribe(selector, on_sample)

    def events(
        self, handler: Callable[[Event], None], *, embodiment: str = "*", component: str = "*", event: str = "*"
    ) -> Closeable:
        pattern = keys.event_pattern(self.mesh, embodiment, component, event)

        def on_sample(sample: Sample) -> None:
            if not sample.deleted:
                try:
                    handler(decode(sample.payload, Event, where=sample.key))
                except ProtocolError:
                    pass

        return self.transport.subscribe(pattern, on_sample)

    def describe(self, embodiment: str, *, timeout: float = 2.0) -> dict[str, Any]:
        """An embodiment's description (name, competency types, actions, inhabitant, version, started at)."""
        outcome = self.request(embodiment, "embodiment", "describe", timeout=timeout)
        value = require_accepted(outcome, keys.request_key(self.mesh, embodiment, "embodiment", "describe"))
        return value if isinstance(value, dict) else {"name": embodiment}

    def describe_all(self, *, timeout: float = 2.0) -> list[dict[str, Any]]:
        """Every live embodiment, described; one that does not answer is listed by name only."""
        names = self.embodiments(timeout=timeout)
        out = []
        with ThreadPoolExecutor(max_workers=max(1, min(16, len(names)))) as pool:
            futures = {name: pool.submit(self.describe, name, timeout=timeout) for name in names}
            for name, future in futures.items():
                try:
                    out.append(future.result())
                except MeshError as exc:
                    out.append({"name": name, "error": str(exc)})
        return out

    def wait_for_embodiment(self, embodiment: str, *, timeout: float = 5.0) -> None:
        """Return once ``embodiment``'s liveliness token is seen, else ``OutcomeUnknown`` naming it."""
        seen = threading.Event()
        key = keys.alive_key(self.mesh, embodiment)

        def on_token(token: str, alive: bool) -> None:
            if alive and token == key:
                seen.set()

        with self.transport.watch_liveliness(key, on_token):
            if not seen.wait(timeout):
                raise OutcomeUnknown(f"embodiment {embodiment!r} not found in mesh {self.mesh!r} within {timeout:g} s"
                                     " (try `cmion-mesh peers` or `cmion-mesh doctor`)")

    def embodiments(self, *, timeout: float = 2.0) -> list[str]:
        """Names of the embodiments whose liveliness token is present."""
        names = []
        for key in self.transport.alive(f"{keys.mesh_prefix(self.mesh)}/{keys.ALIVE}/*", timeout=timeout):
            names.append(key.rsplit("/", 1)[-1])
        return sorted(set(names))


__all__ = ["Entry", "MeshClient", "OutcomeUnknown"]
