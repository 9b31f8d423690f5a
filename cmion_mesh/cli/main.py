"""The ``cmion-mesh`` command line: the only module that reads ``argparse``.

Commands that join a mesh take ``--mesh``, ``--connect``, ``--listen``, ``--config`` (a zenoh
JSON5 file), ``--no-multicast``, ``--multicast-interface`` and ``--certs``; commands whose output
is data take ``--json``. One-shot commands join the mesh before they ask (``client``). Errors are
one clear line on stderr, never a traceback, and the exit code says what happened
(``errors.ExitCode``): 0 succeeded, 1 failed or refused, 2 usage or configuration error,
3 cancelled, 4 outcome unknown, 130 left on a second Ctrl-C.

Library modules are imported inside the commands that use them: ``--help`` and the parser must
not pay for zenoh, lxml and cryptography (start time).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import itertools
import json
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from cmion_mesh import __version__, keys
from cmion_mesh.errors import ConfigError, ExitCode, MeshError, exit_code
from cmion_mesh.signals import Stopper
from cmion_mesh.transport.base import TransportConfig

#: How long a daemon that can find others looks for the rest of the mesh before it claims its name.
JOIN_WINDOW = 1.0
#: After the first Ctrl-C, how long ``act`` waits for the cancelled outcome.
CANCEL_WAIT = 10.0
STORE_LABELS = {keys.BLACKBOARD: "blackboard", keys.WORLD_MODEL: "world model"}
NO_WAIT_ON_OPEN = ("open/return_conditions/connect_scouted", "false")


# --- the session every mesh command opens ---------------------------------------------------------


def transport_config(args: argparse.Namespace, name: str | None = None) -> TransportConfig:
    """The session settings from the common options; ``--certs`` turns them into mutual TLS with
    access control for identity ``--identity`` or ``name`` (see docs/security.md)."""
    config = TransportConfig(
        connect=tuple(args.connect or ()),
        listen=tuple(args.listen or ()),
        config_file=args.config,
        multicast=not args.no_multicast,
        multicast_interface=args.multicast_interface,
        lease_ms=getattr(args, "lease_ms", None),
    )
    if not args.certs:
        return config
    from cmion_mesh.transport import security  # only with --certs: cryptography costs start time

    return security.apply(config, certs_dir=args.certs, mesh=args.mesh, identity=args.identity, name=name,
                          verify_names=args.verify_names)


@contextlib.contextmanager
def session(args: argparse.Namespace, name: str | None = None) -> Iterator[Any]:
    """A zenoh session and a ``MeshClient`` on it, both closed on the way out."""
    from cmion_mesh.client import MeshClient
    from cmion_mesh.transport.zenoh import ZenohTransport

    config = transport_config(args, name)
    # zenoh's open would wait up to its scouting delay (0.5 s) for the peers it scouts; the client's
    # join waits for exactly what the command needs instead.
    config = dataclasses.replace(config, overrides=(*config.overrides, NO_WAIT_ON_OPEN))
    with ZenohTransport(config) as transport, MeshClient(transport, args.mesh) as client:
        yield client


def join_window(args: argparse.Namespace) -> float:
    """How long ``up`` looks for the rest of the mesh: none when it cannot find anyone by itself
    (no scouting, no endpoint to connect to, no zenoh file that could name one)."""
    return JOIN_WINDOW if (not args.no_multicast or args.connect or args.config) else 0.0


def _common(parser: argparse.ArgumentParser, *, json_output: bool = True) -> None:
    group = parser.add_argument_group("mesh")
    group.add_argument("--mesh", default=keys.DEFAULT_MESH, help="deployment name (default: %(default)s)")
    _zenoh_options(group, connect="zenoh endpoint to connect to, e.g. tcp/10.0.0.5:7447",
                   listen="zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447", config="zenoh JSON5 configuration file",
                   no_multicast="do not scout for peers by multicast",
                   multicast_interface="interface to scout on (default: zenoh's choice)")
    group.add_argument("--certs", metavar="DIR",
                       help="certificates folder (cmion-mesh certs): speak zenoh over mutual TLS only, with access control")
    group.add_argument("--identity", metavar="NAME",
                       help="which certificate of DIR to use (default: the embodiment's name where the command has one)")
    group.add_argument("--verify-names", action="store_true",
                       help="with --certs: also check that a peer's certificate names the address dialled (SANs)")
    if json_output:
        _json(parser)


def _zenoh_options(group: Any, **helps: str) -> None:
    """``--connect``, ``--listen``, ``--config``, ``--no-multicast``, ``--multicast-interface``, each
    with the help text given by its name (``no_multicast=...``)."""
    specs: dict[str, dict[str, Any]] = {
        "connect": {"action": "append", "metavar": "ENDPOINT"},
        "listen": {"action": "append", "metavar": "ENDPOINT"},
        "config": {"metavar": "FILE"},
        "no_multicast": {"action": "store_true"},
        "multicast_interface": {"metavar": "IFACE"},
    }
    for name, spec in specs.items():
        group.add_argument("--" + name.replace("_", "-"), help=helps[name], **spec)


def _json(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="machine-readable output (JSON)")


def _timeout(parser: argparse.ArgumentParser, default: float, what: str) -> None:
    parser.add_argument("--timeout", type=float, default=default, metavar="SECONDS", help=f"{what} (default: %(default)s s)")


def _join_timeout(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--join-timeout", "--discover-timeout", dest="join_timeout", type=float, default=5.0, metavar="SECONDS",
                        help="how long to wait for the embodiment to be found in the mesh (default: %(default)s s)")


def parse_value(text: str, as_string: bool) -> Any:
    """CLI values are JSON when they parse as JSON (``3``, ``true``, ``[1,2]``), else plain strings."""
    if as_string:
        return text
    import msgspec

    try:
        return msgspec.json.decode(text)
    except msgspec.DecodeError:
        return text


def to_builtins(value: Any) -> Any:
    """A message as JSON-ready data (``--json`` output)."""
    import msgspec  # imported when a command prints: `up` opens its session before it loads msgspec

    return msgspec.to_builtins(value)


def _print_entries(entries: dict[str, Any], prefix: str, as_json: bool) -> None:
    from cmion_mesh.messages import Container, Property

    if as_json:
        print(json.dumps({k: to_builtins(v) for k, v in entries.items()}))
        return
    width = max(len(k[len(prefix):]) for k in entries) if entries else 0
    for key, entry in entries.items():
        short = key[len(prefix):] or "/"
        if isinstance(entry, Property):
            flag = "  (persistent)" if entry.persistent else ""
            print(f"{short:<{width}}  = {json.dumps(entry.value)}{flag}")
        elif isinstance(entry, Container):
            print(f"{short:<{width}}  [{entry.kind}]")


# --- blackboard and world model -------------------------------------------------------------------


def cmd_store(args: argparse.Namespace) -> int:
    from cmion_mesh.messages import RemoveContainer, RemoveProperty
    from cmion_mesh.requests import require_accepted

    store = args.store
    stop = Stopper() if args.action == "watch" else None  # before any thread starts
    with session(args) as client:
        client.join(args.embodiment, timeout=args.timeout)
        container, _, name = args.path.rpartition("/") if args.path else ("", "", "")
        prefix = keys.storage_key(args.mesh, args.embodiment, store, ()) + "/"
        where = f"{args.embodiment}'s {STORE_LABELS[store]}"
        if args.action in ("get", "tree"):
            entries = client.lookup(args.embodiment, store, args.path or "", below=args.action == "tree", timeout=args.timeout)
            _print_entries(entries, prefix, args.json)
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
                print(json.dumps({"key": key, "entry": to_builtins(entry)}), flush=True)
            elif entry is None:
                print(f"- {short}", flush=True)
            else:
                _print_entries({key: entry}, prefix, False)
                sys.stdout.flush()

        with client.watch(f"{base}/**", show):
            stop.wait()
        return ExitCode.OK


# --- the daemon -----------------------------------------------------------------------------------


def resolve_config(path: str) -> str:
    """``up`` takes a configuration file, a folder holding ``ArchitectureConfiguration.xml``, or the
    name of a shipped embodiment (``robot``, ``screen``, ``phone``, ``cmion_test``, ``ros_robot``)."""
    from cmion_mesh.resources import data_dir

    candidate = Path(path)
    if candidate.is_dir():
        candidate = candidate / "ArchitectureConfiguration.xml"
    elif not candidate.exists() and "/" not in path:
        shipped = data_dir("embodiments") / path / "ArchitectureConfiguration.xml"
        if shipped.exists():
            candidate = shipped
    if not candidate.is_file():
        shipped_names = sorted(p.name for p in data_dir("embodiments").iterdir() if p.is_dir())
        raise ConfigError(f"no architecture configuration at {path!r} (a file, a folder holding ArchitectureConfiguration.xml, "
                          f"or a shipped embodiment: {', '.join(shipped_names)})")
    return str(candidate)


def admit(args: argparse.Namespace) -> dict[str, bytes | None] | None:
    """``--admit NAME[=PUBLICKEY]``: which companions may migrate in (default: any)."""
    from cmion_mesh.migration.signing import decode_public

    if not args.admit:
        return None
    out: dict[str, bytes | None] = {}
    for item in args.admit:
        name, _, key = item.partition("=")
        out[keys.check_name(name, "companion")] = decode_public(key) if key else None
    return out


def _existing(path: str | None, option: str) -> str | None:
    if path is not None and not Path(path).is_file():
        raise ConfigError(f"{option}: no such file", path=path)
    return path


def cmd_up(args: argparse.Namespace) -> int:
    # Only what it takes to know the name and the endpoints is imported before the mesh is joined:
    # the rest is imported and built while the mesh answers the name claim (``presence.Joining``).
    from cmion_mesh.diagnostics import Diagnostics
    from cmion_mesh.migration import devices

    stop = Stopper()
    rules, library, world_model = (_existing(args.rules, "--rules"), _existing(args.library, "--library"),
                                   _existing(args.world_model, "--world-model"))
    components: list[Component] = []
    companion, admitted = args.companion, admit(args)
    # The checks of `validate`, every problem reported: refuse on errors, start with warnings.
    found = Diagnostics()
    arch = None
    # The device table (migration/devices.py) is read before the session opens: it names the embodiment,
    # its endpoints and the companion's birth; options given on the command line win over it.
    if args.path:
        from cmion_mesh.body.architecture import read_architecture

        arch = read_architecture(resolve_config(args.path), found, name=args.name)
        if arch is None:
            found.raise_if_errors()
        assert arch is not None
        # Files given on the command line replace the configuration's own.
        rules = rules or (str(arch.rules) if arch.rules else None)
        library = library or (str(arch.library) if arch.library else None)
        world_model = world_model or (str(arch.world_model) if arch.world_model else None)
        table = devices.table_for_library(library, found) if library else None
        try:
            name = args.name or devices.embodiment_name(table, arch)
        except ConfigError as exc:
            found.problem(exc)
            name = arch.embodiment
        companion = companion or devices.birth(table, arch.companion)
        admitted = arch.admit if admitted is None else {**(arch.admit or {}), **admitted}
    else:
        table = devices.table_for_library(library, found) if library else None
        name = args.name or (table.name if table is not None else None)
        if not name and not found.errors:  # else the table's problems say why it has none
            raise ConfigError("give an architecture configuration (PATH) or at least --name")
        companion = companion or devices.birth(table, None)
    if table is not None:
        filled = devices.with_table_endpoints(TransportConfig(connect=tuple(args.connect or ()), listen=tuple(args.listen or ()),
                                                              config_file=args.config), table)
        args.connect, args.listen = list(filled.connect), list(filled.listen)
    with contextlib.ExitStack() as joining_stack:
        joined = None
        if name and not found.errors and keys.is_name(name) and keys.is_name(args.mesh):
            joined = _join(args, name, joining_stack)
        from cmion_mesh.body.embodiment import Embodiment
        from cmion_mesh.body.validate import check_embodiment, render
        from cmion_mesh.ion import Component
        from cmion_mesh.statedir import default_state_dir

        ruleset, competencies = check_embodiment(rules, library, world_model, remote_types=args.remote_type or (), diagnostics=found,
                                                 check_types=arch is None or library is not None)
        if arch is not None:
            components = arch.build_components(found)
        for item in found:
            print(render(item), file=sys.stderr, flush=True)
        if found.errors:
            return ExitCode.USAGE
        state = args.state_dir or str(default_state_dir(args.mesh, name))
        pages = contextlib.ExitStack()
        web = _web_bodies(args, components)
        with pages:
            # Pages are served before the embodiment is announced: an address in use is refused before
            # anything but the name claim is on the mesh.
            for body in web:
                pages.enter_context(body)
            joining_stack.pop_all()  # from here on the embodiment owns the session and the claim
            embodiment = Embodiment(name, mesh=args.mesh, transport_config=None if joined else transport_config(args, name),
                                    world_model_init=world_model, rules=ruleset, competencies=competencies,
                                    components=components, state_dir=state, companion=companion, admit=admitted,
                                    joined=joined, devices=table)
            _run_daemon(args, embodiment, table, companion, state, stop, web)
    left = [t.name for t in threading.enumerate() if t is not threading.main_thread() and t.is_alive()]
    if left:
        print(f"embodiment {embodiment.name!r} stopped, but threads are still running: {', '.join(left)}", flush=True)
        return ExitCode.FAILED
    print(f"embodiment {embodiment.name!r} stopped cleanly (no thread left)", flush=True)
    sys.stderr.flush()
    # Said only when it is true: everything is closed and on disk, so leave now rather than let
    # the interpreter's finalization (zenoh's runtime among it) keep the process alive after it.
    os._exit(ExitCode.OK)


def _join(args: argparse.Namespace, name: str, stack: contextlib.ExitStack) -> Any:
    """The daemon's session, opened now, and its name claim under way on it (``presence.Joining``);
    ``stack`` closes both unless the embodiment takes them (``pop_all``)."""
    from cmion_mesh.claim import Joining
    from cmion_mesh.transport.zenoh import ZenohTransport

    transport = stack.enter_context(ZenohTransport(transport_config(args, name)))
    return stack.enter_context(Joining(transport, args.mesh, name, window=join_window(args)))


def _web_bodies(args: argparse.Namespace, components: list[Any]) -> list[Any]:
    """The web bodies to serve: the configuration's ``WebBody`` components, and ``--web``'s address
    (replacing the configuration's first one, or adding one)."""
    if not args.web and "cmion_mesh.web.body" not in sys.modules:
        return []  # starlette and uvicorn cost start time: imported only for a page
    from cmion_mesh.web.body import WebBody
    from cmion_mesh.web.server import parse_bind

    bodies = [c for c in components if isinstance(c, WebBody)]
    if args.web:
        host, port = parse_bind(args.web)
        if bodies:
            bodies[0].host, bodies[0].port = host, port
        else:
            bodies.append(WebBody(args.web))
            components.append(bodies[-1])
    if args.certs:
        import secrets

        # An authenticated mesh: what a page senses becomes world-model writes, so only the holder
        # of the printed address (its key) may act there; others may watch.
        for body in bodies:
            body.key = body.key or secrets.token_urlsafe(18)
    return bodies


def _run_daemon(args: argparse.Namespace, embodiment: Any, table: Any, companion: str | None, state: str, stop: Stopper,
                web: list[Any]) -> None:
    from cmion_mesh.transport import security

    name = embodiment.name
    with embodiment:
        mode = security.describe(certs_dir=args.certs, identity=args.identity, name=embodiment.name)
        print(mode, file=sys.stderr if mode.startswith("plain") else sys.stdout, flush=True)
        if args.no_multicast and not args.connect and not args.listen:
            print("warning: no multicast and no endpoints: no peer can find this embodiment", file=sys.stderr)
        if table is not None:
            print(f"device table {table.path}: embodiment {name!r}, knows {', '.join(table.names) or 'no device'}; "
                  f"listen {', '.join(args.listen) or '-'}; connect {', '.join(args.connect) or '-'}"
                  + (f"; companion {companion!r} born here" if companion and table.born_here else ""), flush=True)
        if embodiment.companion_elsewhere:
            print(f"companion {companion!r} already lives on {embodiment.companion_elsewhere!r}: it is not born here",
                  file=sys.stderr, flush=True)
        standins = embodiment.standins()
        if standins:
            print(f"stand-ins, reported unavailable (see docs/portmap.md): {len(standins)}", flush=True)
            for s in standins:
                typed = f"; types {', '.join(s['types'])}" if s.get("types") else ""
                print(f"  {s['class']} ({s['kind']}{typed}) at {s['where']}", flush=True)
        for body in web:
            print(f"web body of {embodiment.name!r} at {body.address} (senses: {', '.join(body.snapshot()['senses']) or 'none'}"
                  + ("; without its key the page only watches)" if body.key else ")"), flush=True)
        print(f"embodiment {embodiment.name!r} up in mesh {args.mesh!r} (zenoh id {embodiment.transport.id}; "
              f"{len(embodiment.execution.competencies)} competencies, {len(embodiment.rules.rules)} rules; state {state})",
              flush=True)
        stop.wait()


def _serve(args: argparse.Namespace, base: type[Any], what: str) -> int:
    """Host a component built from ``CLASS --parameters`` for ``--embodiment`` until stopped, and say
    while that embodiment is not alive (the component then serves nobody)."""
    from cmion_mesh.body.remote import CompetencyHost
    from cmion_mesh.classes import construct, split_parameters
    from cmion_mesh.client import alive_list, did_you_mean
    from cmion_mesh.competency import Competency
    from cmion_mesh.ion import serve

    built = construct(args.cls, base, split_parameters(args.parameters))
    component = CompetencyHost(built) if isinstance(built, Competency) else built
    stop = Stopper()
    target = keys.check_name(args.embodiment, "embodiment")
    with session(args, target) as client, serve(component, embodiment=target, transport=client.transport, mesh=args.mesh):
        print(f"{what} {built.name!r} serving embodiment {target!r}", flush=True)

        def on_change(name: str, alive: bool) -> None:
            if name == target:
                print(f"embodiment {target!r} is alive: serving it" if alive else
                      f"warning: embodiment {target!r} left the mesh: this {what} serves nobody until it is back",
                      file=sys.stderr, flush=True)

        presence = client.presence
        with presence.listen(on_change):
            if not presence.wait(lambda alive: target in alive, JOIN_WINDOW):
                alive = presence.alive()
                print(f"warning: embodiment {target!r} is not alive in mesh {args.mesh!r} (alive: {alive_list(alive)})"
                      f"{did_you_mean(target, alive)}: this {what} serves nobody until it starts", file=sys.stderr, flush=True)
            stop.wait()
    return ExitCode.OK


def cmd_serve_competency(args: argparse.Namespace) -> int:
    from cmion_mesh.competency import Competency

    return _serve(args, Competency, "competency")


def cmd_serve_mind(args: argparse.Namespace) -> int:
    from cmion_mesh.mind import Mind

    return _serve(args, Mind, "mind")


# --- one-shot commands ----------------------------------------------------------------------------


def cmd_peers(args: argparse.Namespace) -> int:
    from cmion_mesh.client import mesh_problems

    with session(args) as client, Spinner("looking for embodiments", enabled=not args.json):
        peers = client.describe_all(timeout=args.timeout)
    for problem in mesh_problems(peers):
        print(f"warning: {problem}", file=sys.stderr)
    if args.json:
        print(json.dumps(peers))
        return ExitCode.OK
    if not peers:
        print(f"(no embodiments found in mesh {args.mesh!r} within {args.timeout:g} s: try `cmion-mesh doctor`)")
        return ExitCode.OK
    rows: list[tuple[str, ...]] = [("EMBODIMENT", "INHABITANT", "COMPETENCY TYPES", "ACTIONS", "VERSION", "UP SINCE")]
    for p in peers:
        since = time.strftime("%H:%M:%S", time.localtime(p.get("started_at", 0))) if p.get("started_at") else "?"
        if p.get("error"):
            rows.append((p["name"], "?", f"({p['error']})", "", "", ""))
            continue
        frozen = [f"{c} (FROZEN: custody fork)" for c, r in (p.get("custody") or {}).items() if isinstance(r, dict) and r.get("frozen")]
        rows.append((p["name"], p.get("inhabitant") or ", ".join(frozen) or "-", ",".join(p.get("competency_types", [])) or "-",
                     "; ".join(p.get("actions", [])) or "-", p.get("version", "?"), since))
    _table(rows)
    return ExitCode.OK


def _table(rows: Sequence[tuple[str, ...]]) -> None:
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
    from cmion_mesh.requests import require_accepted

    stop = Stopper()  # Ctrl-C is collected by the main thread, whichever thread the signal reaches
    with session(args) as client:
        run = client.start_action(args.embodiment, args.action, args.parameters, subject=args.subject, action_id=args.id or "",
                                  deadline=args.deadline, join_timeout=args.join_timeout, on_end=stop.stop)
        with run:
            if args.detach:
                print(json.dumps({"action_id": run.action_id, "status": "running"}) if args.json else
                      f"{run.action_id} running on {args.embodiment} (cmion-mesh cancel {args.embodiment} {run.action_id})")
                return ExitCode.OK
            deadline = time.monotonic() + args.timeout
            interrupts = 0
            with Spinner(f"{args.embodiment}: {' '.join([args.action, *args.parameters])}", enabled=not args.json):
                for _ in range(1000):  # bounded: each round ends on the outcome, a signal or the deadline
                    left = deadline - time.monotonic()
                    if run.ended.is_set() or left <= 0:
                        break
                    if stop.wait(left) is None:
                        continue
                    interrupts += 1
                    if interrupts > 1:
                        print(f"left without waiting: action {run.action_id} may still be running on {args.embodiment} "
                              f"(cmion-mesh cancel {args.embodiment} {run.action_id})", file=sys.stderr)
                        return ExitCode.INTERRUPTED
                    print(f"cancelling {run.action_id} (Ctrl-C again to leave without waiting)", file=sys.stderr, flush=True)
                    key = keys.request_key(args.mesh, args.embodiment, "manager", "cancel")
                    require_accepted(client.cancel(args.embodiment, run.action_id), key)
                    deadline = min(deadline, time.monotonic() + CANCEL_WAIT)
            report = run.result(args.timeout)
    if args.json:
        print(json.dumps(to_builtins(report)))
    else:
        extra = f": {report.reason}" if report.reason else ""
        print(f"{report.action_id} {report.status}{extra}" + (f" (rule {report.rule})" if report.rule else ""))
    return {"succeeded": ExitCode.OK, "cancelled": ExitCode.CANCELLED}.get(report.status, ExitCode.FAILED)


def cmd_cancel(args: argparse.Namespace) -> int:
    from cmion_mesh.requests import require_accepted

    with session(args) as client:
        client.join(args.embodiment, timeout=args.join_timeout)
        key = keys.request_key(args.mesh, args.embodiment, "manager", "cancel")
        require_accepted(client.cancel(args.embodiment, args.action_id), key)
    print(json.dumps({"action_id": args.action_id, "cancel": "accepted"}) if args.json else f"cancel of {args.action_id} accepted")
    return ExitCode.OK


def cmd_events(args: argparse.Namespace) -> int:
    from cmion_mesh.messages import Event

    stop = Stopper()
    lock = threading.Lock()
    seen = [0]

    def show(event: Event) -> None:
        with lock:  # exactly --count events, however many arrive before the main thread stops
            if args.count and seen[0] >= args.count:
                return
            seen[0] += 1
            if args.json:
                print(json.dumps(to_builtins(event)), flush=True)
            else:
                stamp = time.strftime("%H:%M:%S", time.localtime(event.time)) + f".{int(event.time * 1000) % 1000:03d}"
                data = json.dumps(event.data) if event.data is not None else ""
                print(f"{stamp} {event.embodiment}/{event.component} {event.name} {data}", flush=True)
            if args.count and seen[0] == args.count:
                stop.stop()

    with session(args) as client, client.events(show, embodiment=args.embodiment, component=args.component, event=args.event):
        if args.embodiment != "*":
            client.join(args.embodiment, timeout=args.join_timeout)
        else:
            client.presence.wait(bool, args.join_timeout)
        if not args.json:
            print(f"following events of {args.embodiment}/{args.component}/{args.event} in mesh {args.mesh!r} (Ctrl-C to stop)",
                  file=sys.stderr, flush=True)
        deadline = time.monotonic() + args.duration if args.duration else None
        for _ in range(1_000_000):  # bounded; each round ends on a signal, the count or the duration
            left = None if deadline is None else deadline - time.monotonic()
            if (left is not None and left <= 0) or stop.wait(left) is not None:
                break
            with lock:
                if args.count and seen[0] >= args.count:
                    break
    return ExitCode.OK


def cmd_record(args: argparse.Namespace) -> int:
    if args.filters[:1] == ["info"]:
        return _record_info(args.filters[1:], args.json)
    from cmion_mesh.tools.recording import Recorder, parse_size

    if args.split_time is not None and args.split_time <= 0:
        raise ConfigError(f"--split-time {args.split_time:g} must be more than 0 seconds")
    stop = Stopper()  # before any thread starts
    output = args.output or f"cmion-{args.mesh}-{time.strftime('%Y%m%d-%H%M%S')}.mcap"
    split_bytes = parse_size(args.split_size) if args.split_size else 0
    with session(args) as client, Recorder(client.transport, args.mesh, output, filters=args.filters or (),
                                           split_bytes=split_bytes, split_seconds=args.split_time or 0.0,
                                           overwrite=args.force) as recorder:
        # Join before saying we record: the daemons' answers to describe come after they learnt of
        # this session's subscriptions (one link, in order), and describe what they are, in the file.
        alive: list[str] = []
        if client.presence.wait(bool, args.join_timeout):
            described = client.describe_all(timeout=args.join_timeout)
            recorder.describe(described)
            alive = sorted({str(d.get("name")) for d in described})
        print(f"recording mesh {args.mesh!r} to {recorder.stats.files[0]} (alive: {', '.join(alive) or 'none yet'}; "
              "Ctrl-C to stop)", file=sys.stderr, flush=True)
        deadline = time.monotonic() + args.duration if args.duration else None
        for _ in range(1_000_000):  # bounded; each round ends on a signal or the duration
            left = None if deadline is None else deadline - time.monotonic()
            if (left is not None and left <= 0) or stop.wait(left) is not None:
                break
    stats = recorder.stats
    if args.json:
        print(json.dumps({"files": stats.files, "messages": stats.messages, "dropped": stats.dropped,
                          "embodiments": sorted(stats.embodiments)}))
    else:
        print(f"recorded {stats.messages} messages to {', '.join(stats.files)}"
              + (f"; DROPPED {stats.dropped} samples (the writer fell behind)" if stats.dropped else ""))
    return ExitCode.OK


def _record_info(files: list[str], as_json: bool) -> int:
    from cmion_mesh.tools.recording_reader import format_info, info

    if not files:
        raise ConfigError("record info: name the recording (cmion-mesh record info FILE.mcap)")
    summaries = [info(path) for path in files]
    if as_json:
        print(json.dumps(summaries[0] if len(summaries) == 1 else summaries))
    else:
        print("\n\n".join(format_info(s) for s in summaries))
    return ExitCode.OK


def cmd_replay(args: argparse.Namespace) -> int:
    from cmion_mesh.tools.replay import replay

    stop = Stopper()  # before any thread starts
    halt = threading.Event()
    outcome: dict[str, Any] = {}

    def run(client: Any) -> None:
        try:
            outcome["stats"] = replay(client, args.file, rate=args.rate, filters=args.filter or (), join_timeout=args.join_timeout,
                                      wait_for=args.wait_for or (), stop=halt,
                                      warn=lambda text: print(text, file=sys.stderr, flush=True))
        except BaseException as exc:
            outcome["error"] = exc
        finally:
            stop.stop()

    with session(args) as client:
        worker = threading.Thread(target=run, args=(client,), name="replay", daemon=True)
        worker.start()
        for _ in range(1_000_000):  # bounded; each round ends on a signal or the replay's end
            if stop.wait(1.0) is not None:
                halt.set()
            if not worker.is_alive():
                break
        worker.join()
    if "error" in outcome:
        raise outcome["error"]
    stats = outcome["stats"]
    if args.json:
        print(json.dumps(dataclasses.asdict(stats)))
    else:
        print(f"replayed {stats.published} events into mesh {args.mesh!r} in {stats.seconds:.2f} s"
              + (" (stopped)" if halt.is_set() else "")
              + (f"; {stats.undecodable} undecodable skipped" if stats.undecodable else "")
              + ("; the recording is truncated: replayed up to its last complete chunk" if stats.truncated else ""))
    return ExitCode.INTERRUPTED if halt.is_set() else ExitCode.OK


def _run_until(stop: Stopper, done: threading.Event, duration: float, every: float | None = None,
               tick: Callable[[], None] | None = None) -> None:
    """Wait for a signal, ``done`` or ``duration`` seconds (0: no limit), calling ``tick`` every ``every`` s."""
    now = time.monotonic()
    deadline = now + duration if duration else None
    next_tick = now + every if every else None
    for _ in range(10_000_000):  # bounded; each round ends on a signal, ``done``, a tick or the deadline
        now = time.monotonic()
        if done.is_set() or (deadline is not None and now >= deadline):
            return
        if next_tick is not None and tick is not None and now >= next_tick:
            tick()
            next_tick += every or 1.0
        ends = [t for t in (deadline, next_tick) if t is not None]
        if stop.wait(max(0.0, min(ends) - now) if ends else None) is not None:
            return


def cmd_hz(args: argparse.Namespace) -> int:
    from cmion_mesh.tools import hz_echo as tap

    if args.window < 1 or args.count < 0 or args.duration < 0:
        raise ConfigError("--window must be at least 1, --count and --duration at least 0")
    stop = Stopper()
    expression = tap.resolve(args.mesh, args.key)
    hz = tap.Hz(args.window, per_key=args.per_key)
    done = threading.Event()
    shown: dict[str, int] = {}

    def on_seen(seen: tap.Seen) -> None:
        if done.is_set():
            return
        if hz.add(seen, expression) >= (args.count or sys.maxsize):
            done.set()
            stop.stop()

    def report(final: bool = False) -> None:
        for name, stats in hz.report().items():
            if not final and shown.get(name) == stats["count"]:
                continue  # nothing new on it since the last report
            shown[name] = stats["count"]
            if args.json:
                print(json.dumps({"key": name, **stats, **({"final": True} if final else {})}), flush=True)
            else:
                print(tap.format_rate(name, stats, with_name=args.per_key or final), flush=True)

    with session(args) as client, tap.Tap(client.transport, expression, on_seen, liveliness=args.liveliness or None):
        print(f"rate of {expression} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        _run_until(stop, done, args.duration, 1.0, report)
    if not hz.report():
        print(f"error: fewer than two messages on {expression}: no rate", file=sys.stderr)
        return ExitCode.FAILED
    report(final=True)
    return ExitCode.OK


def cmd_echo(args: argparse.Namespace) -> int:
    from cmion_mesh.tools import hz_echo as tap

    if args.count < 0 or args.duration < 0:
        raise ConfigError("--count and --duration must be at least 0")
    stop = Stopper()
    expression = tap.resolve(args.mesh, args.key)
    printer = tap.Printer(as_json=args.json, raw=args.raw)
    count = 1 if args.once else args.count
    done = threading.Event()
    lock = threading.Lock()
    seen_so_far = [0]

    def on_seen(seen: tap.Seen) -> None:
        with lock:  # exactly --count, however many arrive before the main thread stops
            if done.is_set():
                return
            seen_so_far[0] += 1
            printer.show(seen)
            if count and seen_so_far[0] >= count:
                done.set()
                stop.stop()

    with session(args) as client, tap.Tap(client.transport, expression, on_seen, liveliness=args.liveliness or None):
        if not args.json:
            print(f"echo of {expression} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        _run_until(stop, done, args.duration)
    return ExitCode.OK


def cmd_view(args: argparse.Namespace) -> int:
    from cmion_mesh.web.server import WebServer, parse_bind
    from cmion_mesh.web.view import MeshView

    host, port = parse_bind(args.web)
    stop = Stopper()
    loopback = host in ("127.0.0.1", "::1", "localhost")
    with session(args) as client, MeshView(client, allow_actions=args.allow_actions, loopback=loopback) as view, \
            WebServer(view.app, host, port, name="view") as web:
        view.start(web.call_soon)
        mode = "actions allowed" if args.allow_actions else "read-only"
        print(f"view of mesh {args.mesh!r} at {web.url}/ ({mode}; Ctrl-C to stop)", flush=True)
        if args.allow_actions and not loopback:
            print(f"warning: anyone who reaches {web.url} may act on mesh {args.mesh!r}", file=sys.stderr, flush=True)
        stop.wait()
    return ExitCode.OK


def cmd_migrate(args: argparse.Namespace) -> int:
    with session(args) as client, Spinner(f"migrating {args.companion} to {args.to}", enabled=not args.json):
        result = client.migrate(args.companion, args.to, timeout=args.timeout)
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{args.companion} migrated from {result['source']} to {result['target']} (epoch {result['epoch']})")
    return ExitCode.OK


def cmd_custody(args: argparse.Namespace) -> int:
    companion = keys.check_name(args.companion, "companion")
    if args.custody_command == "resolve":
        keep = keys.check_name(args.keep, "embodiment")
        gone = [keys.check_name(name, "embodiment") for name in args.gone or ()]
        sender = "cmion-mesh"
        if args.certs:
            from cmion_mesh.transport import security

            sender = security.choose_identity(args.certs, args.identity)
        with session(args) as client, Spinner(f"resolving the fork of {companion}", enabled=not args.json):
            result = client.resolve_fork(companion, keep, force=args.force, gone=gone, sender=sender, timeout=args.timeout)
        if args.json:
            print(json.dumps(result))
        else:
            down = ", ".join(result["retired"]) or "nobody"
            print(f"{companion}: {down} stood down{' (gone: ' + ', '.join(result['gone']) + ')' if result['gone'] else ''}; "
                  f"it runs on {keep} again")
        return ExitCode.OK
    with session(args) as client, Spinner(f"asking the mesh about {companion}", enabled=not args.json):
        reports = client.custody(companion, timeout=args.timeout)
    forks = {f["description"]: f for report in reports.values() for f in report.get("forks") or ()}
    equivocators = sorted({str(e) for report in reports.values() for e in report.get("equivocators") or ()})
    branches: dict[str, dict[str, Any]] = {}
    for report in reports.values():
        branches.update(report.get("branches") or {})
    unreachable = sorted(h for h in branches if "error" in reports.get(h, {"error": "not alive"}))
    if args.json:
        print(json.dumps({"companion": companion, "reports": reports, "forks": list(forks.values()),
                          "equivocators": equivocators, "branches": branches, "unreachable": unreachable}))
        return ExitCode.OK
    rows: list[tuple[str, ...]] = [("EMBODIMENT", "STATE", "EPOCH", "CUSTODY")]
    for name, report in sorted(reports.items()):
        if "error" in report:
            rows.append((name, "?", "", f"({report['error']})"))
        elif report:
            held = "FROZEN: fork" if report.get("frozen") else "runs it" if report.get("state") == "active" else "in a migration"
            rows.append((name, str(report.get("state")), str(report.get("epoch")), held))
        else:
            rows.append((name, "-", "", ""))
    for name in unreachable:
        rows.append((name, "?", str(branches[name].get("epoch", "")), "holds a branch: NOT REACHABLE"))
    _table(rows)
    if not forks:
        print(f"no fork of {companion}'s chain of custody is reported")
        return ExitCode.OK
    for fork in forks.values():
        print(f"fork at epoch {fork['epoch']}: {fork['description']}")
    for name, info in sorted(branches.items()):
        held = f"; the equivocator {', '.join(map(repr, info.get('equivocators') or ()))} holds it" if info.get("equivocators") else ""
        print(f"  branch of {name}: epoch {info.get('epoch')}{held}")
    if equivocators:
        print(f"equivocated: {', '.join(map(repr, equivocators))}: revoke with `cmion-mesh certs revoke PKI NAME` "
              "(then give the members the new trust.json and restart them)")
    keepable = sorted(h for h, info in branches.items() if not info.get("equivocators"))
    print(f"resolve: cmion-mesh custody resolve {companion} --keep EMBODIMENT "
          f"({'e.g. ' + ', '.join(keepable) if keepable else 'every branch holds an equivocator: --force'}); "
          "every other branch holder stands down first")
    return ExitCode.OK


def cmd_invite(args: argparse.Namespace) -> int:
    with session(args) as client, Spinner(f"{args.embodiment} invites the companion", enabled=not args.json):
        result = client.invite(args.embodiment, args.to or (), timeout=args.timeout)
    if args.json:
        print(json.dumps(result))
    else:
        hosts = ", ".join(result["accepted_by"])
        print(f"invitation from {args.embodiment} accepted by {hosts}: the companion's mind got "
              f"MigrationInvitation {args.embodiment} (`cmion-mesh peers` shows whether it comes)")
    return ExitCode.OK


def cmd_doctor(args: argparse.Namespace) -> int:
    from cmion_mesh.tools.doctor import run_doctor

    return run_doctor(transport_config(args), mesh=args.mesh, timeout=args.timeout, as_json=args.json)


def cmd_validate(args: argparse.Namespace) -> int:
    from cmion_mesh.body.validate import FileReport, expand, render, validate_paths

    reports: list[FileReport] = []
    paths: list[str] = []
    for given in args.files:
        try:
            paths += expand(given)
        except ConfigError as exc:
            failed = FileReport(given)
            failed.diagnostics.problem(exc)
            reports.append(failed)
    reports += validate_paths(paths, remote_types=args.remote_type or ())
    strict = bool(args.strict)
    if args.json:
        out = []
        for r in reports:
            entry: dict[str, Any] = {"path": r.path, "ok": r.ok(strict), "kind": r.kind,
                                     "diagnostics": [d.as_dict() for d in r.diagnostics]}
            if r.checked_with:
                entry["checked_with"] = r.checked_with
            failing = [str(d) for d in r.diagnostics if d.severity == "error" or (strict and d.severity == "warning")]
            if failing:
                entry["error"] = "\n".join(failing)
            out.append(entry)
        print(json.dumps(out))
    else:
        for r in reports:
            if r.ok(strict):
                counts = [f"{n} {word}{'s' if n > 1 else ''}" for word, n in
                          (("warning", len(r.diagnostics.warnings)), ("note", len(r.diagnostics.of("info")))) if n]
                print(f"ok: {r.path} ({r.kind}{', ' if counts else ''}{', '.join(counts)})")
            for item in r.diagnostics:
                print(render(item, strict=strict), file=sys.stderr)
        totals = {s: sum(len(r.diagnostics.of(s)) for r in reports) for s in ("error", "warning", "info")}
        if totals["error"] or totals["warning"]:
            failed_files = sum(not r.ok(strict) for r in reports)
            print(f"{len(reports)} files: {failed_files} failed; {totals['error']} errors, {totals['warning']} warnings"
                  f"{' (errors with --strict)' if strict and totals['warning'] else ''}", file=sys.stderr)
    return ExitCode.OK if all(r.ok(strict) for r in reports) else ExitCode.FAILED


def cmd_demo(args: argparse.Namespace) -> int:
    from cmion_mesh.signals import Interrupter

    stop = Interrupter()  # before any thread: interrupted or terminated, the demo still stops its daemons
    from cmion_mesh.tools.demo import run_demo

    return run_demo(mesh=args.mesh, web=args.web, wait=stop.wait, record=args.record)


def cmd_launch(args: argparse.Namespace) -> int:
    from cmion_mesh.tools import launch, launcher

    plan = launch.load(launch.resolve_file(args.file), mesh=args.mesh)
    if args.check:
        described = launch.describe(plan)
        if args.json:
            print(json.dumps({"file": str(plan.path), "mesh": plan.mesh, "network": plan.network, "processes": described}))
            return ExitCode.OK
        print(f"ok: {plan.path}: {len(described)} processes in mesh {plan.mesh!r} (on_failure {plan.on_failure}; "
              f"network {plan.network}{', ports chosen at each start' if plan.network == 'loopback' else ''})")
        for item in described:
            after = f" after {', '.join(item['after'])}" if item["after"] else ""
            ready = f", ready at a line with {item['ready']!r}" if item["ready"] else ""
            print(f"  {item['name']} ({item['kind']}{after}{ready}): {' '.join(item['command'])}")
        return ExitCode.OK
    stop = Stopper()  # before any thread: the launcher collects Ctrl-C and SIGTERM itself, then stops its children
    return launcher.Launcher(plan, stop).run()


def cmd_router(args: argparse.Namespace) -> int:
    from cmion_mesh.tools.router import DEFAULT_LISTEN, RouterOptions, run

    options = RouterOptions(listen=tuple(args.listen or (DEFAULT_LISTEN,)), connect=tuple(args.connect or ()),
                            config_file=args.config, multicast=not args.no_multicast, multicast_interface=args.multicast_interface,
                            lans=None if args.no_lans else tuple(args.lan or ()))
    return run(options)


def cmd_certs(args: argparse.Namespace) -> int:
    from cmion_mesh.transport import certs, security

    directory = Path(args.dir)
    command = args.certs_command
    if command == "init":
        ca = certs.init(directory, label=args.label, days=args.days, force=args.force)
        print(f"authority created: {ca} (keep {directory / certs.CA_KEY} with the administrator only)")
        print(f"next: cmion-mesh certs issue {directory} <embodiment>")
    elif command == "issue":
        cert, key = certs.issue(directory, args.name, sans=args.san, role=args.role, trust=not args.no_trust,
                                days=args.days, force=args.force, unrevoke=args.unrevoke)
        trusted = "not in the trust list" if args.no_trust else f"trusted as {args.role}"
        print(f"issued {cert} and {key} for {args.name!r} ({trusted})")
        print(f"give the member {directory / certs.CA_CERT}, {directory / certs.TRUST_FILE}, {cert.name} and {key.name}; "
              f"start it with --certs DIR")
    elif command == "list":
        infos = certs.inventory(directory)
        if args.json:
            print(json.dumps([info.__dict__ for info in infos]))
            return ExitCode.OK
        rows = [("NAME", "ROLE", "SIGNED BY CA", "EXPIRES", "KEY", "SANS")]
        for i in infos:
            rows.append((i.name, "(REVOKED)" if i.revoked else i.role or "(not trusted)", "yes" if i.issued_by_ca else "NO",
                         i.not_after + (" (EXPIRED)" if i.expired else ""), "yes" if i.key_present else "-", ",".join(i.sans)))
        _table(rows)
        missing = sorted(set(certs.Trust.load(directory).names) - {i.name for i in infos})
        if missing:
            print(f"trusted but without a certificate here: {', '.join(missing)}")
    elif command == "trust":
        certs.trust_name(directory, args.name, args.role, unrevoke=args.unrevoke)
        print(f"{args.name!r} trusted as {args.role}")
    elif command == "revoke":
        certs.revoke_name(directory, args.name, args.reason)
        print(f"{args.name!r} revoked: out of the trust list, and `certs trust` will not add it back unless told "
              f"(--unrevoke); give the members the new {certs.TRUST_FILE} and restart them for it to take effect")
    elif command == "untrust":
        certs.untrust_name(directory, args.name)
        print(f"{args.name!r} removed from the trust list: restart the mesh's members for it to take effect")
    else:
        text = security.config_json5(directory, args.name, args.mesh, listen=args.listen, connect=args.connect,
                                     multicast=not args.no_multicast, verify_names=args.verify_names)
        if args.output:
            certs.write_file(Path(args.output), text.encode(), private=False, overwrite=True)
        else:
            print(text)
    return ExitCode.OK


# --- the parser -----------------------------------------------------------------------------------


def _store_parsers(sub: Any) -> None:
    for store, label in STORE_LABELS.items():
        sp = sub.add_parser(store, help=f"read, write and watch an embodiment's {label}",
                            description=f"Read, write and watch an embodiment's {label}. Paths are container/.../property"
                                        + ("; entity.property (as $WM(...) writes it) works too." if store == keys.WORLD_MODEL else "."))
        actions = sp.add_subparsers(dest="action", required=True, metavar="ACTION")
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
            _timeout(ap, 5.0, "seconds to wait for the embodiment and its answer")
            _common(ap)
            ap.set_defaults(func=cmd_store, store=store)


def _certs_parsers(parser: argparse.ArgumentParser) -> None:
    from cmion_mesh.transport.certs import CA_DAYS, CERT_DAYS, DEFAULT_SANS, ROLES

    sub = parser.add_subparsers(dest="certs_command", required=True, metavar="COMMAND")
    folder = "the certificates folder"
    p = sub.add_parser("init", help="create the certificate authority and an empty trust list in DIR")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("--label", help="what the authority's name says (default: the folder's name)")
    p.add_argument("--days", type=int, default=CA_DAYS, help="validity (default: %(default)s days)")
    p.add_argument("--force", action="store_true", help="replace an existing authority (every certificate must then be reissued)")

    p = sub.add_parser("issue", help="issue the certificate of an embodiment (or operator) NAME and trust it")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("name", metavar="NAME", help="embodiment name (the certificate's common name)")
    p.add_argument("--san", action="append", default=[], metavar="HOST_OR_IP",
                   help="a DNS name or IP address the embodiment is reached at; repeatable "
                        f"(always added: the name itself, {', '.join(DEFAULT_SANS)})")
    p.add_argument("--role", choices=ROLES, default="embodiment",
                   help="embodiment: its own keys only; operator: the whole mesh (tools of an administrator)")
    p.add_argument("--no-trust", action="store_true", help="do not add NAME to the trust list")
    p.add_argument("--unrevoke", action="store_true", help="trust NAME although it was revoked")
    p.add_argument("--days", type=int, default=CERT_DAYS, help="validity (default: %(default)s days)")
    p.add_argument("--force", action="store_true", help="replace an existing certificate of NAME")

    p = sub.add_parser("list", help="list the certificates in DIR, whether the authority signed them and who is trusted")
    p.add_argument("dir", metavar="DIR", help=folder)
    _json(p)

    p = sub.add_parser("trust", help="add NAME to the trust list (its certificate must already exist)")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("name", metavar="NAME", help="the certificate's name")
    p.add_argument("--role", choices=ROLES, default="embodiment", help="what NAME may do (default: %(default)s)")
    p.add_argument("--unrevoke", action="store_true", help="trust NAME although it was revoked (certs revoke)")

    p = sub.add_parser("revoke", help="revoke NAME: out of the trust list, recorded as revoked so that trust and issue do "
                                      "not add it back; the access control never admits it (restart the members)")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("name", metavar="NAME", help="the certificate's name")
    p.add_argument("--reason", default="", help="why (kept in the trust list), e.g. 'equivocated custody of spirit'")

    p = sub.add_parser("untrust", help="remove NAME from the trust list (revocation: restart the members afterwards)")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("name", metavar="NAME", help="the certificate's name")

    p = sub.add_parser("config", help="print the zenoh JSON5 configuration of NAME (mTLS + access control), e.g. "
                                      "for a client written in another language")
    p.add_argument("dir", metavar="DIR", help=folder)
    p.add_argument("name", metavar="NAME", help="whose configuration")
    p.add_argument("--mesh", default=keys.DEFAULT_MESH, help="deployment name (default: %(default)s)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help="endpoint to listen on; repeatable")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="endpoint to connect to; repeatable")
    p.add_argument("--no-multicast", action="store_true", help="turn multicast scouting off in the file")
    p.add_argument("--verify-names", action="store_true", help="check the peer's address against its certificate's SANs")
    p.add_argument("-o", "--output", metavar="FILE", help="write to FILE instead of standard output")


def _router_parser(parser: argparse.ArgumentParser) -> None:
    from cmion_mesh.tools.router import DEFAULT_LISTEN

    _zenoh_options(parser, listen=f"endpoint to accept peers and routers on; repeatable (default: {DEFAULT_LISTEN})",
                   connect="another router to connect to (chaining sites), e.g. tcp/10.0.0.5:7447; repeatable",
                   config="zenoh JSON5 configuration file (the options here override it, its gateway too unless --no-lans)",
                   no_multicast="do not answer or send multicast scouting (peers must --connect to the router)",
                   multicast_interface="interface for multicast scouting (default: zenoh's choice, 'auto')")
    lans = parser.add_mutually_exclusive_group()
    lans.add_argument("--lan", action="append", metavar="IFACE",
                      help="peers reaching the router through IFACE form one LAN, and the router forwards between LANs; "
                           "repeatable (default: each network interface of this host is a LAN)")
    lans.add_argument("--no-lans", action="store_true",
                      help="leave zenoh's regions as they are (all peers of this router in one region assumed fully connected: "
                           "the router then forwards only between its clients, its peers and other routers)")


class _Absorb:
    """Takes the argument definitions of a sub-command that is not about to run, and keeps none."""

    def __getattr__(self, _name: str) -> Callable[..., _Absorb]:
        return lambda *_args, **_kwargs: self


class _Only:
    """The sub-command parsers, of which only ``command``'s (or all, when it is None) get their
    arguments: argparse builds about 300 of them otherwise. ``build_parser`` builds the whole
    parser again when ``command`` turned out to be no sub-command (a typo: argparse's own error)."""

    def __init__(self, sub: Any, command: str | None) -> None:
        self._sub = sub
        self._command = command
        self.found = command is None

    def builds(self, name: str) -> bool:
        """Whether command ``name`` gets its arguments."""
        return self._command is None or name == self._command

    def add_parser(self, name: str, **kwargs: Any) -> Any:
        parser = self._sub.add_parser(name, **kwargs)  # every command is listed and known to the top level
        if not self.builds(name):
            return _Absorb()
        self.found = True
        return parser


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole command line; given the ``command`` about to run, the sub-commands of ``certs``
    are left out unless it is ``certs`` (they import cryptography, which the others never need)."""
    parser = argparse.ArgumentParser(
        prog="cmion-mesh", description="Zenoh peer-to-peer embodiment mesh (CMION rebuilt).",
        epilog="exit codes: 0 succeeded, 1 failed or refused, 2 usage or configuration error, 3 cancelled, "
               "4 outcome unknown (no answer, the target vanished), 130 left on a second Ctrl-C")
    parser.add_argument("--version", action="version", version=f"cmion-mesh {__version__}")
    sub = _Only(parser.add_subparsers(dest="command", required=True, metavar="COMMAND"), command)

    p = sub.add_parser("up", help="run an embodiment daemon until SIGINT/SIGTERM")
    p.add_argument("path", nargs="?", help="ArchitectureConfiguration file or folder, or a shipped embodiment name (robot, screen...)")
    p.add_argument("--name", help="embodiment name (default: the device table's devicename, else the configuration's)")
    p.add_argument("--world-model", metavar="FILE", help="CMION WorldModel init file (replaces the configuration's)")
    p.add_argument("--rules", metavar="FILE", help="CMION CompetencyManagerRules file (replaces the configuration's)")
    p.add_argument("--library", metavar="FILE", help="CMION CompetencyLibrary file (replaces the configuration's)")
    p.add_argument("--remote-type", action="append", metavar="TYPE",
                   help="a competency type served by another process (serve-competency): rules may use it; repeatable")
    p.add_argument("--lease-ms", type=int, default=2000, help="zenoh link lease: how fast a frozen peer is noticed (ms)")
    p.add_argument("--state-dir", help="durable state: migration records, persistent properties "
                                       "(default: ~/.local/state/cmion-mesh/<mesh>/<name>); one daemon per folder")
    p.add_argument("--companion", help="a companion born here on the first start, if this embodiment holds none "
                                       "and no live embodiment of the mesh hosts it (default: the device table's "
                                       "agent active gives birth to the configuration's Companion, or 'companion')")
    p.add_argument("--web", metavar="[HOST:]PORT",
                   help="serve the body's web page (face, voice, visitor, yes/no, commands) on this address, loopback unless "
                        "HOST says otherwise, e.g. 127.0.0.1:8080 (port 0: any free port; the address is printed; with --certs "
                        "it carries a key, without which the page only watches)")
    p.add_argument("--admit", action="append", metavar="NAME[=KEY]",
                   help="a companion allowed to migrate in, with its public key (see `peers --json`); default: any")
    _common(p, json_output=False)
    p.set_defaults(func=cmd_up)

    _store_parsers(sub)

    p = sub.add_parser("serve-competency", help="host a competency for an embodiment from this process (remote competency)")
    p.add_argument("cls", metavar="CLASS", help="package.module:Class, a Competency subclass")
    p.add_argument("--embodiment", required=True, help="the embodiment this competency works for")
    p.add_argument("--parameters", default="", help="comma-separated constructor parameters")
    _common(p, json_output=False)
    p.set_defaults(func=cmd_serve_competency)

    p = sub.add_parser("serve-mind", help="run a mind in this process, driving an embodiment over the mesh")
    p.add_argument("cls", metavar="CLASS", help="package.module:Class, a Mind subclass")
    p.add_argument("--embodiment", required=True, help="the embodiment this mind drives")
    p.add_argument("--parameters", default="", help="comma-separated constructor parameters")
    _common(p, json_output=False)
    p.set_defaults(func=cmd_serve_mind)

    p = sub.add_parser("peers", help="list the embodiments alive in the mesh, with what they can do")
    _timeout(p, 3.0, "longest wait for the whole mesh to answer (it returns as soon as every live embodiment has)")
    _common(p)
    p.set_defaults(func=cmd_peers)

    p = sub.add_parser("act", help="send a mind action to an embodiment and wait for its outcome (exit code says it)",
                       description="Send a mind action and wait for its outcome. Ctrl-C cancels it and waits for the "
                                   "cancelled outcome; a second Ctrl-C leaves without waiting.")
    p.add_argument("embodiment", help="the embodiment to act")
    p.add_argument("action", help="the action's name, e.g. GoTo (see `peers` for the actions each embodiment knows)")
    p.add_argument("parameters", nargs="*", help="the action's parameters, e.g. Kitchen")
    p.add_argument("--subject", default="", help="who the action is about (rules may match on it)")
    p.add_argument("--id", help="action id (default: generated)")
    _timeout(p, 120.0, "seconds to wait for the outcome")
    p.add_argument("--deadline", type=float, default=0.0, help="deadline of each plan tried, seconds (default: the manager's)")
    p.add_argument("--detach", action="store_true", help="print the action's id and leave it running")
    _join_timeout(p)
    _common(p)
    p.set_defaults(func=cmd_act)

    p = sub.add_parser("cancel", help="cancel a running action")
    p.add_argument("embodiment", help="the embodiment running it")
    p.add_argument("action_id", help="the action's id (act prints it)")
    _join_timeout(p)
    _common(p)
    p.set_defaults(func=cmd_cancel)

    p = sub.add_parser("events", help="follow the event stream (filterable)")
    p.add_argument("--follow", "-f", action="store_true", help="keep following (the default; for familiarity)")
    p.add_argument("--embodiment", default="*", help="only this embodiment's events (default: all)")
    p.add_argument("--component", default="*", help="only this component's events (default: all)")
    p.add_argument("--event", default="*", help="only events of this name (default: all)")
    p.add_argument("--count", type=int, default=0, help="stop after exactly this many events")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    _join_timeout(p)
    _common(p)
    p.set_defaults(func=cmd_events)

    p = sub.add_parser("record", help="record everything the mesh says to an MCAP file (record info FILE: summarise one)",
                       description="Record the mesh to an MCAP file (Foxglove, the mcap CLI and any MCAP reader open it): "
                                   "events (migration steps and actions among them), storage changes and liveliness, one "
                                   "channel per key pattern, JSON messages with JSON schemas, a metadata record per embodiment. "
                                   "Until Ctrl-C or --duration; a killed recorder leaves a file readable up to its last "
                                   "chunk (at most about 0.5 s lost). `cmion-mesh record info FILE` summarises a recording "
                                   "(duration, counts per channel, migrations, embodiments, drops, truncation). See docs/record.md.")
    p.add_argument("filters", nargs="*", metavar="FILTER",
                   help="key expressions of what to record, relative to cmion/<mesh>/ (e.g. robot/ev/** */wm/**) or absolute "
                        "(default: the whole mesh; liveliness is always recorded); `info FILE...` summarises recordings instead")
    p.add_argument("-o", "--output", metavar="FILE", help="the file (default: cmion-<mesh>-<date>-<time>.mcap here)")
    p.add_argument("--force", action="store_true", help="overwrite FILE if it exists (default: refuse)")
    p.add_argument("--split-size", metavar="SIZE",
                   help="start a new file (FILE-0001.mcap...) with the first message past this size, e.g. 100M, 1G")
    p.add_argument("--split-time", type=float, metavar="SECONDS",
                   help="start a new file with the first message after this many seconds")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (default: at Ctrl-C)")
    _join_timeout(p)
    _common(p)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("replay", help="publish a recording's events into a mesh, at their timing or faster",
                       description="Publish the events of an MCAP recording (cmion-mesh record) into --mesh, their keys "
                                   "rewritten to it, in order, spaced as recorded divided by --rate. Storage, liveliness "
                                   "and raw samples are not replayed. Waits (--join-timeout) for a subscriber of the first "
                                   "event before publishing. See docs/record.md.")
    p.add_argument("file", metavar="FILE", help="the recording (.mcap)")
    p.add_argument("--rate", type=float, default=1.0,
                   help="speed: 1 as recorded, 10 ten times faster, 0 (or inf) as fast as possible (default: %(default)s)")
    p.add_argument("--filter", action="append", metavar="PATTERN",
                   help="only events whose key matches, relative to cmion/<mesh>/ (e.g. robot/ev/manager/*); repeatable")
    p.add_argument("--wait-for", action="append", metavar="EMBODIMENT", help="wait for this embodiment to be alive first; repeatable")
    _join_timeout(p)
    _common(p)
    p.set_defaults(func=cmd_replay)


    keys_help = ("a key expression: relative to the mesh (robot/ev/**, robot/bb/**, @alive/*, ** for all it publishes) "
                 "or absolute (cmion/MESH/..., or any zenoh key expression after a leading /)")
    p = sub.add_parser("hz", help="the rate of publications on a key expression (as ros2 topic hz)",
                       description="Print, every second, the rate of what is published on KEY (average rate, min, max and "
                                   "standard deviation of the period, over the last --window periods), as ros2 topic hz "
                                   "does; a final report at the end. Exit 1 when fewer than two messages came.")
    p.add_argument("key", metavar="KEY", help=keys_help)
    p.add_argument("--window", "-w", type=int, default=10_000, help="periods the statistics cover (default: %(default)s)")
    p.add_argument("--per-key", action="store_true", help="one rate per key rather than one for the whole expression")
    p.add_argument("--count", type=int, default=0, help="stop after this many messages")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    p.add_argument("--liveliness", action="store_true", help="count liveliness tokens appearing and going (automatic "
                                                              "when a chunk of KEY starts with @, but @outcome)")
    _common(p)
    p.set_defaults(func=cmd_hz)

    p = sub.add_parser("echo", help="print what is published on a key expression, decoded (as ros2 topic echo)",
                       description="Print what is published on KEY: mesh messages (events, storage values and changes...) "
                                   "decoded, anything else raw (UTF-8 text, or hex); liveliness tokens as they appear and go.")
    p.add_argument("key", metavar="KEY", help=keys_help)
    p.add_argument("--count", type=int, default=0, help="stop after exactly this many messages")
    p.add_argument("--once", action="store_true", help="stop after the first message (--count 1)")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    p.add_argument("--raw", action="store_true", help="never decode: show every payload raw")
    p.add_argument("--liveliness", action="store_true",
                   help="watch liveliness tokens (automatic when a chunk of KEY starts with @, but @outcome)")
    _common(p)
    p.set_defaults(func=cmd_echo)

    p = sub.add_parser("view", help="a live view of the mesh in the browser (embodiments, companions, migrations, events, "
                                    "blackboard, world model, plans)",
                       description="Serve a page that shows the mesh as it happens: every embodiment alive and who "
                                   "inhabits it, migrations with their handshake steps, the event stream, one "
                                   "embodiment's blackboard and world model, running plans. Read-only unless "
                                   "--allow-actions. See docs/view.md.")
    p.add_argument("--web", default="127.0.0.1:8090", metavar="HOST:PORT",
                   help="where to serve the page (default: %(default)s; loopback unless an address says otherwise)")
    p.add_argument("--allow-actions", action="store_true",
                   help="let the page send mind actions and migrations (refused otherwise)")
    _common(p, json_output=False)
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("migrate", help="move a companion to another embodiment (waits for the handshake's end)")
    p.add_argument("companion", help="the companion to move (see `peers`: INHABITANT)")
    p.add_argument("--to", required=True, metavar="EMBODIMENT", help="where to")
    _timeout(p, 60.0, "seconds to wait for the handshake's end")
    _common(p)
    p.set_defaults(func=cmd_migrate)

    p = sub.add_parser("custody", help="a companion's custody across the mesh: who holds it, forks of its chain and "
                                       "how to resolve them",
                       description="`custody show COMPANION`: what every live embodiment reports of the companion's "
                                   "custody, the evidence of a fork (who equivocated) and the command that resolves it. "
                                   "`custody resolve COMPANION --keep EMBODIMENT`: keep one branch of a fork; every other "
                                   "branch holder stands down first (its copy retired on its disk), then the kept one "
                                   "runs again. Refused when a holder of another branch cannot be reached (it would make "
                                   "two), or when the evidence shows an equivocator holding the branch kept (--force).")
    actions = p.add_subparsers(dest="custody_command", required=True, metavar="ACTION")
    cp = actions.add_parser("show", help="what every embodiment reports of a companion's custody, forks and their evidence")
    cp.add_argument("companion", help="the companion")
    _timeout(cp, 3.0, "longest wait for the whole mesh to answer")
    _common(cp)
    cp.set_defaults(func=cmd_custody)
    cp = actions.add_parser("resolve", help="keep one branch of a fork of a companion's chain of custody; the others stand down")
    cp.add_argument("companion", help="the companion")
    cp.add_argument("--keep", required=True, metavar="EMBODIMENT", help="the embodiment whose branch runs the companion")
    cp.add_argument("--force", action="store_true", help="keep it even though the evidence shows an equivocator holding it")
    cp.add_argument("--gone", action="append", metavar="EMBODIMENT",
                    help="a branch holder that is gone for good (wiped, revoked): not waited for; repeatable")
    _timeout(cp, 10.0, "seconds to wait for each answer")
    _common(cp)
    cp.set_defaults(func=cmd_custody)

    p = sub.add_parser("invite", help="have an empty embodiment invite the companion (CMION's migration invitation)",
                       description="EMBODIMENT (which must host no companion) invites the companion: every embodiment of "
                                   "its device table, or without a table every live one, is asked; the one hosting the "
                                   "companion passes MigrationInvitation EMBODIMENT to its mind, which may migrate. Exit 0 "
                                   "when a host accepted the invitation, 1 when nobody did (each answer is listed).")
    p.add_argument("embodiment", help="the inviting embodiment (empty)")
    p.add_argument("--to", action="append", metavar="EMBODIMENT",
                   help="invite only this embodiment; repeatable (default: the device table's, or every live one)")
    _timeout(p, 30.0, "seconds to wait for every answer")
    _common(p)
    p.set_defaults(func=cmd_invite)

    p = sub.add_parser("router", help="run a zenoh router, so embodiments beyond one LAN join one mesh (no --mesh: it routes every mesh)")
    if sub.builds("router"):  # its defaults come from the router module (sockets): only for it
        _router_parser(p)
    p.set_defaults(func=cmd_router)

    p = sub.add_parser("certs", help="a certificate authority and certificates for an authenticated mesh (mutual TLS)")
    if command in (None, "certs"):
        _certs_parsers(p)
    p.set_defaults(func=cmd_certs)

    p = sub.add_parser("doctor", help="explain why peers are (not) found, and what is wrong in the mesh")
    _timeout(p, 3.0, "longest wait for the mesh to answer")
    _common(p)
    p.set_defaults(func=cmd_doctor)

    p = sub.add_parser("validate", help="check CMION XML files against their schemas and semantics (what `up` checks too)",
                       description="Check CMION XML files and list every problem of every file: errors (exit code 1), "
                                   "warnings (stand-ins for CMION classes with no equivalent; exit code 0) and notes.")
    p.add_argument("files", nargs="+", metavar="PATH", help="a file, a folder (its *.xml files) or a shipped embodiment's name")
    p.add_argument("--strict", action="store_true", help="warnings count as errors (exit code 1)")
    p.add_argument("--remote-type", action="append", metavar="TYPE",
                   help="a competency type served by another process (serve-competency): rules may use it; repeatable")
    _json(p)
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("launch", help="start several processes of a mesh from one TOML file; Ctrl-C stops them all",
                       description="Start the embodiments, router, minds, remote competencies and other processes a "
                                   "launch file names (docs/launch.md), each line of their output prefixed with their "
                                   "name; stop them all on Ctrl-C or SIGTERM, or when one fails (the file's on_failure). "
                                   "Exit code 0 when everything stopped cleanly, 1 when a process failed, 2 for a bad file.")
    p.add_argument("file", metavar="FILE", help="a launch file (TOML), or a shipped one's name (spirit)")
    p.add_argument("--check", action="store_true", help="check the file and print what would run, start nothing")
    p.add_argument("--mesh", help="run in this mesh instead of the file's")
    p.add_argument("--json", action="store_true", help="with --check: what would run, as JSON")
    p.set_defaults(func=cmd_launch)

    p = sub.add_parser("demo", help="run the demonstration scenario (three daemons in a mesh of their own)")
    p.add_argument("--mesh", default=keys.DEFAULT_MESH, help="deployment name (default: a fresh one)")
    p.add_argument("--web", action="store_true",
                   help="the screen and the phone serve their pages (addresses printed): answer the companion on the screen's page")
    p.add_argument("--record", metavar="FILE", help="record the demo's mesh to this MCAP file (as `record` does; "
                                                      "never overwritten): read it with `record info FILE` or replay it")
    p.set_defaults(func=cmd_demo)
    if not sub.found:
        return build_parser(None)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    arguments = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in arguments if not a.startswith("-")), None)  # the top level has options only
    args = build_parser(command).parse_args(arguments)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return int(func(args))
    except MeshError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exit_code(exc)
    except KeyboardInterrupt:
        return ExitCode.INTERRUPTED
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return ExitCode.FAILED
    except Exception as exc:
        if os.environ.get("CMION_MESH_DEBUG"):
            raise
        print(f"internal error: {type(exc).__name__}: {exc} (set CMION_MESH_DEBUG=1 for the traceback)", file=sys.stderr)
        return ExitCode.FAILED


if __name__ == "__main__":
    sys.exit(main())
