"""A one-shot command's wall time, process start to exit: what a person at the command line waits.

Three shipped daemons (robot, screen, phone) run in a mesh of their own, on loopback. Each round
runs, one after the other, as separate processes:

* ``python -c "import zenoh"``: the floor for any Python program that speaks zenoh;
* a raw zenoh one-shot (``python -c``): open a session connected to the robot, wait for the three
  daemons' liveliness tokens (the others are found through the robot), one liveliness query,
  close: what "join, then ask" costs in plain zenoh;
* ``cmion-mesh peers --json`` (complete: it must list all three) and ``cmion-mesh bb get robot
  trial`` (it must print the value written before the rounds), each connecting to the robot only.

A wrong answer is a failure of the row, not a slow sample. Rows: median and p99 in ms, with the
ratio to ``import zenoh`` and the issue's aim of 400 ms for the two commands.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

from bench.daemons import Node, bench_env, stop_and_report
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.procs import cli_argv, unique_mesh

LABELS = {
    "import_zenoh": 'python -c "import zenoh" (wall)',
    "raw_oneshot": "raw zenoh one-shot: open, join, liveliness get, close (wall)",
    "cli_peers": "cmion-mesh peers --json, complete (wall)",
    "cli_bb_get": "cmion-mesh bb get robot trial (wall)",
}
RAW_ONESHOT = """
import sys, threading, zenoh
mesh, endpoint = sys.argv[1:3]
config = zenoh.Config()
for key, value in (("mode", '"peer"'), ("connect/endpoints", f'["{endpoint}"]'), ("listen/endpoints", "[]"),
                   ("scouting/multicast/enabled", "false"), ("open/return_conditions/connect_scouted", "false")):
    config.insert_json5(key, value)
with zenoh.open(config) as session:
    names, lock, joined = set(), threading.Lock(), threading.Event()

    def on_token(sample):
        with lock:
            names.add(str(sample.key_expr))
            if len(names) == 3:
                joined.set()

    with session.liveliness().declare_subscriber(f"cmion/{mesh}/@alive/*", on_token, history=True):
        if not joined.wait(10):
            sys.exit(1)
    # Just after a link comes up a liveliness query can reach nobody (its answer is then empty, at
    # once): asked again, as a plain zenoh client must.
    for _ in range(3):
        found = len([r for r in session.liveliness().get(f"cmion/{mesh}/@alive/*", timeout=5) if r.ok is not None])
        if found:
            break
    print(found)
"""


def log(text: str) -> None:
    print(f"  [oneshot] {text}", flush=True)


def command(*args: str) -> list[str]:
    """The installed ``cmion-mesh`` script when there is one beside this interpreter (what a user runs)."""
    script = Path(sys.executable).with_name("cmion-mesh")
    return [str(script), *args] if script.exists() else cli_argv(*args)


def timed(argv: list[str]) -> tuple[float, subprocess.CompletedProcess[str]]:
    started = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, timeout=60, env={**os.environ, **bench_env()},
                          stdin=subprocess.DEVNULL)
    return time.perf_counter() - started, done


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    rounds = 8 if options.quick else 40
    mesh = unique_mesh("oneshot")
    samples: dict[str, list[float]] = {m: [] for m in LABELS}
    failures: dict[str, list[str]] = {m: [] for m in LABELS}
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-oneshot-")))
        nodes = [Node(name, mesh, tmp / name, architecture=name) for name in ("robot", "screen", "phone")]
        for i, node in enumerate(nodes):
            node.connect = tuple(n.listen for n in nodes[:i])
        stack.callback(stop_and_report, nodes, log)
        for node in nodes:
            node.start()
        for node in nodes:
            node.wait_up(60.0)
        net = ["--mesh", mesh, "--no-multicast", "--connect", nodes[0].listen]
        written = subprocess.run(command("bb", "set", "robot", "trial", "7", *net), capture_output=True, text=True, timeout=60,
                                 env={**os.environ, **bench_env()})
        if written.returncode != 0:
            raise RuntimeError(f"bb set failed: {written.stderr.strip()}")
        checks = {
            "import_zenoh": ([sys.executable, "-c", "import zenoh"], lambda out: True),
            "raw_oneshot": ([sys.executable, "-c", RAW_ONESHOT, mesh, nodes[0].listen], lambda out: out.strip() == "3"),
            "cli_peers": (command("peers", "--json", *net),
                          lambda out: sorted(p["name"] for p in json.loads(out)) == ["phone", "robot", "screen"]),
            "cli_bb_get": (command("bb", "get", "robot", "trial", *net), lambda out: out.split() == ["trial", "=", "7"]),
        }
        for i in range(rounds):
            for metric, (argv, right) in checks.items():
                took, done = timed(argv)
                samples[metric].append(took)
                if done.returncode != 0 or not right(done.stdout):
                    failures[metric].append(f"round {i}: exit {done.returncode}: {(done.stderr or done.stdout).strip()[:200]}")
        log(f"{rounds} rounds done")
    rows = [Row(m, LABELS[m], summarize(samples[m]), extra={"rounds": rounds}, failures=failures[m][:3]) for m in LABELS]
    compare(rows, {"raw_oneshot": "import_zenoh", "cli_peers": "import_zenoh", "cli_bb_get": "import_zenoh"}, None)
    return rows
