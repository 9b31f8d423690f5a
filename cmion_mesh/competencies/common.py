"""What the competencies share: the companion's name on a body, reading run and constructor
parameters, and writing to the embodiment's stores.

The simulated competencies (``competencies/spirit.py``), the web ones (``web/competencies.py``) and
the ROS 2 ones (``ros2/competencies.py``) read their parameters and write their effects the same
way, through these. Every write goes through the run's ``RunContext``, so they work both in the
embodiment and in a competency hosted remotely.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from cmion_mesh import keys
from cmion_mesh.competency import RunContext
from cmion_mesh.errors import ConfigError, MeshError, RequestRejected
from cmion_mesh.messages import CONTAINER_KIND, AddContainer, Code, RemoveProperty, SetProperty
from cmion_mesh.storage import Store

log = logging.getLogger(__name__)

#: The WM agent that stands for the companion on this body (CMION/FAtiMA call it SELF).
SELF = "Self"
#: The BB container through which tests and the demo simulate the world.
SIM = "sim"
#: Kind given to blackboard containers these competencies create (as ``RunContext.bb_set`` does).
BB_CONTAINER = CONTAINER_KIND

_TRUE = {"true", "yes", "1"}


# --- parsing ------------------------------------------------------------------------------------


def parse_seconds(value: Any, what: str) -> float:
    """A non-negative, finite number of seconds; ``ConfigError`` naming ``what`` otherwise.

    ConfigError is a MeshError, so a bad constructor parameter is reported by the library loader
    with the file and line of the entry.
    """
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{what}: {value!r} is not a number of seconds") from None
    if not math.isfinite(number) or number < 0:
        raise ConfigError(f"{what}: {value!r} must be a finite number of seconds, at least 0")
    return number


def parse_count(value: Any, what: str) -> int:
    """A whole number, at least 0; ``ConfigError`` naming ``what`` otherwise."""
    if isinstance(value, bool):  # bool is an int subclass, but True steps means nothing
        raise ConfigError(f"{what}: {value!r} is not a whole number")
    try:
        number = int(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{what}: {value!r} is not a whole number") from None
    if number < 0:
        raise ConfigError(f"{what}: {value!r} must be at least 0")
    return number


def truthy(value: Any) -> bool:
    # WM init files hold strings unless a property says Type="bool": accept both spellings.
    return value is True or (isinstance(value, str) and value.strip().lower() in _TRUE)


def text_parameter(parameters: dict[str, Any], name: str) -> str:
    """A run parameter as text, stripped; "" when it is missing."""
    value = parameters.get(name)
    return "" if value is None else str(value).strip()


# --- store writes (work both in the embodiment and when hosted remotely: all go through ctx) ----


def local_store(ctx: RunContext, store: str) -> Store | None:
    """The store ``store`` when it runs in this process (None for a competency hosted remotely)."""
    found = ctx.competency.sim.components_by_name().get(store)
    return found if isinstance(found, Store) else None


def ensure_container(ctx: RunContext, store: str, path: str, kind: str) -> None:
    """Create ``path`` (and its parents) if missing; someone else creating it first is fine."""
    local = local_store(ctx, store)
    if local is not None and local.has_container(path):
        return  # the common case costs no request
    parent = ""
    for chunk in keys.split_path(path):
        try:
            ctx.write(store, AddContainer(parent, chunk, kind))
        except RequestRejected as exc:
            # Created before, or by another writer in this same update (a conflict): both fine.
            if exc.code not in (Code.EXISTS, Code.CONFLICT):
                raise
        parent = f"{parent}/{chunk}" if parent else chunk


def set_property(ctx: RunContext, store: str, container: str, name: str, value: Any, *, kind: str, persistent: bool = False) -> None:
    """Set a property, creating its container (of ``kind``) on the first refusal for lack of it."""
    write = SetProperty(container, name, value, persistent)
    try:
        ctx.write(store, write)
    except RequestRejected as exc:
        if not container or exc.code != Code.NOT_FOUND:  # a set refers to nothing but its container
            raise
        ensure_container(ctx, store, container, kind)
        ctx.write(store, write)


def remove_property(ctx: RunContext, store: str, container: str, name: str) -> None:
    """Remove a property if it is there; already gone is fine."""
    try:
        ctx.write(store, RemoveProperty(container, name))
    except RequestRejected as exc:
        if exc.code != Code.NOT_FOUND:
            raise


def bb_set(ctx: RunContext, path: str, value: Any) -> None:
    """Set the blackboard property ``container/name``, creating its container (``RunContext.bb_set``)."""
    ctx.bb_set(path, value)


def bb_remove(ctx: RunContext, path: str) -> None:
    """Remove the blackboard property ``container/name`` if it is there."""
    container, _, name = path.rpartition("/")
    remove_property(ctx, keys.BLACKBOARD, container, name)


def wm_set(ctx: RunContext, entity: str, name: str, value: Any, *, kind: str = "agent", persistent: bool = False) -> None:
    """Set a world-model property, creating its entity (of ``kind``) if it is missing."""
    set_property(ctx, keys.WORLD_MODEL, entity, name, value, kind=kind, persistent=persistent)


def quietly(what: str, fn: Callable[..., object], *args: Any) -> None:
    """Clean-up after a cancel or a failure: it must not replace the run's own outcome."""
    try:
        fn(*args)
    except MeshError as exc:  # e.g. the embodiment is shutting down
        log.debug("%s skipped: %s", what, exc)
