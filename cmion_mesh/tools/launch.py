"""``cmion-mesh launch FILE``: several processes of a mesh started, watched and stopped as one.

A launch file is TOML (Python reads it with the standard library's ``tomllib``: no dependency,
comments, and errors that carry a line). It names the processes to run: ``[[embodiment]]``
daemons, a ``[[router]]``, ``[[mind]]`` and ``[[competency]]`` processes serving an embodiment,
and any other ``[[process]]``. ``docs/launch.md`` describes every key; ``embodiments/spirit.launch.toml``
starts the Spirit of the Building.

Here: the file (``load``: every problem in one error, naming the file and line), the order its
processes start in, their command lines (``commands``) and what ``launch --check`` prints
(``describe``). Running them: ``tools/launcher.py``.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cmion_mesh import keys, tomlsafe
from cmion_mesh.diagnostics import Diagnostics
from cmion_mesh.errors import ConfigError
from cmion_mesh.procs import cli_argv, free_port

ON_FAILURE = ("stop_all", "continue", "restart")
NETWORKS = ("lan", "loopback")
SUFFIX = ".launch.toml"
WHAT = "launch file"
#: The line each kind of cmion-mesh process writes once it serves: it is then ready.
READY_LINES = {"embodiment": "up in mesh", "router": "router up", "mind": "serving embodiment",
               "competency": "serving embodiment"}
#: Largest launch file read (``tomlsafe``): one is a few KiB; a bigger one is a mistake, not a mesh to start.
MAX_FILE = tomlsafe.MAX_FILE
#: Longest ``stop_timeout`` / ``ready_timeout``: the clocks waited on overflow beyond some size.
MAX_SECONDS = 24 * 3600.0

_COMMON = {"name": str, "args": list, "env": dict, "after": list, "on_failure": str, "ready": str, "cwd": str}
_KEYS: dict[str, dict[str, type]] = {
    "launch": {"mesh": str, "on_failure": str, "restarts": int, "stop_timeout": float, "ready_timeout": float,
               "network": str, "connect": list, "no_multicast": bool, "certs": str},
    "embodiment": {**_COMMON, "config": str, "listen": list, "connect": list, "state_dir": str, "web": str},
    "router": {**_COMMON, "listen": list, "connect": list},
    "mind": {**_COMMON, "class": str, "embodiment": str, "parameters": str},
    "competency": {**_COMMON, "class": str, "embodiment": str, "parameters": str},
    "process": {**_COMMON, "command": list},
}
_REQUIRED = {"mind": ("class", "embodiment"), "competency": ("class", "embodiment"), "process": ("command",)}
KINDS = ("embodiment", "router", "mind", "competency", "process")


@dataclass(frozen=True, slots=True)
class Spec:
    """One process to run, as the file says it (its command line is built at start: ports)."""

    name: str
    kind: str
    table: dict[str, Any]
    line: int | None
    after: tuple[str, ...]
    on_failure: str
    ready: str | None


@dataclass(frozen=True, slots=True)
class LaunchFile:
    path: Path
    mesh: str
    on_failure: str
    restarts: int
    stop_timeout: float
    ready_timeout: float
    network: str
    connect: tuple[str, ...]
    no_multicast: bool
    certs: str | None
    specs: tuple[Spec, ...]  # in an order where every process comes after those it waits for

    @property
    def folder(self) -> Path:
        return self.path.resolve().parent


def resolve_file(given: str) -> Path:
    """``launch`` takes a file, or the name of a shipped launch file (``spirit``)."""
    from cmion_mesh.resources import data_dir

    path = Path(given)
    try:
        if path.is_file():
            return path
    except OSError as exc:  # a name too long, a folder on the way that cannot be searched...
        raise ConfigError(f"cannot read the launch file: {exc.strerror or exc}", path=given) from None
    if "/" not in given:
        shipped = data_dir("embodiments") / (given if given.endswith(SUFFIX) else given + SUFFIX)
        if shipped.is_file():
            return shipped
    names = sorted(p.name[: -len(SUFFIX)] for p in data_dir("embodiments").glob("*" + SUFFIX))
    raise ConfigError(f"no launch file at {given!r} (a TOML file, or a shipped one: {', '.join(names)})")


class _Checker:
    """Reads one table, reporting every problem with the file, line and key."""

    def __init__(self, path: Path, text: str, found: Diagnostics) -> None:
        self.path, self.text, self.found = path, text, found
        self.headers = tomlsafe.header_lines(text)

    def table(self, kind: str, index: int, values: Any, what: str) -> dict[str, Any]:
        line = self.headers.get((kind, index))
        if not isinstance(values, dict):
            self.found.error(f"{what} must be a table", self.path, line)
            return {}
        allowed = _KEYS[kind]
        out: dict[str, Any] = {}
        for key, value in values.items():
            where = tomlsafe.key_line(self.text, line, key)
            if key not in allowed:
                from cmion_mesh.client import did_you_mean

                self.found.error(f"{what}: unknown key {key!r}{did_you_mean(key, allowed)} (known: {', '.join(sorted(allowed))})",
                                 self.path, where)
                continue
            problem = _type_problem(value, allowed[key])
            if problem:
                self.found.error(f"{what}: {key!r} must be {problem}, not {_show(value)}", self.path, where)
                continue
            out[key] = float(value) if allowed[key] is float else value
        for key in _REQUIRED.get(kind, ()):
            if key not in values:
                self.found.error(f"{what}: {key!r} is required", self.path, line)
        return out

    def choice(self, table: dict[str, Any], key: str, choices: Sequence[str], default: str, what: str, line: int | None) -> str:
        value = table.get(key, default)
        if value not in choices:
            self.found.error(f"{what}: {key!r} must be one of {', '.join(choices)}, not {value!r}", self.path,
                             tomlsafe.key_line(self.text, line, key))
            return default
        return str(value)


def _type_problem(value: Any, kind: type) -> str:
    # Every string of a launch file ends up in a command line, an environment or a path, none of
    # which can carry a NUL character.
    if kind is float:
        number = isinstance(value, int | float) and not isinstance(value, bool)
        return "" if number and 0 < value <= MAX_SECONDS else f"a positive number of seconds, at most {MAX_SECONDS:g}"
    if kind is int:
        return "" if isinstance(value, int) and not isinstance(value, bool) and value >= 0 else "a whole number >= 0"
    if kind is list:
        return "" if isinstance(value, list) and all(_text(v) for v in value) else "a list of strings (without NUL characters)"
    if kind is dict:
        fine = isinstance(value, dict) and all(_text(v) and _text(k) and k and "=" not in k for k, v in value.items())
        return "" if fine else "a table of strings (names without '=', no NUL characters)"
    if kind is bool:
        return "" if isinstance(value, bool) else "true or false"
    return "" if _text(value) else "a string (without NUL characters)"


def _text(value: Any) -> bool:
    return isinstance(value, str) and "\0" not in value


def _show(value: Any) -> str:
    return f"{type(value).__name__} {value!r}"[:80]


def load(path: str | Path, *, mesh: str | None = None) -> LaunchFile:
    """Read and check a launch file; every problem in one ``ConfigError`` (file and line of the first)."""
    path = Path(path)
    text, data = tomlsafe.load(path, WHAT)
    found = Diagnostics()
    check = _Checker(path, text, found)
    for key in data:
        if key not in _KEYS:
            from cmion_mesh.client import did_you_mean

            found.error(f"unknown table [{key}]{did_you_mean(key, _KEYS)} (known: [launch], "
                        f"{', '.join(f'[[{k}]]' for k in KINDS)})", path, check.headers.get((key, 0)))
    if "launch" in data and isinstance(data["launch"], list):
        found.error("[launch] is one table: write [launch], not [[launch]]", path, check.headers.get(("launch", 0)))
        data["launch"] = {}
    top = check.table("launch", 0, data.get("launch", {}), "[launch]")
    top_line = check.headers.get(("launch", 0))
    on_failure = check.choice(top, "on_failure", ON_FAILURE, "stop_all", "[launch]", top_line)
    network = check.choice(top, "network", NETWORKS, "lan", "[launch]", top_line)
    chosen_mesh = mesh or top.get("mesh", keys.DEFAULT_MESH)
    if not keys.is_name(chosen_mesh):
        found.error(f"[launch]: mesh {chosen_mesh!r} is not a valid name", path, tomlsafe.key_line(text, top_line, "mesh"))
    specs = _ordered(_specs(check, data, on_failure), check)
    if not specs and not found.errors:
        found.error(f"nothing to launch: no {', '.join(f'[[{k}]]' for k in KINDS)}", path, 1)
    certs = top.get("certs")
    by_line = Diagnostics()  # the problems from the top of the file down
    by_line.extend(sorted(found, key=lambda d: d.line or 0))
    by_line.raise_if_errors()
    return LaunchFile(path=path, mesh=chosen_mesh, on_failure=on_failure, restarts=top.get("restarts", 3),
                      stop_timeout=top.get("stop_timeout", 10.0), ready_timeout=top.get("ready_timeout", 60.0),
                      network=network, connect=tuple(top.get("connect", ())), no_multicast=top.get("no_multicast", False),
                      certs=str(path.parent / certs) if certs else None, specs=specs)


def _specs(check: _Checker, data: dict[str, Any], default_failure: str) -> list[Spec]:
    specs: list[Spec] = []
    for kind in KINDS:
        entries = data.get(kind, [])
        if not isinstance(entries, list):
            check.found.error(f"[{kind}] must be written [[{kind}]], one table per process", check.path, check.headers.get((kind, 0)))
            continue
        for index, raw in enumerate(entries):
            line = check.headers.get((kind, index))
            table = check.table(kind, index, raw, f"[[{kind}]] #{index + 1}")
            name = table.get("name") or (kind if kind == "router" else None)
            if name is None:
                if kind in ("mind", "competency") and "class" in table:
                    name = table["class"].rpartition(":")[2]
                elif kind == "process" and table.get("command"):
                    name = Path(table["command"][0]).name
                else:
                    check.found.error(f"[[{kind}]] #{index + 1}: 'name' is required", check.path, line)
                    continue
            if not keys.is_name(name):
                check.found.error(f"[[{kind}]] #{index + 1}: name {name!r} is not a valid name (no / * $ # ?, no leading @)",
                                  check.path, tomlsafe.key_line(check.text, line, "name"))
                continue
            if kind == "process" and "command" in table and not table["command"]:
                check.found.error(f"[[process]] {name!r}: 'command' is empty", check.path, tomlsafe.key_line(check.text, line, "command"))
            if kind == "embodiment":
                _check_config(check, table, name, line)
            after = list(table.get("after", ()))
            if kind in ("mind", "competency") and "after" not in table and "embodiment" in table:
                after = [table["embodiment"]]  # serving an embodiment not yet up would only warn
            failure = check.choice(table, "on_failure", ON_FAILURE, default_failure, f"[[{kind}]] {name!r}", line)
            specs.append(Spec(name=name, kind=kind, table=table, line=line, after=tuple(after), on_failure=failure,
                              ready=table.get("ready", READY_LINES.get(kind))))
    return specs


def _check_config(check: _Checker, table: dict[str, Any], name: str, line: int | None) -> None:
    from cmion_mesh.resources import data_dir

    config = table.get("config", name)
    local = check.path.parent / config
    shipped = data_dir("embodiments") / config / "ArchitectureConfiguration.xml"
    if local.exists():
        table["config"] = str(local.resolve())
    elif "/" not in config and shipped.is_file():
        table["config"] = config
    else:
        check.found.error(f"[[embodiment]] {name!r}: config {config!r}: no such file or folder beside the launch file, "
                          f"nor a shipped embodiment", check.path, tomlsafe.key_line(check.text, line, "config"))


def _ordered(specs: list[Spec], check: _Checker) -> tuple[Spec, ...]:
    """The specs in file order, each moved after those it waits for; unknown names and cycles reported."""
    by_name: dict[str, Spec] = {}
    for spec in specs:
        if spec.name in by_name:
            check.found.error(f"two processes named {spec.name!r} (names must be unique)", check.path, spec.line)
        by_name[spec.name] = spec
    for spec in specs:
        for other in spec.after:
            if other not in by_name:
                from cmion_mesh.client import did_you_mean

                check.found.error(f"[[{spec.kind}]] {spec.name!r}: after {other!r}: no process of that name{did_you_mean(other, by_name)}",
                                  check.path, tomlsafe.key_line(check.text, spec.line, "after"))
            elif other == spec.name:
                check.found.error(f"[[{spec.kind}]] {spec.name!r}: comes after itself", check.path, spec.line)
    out: list[Spec] = []
    state: dict[str, str] = {}

    def waits_for(spec: Spec) -> Iterator[Spec]:
        return (by_name[other] for other in spec.after if other in by_name and other != spec.name)

    # Depth first, with a stack of our own: a chain of 'after' is as long as the file makes it,
    # and Python's own stack is not.
    for root in specs:
        if state.get(root.name) == "done":
            continue
        state[root.name] = "visiting"
        stack: list[tuple[Spec, Iterator[Spec]]] = [(root, waits_for(root))]
        while stack:
            spec, others = stack[-1]
            for waited in others:
                if state.get(waited.name) == "done":
                    continue
                if state.get(waited.name) == "visiting":
                    path = [on.name for on, _ in stack]
                    cycle = [*path[path.index(waited.name):], waited.name]
                    check.found.error(f"a cycle of 'after': {' -> '.join(cycle)}", check.path, waited.line)
                    continue
                state[waited.name] = "visiting"
                stack.append((waited, waits_for(waited)))
                break
            else:
                stack.pop()
                state[spec.name] = "done"
                out.append(spec)
    return tuple(out)


# --- the command lines ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Command:
    """A process ready to start: its command line, environment additions and folder."""

    spec: Spec
    argv: tuple[str, ...]
    env: dict[str, str]
    cwd: str


def commands(launch: LaunchFile) -> list[Command]:
    """Each process's command line. With ``network = "loopback"`` each embodiment and router listens
    on a free loopback port chosen now, and every cmion-mesh process connects to all of them."""
    listens: dict[str, list[str]] = {}
    if launch.network == "loopback":
        for spec in launch.specs:
            if spec.kind in ("embodiment", "router"):
                listens[spec.name] = [f"tcp/127.0.0.1:{free_port()}"]
    everyone = [endpoint for endpoints in listens.values() for endpoint in endpoints]
    out = []
    for spec in launch.specs:
        table = spec.table
        own = listens.get(spec.name, []) + list(table.get("listen", ()))
        connect = [*launch.connect, *(e for e in everyone if e not in own), *table.get("connect", ())]
        net = [*(x for e in own for x in ("--listen", e)), *(x for e in connect for x in ("--connect", e))]
        if launch.no_multicast or launch.network == "loopback":
            net.append("--no-multicast")
        mesh = ["--mesh", launch.mesh, *(("--certs", launch.certs) if launch.certs else ())]
        args = list(table.get("args", ()))
        if spec.kind == "embodiment":
            argv = cli_argv("up", table["config"], "--name", spec.name, *mesh, *net)
            if "state_dir" in table:
                argv += ["--state-dir", str(launch.folder / table["state_dir"])]
            if "web" in table:
                argv += ["--web", table["web"]]
        elif spec.kind == "router":
            argv = cli_argv("router", *net)
        elif spec.kind in ("mind", "competency"):
            argv = cli_argv(f"serve-{spec.kind}", table["class"], "--embodiment", table["embodiment"], *mesh, *net)
            if table.get("parameters"):
                argv += ["--parameters", table["parameters"]]
        else:
            command = list(table["command"])
            argv = cli_argv(*command[1:]) if command[0] == "cmion-mesh" else command  # the same installation
        env = {"CMION_MESH": launch.mesh, **({"CMION_MESH_CONNECT": ",".join(everyone)} if everyone else {}),
               **table.get("env", {})}
        out.append(Command(spec, (*argv, *args), env, str(launch.folder / table.get("cwd", "."))))
    return out


def as_typed(argv: Sequence[str]) -> list[str]:
    """The command line as a person would type it: ``cmion-mesh`` for this interpreter's CLI."""
    prefix = cli_argv()
    return ["cmion-mesh", *argv[len(prefix):]] if list(argv[: len(prefix)]) == prefix else list(argv)


def describe(launch: LaunchFile) -> list[dict[str, Any]]:
    """What ``launch --check`` prints: each process in start order, with its command line."""
    return [{"name": c.spec.name, "kind": c.spec.kind, "after": list(c.spec.after), "ready": c.spec.ready,
             "on_failure": c.spec.on_failure, "command": as_typed(c.argv), "cwd": c.cwd, "env": c.env}
            for c in commands(launch)]
