"""Growth curve (c): discovery convergence and per-daemon cost against the number of daemons.

For each mesh size N, the measuring process (a zenoh peer listening on a loopback endpoint, with
a liveliness subscriber on the mesh's ``@alive`` keys) first spawns N raw zenoh processes at once
(``python -m bench.rawtoken``: a session connected to the watcher and listening on a loopback port
of its own, as a daemon does, so that they form the same full mesh; one liveliness token),
waits until it has seen every token, samples their memory and stops them; then it spawns N
``cmion-mesh up`` daemons of the bench embodiment at once (each listening on its own loopback
port, connecting to the watcher; zenoh's gossip lets them find each other through it) and takes
the time until every token has been seen *and* every daemon has answered a ``describe``. Then,
after a settling second, ``/proc`` gives each process's resident memory and threads, and a
window of 2 s (quick 1 s) its CPU. All of it on this 2-core machine: with many processes the
times are dominated by starting Python processes in parallel, which the rows separate out
(spawn -> last "up in mesh" line). The raw processes' idle CPU is sampled over the same window:
each zenoh peer of a mesh of N keeps N-1 links alive, whatever runs above it. Each size is measured twice (once with ``--quick`` and for
32 daemons); memory, threads and CPU are per process, pooled over the repeats.
"""

from __future__ import annotations

import tempfile
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

from bench.daemons import Node, Stamped, cpu_percent, proc_sample, stop_and_report
from bench.discovery import Watcher, token_child
from bench.harness import loopback_config, loopback_endpoint
from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.procs import unique_mesh
from cmion_mesh.transport.zenoh import ZenohTransport


@dataclass
class Point:
    """One mesh size, measured ``repeats`` times: each list holds one value per repeat (times) or
    one per process (memory, threads, CPU)."""

    n: int
    raw_converged: list[float] = field(default_factory=list)  # s, spawn all -> every token seen
    mesh_converged: list[float] = field(default_factory=list)  # s, spawn all -> every token seen and every daemon described
    mesh_tokens: list[float] = field(default_factory=list)  # s, spawn all -> every token seen
    mesh_last_up: list[float] = field(default_factory=list)  # s, spawn all -> the last "up in mesh" line
    raw_rss: list[float] = field(default_factory=list)
    mesh_rss: list[float] = field(default_factory=list)
    raw_threads: list[float] = field(default_factory=list)
    raw_cpu: list[float] = field(default_factory=list)
    mesh_threads: list[float] = field(default_factory=list)
    mesh_cpu: list[float] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)


def log(text: str) -> None:
    print(f"  [convergence] {text}", flush=True)


def stop_children(children: Sequence[Stamped]) -> None:
    for child in children:
        if child.proc.poll() is None:
            child.proc.terminate()
    for child in children:
        try:
            child.proc.wait(10.0)
        except Exception:
            child.kill()


def measure_once(point: Point, window: float) -> None:
    n = point.n
    mesh = unique_mesh("bench")
    watch_ep = loopback_endpoint()
    alive = f"{keys.mesh_prefix(mesh)}/{keys.ALIVE}"
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-convergence-")))
        transport = ZenohTransport(loopback_config(listen=watch_ep))
        stack.callback(transport.close)
        watcher = Watcher(transport, f"{alive}/*")
        stack.callback(watcher.close)
        client = MeshClient(transport, mesh)

        raws: list[Stamped] = []
        try:
            t0 = time.perf_counter()
            # Each listening on a port of its own, as the daemons do: the raw peers form the same full
            # mesh (N-1 links each, found by gossip) rather than a star around the watcher.
            raws = [token_child(f"{alive}/raw{j}", watch_ep, f"raw{j}", listen=loopback_endpoint()) for j in range(n)]
            point.raw_converged.append(watcher.wait_all([f"raw{j}" for j in range(n)], alive, 60.0 + 5 * n) - t0)
            threading.Event().wait(1.0)
            raw_first = {child.proc.pid: proc_sample(child.proc.pid) for child in raws}
            threading.Event().wait(window)
            for child in raws:
                sample = proc_sample(child.proc.pid)
                point.raw_rss.append(sample.rss_mb)
                point.raw_threads.append(float(sample.threads))
                point.raw_cpu.append(cpu_percent(raw_first[child.proc.pid], sample))
        finally:
            stop_children(raws)

        names = [f"n{j}" for j in range(n)]
        nodes = [Node(name, mesh, tmp / name, connect=(watch_ep,)) for name in names]
        stack.callback(stop_and_report, nodes, point.problems.append)
        t0 = time.perf_counter()
        for node in nodes:
            node.start()
        point.mesh_tokens.append(watcher.wait_all(names, alive, 60.0 + 5 * n) - t0)
        with ThreadPoolExecutor(max_workers=min(16, n)) as pool:
            list(pool.map(partial(client.describe, timeout=30.0), names))
        point.mesh_converged.append(time.perf_counter() - t0)
        point.mesh_last_up.append(max(node.wait_up(60.0) for node in nodes) - t0)
        threading.Event().wait(1.0)
        first = {node.name: proc_sample(node.pid) for node in nodes}
        threading.Event().wait(window)
        for node in nodes:
            last = proc_sample(node.pid)
            point.mesh_rss.append(last.rss_mb)
            point.mesh_threads.append(float(last.threads))
            point.mesh_cpu.append(cpu_percent(first[node.name], last))


def measure(sizes: Sequence[int], quick: bool) -> list[Point]:
    points = []
    window = 1.0 if quick else 2.0
    for n in sizes:
        point = Point(n)
        repeats = 1 if quick or n > 16 else 2
        for _ in range(repeats):
            measure_once(point, window)
        for problem in point.problems:
            log(problem)
        log(f"{n} daemons: converged in {', '.join(f'{t:.2f}' for t in point.mesh_converged)} s "
            f"(raw processes {', '.join(f'{t:.2f}' for t in point.raw_converged)} s)")
        points.append(point)
    return points
