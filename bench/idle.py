"""An idle daemon's cost: CPU, resident memory and threads of ``cmion-mesh up robot``, beside a raw zenoh peer.

``cmion-mesh up robot`` runs the shipped robot embodiment (its planner mind, competencies with a
background operator console, the companion born there) with ``--state-dir`` in a temporary
folder, listening on a loopback endpoint, nobody else in its mesh. Beside it, for comparison,
``python -m bench.core serve-raw``: a Python process with one zenoh peer session, a subscriber
and a queryable, each drained by a thread. Once both are up and have settled (2 s; quick 1 s),
``/proc/<pid>/stat`` (utime + stime) and ``/proc/<pid>/status`` (VmRSS, Threads) are read every
second (quick: every half second) for the window (5 s; quick 2 s). CPU % is of one core, per
interval; the rows give the median and p99 over the intervals and, in the JSON, the whole
window's average.
"""

from __future__ import annotations

import itertools
import tempfile
import threading
from contextlib import ExitStack
from pathlib import Path

from bench.daemons import Node, ProcSample, Sampler, cpu_percent, stop_and_report
from bench.harness import loopback_endpoint, start_child, stop_child
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.procs import unique_mesh


def log(text: str) -> None:
    print(f"  [idle] {text}", flush=True)


def interval_cpu(samples: list[ProcSample]) -> list[float]:
    return [cpu_percent(a, b) for a, b in itertools.pairwise(samples)]


def rows_for(prefix: str, who: str, samples: list[ProcSample], window: float) -> list[Row]:
    cpu = interval_cpu(samples)
    whole = cpu_percent(samples[0], samples[-1])
    extra = {"window_s": round(window, 2), "window_cpu_percent": whole}
    return [
        Row(f"{prefix}_cpu", f"{who}: CPU (% of one core)", summarize(cpu, 1.0), unit="%", extra=extra),
        Row(f"{prefix}_rss", f"{who}: resident memory (VmRSS)", summarize([s.rss_mb for s in samples], 1.0), unit="MiB"),
        Row(f"{prefix}_threads", f"{who}: threads", summarize([float(s.threads) for s in samples], 1.0), unit="threads"),
    ]


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    settle, window, interval = (1.0, 2.0, 0.5) if options.quick else (2.0, 5.0, 1.0)
    mesh = unique_mesh("bench")
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-idle-")))
        raw = start_child("bench.core", "serve-raw", "--listen", loopback_endpoint(), "--tag", mesh, name="serve-raw")
        stack.callback(stop_child, raw)
        node = Node("robot", mesh, tmp / "robot", architecture="robot")
        node.start()
        stack.callback(stop_and_report, [node], log)
        raw.wait_line("ready", 30.0)
        node.wait_up(60.0)
        log(f"robot daemon (pid {node.pid}) and raw peer (pid {raw.proc.pid}) up; settling {settle:g} s, then {window:g} s")
        threading.Event().wait(settle)
        sampler = Sampler({"daemon": node.pid, "raw": raw.proc.pid}, interval).start()
        threading.Event().wait(window)
        sampler.stop()
        if node.daemon is not None and node.daemon.proc.poll() is not None:
            raise RuntimeError(f"the robot daemon exited during the window: {node.daemon.lines[-5:]}")
    rows = [*rows_for("daemon", "cmion-mesh up robot, idle", sampler.samples["daemon"], window),
            *rows_for("raw", "raw zenoh peer process, idle", sampler.samples["raw"], window)]
    compare(rows, {"daemon_cpu": "raw_cpu", "daemon_rss": "raw_rss", "daemon_threads": "raw_threads"}, None)
    order = ["daemon_cpu", "raw_cpu", "daemon_rss", "raw_rss", "daemon_threads", "raw_threads"]
    by_id = {r.metric: r for r in rows}
    return [by_id[m] for m in order]
