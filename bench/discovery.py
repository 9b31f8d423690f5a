"""Daemon start -> discovered: spawning ``cmion-mesh up`` until a watcher sees its liveliness token.

The watcher is the measuring process: a zenoh peer listening on a loopback endpoint with a
liveliness subscriber (``transport.watch_liveliness``, no polling) on the mesh's ``@alive`` keys.
Each round spawns, one after the other:

* a raw zenoh process (``python -m bench.rawtoken``, which imports zenoh and nothing of cmion_mesh
  or of the harness): the same interpreter opens a zenoh session configured as ``ZenohTransport``
  would be, connects to the watcher and declares a liveliness token: the floor for "a Python
  process joins a zenoh mesh";
* a daemon (``cmion-mesh up`` of the bench embodiment, with its state in a temporary folder),
  connecting to the watcher.

For each, the time from just before ``Popen`` to the token being seen by the watcher; for the
daemon also to its own ``up in mesh`` line (as read by the parent: process start, imports,
configuration, session, stores and components) and to a ``describe`` answered, plus the
difference line -> token (negative when the token is seen before the line is printed). Each
process is stopped before the next round. Two more rows say where process start goes: the wall
time of ``python -c "import zenoh"`` and of importing what ``cmion-mesh up`` imports.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from contextlib import ExitStack
from pathlib import Path

from bench.daemons import Node, Stamped, bench_env, stop_all
from bench.harness import loopback_config, loopback_endpoint
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.procs import unique_mesh
from cmion_mesh.transport.zenoh import ZenohTransport, settings

LABELS = {
    "raw_token_seen": "raw zenoh process: spawn -> token seen",
    "mesh_token_seen": "cmion-mesh up: spawn -> token seen",
    "mesh_up_line": "cmion-mesh up: spawn -> 'up in mesh' line",
    "mesh_line_to_token": "cmion-mesh up: 'up' line -> token seen",
    "mesh_described": "cmion-mesh up: spawn -> describe answered",
    "mesh_token_seen_joined": "cmion-mesh up, a daemon already in the mesh: spawn -> token seen",
    "import_zenoh": "python -c 'import zenoh' (wall)",
    "import_cmion": "python -c 'import <what up imports>' (wall)",
}
IMPORTS = ("import cmion_mesh.cli.main, cmion_mesh.cli.daemon, cmion_mesh.body.embodiment, cmion_mesh.transport.zenoh, "
           "bench.minds, bench.competencies")


def log(text: str) -> None:
    print(f"  [discovery] {text}", flush=True)


class Watcher:
    """First time (perf_counter) each liveliness key under ``selector`` was seen alive."""

    def __init__(self, transport: ZenohTransport, selector: str) -> None:
        self.seen: dict[str, float] = {}
        self._cond = threading.Condition()
        self.handle = transport.watch_liveliness(selector, self._on_token)

    def _on_token(self, key: str, alive: bool) -> None:
        now = time.perf_counter()
        if alive:
            with self._cond:
                self.seen.setdefault(key, now)
                self._cond.notify_all()

    def wait(self, key: str, timeout: float) -> float:
        with self._cond:
            if not self._cond.wait_for(lambda: key in self.seen, timeout):
                raise TimeoutError(f"liveliness token {key} not seen within {timeout:g} s")
            return self.seen[key]

    def wait_all(self, names: Sequence[str], prefix: str, timeout: float) -> float:
        """When the last of ``prefix/<name>`` was seen."""
        wanted = [f"{prefix}/{n}" for n in names]
        with self._cond:
            if not self._cond.wait_for(lambda: all(k in self.seen for k in wanted), timeout):
                missing = [k for k in wanted if k not in self.seen]
                raise TimeoutError(f"{len(missing)} of {len(wanted)} tokens not seen within {timeout:g} s: {missing[:5]}")
            return max(self.seen[k] for k in wanted)

    def close(self) -> None:
        self.handle.close()


def token_child(key: str, connect: str, name: str, listen: str = "") -> Stamped:
    """``bench.rawtoken`` declaring ``key``, connected to ``connect`` with ``ZenohTransport``'s settings
    (and listening on ``listen``, if given: then peers that gossip find it, as they find a daemon)."""
    config = loopback_config(connect=connect, listen=listen) if listen else loopback_config(connect=connect)
    argv = [sys.executable, "-m", "bench.rawtoken", key, json.dumps(settings(config)), str(os.getpid())]
    return Stamped(argv, env=bench_env(), name=name)


def import_wall(code: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], env={**os.environ, **bench_env()}, check=True, timeout=60,
                   stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    rounds = 3 if options.quick else 10
    mesh = unique_mesh("bench")
    watch_ep = loopback_endpoint()
    alive = f"{keys.mesh_prefix(mesh)}/{keys.ALIVE}"
    samples: dict[str, list[float]] = {m: [] for m in LABELS}
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-discovery-")))
        transport = ZenohTransport(loopback_config(listen=watch_ep))
        stack.callback(transport.close)
        watcher = Watcher(transport, f"{alive}/*")
        stack.callback(watcher.close)
        client = MeshClient(transport, mesh)
        for i in range(-1, rounds):  # round -1 warms up (first link, bytecode cache): not recorded
            raw = token_child(f"{alive}/raw-{i}", watch_ep, f"raw-{i}")
            try:
                seen = watcher.wait(f"{alive}/raw-{i}", 30.0)
                if i >= 0:
                    samples["raw_token_seen"].append(seen - raw.spawned)
            finally:
                raw.stop(grace=5.0)
            node = Node(f"d{i}", mesh, tmp / f"d{i}", connect=(watch_ep,))
            node.start()
            try:
                assert node.daemon is not None
                spawned = node.daemon.spawned
                seen = watcher.wait(f"{alive}/d{i}", 60.0)
                client.describe(f"d{i}", timeout=10.0)
                described = time.perf_counter()
                line = node.wait_up(30.0)
                if i >= 0:
                    samples["mesh_token_seen"].append(seen - spawned)
                    samples["mesh_up_line"].append(line - spawned)
                    samples["mesh_line_to_token"].append(seen - line)
                    samples["mesh_described"].append(described - spawned)
            finally:
                for problem in stop_all([node]):
                    log(problem)
        log(f"{rounds} rounds of spawn -> discovered done")
        # The same, with a daemon already in the mesh: a joining daemon asks the mesh who holds its
        # name and gets an answer at once; in a mesh with no token at all (above) it waits a moment
        # (presence.SETTLE) before believing that nobody is there.
        anchor = Node("anchor", mesh, tmp / "anchor", connect=(watch_ep,))
        anchor.start()
        stack.callback(stop_all, [anchor])
        watcher.wait(f"{alive}/anchor", 60.0)
        for i in range(-1, rounds):
            node = Node(f"j{i}", mesh, tmp / f"j{i}", connect=(watch_ep,))
            node.start()
            try:
                assert node.daemon is not None
                seen = watcher.wait(f"{alive}/j{i}", 60.0)
                if i >= 0:
                    samples["mesh_token_seen_joined"].append(seen - node.daemon.spawned)
            finally:
                for problem in stop_all([node]):
                    log(problem)
        log(f"{rounds} rounds of spawn -> discovered, joining a daemon, done")
        for _ in range(rounds):
            samples["import_zenoh"].append(import_wall("import zenoh"))
            samples["import_cmion"].append(import_wall(IMPORTS))
    rows = [Row(m, LABELS[m], summarize(samples[m]), extra={"rounds": rounds}) for m in LABELS]
    compare(rows, {"mesh_token_seen": "raw_token_seen", "mesh_token_seen_joined": "raw_token_seen", "import_cmion": "import_zenoh"},
            None)
    return rows
