"""Tools around a mesh: ``doctor`` (what is wrong), ``router``, ``launch`` (several processes from one
file) and ``demo``."""

from __future__ import annotations

import argparse
import json

from cmion_mesh import keys
from cmion_mesh.cli.common import mesh_options, timeout_option, transport_config, zenoh_options
from cmion_mesh.errors import ExitCode
from cmion_mesh.signals import Interrupter, Stopper
from cmion_mesh.tools import launch, launcher
from cmion_mesh.tools.demo import run_demo
from cmion_mesh.tools.doctor import run_doctor
from cmion_mesh.tools.router import DEFAULT_LISTEN, RouterOptions, run


def doctor_arguments(p: argparse.ArgumentParser) -> None:
    timeout_option(p, 3.0, "longest wait for the mesh to answer")
    mesh_options(p)


def cmd_doctor(args: argparse.Namespace) -> int:
    return run_doctor(transport_config(args), mesh=args.mesh, timeout=args.timeout, as_json=args.json, certs=bool(args.certs))


def router_arguments(parser: argparse.ArgumentParser) -> None:
    zenoh_options(parser, listen=f"endpoint to accept peers and routers on; repeatable (default: {DEFAULT_LISTEN})",
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


def cmd_router(args: argparse.Namespace) -> int:
    options = RouterOptions(listen=tuple(args.listen or (DEFAULT_LISTEN,)), connect=tuple(args.connect or ()),
                            config_file=args.config, multicast=not args.no_multicast, multicast_interface=args.multicast_interface,
                            lans=None if args.no_lans else tuple(args.lan or ()))
    return run(options)


def launch_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Start the embodiments, router, minds, remote competencies and other processes a "
                     "launch file names (docs/launch.md), each line of their output prefixed with their "
                     "name; stop them all on Ctrl-C or SIGTERM, or when one fails (the file's on_failure). "
                     "Exit code 0 when everything stopped cleanly, 1 when a process failed, 2 for a bad file.")
    p.add_argument("file", metavar="FILE", help="a launch file (TOML), or a shipped one's name (spirit)")
    p.add_argument("--check", action="store_true", help="check the file and print what would run, start nothing")
    p.add_argument("--mesh", help="run in this mesh instead of the file's")
    p.add_argument("--json", action="store_true", help="with --check: what would run, as JSON")


def cmd_launch(args: argparse.Namespace) -> int:
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


def demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mesh", default=keys.DEFAULT_MESH, help="deployment name (default: a fresh one)")
    p.add_argument("--web", action="store_true",
                   help="the screen and the phone serve their pages (addresses printed): answer the companion on the screen's page")
    p.add_argument("--record", metavar="FILE", help="record the demo's mesh to this MCAP file (as `record` does; "
                                                      "never overwritten): read it with `record info FILE` or replay it")


def cmd_demo(args: argparse.Namespace) -> int:
    stop = Interrupter()  # before any thread: interrupted or terminated, the demo still stops its daemons
    try:
        return run_demo(mesh=args.mesh, web=args.web, wait=stop.wait, record=args.record)
    except KeyboardInterrupt:  # the story cut short by SIGINT or SIGTERM: the shell's 130 or 143
        return stop.exit_code()
