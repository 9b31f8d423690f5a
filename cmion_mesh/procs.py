"""Starting and stopping daemon processes, and waiting on them: used by the demo, ``launch``, the
benchmarks and the tests.

Processes are started with ``subprocess`` (never ``fork`` after zenoh is open: the child hangs),
always stopped (SIGTERM, then SIGKILL after a grace period), and their output is read by a
thread so that waiting for a line has a deadline.

A parent that is itself SIGKILLed cannot stop its children: ``child_setup`` has the kernel send
them SIGTERM when it dies (Linux's ``PR_SET_PDEATHSIG``), so a killed ``launch`` or ``demo``
leaves no daemon running for ever.

``wait_for`` waits, with a deadline, on a condition that nothing signals (another process's state).
"""

from __future__ import annotations

import ctypes
import os
import queue
import random
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from typing import TypeVar

#: ``prctl`` option: the signal the kernel sends this process when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1

T = TypeVar("T")


#: Where ``free_port`` looks first, below the kernel's ephemeral range (see ``ephemeral_floor``).
PORTS_FROM = 20000
#: Ports ``free_port`` handed out in this process, never handed out again by it.
_handed_out: set[int] = set()
_ports = random.Random()  # seeded per process: two processes try different ports first


def ephemeral_floor() -> int:
    """The lowest port the kernel gives to outgoing connections and to binds on port 0."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 0


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, for a process about to listen on it.

    Chosen below the kernel's ephemeral range where there is one: a port from that range can be
    taken meanwhile by any outgoing connection (every zenoh session that links to a peer takes
    one), and a daemon starting 0.2 s later then fails with "Address already in use"."""
    floor = ephemeral_floor()
    for _ in range(64 if floor > PORTS_FROM else 0):
        port = _ports.randrange(PORTS_FROM, floor)
        if port in _handed_out:
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _handed_out.add(port)
        return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        chosen: int = s.getsockname()[1]
        return chosen


def unique_mesh(prefix: str = "t") -> str:
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


def _prctl() -> Callable[..., int] | None:
    """libc's ``prctl``, looked up before any fork (nothing may be loaded between fork and exec);
    None where there is none (not Linux)."""
    try:
        function: Callable[..., int] = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    return function


def child_setup(die_with_parent: bool = True) -> Callable[[], None]:
    """A ``preexec_fn`` for ``subprocess.Popen``, run in the child between fork and exec.

    * It unblocks every signal: a parent waiting with ``signals.Stopper`` blocks SIGINT and SIGTERM,
      and a blocked mask survives exec, so a child that does not ``sigwait`` itself (any program
      but cmion-mesh) could never be stopped by them.
    * ``die_with_parent``: the kernel sends the child SIGTERM when the parent dies, even by SIGKILL.
      A pipe the child watches would need every child's cooperation; this needs none. The kernel
      ties it to the *thread* that forked: start children from a thread that lives as long as the
      parent (the main thread). Without ``prctl`` (not Linux) nothing is set.
    """
    prctl = _prctl() if die_with_parent else None
    parent = os.getpid()

    def setup() -> None:
        signal.pthread_sigmask(signal.SIG_SETMASK, ())
        if prctl is not None:
            prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
            if os.getppid() != parent:  # the parent died before prctl: nobody would ever send it
                os._exit(1)

    return setup


class Daemon:
    """A child process whose output lines are collected; a context manager that always stops it."""

    def __init__(self, argv: Sequence[str], *, env: dict[str, str] | None = None, name: str = "", stdin: bool = False,
                 die_with_parent: bool = False, cwd: str | os.PathLike[str] | None = None) -> None:
        """``stdin``: a pipe to the child's standard input (``send`` writes a line to it); else none.
        ``cwd``: the folder it runs in (default: this process's).
        ``die_with_parent``: see ``child_setup`` (only from a thread that lives as long as this process)."""
        self.name = name or os.path.basename(argv[0])
        self.argv = list(argv)
        full_env = dict(os.environ)
        full_env["PYTHONUNBUFFERED"] = "1"
        if env:
            full_env.update(env)
        self.proc = subprocess.Popen(
            self.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            env=full_env, text=True, start_new_session=True, cwd=cwd, preexec_fn=child_setup(die_with_parent) if die_with_parent else None,
        )
        self.lines: list[str] = []
        self._queue: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        self._reader = threading.Thread(target=self._read, name=f"out-{self.name}", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            line = raw.rstrip("\n")
            self.lines.append(line)
            self._queue.put(line)
        self._queue.put(None)

    def wait_line(self, needle: str, timeout: float = 15.0) -> str:
        """Wait for an output line containing ``needle``; ``TimeoutError`` with the output so far."""
        deadline = time.monotonic() + timeout
        for line in list(self.lines):
            if needle in line:
                return line
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            try:
                got = self._queue.get(timeout=left)
            except queue.Empty:
                break
            if got is None:
                break
            if needle in got:
                return got
        tail = "\n".join(self.lines[-20:])
        raise TimeoutError(f"{self.name}: no line with {needle!r} within {timeout:g} s; output:\n{tail}")

    def send(self, line: str) -> None:
        """Write ``line`` to the child's standard input (started with ``stdin=True``)."""
        if self.proc.stdin is None:
            raise ValueError(f"{self.name}: started without a pipe to its standard input")
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def stop(self, sig: int = signal.SIGTERM, grace: float = 10.0) -> int:
        if self.proc.poll() is None:
            try:
                self.proc.send_signal(sig)
                self.proc.wait(grace)
            except subprocess.TimeoutExpired:
                self.kill()
        code = self.proc.wait(grace)
        self._reader.join(grace)
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        return code

    def kill(self) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.proc.wait(10)

    def __enter__(self) -> Daemon:
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()


def cli_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "cmion_mesh.cli.main", *args]


def wait_for(condition: Callable[[], T], timeout: float, what: str, interval: float = 0.02) -> T:
    """Return ``condition()``'s first truthy value, or raise ``TimeoutError`` naming ``what``.

    For conditions that cannot be waited on directly (another process's state): bounded in
    time, and each try is cheap.
    """
    deadline = time.monotonic() + timeout
    tries = 0
    while True:
        tries += 1
        value = condition()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise TimeoutError(f"{what}: not true after {timeout:g} s ({tries} tries)")
        threading.Event().wait(interval)
