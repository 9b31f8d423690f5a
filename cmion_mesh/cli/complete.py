"""Shell completion, through argcomplete: verbs, options, and the names of what is alive in the mesh
(embodiments, companions, the actions an embodiment's rules accept), asked of the mesh that the
line being completed names (its ``--mesh``, ``--connect``, ``--certs``...).

argcomplete runs this program with its protocol's variables set (``_ARGCOMPLETE``, ``COMP_LINE``,
``COMP_POINT``) and reads the completions from it; the shell is waiting, so a name lookup is bounded:
a short join (``LOOKUP_WAIT``), and whatever is not known by ``LOOKUP_LIMIT`` is left out, never
waited for. Enable it with ``eval "$(register-python-argcomplete cmion-mesh)"`` (README).
"""

from __future__ import annotations

import argparse
import os
import shlex
import threading
from collections.abc import Callable
from typing import Any

from cmion_mesh import keys

#: How long a lookup looks for the mesh's embodiments and waits for their descriptions.
LOOKUP_WAIT = 0.8
#: The longest a completion waits for a lookup in all (the session's opening and closing included).
LOOKUP_LIMIT = 1.5
#: Arguments (by dest) that name an embodiment, a companion, an action.
EMBODIMENT_DESTS = frozenset({"embodiment", "to", "keep", "gone", "wait_for"})
COMPANION_DESTS = frozenset({"companion"})
ACTION_DESTS = frozenset({"action"})


def autocomplete(build_parser: Callable[[str | None, str | None], argparse.ArgumentParser],
                 verb_of: Callable[[list[str]], tuple[str | None, str | None]]) -> None:
    """Answer argcomplete's request (and leave the process: argcomplete ends it) with the parser of
    the verb on the line (``verb_of`` the words typed so far), its name arguments given completers."""
    try:
        import argcomplete
    except ImportError:  # the `completion` extra is not installed: never run the command instead
        raise SystemExit(1) from None

    whole = os.environ.get("COMP_LINE", "")
    point = int(os.environ.get("COMP_POINT", "0") or 0)
    line = whole[:point]
    words = _split(line)
    done = words[1:] if line.endswith(" ") else words[1:-1]  # the words finished, the one being typed left out
    # The mesh options anywhere on the line, after the cursor too (`act robot G<TAB> --mesh lab`):
    # argcomplete parses only what is before it.
    after = _split(whole[point:])
    if after and not whole[point:point + 1].isspace():
        after = after[1:]  # the rest of the word being typed
    _line_options.update(line_mesh_options([*done, *after]))
    parser = build_parser(*verb_of(done))
    attach(parser)
    argcomplete.autocomplete(parser)


def _split(text: str) -> list[str]:
    try:
        return shlex.split(text)
    except ValueError:  # an open quote: complete what can be
        return text.split()


#: The mesh options the whole line gives (``line_mesh_options``), over what argcomplete parsed.
_line_options: dict[str, Any] = {}


def line_mesh_options(words: list[str]) -> dict[str, Any]:
    """The mesh options (``common.mesh_options``) given in ``words``, wherever they stand."""
    from cmion_mesh.cli.common import mesh_options

    parser = argparse.ArgumentParser(add_help=False)
    mesh_options(parser, json_output=False)
    try:
        known, _ = parser.parse_known_args(words)
    except SystemExit:  # a mesh option without its value: none of them then
        return {}
    given = {k: v for k, v in vars(known).items() if v != DEFAULTS.get(k)}
    return given


def attach(parser: argparse.ArgumentParser) -> None:
    """Give every argument that names a live thing its completer, in ``parser`` and below."""
    for action in parser._actions:  # argparse has no public walk of its actions
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                attach(sub)
        elif action.dest in EMBODIMENT_DESTS or (action.dest == "name" and parser.prog.endswith(" peers")):
            action.completer = embodiments  # type: ignore[attr-defined]
        elif action.dest in COMPANION_DESTS:
            action.completer = companions  # type: ignore[attr-defined]
        elif action.dest in ACTION_DESTS and not action.option_strings:
            action.completer = actions  # type: ignore[attr-defined]
        elif action.dest == "filters" and parser.prog.endswith(" record"):
            action.completer = record_words  # type: ignore[attr-defined]
        elif action.dest == "path" and parser.prog.split()[1:2] in (["bb"], ["wm"]):
            action.completer = store_paths  # type: ignore[attr-defined]
        elif parser.prog.split()[1:2] in (["bb"], ["wm"]) and not action.option_strings:
            action.completer = nothing  # type: ignore[attr-defined]  # values, new names: not file names


