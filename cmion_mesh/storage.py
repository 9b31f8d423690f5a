"""Storage containers: the blackboard and the world model, served as zenoh keys.

A store is a tree of containers; each container holds properties (plain-data values, optionally
*persistent*, i.e. part of what a companion carries when it migrates) and named sub-containers
with a kind (the world model's top-level entities are of kind ``agent`` or ``object``).
Property and sub-container names share one namespace per container.

On the mesh (see ``keys``)::

    cmion/<mesh>/<embodiment>/<store>                       the root container
    cmion/<mesh>/<embodiment>/<store>/<c1>/.../<cN>          a container     -> ``Container``
    cmion/<mesh>/<embodiment>/<store>/<c1>/.../<property>    a property      -> ``Property``

A plain zenoh ``get`` on a key or wildcard answers the current values; a plain subscriber sees
every change (a put of the new ``Property``/``Container``, a delete when removed). Writes are
requests to ``.../rq/<store>/<set_property|remove_property|add_container|remove_container>``;
the world model also takes ``add_entity`` (an entity and its properties in one write), and its
root holds entities only, no properties. A ``set_property`` with ``create`` adds the containers
it needs on the way (kind ``container``; never an entity, which has a kind of its own).

*Persistent* properties survive a restart of their daemon: with a state folder (``keep_persistent``)
a store saves them (with the kinds of the containers holding them) after every write that
changes one, and restores them over the init file at start. The world model's persistent
properties also belong to the companion: they travel with it when it migrates (see
``embodiment``), and overwrite the target's values of the same names; the source keeps its copy.

Mediation policy (CMION's): within one update, the *first* write to a property (or to a
sub-container name) wins; later writes to the same name in that update get ``conflict``.
Writes to a missing container, or that clash with an existing name of the other sort, are
``rejected`` with the reason and a code (``not_found``, ``exists``, ``invalid``: see
``messages.Code``). A write is applied whole or not at all. After each applied write the store
raises an event per change (``PropertyChanged``, ``PropertyRemoved``, ``SubContainerAdded``,
``SubContainerRemoved``) whose data is a ``StorageChange``: the containers a write added come
first, so a mind hears of an entity before its properties, as from a sensor that writes them.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import msgspec

from cmion_mesh import keys, xmlsafe
from cmion_mesh.errors import ConfigError, InvalidName, StorageError
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import (
    CONTAINER_KIND,
    STORAGE_WRITES,
    AddContainer,
    AddEntity,
    Code,
    Container,
    Message,
    Property,
    RemoveContainer,
    RemoveProperty,
    SetProperty,
    StorageChange,
    StorageWrite,
    check_value,
    encode,
    tag,
)
from cmion_mesh.requests import IncomingRequest
from cmion_mesh.statedir import write_atomic
from cmion_mesh.transport.base import IncomingQuery

log = logging.getLogger(__name__)

#: Deepest container path (a store's tree is walked recursively).
MAX_CONTAINER_DEPTH = 32

EVENT_FOR_OP = {
    "set_property": "PropertyChanged",
    "remove_property": "PropertyRemoved",
    "add_container": "SubContainerAdded",
    "remove_container": "SubContainerRemoved",
}


#: One applied change: its op, its event's data, the path it changed, its new wire value (None: removed).
_Change = tuple[str, StorageChange, tuple[str, ...], bytes | None]


class _Prop(msgspec.Struct):
    value: Any
    persistent: bool
    wire: bytes  # encoded ``Property``, kept so that reads never re-encode


class Node(msgspec.Struct):
    """One container of a store."""

    kind: str
    properties: dict[str, _Prop] = msgspec.field(default_factory=dict)
    children: dict[str, Node] = msgspec.field(default_factory=dict)
    wire: bytes = b""

    def __post_init__(self) -> None:
        self.wire = encode(Container(self.kind))


def _path(container: str | Sequence[str]) -> tuple[str, ...]:
    return keys.split_path(container)


def _join(path: Sequence[str]) -> str:
    return "/".join(path)


def _everything(node: Node, key: str, out: list[tuple[str, bytes]]) -> None:
    """``(key, wire)`` of ``node`` (at ``key``) and of every container and property below it."""
    out.append((key, node.wire))
    out.extend((f"{key}/{name}", prop.wire) for name, prop in node.properties.items())
    for name, child in node.children.items():
        _everything(child, f"{key}/{name}", out)


class Store(Component):
    """A tree of containers of properties, mediated per update and served on its key-space."""

    requests: Mapping[str, type[Message]] = {tag(write): write for write in STORAGE_WRITES}
    #: Kinds allowed for the root's sub-containers (None: any).
    root_kinds: frozenset[str] | None = None
    root_kind = "store"
    #: Whether the root holds properties of its own (the world model's holds only entities).
    root_properties = True

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.root = Node(self.root_kind)
        self._lock = threading.RLock()
        self._prefix = ""
        self._reads: Any = None
        self._persist_path: Path | None = None
        self._persist_dirty = False

    # --- life cycle ---------------------------------------------------------------------------

    def attach(self, sim: Simulation) -> None:
        self._prefix = f"{keys.embodiment_prefix(sim.mesh, sim.embodiment)}/{self.name}"
        # Reads are answered on the transport's worker, not the loop: they need only the lock.
        self._reads = sim.transport.declare_queryable(f"{self._prefix}/**", self._answer_read)

    def detach(self) -> None:
        if self._reads is not None:
            self._reads.close()
            self._reads = None

    def _key(self, path: Sequence[str]) -> str:
        return "/".join((self._prefix, *path)) if path else self._prefix

    # --- reading (any thread) -----------------------------------------------------------------

    def node(self, container: str | Sequence[str] = ()) -> Node:
        path = _path(container)
        with self._lock:
            node = self.root
            for i, chunk in enumerate(path):
                child = node.children.get(chunk)
                if child is None:
                    raise StorageError(self._missing(path[: i + 1]))
                node = child
            return node

    def has_container(self, container: str | Sequence[str]) -> bool:
        try:
            self.node(container)
            return True
        except StorageError:
            return False

    def get(self, container: str | Sequence[str], name: str, default: Any = None) -> Any:
        with self._lock:
            try:
                prop = self.node(container).properties.get(name)
            except StorageError:
                return default
            return default if prop is None else prop.value

    def property(self, container: str | Sequence[str], name: str) -> tuple[Any, bool]:
        """``(value, persistent)``; ``StorageError`` naming the property if it is not there."""
        with self._lock:
            prop = self.node(container).properties.get(name)
            if prop is None:
                raise StorageError(f"{self.name}: no property {_join((*_path(container), name))!r}")
            return prop.value, prop.persistent

    def tree(self, container: str | Sequence[str] = ()) -> dict[str, Any]:
        """A plain-data copy: ``{"kind", "properties": {name: {value, persistent}}, "children": {...}}``."""
        with self._lock:
            return _plain(self.node(container))

    def _walk(self, node: Node, path: tuple[str, ...]) -> Iterator[tuple[tuple[str, ...], Node | _Prop]]:
        yield path, node
        for name, prop in node.properties.items():
            yield (*path, name), prop
        for name, child in node.children.items():
            yield from self._walk(child, (*path, name))

    def _answer_read(self, query: IncomingQuery) -> None:
        try:
            pattern = query.key
            rest = pattern[len(self._prefix) :].lstrip("/").split("/") if len(pattern) > len(self._prefix) else []
            # Descend through the literal head of the selector instead of scanning the whole tree.
            node: Node = self.root
            path: tuple[str, ...] = ()
            with self._lock:
                while rest and rest[0] not in ("*", "**") and "$" not in rest[0]:
                    if len(rest) == 1 and rest[0] in node.properties:
                        query.reply(self._key((*path, rest[0])), node.properties[rest[0]].wire)
                    child = node.children.get(rest[0])
                    if child is None:
                        return
                    node, path, rest = child, (*path, rest[0]), rest[1:]
                if not rest:
                    query.reply(self._key(path), node.wire)
                    return
                found: list[tuple[str, bytes]] = []
                if rest == ["**"]:  # everything below: no matching, keys built chunk by chunk
                    _everything(node, self._key(path), found)
                else:
                    found = [
                        (self._key(p), item.wire)
                        for p, item in self._walk(node, path)
                        if keys.matches_chunks(rest, p[len(path) :])
                    ]
            reply = query.reply
            for key, wire in found:
                reply(key, wire)
        finally:
            query.finish()

    # --- persistence --------------------------------------------------------------------------

    def persistent_items(self) -> list[dict[str, Any]]:
        """Every persistent property: ``{"path", "kinds", "name", "value"}`` (``kinds``: of the
        containers on ``path``), plain data for a file or a companion's identity."""
        items: list[dict[str, Any]] = []

        def walk(node: Node, path: tuple[str, ...], kinds: tuple[str, ...]) -> None:
            for name, prop in node.properties.items():
                if prop.persistent:
                    items.append({"path": list(path), "kinds": list(kinds), "name": name, "value": prop.value})
            for name, child in node.children.items():
                walk(child, (*path, name), (*kinds, child.kind))

        with self._lock:
            walk(self.root, (), ())
        return items

    def restore(self, items: Any, *, source: str) -> int:
        """Set the persistent properties ``items`` (as ``persistent_items`` gives them), adding the
        containers they need; an item that does not fit is skipped with a warning naming ``source``.
        Returns how many were set."""
        restored = 0
        saving, self._persist_path = self._persist_path, None  # one save at the end, not one per item
        try:
            restored = self._restore(items, source)
        finally:
            self._persist_path = saving
        self._save_persistent()
        return restored

    def _restore(self, items: Any, source: str) -> int:
        restored = 0
        for item in items if isinstance(items, list) else []:
            try:
                path = keys.split_path([str(p) for p in item["path"]])
                kinds = [str(k) for k in item["kinds"]]
                if len(kinds) != len(path):
                    raise ValueError("path and kinds differ in length")
                for depth, (chunk, kind) in enumerate(zip(path, kinds, strict=True)):
                    if not self.has_container(path[: depth + 1]):
                        self.apply_now(AddContainer(_join(path[:depth]), chunk, kind))
                self.apply_now(SetProperty(_join(path), str(item["name"]), item["value"], True))
                restored += 1
            except (KeyError, TypeError, ValueError, StorageError) as exc:
                log.warning("%s: persistent property %r not restored: %s", source, item, exc)
        return restored

    def keep_persistent(self, path: str | os.PathLike[str]) -> int:
        """Restore the persistent properties saved at ``path`` (if any), and save them there after
        every write that changes one. Returns how many were restored."""
        file = Path(path)
        restored = 0
        if file.exists():
            try:
                items = msgspec.json.decode(file.read_bytes())
            except (OSError, msgspec.DecodeError) as exc:
                raise ConfigError(f"unreadable persistent properties: {exc}", path=str(file)) from None
            restored = self.restore(items, source=str(file))
        self._persist_path = file
        return restored

    def _save_persistent(self) -> None:
        if self._persist_path is None or not self._persist_dirty:
            return
        self._persist_dirty = False
        try:
            write_atomic(self._persist_path, msgspec.json.encode(self.persistent_items()))
        except OSError as exc:
            log.error("%s: persistent properties not saved to %s: %s", self.name, self._persist_path, exc)

    # --- writing (on the loop) ----------------------------------------------------------------

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        written: set[tuple[str, ...]] = set()
        changes: list[_Change] = []
        with self._lock:
            for request in batch:
                try:
                    applied = self._apply(request.payload, written)
                except StorageError as exc:
                    request.reject(str(exc), Code(exc.code))
                except _Conflict as exc:
                    request.conflict(str(exc))
                except (InvalidName, ValueError) as exc:
                    request.reject(f"{self.name}: {exc}", Code.INVALID)
                else:
                    request.accept()
                    changes.extend(applied)
        self._save_persistent()
        self._publish(changes)

    def apply_now(self, write: StorageWrite) -> None:
        """Apply one write outside mediation (loading, restoring); raises ``StorageError``."""
        with self._lock:
            changes = self._apply(write, set())
        self._save_persistent()
        if self._sim is not None and self._prefix:
            self._publish(changes)

    def _publish(self, changes: list[_Change]) -> None:
        if self._sim is None or not self._prefix:
            return
        transport = self._sim.transport
        for op, change, path, wire in changes:
            key = self._key(path)
            if wire is None:
                transport.delete(key)
            else:
                transport.publish(key, wire, block=True)
            self.raise_event(EVENT_FOR_OP[op], msgspec.to_builtins(change))

    def _missing(self, path: Sequence[str]) -> str:
        """Why ``path``, a container that is not there, cannot be written to."""
        return f"{self.name}: no container {_join(path)!r}"

    def _apply(self, write: StorageWrite, written: set[tuple[str, ...]]) -> list[_Change]:
        """Apply ``write`` whole or not at all (``StorageError``, ``_Conflict``, ``ValueError``),
        returning its changes in order: the containers it added, then what it was asked."""
        if isinstance(write, AddEntity):
            return self._add_entity(write, written)
        path = _path(write.container)
        name = keys.check_name(write.name, "property" if isinstance(write, (SetProperty, RemoveProperty)) else "container")
        full = (*path, name)
        where = f"{self.name}/{_join(full)}"
        if full in written:
            raise _Conflict(f"{where}: lost to an earlier write to the same name in this update")
        added: list[_Change] = []
        wire: bytes | None = None
        match write:
            case SetProperty(value=value, persistent=persistent, create=create):
                value = check_value(value)  # before any container is added: all or nothing
                if not path and not self.root_properties:
                    raise StorageError(f"{where}: the {self.root_kind.replace('_', ' ')}'s root holds entities, not properties: "
                                       "name a property as entity.property or entity/property", code=Code.INVALID)
                node = self._containers(path, written, added) if create else self.node(path)
                if name in node.children:
                    raise StorageError(f"{where} is a container, not a property", code=Code.INVALID)
                wire = encode(Property(value, persistent))
                old = node.properties.get(name)
                self._persist_dirty |= persistent or (old is not None and old.persistent)
                node.properties[name] = _Prop(value, persistent, wire)
                change = StorageChange("set_property", _join(path), name, value, persistent)
            case RemoveProperty():
                prop = self.node(path).properties.pop(name, None)
                if prop is None:
                    raise StorageError(f"{where}: no such property", code=Code.NOT_FOUND)
                self._persist_dirty |= prop.persistent
                change = StorageChange("remove_property", _join(path), name, None, prop.persistent)
            case AddContainer(kind=kind):
                node = self.node(path)
                self._check_new_container(node, path, name, kind)
                child = node.children[name] = Node(kind)
                change = StorageChange("add_container", _join(path), name, kind=kind)
                wire = child.wire
            case RemoveContainer():
                node = self.node(path)
                if name not in node.children:
                    raise StorageError(f"{where}: no such container", code=Code.NOT_FOUND)
                child = node.children.pop(name)
                self._persist_dirty = True  # it may have held persistent properties
                change = StorageChange("remove_container", _join(path), name, kind=child.kind)
        written.add(full)
        added.append((change.op, change, full, wire))
        return added

    def _check_new_container(self, node: Node, path: tuple[str, ...], name: str, kind: str) -> None:
        """Refuse a container ``name`` of ``kind`` in ``node`` (at ``path``) that may not be added."""
        where = f"{self.name}/{_join((*path, name))}"
        if len(path) >= MAX_CONTAINER_DEPTH:
            raise StorageError(f"{where}: containers nest at most {MAX_CONTAINER_DEPTH} deep", code=Code.INVALID)
        if name in node.properties or name in node.children:
            raise StorageError(f"{where} already exists", code=Code.EXISTS)
        if not path and self.root_kinds is not None and kind not in self.root_kinds:
            raise StorageError(f"{where}: kind {kind!r} is not one of {sorted(self.root_kinds)}", code=Code.INVALID)
        if not path and self.root_kinds is not None:
            try:
                keys.check_entity(name)
            except InvalidName as exc:
                raise StorageError(f"{self.name}: {exc}", code=Code.INVALID) from None

    def _containers(self, path: tuple[str, ...], written: set[tuple[str, ...]], added: list[_Change]) -> Node:
        """The container at ``path``, the missing ones on the way added (kind ``CONTAINER_KIND``)
        once every one of them is known to be allowed; their changes appended to ``added``."""
        node = self.root
        depth = 0
        while depth < len(path) and path[depth] in node.children:
            node = node.children[path[depth]]
            depth += 1
        if depth == len(path):
            return node
        if depth == 0 and self.root_kinds is not None:  # an entity has a kind: added on its own
            raise StorageError(self._missing(path[:1]), code=Code.NOT_FOUND)
        if path[depth] in node.properties:
            raise StorageError(f"{self.name}/{_join(path[: depth + 1])} is a property, not a container", code=Code.INVALID)
        for end in range(depth + 1, len(path) + 1):
            if path[:end] in written:
                raise _Conflict(f"{self.name}/{_join(path[:end])}: lost to an earlier write to the same name in this update")
        self._check_new_container(node, path[:depth], path[depth], CONTAINER_KIND)
        if len(path) > MAX_CONTAINER_DEPTH:
            raise StorageError(f"{self.name}/{_join(path)}: containers nest at most {MAX_CONTAINER_DEPTH} deep",
                               code=Code.INVALID)
        for end in range(depth + 1, len(path) + 1):
            child = node.children[path[end - 1]] = Node(CONTAINER_KIND)
            change = StorageChange("add_container", _join(path[: end - 1]), path[end - 1], kind=CONTAINER_KIND)
            added.append((change.op, change, path[:end], child.wire))
            written.add(path[:end])
            node = child
        return node

    def _add_entity(self, write: AddEntity, written: set[tuple[str, ...]]) -> list[_Change]:
        name = keys.check_name(write.name, "entity")
        where = f"{self.name}/{name}"
        if (name,) in written:
            raise _Conflict(f"{where}: lost to an earlier write to the same name in this update")
        self._check_new_container(self.root, (), name, write.kind)
        values = {keys.check_name(p, "property"): check_value(v) for p, v in write.properties.items()}
        child = self.root.children[name] = Node(write.kind)
        added = StorageChange("add_container", "", name, kind=write.kind)
        changes: list[_Change] = [(added.op, added, (name,), child.wire)]
        written.add((name,))
        for prop, value in values.items():
            wire = encode(Property(value, write.persistent))
            child.properties[prop] = _Prop(value, write.persistent, wire)
            change = StorageChange("set_property", name, prop, value, write.persistent)
            changes.append((change.op, change, (name, prop), wire))
            written.add((name, prop))
        self._persist_dirty |= write.persistent and bool(values)
        return changes


