"""The key-space: one grammar for every key cmion-mesh reads, writes, publishes or queries.

::

    cmion/<mesh>/<embodiment>/bb/<container>/.../<property>   blackboard property or container
    cmion/<mesh>/<embodiment>/wm/<entity>/.../<property>      world-model property or entity
    cmion/<mesh>/<embodiment>/ev/<component>/<event>          event publications
    cmion/<mesh>/<embodiment>/rq/<component>/<request>        request queryables
    cmion/<mesh>/<embodiment>/rq/<component>/<request>/<sender>   per-sender requests (migration handshake)
    cmion/<mesh>/<embodiment>/@outcome/<component>/<request>  requests answered (only while someone listens)
    cmion/<mesh>/@alive/<embodiment>                          liveliness tokens
    cmion/<mesh>/@claim/<embodiment>/<rank>                   a daemon's claim on its name (liveliness)
    cmion/<mesh>/@competency/<embodiment>/<type>/<name>       remote competencies (liveliness)
    cmion/<mesh>/@custody/<embodiment>/<companion>/<epoch>    custody: who holds which companion (liveliness)

``<mesh>`` names one deployment (default ``default``): two meshes never hear each other.
Every name is one key chunk; a name containing ``/ * $ # ?``, a leading ``@``, white space at its
ends, or nothing at all is refused with ``InvalidName`` naming it.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Sequence

import msgspec

from cmion_mesh.errors import InvalidName

ROOT = "cmion"
DEFAULT_MESH = "default"
BLACKBOARD = "bb"
WORLD_MODEL = "wm"
EVENTS = "ev"
REQUESTS = "rq"
ALIVE = "@alive"
COMPETENCY = "@competency"
CUSTODY = "@custody"
CLAIM = "@claim"
#: Answers to requests, published while some session subscribes to them (a recorder). ``@``: a
#: verbatim chunk, which ``*`` and ``**`` never match: only a subscriber naming it gets them.
OUTCOMES = "@outcome"

_FORBIDDEN = set("/*$#?")
MAX_NAME = 200
#: Exactly the names ``check_name`` accepts: 1..MAX_NAME characters, none of ``/ * $ # ?`` nor a
#: control character, no leading ``@``, no white space at either end (``\s`` is ``str.isspace``,
#: the test ``str.strip`` uses). Names are checked on every key built, so the valid case is one
#: ``fullmatch``; the detailed checks below run only to word the error.
_VALID_NAME = re.compile(rf"(?!@)(?!\s)[^/*$#?\x00-\x1f]{{1,{MAX_NAME}}}(?<!\s)")


def check_name(name: str, what: str = "name") -> str:
    """Return ``name`` if it can be one key chunk, else raise ``InvalidName`` naming it."""
    if isinstance(name, str) and _VALID_NAME.fullmatch(name) is not None:
        return name
    return _refuse(name, what)


def check_entity(name: str) -> str:
    """``check_name`` for a world-model entity, which also holds no ``.``: a dotted path means
    entity.property in every read and write, so an entity named with a dot could be added but
    never read nor removed (``InvalidName`` saying what to use)."""
    check_name(name, "entity")
    if "." in name:
        raise InvalidName(f"entity {name!r} holds '.', which world-model paths read as entity.property: "
                          f"name it without a dot (e.g. {name.replace('.', '_')!r})")
    return name


def is_name(name: str) -> bool:
    """Whether ``check_name`` accepts ``name`` (for input that is skipped, not refused, when invalid)."""
    return isinstance(name, str) and _VALID_NAME.fullmatch(name) is not None


def _refuse(name: str, what: str) -> str:
    """The slow path of ``check_name``: raise ``InvalidName`` saying what is wrong with ``name``."""
    if not isinstance(name, str):
        raise InvalidName(f"{what} must be a string, got {type(name).__name__}: {name!r}")
    if name == "":
        raise InvalidName(f"{what} is empty")
    bad = sorted(set(name) & _FORBIDDEN)
    if bad:
        raise InvalidName(f"{what} {name!r} contains {' '.join(repr(c) for c in bad)}, which a zenoh key chunk cannot carry")
    if name.startswith("@"):
        raise InvalidName(f"{what} {name!r} starts with '@', which zenoh reserves")
    if name != name.strip() or any(ord(c) < 32 for c in name):
        raise InvalidName(f"{what} {name!r} has surrounding white space or control characters")
    if len(name) > MAX_NAME:
        raise InvalidName(f"{what} {name[:40]!r}... is longer than {MAX_NAME} characters")
    return name


def split_path(path: str | Sequence[str], what: str = "container path") -> tuple[str, ...]:
    """A container path, given as ``"a/b"`` or ``["a", "b"]``, checked chunk by chunk. ``""`` is the root."""
    parts: Sequence[str] = ([] if path == "" else path.split("/")) if isinstance(path, str) else path
    return tuple(check_name(p, f"{what} element") for p in parts)


def store_path(store: str, path: str) -> tuple[str, ...]:
    """The chunks of ``path`` in ``store`` (see the module's doc): ``a/b/c``; in the world model
    ``entity.property`` too, split at the first dot. ``""`` is the root."""
    if store == WORLD_MODEL and "/" not in path and "." in path:
        entity, _, prop = path.partition(".")
        if not entity or not prop:
            raise InvalidName(f"world-model path {path!r}: entity.property names an entity and a property "
                              "(a name holding a dot is written with slashes: entity/property)")
        return check_name(entity, "entity"), check_name(prop, "property")
    return split_path(path, "path")


def property_path(store: str, path: str) -> tuple[str, str]:
    """``(container, name)`` of the property at ``path`` in ``store`` (``store_path``), the
    container as a ``/`` path ("" for the root)."""
    chunks = store_path(store, path)
    if not chunks:
        raise InvalidName("a property path is empty")
    return "/".join(chunks[:-1]), chunks[-1]


def mesh_prefix(mesh: str) -> str:
    return f"{ROOT}/{check_name(mesh, 'mesh')}"


def embodiment_prefix(mesh: str, embodiment: str) -> str:
    return f"{mesh_prefix(mesh)}/{check_name(embodiment, 'embodiment')}"


def storage_key(mesh: str, embodiment: str, store: str, path: Sequence[str], name: str | None = None) -> str:
    """Key of a container (``name`` None) or of a property inside it."""
    chunks = [embodiment_prefix(mesh, embodiment), check_name(store, "store"), *split_path(path)]
    if name is not None:
        chunks.append(check_name(name, "property"))
    return "/".join(chunks)


def event_key(mesh: str, embodiment: str, component: str, event: str) -> str:
    return f"{embodiment_prefix(mesh, embodiment)}/{EVENTS}/{check_name(component, 'component')}/{check_name(event, 'event')}"


@functools.lru_cache(maxsize=4096)  # a client sends the same requests again and again: checked once
def request_key(mesh: str, embodiment: str, component: str, request: str, sender: str | None = None) -> str:
    """Key of a request; with ``sender``, the per-sender form ``.../rq/<component>/<request>/<sender>``
    that access control can restrict to the sender's own certificate."""
    key = f"{embodiment_prefix(mesh, embodiment)}/{REQUESTS}/{check_name(component, 'component')}/{check_name(request, 'request')}"
    return key if sender is None else f"{key}/{check_name(sender, 'sender')}"


def outcome_key(mesh: str, embodiment: str, component: str, request: str) -> str:
    """Key on which ``embodiment`` tells how it answered ``component``'s ``request`` (``RequestAnswered``)."""
    return f"{embodiment_prefix(mesh, embodiment)}/{OUTCOMES}/{check_name(component, 'component')}/{check_name(request, 'request')}"


def outcome_pattern(mesh: str, embodiment: str = "*") -> str:
    return f"{mesh_prefix(mesh)}/{pattern_chunk(embodiment, 'embodiment')}/{OUTCOMES}/**"


def alive_key(mesh: str, embodiment: str) -> str:
    return f"{mesh_prefix(mesh)}/{ALIVE}/{check_name(embodiment, 'embodiment')}"


def custody_key(mesh: str, embodiment: str, companion: str, epoch: int) -> str:
    """Liveliness token by which ``embodiment`` says it holds ``companion`` at ``epoch``."""
    return f"{mesh_prefix(mesh)}/{CUSTODY}/{check_name(embodiment, 'embodiment')}/{check_name(companion, 'companion')}/{int(epoch)}"


def custody_pattern(mesh: str) -> str:
    return f"{mesh_prefix(mesh)}/{CUSTODY}/*/*/*"


def claim_key(mesh: str, embodiment: str, rank: str) -> str:
    """Liveliness token of a daemon's claim on the name ``embodiment``; ``rank`` orders claims (earliest first)."""
    return f"{mesh_prefix(mesh)}/{CLAIM}/{check_name(embodiment, 'embodiment')}/{check_name(rank, 'claim rank')}"


def claim_pattern(mesh: str, embodiment: str) -> str:
    return f"{mesh_prefix(mesh)}/{CLAIM}/{check_name(embodiment, 'embodiment')}/*"


def competency_alive_key(mesh: str, embodiment: str, competency_type: str, name: str) -> str:
    """Liveliness token of a remote competency serving ``embodiment``."""
    return "/".join((mesh_prefix(mesh), COMPETENCY, check_name(embodiment, "embodiment"),
                     check_name(competency_type, "competency type"), check_name(name, "competency name")))


def competency_alive_pattern(mesh: str, embodiment: str) -> str:
    return f"{mesh_prefix(mesh)}/{COMPETENCY}/{check_name(embodiment, 'embodiment')}/*/*"


def pattern_chunk(value: str, what: str) -> str:
    """A chunk of a subscription pattern: ``*`` (any one chunk) or a valid name."""
    return value if value == "*" else check_name(value, what)


def event_pattern(mesh: str, embodiment: str = "*", component: str = "*", event: str = "*") -> str:
    return "/".join(
        [mesh_prefix(mesh), pattern_chunk(embodiment, "embodiment"), EVENTS,
         pattern_chunk(component, "component"), pattern_chunk(event, "event")]
    )


class ParsedKey(msgspec.Struct, frozen=True):
    """A key taken apart: ``kind`` is ``bb``, ``wm``, ``ev``, ``rq`` or ``@alive``."""

    mesh: str
    embodiment: str
    kind: str
    rest: tuple[str, ...]


def parse(key: str) -> ParsedKey:
    """Take a concrete key apart; raises ``InvalidName`` if it is not in the grammar."""
    chunks = key.split("/")
    if len(chunks) < 4 or chunks[0] != ROOT:
        raise InvalidName(f"key {key!r} is not of the form {ROOT}/<mesh>/<embodiment>/<kind>/...")
    mesh = check_name(chunks[1], "mesh")
    if chunks[2] == ALIVE:
        if len(chunks) != 4:
            raise InvalidName(f"liveliness key {key!r} must be {ROOT}/<mesh>/{ALIVE}/<embodiment>")
        return ParsedKey(mesh, check_name(chunks[3], "embodiment"), ALIVE, ())
    embodiment = check_name(chunks[2], "embodiment")
    kind = chunks[3]
    rest = tuple(check_name(c, "key element") for c in chunks[4:])
    if kind == EVENTS and len(rest) != 2:
        raise InvalidName(f"key {key!r}: {kind} keys are .../{kind}/<component>/<name>")
    if kind == REQUESTS and len(rest) not in (2, 3):
        raise InvalidName(f"key {key!r}: {kind} keys are .../{kind}/<component>/<name>[/<sender>]")
    if kind not in (EVENTS, REQUESTS, BLACKBOARD, WORLD_MODEL):
        raise InvalidName(f"key {key!r}: unknown kind {kind!r}")
    return ParsedKey(mesh, embodiment, kind, rest)


def matches(pattern: str, key: str, *, verbatim: bool = False) -> bool:
    """Whether a concrete ``key`` matches ``pattern`` (``*`` = one chunk, ``**`` = zero or more).
    ``verbatim``: as zenoh does, a chunk starting with ``@`` is matched only by itself, never by a wildcard."""
    return _match(pattern.split("/"), key.split("/"), verbatim)


def matches_chunks(pattern: Sequence[str], chunks: Sequence[str]) -> bool:
    """``matches`` on keys already split; ``chunks`` may be empty (the prefix itself)."""
    return _match(list(pattern), list(chunks))


def intersects_below(pattern: str, prefix: str, *, one_chunk: bool) -> bool:
    """Whether key expression ``pattern`` intersects ``prefix/*`` (``one_chunk``) or ``prefix/**``
    (``prefix`` concrete): whether some key both match. What a queryable declared on one of those
    would have been reached by (``ion``: one queryable for many components' requests)."""
    pat = pattern.split("/")
    states = _states(pat, prefix.split("/"))
    if not one_chunk:
        return bool(states)  # whatever is left of the pattern, some chunks match it
    # One chunk more must end it: at most one chunk of the rest that is not ``**`` (which may match none).
    return any(sum(chunk != "**" for chunk in pat[i:]) == 1 or (pat[i:] and all(c == "**" for c in pat[i:]))
               for i in states)


def _match(pat: list[str], chunks: list[str], verbatim: bool = False) -> bool:
    return len(pat) in _states(pat, chunks, verbatim)


def _states(pat: list[str], chunks: list[str], verbatim: bool = False) -> set[int]:
    # The set of pattern positions reachable after each chunk: O(len(pat) * len(chunks)) whatever the
    # number of ``**`` (a selector comes from the network: backtracking would be exponential).
    def closure(states: set[int]) -> set[int]:
        todo = list(states)
        while todo:  # ``**`` may match no chunk at all
            i = todo.pop()
            if i < len(pat) and pat[i] == "**" and i + 1 not in states:
                states.add(i + 1)
                todo.append(i + 1)
        return states

    states = closure({0})
    for chunk in chunks:
        following: set[int] = set()
        wild = not (verbatim and chunk.startswith("@"))
        for i in states:
            if i < len(pat):
                if pat[i] == "**" and wild:
                    following.add(i)
                elif (pat[i] == "*" and wild) or pat[i] == chunk:
                    following.add(i + 1)
        if not following:
            return set()
        states = closure(following)
    return states
