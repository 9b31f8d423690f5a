"""Running a launch file's processes (``tools/launch.py`` reads the file): started, watched and
stopped as one.

Every child is a process group of its own (a Ctrl-C at the terminal reaches the launcher only,
which then stops the children in order and waits for them); each line a child writes is printed
with its name in front; a child starts once the ones it comes ``after`` are
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
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import IO

from cmion_mesh.errors import ExitCode
from cmion_mesh.procs import child_setup
from cmion_mesh.signals import Stopper
from cmion_mesh.tools.launch import Command, LaunchFile, as_typed, commands

#: Delay before the n-th restart of a failed process (seconds): 1, 2, 4... at most this.
MAX_BACKOFF = 10.0
#: After SIGKILL, how long a process may take to be reaped before the launcher gives up on it.
KILL_WAIT = 5.0
#: A second stop signal kills at once only this long after the first: some tools deliver one
#: signal twice at once (GNU timeout signals its child, then its whole process group).
SECOND_SIGNAL_GAP = 1.0
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
        self.out.say(f"started {child.name} (pid {proc.pid}): {' '.join(as_typed(command.argv))}")
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
