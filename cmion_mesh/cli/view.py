"""``view``: a live view of the mesh in the browser (docs/view.md)."""

from __future__ import annotations

import argparse
import sys

from cmion_mesh.cli.common import mesh_options
from cmion_mesh.cli.session import session
from cmion_mesh.errors import ExitCode
from cmion_mesh.signals import Stopper
from cmion_mesh.web.server import WebServer, parse_bind
from cmion_mesh.web.view import MeshView


def view_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Serve a page that shows the mesh as it happens: every embodiment alive and who "
                     "inhabits it, migrations with their handshake steps, the event stream, one "
                     "embodiment's blackboard and world model, running plans. Read-only unless "
                     "--allow-actions. With --recording, plays a recording through the same page. See docs/view.md.")
    p.add_argument("--web", default="127.0.0.1:8090", metavar="HOST:PORT",
                   help="where to serve the page (default: %(default)s; loopback unless an address says otherwise)")
    p.add_argument("--allow-actions", action="store_true",
                   help="let the page send mind actions and migrations (refused otherwise)")
    p.add_argument("--recording", metavar="FILE.mcap",
                   help="play a recording (cmion-mesh record, demo --record) through the view instead of joining "
                        "a mesh: it starts when the page opens; the page pauses, changes the speed and seeks")
    mesh_options(p, json_output=False)


def cmd_view(args: argparse.Namespace) -> int:
    host, port = parse_bind(args.web)
    if args.recording:
        return _play(args, host, port)
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


def _play(args: argparse.Namespace, host: str, port: int) -> int:
    from cmion_mesh.tools.view_player import RecordingPlayer, load

    mesh, items, truncated = load(args.recording)
    stop = Stopper()
    loopback = host in ("127.0.0.1", "::1", "localhost")
    with MeshView(None, mesh=mesh, loopback=loopback) as view, WebServer(view.app, host, port, name="view") as web, \
            RecordingPlayer(view, items, path=args.recording, truncated=truncated):
        view.start(web.call_soon)
        cut = "; read in part (truncated)" if truncated else ""
        print(f"view of mesh {mesh!r} at {web.url}/ (playing {args.recording}: {len(items)} messages{cut}; "
              "Ctrl-C to stop)", flush=True)
        stop.wait()
    return ExitCode.OK
