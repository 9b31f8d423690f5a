"""``python -m bench``: run the registered benchmarks, print a table, write JSON.

    python -m bench [--quick] [--only events,get,set] [--samples N] [--json PATH] [--check]
    python -m bench --only breakdown             # diagnostic: per-hop timestamps
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import shlex
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, replace
from importlib import metadata
from pathlib import Path
from typing import Any

from bench.registry import BENCHMARKS, Options, Row, select

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> dict[str, Any]:
    try:
        zenoh_version = metadata.version("eclipse-zenoh")
    except metadata.PackageNotFoundError:
        zenoh_version = "unknown"
    return {
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "zenoh": zenoh_version,
    }


def _fmt(value: float | None, spec: str, suffix: str = "") -> str:
    return "-" if value is None else f"{value:{spec}}{suffix}"


def table(rows: Sequence[Row]) -> str:
    labels = {row.metric: row.label for row in rows}
    header = ("metric", "n", "median (ms)", "p99 (ms)", "ratio vs raw", "vs", "target")
    body = []
    for row in rows:
        meets = row.meets
        verdict = "-" if meets is None else (f"<= {row.target:g}x " + ("met" if meets else "MISSED"))
        body.append((
            row.label,
            str(row.summary.n),
            f"{row.summary.median_ms:.3f}",
            f"{row.summary.p99_ms:.3f}",
            _fmt(row.ratio, ".2f", "x"),
            "-" if row.baseline is None else labels.get(row.baseline, row.baseline).split(",")[0],
            verdict,
        ))
    widths = [max(len(r[i]) for r in (header, *body)) for i in range(len(header))]
    right = {1, 2, 3, 4}

    def line(cells: Sequence[str]) -> str:
        return "  ".join(c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths, strict=True)))

    rule = "  ".join("-" * w for w in widths)
    return "\n".join(text.rstrip() for text in [line(header), rule, *(line(r) for r in body)])


def main(argv: Sequence[str] | None = None) -> int:
    names = ", ".join(f"{b.name} ({', '.join(b.groups)})" for b in BENCHMARKS)
    parser = argparse.ArgumentParser(
        prog="python -m bench", description=f"cmion_mesh benchmarks vs raw zenoh. Registered: {names}."
    )
    parser.add_argument("--quick", action="store_true", help="fewer samples (300) and a shorter warm-up (100)")
    parser.add_argument("--only", metavar="LIST", help="comma-separated benchmarks or groups, e.g. events,get,set")
    parser.add_argument("--samples", type=int, metavar="N", help="measured samples per metric (default 2000, --quick 300)")
    parser.add_argument("--warmup", type=int, metavar="N", help="unrecorded iterations per metric first (default 200, quick 100)")
    parser.add_argument("--rounds", type=int, default=4, metavar="N", help="raw/cmion alternations (default %(default)s)")
    parser.add_argument("--json", metavar="PATH", help="write the whole run here (default bench/results/<benchmark>.json)")
    parser.add_argument("--check", action="store_true", help="exit 1 if a cmion metric misses its target ratio")
    args = parser.parse_args(argv)

    samples = args.samples if args.samples is not None else (300 if args.quick else 2000)
    warmup = args.warmup if args.warmup is not None else (100 if args.quick else 200)
    if samples < 1 or warmup < 0 or args.rounds < 1:
        parser.error("--samples and --rounds must be at least 1, --warmup at least 0")
    options = replace(Options(), quick=args.quick, samples=samples, warmup=warmup, rounds=args.rounds)
    try:
        chosen = select(args.only.split(",") if args.only else None)
    except ValueError as exc:
        parser.error(str(exc))

    command = "python -m bench" + ("" if not sys.argv[1:] else " " + shlex.join(sys.argv[1:] if argv is None else argv))
    host = machine()
    meta: dict[str, Any] = {"command": command, "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                            "machine": host, "options": asdict(options)}
    print(f"{command}: {samples} samples per metric in {options.rounds} interleaved rounds after {warmup} warm-up "
          f"iterations; {host['cpus']} CPUs, zenoh {host['zenoh']}", flush=True)
    everything: dict[str, Any] = {**meta, "benchmarks": {}}
    failed = False
    for bench, groups in chosen:
        print(f"\n== {bench.name}: {bench.description} [{', '.join(sorted(groups))}]", flush=True)
        started = time.monotonic()
        rows = bench.load()(options, groups)
        elapsed = time.monotonic() - started
        print(table(rows), flush=True)
        for row in rows:
            if row.meets is False:
                failed = True
        doc = {**meta, "benchmark": bench.name, "groups": sorted(groups), "seconds": round(elapsed, 1),
               "rows": [row.to_json() for row in rows]}
        everything["benchmarks"][bench.name] = doc
        if not args.json:
            RESULTS.mkdir(parents=True, exist_ok=True)
            path = RESULTS / f"{bench.name}.json"
            path.write_text(json.dumps(doc, indent=2) + "\n")
            print(f"({elapsed:.1f} s; written to {os.path.relpath(path)})")
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(everything, indent=2) + "\n")
        print(f"\nwritten to {path}")
    return 1 if args.check and failed else 0


if __name__ == "__main__":
    sys.exit(main())
