"""Starting and stopping daemon processes: used by the demo, the benchmarks and the tests.

Processes are started with ``subprocess`` (never ``fork`` after zenoh is open: the child hangs),
always stopped (SIGTERM, then SIGKILL after a grace period), and their output is read by a
thread so that waiting for a line has a deadline.
"""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Sequence


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def unique_mesh(prefix: str = "t") -> str:
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


class Daemon:
    """A child process whose output lines are collected; a context manager that always stops it."""

    def __init__(self, argv: Sequence[str], *, env: dict[str, str] | None = None, name: str = "", stdin: bool = False) -> None:
        """``stdin``: a pipe to the child's standard input (``send`` writes a line to it); else none."""
        self.name = name or os.path.basename(argv[0])
        self.argv = list(argv)
        full_env = dict(os.environ)
        full_env["PYTHONUNBUFFERED"] = "1"
        if env:
            full_env.update(env)
        self.proc = subprocess.Popen(
            self.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            env=full_env, text=True, start_new_session=True,
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
    return [sys.executable, "-m", "cmion_mesh.cli", *args]
