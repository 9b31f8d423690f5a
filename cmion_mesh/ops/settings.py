"""One settings file per device: every option of ``cmion-mesh up`` in a TOML file.

``cmion-mesh up --settings device.toml`` reads the file, then the command line: an option given
on the command line wins over the file, which wins over the option's default (flag > settings >
default). ``device.example.toml`` beside this module is the documented example: every key,
commented out, with its default.

The file is flat: one key per option, named as the option without its dashes (``state-dir =
"/var/lib/cmion-mesh"`` for ``--state-dir``), except two: ``architecture`` is ``up``'s PATH (the
ArchitectureConfiguration file or folder, or a shipped embodiment's name) and ``multicast =
false`` is ``--no-multicast``. Repeatable options take a list (``connect = ["tcp/10.0.0.5:7447"]``).
Relative paths are taken from the settings file's folder. The file is read as the launch file is
(``tomlsafe``: bounded size and nesting, UTF-8); each problem names the file, the line and the
key: an unknown key with the closest known one and the list of known keys, a value of the wrong
type with the type wanted. Every problem is reported at once, as one ``ConfigError`` (exit code 2).

Wiring (the command line, ``up``; each one call):

* ``add_argument(parser)`` on ``up``'s parser: ``--settings FILE``;
* ``apply(args, parser, argv)`` right after ``parser.parse_args(argv)`` and before the command
  runs (inside the ``try`` that turns a ``ConfigError`` into exit code 2): with ``--settings``,
  it sets on ``args`` every value of the file whose option the command line does not give.
  ``parser`` and ``argv`` are the ones just parsed (the whole command line: the options given
  are found by parsing it again with no defaults).

This module is part of the command line's edge: ``given_options`` reads ``argv`` again with
``argparse``, imported there only (importing the module does not load it).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

import msgspec

from cmion_mesh import keys, tomlsafe
from cmion_mesh.transport.base import LEASE_MS

if TYPE_CHECKING:
    import argparse

WHAT: Final = "settings file"
EXAMPLE: Final = Path(__file__).with_name("device.example.toml")
#: Longest zenoh lease accepted (ms): beyond, a frozen peer would not be noticed for hours.
MAX_LEASE_MS: Final = 3_600_000


class Option(msgspec.Struct, frozen=True):
    """One key of the settings file: the option of ``up`` it gives (``dest``, as ``argparse``
    names it), its kind of value, and what the example file says of it."""

    key: str
    dest: str
    kind: str  # name, text, path, file, folder, architecture, int, bool, list, names, choice, address
    help: str
    default: Any = None  # None: the option has no value unless given
    example: Any = None  # the value shown (commented out) in the example file when there is no default
    choices: tuple[str, ...] = ()
    invert: bool = False  # the value given is the option's negation (multicast = false: --no-multicast)


#: Every option of ``up``, in the order of ``up --help``.
OPTIONS: Final[tuple[Option, ...]] = (
    Option("architecture", "path", "architecture",
           "the ArchitectureConfiguration file or folder, or a shipped embodiment's name (up's PATH)", example="robot"),
    Option("name", "name", "name", "the embodiment's name (default: the device table's devicename, else the configuration's)",
           example="robot"),
    Option("world-model", "world_model", "file", "CMION WorldModel init file (replaces the configuration's)",
           example="WorldModel.xml"),
    Option("rules", "rules", "file", "CMION CompetencyManagerRules file (replaces the configuration's)",
           example="CompetencyManagerRules.xml"),
    Option("library", "library", "file", "CMION CompetencyLibrary file (replaces the configuration's)",
           example="CompetencyLibrary.xml"),
    Option("remote-type", "remote_type", "list", "competency types served by other processes (serve-competency)",
           example=["Speech"]),
    Option("lease-ms", "lease_ms", "int", "zenoh link lease: how fast a frozen peer is noticed (ms)", default=LEASE_MS),
    Option("state-dir", "state_dir", "path", "durable state: migration records, persistent properties; one daemon per folder "
           "(default: ~/.local/state/cmion-mesh/<mesh>/<name>)", example="state"),
    Option("companion", "companion", "name", "a companion born here on the first start, if no live embodiment hosts it",
           example="companion"),
    Option("web", "web", "address", "serve the body's web page on [HOST:]PORT (loopback unless HOST says otherwise)",
           example="127.0.0.1:8080"),
    Option("admit", "admit", "names", "companions allowed to migrate in, each NAME or NAME=PUBLICKEY (default: any)",
           example=["companion"]),
    Option("mesh", "mesh", "name", "deployment name", default=keys.DEFAULT_MESH),
    Option("connect", "connect", "list", "zenoh endpoints to connect to", example=["tcp/10.0.0.5:7447"]),
    Option("listen", "listen", "list", "zenoh endpoints to listen on", example=["tcp/0.0.0.0:7447"]),
    Option("config", "config", "file", "zenoh JSON5 configuration file", example="zenoh.json5"),
    Option("multicast", "no_multicast", "bool", "scout for peers by multicast (false: --no-multicast)", default=True, invert=True),
    Option("multicast-interface", "multicast_interface", "text", "interface to scout on (default: zenoh's choice)",
           example="eth0"),
    Option("certs", "certs", "folder", "certificates folder (cmion-mesh certs): mutual TLS only, with access control",
           example="certs"),
    Option("identity", "identity", "name", "which certificate of the folder to use (default: the embodiment's name)",
           example="robot"),
    Option("verify-names", "verify_names", "bool", "with certs: check that a peer's certificate names the address dialled",
           default=False),
    Option("log-level", "log_level", "choice", "the least important log lines written", default="info",
           choices=("debug", "info", "warning", "error")),
    Option("log-format", "log_format", "choice", "text lines, or one JSON object per line", default="text",
           choices=("text", "json")),
    Option("log-file", "log_file", "path", "append the log lines to this file instead of standard error",
           example="cmion-mesh.log"),
    Option("metrics", "metrics", "address", "serve metrics and health on [HOST:]PORT (loopback unless HOST says otherwise)",
           example="127.0.0.1:9464"),
)
BY_KEY: Final = {o.key: o for o in OPTIONS}


class Settings(msgspec.Struct, frozen=True):
    """A settings file as read: ``values`` by ``argparse`` destination (only the keys the file
    gives, paths made absolute), and the line of each key."""

    path: Path
    values: dict[str, Any] = msgspec.field(default_factory=dict)
    lines: dict[str, int | None] = msgspec.field(default_factory=dict)

    def merge(self, args: argparse.Namespace, given: Collection[str] = ()) -> argparse.Namespace:
        """Set on ``args`` each value of the file whose destination is not in ``given`` (the
        options the command line gave); ``args`` is returned."""
        for dest, value in self.values.items():
            if dest not in given:
                setattr(args, dest, list(value) if isinstance(value, list) else value)
        return args


def add_argument(parser: Any) -> None:
    """``--settings FILE`` on ``parser`` (an ``argparse`` parser)."""
    parser.add_argument("--settings", metavar="FILE",
                        help="read every option not given on the command line from this TOML file (see docs/deploy.md)")


def apply(args: argparse.Namespace, parser: argparse.ArgumentParser, argv: Sequence[str]) -> Settings | None:
    """With ``args.settings``: read that file and set on ``args`` what it gives and ``argv`` does
    not. None without ``--settings``."""
    path = getattr(args, "settings", None)
    if not path:
        return None
    settings = load(path)
    settings.merge(args, given_options(parser, argv))
    return settings


def given_options(parser: argparse.ArgumentParser, argv: Sequence[str]) -> set[str]:
    """The destinations ``argv`` gives a value to, as ``parser`` (and the sub-command's parser)
    parses it: it is parsed again with every default taken away, so an option given with its
    default value counts as given."""
    import argparse

    saved: list[tuple[Any, str, Any]] = []

    def strip(p: argparse.ArgumentParser) -> None:
        # argparse has no public way to parse without defaults: its actions' defaults and each
        # parser's set_defaults() are set aside for the second parse and put back after it.
        saved.append((p, "_defaults", p._defaults))
        p._defaults = {}
        for action in p._actions:
            saved.append((action, "default", action.default))
            action.default = argparse.SUPPRESS
            if isinstance(action, argparse._SubParsersAction):
                for sub in {id(s): s for s in action.choices.values()}.values():
                    strip(sub)

    try:
        strip(parser)
        namespace, _ = parser.parse_known_args(list(argv))
    finally:
        for owner, attribute, value in reversed(saved):
            setattr(owner, attribute, value)
    return set(vars(namespace))


def load(path: str | os.PathLike[str], *, check_files: bool = True) -> Settings:
    """Read and check a settings file; every problem in one ``ConfigError`` (naming the file and
    the line of the first). ``check_files``: files and folders named must exist (those the
    daemon only reads)."""
    from cmion_mesh.diagnostics import Diagnostics  # not for the parser (add_argument): it imports lxml

    file = Path(path)
    text, data = tomlsafe.load(file, WHAT)
    found = Diagnostics()
    headers = tomlsafe.header_lines(text)
    folder = file.resolve().parent
    values: dict[str, Any] = {}
    lines: dict[str, int | None] = {}
    for key, value in data.items():
        line = headers.get((key, 0)) or tomlsafe.key_line(text, 0, key)  # a table's header, else the key's line
        lines[key] = line
        option = BY_KEY.get(key)
        if option is None:
            from cmion_mesh.client import did_you_mean

            found.error(f"unknown key {key!r}{did_you_mean(key, BY_KEY)} (known: {', '.join(BY_KEY)})", file, line)
            continue
        try:
            checked = _check(option, value, folder, check_files)
        except ValueError as exc:
            found.error(f"{key!r} must be {exc}", file, line)
            continue
        values[option.dest] = not checked if option.invert else checked
    found.raise_if_errors()
    return Settings(path=file, values=values, lines=lines)


# --- values ---------------------------------------------------------------------------------------


def _show(value: Any) -> str:
    return f"{type(value).__name__} {value!r}"[:80]


def _text(value: Any, what: str = "a string") -> str:
    if not isinstance(value, str) or not value or "\0" in value:
        raise ValueError(f"{what} (not empty, no NUL character), not {_show(value)}")
    return value


def _name(value: Any) -> str:
    if not isinstance(value, str) or not keys.is_name(value):
        raise ValueError(f"a valid name (no / * $ # ? or spaces, no leading @), not {_show(value)}")
    return value


def _list(value: Any, item: Callable[[Any], str], what: str) -> list[str]:
    if not isinstance(value, list):
        raise ValueError(f"a list of {what}, e.g. [\"...\"], not {_show(value)}")
    try:
        return [item(v) for v in value]
    except ValueError:
        raise ValueError(f"a list of {what}, not {_show(value)}") from None


def _admitted(value: Any) -> str:
    name, _, _key = _text(value).partition("=")
    _name(name)
    return str(value)


def _address(value: Any) -> str:
    text = str(value) if isinstance(value, int) and not isinstance(value, bool) else value
    if isinstance(text, str):
        host, _, port = text.rpartition(":")
        if port.isascii() and port.isdigit() and int(port) <= 65535 and "\0" not in host and " " not in host:
            return text
    raise ValueError(f"a port or \"HOST:PORT\" (port 0 to 65535), not {_show(value)}")


def _check(option: Option, value: Any, folder: Path, check_files: bool) -> Any:
    """The value the option gets from ``value`` as the file gives it; ``ValueError`` saying what
    was expected."""
    kind = option.kind
    if kind == "bool":
        if not isinstance(value, bool):
            raise ValueError(f"true or false, not {_show(value)}")
        return value
    if kind == "int":
        if not isinstance(value, int) or isinstance(value, bool) or not 0 < value <= MAX_LEASE_MS:
            raise ValueError(f"a whole number from 1 to {MAX_LEASE_MS}, not {_show(value)}")
        return value
    if kind == "choice":
        if not isinstance(value, str) or value.lower() not in option.choices:
            raise ValueError(f"one of {', '.join(option.choices)}, not {_show(value)}")
        return value.lower()
    if kind == "name":
        return _name(value)
    if kind == "list":
        return _list(value, _text, "strings")
    if kind == "names":
        return _list(value, _admitted, "NAME or NAME=PUBLICKEY strings")
    if kind == "address":
        return _address(value)
    text = _text(value)
    if kind == "text":
        return text
    path = folder / os.path.expanduser(text)
    if kind == "architecture":
        if "/" not in text and not path.exists():
            _shipped(text, check_files)
            return text  # a shipped embodiment's name
        kind = "file or folder"
    if check_files:
        if kind == "file" and not path.is_file():
            raise ValueError(f"an existing file: no file at {str(path)!r}")
        if kind in ("folder", "file or folder") and not path.exists():
            raise ValueError(f"an existing {kind}: nothing at {str(path)!r}")
    return str(path)


def _shipped(name: str, check: bool) -> None:
    from cmion_mesh.resources import data_dir

    shipped = data_dir("embodiments")
    if check and not (shipped / name / "ArchitectureConfiguration.xml").is_file():
        names = sorted(p.name for p in shipped.iterdir() if p.is_dir())
        raise ValueError(f"a file or folder beside the settings file, or a shipped embodiment ({', '.join(names)}), "
                         f"not {name!r}")
