"""The package's inner boundaries: its layers (each imports only its own and those below, with no
circle), argparse only at the edge (cli/), no import of bench/, one set of exit codes; the command
table imports only the verb that runs."""

from __future__ import annotations

import argparse
import ast
import importlib
import itertools
import subprocess
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import pytest

from cmion_mesh.errors import ConfigError, ExitCode, InvalidName, NotAlive, NotReached, RequestRejected, Vanished, exit_code

PACKAGE = Path(__file__).resolve().parents[1] / "cmion_mesh"
TESTS = Path(__file__).resolve().parent

# --- the layers ---------------------------------------------------------------------------------

#: The top-level modules every layer builds on: the standard library and the outside packages only.
GROUND = frozenset({"errors", "keys", "messages", "classes", "xmlsafe", "diagnostics", "resources", "signals", "procs",
                    "statedir", "logs", "log_writer", "tomlsafe"})
#: The top-level modules of the kernel: the update loop, the stores, the client (its action runs and
#: companion operations), the mind and competency interfaces, who is alive and the claim on a name;
#: requests and timers of the loop.
KERNEL = frozenset({"ion", "requests", "timers", "storage", "client", "action_runs", "companions", "mind", "competency",
                    "presence", "claim"})
#: Lowest first. A module imports its own layer and the layers below it, never one above; the
#: folders of one layer may import each other (without a circle).
LAYERS: tuple[frozenset[str], ...] = (
    frozenset({"ground"}),
    frozenset({"transport"}),
    frozenset({"kernel"}),
    frozenset({"migration"}),
    frozenset({"body"}),
    frozenset({"minds", "web", "ros2", "competencies"}),
    frozenset({"tools", "ops"}),
    frozenset({"cli"}),
)
#: The harness of the tests and benchmarks: it may import anything, and nothing in the package imports it.
HARNESS = "testing"
#: What a module of the package may take from the package's face (``cmion_mesh/__init__.py``): what
#: the face defines itself. The names it exports lazily are imported from their own modules.
FACE_OWN = frozenset({"__version__"})
#: Imports that break the layers today, each with why and when it goes. A stale entry fails too.
LAYER_EXCEPTIONS: dict[tuple[str, str], str] = {}


@dataclass(frozen=True)
class Import:
    """``module`` (in file ``path``) imports ``target`` at ``line``, at any depth (inside a function too);
    ``name``: what it takes from the package's face when ``target`` is the package itself."""

    module: str
    path: str
    line: int
    target: str
    name: str = ""


