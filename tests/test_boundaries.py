"""The package's inner boundaries: argparse only at the edge (cli/), no import of bench/, no
import cycle between certs and security, one set of exit codes; the command table imports only
the verb that runs."""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from pathlib import Path

from cmion_mesh.errors import ConfigError, ExitCode, InvalidName, NotAlive, NotReached, RequestRejected, Vanished, exit_code

PACKAGE = Path(__file__).resolve().parents[1] / "cmion_mesh"
#: The modules that read a command line: the package's (every module of cli/), the handshake
#: simulation's own, and the settings file's (it parses ``up``'s command line again to know which
#: options it gives).
COMMAND_LINES = ("testing/simulation.py", "ops/settings.py")


def imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports, at any level (inside functions too)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def modules() -> dict[str, set[str]]:
    return {str(p.relative_to(PACKAGE)): imported_modules(p) for p in sorted(PACKAGE.rglob("*.py"))}


def test_only_cli_imports_argparse() -> None:
    offenders = sorted(name for name, imports in modules().items()
                       if "argparse" in imports and name not in COMMAND_LINES and not name.startswith("cli/"))
    assert offenders == [], f"argparse is read by the command line only (cli/), but also imported by: {offenders}"


def test_importing_the_library_does_not_load_argparse() -> None:
    code = ("import importlib, pkgutil, sys, cmion_mesh\n"
            "for m in pkgutil.walk_packages(cmion_mesh.__path__, 'cmion_mesh.'):\n"
            "    if not m.name.startswith('cmion_mesh.cli.'): importlib.import_module(m.name)\n"
            "print(sorted(k for k in sys.modules if k == 'argparse' or k.split('.')[0] == 'bench'))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert result.stdout.strip() == "[]", result.stdout


def test_nothing_in_the_package_imports_bench() -> None:
    offenders = sorted(name for name, imports in modules().items() if any(m.split(".")[0] == "bench" for m in imports))
    assert offenders == [], f"bench/ is not installed with the package: {offenders} import it"


def loaded_by(code: str) -> list[str]:
    """The heavy modules (cryptography, lxml, the certificates, the planner) a fresh interpreter has
    loaded after running ``code``."""
    probe = (f"import sys\n{code}\n"
             "heavy = ('cryptography', 'lxml', 'cmion_mesh.transport.certs', 'cmion_mesh.minds.planner.mind', "
             "'cmion_mesh.minds.planner.search')\n"
             "print(sorted(m for m in sys.modules if m in heavy or m.split('.')[0] in heavy[:2]))\n")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True)
    return [m for m in ast.literal_eval(result.stdout.strip()) if "." not in m or m.startswith("cmion_mesh")]


def test_a_one_shot_command_loads_no_xml_crypto_or_planner() -> None:
    # what `cmion-mesh peers` / `bb get` load before they open their session: start time is theirs
    code = ("import cmion_mesh.cli.main as cli\n"
            "cli.build_parser('peers').parse_args(['peers'])\n"
            "import cmion_mesh.client, cmion_mesh.presence, cmion_mesh.transport.zenoh")
    assert loaded_by(code) == []


def test_a_daemon_without_certificates_or_companion_loads_no_crypto() -> None:
    # `up` reads XML; it signs nothing until a companion is born or arrives, and --certs is off
    code = ("import cmion_mesh.cli.main as cli\n"
            "cli.build_parser('up').parse_args(['up', 'robot'])\n"
            "import cmion_mesh.body.embodiment, cmion_mesh.body.validate, cmion_mesh.transport.security, cmion_mesh.migration.devices, "
            "cmion_mesh.statedir")
    assert loaded_by(code) == ["lxml"]


def test_no_import_cycle_between_certs_and_security() -> None:
    found = modules()
    assert "cmion_mesh.transport.certs" in found["transport/security.py"]  # security builds on certs...
    assert "cmion_mesh.transport.security" not in found["transport/certs.py"], "...never the reverse"


