"""``bb`` and ``wm``: read, write and watch an embodiment's blackboard and world model; ``wm add``
and ``wm remove`` add and remove entities (CMION's AgentSimulator and WorldModelSimulator)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.cli.common import join_timeout_option, mesh_options, timeout_option
from cmion_mesh.cli.session import session
from cmion_mesh.client import STORE_LABELS, MeshClient
from cmion_mesh.errors import ConfigError, ExitCode, InvalidName, RequestRejected
from cmion_mesh.messages import Code, Container, Property
from cmion_mesh.signals import Stopper


def bb_arguments(parser: argparse.ArgumentParser) -> None:
    store_arguments(parser, keys.BLACKBOARD)


def wm_arguments(parser: argparse.ArgumentParser) -> None:
    store_arguments(parser, keys.WORLD_MODEL)


#: Per action: its help, and (store -> an example) for its description.
ACTIONS: dict[str, tuple[str, dict[str, str]]] = {
    "get": ("read a property or a container (everything, without PATH)",
            {keys.BLACKBOARD: "cmion-mesh bb get robot navigation/state",
             keys.WORLD_MODEL: "cmion-mesh wm get robot Self.location      # the same as Self/location"}),
    "tree": ("list a container and all below it",
             {keys.BLACKBOARD: "cmion-mesh bb tree robot", keys.WORLD_MODEL: "cmion-mesh wm tree robot Visitor"}),
    "set": ("set a property to a value",
            {keys.BLACKBOARD: "cmion-mesh bb set robot battery 0.8 --persistent",
             keys.WORLD_MODEL: "cmion-mesh wm set robot Visitor.present true   # Visitor must be there: wm add"}),
    "add": ("add an entity (an agent, or an object) with its properties, in one write: minds hear it added "
            "(CMION's AgentSimulator)",
            {keys.WORLD_MODEL: "cmion-mesh wm add robot Visitor present=true name=Ada"}),
    "remove": ("remove a property or a container",
               {keys.BLACKBOARD: "cmion-mesh bb remove robot navigation --container",
                keys.WORLD_MODEL: "cmion-mesh wm remove robot Visitor   # the entity; Visitor.present: a property"}),
    "watch": ("follow changes until Ctrl-C", {keys.BLACKBOARD: "cmion-mesh bb watch robot speech",
                                              keys.WORLD_MODEL: "cmion-mesh wm watch robot"}),
}
WM_PATHS = ("World-model paths are entity/.../property or entity.property (as $WM(...) writes it), alike in every "
            "action: a path without / is split at its first dot. A name holding a dot is written with slashes "
            "(Self/pose.x); an entity's name holds no dot. The world model's root holds entities only.")


def store_arguments(parser: argparse.ArgumentParser, store: str) -> None:
    label = STORE_LABELS[store]
    world = store == keys.WORLD_MODEL
    parser.description = (f"Read, write and watch an embodiment's {label}. "
                           + (WM_PATHS if world else "Paths are container/.../property; a dot is part of a name."))
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    for action, (text, examples) in ACTIONS.items():
        if store not in examples:
            continue
        description = text[0].upper() + text[1:] + "." + (" " + WM_PATHS if world and action != "add" else "")
        if action == "remove" and world:
            description += " A one-name path is an entity, removed with all it holds: minds hear it removed."
        ap = actions.add_parser(action, help=text, description=description, epilog=f"example: {examples[store]}")
        ap.add_argument("embodiment", help="the embodiment whose store this is")
        if action == "add":
            ap.add_argument("entity", help="the new entity's name")
            ap.add_argument("properties", nargs="*", metavar="PROPERTY=VALUE",
                            help="its properties; each VALUE is JSON (3, true, [1,2]) or plain text, split at the first =")
            ap.add_argument("--object", dest="kind", action="store_const", const="object", default="agent",
                            help="the entity is an object (default: an agent)")
            ap.set_defaults(intermixed="properties")  # PROPERTY=VALUE after the options too (cli.main.parse)
        else:
            ap.add_argument("path", nargs="?" if action in ("get", "tree", "watch") else None, default="",
                            help="container/.../property" + (" or entity.property" if world else ""))
        if action == "set":
            ap.add_argument("value", help="JSON value (3, true, [1,2], {\"a\":1}) or plain text")
        if action in ("set", "add"):
            ap.add_argument("--persistent", action="store_true",
                            help="survives a restart of the daemon" + ("; travels with the companion when it migrates"
                                                                       if world else ""))
            ap.add_argument("--string", action="store_true", help="take the values as text, never JSON")
        if action == "remove":
            ap.add_argument("--container", action="store_true", help="the path names a container"
                            + (" (implied for an entity)" if world else ""))
        timeout_option(ap, 5.0, "seconds to wait for the answer")
        join_timeout_option(ap)
        mesh_options(ap)
        ap.set_defaults(store=store)


def parse_value(text: str, as_string: bool) -> Any:
    """CLI values are JSON when they parse as JSON (``3``, ``true``, ``[1,2]``), else plain strings."""
    if as_string:
        return text
    try:
        return msgspec.json.decode(text)
    except msgspec.DecodeError:
        return text


def print_entries(entries: dict[str, Any], prefix: str, as_json: bool) -> None:
    if as_json:
        print(json.dumps({k: msgspec.to_builtins(v) for k, v in entries.items()}))
        return
    width = max(len(k[len(prefix):]) for k in entries) if entries else 0
    for key, entry in entries.items():
        short = key[len(prefix):] or "/"
        if isinstance(entry, Property):
            flag = "  (persistent)" if entry.persistent else ""
            print(f"{short:<{width}}  = {json.dumps(entry.value)}{flag}")
        elif isinstance(entry, Container):
            print(f"{short:<{width}}  [{entry.kind}]")


def cmd_store(args: argparse.Namespace) -> int:
    store = args.store
    stop = Stopper() if args.action == "watch" else None  # before any thread starts
    # A path is read before joining: one that cannot be is a usage error, said at once.
    chunks = keys.store_path(store, getattr(args, "path", ""))
    shown = "/".join(chunks)
    if args.action in ("set", "remove") and not chunks:
        raise InvalidName(f"{args.action} needs a path")
    properties = _properties(args) if args.action == "add" else {}
    if args.action == "add":
        keys.check_entity(args.entity)
    with session(args) as client:
        client.join(args.embodiment, timeout=args.join_timeout)
        prefix = keys.storage_key(args.mesh, args.embodiment, store, ()) + "/"
        where = f"{args.embodiment}'s {STORE_LABELS[store]}"
        if args.action in ("get", "tree"):
            entries = client.lookup(args.embodiment, store, args.path or "", below=args.action == "tree", timeout=args.timeout)
            print_entries(entries, prefix, args.json)
            return ExitCode.OK
        if args.action == "add":
            return _add_entity(client, args, properties, prefix, where)
        if args.action == "set":
            value = parse_value(args.value, args.string)
            try:
                client.set_property(args.embodiment, store, "/".join(chunks[:-1]), chunks[-1], value, persistent=args.persistent)
            except RequestRejected as exc:
                if store == keys.WORLD_MODEL and exc.code == Code.NOT_FOUND and len(chunks) == 2:
                    raise RequestRejected(f"{exc} (add it first: cmion-mesh wm add {args.embodiment} {chunks[0]})",
                                          key=exc.key, reason=exc.reason, code=exc.code) from None
                raise
            print(json.dumps({"key": prefix + shown, "value": value, "persistent": args.persistent}) if args.json
                  else f"{where}: {shown} = {json.dumps(value)}" + (" (persistent)" if args.persistent else ""))
            return ExitCode.OK
        if args.action == "remove":
            entity = store == keys.WORLD_MODEL and len(chunks) == 1
            if args.container or entity:
                client.remove_container(args.embodiment, store, shown)
            else:
                client.remove_property(args.embodiment, store, shown)
            print(json.dumps({"removed": prefix + shown}) if args.json
                  else f"{where}: removed {'entity ' if entity else ''}{shown}")
            return ExitCode.OK
        assert stop is not None
        base = keys.storage_key(args.mesh, args.embodiment, store, chunks)

        def show(key: str, entry: Any) -> None:
            short = key[len(prefix):]
            if args.json:
                print(json.dumps({"key": key, "entry": msgspec.to_builtins(entry)}), flush=True)
            elif entry is None:
                print(f"- {short}", flush=True)
            else:
                print_entries({key: entry}, prefix, False)
                sys.stdout.flush()

        with client.watch(f"{base}/**", show):
            stop.wait()
        return ExitCode.OK


def _properties(args: argparse.Namespace) -> dict[str, Any]:
    """``wm add``'s PROPERTY=VALUE arguments, as a map (``ConfigError`` naming the one at fault)."""
    properties: dict[str, Any] = {}
    for item in args.properties:
        name, equals, text = item.partition("=")
        if not equals:
            raise ConfigError(f"{item!r} is not PROPERTY=VALUE")
        if name in properties:
            raise ConfigError(f"property {name!r} is given twice")
        properties[keys.check_name(name, "property")] = parse_value(text, args.string)
    return properties


def _add_entity(client: MeshClient, args: argparse.Namespace, properties: dict[str, Any], prefix: str, where: str) -> int:
    client.add_entity(args.embodiment, args.entity, properties, kind=args.kind, persistent=args.persistent)
    if args.json:
        print(json.dumps({"added": prefix + args.entity, "kind": args.kind, "properties": properties,
                          "persistent": args.persistent}))
    else:
        shown = " ".join(f"{n}={json.dumps(v)}" for n, v in properties.items())
        print(f"{where}: added {args.kind} {args.entity}" + (f" {shown}" if shown else "")
              + (" (persistent)" if args.persistent and properties else ""))
    return ExitCode.OK