def module_name(root: Path, path: Path) -> str:
    parts = [root.name, *path.relative_to(root).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def package_imports(root: Path) -> list[Import]:
    """Every import of a module of the package at ``root`` by a module of it, from the syntax tree
    of each file (every level: a function-local import counts as much as a top-level one)."""
    files = {module_name(root, p): p for p in sorted(root.rglob("*.py"))}

    def resolve(name: str) -> str | None:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    found: dict[Import, None] = {}  # one per module, line and target (``from m import a, b`` is one)
    for module, path in files.items():
        shown = f"{root.name}/{path.relative_to(root)}"
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
                names = ["" for _ in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                # ``from pkg import sub`` imports the module ``pkg.sub``; ``from pkg import name``, ``pkg``
                targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in files else base for alias in node.names]
                names = [alias.name for alias in node.names]
            else:
                continue
            for target, name in zip(targets, names, strict=True):
                resolved = resolve(target) if target.split(".")[0] == root.name else None
                if resolved is not None and resolved != module:
                    found[Import(module, shown, node.lineno, resolved, name if resolved == root.name else "")] = None
    return list(found)


def layer_of(module: str) -> str:
    """The layer (or folder) a module of the package is in: ``ground``, ``kernel`` or its folder."""
    parts = module.split(".")[1:]
    if not parts:
        return "face"
    if len(parts) == 1:
        if parts[0] in GROUND:
            return "ground"
        if parts[0] in KERNEL:
            return "kernel"
        return "?"
    return parts[0]


def rank(layer: str) -> int | None:
    return next((i for i, names in enumerate(LAYERS) if layer in names), None)


ORDER = " < ".join(", ".join(sorted(names)) for names in LAYERS)


def layer_violations(imports: Iterable[Import], exceptions: dict[tuple[str, str], str] | None = None) -> list[str]:
    """One line per import that breaks the layers: ``path:line: what imports what``, then the rule."""
    allowed = LAYER_EXCEPTIONS if exceptions is None else exceptions
    problems: list[str] = []
    for imp in imports:
        if (imp.module, imp.target) in allowed:
            continue
        source, target = layer_of(imp.module), layer_of(imp.target)
        where = f"{imp.path}:{imp.line}: {imp.module} ({source}) imports {imp.target}{f'.{imp.name}' if imp.name else ''}"
        low, high = rank(source), rank(target)
        if target == "face":
            if imp.name and imp.name not in FACE_OWN:
                problems.append(f"{where}: the package's face exports it lazily; import it from its own module")
        elif target == HARNESS and source != HARNESS:
            problems.append(f"{where} ({HARNESS}): nothing in the package imports the test harness")
        elif source in (HARNESS, "face"):
            continue  # the harness and the face may import any layer
        elif low is None or high is None:
            unknown = imp.module if low is None else imp.target
            problems.append(f"{where}: {unknown} is in no layer: add it to the layer table (GROUND, KERNEL or LAYERS)")
        elif high > low:
            problems.append(f"{where} ({target}): an upward import; a layer imports only its own and the layers below ({ORDER})")
    return problems


def import_circles(imports: Iterable[Import]) -> list[str]:
    """One line per circle of imports between modules (the face, which names every layer, aside)."""
    edges: dict[str, dict[str, Import]] = {}
    for imp in imports:
        if layer_of(imp.module) != "face" and layer_of(imp.target) != "face":
            edges.setdefault(imp.module, {}).setdefault(imp.target, imp)
    # Tarjan's strongly connected components, iteratively (a deep package must not hit the recursion limit)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[str] = []
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges.get(start, {}))))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges.get(child, {})))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                members = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    members.append(member)
                    if member == node:
                        break
                if len(members) > 1:
                    circles.append(_circle(sorted(members), edges))
    return circles


def _circle(members: list[str], edges: dict[str, dict[str, Import]]) -> str:
    """One path around the circle through ``members``, with the line of each import on it."""
    inside = set(members)
    path = [members[0]]
    while True:  # bounded: each step moves to a member not yet on the path, or closes the circle
        nxt = sorted(t for t in edges.get(path[-1], {}) if t in inside)
        closing = members[0] in nxt and len(path) > 1
        fresh = [t for t in nxt if t not in path]
        if closing or not fresh:
            path.append(members[0] if closing or members[0] in nxt else nxt[0])
            break
        path.append(fresh[0])
    lines = ", ".join(f"{edges[a][b].path}:{edges[a][b].line}" for a, b in itertools.pairwise(path) if b in edges.get(a, {}))
    return f"import circle: {' -> '.join(path)} ({lines}): modules, in one layer or not, never import each other in a circle"


def test_every_module_imports_only_its_own_layer_and_those_below() -> None:
    assert layer_violations(package_imports(PACKAGE)) == []


def test_no_import_circle() -> None:
    assert import_circles(package_imports(PACKAGE)) == []


def test_every_layer_exception_is_still_needed() -> None:
    found = {(imp.module, imp.target) for imp in package_imports(PACKAGE)}
    stale = sorted(pair for pair in LAYER_EXCEPTIONS if pair not in found)
    assert stale == [], f"these imports are gone: remove their entries from LAYER_EXCEPTIONS: {stale}"


def scratch_package(root: Path, files: dict[str, str]) -> Path:
    package = root / "cmion_mesh"
    for name, text in {"__init__.py": "", **files}.items():
        path = package / name
        path.parent.mkdir(parents=True, exist_ok=True)
        (path.parent / "__init__.py").touch()
        path.write_text(text)
    return package


