"""``up``: an embodiment daemon, from its configuration to its clean stop.

What ``up`` needs to know its name and endpoints is imported with this module; the embodiment
itself (``body.embodiment``, ``body.validate``, ``ops.systemd``: most of the package) is imported
while the mesh answers the name claim (``claim.Joining``), so that import and the mesh's
answer overlap; the metrics (``prometheus_client``) only with ``--metrics``.

Run for months (docs/deploy.md): ``--log-level``, ``--log-format``, ``--log-file`` (``logs``),
``--settings FILE`` (``ops.settings``, merged by ``cli.main`` before the command runs),
``--metrics HOST:PORT`` (``ops.metrics``), and under systemd ``READY=1`` once the name is held,
the watchdog fed by the update loop and ``STOPPING=1`` on SIGTERM (``ops.systemd``). What cannot
start for what it was given (a state folder that cannot be made, an address in use, a settings
or log file it cannot read) is one line naming it, exit code 2, and nothing left behind.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import gc
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from cmion_mesh import keys, logs
from cmion_mesh.body import architecture
from cmion_mesh.body import library as library_files
from cmion_mesh.body.architecture import read_architecture
from cmion_mesh.claim import Joining
from cmion_mesh.cli.common import JOIN_WINDOW, mesh_options, plural, transport_config
from cmion_mesh.diagnostics import Diagnostics
from cmion_mesh.errors import ConfigError, ExitCode, WebServerError
from cmion_mesh.migration import devices
from cmion_mesh.migration.signing import decode_public
from cmion_mesh.ops import settings
from cmion_mesh.resources import data_dir
from cmion_mesh.signals import Stopper
from cmion_mesh.transport import security
from cmion_mesh.transport.base import LEASE_MS, TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

if TYPE_CHECKING:
    from cmion_mesh.body.embodiment import Embodiment
    from cmion_mesh.ion import Component
    from cmion_mesh.ops.metrics import MetricsServer

log = logging.getLogger(__name__)
T = TypeVar("T")


def up_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", nargs="?", help="ArchitectureConfiguration file or folder, or a shipped embodiment name (robot, screen...)")
    p.add_argument("--name", help="embodiment name (default: the device table's devicename, else the configuration's)")
    p.add_argument("--world-model", metavar="FILE", help="CMION WorldModel init file (replaces the configuration's)")
    p.add_argument("--rules", metavar="FILE", help="CMION CompetencyManagerRules file (replaces the configuration's)")
    p.add_argument("--library", metavar="FILE", help="CMION CompetencyLibrary file (replaces the configuration's)")
    p.add_argument("--remote-type", action="append", metavar="TYPE",
                   help="a competency type served by another process (serve-competency): rules may use it; repeatable")
    # zenoh keeps each link alive with four keep-alives per lease: per-peer work on an idle daemon.
    # zenoh's own 10 s keeps it flat with the mesh's size; a shorter lease notices a frozen peer sooner.
    p.add_argument("--lease-ms", type=int, default=LEASE_MS,
                   help=f"zenoh link lease: how fast a frozen peer is noticed (ms; default {LEASE_MS}, zenoh's; each "
                        "link of an idle daemon carries four keep-alives per lease)")
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
    p.add_argument("--metrics", metavar="[HOST:]PORT",
                   help="serve Prometheus metrics on /metrics and a health check on /healthz at this address, loopback "
                        "unless HOST says otherwise, e.g. 127.0.0.1:9464 (see docs/deploy.md)")
    settings.add_argument(p)
    mesh_options(p, json_output=False)
    logs.add_arguments(p)


def resolve_config(path: str) -> str:
    """``up`` takes a configuration file, a folder holding ``ArchitectureConfiguration.xml``, or the
    name of a shipped embodiment (``robot``, ``screen``, ``phone``, ``cmion_test``, ``ros_robot``)."""
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
    if not args.admit:
        return None
    out: dict[str, bytes | None] = {}
    for item in args.admit:
        name, _, key = item.partition("=")
        out[keys.check_name(name, "companion")] = decode_public(key) if key else None
    return out


def join_window(args: argparse.Namespace) -> float:
    """How long ``up`` looks for the rest of the mesh: none when it cannot find anyone by itself
    (no scouting, no endpoint to connect to, no zenoh file that could name one)."""
    return JOIN_WINDOW if (not args.no_multicast or args.connect or args.config) else 0.0


def _existing(path: str | None, option: str) -> str | None:
    if path is not None and not Path(path).is_file():
        raise ConfigError(f"{option}: no such file", path=path)
    return path


def cmd_up(args: argparse.Namespace) -> int:
    logs.configure(args.log_level, args.log_format, args.log_file)
    # Starting makes objects that live as long as the daemon, and no garbage: the cyclic collector
    # waits until the embodiment is up, then skips them (``_up``; as ``main`` does for loading).
    collecting = gc.isenabled()
    gc.disable()
    try:
        return _up(args, collecting)  # a clean stop leaves the process from within (os._exit)
    finally:
        if collecting:
            gc.enable()
        # Refused or failed: the lines written, and the process's logging as it was (main may be
        # called in a process that goes on, as the tests do).
        logs.shutdown()
        logs.set_embodiment(None)
        logs.unconfigure()


def _up(args: argparse.Namespace, collecting: bool) -> int:
    metrics_server: MetricsServer | None = None
    if args.metrics:
        # Only with --metrics: prometheus_client is no other daemon's start-up cost.
        from cmion_mesh.ops import metrics

        metrics.parse_address(args.metrics)  # a malformed address is refused before the session opens
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
        arch = read_architecture(resolve_config(args.path), found, name=args.name)
        if arch is None:
            found.raise_if_errors()
        assert arch is not None
        # Files given on the command line replace the configuration's own.
        rules = rules or (str(arch.rules) if arch.rules else None)
        library = library or (str(arch.library) if arch.library else None)
        world_model = world_model or (str(arch.world_model) if arch.world_model else None)
        table = library_files.table_for_library(library, found) if library else None
        try:
            name = args.name or architecture.embodiment_name(table, arch)
        except ConfigError as exc:
            found.problem(exc)
            name = arch.embodiment
        companion = companion or devices.birth(table, arch.companion)
        admitted = arch.admit if admitted is None else {**(arch.admit or {}), **admitted}
    else:
        table = library_files.table_for_library(library, found) if library else None
        name = args.name or (table.name if table is not None else None)
        if not name and not found.errors:  # else the table's problems say why it has none
            raise ConfigError("give an architecture configuration (PATH) or at least --name")
        companion = companion or devices.birth(table, None)
    if table is not None:
        filled = devices.with_table_endpoints(TransportConfig(connect=tuple(args.connect or ()), listen=tuple(args.listen or ()),
                                                              config_file=args.config), table)
        args.connect, args.listen = list(filled.connect), list(filled.listen)
    if name:
        logs.set_embodiment(name)
    if args.settings:
        logs.event(log, "settings read", file=str(Path(args.settings).resolve()))
    with contextlib.ExitStack() as joining_stack:
        joined = None
        if name and not found.errors and keys.is_name(name) and keys.is_name(args.mesh):
            joined = _join(args, name, joining_stack)
        # Imported now, while the mesh answers the claim: most of the package's import time overlaps it.
        from cmion_mesh.body.embodiment import Embodiment
        from cmion_mesh.body.validate import check_embodiment, render
        from cmion_mesh.ops import systemd
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
            # Pages and metrics are served before the embodiment is announced: an address in use is
            # refused before anything but the name claim is on the mesh.
            for body in web:
                _listening(functools.partial(pages.enter_context, body))
            if args.metrics:
                metrics_server = pages.enter_context(_listening(functools.partial(metrics.MetricsServer, args.metrics)))
            joining_stack.pop_all()  # from here on the embodiment owns the session and the claim
            embodiment = Embodiment(name, mesh=args.mesh, transport_config=None if joined else transport_config(args, name),
                                    world_model_init=world_model, rules=ruleset, competencies=competencies,
                                    components=components, state_dir=state, companion=companion, admit=admitted,
                                    joined=joined, devices=table)
            with embodiment, systemd.Service(embodiment) as service:
                # READY=1 said (under systemd): joined, the name held, the loop turning. Leaving says STOPPING=1.
                if metrics_server is not None:
                    metrics_server.attach(metrics.Metrics(embodiment, heartbeat=service.heartbeat))
                if collecting:
                    gc.freeze()
                    gc.enable()
                _run_daemon(args, embodiment, table, companion, state, stop, web, metrics_server)
    # The log's writer thread stopped (its lines written): the lines below are written at once.
    logs.shutdown()
    left = [t.name for t in threading.enumerate() if t is not threading.main_thread() and t.is_alive()]
    if left:
        print(f"embodiment {embodiment.name!r} stopped, but threads are still running: {', '.join(left)}", flush=True)
        logs.event(log, "embodiment stopped, threads still running", level=logging.ERROR, threads=left)
        return ExitCode.FAILED
    print(f"embodiment {embodiment.name!r} stopped cleanly (no thread left)", flush=True)
    logs.event(log, "embodiment stopped cleanly")
    logs.shutdown()
    sys.stderr.flush()
    # Said only when it is true: everything is closed and on disk, so leave now rather than let
    # the interpreter's finalization (zenoh's runtime among it) keep the process alive after it.
    os._exit(ExitCode.OK)


def _join(args: argparse.Namespace, name: str, stack: contextlib.ExitStack) -> Joining:
    """The daemon's session, opened now, and its name claim under way on it (``claim.Joining``);
    ``stack`` closes both unless the embodiment takes them (``pop_all``)."""
    transport = stack.enter_context(ZenohTransport(transport_config(args, name)))
    joining = Joining(transport, args.mesh, name, window=join_window(args))
    stack.enter_context(joining)
    return joining


def _listening(bind: Callable[[], T]) -> T:
    """``bind()``, a server taking its address; one it cannot listen on (in use, not this host's) is
    a configuration error: the address given is at fault, and starting again would not help."""
    try:
        return bind()
    except WebServerError as exc:
        if "cannot listen on" in str(exc):
            raise ConfigError(str(exc)) from None
        raise


def _web_bodies(args: argparse.Namespace, components: list[Component]) -> list[Any]:
    """The web bodies to serve: the configuration's ``WebBody`` components, and ``--web``'s address
    (replacing the configuration's first one, or adding one)."""
    if not args.web and "cmion_mesh.web.body" not in sys.modules:
        return []  # starlette and uvicorn cost start time: imported only for a page (--web, or a WebBody configured)
    import secrets  # with the page: it loads hashlib (OpenSSL), which a daemon with no page or companion never needs

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
        # An authenticated mesh: what a page senses becomes world-model writes, so only the holder
        # of the printed address (its key) may act there; others may watch.
        for body in bodies:
            body.key = body.key or secrets.token_urlsafe(18)
    return bodies


def _run_daemon(args: argparse.Namespace, embodiment: Embodiment, table: devices.DeviceTable | None, companion: str | None,
                state: str, stop: Stopper, web: list[Any], metrics_server: MetricsServer | None) -> None:
    """What the started embodiment says of itself, then its wait for SIGINT or SIGTERM."""
    name = embodiment.name
    # Warnings are log lines (standard error, or --log-file; JSON with --log-format json); what the
    # daemon is and where it listens is said on standard output.
    mode = security.describe(certs_dir=args.certs, identity=args.identity, name=embodiment.name)
    if mode.startswith("plain"):
        log.warning("%s", mode)
    else:
        print(mode, flush=True)
    if args.no_multicast and not args.connect and not args.listen:
        log.warning("no multicast and no endpoints: no peer can find this embodiment")
    if table is not None:
        print(f"device table {table.path}: embodiment {name!r}, knows {', '.join(table.names) or 'no device'}; "
              f"listen {', '.join(args.listen) or '-'}; connect {', '.join(args.connect) or '-'}"
              + (f"; companion {companion!r} born here" if companion and table.born_here else ""), flush=True)
    if embodiment.companion_elsewhere:
        log.warning("companion %r already lives on %r: it is not born here", companion, embodiment.companion_elsewhere)
    standins = embodiment.standins()
    if standins:
        print(f"stand-ins, reported unavailable (see docs/portmap.md): {len(standins)}", flush=True)
        for s in standins:
            typed = f"; types {', '.join(s['types'])}" if s.get("types") else ""
            print(f"  {s['class']} ({s['kind']}{typed}) at {s['where']}", flush=True)
    for body in web:
        print(f"web body of {embodiment.name!r} at {body.address} (senses: {', '.join(body.snapshot()['senses']) or 'none'}"
              + ("; without its key the page only watches)" if body.key else ")"), flush=True)
        logs.event(log, "web body served", url=body.address)  # its key, if any, is never logged
    for mind in embodiment.minds:
        link = mind.connection()  # a mind outside this process (FAtiMA) connects to its connector here
        if link is not None and link.get("listening"):
            print(f"{link.get('protocol', 'mind')} connector {mind.name!r} of {name!r} listening at {link['listening']} "
                  "(start the mind pointed there: docs/fatima.md)", flush=True)
    if metrics_server is not None:
        print(f"metrics of {name!r} at {metrics_server.url}/metrics (health: {metrics_server.url}/healthz)", flush=True)
        logs.event(log, "metrics served", url=f"{metrics_server.url}/metrics", health=f"{metrics_server.url}/healthz")
    logs.flush()  # what was logged while starting (plain mode, a companion living elsewhere...) comes before "up"
    print(f"embodiment {embodiment.name!r} up in mesh {args.mesh!r} (zenoh id {embodiment.transport.id}; "
          f"{plural(len(embodiment.execution.competencies), 'competency', 'competencies')}, "
          f"{plural(len(embodiment.rules.rules), 'rule')}; state {state})",
          flush=True)
    logs.event(log, "embodiment up", mesh=args.mesh, zenoh_id=str(embodiment.transport.id),
               competencies=len(embodiment.execution.competencies), rules=len(embodiment.rules.rules), state=state,
               companion=embodiment.inhabitant)
    received = stop.wait()
    logs.event(log, "embodiment stopping", signal=signal.Signals(received).name if received else None)
