"""The benchmark registry and the types every benchmark shares.

A benchmark is a function ``run(options, groups) -> list[Row]`` in some module under ``bench/``;
it is registered below by name with the metric groups it can measure (``--only`` selects
benchmarks by name or by group). To add one (competency actions, discovery, migration...):
write ``bench/<name>.py`` with a ``run`` function and append a ``Benchmark`` to ``BENCHMARKS``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

from bench.stats import Summary


@dataclass(frozen=True, slots=True)
class Options:
    """What the command line asked for; every benchmark reads the same options."""

    quick: bool = False
    samples: int = 2000  # measured samples per metric (pooled over the rounds)
    warmup: int = 200  # unrecorded iterations per metric before the first round
    rounds: int = 4  # raw and cmion measurements alternate this many times
    rewarm: int = 20  # unrecorded iterations at the start of every chunk of a round


@dataclass(slots=True)
class Row:
    """One measured metric: ``median``/``p99`` in milliseconds; ``ratio`` = median / baseline's median."""

    metric: str  # stable id, used in JSON and as a baseline reference
    label: str  # what the table shows
    summary: Summary
    baseline: str | None = None  # id of the raw-zenoh row this one is compared with
    ratio: float | None = None
    target: float | None = None  # the ratio the issue asks for (at most)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def meets(self) -> bool | None:
        if self.ratio is None or self.target is None:
            return None
        return self.ratio <= self.target

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "metric": self.metric,
            "label": self.label,
            **asdict(self.summary),
            "baseline": self.baseline,
            "ratio_vs_raw": self.ratio,
            "target_ratio": self.target,
            "meets_target": self.meets,
        }
        out.update(self.extra)
        return out


def compare(rows: Iterable[Row], pairs: dict[str, str], target: float) -> None:
    """Fill ``ratio`` of each row whose id is a key of ``pairs`` against the row named by its value."""
    by_id = {row.metric: row for row in rows}
    for metric, baseline in pairs.items():
        row, base = by_id.get(metric), by_id.get(baseline)
        if row is None or base is None or base.summary.median_ms <= 0:
            continue
        row.baseline = baseline
        row.ratio = row.summary.median_ms / base.summary.median_ms
        row.target = target


RunFn = Callable[[Options, frozenset[str]], list[Row]]


@dataclass(frozen=True, slots=True)
class Benchmark:
    name: str
    entry: str  # "module:function", imported only when the benchmark runs
    groups: tuple[str, ...]
    description: str
    default: bool = True  # run without --only (diagnostics run only when named)

    def load(self) -> RunFn:
        module_name, _, func = self.entry.partition(":")
        fn: RunFn = getattr(importlib.import_module(module_name), func)
        return fn


BENCHMARKS: list[Benchmark] = [
    Benchmark(
        "core",
        "bench.core:run",
        ("events", "get", "set"),
        "event delivery, property get and set round trips vs raw zenoh pub/sub and get",
    ),
    Benchmark(
        "breakdown",
        "bench.breakdown:run",
        (),
        "diagnostic: per-hop timestamps of an event echo and a set request vs raw zenoh",
        default=False,
    ),
]


def select(only: Iterable[str] | None) -> list[tuple[Benchmark, frozenset[str]]]:
    """The benchmarks to run with the groups of each; ``only`` holds benchmark or group names."""
    chosen = None if only is None else {name.strip() for name in only if name.strip()}
    known = {b.name for b in BENCHMARKS} | {g for b in BENCHMARKS for g in b.groups}
    if chosen is not None and chosen - known:
        raise ValueError(f"unknown benchmark or group: {', '.join(sorted(chosen - known))} (known: {', '.join(sorted(known))})")
    out: list[tuple[Benchmark, frozenset[str]]] = []
    for bench in BENCHMARKS:
        if (chosen is None and bench.default) or (chosen is not None and bench.name in chosen):
            out.append((bench, frozenset(bench.groups)))
        elif chosen is not None and chosen & set(bench.groups):
            out.append((bench, frozenset(chosen & set(bench.groups))))
    return out