def test_an_upward_import_inside_a_function_fails_naming_module_line_and_rule(tmp_path: Path) -> None:
    package = scratch_package(tmp_path, {
        "errors.py": "import os\n\n\ndef f():\n    from cmion_mesh.cli import main\n",
        "client.py": "from cmion_mesh import errors, __version__\nfrom cmion_mesh.body.embodiment import Embodiment\n",
        "cli/main.py": "from cmion_mesh.client import x\nfrom cmion_mesh.testing.wait import wait_for\n",
        "body/embodiment.py": "from cmion_mesh import MeshClient\n",
        "testing/wait.py": "from cmion_mesh.cli import main\n",
    })
    assert layer_violations(package_imports(package), {}) == [
        "cmion_mesh/body/embodiment.py:1: cmion_mesh.body.embodiment (body) imports cmion_mesh.MeshClient: the package's face "
        "exports it lazily; import it from its own module",
        "cmion_mesh/cli/main.py:2: cmion_mesh.cli.main (cli) imports cmion_mesh.testing.wait (testing): nothing in the "
        "package imports the test harness",
        f"cmion_mesh/client.py:2: cmion_mesh.client (kernel) imports cmion_mesh.body.embodiment (body): an upward import; "
        f"a layer imports only its own and the layers below ({ORDER})",
        f"cmion_mesh/errors.py:5: cmion_mesh.errors (ground) imports cmion_mesh.cli.main (cli): an upward import; "
        f"a layer imports only its own and the layers below ({ORDER})",
    ]


def test_a_module_in_no_layer_fails(tmp_path: Path) -> None:
    package = scratch_package(tmp_path, {"helpers.py": "from cmion_mesh import errors\n", "errors.py": ""})
    [problem] = layer_violations(package_imports(package), {})
    assert problem.startswith("cmion_mesh/helpers.py:1: cmion_mesh.helpers (?) imports cmion_mesh.errors: cmion_mesh.helpers "
                              "is in no layer")


def test_an_import_circle_in_one_layer_fails_naming_each_line(tmp_path: Path) -> None:
    package = scratch_package(tmp_path, {
        "client.py": "from cmion_mesh.presence import Presence\n",
        "presence.py": "def where():\n    from cmion_mesh.client import MeshClient\n",
        "web/body.py": "from cmion_mesh.web.competencies import WebSense\n",
        "web/competencies.py": "import cmion_mesh.web.body\n",
        "minds/mind.py": "from cmion_mesh.web.body import x\n",
    })
    imports = package_imports(package)
    assert layer_violations(imports, {}) == []  # each import alone keeps the layers
    assert import_circles(imports) == [
        "import circle: cmion_mesh.client -> cmion_mesh.presence -> cmion_mesh.client (cmion_mesh/client.py:1, "
        "cmion_mesh/presence.py:2): modules, in one layer or not, never import each other in a circle",
        "import circle: cmion_mesh.web.body -> cmion_mesh.web.competencies -> cmion_mesh.web.body (cmion_mesh/web/body.py:1, "
        "cmion_mesh/web/competencies.py:1): modules, in one layer or not, never import each other in a circle",
    ]


@pytest.mark.parametrize("statement", ["from .. import cli", "from ..cli import main", "import cmion_mesh.cli.main as m"])
def test_relative_and_aliased_imports_are_seen(tmp_path: Path, statement: str) -> None:
    package = scratch_package(tmp_path, {"transport/base.py": f"{statement}\n", "cli/main.py": ""})
    [problem] = layer_violations(package_imports(package), {})
    assert problem.startswith("cmion_mesh/transport/base.py:1: cmion_mesh.transport.base (transport) imports cmion_mesh.cli")


def test_no_test_imports_bench() -> None:
    offenders = sorted(p.name for p in TESTS.rglob("*.py") if any(m.split(".")[0] == "bench" for m in imported_modules(p)))
    assert offenders == [], f"tests run the benchmarks as a user does (python -m bench): {offenders} import bench/"


# --- the face ---------------------------------------------------------------------------------

#: What a user writes code against, on the package's face (``cmion_mesh/__init__.py``).
FACE = ("MeshClient", "Component", "Simulation", "Competency", "RunContext", "Mind", "Embodiment", "MeshError")


def test_the_face_gives_each_name_from_its_module() -> None:
    import cmion_mesh
    from cmion_mesh import errors

    families = sorted(n for n, v in vars(errors).items() if isinstance(v, type) and issubclass(v, errors.MeshError))
    assert set(FACE) | set(families) <= set(cmion_mesh.__all__), "each error family is on the face too"
    for name in cmion_mesh.__all__:
        value = getattr(cmion_mesh, name)
        assert name in dir(cmion_mesh)
        if name != "__version__":
            assert value is getattr(importlib.import_module(value.__module__), name), name
    assert cmion_mesh.Competency.__module__ == "cmion_mesh.competency" and cmion_mesh.MeshClient.__module__ == "cmion_mesh.client"
    with pytest.raises(AttributeError, match="has no attribute 'Nothing'"):
        cmion_mesh.Nothing  # noqa: B018  # the attribute read is the test


