"""``cmion-mesh launch FILE``: several processes of a mesh started, watched and stopped as one.

A launch file is TOML (Python reads it with the standard library's ``tomllib``: no dependency,
comments, and errors that carry a line). It names the processes to run: ``[[embodiment]]``
daemons, a ``[[router]]``, ``[[mind]]`` and ``[[competency]]`` processes serving an embodiment,
and any other ``[[process]]``. ``docs/launch.md`` describes every key; ``embodiments/spirit.launch.toml``
starts the Spirit of the Building.

How it runs: every child is a process group of its own (a Ctrl-C at the terminal reaches the
launcher only, which then stops the children in order and waits for them); each line a child
writes is printed with its name in front; a child starts once the ones it comes ``after`` are
ready (their ``ready`` line written); a child that fails stops them all (``on_failure``:
``stop_all``, ``continue`` or ``restart``, bounded). Stopping sends SIGINT (SIGTERM when the
launcher got SIGTERM) to every group, waits up to ``stop_timeout``, then SIGKILLs what is left; a
second Ctrl-C (a second or more after the first) SIGKILLs at once. Children get SIGTERM from the kernel if the launcher dies, even
SIGKILLed (``procs.child_setup``), so none is left running for ever.
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from cmion_mesh import keys, tomlsafe
from cmion_mesh.diagnostics import Diagnostics
from cmion_mesh.errors import ConfigError, ExitCode
from cmion_mesh.procs import child_setup, cli_argv, free_port
from cmion_mesh.signals import Stopper

ON_FAILURE = ("stop_all", "continue", "restart")
NETWORKS = ("lan", "loopback")
SUFFIX = ".launch.toml"
WHAT = "launch file"
#: The line each kind of cmion-mesh process writes once it serves: it is then ready.
READY_LINES = {"embodiment": "up in mesh", "router": "router up", "mind": "serving embodiment",
               "competency": "serving embodiment"}
#: Delay before the n-th restart of a failed process (seconds): 1, 2, 4... at most this.
MAX_BACKOFF = 10.0
#: After SIGKILL, how long a process may take to be reaped before the launcher gives up on it.
KILL_WAIT = 5.0
#: A second stop signal kills at once only this long after the first: some tools deliver one
#: signal twice at once (GNU timeout signals its child, then its whole process group).
SECOND_SIGNAL_GAP = 1.0
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


# --- running them ---------------------------------------------------------------------------------


COLOURS = ("36", "33", "35", "32", "34", "31", "96", "93", "95", "92")


class _Output:
    """Prefixed lines on the launcher's stdout and stderr, one writer at a time."""

    def __init__(self, names: Sequence[str]) -> None:
        self.width = max([len("launch"), *(len(n) for n in names)])
        self.lock = threading.Lock()
        colour = os.environ.get("NO_COLOR") is None
        self.colours = {name: COLOURS[i % len(COLOURS)] for i, name in enumerate(names)} if colour else {}

    def write(self, name: str, line: str, stream: IO[str]) -> None:
        label = f"{name:<{self.width}} |"
        code = self.colours.get(name, "1" if name == "launch" and self.colours else "")
        if code and stream.isatty():
            label = f"\x1b[{code}m{label}\x1b[0m"
        with self.lock:
            try:
                stream.write(f"{label} {line}\n")
                stream.flush()
            except (OSError, ValueError):  # our output is gone (a closed pipe): the children still run and are stopped
                pass

    def say(self, text: str, *, error: bool = False) -> None:
        self.write("launch", text, sys.stderr if error else sys.stdout)


@dataclass
class _Child:
    command: Command
    proc: subprocess.Popen[bytes] | None = None
    generation: int = 0
    state: str = "waiting"  # waiting, starting, ready, ended, failed
    started: float = 0.0
    restarts: int = 0
    restart_at: float | None = None
    readers: list[threading.Thread] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.command.spec.name

    @property
    def running(self) -> bool:
        return self.state in ("starting", "ready")


