# PYTHON_ARGCOMPLETE_OK (argcomplete's mark: this command completes itself in bash, zsh, fish)
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
3 cancelled, 4 outcome unknown, 130 left on a second Ctrl-C; 141, quietly, when the reader of its
output left (``| head``), as a command SIGPIPE ends.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import re
import shlex
import signal
import sys
from collections.abc import Callable, Iterable, Sequence
from typing import Any, NamedTuple, NoReturn

from cmion_mesh import __version__
from cmion_mesh.errors import ExitCode, MeshError, exit_code


class Command(NamedTuple):
    """One verb: ``module`` (in ``cmion_mesh.cli``) has ``arguments(parser)``, which adds the verb's
    arguments (and may give a longer description) to its parser, and ``handler(args) -> exit code``;
    ``summary`` is its line in ``cmion-mesh --help`` and its description unless it gives one;
    ``example`` (lines) ends its ``--help``."""

    module: str
    arguments: str
    handler: str
    summary: str
    example: str


#: Every verb, in the order ``cmion-mesh --help`` lists them.
COMMANDS: dict[str, Command] = {
    "up": Command("daemon", "up_arguments", "cmd_up", "run an embodiment daemon until SIGINT/SIGTERM",
                  "cmion-mesh up robot\ncmion-mesh up screen --web 127.0.0.1:8081 --connect tcp/127.0.0.1:7447"),
    "service": Command("service", "service_arguments", "cmd_service",
                       "the systemd unit that runs an embodiment daemon (service unit NAME)",
                       "cmion-mesh service unit robot --metrics 127.0.0.1:9464"),
    "bb": Command("stores", "bb_arguments", "cmd_store", "read, write and watch an embodiment's blackboard",
                  "cmion-mesh bb get robot navigation/state\ncmion-mesh bb set robot battery 0.8 --persistent"),
    "wm": Command("stores", "wm_arguments", "cmd_store", "read, write and watch an embodiment's world model",
                  "cmion-mesh wm tree robot\ncmion-mesh wm add robot Visitor present=true"),
    "serve-competency": Command("serve", "competency_arguments", "cmd_serve_competency",
                                "host a competency for an embodiment from this process (remote competency)",
                                "cmion-mesh serve-competency my.module:Arm --embodiment robot --parameters fast"),
    "serve-mind": Command("serve", "mind_arguments", "cmd_serve_mind",
                          "run a mind in this process, driving an embodiment over the mesh",
                          "cmion-mesh serve-mind my.module:MyMind --embodiment robot"),
    "peers": Command("actions", "peers_arguments", "cmd_peers", "list the embodiments alive in the mesh, with what they can do",
                     "cmion-mesh peers\ncmion-mesh peers robot          # everything robot says of itself"),
    "keys": Command("wire", "keys_arguments", "cmd_keys",
                    "the keys that exist in the mesh, with their kind (as ros2 topic list)",
                    "cmion-mesh keys\ncmion-mesh keys 'robot/rq/**'"),
    "pub": Command("wire", "pub_arguments", "cmd_pub", "publish one message on a key (as ros2 topic pub)",
                   "cmion-mesh pub robot/ev/sensor/Touched '{\"where\": \"head\"}'"),
    "call": Command("wire", "call_arguments", "cmd_call",
                    "send a request to a key and print its decoded answer (as ros2 service call)",
                    "cmion-mesh call robot/rq/bb/set_property '{\"container\": \"\", \"name\": \"battery\", \"value\": 0.8}'"),
    "act": Command("actions", "act_arguments", "cmd_act",
                   "send a mind action to an embodiment and wait for its outcome (exit code says it)",
                   "cmion-mesh act robot GoTo Kitchen\ncmion-mesh act robot GoTo Lab --detach"),
    "cancel": Command("actions", "cancel_arguments", "cmd_cancel", "cancel a running action",
                      "cmion-mesh cancel robot 3f2a9c1e"),
    "remote-action": Command("actions", "remote_action_arguments", "cmd_remote_action",
                             "tell an embodiment's minds that another agent did an action (CMION's RemoteActionSimulator)",
                             "cmion-mesh remote-action robot Greet Spirit --subject Visitor"),
    "events": Command("observe", "events_arguments", "cmd_events", "follow the event stream (filterable)",
                      "cmion-mesh events --embodiment robot --component manager"),
    "record": Command("recording", "record_arguments", "cmd_record",
                      "record everything the mesh says to an MCAP file (record info FILE: summarise one)",
                      "cmion-mesh record -o visit.mcap\ncmion-mesh record 'robot/ev/**' --duration 60 -o robot.mcap\n"
                      "cmion-mesh record info visit.mcap"),
    "replay": Command("recording", "replay_arguments", "cmd_replay",
                      "publish a recording's events into a mesh, at their timing or faster",
                      "cmion-mesh replay visit.mcap --mesh test --rate 10"),
    "foxglove": Command("recording", "foxglove_arguments", "cmd_foxglove",
                        "serve the mesh live to Foxglove (the channels and schemas of a recording)",
                        "cmion-mesh foxglove --web 127.0.0.1:8765"),
    "hz": Command("observe", "hz_arguments", "cmd_hz", "the rate of publications on a key expression (as ros2 topic hz)",
                  "cmion-mesh hz 'robot/ev/**' --duration 10"),
    "echo": Command("observe", "echo_arguments", "cmd_echo",
                    "print what is published on a key expression, decoded (as ros2 topic echo)",
                    "cmion-mesh echo 'robot/ev/manager/*'\ncmion-mesh echo '@alive/*'"),
    "view": Command("view", "view_arguments", "cmd_view",
                    "a live view of the mesh in the browser (a graph of the embodiments with the companion travelling, "
                    "a timeline to scrub back, events, blackboard, world model, plans), or of a recording",
                    "cmion-mesh view --web 127.0.0.1:8090\ncmion-mesh view --recording visit.mcap"),
    "migrate": Command("actions", "migrate_arguments", "cmd_migrate",
                       "move a companion to another embodiment (waits for the handshake's end)",
                       "cmion-mesh migrate spirit --to screen"),
    "custody": Command("actions", "custody_arguments", "cmd_custody",
                       "a companion's custody across the mesh: who holds it, forks of its chain and how to resolve them",
                       "cmion-mesh custody show spirit\ncmion-mesh custody resolve spirit --keep robot"),
    "mcp": Command("mcp", "mcp_arguments", "cmd_mcp",
                   "serve a companion to MCP clients: its body's actions as tools, its world model as resources",
                   "cmion-mesh mcp spirit --allow-actions           # what a desktop client starts\n"
                   "cmion-mesh mcp spirit --http --allow-actions    # then http://127.0.0.1:8766/mcp"),
    "invite": Command("actions", "invite_arguments", "cmd_invite",
                      "have an empty embodiment invite the companion (CMION's migration invitation)",
                      "cmion-mesh invite screen"),
    "router": Command("tools", "router_arguments", "cmd_router",
                      "run a zenoh router, so embodiments beyond one LAN join one mesh (no --mesh: it routes every mesh)",
                      "cmion-mesh router --listen tcp/0.0.0.0:7447"),
    "certs": Command("certs", "certs_arguments", "cmd_certs",
                     "a certificate authority and certificates for an authenticated mesh (mutual TLS)",
                     "cmion-mesh certs init pki/\ncmion-mesh certs issue pki/ robot"),
    "doctor": Command("tools", "doctor_arguments", "cmd_doctor", "explain why peers are (not) found, and what is wrong in the mesh",
                      "cmion-mesh doctor --mesh lab\ncmion-mesh doctor --certs pki/ --identity operator"),
    "validate": Command("validate", "validate_arguments", "cmd_validate",
                        "check CMION XML files against their schemas and semantics (what `up` checks too)",
                        "cmion-mesh validate embodiments/robot\ncmion-mesh validate --strict my-cmion-project/"),
    "launch": Command("tools", "launch_arguments", "cmd_launch",
                      "start several processes of a mesh from one TOML file; Ctrl-C stops them all",
                      "cmion-mesh launch spirit\ncmion-mesh launch my.launch.toml --check"),
    "demo": Command("tools", "demo_arguments", "cmd_demo", "run the demonstration scenario (three daemons in a mesh of their own)",
                    "cmion-mesh demo\ncmion-mesh demo --web --record demo.mcap"),
}

