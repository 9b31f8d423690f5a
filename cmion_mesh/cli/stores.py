"""``bb`` and ``wm``: read, write and watch an embodiment's blackboard and world model."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.cli.common import mesh_options, timeout_option
from cmion_mesh.cli.session import session
from cmion_mesh.client import STORE_LABELS
from cmion_mesh.errors import ExitCode
from cmion_mesh.messages import Container, Property, RemoveContainer, RemoveProperty
from cmion_mesh.requests import require_accepted
from cmion_mesh.signals import Stopper


def bb_arguments(parser: argparse.ArgumentParser) -> None:
    store_arguments(parser, keys.BLACKBOARD)


def wm_arguments(parser: argparse.ArgumentParser) -> None:
    store_arguments(parser, keys.WORLD_MODEL)


def store_arguments(parser: argparse.ArgumentParser, store: str) -> None:
    label = STORE_LABELS[store]
    parser.description = (f"Read, write and watch an embodiment's {label}. Paths are container/.../property"
                          + ("; entity.property (as $WM(...) writes it) works too." if store == keys.WORLD_MODEL else "."))
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    for action, text in (("get", "read a property or a container (everything, without PATH)"),
                         ("tree", "list a container and all below it"), ("set", "set a property"),
                         ("remove", "remove a property or container"), ("watch", "follow changes until Ctrl-C")):
        ap = actions.add_parser(action, help=text, description=text)
        ap.add_argument("embodiment", help="the embodiment whose store this is")
        ap.add_argument("path", nargs="?" if action in ("get", "tree", "watch") else None, default="",
                        help="container/.../property" + (" or entity.property" if store == keys.WORLD_MODEL else ""))
        if action == "set":
            ap.add_argument("value", help="JSON value (3, true, [1,2], {\"a\":1}) or plain text")
            ap.add_argument("--persistent", action="store_true",
                            help="survives a restart of the daemon" + ("; travels with the companion when it migrates"
                                                                       if store == keys.WORLD_MODEL else ""))
            ap.add_argument("--string", action="store_true", help="take the value as text, never JSON")
        if action == "remove":
            ap.add_argument("--container", action="store_true", help="the path names a container")
        timeout_option(ap, 5.0, "seconds to wait for the embodiment and its answer")
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
    with session(args) as client:
        client.join(args.embodiment, timeout=args.timeout)
        container, _, name = args.path.rpartition("/") if args.path else ("", "", "")
        prefix = keys.storage_key(args.mesh, args.embodiment, store, ()) + "/"
        where = f"{args.embodiment}'s {STORE_LABELS[store]}"
        if args.action in ("get", "tree"):
            entries = client.lookup(args.embodiment, store, args.path or "", below=args.action == "tree", timeout=args.timeout)
            print_entries(entries, prefix, args.json)
            return ExitCode.OK
        if args.action == "set":
            value = parse_value(args.value, args.string)
            client.set_property(args.embodiment, store, container, name, value, persistent=args.persistent)
            print(json.dumps({"key": prefix + args.path, "value": value, "persistent": args.persistent}) if args.json
                  else f"{where}: {args.path} = {json.dumps(value)}" + (" (persistent)" if args.persistent else ""))
            return ExitCode.OK
        if args.action == "remove":
            write = RemoveContainer(container, name) if args.container else RemoveProperty(container, name)
            require_accepted(client.write(args.embodiment, store, write), f"{store}/{args.path}")
            print(json.dumps({"removed": prefix + args.path}) if args.json else f"{where}: removed {args.path}")
            return ExitCode.OK
        assert stop is not None
        base = keys.storage_key(args.mesh, args.embodiment, store, keys.split_path(args.path or ""))

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