def test_importing_the_package_loads_none_of_the_modules_behind_its_face() -> None:
    code = ("import sys, cmion_mesh\n"
            "listed = dir(cmion_mesh)\n"
            "heavy = ('cmion_mesh.', 'zenoh', 'msgspec', 'lxml', 'cryptography', 'starlette', 'uvicorn')\n"
            "print(sorted(m for m in sys.modules if m.startswith(heavy)))\n"
            "print(listed)\n"
            "from cmion_mesh import MeshClient, Competency\n"
            "print('zenoh' in sys.modules)\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    loaded, listed, zenoh = (ast.literal_eval(line) for line in result.stdout.splitlines())
    assert loaded == []
    assert set(FACE) <= set(listed)
    assert zenoh is False, "the client and the competencies run on any transport: zenoh is loaded by its adapter only"


# --- the edges ----------------------------------------------------------------------------------
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


def test_a_body_serving_no_page_loads_no_web_server() -> None:
    # The robot's library holds web competencies (a page may be added with --web); without one, the
    # HTTP server (starlette, uvicorn and asyncio: megabytes and tens of ms of start) stays unloaded.
    library = PACKAGE.parent / "embodiments" / "robot" / "CompetencyLibrary.xml"
    probe = ("import sys\n"
             "from cmion_mesh.body.library import load_library\n"
             f"print(sorted(type(c).__name__ for c in load_library({str(library)!r})))\n"
             "print(sorted(m for m in sys.modules if m.split('.')[0] in ('starlette', 'uvicorn', 'asyncio', 'anyio') "
             "or m == 'cmion_mesh.web.body'))\n")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True)
    classes, loaded = (ast.literal_eval(line) for line in result.stdout.splitlines())
    assert {"WebSpeechSynthesis", "WebCommandInput"} <= set(classes)
    assert loaded == []


def test_a_daemon_starts_without_the_modules_of_paths_it_may_never_take() -> None:
    # Each is milliseconds of every start (hashlib: OpenSSL, 3.5 MiB): taken when a companion is
    # hashed, a settings file read, systemd notified, a line spoken, a page's key made.
    assert loaded_after("import cmion_mesh.cli.main as cli\n"
                        "cli.build_parser('up').parse_args(['up', 'robot'])\n"
                        "import cmion_mesh.cli.daemon, cmion_mesh.body.embodiment, cmion_mesh.migration.manager, "
                        "cmion_mesh.ops.systemd, cmion_mesh.web.competencies\n",
                        ("hashlib", "secrets", "random", "socket", "tomllib", "subprocess")) == []


def test_a_companions_birth_loads_one_openssl_and_no_key_serialization() -> None:
    # Hashing and signing both go through cryptography, which carries its own OpenSSL: hashlib would
    # load the system's beside it (3.3 MiB resident), serialization 32 modules for raw key bytes.
    assert loaded_after("from cmion_mesh.migration import custody, signing\n"
                        "from cmion_mesh.migration.identity import Identity\n"
                        "packed = Identity('spirit', 1, {'mind': {'mood': 1}}).pack_sections()\n"
                        "link = custody.birth('spirit', 'robot', signing.new_key(), packed.manifest)\n"
                        "assert signing.valid(link.public_key, link.signed_bytes(), link.signature)\n",
                        ("hashlib", "cryptography.hazmat.primitives.serialization")) == []


def loaded_after(code: str, modules: tuple[str, ...]) -> list[str]:
    """Which of ``modules`` a fresh interpreter has loaded once it ran ``code``."""
    probe = f"import sys\n{code}print(sorted(m for m in {modules!r} if m in sys.modules))\n"
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True)
    found: list[str] = ast.literal_eval(result.stdout.strip())
    return found


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
    assert typo.stderr == "cmion-mesh: error: argument COMMAND: invalid choice: 'pers' (did you mean 'peers'?)\n", typo.stderr


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