class _Conflict(Exception):
    pass



def _plain(node: Node) -> dict[str, Any]:
    return {
        "kind": node.kind,
        "properties": {n: {"value": p.value, "persistent": p.persistent} for n, p in node.properties.items()},
        "children": {n: _plain(c) for n, c in node.children.items()},
    }


class Blackboard(Store):
    root_kind = "blackboard"

    def __init__(self, name: str = keys.BLACKBOARD) -> None:
        super().__init__(name)


class WorldModel(Store):
    """The world model: top-level entities are agents or objects, addressed by unique name."""

    requests = {**Store.requests, tag(AddEntity): AddEntity}
    root_kind = "world_model"
    root_kinds = frozenset({"agent", "object"})
    root_properties = False

    def __init__(self, name: str = keys.WORLD_MODEL) -> None:
        super().__init__(name)

    def _missing(self, path: Sequence[str]) -> str:
        if len(path) == 1:
            return f"{self.name}: no entity {path[0]!r}"
        return super()._missing(path)

    def load_init(self, path: str | os.PathLike[str]) -> int:
        """Load a CMION ``WorldModel`` init file; returns the number of entities added."""
        entities = load_world_model_init(path)
        for entity in entities:
            self.apply_now(AddContainer("", entity.name, entity.kind))
            for prop in entity.properties:
                self.apply_now(SetProperty(entity.name, prop.name, prop.value, prop.persistent))
        return len(entities)