#: Verbs with a verb of their own under them whose arguments differ from the verb's (``record info
#: FILE`` beside ``record [FILTER...]``): (verb, word) -> its command.
SUBVERBS: dict[tuple[str, str], Command] = {
    ("record", "info"): Command("recording", "record_info_arguments", "cmd_record_info",
                                "summarise recordings: duration, counts per channel, migrations, embodiments, drops",
                                "cmion-mesh record info visit.mcap\ncmion-mesh record info visit-0000.mcap visit-0001.mcap --json"),
}


def build_parser(command: str | None = None, word: str | None = None) -> argparse.ArgumentParser:
    """The command line. With ``command`` one of ``COMMANDS``: the parser that runs it, that verb's
    arguments added (its module imported); with ``word`` naming one of its ``SUBVERBS`` (``record
    info``), that one's instead. Otherwise (``--help``, no verb, a typo): every verb listed with its
    summary, none of their modules imported, and argparse's own messages."""
    if command in COMMANDS:
        return _parser([command], word=word)
    return _parser(COMMANDS, fill=False)


def whole_parser() -> argparse.ArgumentParser:
    """Every verb with its arguments (every module imported): what the command line accepts, whole."""
    return _parser(COMMANDS)


class HelpFormatter(argparse.HelpFormatter):
    """argparse's, but an epilog's lines (the examples) are kept as written."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("example"):
            return "\n".join(indent + line for line in text.splitlines())
        return super()._fill_text(text, width, indent)


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors are one line (exit 2) that says what was meant when
    a verb or an option is a typo of one (``peer``: ``peers``; ``--mehs``: ``--mesh``). Its help
    keeps examples as written (``HelpFormatter``), in the parsers of verbs under a verb too (they
    are of their parent's class: ``common.subverb``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(ExitCode.USAGE, f"{self.prog}: error: {hint(self, message)}\n")


#: ``--join``'s spellings (``common.join_timeout_option``).
JOIN_SPELLINGS = ("--join", "--join-timeout", "--discover-timeout")


def hint(parser: argparse.ArgumentParser, message: str) -> str:
    """argparse's ``message``, with a did-you-mean for an unknown choice or option."""
    import difflib  # only on a usage error

    required = re.match(r"the following arguments are required: (.*)$", message)
    if required:
        # argparse lists a missing nargs="*" positional as required (act's parameters): name only the needed.
        optional = {action.metavar or action.dest for action in parser._actions
                    if not action.option_strings and action.nargs in ("*", "?")}
        needed = [name for name in required.group(1).split(", ") if name not in optional]
        return f"the following arguments are required: {', '.join(needed)}" if needed else message
    choice = re.match(r"(argument .*?: invalid choice: '(.*?)') \(choose from (.*)\)$", message)
    if choice:
        options = re.findall(r"'([^']*)'", choice.group(3))
        close = difflib.get_close_matches(choice.group(2), options, n=1, cutoff=0.6)
        if close:
            return f"{choice.group(1)} (did you mean '{close[0]}'?)"
        return message
    unknown = re.match(r"unrecognized arguments: (.*)$", message)
    if unknown:
        known = option_strings(parser)
        for word in unknown.group(1).split():
            if word.split("=", 1)[0] in JOIN_SPELLINGS and "--timeout" in known:
                # peers, doctor: finding the embodiments is their whole work, one wait for both
                return f"{message} (this command has no --join: its --timeout is its whole wait, looking for the " \
                       "embodiments included: use --timeout SECONDS)"
            if word.startswith("-"):
                close = difflib.get_close_matches(word.split("=", 1)[0], known, n=1, cutoff=0.6)
                if close:
                    return f"{message} (did you mean '{close[0]}'?)"
    return message


