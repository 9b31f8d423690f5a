"""The ``cmion-mesh`` command line.

Every command takes ``--mesh``, ``--connect``, ``--listen``, ``--config`` (a zenoh JSON5 file)
and ``--no-multicast``; errors are one clear line on stderr and a non-zero exit, never a traceback.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import msgspec

from cmion_mesh import keys
from cmion_mesh.competency import Competency
from cmion_mesh.errors import MeshError
from cmion_mesh.messages import Container, Property, RemoveContainer, RemoveProperty
from cmion_mesh.signals import Stopper
from cmion_mesh.transport import TransportConfig

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_CANCELLED = 0, 1, 2, 3


def transport_config(args: argparse.Namespace, name: str | None = None) -> TransportConfig:
    """The session settings from the common options; ``--certs`` turns them into mutual TLS with
    access control for identity ``name`` (see docs/security.md)."""
    from cmion_mesh import security

    config = TransportConfig(
        connect=tuple(args.connect or ()),
        listen=tuple(args.listen or ()),
        config_file=args.config,
        multicast=not args.no_multicast,
        multicast_interface=getattr(args, "multicast_interface", None),
        lease_ms=getattr(args, "lease_ms", None),
    )
    return security.apply(args, config, name=name)


def _common(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("mesh")
    group.add_argument("--mesh", default=keys.DEFAULT_MESH, help="deployment name (default: %(default)s)")
    group.add_argument("--connect", action="append", metavar="ENDPOINT", help="zenoh endpoint to connect to, e.g. tcp/10.0.0.5:7447")
    group.add_argument("--listen", action="append", metavar="ENDPOINT", help="zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447")
    group.add_argument("--config", metavar="FILE", help="zenoh JSON5 configuration file")
    group.add_argument("--no-multicast", action="store_true", help="do not scout for peers by multicast")
    group.add_argument("--multicast-interface", metavar="IFACE", help="interface to scout on (default: zenoh's choice)")
    group.add_argument("--json", action="store_true", help="machine-readable output")
    from cmion_mesh import security

    security.add_arguments(group)


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
    stop = _stop_on_signals() if args.action == "watch" else None  # before any thread starts
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
            assert stop is not None
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


def _stop_on_signals() -> Stopper:
    return Stopper()


def resolve_config(path: str) -> str:
    """``up`` takes a configuration file, a folder holding ``ArchitectureConfiguration.xml``, or the
    name of a shipped embodiment (``robot``, ``screen``, ``phone``, ``cmion_test``)."""
    from pathlib import Path

    from cmion_mesh.resources import data_dir

    candidate = Path(path)
    if candidate.is_dir():
        candidate = candidate / "ArchitectureConfiguration.xml"
    elif not candidate.exists() and "/" not in path:
        shipped = data_dir("embodiments") / path / "ArchitectureConfiguration.xml"
        if shipped.exists():
            candidate = shipped
    if not candidate.is_file():
        raise MeshError(f"no architecture configuration at {path!r}")
    return str(candidate)


def state_dir(args: argparse.Namespace, name: str) -> str:
    """Where an embodiment keeps its durable migration records: ``--state-dir`` or a per-user folder."""
    if args.state_dir:
        return str(args.state_dir)
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return os.path.join(base, "cmion-mesh", args.mesh, name)


def admit(args: argparse.Namespace) -> dict[str, bytes | None] | None:
    """``--admit NAME[=PUBLICKEY]``: which companions may migrate in (default: any)."""
    from cmion_mesh.signing import decode_public

    if not args.admit:
        return None
    out: dict[str, bytes | None] = {}
    for item in args.admit:
        name, _, key = item.partition("=")
        out[keys.check_name(name, "companion")] = decode_public(key) if key else None
    return out


def cmd_up(args: argparse.Namespace) -> int:
    from cmion_mesh.embodiment import Embodiment

    stop = _stop_on_signals()
    if args.path:
        config = resolve_config(args.path)
        from cmion_mesh.architecture import load_architecture

        name = args.name or load_architecture(config).embodiment
        embodiment = Embodiment.from_architecture(config, mesh=args.mesh, name=name, transport_config=transport_config(args, name),
                                                  state_dir=state_dir(args, name), companion=args.companion, admit=admit(args))
    else:
        if not args.name:
            raise MeshError("give an architecture configuration (PATH) or at least --name")
        embodiment = Embodiment(args.name, mesh=args.mesh, transport_config=transport_config(args, args.name),
                                world_model_init=args.world_model, rules=args.rules, library=args.library,
                                state_dir=state_dir(args, args.name), companion=args.companion, admit=admit(args))
    with embodiment:
        from cmion_mesh import security

        mode = security.describe(args, name=embodiment.name)
        print(mode, file=sys.stderr if mode.startswith("plain") else sys.stdout, flush=True)
        if args.no_multicast and not args.connect and not args.listen:
            print("warning: no multicast and no endpoints: no peer can find this embodiment", file=sys.stderr)
        print(f"embodiment {embodiment.name!r} up in mesh {args.mesh!r} (zenoh id {embodiment.transport.id}; "
              f"{len(embodiment.execution.competencies)} competencies, {len(embodiment.rules.rules)} rules)", flush=True)
        stop.wait()
    left = [t.name for t in threading.enumerate() if t is not threading.main_thread() and t.is_alive()]
    if left:
        print(f"embodiment {embodiment.name!r} stopped, but threads are still running: {', '.join(left)}", flush=True)
        return EXIT_FAILED
    print(f"embodiment {embodiment.name!r} stopped cleanly (no thread left)", flush=True)
    return EXIT_OK


def _serve(args: argparse.Namespace, base: type[Any], what: str) -> int:
    """Host a component built from ``CLASS --parameters`` for ``--embodiment`` until stopped."""
    from cmion_mesh.classes import construct, split_parameters
    from cmion_mesh.ion import serve
    from cmion_mesh.remote import CompetencyHost
    from cmion_mesh.zenoh_transport import ZenohTransport

    built = construct(args.cls, base, split_parameters(args.parameters))
    component = CompetencyHost(built) if isinstance(built, Competency) else built
    stop = _stop_on_signals()
    config = transport_config(args, args.embodiment)
    with ZenohTransport(config) as transport, serve(component, embodiment=args.embodiment, transport=transport, mesh=args.mesh):
        print(f"{what} {built.name!r} serving embodiment {args.embodiment!r}", flush=True)
        stop.wait()
    return EXIT_OK


def cmd_serve_competency(args: argparse.Namespace) -> int:
    return _serve(args, Competency, "competency")


def cmd_serve_mind(args: argparse.Namespace) -> int:
    from cmion_mesh.mind import Mind

    return _serve(args, Mind, "mind")


def cmd_peers(args: argparse.Namespace) -> int:
    transport, client = _client(args)
    with transport, Spinner("looking for embodiments", enabled=not args.json):
        peers = client.describe_all(timeout=args.timeout)
    if args.json:
        print(json.dumps(peers))
        return EXIT_OK
    if not peers:
        print("(no embodiments found: try `cmion-mesh doctor`)")
        return EXIT_OK
    rows: list[tuple[str, ...]] = [("EMBODIMENT", "INHABITANT", "COMPETENCY TYPES", "ACTIONS", "VERSION", "UP SINCE")]
    for p in peers:
        since = time.strftime("%H:%M:%S", time.localtime(p.get("started_at", 0))) if p.get("started_at") else "?"
        rows.append((p["name"], p.get("inhabitant") or "-", ",".join(p.get("competency_types", [])) or "-",
                     "; ".join(p.get("actions", [])) or "-", p.get("version", "?"), since))
    _table(rows)
    return EXIT_OK


def _table(rows: list[tuple[str, ...]]) -> None:
    widths = [min(40, max(len(r[i]) for r in rows)) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell[:40].ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())


class Spinner:
    """A progress line on stderr while a command waits (only on a terminal)."""

    def __init__(self, text: str, *, enabled: bool = True) -> None:
        self.text = text
        self.enabled = enabled and sys.stderr.isatty()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> Spinner:
        if self.enabled:
            self._thread = threading.Thread(target=self._spin, daemon=True)
            self._thread.start()
        return self

    def _spin(self) -> None:
        frames = "|/-\\"
        start = time.monotonic()
        for i in itertools.count():
            if self._stop.wait(0.1):
                break
            sys.stderr.write(f"\r{frames[i % 4]} {self.text} ({time.monotonic() - start:.1f} s)")
            sys.stderr.flush()
        sys.stderr.write("\r" + " " * (len(self.text) + 16) + "\r")
        sys.stderr.flush()

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1)


def cmd_act(args: argparse.Namespace) -> int:
    transport, client = _client(args)
    with transport:
        client.wait_for_embodiment(args.embodiment, timeout=args.discover_timeout)
        with Spinner(f"{args.embodiment}: {' '.join([args.action, *args.parameters])}", enabled=not args.json):
            report = client.act(args.embodiment, args.action, args.parameters, subject=args.subject, action_id=args.id or "",
                                timeout=args.timeout, deadline=args.deadline)
    if args.json:
        print(json.dumps(msgspec.to_builtins(report)))
    else:
        extra = f": {report.reason}" if report.reason else ""
        print(f"{report.action_id} {report.status}{extra}" + (f" (rule {report.rule})" if report.rule else ""))
    return {"succeeded": EXIT_OK, "cancelled": EXIT_CANCELLED}.get(report.status, EXIT_FAILED)


def cmd_cancel(args: argparse.Namespace) -> int:
    from cmion_mesh.ion import require_accepted

    transport, client = _client(args)
    with transport:
        client.wait_for_embodiment(args.embodiment, timeout=args.discover_timeout)
        require_accepted(client.cancel(args.embodiment, args.action_id), f"{args.embodiment}/manager/cancel")
    print(f"cancel of {args.action_id} accepted")
    return EXIT_OK


def cmd_events(args: argparse.Namespace) -> int:
    from cmion_mesh.messages import Event

    stop = _stop_on_signals()
    seen = [0]

    def show(event: Event) -> None:
        if args.json:
            print(json.dumps(msgspec.to_builtins(event)), flush=True)
        else:
            stamp = time.strftime("%H:%M:%S", time.localtime(event.time)) + f".{int(event.time * 1000) % 1000:03d}"
            data = json.dumps(event.data) if event.data is not None else ""
            print(f"{stamp} {event.embodiment}/{event.component} {event.name} {data}", flush=True)
        seen[0] += 1
        if args.count and seen[0] == args.count:
            stop.stop()

    transport, client = _client(args)
    with transport, client.events(show, embodiment=args.embodiment, component=args.component, event=args.event):
        if not args.json:
            print(f"following events of {args.embodiment}/{args.component}/{args.event} in mesh {args.mesh!r} (Ctrl-C to stop)",
                  file=sys.stderr, flush=True)
        stop.wait(args.duration or None)
    return EXIT_OK


def cmd_migrate(args: argparse.Namespace) -> int:
    transport, client = _client(args)
    with transport, Spinner(f"migrating {args.companion} to {args.to}", enabled=not args.json):
        result = client.migrate(args.companion, args.to, timeout=args.timeout)
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{args.companion} migrated from {result['source']} to {result['target']} (epoch {result['epoch']})")
    return EXIT_OK


def cmd_bench(args: argparse.Namespace) -> int:
    """``cmion-mesh bench ...`` is ``python -m bench ...`` from a source checkout (bench/ is not installed)."""
    try:
        from bench.__main__ import main as bench_main
    except ImportError:
        raise MeshError("the benchmarks live in the source checkout's bench/ folder: run this command from there") from None
    code: int = bench_main(args.bench_args)
    return code


def cmd_router(args: argparse.Namespace) -> int:
    from cmion_mesh import router

    return router.run(args)


def cmd_doctor(args: argparse.Namespace) -> int:
    from cmion_mesh.doctor import run_doctor

    return run_doctor(args, transport_config(args))


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
    p.add_argument("path", nargs="?", help="ArchitectureConfiguration file or folder, or a shipped embodiment name (robot, screen...)")
    p.add_argument("--name", help="embodiment name (default: from the configuration)")
    p.add_argument("--world-model", metavar="FILE", help="CMION WorldModel init file to load at start")
    p.add_argument("--rules", metavar="FILE", help="CMION CompetencyManagerRules file")
    p.add_argument("--library", metavar="FILE", help="CMION CompetencyLibrary file")
    p.add_argument("--lease-ms", type=int, default=2000, help="zenoh link lease: how fast a frozen peer is noticed")
    p.add_argument("--state-dir", help="durable migration records (default: ~/.local/state/cmion-mesh/<mesh>/<name>)")
    p.add_argument("--companion", help="a companion born here on the first start, if this embodiment holds none")
    p.add_argument("--admit", action="append", metavar="NAME[=KEY]",
                   help="a companion allowed to migrate in, with its public key (see `peers --json`); default: any")
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

    p = sub.add_parser("peers", help="list the embodiments alive in the mesh, with what they can do")
    p.add_argument("--timeout", type=float, default=1.5, help="seconds to wait for answers")
    _common(p)
    p.set_defaults(func=cmd_peers)

    p = sub.add_parser("act", help="send a mind action to an embodiment and wait for its outcome (exit code says it)")
    p.add_argument("embodiment")
    p.add_argument("action")
    p.add_argument("parameters", nargs="*")
    p.add_argument("--subject", default="")
    p.add_argument("--id", help="action id (default: generated)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for the outcome")
    p.add_argument("--deadline", type=float, default=0.0, help="deadline of each plan tried, seconds")
    p.add_argument("--discover-timeout", type=float, default=5.0, help="seconds to wait for the embodiment to be found")
    _common(p)
    p.set_defaults(func=cmd_act)

    p = sub.add_parser("cancel", help="cancel a running action")
    p.add_argument("embodiment")
    p.add_argument("action_id")
    p.add_argument("--discover-timeout", type=float, default=5.0)
    _common(p)
    p.set_defaults(func=cmd_cancel)

    p = sub.add_parser("events", help="follow the event stream (filterable)")
    p.add_argument("--follow", "-f", action="store_true", help="keep following (the default; for familiarity)")
    p.add_argument("--embodiment", default="*")
    p.add_argument("--component", default="*")
    p.add_argument("--event", default="*")
    p.add_argument("--count", type=int, default=0, help="stop after this many events")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    _common(p)
    p.set_defaults(func=cmd_events)

    p = sub.add_parser("migrate", help="move a companion to another embodiment (waits for the handshake's end)")
    p.add_argument("companion")
    p.add_argument("--to", required=True, metavar="EMBODIMENT")
    p.add_argument("--timeout", type=float, default=60.0)
    _common(p)
    p.set_defaults(func=cmd_migrate)

    p = sub.add_parser("serve-mind", help="run a mind in this process, driving an embodiment over the mesh")
    p.add_argument("cls", metavar="CLASS", help="package.module:Class, a Mind subclass")
    p.add_argument("--embodiment", required=True)
    p.add_argument("--parameters", default="", help="comma-separated constructor parameters")
    _common(p)
    p.set_defaults(func=cmd_serve_mind)

    p = sub.add_parser("router", help="run a zenoh router, so embodiments beyond one LAN join one mesh")
    from cmion_mesh import router as router_module

    router_module.add_arguments(p)
    p.set_defaults(func=cmd_router)

    p = sub.add_parser("certs", help="a certificate authority and certificates for an authenticated mesh (mutual TLS)")
    from cmion_mesh import certs as certs_module

    certs_module.add_arguments(p)
    p.set_defaults(func=certs_module.run)

    p = sub.add_parser("bench", help="run the benchmarks (from a source checkout; see bench/README.md)", add_help=False)
    p.add_argument("bench_args", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("doctor", help="explain why peers are (not) found: interfaces, multicast, zenoh config")
    p.add_argument("--timeout", type=float, default=2.0)
    _common(p)
    p.set_defaults(func=cmd_doctor)

    p = sub.add_parser("validate", help="check CMION XML files against their schemas and semantics")
    p.add_argument("files", nargs="+")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("demo", help="run the demonstration scenario")
    _common(p)
    p.set_defaults(func=cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    # After "bench", every argument is the benchmark's own, options included.
    bench = argv[:1] == ["bench"]
    args = argparse.Namespace(func=cmd_bench, bench_args=argv[1:]) if bench else parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except MeshError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        return 130
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except Exception as exc:
        if os.environ.get("CMION_MESH_DEBUG"):
            raise
        print(f"internal error: {type(exc).__name__}: {exc} (set CMION_MESH_DEBUG=1 for the traceback)", file=sys.stderr)
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