def test_one_set_of_exit_codes() -> None:
    assert [int(c) for c in ExitCode] == [0, 1, 2, 3, 4, 130]
    assert exit_code(ConfigError("x")) == ExitCode.USAGE and exit_code(InvalidName("x")) == ExitCode.USAGE
    assert exit_code(RequestRejected("x")) == ExitCode.FAILED and exit_code(NotAlive("x")) == ExitCode.FAILED
    assert exit_code(NotReached("x")) == ExitCode.UNKNOWN and exit_code(Vanished("x")) == ExitCode.UNKNOWN
    for path in PACKAGE.rglob("*.py"):
        source = path.read_text()
        assert "EXIT_OK" not in source and "EXIT_FAILED" not in source, f"{path.name} defines exit codes of its own"


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))  # argparse has no public walk
    return dict(subs.choices)


def cli_modules_loaded_by(code: str) -> list[str]:
    """The modules of cmion_mesh.cli a fresh interpreter has loaded after running ``code``."""
    probe = (f"import sys\n{code}\n"
             "print(sorted(m for m in sys.modules if m == 'cmion_mesh.cli' or m.startswith('cmion_mesh.cli.')))\n")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True)
    return list(ast.literal_eval(result.stdout.strip().splitlines()[-1]))


def test_the_command_table_lists_every_verb_without_importing_one() -> None:
    # --help, no verb and a typo: every verb with its summary from the table, no verb's module imported
    from cmion_mesh.cli import main as cli

    listed = cli.build_parser()
    assert list(subcommands(listed)) == list(cli.COMMANDS)
    text = listed.format_help()
    for verb, command in cli.COMMANDS.items():
        assert verb in text and " ".join(command.summary.split()[:4]) in " ".join(text.split()), verb
    code = ("from cmion_mesh.cli.main import main\n"
            "import contextlib, io\n"
            "for argv in (['--help'], ['pers'], []):\n"
            "    with contextlib.suppress(SystemExit), contextlib.redirect_stdout(io.StringIO()), "
            "contextlib.redirect_stderr(io.StringIO()):\n"
            "        main(argv)\n")
    assert cli_modules_loaded_by(code) == ["cmion_mesh.cli", "cmion_mesh.cli.main"]
    typo = subprocess.run([sys.executable, "-m", "cmion_mesh.cli", "pers"], capture_output=True, text=True, timeout=60)
    assert typo.returncode == ExitCode.USAGE
    assert "cmion-mesh: error: argument COMMAND: invalid choice: 'pers' (choose from 'up', " in typo.stderr, typo.stderr


def test_a_verb_imports_its_own_module_only() -> None:
    code = ("from cmion_mesh.cli.main import build_parser\n"
            "build_parser('bb').parse_args(['bb', 'get', 'robot'])\n")
    assert cli_modules_loaded_by(code) == ["cmion_mesh.cli", "cmion_mesh.cli.common", "cmion_mesh.cli.main",
                                           "cmion_mesh.cli.session", "cmion_mesh.cli.stores"]


def test_the_parser_of_one_command_parses_as_the_whole_one() -> None:
    # build_parser(verb) adds that verb's arguments only (its module's): what it parses does not
    # change, and every verb of the table names functions its module has
    from cmion_mesh.cli import main as cli

    whole = subcommands(cli.whole_parser())
    assert list(whole) == list(cli.COMMANDS)
    for name in cli.COMMANDS:
        only = subcommands(cli.build_parser(name))
        assert list(only) == [name]
        assert [a.dest for a in only[name]._actions] == [a.dest for a in whole[name]._actions], name
        assert only[name].description == whole[name].description, name
    for argv in (["peers", "--mesh", "m", "--json"], ["up", "robot", "--name", "x", "--connect", "tcp/127.0.0.1:1"],
                 ["bb", "set", "e", "a/b", "3", "--persistent"], ["certs", "init", "d"], ["custody", "show", "c"]):
        assert vars(cli.build_parser(argv[0]).parse_args(argv)) == vars(cli.whole_parser().parse_args(argv))