def record_words(prefix: str, parsed_args: argparse.Namespace, **_: Any) -> list[str]:
    """``record``'s FILTERs are key expressions, free to write; ``info`` is its other verb."""
    return ["info"] if "info".startswith(prefix) and not getattr(parsed_args, "filters", None) else []


def nothing(prefix: str, parsed_args: argparse.Namespace, **_: Any) -> list[str]:
    return []


def store_paths(prefix: str, parsed_args: argparse.Namespace, **_: Any) -> list[str]:
    """The paths in the line's embodiment's store (``bb``/``wm`` get, set...) starting with ``prefix``."""
    embodiment, store = getattr(parsed_args, "embodiment", None), getattr(parsed_args, "store", None)
    if not embodiment or not store:
        return []
    found: list[str] = []

    def ask(client: Any) -> None:
        root = keys.storage_key(client.mesh, embodiment, store, ()) + "/"
        client.join(embodiment, timeout=LOOKUP_WAIT)
        found.extend(key.removeprefix(root) for key in client.lookup(embodiment, store, "", below=True, timeout=LOOKUP_WAIT)
                     if key.startswith(root))

    bounded(parsed_args, ask)
    return sorted(p for p in found if p.startswith(prefix))


def embodiments(prefix: str, parsed_args: argparse.Namespace, **_: Any) -> list[str]:
    return [str(d.get("name")) for d in describe(parsed_args) if str(d.get("name", "")).startswith(prefix)]


def companions(prefix: str, parsed_args: argparse.Namespace, **_: Any) -> list[str]:
    found = {str(c) for d in describe(parsed_args) for c in (d.get("custody") or {}) if isinstance(c, str)}
    found |= {str(d["inhabitant"]) for d in describe(parsed_args) if d.get("inhabitant")}
    return sorted(c for c in found if c.startswith(prefix))


def actions(prefix: str, parsed_args: argparse.Namespace, **_: Any) -> list[str]:
    """The actions the embodiment named before on the line accepts (its rules' ``GoTo *``: GoTo)."""
    embodiment = getattr(parsed_args, "embodiment", None)
    names = {str(a).split()[0] for d in describe(parsed_args) if embodiment in (None, d.get("name"))
             for a in d.get("actions") or () if str(a).strip()}
    return sorted(n for n in names if n.startswith(prefix))


_described: dict[str, list[dict[str, Any]]] = {}


def describe(parsed_args: argparse.Namespace) -> list[dict[str, Any]]:
    """What the live embodiments of the line's mesh say of themselves, as far as known within
    ``LOOKUP_LIMIT`` (nothing when the mesh cannot be reached): asked once per completion."""
    if "found" in _described:
        return _described["found"]
    found: list[dict[str, Any]] = []

    def ask(client: Any) -> None:
        found.extend(d for d in client.describe_all(timeout=LOOKUP_WAIT) if not d.get("error"))

    _described["found"] = list(found) if bounded(parsed_args, ask) else []
    return _described["found"]


def bounded(parsed_args: argparse.Namespace, ask: Callable[[Any], None]) -> bool:
    """Run ``ask(client)`` in a session of the line's mesh, at most ``LOOKUP_LIMIT``: whether it
    ended (any error ends it, unsaid: a completion never shows one)."""

    def run() -> None:
        from cmion_mesh.cli.session import session

        args = argparse.Namespace(**{**DEFAULTS, **{k: v for k, v in vars(parsed_args).items() if v is not None},
                                     **_line_options})
        try:
            with session(args) as client:
                ask(client)
        except Exception:
            return

    worker = threading.Thread(target=run, name="complete", daemon=True)  # argcomplete leaves by os._exit
    worker.start()
    worker.join(LOOKUP_LIMIT)
    return not worker.is_alive()


#: The mesh options' values when the line gives none (as ``mesh_options`` defaults them).
DEFAULTS: dict[str, Any] = {"mesh": keys.DEFAULT_MESH, "connect": None, "listen": None, "config": None, "no_multicast": False,
                            "multicast_interface": None, "certs": None, "identity": None, "verify_names": False}
