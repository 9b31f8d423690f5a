"""Growth curves (issue 6): how the costs grow with the load, each as a table (``--png`` draws them).

* ``fanout`` (``bench.fanout``): sustained event throughput, with none lost (checked by sequence
  numbers), against 1, 2, 4 and 8 subscriber processes; cmion and raw zenoh.
* ``wildcard`` (``bench.wildcard``): a wildcard get of a whole blackboard against its size (10,
  1k, 100k properties); cmion ``MeshClient.read`` and a raw zenoh get of as many replies.
* ``convergence`` (``bench.convergence``): the time until a watcher has seen and described every
  daemon, and per-daemon memory, threads and idle CPU, against 2, 8, 16 daemons (32 with
  ``--full``; quick: 2 and 8), beside as many raw zenoh processes.
* migration time against document size is the ``migration`` benchmark's curve.
"""

from __future__ import annotations

import time

from bench import convergence, fanout, wildcard
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.procs import unique_mesh

GROUPS = (1, 2, 4, 8)
SIZES = (10, 1000, 100_000)


def log(text: str) -> None:
    print(f"  [growth] {text}", flush=True)


def curve(name: str, title: str, x_label: str, x: float, series: str) -> dict[str, object]:
    return {"curve": name, "curve_title": title, "x_label": x_label, "x": x, "series": series}


def fanout_rows(options: Options) -> list[Row]:
    count, rounds = (5000, 1) if options.quick else (20000, 3)
    rows = []
    for result in fanout.measure(unique_mesh("bench"), GROUPS, count, rounds):
        who = "raw zenoh" if result.kind == "raw" else "cmion"
        row = Row(f"fanout_{result.kind}_{result.group}", f"{who} events/s, {result.group} subscriber process(es)", result.summary(),
                  unit="events/s", extra={"events_per_run": count, "lost": result.lost, "reordered": result.reordered,
                                          **curve("fanout", "event throughput vs subscriber processes", "subscribers",
                                                  result.group, who)})
        if result.lost:
            row.failures.append(f"{result.lost} events lost")
        if result.reordered:
            row.failures.append(f"{result.reordered} events out of order")
        rows.append(row)
    rows.sort(key=lambda r: (r.extra["x"], r.extra["series"] != "raw zenoh"))
    compare(rows, {f"fanout_mesh_{g}": f"fanout_raw_{g}" for g in GROUPS}, None)
    return rows


def wildcard_rows(options: Options) -> list[Row]:
    repeats = {10: 20, 1000: 10, 100_000: 1} if options.quick else {10: 100, 1000: 30, 100_000: 3}
    samples = wildcard.measure(unique_mesh("bench"), SIZES, repeats)
    rows = []
    for size in SIZES:
        for kind in ("raw", "mesh"):
            who = "raw zenoh" if kind == "raw" else "cmion"
            label = (f"raw zenoh get, {size} replies" if kind == "raw" else f"cmion wildcard get of a blackboard of {size} properties")
            rows.append(Row(f"wildcard_{kind}_{size}", label, summarize(samples[(kind, size)]),
                            extra=curve("wildcard", "wildcard get vs blackboard size", "properties", size, who)))
    compare(rows, {f"wildcard_mesh_{s}": f"wildcard_raw_{s}" for s in SIZES}, None)
    return rows


def convergence_rows(options: Options) -> list[Row]:
    sizes = (2, 8) if options.quick else ((2, 8, 16, 32) if options.full else (2, 8, 16))
    rows = []
    for p in convergence.measure(sizes, options.quick):
        conv = curve("convergence", "discovery convergence vs daemons", "daemons", p.n, "cmion (tokens + describe)")
        raw_conv = curve("convergence", "discovery convergence vs daemons", "daemons", p.n, "raw zenoh (tokens)")
        mem = curve("memory", "resident memory per process vs daemons", "daemons", p.n, "cmion daemon")
        raw_mem = curve("memory", "resident memory per process vs daemons", "daemons", p.n, "raw zenoh process")
        block = [
            Row(f"convergence_raw_{p.n}", f"{p.n} raw zenoh processes: spawn all -> every token seen",
                summarize(p.raw_converged, 1.0), unit="s", extra=raw_conv),
            Row(f"convergence_{p.n}", f"{p.n} daemons: spawn all -> every token seen + described", summarize(p.mesh_converged, 1.0),
                unit="s", extra={**conv, "tokens_s": p.mesh_tokens, "last_up_line_s": p.mesh_last_up}),
            Row(f"last_up_{p.n}", f"{p.n} daemons: spawn all -> last 'up in mesh' line", summarize(p.mesh_last_up, 1.0), unit="s"),
            Row(f"rss_raw_{p.n}", f"{p.n} raw zenoh processes: memory per process", summarize(p.raw_rss, 1.0), unit="MiB", extra=raw_mem),
            Row(f"rss_{p.n}", f"{p.n} daemons: memory per daemon", summarize(p.mesh_rss, 1.0), unit="MiB", extra=mem),
            Row(f"threads_{p.n}", f"{p.n} daemons: threads per daemon", summarize(p.mesh_threads, 1.0), unit="threads"),
            Row(f"cpu_raw_{p.n}", f"{p.n} raw zenoh processes: idle CPU per process", summarize(p.raw_cpu, 1.0), unit="%",
                extra=curve("idle_cpu", "idle CPU per process vs daemons", "daemons", p.n, "raw zenoh process")),
            Row(f"cpu_{p.n}", f"{p.n} daemons: idle CPU per daemon", summarize(p.mesh_cpu, 1.0), unit="%",
                extra=curve("idle_cpu", "idle CPU per process vs daemons", "daemons", p.n, "cmion daemon")),
        ]
        block[1].failures.extend(p.problems)
        compare(block, {f"convergence_{p.n}": f"convergence_raw_{p.n}", f"rss_{p.n}": f"rss_raw_{p.n}",
                        f"cpu_{p.n}": f"cpu_raw_{p.n}"}, None)
        rows += block
    return rows


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    rows: list[Row] = []
    for group, fn in (("fanout", fanout_rows), ("wildcard", wildcard_rows), ("convergence", convergence_rows)):
        if group in groups:
            started = time.monotonic()
            rows += fn(options)
            log(f"{group} measured in {time.monotonic() - started:.1f} s")
    return rows
