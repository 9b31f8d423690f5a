"""Plumbing shared by benchmarks: loopback-only zenoh configs, child processes, deadlines, rounds.

Only loopback traffic is allowed: every session either listens on ``tcp/127.0.0.1:<port>`` or
listens on nothing (zenoh's default peer listener is ``tcp/[::]:0``, i.e. every interface), and
multicast scouting is off, so sessions find each other only through explicit endpoints.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from types import FrameType
from typing import Protocol, TypeVar

from cmion_mesh.procs import Daemon, free_port
from cmion_mesh.transport.base import TransportConfig

T = TypeVar("T")

REPO_ROOT = Path(__file__).resolve().parent.parent


def loopback_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def loopback_config(*, listen: str | None = None, connect: str | None = None) -> TransportConfig:
    """A peer that listens only on ``listen`` (or nowhere) and connects only to ``connect``."""
    for endpoint in (listen, connect):
        if endpoint is not None and not endpoint.startswith("tcp/127.0.0.1:"):
            raise ValueError(f"benchmarks use loopback only, not {endpoint!r}")
    return TransportConfig(
        listen=(listen,) if listen else (),
        connect=(connect,) if connect else (),
        multicast=False,
        overrides=() if listen else (("listen/endpoints", "[]"),),
    )


def start_child(module: str, *args: str, name: str) -> Daemon:
    """``python -m <module> <args>`` with the repository importable; output collected by ``Daemon``."""
    path = os.pathsep.join(p for p in (str(REPO_ROOT), os.environ.get("PYTHONPATH", "")) if p)
    argv = [sys.executable, "-m", module, *args, "--parent", str(os.getpid())]
    return Daemon(argv, env={"PYTHONPATH": path}, name=name)


def stop_child(child: Daemon) -> None:
    """SIGTERM, then SIGKILL after a grace period (``Daemon.stop``); never raises, reports a bad exit."""
    try:
        code = child.stop(grace=5.0)
    except Exception as exc:
        child.kill()
        print(f"  [{child.name}] could not be stopped cleanly ({exc}); killed", flush=True)
        return
    if code != 0:
        tail = "\n".join(child.lines[-10:])
        print(f"  [{child.name}] exited with {code}; last output:\n{tail}", flush=True)


class StopSignal:
    """Install SIGTERM/SIGINT handlers at once (first thing a child does), wait for them later."""

    def __init__(self, parent: int | None) -> None:
        self.parent = parent
        self.event = threading.Event()
        signal.signal(signal.SIGTERM, self._on_signal)
        signal.signal(signal.SIGINT, self._on_signal)

    def _on_signal(self, _sig: int, _frame: FrameType | None) -> None:
        self.event.set()

    def wait(self) -> None:
        """Block until signalled or until the parent process is gone."""
        # The timeout is a watchdog for an orphaned child (parent killed), not a readiness wait.
        while not self.event.wait(1.0):
            if self.parent is not None and os.getppid() != self.parent:
                break


def with_deadline(fn: Callable[[], T], timeout: float, what: str) -> T:
    """Run ``fn`` on a daemon thread; its result, its exception, or ``TimeoutError`` naming ``what``.

    Blocking zenoh receives have no timeout of their own: a lost message must not hang the run.
    A thread left blocked is released when its session closes.
    """
    result: list[T] = []
    error: list[BaseException] = []

    def target() -> None:
        try:
            result.append(fn())
        except BaseException as exc:
            error.append(exc)

    thread = threading.Thread(target=target, name=f"bench-{what}", daemon=True)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        raise TimeoutError(f"{what}: not done within {timeout:g} s")
    if error:
        raise error[0]
    return result[0]


def retry_until(action: Callable[[], None], done: threading.Event, *, timeout: float, what: str, interval: float = 0.05) -> None:
    """Repeat ``action`` every ``interval`` until ``done`` is set (by whoever sees the answer), bounded."""
    deadline = time.monotonic() + timeout
    tries = 0
    while not done.is_set():
        if time.monotonic() >= deadline:
            raise TimeoutError(f"{what}: no answer after {timeout:g} s ({tries} tries)")
        tries += 1
        action()
        done.wait(interval)


class Probe(Protocol):
    """One metric measured by repeated round trips; samples are in seconds."""

    metric: str

    def contact(self) -> None:
        """Return once a first round trip succeeded (routes declared both ways); bounded in time."""

    def measure(self, count: int) -> list[float]:
        """``count`` consecutive samples."""


def chunk_sizes(total: int, rounds: int) -> list[int]:
    rounds = max(1, min(rounds, total))
    base = total // rounds
    return [base + (1 if i < total % rounds else 0) for i in range(rounds)]


def chunk_timeout(count: int) -> float:
    """Generous: 30 s plus 50 ms per round trip (medians are well under a millisecond)."""
    return 30.0 + 0.05 * count


def interleaved(probes: Sequence[Probe], *, samples: int, warmup: int, rounds: int, rewarm: int,
                log: Callable[[str], None]) -> dict[str, list[float]]:
    """Warm every probe up, then measure them in turn, round after round, pooling samples per metric.

    Probes are given raw first, then cmion, so each round measures a raw metric right before
    the cmion metrics compared with it: slow drifts of the machine affect both alike.
    """
    pooled: dict[str, list[float]] = {p.metric: [] for p in probes}
    for probe in probes:
        with_deadline(probe.contact, 30.0, f"{probe.metric} first contact")
        if warmup:
            with_deadline(partial(probe.measure, warmup), chunk_timeout(warmup), f"{probe.metric} warm-up")
    sizes = chunk_sizes(samples, rounds)
    for i, size in enumerate(sizes):
        for probe in probes:
            if rewarm:
                with_deadline(partial(probe.measure, rewarm), chunk_timeout(rewarm), f"{probe.metric} re-warm")
            got = with_deadline(partial(probe.measure, size), chunk_timeout(size), f"{probe.metric} round {i + 1}")
            pooled[probe.metric].extend(got)
        log(f"round {i + 1}/{len(sizes)} done ({size} samples per metric)")
    return pooled
