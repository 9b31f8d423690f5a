"""``mcp``: an MCP server for a companion, so that any MCP client drives the body it lives in
(docs/llm.md). The server itself is ``tools/mcp_server.py``."""

from __future__ import annotations

import argparse
import socket
import sys

from cmion_mesh.cli.common import mesh_options
from cmion_mesh.cli.session import session
from cmion_mesh.errors import ConfigError, ExitCode
from cmion_mesh.transport import security

#: Where ``--http`` alone serves.
DEFAULT_HTTP = "127.0.0.1:8766"
LOOPBACK = frozenset({"127.0.0.1", "::1", "localhost"})


def mcp_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Serve COMPANION to MCP clients (Model Context Protocol): its tools are the actions of the body it "
                     "lives in now (they change, with a list-changed notification, when it migrates), plus migrate and "
                     "peers; its resources are that body's world model and blackboard (subscribe to follow changes). "
                     "Over stdio by default (what desktop clients start), or streamable HTTP with --http. Read-only "
                     "unless --allow-actions: tools are listed, calls that act are refused. See docs/llm.md.")
    p.add_argument("companion", help="the companion to serve, e.g. spirit")
    p.add_argument("--http", nargs="?", const=DEFAULT_HTTP, metavar="HOST:PORT",
                   help=f"serve streamable HTTP at /mcp instead of stdio (default address: {DEFAULT_HTTP}; loopback "
                        "unless an address says otherwise)")
    p.add_argument("--allow-actions", action="store_true",
                   help="let clients act (the body's actions, migrate); refused otherwise")
    p.add_argument("--join", "--join-timeout", "--discover-timeout", dest="join_timeout", type=float, default=5.0, metavar="SECONDS",
                   help="how long to look for the embodiment the companion lives in (default: %(default)s s)")
    mesh_options(p, json_output=False)


def cmd_mcp(args: argparse.Namespace) -> int:
    import anyio

    from cmion_mesh.tools.mcp_server import CompanionServer
    from cmion_mesh.web.server import parse_bind

    sock: socket.socket | None = None
    if args.http is not None:
        host, port = parse_bind(args.http)
        sock = _bind(host, port)
    mode = "actions allowed" if args.allow_actions else "read-only"
    if args.certs:
        print(security.describe(certs_dir=args.certs, identity=args.identity), file=sys.stderr, flush=True)
    try:
        with session(args) as client, CompanionServer(client, args.companion, allow_actions=args.allow_actions,
                                                      join_timeout=args.join_timeout, secure=bool(args.certs)) as server:
            if sock is None:
                def on_stdio() -> None:  # stdout is the protocol's: what a person reads goes to stderr
                    print(f"mcp server of companion {args.companion!r} (on {server.host}) in mesh {args.mesh!r} on stdio "
                          f"({mode})", file=sys.stderr, flush=True)

                anyio.run(server.serve_stdio, on_stdio)
                return ExitCode.OK

            def ready(url: str) -> None:
                print(f"mcp server of companion {args.companion!r} (on {server.host}) in mesh {args.mesh!r} at {url} "
                      f"({mode}; Ctrl-C to stop)", flush=True)
                if args.allow_actions and sock is not None and sock.getsockname()[0] not in LOOPBACK:
                    print(f"warning: anyone who reaches {url} may act on mesh {args.mesh!r}", file=sys.stderr, flush=True)

            bound = sock
            anyio.run(lambda: server.serve_http(bound, ready))
    finally:
        if sock is not None:
            sock.close()
    return ExitCode.OK


def _bind(host: str, port: int) -> socket.socket:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        return socket.create_server((host, port), family=family, reuse_port=False)
    except OSError as exc:
        raise ConfigError(f"cannot serve MCP on {host}:{port}: {exc.strerror or exc}") from None
