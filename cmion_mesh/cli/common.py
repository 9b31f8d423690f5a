"""What the verbs' parsers and handlers share: the options every mesh command takes and the
session settings they give, and the ways a command shows its output (tables, a progress line).
Light on purpose: every verb's module imports it, the ones that never open a session too
(``certs``, ``validate``), and ``up`` before it joins the mesh.
"""

from __future__ import annotations

import argparse
import itertools
import shutil
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

from cmion_mesh import keys
from cmion_mesh.transport import security
from cmion_mesh.transport.base import TransportConfig

#: How long a daemon that can find others looks for the rest of the mesh before it claims its name.
JOIN_WINDOW = 1.0


def mesh_options(parser: argparse.ArgumentParser, *, json_output: bool = True) -> None:
    """``--mesh``, the zenoh options, ``--certs``, ``--identity``, ``--verify-names`` (see
    ``transport_config``) and, with ``json_output``, ``--json``."""
    group = parser.add_argument_group("mesh")
    group.add_argument("--mesh", default=keys.DEFAULT_MESH, help="deployment name (default: %(default)s)")
    zenoh_options(group, connect="zenoh endpoint to connect to, e.g. tcp/10.0.0.5:7447",
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
        json_option(parser)


def transport_config(args: argparse.Namespace, name: str | None = None) -> TransportConfig:
    """The session settings from ``mesh_options``; ``--certs`` turns them into mutual TLS with
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
    return security.apply(config, certs_dir=args.certs, mesh=args.mesh, identity=args.identity, name=name,
                          verify_names=args.verify_names)


def zenoh_options(group: Any, **helps: str) -> None:
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


def subverb(sub: Any, name: str, text: str, example: str, description: str | None = None) -> argparse.ArgumentParser:
    """A verb under a verb (``certs init``, ``custody show``), added to ``sub`` (an
    ``add_subparsers`` result) with its line in the verb's help (``text``), its description (``text``
    as a sentence unless given) and ``example`` ending its ``--help``, as every verb has (kept as
    written: the parser is of its parent's class, ``main.Parser``)."""
    parser: argparse.ArgumentParser = sub.add_parser(name, help=text, description=description or text[0].upper() + text[1:] + ".",
                                                     epilog=f"example: {example}")
    return parser


def json_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="machine-readable output (JSON)")


# One meaning per option, in every command: ``--timeout`` is how long to wait for the outcome (the
# answer, the handshake's end, the mesh's descriptions); ``--join`` how long to look for the peers
# the command needs before it asks (``--join-timeout`` and ``--discover-timeout``, its older
# names, still work).
def timeout_option(parser: argparse.ArgumentParser, default: float, what: str) -> None:
    parser.add_argument("--timeout", type=float, default=default, metavar="SECONDS", help=f"{what} (default: %(default)s s)")


def join_timeout_option(parser: argparse.ArgumentParser, default: float = 5.0) -> None:
    parser.add_argument("--join", "--join-timeout", "--discover-timeout", dest="join_timeout", type=float, default=default,
                        metavar="SECONDS", help="how long to look for the embodiments it needs in the mesh before it gives up "
                                                "(default: %(default)s s)")


def plural(count: int, one: str, many: str | None = None) -> str:
    """``1 rule``, ``2 rules``; ``many`` where adding an s is wrong (competency, competencies)."""
    return f"{count} {one if count == 1 else many or one + 's'}"


def table(rows: Sequence[tuple[str, ...]], width: int | None = None) -> None:
    """Print ``rows`` (the first one the header) as aligned columns that fit ``width`` (default: the
    terminal's): the widest columns are narrowed first and their cells wrap at spaces onto more
    lines, so no word is ever cut (a word longer than its column overflows it whole). ``item``
    keeps a list's item on one line. Into a pipe or a file nothing wraps: one line a row, whole,
    for grep and scripts."""
    if width is None:
        width = shutil.get_terminal_size().columns if sys.stdout.isatty() else sys.maxsize
    for line in table_lines(rows, width):
        print(line)


def table_lines(rows: Sequence[tuple[str, ...]], width: int) -> list[str]:
    import textwrap  # only where a table is printed

    columns = len(rows[0])
    natural = [max(len(r[i]) for r in rows) for i in range(columns)]
    # No column narrower than its longest word or its header, nor than 8, unless that is its whole width.
    floor = [min(natural[i], max(8, len(rows[0][i]), *(len(w) for r in rows for w in r[i].split(" ")))) for i in range(columns)]
    widths = list(natural)
    for _ in range(sum(natural)):  # bounded: each round narrows one column by one
        if sum(widths) + 2 * (columns - 1) <= width:
            break
        shrinkable = [i for i in range(columns) if widths[i] > floor[i]]
        if not shrinkable:
            break
        widths[max(shrinkable, key=lambda i: widths[i])] -= 1
    lines: list[str] = []
    for row in rows:
        cells = [textwrap.wrap(cell, w, break_long_words=False, break_on_hyphens=False) or [""]
                 for cell, w in zip(row, widths, strict=True)]
        for n in range(max(len(c) for c in cells)):
            line = "  ".join((c[n] if n < len(c) else "").ljust(w) for c, w in zip(cells, widths, strict=True))
            lines.append(line.rstrip().replace(_KEEP, " "))
    return lines


#: A space that does not wrap (textwrap breaks at ASCII white space only).
_KEEP = "\xa0"


def item(text: str) -> str:
    """``text`` as one unbreakable item of a table's cell (``GoTo *`` never split after GoTo)."""
    return text.replace(" ", _KEEP)


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
