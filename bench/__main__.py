"""``python -m bench``: run the registered benchmarks, print a table, write JSON.

    python -m bench [--quick] [--full] [--only events,get,set] [--samples N] [--json PATH] [--check] [--png PATH]
    python -m bench --only breakdown             # diagnostic: per-hop timestamps
    python -m bench soak [--seconds N]           # the soak (not part of the default set)
    python -m bench sim [--schedules N]          # handshake simulation testing (cmion_mesh/testing/simulation.py)
    python -m bench report [RUN.json ...] [--readme] [--check]   # the targets table of earlier runs

Exit status: 1 if a correctness check failed (a row's ``failures``: lost events or writes, a lost
or duplicated companion, growth during the soak...), or with ``--check`` if a target of
``bench.targets`` is missed (each one is named); else 0. A target whose metric the run did not
measure is "not measured", never a miss.
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

from bench import targets
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


def value(number: float, unit: str) -> str:
    """A median or p99 as the table shows it: the precision its unit and size call for."""
    if unit in ("events/s", "threads") or abs(number) >= 10_000:
        return f"{number:.0f}"
    if unit == "MiB" or abs(number) >= 1000:
        return f"{number:.1f}"
    if unit == "%":
        return f"{number:.2f}"
    return f"{number:.3f}"


def grid(header: Sequence[str], body: Sequence[Sequence[str]], right: set[int]) -> str:
    widths = [max(len(r[i]) for r in (header, *body)) for i in range(len(header))]

    def line(cells: Sequence[str]) -> str:
        return "  ".join(c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths, strict=True)))

    rule = "  ".join("-" * w for w in widths)
    return "\n".join(text.rstrip() for text in [line(header), rule, *(line(r) for r in body)])


def table(rows: Sequence[Row]) -> str:
    labels = {row.metric: row.label for row in rows}
    header = ("metric", "n", "median", "p99", "unit", "ratio vs raw", "vs", "target")
    body = []
    for row in rows:
        body.append((
            row.label,
            str(row.summary.n),
            value(row.summary.median_ms, row.unit),
            value(row.summary.p99_ms, row.unit),
            row.unit,
            _fmt(row.ratio, ".2f", "x"),
            "-" if row.baseline is None else labels.get(row.baseline, row.baseline).split(",")[0],
            row.verdict(),
        ))
    return grid(header, body, {1, 2, 3, 5})


def curve_tables(rows: Sequence[Row]) -> list[str]:
    """One table per growth curve among ``rows``: x down, one column of medians per series."""
    curves: dict[str, list[Row]] = {}
    for row in rows:
        if "curve" in row.extra:
            curves.setdefault(str(row.extra["curve"]), []).append(row)
    out = []
    for members in curves.values():
        first = members[0].extra
        series = list(dict.fromkeys(str(r.extra.get("series", "")) for r in members))
        xs = list(dict.fromkeys(r.extra["x"] for r in members))
        cell = {(r.extra["x"], str(r.extra.get("series", ""))): r for r in members}
        header = [str(first.get("x_label", "x")), *series]
        if len(series) == 2:
            header.append(f"{series[1]} / {series[0]}")
        body = []
        for x in xs:
            cells = [str(x)]
            for name in series:
                found = cell.get((x, name))
                cells.append("-" if found is None else value(found.summary.median_ms, found.unit))
            if len(series) == 2:
                a, b = cell.get((x, series[0])), cell.get((x, series[1]))
                ok = a is not None and b is not None and a.summary.median_ms > 0
                cells.append(f"{b.summary.median_ms / a.summary.median_ms:.2f}x" if ok and b is not None and a is not None else "-")
            body.append(cells)
        title = f"{first.get('curve_title', first['curve'])} ({members[0].unit}, median)"
        out.append(title + "\n" + grid(header, body, set(range(1, len(header)))))
    return out


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
    parser.add_argument("--check", action="store_true", help="exit 1 if a measured metric misses its target (bench/targets.py)")
    parser.add_argument("--full", action="store_true", help="also the slow parts (the 32-daemon point of the discovery curve)")
    parser.add_argument("--soak-seconds", type=float, default=20.0, metavar="N",
                        help="traffic phase of the soak (with --only soak; default %(default)s)")
    parser.add_argument("--png", metavar="PATH", help="draw the growth curves into PATH (needs matplotlib)")
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["sim"]:
        from cmion_mesh.testing import simulation  # only this command needs it

        return simulation.main(argv[1:])
    if argv[:1] == ["report"]:
        return report(argv[1:])
    if argv[:1] == ["soak"]:
        soak = argparse.ArgumentParser(prog="python -m bench soak", description="the soak: see bench/soak.py")
        soak.add_argument("--seconds", type=float, default=20.0, help="traffic phase, seconds (default %(default)s)")
        soak.add_argument("--json", metavar="PATH")
        known = soak.parse_args(argv[1:])
        argv = ["--only", "soak", "--soak-seconds", str(known.seconds), *(["--json", known.json] if known.json else [])]
    args = parser.parse_args(argv)
    if not 0 < args.soak_seconds <= 3600:
        parser.error("--soak-seconds must be in (0, 3600]")

    samples = args.samples if args.samples is not None else (300 if args.quick else 2000)
    warmup = args.warmup if args.warmup is not None else (100 if args.quick else 200)
    if samples < 1 or warmup < 0 or args.rounds < 1:
        parser.error("--samples and --rounds must be at least 1, --warmup at least 0")
    options = replace(Options(), quick=args.quick, samples=samples, warmup=warmup, rounds=args.rounds, full=args.full,
                      soak_seconds=args.soak_seconds)
    try:
        chosen = select(args.only.split(",") if args.only else None)
    except ValueError as exc:
        parser.error(str(exc))

    command = "python -m bench" + ("" if not argv else " " + shlex.join(argv))
    host = machine()
    meta: dict[str, Any] = {"command": command, "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                            "machine": host, "options": asdict(options)}
    print(f"{command}: {samples} samples per metric in {options.rounds} interleaved rounds after {warmup} warm-up "
          f"iterations; {host['cpus']} CPUs, zenoh {host['zenoh']}", flush=True)
    everything: dict[str, Any] = {**meta, "benchmarks": {}}
    broken: list[str] = []
    all_rows: list[Row] = []
    run_started = time.monotonic()
    for bench, groups in chosen:
        print(f"\n== {bench.name}: {bench.description} [{', '.join(sorted(groups))}]", flush=True)
        started = time.monotonic()
        rows = bench.load()(options, groups)
        elapsed = time.monotonic() - started
        targets.apply(rows)
        print(table(rows), flush=True)
        for text in curve_tables(rows):
            print("\n" + text, flush=True)
        all_rows.extend(rows)
        for row in rows:
            if row.failures:
                broken.append(f"{bench.name}: {row.label}: {'; '.join(row.failures)}")
        doc = {**meta, "benchmark": bench.name, "groups": sorted(groups), "seconds": round(elapsed, 1),
               "rows": [row.to_json() for row in rows]}
        everything["benchmarks"][bench.name] = doc
        if not args.json:
            RESULTS.mkdir(parents=True, exist_ok=True)
            path = RESULTS / f"{bench.name}.json"
            path.write_text(json.dumps(doc, indent=2) + "\n")
            print(f"({elapsed:.1f} s; written to {os.path.relpath(path)})")
    everything["seconds"] = round(time.monotonic() - run_started, 1)
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(everything, indent=2) + "\n")
        print(f"\nwritten to {path}")
    if args.png:
        from bench.charts import draw

        print(draw(all_rows, Path(args.png)))
    print(f"\ntotal {everything['seconds']:.1f} s")
    missed = print_check(all_rows) if args.check else []
    if broken:
        print("\nFAILED checks:\n  " + "\n  ".join(broken), flush=True)
        return 1
    return 1 if missed else 0


def print_check(rows: Sequence[Row]) -> list[targets.Verdict]:
    """Print each measured target, met or missed (and how many were not measured); the missed ones."""
    verdicts = targets.verdicts(rows)
    measured = [v for v in verdicts if v.state != "not measured"]
    missed = targets.missed(rows)
    print(f"\ntargets: {len(measured) - len(missed)} met, {len(missed)} missed, {len(verdicts) - len(measured)} not measured "
          "in this run (bench/targets.py)")
    for verdict in measured:
        print(("  MISSED " if verdict in missed else "  met    ") + verdict.line())
    return missed


def report(argv: Sequence[str]) -> int:
    """``python -m bench report``: the targets table of earlier runs, in markdown."""
    from bench import tables

    parser = argparse.ArgumentParser(prog="python -m bench report",
                                     description="the targets table (markdown) of earlier runs' JSON; a later run's row wins")
    parser.add_argument("runs", nargs="*", metavar="RUN.json",
                        help="runs written by --json or bench/results/*.json (default: bench/results/*.json, oldest first)")
    parser.add_argument("--readme", action="store_true", help="also write the table into bench/README.md")
    parser.add_argument("--check", action="store_true", help="exit 1 if a measured target is missed")
    args = parser.parse_args(argv)
    paths = [Path(p) for p in args.runs] or sorted(RESULTS.glob("*.json"), key=lambda p: p.stat().st_mtime)
    if not paths:
        parser.error(f"no runs given and none in {os.path.relpath(RESULTS)}")
    try:
        rows, runs = tables.load(paths)
    except ValueError as exc:
        parser.error(str(exc))
    text = tables.header(runs) + "\n\n" + tables.markdown(rows)
    print(text)
    if args.readme:
        tables.write_readme(text)
        print(f"\nwritten into {os.path.relpath(tables.README)}")
    missed = print_check(rows) if args.check else []
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
