"""The ``cmion-mesh`` command line.

Every command takes ``--mesh``, ``--connect``, ``--listen``, ``--config`` (a zenoh JSON5 file)
and ``--no-multicast``; errors are one clear line on stderr and a non-zero exit, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.errors import MeshError
from cmion_mesh.messages import Container, Property, RemoveContainer, RemoveProperty
from cmion_mesh.transport import TransportConfig

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def transport_config(args: argparse.Namespace) -> TransportConfig:
    return TransportConfig(
        connect=tuple(args.connect or ()),
        listen=tuple(args.listen or ()),
        config_file=args.config,
        multicast=not args.no_multicast,
        lease_ms=getattr(args, "lease_ms", None),
    )


def _common(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("mesh")
    group.add_argument("--mesh", default=keys.DEFAULT_MESH, help="deployment name (default: %(default)s)")
    group.add_argument("--connect", action="append", metavar="ENDPOINT", help="zenoh endpoint to connect to, e.g. tcp/10.0.0.5:7447")
    group.add_argument("--listen", action="append", metavar="ENDPOINT", help="zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447")
    group.add_argument("--config", metavar="FILE", help="zenoh JSON5 configuration file")
    group.add_argument("--no-multicast", action="store_true", help="do not scout for peers by multicast")
    group.add_argument("--json", action="store_true", help="machine-readable output")


def parse_value(text: str, as_string: bool) -> Any:
    """CLI values are JSON when they parse as JSON (``3``, ``true``, ``[1,2]``), else plain strings."""
    if as_string:
        return text
    try:
        return msgspec.json.decode(text)
    except msgspec.DecodeError:
        return text


def _client(args: argparse.Namespace) -> Any:
    from cmion_mesh.client import MeshClient
    from cmion_mesh.zenoh_transport import ZenohTransport

    transport = ZenohTransport(transport_config(args))
    return transport, MeshClient(transport, args.mesh)


def _print_entries(entries: dict[str, Any], prefix: str, as_json: bool) -> None:
    if as_json:
        print(json.dumps({k: msgspec.to_builtins(v) for k, v in entries.items()}, indent=None))
        return
    if not entries:
        print("(nothing found: is the embodiment running and reachable? try `cmion-mesh peers`)")
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
    transport, client = _client(args)
    with transport:
        container, _, name = args.path.rpartition("/") if args.path else ("", "", "")
        prefix = keys.storage_key(args.mesh, args.embodiment, store, ()) + "/"
        if args.action in ("get", "tree"):
            base = keys.storage_key(args.mesh, args.embodiment, store, keys.split_path(args.path or ""))
            entries = client.read(base if args.action == "get" and args.path else f"{base}/**")
            if args.action == "get" and args.path and not entries:
                entries = client.read(f"{base}/**")
            _print_entries(entries, prefix, args.json)
            return EXIT_OK if entries else EXIT_FAILED
        if args.action == "set":
            value = parse_value(args.value, args.string)
            client.set_property(args.embodiment, store, container, name, value, persistent=args.persistent)
            print(f"{store}/{args.path} = {json.dumps(value)}")
            return EXIT_OK
        if args.action == "remove":
            from cmion_mesh.ion import require_accepted

            write = RemoveContainer(container, name) if args.container else RemoveProperty(container, name)
            require_accepted(client.write(args.embodiment, store, write), f"{store}/{args.path}")
            print(f"removed {store}/{args.path}")
            return EXIT_OK
        if args.action == "watch":
            stop = _stop_on_signals()
            base = keys.storage_key(args.mesh, args.embodiment, store, keys.split_path(args.path or ""))

            def show(key: str, entry: Any) -> None:
                short = key[len(prefix):]
                if args.json:
                    print(json.dumps({"key": key, "entry": msgspec.to_builtins(entry)}), flush=True)
                elif entry is None:
                    print(f"- {short}", flush=True)
                else:
                    _print_entries({key: entry}, prefix, False)
                    sys.stdout.flush()

            with client.watch(f"{base}/**", show):
                stop.wait()
            return EXIT_OK
    return EXIT_USAGE


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()

    def handler(_signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def cmd_up(args: argparse.Namespace) -> int:
    from cmion_mesh.embodiment import Embodiment

    stop = _stop_on_signals()
    with Embodiment(
        args.name, mesh=args.mesh, transport_config=transport_config(args), world_model_init=args.world_model,
        rules=args.rules, library=args.library,
    ) as embodiment:
        print(f"embodiment {embodiment.name!r} up in mesh {args.mesh!r} (zenoh id {embodiment.transport.id})", flush=True)
        stop.wait()
    print(f"embodiment {args.name!r} stopped", flush=True)
    return EXIT_OK


def cmd_serve_competency(args: argparse.Namespace) -> int:
    from cmion_mesh.competency import Competency, import_class, split_parameters
    from cmion_mesh.remote import serve
    from cmion_mesh.zenoh_transport import ZenohTransport

    cls = import_class(args.cls)
    if not issubclass(cls, Competency):
        raise MeshError(f"{args.cls} is not a Competency subclass")
    competency = cls(*split_parameters(args.parameters))
    stop = _stop_on_signals()
    with ZenohTransport(transport_config(args)) as transport, serve(competency, embodiment=args.embodiment, transport=transport,
                                                                    mesh=args.mesh):
        print(f"competency {competency.name!r} ({competency.type}) serving embodiment {args.embodiment!r}", flush=True)
        stop.wait()
    return EXIT_OK


def cmd_peers(args: argparse.Namespace) -> int:
    transport, client = _client(args)
    with transport:
        names = client.embodiments()
    if args.json:
        print(json.dumps(names))
    else:
        print("\n".join(names) if names else "(no embodiments found)")
    return EXIT_OK


def cmd_validate(args: argparse.Namespace) -> int:
    from cmion_mesh.validate import validate_file

    failed = 0
    for path in args.files:
        try:
            kind = validate_file(path)
        except MeshError as exc:
            failed += 1
            print(f"error: {exc}", file=sys.stderr)
        else:
            print(f"ok: {path} ({kind})")
    return EXIT_FAILED if failed else EXIT_OK


def cmd_demo(args: argparse.Namespace) -> int:
    from cmion_mesh.demo import run_demo

    return run_demo(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cmion-mesh", description="Zenoh peer-to-peer embodiment mesh (CMION rebuilt).")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("up", help="run an embodiment daemon until SIGINT/SIGTERM")
    p.add_argument("--name", required=True, help="embodiment name")
    p.add_argument("--world-model", metavar="FILE", help="CMION WorldModel init file to load at start")
    p.add_argument("--rules", metavar="FILE", help="CMION CompetencyManagerRules file")
    p.add_argument("--library", metavar="FILE", help="CMION CompetencyLibrary file")
    p.add_argument("--lease-ms", type=int, default=2000, help="zenoh link lease: how fast a frozen peer is noticed")
    _common(p)
    p.set_defaults(func=cmd_up)

    for store, label in ((keys.BLACKBOARD, "blackboard"), (keys.WORLD_MODEL, "world model")):
        sp = sub.add_parser(store, help=f"read, write and watch an embodiment's {label}")
        actions = sp.add_subparsers(dest="action", required=True)
        for action, text in (("get", "read a property, a container or everything"), ("tree", "list a container and all below it"),
                             ("set", "set a property"), ("remove", "remove a property or container"), ("watch", "follow changes")):
            ap = actions.add_parser(action, help=text)
            ap.add_argument("embodiment")
            ap.add_argument("path", nargs="?" if action in ("get", "tree", "watch") else None, default="",
                            help="container/.../property")
            if action == "set":
                ap.add_argument("value", help="JSON value (3, true, [1,2], {\"a\":1}) or plain text")
                ap.add_argument("--persistent", action="store_true")
                ap.add_argument("--string", action="store_true", help="take the value as text, never JSON")
            if action == "remove":
                ap.add_argument("--container", action="store_true", help="the path names a container")
            _common(ap)
            ap.set_defaults(func=cmd_store, store=store)

    p = sub.add_parser("serve-competency", help="host a competency for an embodiment from this process (remote competency)")
    p.add_argument("cls", metavar="CLASS", help="package.module:Class, a Competency subclass")
    p.add_argument("--embodiment", required=True)
    p.add_argument("--parameters", default="", help="comma-separated constructor parameters")
    _common(p)
    p.set_defaults(func=cmd_serve_competency)

    p = sub.add_parser("peers", help="list the embodiments alive in the mesh")
    _common(p)
    p.set_defaults(func=cmd_peers)

    p = sub.add_parser("validate", help="check CMION XML files against their schemas and semantics")
    p.add_argument("files", nargs="+")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("demo", help="run the demonstration scenario")
    _common(p)
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except MeshError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
