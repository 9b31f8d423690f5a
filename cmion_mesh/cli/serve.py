"""``serve-competency`` and ``serve-mind``: a part of an embodiment hosted by another process."""

from __future__ import annotations

import argparse
import sys
import threading
from typing import Any

from cmion_mesh import keys
from cmion_mesh.body.remote import CompetencyHost
from cmion_mesh.body.remote_mind import serve_mind
from cmion_mesh.classes import construct, split_parameters
from cmion_mesh.cli.common import JOIN_WINDOW, mesh_options
from cmion_mesh.cli.session import session
from cmion_mesh.client import alive_list, did_you_mean
from cmion_mesh.competency import Competency
from cmion_mesh.errors import ExitCode
from cmion_mesh.ion import serve
from cmion_mesh.mind import Mind
from cmion_mesh.signals import Stopper


def competency_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("cls", metavar="CLASS", help="package.module:Class, a Competency subclass")
    p.add_argument("--embodiment", required=True, help="the embodiment this competency works for")
    p.add_argument("--parameters", default="", help="comma-separated constructor parameters")
    mesh_options(p, json_output=False)


def cmd_serve_competency(args: argparse.Namespace) -> int:
    return _serve(args, Competency, "competency")


def mind_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("cls", metavar="CLASS", help="package.module:Class, a Mind subclass")
    p.add_argument("--embodiment", required=True, help="the embodiment this mind drives")
    p.add_argument("--parameters", default="", help="comma-separated constructor parameters")
    p.add_argument("--name", help="the mind's name on its embodiment (default: the one its class gives); "
                                  "refused (exit 2) when the embodiment has a component of that name")
    mesh_options(p, json_output=False)


def cmd_serve_mind(args: argparse.Namespace) -> int:
    """Wait until the embodiment is alive, then serve the mind (``body.remote_mind``: its ``on_start``
    can act, and its name is checked against the embodiment's)."""
    mind = construct(args.cls, Mind, split_parameters(args.parameters))
    if args.name is not None:
        mind.name = keys.check_name(args.name, "mind name")
    stop = Stopper()
    target = keys.check_name(args.embodiment, "embodiment")
    arrived = threading.Event()
    with session(args, target) as client:

        def on_change(name: str, alive: bool) -> None:
            if name != target:
                return
            if alive and not arrived.is_set():
                arrived.set()
                stop.stop()  # wakes the wait below
            else:
                print(f"embodiment {target!r} is back" if alive else
                      f"warning: embodiment {target!r} left the mesh: this mind serves nobody until it is back",
                      file=sys.stderr, flush=True)

        presence = client.presence
        with presence.listen(on_change, replay=True):
            if not presence.wait(lambda alive: target in alive, JOIN_WINDOW):
                alive = presence.alive()
                print(f"warning: embodiment {target!r} is not alive in mesh {args.mesh!r} (alive: {alive_list(alive)})"
                      f"{did_you_mean(target, alive)}: this mind starts once it is", file=sys.stderr, flush=True)
            while not arrived.is_set():  # each pass ends on a signal or on the embodiment's arrival
                if stop.wait() is not None:
                    return ExitCode.OK
            with serve_mind(mind, embodiment=target, transport=client.transport, mesh=args.mesh):
                print(f"mind {mind.name!r} serving embodiment {target!r}", flush=True)
                while stop.wait() is None:  # a wake-up left over from the arrival, not a signal
                    pass
    return ExitCode.OK


def _serve(args: argparse.Namespace, base: type[Any], what: str) -> int:
    """Host a component built from ``CLASS --parameters`` for ``--embodiment`` until stopped, and say
    while that embodiment is not alive (the component then serves nobody)."""
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
