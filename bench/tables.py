"""The targets as a markdown table: each target's row of a run, raw zenoh beside it, met or missed.

``python -m bench report RUN.json [RUN.json ...]`` prints it; ``--readme`` also writes it into
``bench/README.md`` between the ``targets`` markers, so that the README keeps the latest table.
Given several runs, a later run's row replaces an earlier one's (one run per benchmark is enough).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from bench.registry import Row
from bench.targets import TARGETS, Target, verdicts

BEGIN = "<!-- targets:begin (written by `python -m bench report RUN.json --readme`) -->"
END = "<!-- targets:end -->"
README = Path(__file__).resolve().parent / "README.md"


def rows_of(doc: dict[str, Any]) -> list[Row]:
    """The rows of a run's JSON: a whole run (``--json``: ``benchmarks``) or one benchmark's file.
    Each row's ``extra["benchmark"]`` names its benchmark: raw rows share ids across benchmarks
    (``raw_get`` in core, actions...), and a row's baseline is the one of its own benchmark."""
    benches = doc["benchmarks"].items() if "benchmarks" in doc else [(doc.get("benchmark", ""), doc)]
    rows = []
    for name, bench in benches:
        for r in bench.get("rows", ()):
            row = Row.from_json(r)
            row.extra["benchmark"] = name
            rows.append(row)
    return rows


def load(paths: Iterable[Path]) -> tuple[list[Row], list[dict[str, Any]]]:
    """Rows of every run (later runs last) and each run's header (command, date, machine)."""
    rows: list[Row] = []
    runs: list[dict[str, Any]] = []
    for path in paths:
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: not a benchmark run's JSON: {exc}") from None
        if not isinstance(doc, dict) or not ("benchmarks" in doc or "rows" in doc):
            raise ValueError(f"{path}: not a benchmark run's JSON (no 'benchmarks' or 'rows')")
        rows += rows_of(doc)
        runs.append({k: doc.get(k) for k in ("command", "created", "machine")})
    return rows, runs


def _number(value: float, unit: str) -> str:
    if unit == "events/s":
        return f"{value / 1000:.0f} k"
    if unit == "%":
        return f"{value:.2f}"
    return f"{value:.3g}" if abs(value) < 100 else f"{value:.0f}"


def _cell(row: Row | None) -> str:
    if row is None:
        return "-"
    s = row.summary
    return f"{_number(s.median_ms, row.unit)} {row.unit} (p99 {_number(s.p99_ms, row.unit)})"


def markdown(rows: Sequence[Row], targets: Sequence[Target] = TARGETS) -> str:
    """One line per target: what raw zenoh and cmion measured (median, p99), the ratio, the target, met?"""
    by_metric = {(row.extra.get("benchmark"), row.metric): row for row in rows}
    lines = ["| metric | raw zenoh | cmion | ratio | target | |", "|---|---|---|---|---|---|"]
    for verdict in verdicts(rows, targets):
        target, row = verdict.target, verdict.row
        base = by_metric.get((row.extra.get("benchmark"), row.baseline)) if row is not None and row.baseline else None
        ratio = f"{row.ratio:.2f}x" if row is not None and row.ratio is not None else "-"
        state = {"met": "met", "missed": "**missed**", "not measured": "not measured", "no ratio": "**no ratio**",
                 "wrong unit": f"**in {row.unit if row else '?'}, not {target.unit}**"}[verdict.state]
        lines.append(f"| {target.label} (`{target.metric}`) | {_cell(base)} | {_cell(row)} | {ratio} | "
                     f"{target.describe()} ({target.source}) | {state} |")
    return "\n".join(lines)


def header(runs: Sequence[dict[str, Any]]) -> str:
    """Which runs the table comes from: each one's command (without where its JSON went), date, machine."""
    parts = []
    for run in runs:
        machine = run.get("machine") or {}
        command = re.sub(r" --json \S+", "", str(run.get("command")))
        parts.append(f"`{command}` ({run.get('created')}; {machine.get('cpus')} CPUs, Python {machine.get('python')}, "
                     f"zenoh {machine.get('zenoh')})")
    return "From " + "; ".join(parts) + "." if parts else ""


def write_readme(text: str, readme: Path = README) -> None:
    """Replace what is between the markers in ``readme`` by ``text`` (the markers must be there)."""
    current = readme.read_text()
    start, end = current.find(BEGIN), current.find(END)
    if start < 0 or end < start:
        raise ValueError(f"{readme}: no {BEGIN!r} ... {END!r} markers to write the table between")
    readme.write_text(current[: start + len(BEGIN)] + "\n" + text.rstrip("\n") + "\n" + current[end:])
