"""The ``cmion-mesh`` command line: the command table, and ``main``.

``COMMANDS`` maps each verb to the module of ``cmion_mesh.cli`` that owns it, the function there
that adds the verb's arguments to its parser, the handler that runs it, and the one-line summary
``cmion-mesh --help`` lists. Only the module of the verb that runs is imported: the list of verbs,
a typo and ``--help`` import none, so start-up is fast by structure (as pip's command table).

Commands that join a mesh take ``--mesh``, ``--connect``, ``--listen``, ``--config`` (a zenoh
JSON5 file), ``--no-multicast``, ``--multicast-interface`` and ``--certs``; commands whose output
is data take ``--json``. One-shot commands join the mesh before they ask (``client``). Errors are
one clear line on stderr, never a traceback, and the exit code says what happened
(``errors.ExitCode``): 0 succeeded, 1 failed or refused, 2 usage or configuration error,
3 cancelled, 4 outcome unknown, 130 left on a second Ctrl-C.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable, Iterable, Sequence
from typing import NamedTuple

from cmion_mesh import __version__
from cmion_mesh.errors import ExitCode, MeshError, exit_code


class Command(NamedTuple):
    """One verb: ``module`` (in ``cmion_mesh.cli``) has ``arguments(parser)``, which adds the verb's
    arguments (and description) to its parser, and ``handler(args) -> exit code``."""

    module: str
    arguments: str
    handler: str
    summary: str


#: Every verb, in the order ``cmion-mesh --help`` lists them.
COMMANDS: dict[str, Command] = {
    "up": Command("daemon", "up_arguments", "cmd_up", "run an embodiment daemon until SIGINT/SIGTERM"),
    "service": Command("service", "service_arguments", "cmd_service",
                       "the systemd unit that runs an embodiment daemon (service unit NAME)"),
    "bb": Command("stores", "bb_arguments", "cmd_store", "read, write and watch an embodiment's blackboard"),
    "wm": Command("stores", "wm_arguments", "cmd_store", "read, write and watch an embodiment's world model"),
    "serve-competency": Command("serve", "competency_arguments", "cmd_serve_competency",
                                "host a competency for an embodiment from this process (remote competency)"),
    "serve-mind": Command("serve", "mind_arguments", "cmd_serve_mind",
                          "run a mind in this process, driving an embodiment over the mesh"),
    "peers": Command("actions", "peers_arguments", "cmd_peers", "list the embodiments alive in the mesh, with what they can do"),
    "act": Command("actions", "act_arguments", "cmd_act",
                   "send a mind action to an embodiment and wait for its outcome (exit code says it)"),
    "cancel": Command("actions", "cancel_arguments", "cmd_cancel", "cancel a running action"),
    "remote-action": Command("actions", "remote_action_arguments", "cmd_remote_action",
                             "tell an embodiment's minds that another agent did an action (CMION's RemoteActionSimulator)"),
    "events": Command("observe", "events_arguments", "cmd_events", "follow the event stream (filterable)"),
    "record": Command("recording", "record_arguments", "cmd_record",
                      "record everything the mesh says to an MCAP file (record info FILE: summarise one)"),
    "replay": Command("recording", "replay_arguments", "cmd_replay",
                      "publish a recording's events into a mesh, at their timing or faster"),
    "foxglove": Command("recording", "foxglove_arguments", "cmd_foxglove",
                        "serve the mesh live to Foxglove (the channels and schemas of a recording)"),
    "hz": Command("observe", "hz_arguments", "cmd_hz", "the rate of publications on a key expression (as ros2 topic hz)"),
    "echo": Command("observe", "echo_arguments", "cmd_echo",
                    "print what is published on a key expression, decoded (as ros2 topic echo)"),
    "view": Command("view", "view_arguments", "cmd_view",
                    "a live view of the mesh in the browser (embodiments, companions, migrations, events, "
                    "blackboard, world model, plans)"),
    "migrate": Command("actions", "migrate_arguments", "cmd_migrate",
                       "move a companion to another embodiment (waits for the handshake's end)"),
    "custody": Command("actions", "custody_arguments", "cmd_custody",
                       "a companion's custody across the mesh: who holds it, forks of its chain and how to resolve them"),
    "mcp": Command("mcp", "mcp_arguments", "cmd_mcp",
                   "serve a companion to MCP clients: its body's actions as tools, its world model as resources"),
    "invite": Command("actions", "invite_arguments", "cmd_invite",
                      "have an empty embodiment invite the companion (CMION's migration invitation)"),
    "router": Command("tools", "router_arguments", "cmd_router",
                      "run a zenoh router, so embodiments beyond one LAN join one mesh (no --mesh: it routes every mesh)"),
    "certs": Command("certs", "certs_arguments", "cmd_certs",
                     "a certificate authority and certificates for an authenticated mesh (mutual TLS)"),
    "doctor": Command("tools", "doctor_arguments", "cmd_doctor", "explain why peers are (not) found, and what is wrong in the mesh"),
    "validate": Command("validate", "validate_arguments", "cmd_validate",
                        "check CMION XML files against their schemas and semantics (what `up` checks too)"),
    "launch": Command("tools", "launch_arguments", "cmd_launch",
                      "start several processes of a mesh from one TOML file; Ctrl-C stops them all"),
    "demo": Command("tools", "demo_arguments", "cmd_demo", "run the demonstration scenario (three daemons in a mesh of their own)"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line. With ``command`` one of ``COMMANDS``: the parser that runs it, that verb's
    arguments added (its module imported). Otherwise (``--help``, no verb, a typo): every verb
    listed with its summary, none of their modules imported, and argparse's own messages."""
    if command in COMMANDS:
        return _parser([command])
    return _parser(COMMANDS, fill=False)


def whole_parser() -> argparse.ArgumentParser:
    """Every verb with its arguments (every module imported): what the command line accepts, whole."""
    return _parser(COMMANDS)


def _parser(verbs: Iterable[str], *, fill: bool = True) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cmion-mesh", description="Zenoh peer-to-peer embodiment mesh (CMION rebuilt).",
        epilog="exit codes: 0 succeeded, 1 failed or refused, 2 usage or configuration error, 3 cancelled, "
               "4 outcome unknown (no answer, the target vanished), 130 left on a second Ctrl-C")
    parser.add_argument("--version", action="version", version=f"cmion-mesh {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for verb in verbs:
        command = COMMANDS[verb]
        p = sub.add_parser(verb, help=command.summary)
        if fill:
            module = importlib.import_module(f"cmion_mesh.cli.{command.module}")
            add_arguments: Callable[[argparse.ArgumentParser], None] = getattr(module, command.arguments)
            add_arguments(p)
            p.set_defaults(func=getattr(module, command.handler))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    arguments = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in arguments if not a.startswith("-")), None)  # the top level has options only
    parser = build_parser(command)
    args = parser.parse_args(arguments)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        if getattr(args, "settings", None):
            # up --settings FILE: the file gives what the command line does not. Imported only then:
            # reading TOML is no other command's start-up cost.
            from cmion_mesh.ops import settings

            settings.apply(args, parser, arguments)
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
