"""A mesh client: what tools (the CLI, tests, other programs) use to read, write and watch.

It needs only a transport, not a simulation: no update loop, no components of its own.

Join, then ask: a session that has just opened knows nobody. Whatever is addressed to a named
embodiment (``act``, ``migrate``, ``join``) first waits, within its deadline, for that
embodiment's liveliness token, and ``describe_all`` waits until it has described every embodiment
that any live daemon sees: a daemon has been in the mesh long enough to know all of it.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

from cmion_mesh import companions, keys
from cmion_mesh.action_runs import ActionRun, ActionWatch
from cmion_mesh.errors import (
    MeshError,
    NotAlive,
    NotReached,
    OutcomeUnknown,
    ProtocolError,
    StorageError,
    Vanished,
)
from cmion_mesh.messages import (
    CONTAINER_KIND,
    Act,
    ActionReport,
    AddContainer,
    AddEntity,
    CancelAction,
    Container,
    Describe,
    Event,
    Message,
    Outcome,
    Property,
    RemoteAction,
    RemoveContainer,
    RemoveProperty,
    SetProperty,
    StorageWrite,
    decode,
    decoder,
    encode,
    many_decoder,
    tag,
)
from cmion_mesh.presence import Presence, alive_list, did_you_mean
from cmion_mesh.requests import DEFAULT_REQUEST_TIMEOUT, require_accepted, send_request
from cmion_mesh.transport.base import Closeable, Sample, Transport

Entry = Property | Container
_decode_entry: Callable[[bytes, str], Entry] = decoder(Entry)
_decode_entries: Callable[[list[bytes]], list[Entry]] = many_decoder(Entry)
#: How long a request whose embodiment is alive is sent again while it reaches nobody (its
#: queryable not yet known to a session that has just joined).
REACH_RETRY = 0.5
STORE_LABELS = {keys.BLACKBOARD: "blackboard", keys.WORLD_MODEL: "world model"}
#: Most embodiments described at once.
MAX_PARALLEL_DESCRIBE = 16
#: Most embodiments whose action ends a client follows at once (``watch_actions``); beyond it,
#: the least recently used watch with no action in flight is closed.
MAX_ACTION_WATCHES = 64


def _one_embodiment(first: str, last: str) -> bool:
    """Whether every key from ``first`` to ``last`` (sorted) is one embodiment's: the two share
    ``cmion/<mesh>/<embodiment>/``, and so does every key that sorts between them."""
    head = first.split("/", 3)
    return len(head) == 4 and last.startswith(f"{head[0]}/{head[1]}/{head[2]}/")


class MeshClient:
    """Reads, writes, requests and follows a mesh through ``transport``. A context manager:
    ``close`` (idempotent) stops the liveliness watch it starts on first use; not the transport."""

    def __init__(self, transport: Transport, mesh: str = keys.DEFAULT_MESH) -> None:
        self.transport = transport
        self.mesh = keys.check_name(mesh, "mesh")
        self._presence: Presence | None = None
        self._lock = threading.Lock()
        self._watches: dict[str, ActionWatch] = {}  # by embodiment, least recently used first
        self._id: str | None = None

    def __enter__(self) -> MeshClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        with self._lock:
            presence, self._presence = self._presence, None
            watches, self._watches = list(self._watches.values()), {}
        for watch in watches:
            watch.close()
        if presence is not None:
            presence.close()

    @property
    def presence(self) -> Presence:
        """The embodiments alive, as this session sees them (watched from the first use on)."""
        with self._lock:
            if self._presence is None:
                self._presence = Presence(self.transport, self.mesh)
            return self._presence

    # --- joining ------------------------------------------------------------------------------

    def join(self, embodiment: str, *, timeout: float = 5.0) -> None:
        """Return once ``embodiment`` is alive as seen from here; ``NotAlive`` naming the ones that are
        alive otherwise, at once when the daemons that are alive say they do not see it either."""
        keys.check_name(embodiment, "embodiment")
        deadline = time.monotonic() + timeout
        presence = self.presence
        if not presence.wait(lambda alive: bool(alive), timeout):
            raise NotAlive(f"embodiment {embodiment!r} is not alive in mesh {self.mesh!r}: no embodiment at all found "
                           f"within {timeout:g} s (try `cmion-mesh doctor`)")
        if embodiment in presence.alive():
            return
        # Others are alive, not this one (yet?). The daemons have seen the mesh longer: ask them.
        reported = self.reported_alive(presence.alive(), deadline)
        if embodiment in reported | presence.alive() and \
                presence.wait(lambda alive: embodiment in alive, deadline - time.monotonic()):
            return
        known = presence.alive() | reported
        if embodiment in known:
            raise NotAlive(f"embodiment {embodiment!r} is alive in mesh {self.mesh!r} (so say the others) but not "
                           f"reachable from this session within {timeout:g} s (try `cmion-mesh doctor`)")
        raise NotAlive(f"embodiment {embodiment!r} is not alive in mesh {self.mesh!r} (alive: {alive_list(known)})"
                       + did_you_mean(embodiment, known))

    def wait_for_embodiment(self, embodiment: str, *, timeout: float = 5.0) -> None:
        """Return once ``embodiment`` is alive as seen from here, however long it takes to start
        (``join`` instead says at once that it is not alive); ``NotAlive`` after ``timeout``."""
        if not self.presence.wait(lambda alive: embodiment in alive, timeout):
            raise self.not_alive(embodiment, timeout)

    def not_alive(self, embodiment: str, timeout: float) -> NotAlive:
        """The error for ``embodiment`` not alive after ``timeout`` s: it names those alive, and a
        close name when there is one."""
        alive = self.presence.alive()
        return NotAlive(f"embodiment {embodiment!r} not alive in mesh {self.mesh!r} within {timeout:g} s "
                        f"(alive: {alive_list(alive)}){did_you_mean(embodiment, alive)}")

    def reported_alive(self, asked: Iterable[str], deadline: float) -> set[str]:
        """The embodiments that the daemons ``asked`` see alive (those that answer before ``deadline``)."""
        names = sorted(asked)
        out: set[str] = set()
        with ThreadPoolExecutor(max_workers=max(1, min(MAX_PARALLEL_DESCRIBE, len(names)))) as pool:
            for future in [pool.submit(self._describe_replies, name, deadline) for name in names]:
                try:
                    for description in future.result():
                        out.update(str(n) for n in description.get("alive") or ())
                except MeshError:
                    continue
        return out

    # --- storage ------------------------------------------------------------------------------

    def read(self, selector: str, *, timeout: float = 5.0) -> dict[str, Entry]:
        """All properties and containers under a zenoh selector, by key (in key order)."""
        # No tuple per entry on the way: at 100k properties, making and collecting them cost more
        # than decoding (get_values keeps the later of two answers for one key).
        values = self.transport.get_values(selector, timeout=timeout)
        ordered = sorted(values)
        if len(ordered) > 1 and _one_embodiment(ordered[0], ordered[-1]):
            try:  # one embodiment's answers: decoded in one call (see many_decoder)
                return dict(zip(ordered, _decode_entries([values[key] for key in ordered]), strict=True))
            except ProtocolError:
                pass  # one of them is not an entry: each on its own, to leave out only that one
        found: dict[str, Entry] = {}
        for key in ordered:
            try:
                found[key] = _decode_entry(values[key], key)
            except ProtocolError:
                continue  # not a storage entry (another program answering the same keys)
        return found

    def read_store(self, embodiment: str, store: str, path: str = "", *, timeout: float = 5.0) -> dict[str, Entry]:
        base = keys.storage_key(self.mesh, embodiment, store, keys.split_path(path))
        return self.read(f"{base}/**", timeout=timeout)

    def lookup(self, embodiment: str, store: str, path: str = "", *, below: bool = False, timeout: float = 5.0) -> dict[str, Entry]:
        """The property or container at ``path`` in ``embodiment``'s ``store``, by key; with ``below``
        (or no ``path``), everything under it too. In the world model ``entity.property`` (the form
        ``$WM(...)`` uses) names ``entity/property``, as in every write (``keys.store_path``).

        Raises ``StorageError`` naming the path when the store answers but holds no such thing, and
        ``OutcomeUnknown`` when the store does not answer within ``timeout``.
        """
        label = STORE_LABELS.get(store, f"{store!r} store")
        chunks = keys.store_path(store, path)
        root = keys.storage_key(self.mesh, embodiment, store, ())
        base = keys.storage_key(self.mesh, embodiment, store, chunks)
        deadline = time.monotonic() + timeout
        delay = 0.01
        def find() -> dict[str, Entry]:
            return self.read(f"{base}/**" if below or not chunks else base, timeout=max(0.01, deadline - time.monotonic()))

        while True:
            entries = find()
            if entries:
                return entries
            if self.read(root, timeout=max(0.01, deadline - time.monotonic())):
                entries = find()  # the store is reachable now: ask again before saying it is not there
                if entries:
                    return entries
                siblings = self.read(f"{keys.storage_key(self.mesh, embodiment, store, chunks[:-1])}/*", timeout=2.0)
                raise StorageError(f"no property or container {path!r} in {embodiment}'s {label}"
                                   + did_you_mean(chunks[-1], (k.rsplit("/", 1)[-1] for k in siblings)))
            if time.monotonic() + delay >= deadline:
                raise OutcomeUnknown(f"{embodiment}'s {label} did not answer within {timeout:g} s", key=root)
            self.presence.wait(lambda alive: embodiment not in alive, delay)  # not routed here yet: again, soon
            delay = min(delay * 2, 0.2)

    def get_property(self, embodiment: str, store: str, container: str, name: str, *, timeout: float = 5.0) -> Property:
        key = keys.storage_key(self.mesh, embodiment, store, keys.split_path(container), name)
        for reply in self.transport.get(key, timeout=timeout):
            if reply.ok and reply.key == key:
                entry = decode(reply.payload, Entry, where=key)
                if isinstance(entry, Property):
                    return entry
        raise StorageError(f"no property at {key} (or no store answered)")

    def write(self, embodiment: str, store: str, write: StorageWrite, *, timeout: float = DEFAULT_REQUEST_TIMEOUT) -> Outcome:
        """Send one storage write; returns its outcome (accepted, rejected, conflict)."""
        key = keys.request_key(self.mesh, embodiment, store, tag(type(write)))
        return self._send(embodiment, key, write, timeout=timeout)

    def set_property(
        self, embodiment: str, store: str, container: str, name: str, value: Any, *, persistent: bool = False,
        create: bool = False,
    ) -> None:
        """Set a property or raise ``RequestRejected`` / ``OutcomeUnknown`` naming the key. ``create``:
        add the containers missing on the way, in the same write (never a world-model entity)."""
        self._write(embodiment, store, SetProperty(container, name, value, persistent, create))

    def remove_property(self, embodiment: str, store: str, path: str) -> None:
        """Remove the property at ``path`` (``keys.store_path``: ``entity.property`` in the world model)."""
        self._write(embodiment, store, RemoveProperty(*keys.property_path(store, path)))

    def add_container(self, embodiment: str, store: str, path: str, *, kind: str = CONTAINER_KIND) -> None:
        """Add the container at ``path`` (its parent must be there); a world-model entity is ``add_entity``'s."""
        self._write(embodiment, store, AddContainer(*keys.property_path(store, path), kind))

    def remove_container(self, embodiment: str, store: str, path: str) -> None:
        """Remove the container at ``path`` and all it holds (an entity, when ``path`` is one name in the world model)."""
        self._write(embodiment, store, RemoveContainer(*keys.property_path(store, path)))

    def add_entity(self, embodiment: str, name: str, properties: dict[str, Any] | None = None, *, kind: str = "agent",
                   persistent: bool = False) -> None:
        """Add the world-model entity ``name`` (``agent`` or ``object``) with ``properties``, in one
        write: minds hear the entity added, then each property set (CMION's AgentSimulator)."""
        self._write(embodiment, keys.WORLD_MODEL, AddEntity(name, kind, dict(properties or {}), persistent))

    def remove_entity(self, embodiment: str, name: str) -> None:
        """Remove the world-model entity ``name``: minds hear it removed."""
        self._write(embodiment, keys.WORLD_MODEL, RemoveContainer("", name))

    def _write(self, embodiment: str, store: str, write: StorageWrite) -> None:
        key = keys.request_key(self.mesh, embodiment, store, tag(type(write)))
        require_accepted(self.write(embodiment, store, write), key)

    def remote_action(self, embodiment: str, name: str, parameters: Sequence[str] = (), subject: str = "",
                      *, timeout: float = DEFAULT_REQUEST_TIMEOUT) -> list[str]:
        """Tell ``embodiment`` that another agent (``subject``) did ``name parameters``: its minds
        perceive it as a remote action (CMION's RemoteActionSimulator). Returns the minds of the
        daemon's own process that were awake to perceive it; ``RequestRejected`` (code ``invalid``)
        for an action minds cannot be told (``mind.remote_action_problem``)."""
        key = keys.request_key(self.mesh, embodiment, "embodiment", "remote_action")
        answer = require_accepted(self.request(embodiment, "embodiment", "remote_action",
                                               RemoteAction(name, list(parameters), subject), timeout=timeout), key)
        minds = answer.get("minds") if isinstance(answer, dict) else None
        return [str(m) for m in minds] if isinstance(minds, list) else []

    # --- requests and events ------------------------------------------------------------------

    def request(
        self, embodiment: str, component: str, name: str, payload: Message,
        *, timeout: float = DEFAULT_REQUEST_TIMEOUT, sender: str | None = None,
    ) -> Outcome:
        key = keys.request_key(self.mesh, embodiment, component, name, sender)
        return self._send(embodiment, key, payload, timeout=timeout)

    def _send(self, embodiment: str, key: str, payload: Message, *, timeout: float) -> Outcome:
        """``send_request``, sent again for a moment while it reaches nobody although ``embodiment`` is
        alive (a session that has just joined may know the token before the queryable): safe, since
        a request that reached nobody was not delivered."""
        deadline = time.monotonic() + timeout
        retry_until = time.monotonic() + min(REACH_RETRY, timeout)
        delay = 0.01
        while True:
            try:
                return send_request(self.transport, key, payload, timeout=max(0.01, deadline - time.monotonic()))
            except NotReached:
                presence = self._presence
                if presence is None or embodiment not in presence.alive() or time.monotonic() + delay > retry_until:
                    raise
                presence.wait(lambda alive: embodiment not in alive, delay)
                delay *= 2

    def start_action(
        self, embodiment: str, name: str, parameters: Sequence[str] = (), *, subject: str = "", action_id: str = "",
        deadline: float = 0.0, join_timeout: float = 5.0, on_end: Callable[[], None] | None = None,
    ) -> ActionRun:
        """Join, send a mind action and follow it: an ``ActionRun`` (close it when done with it).

        Raises ``NotAlive`` if the embodiment is not alive, ``RequestRejected`` if the manager refuses
        the action (no rule, duplicate id). ``on_end`` runs (on a transport worker) when the action
        ends or the embodiment vanishes.
        """
        self.join(embodiment, timeout=join_timeout)
        if self._id is None:
            self._id = self.transport.id[:8]
        action_id = action_id or f"{self._id}-{uuid.uuid4().hex[:12]}"
        run = ActionRun(self, embodiment, action_id, on_end)
        try:
            key = keys.request_key(self.mesh, embodiment, "manager", "act")
            outcome = self._send(embodiment, key, Act(name, list(parameters), subject, action_id, deadline),
                                 timeout=DEFAULT_REQUEST_TIMEOUT)
            require_accepted(outcome, key)
        except BaseException:
            run.close()
            raise
        return run

    def watch_actions(self, embodiment: str) -> ActionWatch:
        """Follow ``embodiment``'s action ends from now on, for every action this client sends it: one
        subscription instead of one per action (``act`` and ``start_action`` open it on first use).
        It stays open until ``close()`` on it or on the client; of more than ``MAX_ACTION_WATCHES``
        embodiments, the least recently used watch with no action in flight is closed."""
        return self._follow(embodiment, None)

    def _follow(self, embodiment: str, run: ActionRun | None) -> ActionWatch:
        """``watch_actions(embodiment)``, handing it ``run`` in the same step (so that it is never
        closed as idle between the two)."""
        keys.check_name(embodiment, "embodiment")
        evicted: list[ActionWatch] = []
        with self._lock:
            watch = self._watches.pop(embodiment, None)
            if watch is None or watch.closed:
                watch = ActionWatch(self, embodiment)
            if run is not None:
                watch._add(run)
            self._watches[embodiment] = watch  # most recently used last
            for name, other in list(self._watches.items()):
                if len(self._watches) <= MAX_ACTION_WATCHES:
                    break
                if not other.busy:
                    evicted.append(self._watches.pop(name))
        for old in evicted:
            old.close()
        return watch

    def _forget(self, watch: ActionWatch) -> None:
        with self._lock:
            if self._watches.get(watch.embodiment) is watch:
                del self._watches[watch.embodiment]

    def act(
        self, embodiment: str, name: str, parameters: Sequence[str] = (), *, subject: str = "", action_id: str = "",
        timeout: float = 60.0, deadline: float = 0.0,
    ) -> ActionReport:
        """Send a mind action and wait for its end; returns the final report (succeeded/failed/cancelled).

        Raises ``NotAlive`` if the embodiment is not alive, ``RequestRejected`` if the manager refuses
        it (no rule, duplicate id), ``Vanished`` if the embodiment leaves the mesh before the end and
        ``OutcomeUnknown`` if the end is not heard within ``timeout``. The ends are followed by the
        embodiment's ``watch_actions``, kept from the first action on.
        """
        with self.start_action(embodiment, name, parameters, subject=subject, action_id=action_id, deadline=deadline) as run:
            return run.wait(timeout)

    def cancel(self, embodiment: str, action_id: str) -> Outcome:
        return self.request(embodiment, "manager", "cancel", CancelAction(action_id))

    def find_companion(self, companion: str, *, timeout: float = 2.0) -> str:
        """The embodiment inhabited by ``companion`` (``companions.find_companion``)."""
        return companions.find_companion(self, companion, timeout=timeout)

    def migrate(self, companion: str, target: str, *, timeout: float = 60.0, join_timeout: float = 5.0) -> dict[str, Any]:
        """Move ``companion`` to ``target`` once the target committed (``companions.migrate``)."""
        return companions.migrate(self, companion, target, timeout=timeout, join_timeout=join_timeout)

    def invite(self, inviter: str, to: Sequence[str] = (), *, timeout: float = 30.0, join_timeout: float = 5.0) -> dict[str, Any]:
        """Have the empty embodiment ``inviter`` invite the companion (``companions.invite``)."""
        return companions.invite(self, inviter, to, timeout=timeout, join_timeout=join_timeout)

    def set_policy(self, companion: str, accepts: Sequence[str] | None) -> None:
        """Say which embodiments ``companion`` accepts (None: any); it travels with the companion."""
        companions.set_policy(self, companion, accepts)

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

    # --- discovery ----------------------------------------------------------------------------

    def describe(self, embodiment: str, *, timeout: float = 2.0) -> dict[str, Any]:
        """An embodiment's description (name, competency types, actions, inhabitant, version, started at...)."""
        outcome = self.request(embodiment, "embodiment", "describe", Describe(), timeout=timeout)
        value = require_accepted(outcome, keys.request_key(self.mesh, embodiment, "embodiment", "describe"))
        return value if isinstance(value, dict) else {"name": embodiment}

    def _describe_replies(self, embodiment: str, deadline: float) -> list[dict[str, Any]]:
        """Every description answering for ``embodiment``: two when two daemons share its name (when
        one says it sees a twin, the twin's answer is waited for too, within ``deadline``)."""
        key = keys.request_key(self.mesh, embodiment, "embodiment", "describe")
        payload = encode(Describe())
        found: dict[str, dict[str, Any]] = {}  # by zenoh id
        delay = 0.01
        while True:
            left = deadline - time.monotonic()
            replies = self.transport.get(key, payload, timeout=max(0.01, left))
            for reply in replies:
                try:
                    outcome = decode(reply.payload, Outcome, where=key) if reply.ok else None
                except ProtocolError:
                    continue
                if outcome is not None and outcome.status == "accepted" and isinstance(outcome.value, dict):
                    found[str(outcome.value.get("zenoh_id", len(found)))] = outcome.value
            expected = 1 + max((len(d.get("duplicates") or ()) for d in found.values()), default=0)
            late = deadline - time.monotonic() < delay
            if found and (len(found) >= expected or late):
                return list(found.values())
            if not found and (replies or late):
                raise OutcomeUnknown(f"{embodiment} did not describe itself within {max(0.0, left):.1f} s", key=key)
            self.presence.wait(lambda alive: embodiment not in alive, delay)  # not routed yet: again, soon
            if embodiment not in self.presence.alive():
                raise Vanished(f"{embodiment} left the mesh", key=key)
            delay = min(delay * 2, 0.2)

    def describe_all(self, *, timeout: float = 2.0) -> list[dict[str, Any]]:
        """Every live embodiment, described, once this session has joined the mesh: it waits (within
        ``timeout``) until it has described every embodiment that any live daemon sees. One that
        does not answer is listed with an ``error``; two daemons answering for one name both appear."""
        deadline = time.monotonic() + timeout
        presence = self.presence
        if not presence.wait(lambda alive: bool(alive), timeout):
            return []
        changed = threading.Condition()
        described: dict[str, list[dict[str, Any]]] = {}
        failed: dict[str, str] = {}
        pending: dict[str, Future[list[dict[str, Any]]]] = {}

        def wake(*_: object) -> None:
            with changed:
                changed.notify_all()

        with presence.listen(wake), ThreadPoolExecutor(max_workers=MAX_PARALLEL_DESCRIBE) as pool:
            for _ in range(10_000):  # bounded; each round waits for a change or the deadline
                alive = presence.alive()
                for name, future in list(pending.items()):
                    if future.done():
                        del pending[name]
                        try:
                            described[name] = future.result()
                        except MeshError as exc:
                            failed[name] = str(exc)
                for name in sorted(alive - described.keys() - failed.keys() - pending.keys()):
                    pending[name] = pool.submit(self._describe_replies, name, deadline)
                    pending[name].add_done_callback(wake)
                reported = {str(n) for found in described.values() for d in found for n in d.get("alive") or ()}
                missing = (alive | reported) - described.keys() - failed.keys()
                left = deadline - time.monotonic()
                if (not missing and not pending) or left <= 0:
                    break
                with changed:
                    if not any(f.done() for f in pending.values()) and presence.alive() == alive:
                        changed.wait(min(left, 0.5))
            for future in pending.values():
                future.cancel()
        alive = presence.alive()
        out: list[dict[str, Any]] = []
        for name in sorted(described.keys() | failed.keys() | missing):
            if name in described:
                out.extend(described[name])
            elif name in failed:
                if name in alive:
                    out.append({"name": name, "error": failed[name]})
            else:
                out.append({"name": name, "error": "alive (so say the other daemons) but not reachable from this session"})
        return out

    def custody(self, companion: str, *, timeout: float = 2.0, join_timeout: float | None = None) -> dict[str, dict[str, Any]]:
        """What every live embodiment says of ``companion``'s custody (``companions.custody``)."""
        return companions.custody(self, companion, timeout=timeout, join_timeout=join_timeout)

    def resolve_fork(self, companion: str, keep: str, *, force: bool = False, gone: Sequence[str] = (),
                     sender: str = "cmion-mesh", timeout: float = 10.0, join_timeout: float = 5.0) -> dict[str, Any]:
        """Resolve a fork of ``companion``'s custody by keeping ``keep``'s branch (``companions.resolve_fork``)."""
        return companions.resolve_fork(self, companion, keep, force=force, gone=gone, sender=sender, timeout=timeout,
                                       join_timeout=join_timeout)

    def embodiments(self, *, timeout: float = 2.0) -> list[str]:
        """Names of the embodiments whose liveliness token is present (one liveliness query)."""
        names = []
        for key in self.transport.alive(f"{keys.mesh_prefix(self.mesh)}/{keys.ALIVE}/*", timeout=timeout):
            names.append(key.rsplit("/", 1)[-1])
        return sorted(set(names))