def option_strings(parser: argparse.ArgumentParser) -> list[str]:
    """Every long option of ``parser`` and of the parsers below it."""
    found: list[str] = []
    for action in parser._actions:  # argparse has no public walk of its actions
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found += option_strings(sub)
        found += [o for o in action.option_strings if o.startswith("--")]
    return sorted(set(found))


def _parser(verbs: Iterable[str], *, fill: bool = True, word: str | None = None) -> argparse.ArgumentParser:
    parser = Parser(
        prog="cmion-mesh", description="Zenoh peer-to-peer embodiment mesh (CMION rebuilt).",
        epilog="exit codes: 0 succeeded, 1 failed or refused, 2 usage or configuration error, 3 cancelled, "
               "4 outcome unknown (no answer, the target vanished), 130 left on a second Ctrl-C")
    parser.add_argument("--version", action="version", version=f"cmion-mesh {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    for verb in verbs:
        command = COMMANDS[verb]
        p = sub.add_parser(verb, help=command.summary, formatter_class=HelpFormatter, description=_description(command),
                           epilog=_examples(command))
        if not fill:
            continue
        nested = SUBVERBS.get((verb, word or ""))
        if nested is not None:
            # `record info ...`: the verb's own parser holds the word, whose parser is the subverb's.
            words = p.add_subparsers(dest="subverb", required=True, metavar="ACTION", parser_class=Parser)
            p = words.add_parser(word or "", help=nested.summary, formatter_class=HelpFormatter, description=_description(nested),
                                 epilog=_examples(nested))
            command = nested
        module = importlib.import_module(f"cmion_mesh.cli.{command.module}")
        add_arguments: Callable[[argparse.ArgumentParser], None] = getattr(module, command.arguments)
        add_arguments(p)
        p.set_defaults(func=getattr(module, command.handler))
    return parser


def _description(command: Command) -> str:
    """The summary as a sentence: a verb's description until its module gives a longer one."""
    return command.summary[0].upper() + command.summary[1:] + "."


def _examples(command: Command) -> str:
    """The end of a verb's ``--help``: its examples, one a line."""
    lines = command.example.splitlines()
    return ("example:\n" if len(lines) == 1 else "examples:\n") + "\n".join(f"  {line}" for line in lines)


def _verb(arguments: Sequence[str]) -> tuple[str | None, str | None]:
    """The verb (the top level has options only) and, when it has ``SUBVERBS``, the word after it."""
    words = [a for a in arguments if not a.startswith("-")]
    command = words[0] if words else None
    word = words[1] if len(words) > 1 and (command, words[1]) in SUBVERBS else None
    return command, word


def parse(parser: argparse.ArgumentParser, arguments: Sequence[str]) -> argparse.Namespace:
    """``parser.parse_args``, but a verb that sets ``intermixed`` (the name of its ``nargs="*"``
    positional, ``wm add``'s PROPERTY=VALUE) also takes those words after its options: argparse
    ends such a list at the first option and leaves the rest unrecognized (its
    ``parse_intermixed_args`` refuses subparsers)."""
    args, extra = parser.parse_known_args(arguments)
    field = getattr(args, "intermixed", None)
    if extra and field and all("=" in word and not word.startswith("-") for word in extra):
        setattr(args, field, [*getattr(args, field), *extra])
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    arguments = list(sys.argv[1:] if argv is None else argv)
    if "_ARGCOMPLETE" in os.environ:  # the shell asks for completions (argcomplete's protocol)
        from cmion_mesh.cli import complete

        complete.autocomplete(build_parser, _verb)
    if argv is None:
        # This process is the command: loading it makes tens of thousands of objects that live as
        # long as the process and no garbage, and the cyclic collector's passes over them are start
        # time for nothing. Paused while the command loads; what it loaded is then frozen (never
        # looked at again) before the collector resumes, in ``_main``.
        gc.disable()
    try:
        code = _main(arguments, loading=argv is None)
        sys.stdout.flush()  # here, not at exit: a reader gone (| head) is then ours to say nothing of
        return code
    except BrokenPipeError:
        # The reader of our output left (| head): stop quietly, as other commands do. Standard output
        # goes to /dev/null so that Python's flush at exit does not complain again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE


def _main(arguments: list[str], loading: bool = False) -> int:
    if arguments and arguments[0].startswith("-") and arguments[0] not in ("-h", "--help", "--version"):
        # `cmion-mesh --mesh x peers`: the top level takes no option but --help and --version.
        at = next((i for i, a in enumerate(arguments) if a in COMMANDS), None)
        moved = ("COMMAND " + " ".join(map(shlex.quote, arguments)) if at is None else
                 " ".join(shlex.quote(a) for a in [arguments[at], *arguments[at + 1:], *arguments[:at]]))
        build_parser().error(f"options go after the command: cmion-mesh {moved}")
    command, word = _verb(arguments)
    parser = build_parser(command, word)
    args = parse(parser, arguments)
    func: Callable[[argparse.Namespace], int] = args.func
    if loading:
        gc.freeze()
        gc.enable()
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
    except BrokenPipeError:
        raise  # main's: no error line for a reader that left
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