class Launcher:
    """Runs a launch file's processes until a signal, a failure (``on_failure``) or their end.
    ``run`` must be called on the main thread (it starts the children: see ``procs.child_setup``)."""

    def __init__(self, launch: LaunchFile, stopper: Stopper, *, out: _Output | None = None) -> None:
        self.launch = launch
        self.stopper = stopper
        self.children = {c.spec.name: _Child(c) for c in commands(launch)}
        self.out = out or _Output(list(self.children))
        self.events: queue.SimpleQueue[tuple[str, str, int, int]] = queue.SimpleQueue()
        self.failed: list[str] = []
        self.stop_all = False
        self._told_reach = False

    # reader threads: lines out, "ready" and "exit" to the main thread
    def _read(self, child: _Child, generation: int, stream: IO[bytes], target: IO[str], ready: str | None,
              then: Callable[[], None] | None) -> None:
        announced = False
        for raw in stream:
            line = raw.decode("utf-8", "replace").rstrip("\r\n")
            self.out.write(child.name, line, target)
            if ready and not announced and ready in line:
                announced = True
                self._post("ready", child.name, generation, 0)
        stream.close()
        if then is not None:
            then()

    def _post(self, kind: str, name: str, generation: int, code: int) -> None:
        self.events.put((kind, name, generation, code))
        self.stopper.stop()

    def _start(self, child: _Child) -> None:
        command = child.command
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **command.env}
        child.generation += 1
        generation = child.generation
        try:
            proc = subprocess.Popen(command.argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    env=env, cwd=command.cwd, start_new_session=True, preexec_fn=child_setup())
        except OSError as exc:
            self.out.say(f"{child.name}: cannot start {command.argv[0]}: {exc}", error=True)
            self._failed(child, f"cannot start: {exc}")
            return
        child.proc, child.started, child.state = proc, time.monotonic(), "starting"
        assert proc.stdout is not None and proc.stderr is not None
        ready = command.spec.ready
        err = threading.Thread(target=self._read, args=(child, generation, proc.stderr, sys.stderr, ready, None),
                               name=f"launch-err-{child.name}", daemon=True)

        def ended() -> None:
            err.join()
            self._post("exit", child.name, generation, proc.wait())

        out = threading.Thread(target=self._read, args=(child, generation, proc.stdout, sys.stdout, ready, ended),
                               name=f"launch-out-{child.name}", daemon=True)
        child.readers += [err, out]  # a run before a restart may still be reading (a grandchild holding its pipes)
        err.start()
        out.start()
        self.out.say(f"started {child.name} (pid {proc.pid}): {' '.join(_short(command.argv))}")
        if ready is None:
            child.state = "ready"

    def _failed(self, child: _Child, why: str) -> None:
        """Apply the child's ``on_failure``: a restart later, nothing, or ``stop_all``."""
        child.state = "failed"
        policy = child.command.spec.on_failure
        if policy == "restart" and child.restarts < self.launch.restarts:
            child.restarts += 1
            delay = min(MAX_BACKOFF, 2.0 ** min(child.restarts - 1, 16))  # no float overflow after 1024 restarts
            child.restart_at = time.monotonic() + delay
            self.out.say(f"{child.name} {why}: restarting in {delay:g} s (restart {child.restarts} of {self.launch.restarts})",
                         error=True)
            return
        self.failed.append(child.name)
        if policy == "continue":
            self.out.say(f"{child.name} {why}; the others go on (on_failure = \"continue\")", error=True)
            return
        extra = f" after {child.restarts} restarts" if policy == "restart" else ""
        self.out.say(f"{child.name} {why}{extra}: stopping everything", error=True)
        self.stop_all = True

    def run(self) -> int:
        stopped_by: int | None = None
        for _ in range(10_000_000):  # bounded: each round ends on an event, a signal or a deadline
            now = time.monotonic()
            self._start_ready(now)
            if self.stop_all:
                break
            deadlines = [c.restart_at for c in self.children.values() if c.restart_at is not None]
            deadlines += [c.started + self.launch.ready_timeout for c in self.children.values() if c.state == "starting"]
            if not any(c.running or c.restart_at is not None for c in self.children.values()):
                break
            sig = self.stopper.wait(max(0.0, min(deadlines) - now) if deadlines else None)
            if sig is not None:
                stopped_by = sig
                self.out.say(f"got {signal.Signals(sig).name}: stopping everything (Ctrl-C again: kill at once)")
                break
            self._drain()
            now = time.monotonic()
            for child in self.children.values():
                if child.state == "starting" and now >= child.started + self.launch.ready_timeout:
                    self.out.say(f"{child.name} did not become ready within {self.launch.ready_timeout:g} s "
                                 f"(no line with {child.command.spec.ready!r})", error=True)
                    self._kill(child)
                    self._failed(child, "was not ready in time")
        unstarted = [c.name for c in self.children.values() if c.state == "waiting"]
        if unstarted and not self.stop_all and stopped_by is None:
            self.out.say(f"never started (waiting for failed processes): {', '.join(unstarted)}", error=True)
        clean = self._stop(signal.SIGTERM if stopped_by == signal.SIGTERM else signal.SIGINT)
        return ExitCode.OK if clean and not self.failed and not (unstarted and stopped_by is None) else ExitCode.FAILED

    def _start_ready(self, now: float) -> None:
        if self.stop_all:
            return
        for child in self.children.values():
            if child.restart_at is not None and now >= child.restart_at:
                child.restart_at = None
                self._start(child)
            elif child.state == "waiting" and all(self.children[o].state in ("ready", "ended") for o in child.command.spec.after):
                self._start(child)
            if self.stop_all:
                return

    def _drain(self) -> None:
        while True:
            try:
                kind, name, generation, code = self.events.get_nowait()
            except queue.Empty:
                return
            child = self.children[name]
            if generation != child.generation:
                continue  # from a run before a restart
            if kind == "ready" and child.state == "starting":
                child.state = "ready"
                self.out.say(f"{name} is ready")
                self._tell_reach()
            elif kind == "exit" and child.running:
                if code == 0:
                    child.state = "ended"
                    self.out.say(f"{name} ended (exit code 0)")
                else:
                    self._failed(child, f"exited with {_code(code)}")

    def _tell_reach(self) -> None:
        """Once every process is ready, the options that reach this mesh from another command: on a
        loopback network the daemons take no part in multicast scouting, so a command must be told
        where one listens."""
        if self._told_reach or any(c.state != "ready" for c in self.children.values()):
            return
        self._told_reach = True
        listens = [argv[i + 1] for c in self.children.values() if c.command.spec.kind in ("embodiment", "router")
                   for argv in (c.command.argv,) for i in range(len(argv) - 1) if argv[i] == "--listen"]
        reach = ["--mesh", self.launch.mesh, *(("--certs", self.launch.certs) if self.launch.certs else ())]
        if self.launch.network == "loopback" or self.launch.no_multicast:
            reach += ["--no-multicast", *(x for e in listens[:1] for x in ("--connect", e))]
        self.out.say(f"all ready; reach this mesh with: cmion-mesh peers {' '.join(reach)}")

    def _kill(self, child: _Child) -> None:
        if child.proc is not None and child.proc.poll() is None:
            _signal_group(child.proc.pid, signal.SIGKILL)
            try:
                child.proc.wait(KILL_WAIT)
            except subprocess.TimeoutExpired:
                pass

    def _stop(self, sig: int) -> bool:
        """Signal every running group, wait up to ``stop_timeout``, SIGKILL the rest; True when every
        child stopped on the signal. Then every group is emptied and every reader joined."""
        running = [c for c in self.children.values() if c.proc is not None and c.proc.poll() is None]
        for child in running:
            assert child.proc is not None
            _signal_group(child.proc.pid, sig)
        clean = True
        began = time.monotonic()
        deadline = began + self.launch.stop_timeout
        for _ in range(100_000):
            left = [c for c in running if c.proc is not None and c.proc.poll() is None]
            remaining = deadline - time.monotonic()
            if not left or remaining <= 0:
                break
            if self.stopper.wait(min(remaining, 0.1)) is not None and time.monotonic() - began >= SECOND_SIGNAL_GAP:
                self.out.say("second signal: killing everything now", error=True)
                break
        for child in running:
            assert child.proc is not None
            if child.proc.poll() is None:
                self.out.say(f"{child.name} did not stop within {self.launch.stop_timeout:g} s: killed", error=True)
                self._kill(child)
                clean = False
            else:
                code = child.proc.returncode
                if code not in (0, -sig, 128 + sig):
                    self.out.say(f"{child.name} stopped with {_code(code)}", error=True)
                    clean = False
        for child in self.children.values():
            if child.proc is not None:
                _signal_group(child.proc.pid, signal.SIGKILL)  # whatever the leader left behind in its group
                for reader in child.readers:
                    reader.join(KILL_WAIT)
        states = ", ".join(f"{c.name} {_code(c.proc.returncode)}" for c in self.children.values()
                           if c.proc is not None and c.proc.returncode is not None)
        self.out.say(f"all stopped ({states or 'nothing was started'})")
        return clean


def _signal_group(pid: int, sig: int) -> None:
    try:
        os.killpg(pid, sig)  # a child is the leader of its own group: its group id is its pid
    except (ProcessLookupError, PermissionError):
        pass


def _code(code: int | None) -> str:
    if code is None:
        return "no exit code"
    if code < 0:
        try:
            return f"signal {signal.Signals(-code).name}"
        except ValueError:
            return f"signal {-code}"
    return f"exit code {code}"


def _short(argv: Sequence[str]) -> list[str]:
    """The command line as a person would type it: ``cmion-mesh`` for this interpreter's CLI."""
    prefix = cli_argv()
    return ["cmion-mesh", *argv[len(prefix):]] if list(argv[: len(prefix)]) == prefix else list(argv)


def describe(launch: LaunchFile) -> list[dict[str, Any]]:
    """What ``launch --check`` prints: each process in start order, with its command line."""
    return [{"name": c.spec.name, "kind": c.spec.kind, "after": list(c.spec.after), "ready": c.spec.ready,
             "on_failure": c.spec.on_failure, "command": _short(c.argv), "cwd": c.cwd, "env": c.env}
            for c in commands(launch)]