def mesh_problems(described: Sequence[dict[str, Any]]) -> list[str]:
    """What is wrong in a mesh, from its embodiments' descriptions: two daemons with one name, a
    companion two embodiments claim, duplicates a daemon reports itself."""
    problems = []
    names: dict[str, int] = {}
    hosts: dict[str, list[str]] = {}
    for d in described:
        names[str(d.get("name"))] = names.get(str(d.get("name")), 0) + 1
        if d.get("inhabitant"):
            hosts.setdefault(str(d["inhabitant"]), []).append(str(d.get("name")))
        for twin in d.get("duplicates") or ():
            problems.append(f"DUPLICATE EMBODIMENT: {d.get('name')} (zenoh id {d.get('zenoh_id')}) sees another daemon named "
                            f"{d.get('name')!r} (zenoh id {twin}) in the mesh")
    for name, count in sorted(names.items()):
        if count > 1:
            where = ", ".join(f"{d.get('host', '?')} pid {d.get('pid', '?')}" for d in described if d.get("name") == name)
            problems.append(f"DUPLICATE EMBODIMENT: {count} daemons answer as {name!r} ({where})")
    for companion, embodiments in sorted(hosts.items()):
        if len(embodiments) > 1:
            problems.append(f"DUPLICATE COMPANION: {companion!r} is hosted by {' and '.join(sorted(embodiments))}")
    frozen: dict[str, list[str]] = {}
    for d in described:
        for companion, report in (d.get("custody") or {}).items():
            if isinstance(report, dict) and report.get("frozen"):
                frozen.setdefault(str(companion), []).append(f"{d.get('name')} (epoch {report.get('epoch')})")
    for companion, holders in sorted(frozen.items()):
        problems.append(f"CUSTODY FORK: {companion!r} is frozen on {', '.join(sorted(holders))}: see "
                        f"`cmion-mesh custody show {companion}`")
    return list(dict.fromkeys(problems))


# did_you_mean and alive_list are presence.py's; offered here too, where the commands have always found them.
__all__ = ["Entry", "MeshClient", "OutcomeUnknown", "alive_list", "did_you_mean", "mesh_problems"]