class InitProperty(msgspec.Struct, frozen=True):
    name: str
    value: Any
    persistent: bool


class InitEntity(msgspec.Struct, frozen=True):
    name: str
    kind: str
    properties: tuple[InitProperty, ...]


_TRUE = {"true", "yes", "1"}
_FALSE = {"false", "no", "0"}


def _typed(raw: str, kind: str, where: str) -> Any:
    try:
        if kind == "string":
            return raw
        if kind == "int":
            return check_value(int(raw))
        if kind == "float":
            return float(raw)
        if kind == "bool":
            low = raw.strip().lower()
            if low in _TRUE | _FALSE:
                return low in _TRUE
            raise ValueError(f"not a boolean: {raw!r}")
        if kind == "json":
            return check_value(msgspec.json.decode(raw))
    except (ValueError, msgspec.DecodeError, RecursionError) as exc:
        raise ValueError(f"{where}: {exc}") from None
    raise ValueError(f"{where}: unknown Type {kind!r}")


def load_world_model_init(path: str | os.PathLike[str], problems: list[ConfigError] | None = None) -> list[InitEntity]:
    """Parse a CMION world-model init file (validated by ``schemas/WorldModel.xsd``).

    Values are strings, as in CMION, unless a property says ``Type="int|float|bool|json"``.
    Names and values are trimmed of surrounding white space, as CMION's loader trimmed them.
    With ``problems``, an entity at fault is left out and its error appended there (``validate``
    reports every one in a run).
    """
    tree = xmlsafe.load(path, "WorldModel.xsd")
    entities: list[InitEntity] = []
    seen: dict[str, int] = {}
    for element in tree.getroot():
        if not isinstance(element.tag, str):
            continue
        try:
            entity = _init_entity(element, str(path), seen)
        except ConfigError as exc:
            if problems is None:
                raise
            problems.append(exc)
            continue
        entities.append(entity)
    return entities


def _init_entity(element: Any, path: str, seen: dict[str, int]) -> InitEntity:
    name = element.get("Name", "").strip()
    line = xmlsafe.sourceline(element)
    try:
        keys.check_entity(name)
    except InvalidName as exc:
        raise ConfigError(str(exc), path=path, line=line) from None
    if name in seen:
        raise ConfigError(f"entity {name!r} already defined at line {seen[name]}", path=path, line=line)
    seen[name] = line or 0
    props = []
    names: set[str] = set()
    for p in element:
        if not isinstance(p.tag, str):
            continue
        pname = p.get("Name", "").strip()
        try:
            keys.check_name(pname, "property name")
            if pname in names:
                raise ValueError(f"property {pname!r} of {name!r} defined twice")
            value = _typed(p.get("Value", "").strip(), p.get("Type", "string"), f"property {pname!r}")
        except ValueError as exc:
            raise ConfigError(str(exc), path=path, line=xmlsafe.sourceline(p)) from None
        names.add(pname)
        persistent = p.get("Persistent", "false").strip().lower() in _TRUE
        props.append(InitProperty(pname, value, persistent))
    return InitEntity(name, str(element.tag).lower(), tuple(props))
