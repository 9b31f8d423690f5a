"""The benchmark registry and the types every benchmark shares.

A benchmark is a function ``run(options, groups) -> list[Row]`` in some module under ``bench/``;
it is registered below by name with the metric groups it can measure (``--only`` selects
benchmarks by name or by group). To add one: write ``bench/<name>.py`` with a ``run`` function
and append a ``Benchmark`` to ``BENCHMARKS``.

A row is usually a latency in milliseconds compared with a raw-zenoh row (``ratio``); it may
instead hold another quantity (``unit``: "%", "MiB", "events/s", "s"...), carry ``failures`` (a
correctness check that did not hold: lost events, a lost companion...; any failure makes
``python -m bench`` exit 1) and belong to a growth curve (``extra["curve"]``, ``extra["x"]``,
``extra["series"]``), which is printed as its own table and drawn by ``--png``. Its target (a
bound on the ratio, ``at_least`` for rates where higher is better, and/or a ``limit`` on the
median) comes from ``bench.targets.TARGETS``, the one table of every target.
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
    full: bool = False  # also the slow parts (32 daemons)
    soak_seconds: float = 20.0  # length of the soak's traffic phase


@dataclass(slots=True)
class Row:
    """One measured metric: ``median``/``p99`` in ``unit``; ``ratio`` = median / baseline's median."""

    metric: str  # stable id, used in JSON and as a baseline reference
    label: str  # what the table shows
    summary: Summary
    baseline: str | None = None  # id of the raw-zenoh row this one is compared with
    ratio: float | None = None
    target: float | None = None  # the ratio the issue asks for (at most)
    extra: dict[str, Any] = field(default_factory=dict)
    unit: str = "ms"
    limit: float | None = None  # the median the issue asks for (at most), in ``unit``
    failures: list[str] = field(default_factory=list)  # correctness checks that did not hold
    at_least: bool = False  # ``target`` is a floor on the ratio (rates: higher is better), not a ceiling
    strict: bool = False  # the median must be below ``limit``, not at it

    def ratio_ok(self) -> bool | None:
        """Whether the ratio is on the right side of ``target`` (None: no ratio or no target)."""
        if self.ratio is None or self.target is None:
            return None
        return self.ratio >= self.target if self.at_least else self.ratio <= self.target

    def limit_ok(self) -> bool | None:
        """Whether the median is within ``limit`` (None: no limit)."""
        if self.limit is None:
            return None
        median = self.summary.median_ms
        return median < self.limit if self.strict else median <= self.limit

    @property
    def meets(self) -> bool | None:
        """Whether the row meets its target ratio and/or absolute limit (None: it has neither, or the
        ratio its target bounds could not be computed)."""
        checks = [ok for ok in (self.ratio_ok(), self.limit_ok()) if ok is not None]
        return all(checks) if checks else None

    def bounds(self) -> str:
        """The target in words: ``< 20 ms``, ``<= 1.3x``, ``>= 0.5x`` (``-`` when there is none)."""
        parts = []
        if self.limit is not None:
            parts.append(f"{'<' if self.strict else '<='} {self.limit:g} {self.unit}")
        if self.target is not None:
            parts.append(f"{'>=' if self.at_least else '<='} {self.target:g}x")
        return ", ".join(parts) or "-"

    def verdict(self) -> str:
        """The table's target column: the failures, else each target with met/MISSED."""
        if self.failures:
            return "FAILED: " + "; ".join(self.failures)
        parts = []
        if self.limit is not None:
            parts.append(f"{'<' if self.strict else '<='} {self.limit:g} {self.unit} " + ("met" if self.limit_ok() else "MISSED"))
        if self.target is not None:
            ok = self.ratio_ok()
            state = "no ratio" if ok is None else ("met" if ok else "MISSED")
            parts.append(f"{'>=' if self.at_least else '<='} {self.target:g}x {state}")
        return ", ".join(parts) or "-"

    def to_json(self) -> dict[str, Any]:
        summary = asdict(self.summary)
        if self.unit != "ms":
            summary = {k.removesuffix("_ms"): v for k, v in summary.items()}
        out: dict[str, Any] = {
            "metric": self.metric,
            "label": self.label,
            "unit": self.unit,
            **summary,
            "baseline": self.baseline,
            "ratio_vs_raw": self.ratio,
            "target_ratio": self.target,
            "limit": self.limit,
            "meets_target": self.meets,
            "failures": list(self.failures),
        }
        if self.at_least:
            out["target_at_least"] = True
        if self.strict:
            out["limit_strict"] = True
        out.update(self.extra)
        return out

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> Row:
        """The row ``to_json`` wrote (what ``python -m bench report`` reads back from a run's JSON)."""
        unit = str(doc.get("unit", "ms"))
        # to_json names the summary's fields as Summary does for ms rows, without "_ms" otherwise
        names = {name: name if unit == "ms" or name == "n" else name.removesuffix("_ms") for name in Summary.__dataclass_fields__}
        summary = Summary(**{name: (int if name == "n" else float)(doc[key]) for name, key in names.items()})
        known = {"metric", "label", "unit", "baseline", "ratio_vs_raw", "target_ratio", "limit", "meets_target", "failures",
                 "target_at_least", "limit_strict", *names.values()}
        return cls(str(doc["metric"]), str(doc.get("label", doc["metric"])), summary, baseline=doc.get("baseline"),
                   ratio=doc.get("ratio_vs_raw"), target=doc.get("target_ratio"), unit=unit, limit=doc.get("limit"),
                   failures=list(doc.get("failures") or ()), at_least=bool(doc.get("target_at_least")),
                   strict=bool(doc.get("limit_strict")), extra={k: v for k, v in doc.items() if k not in known})


def compare(rows: Iterable[Row], pairs: dict[str, str], target: float | None) -> None:
    """Fill ``ratio`` of each row whose id is a key of ``pairs`` against the row named by its value
    (``target`` None: the ratio is given for context, with no target)."""
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
        "actions",
        "bench.actions:run",
        ("actions",),
        "mind action -> succeeded, one-step and four-step plans, in the daemon and from another process",
    ),
    Benchmark(
        "mindproto",
        "bench.mindproto:run",
        ("mindproto",),
        "FAtiMA line protocol: action line -> ACTION-FINISHED (one-step plan) vs a raw TCP echo, beside CMION's ~200 ms",
    ),
    Benchmark(
        "discovery",
        "bench.discovery:run",
        ("discovery",),
        "spawning `cmion-mesh up` -> its liveliness token seen by a watcher, vs a raw zenoh process",
    ),
    Benchmark(
        "oneshot",
        "bench.oneshot:run",
        ("oneshot",),
        "one-shot `cmion-mesh peers` / `bb get` wall time, process start to exit, vs `python -c \"import zenoh\"`",
    ),
    Benchmark(
        "idle",
        "bench.idle:run",
        ("idle",),
        "CPU, memory and threads of an idle `cmion-mesh up robot` daemon vs an idle raw zenoh peer",
    ),
    Benchmark(
        "migration",
        "bench.migration:run",
        ("migration",),
        "migration command -> companion awake at the target, 10 KiB / 1 MiB / 10 MiB, vs raw transfer + fsync",
    ),
    Benchmark(
        "ros2",
        "bench.ros2:run",
        ("ros2",),
        "a ROS 2 robot as a body: mind action -> Nav2 goal at the ROS 2 node, goal result -> action succeeded",
    ),
    Benchmark(
        "ros2_rclpy",
        "bench.ros2_rclpy:run",
        ("ros2_rclpy",),
        "a DDS robot as a body: Drive -> first Twist at a real rclpy node, goal -> accepted by a real rclpy action server, "
        "beside rmw_zenoh",
    ),
    Benchmark(
        "flood",
        "bench.flood:run",
        ("flood",),
        "a legitimate action's latency during a flood of 20,000 action requests, vs a raw zenoh get in the same moment",
    ),
    Benchmark(
        "record",
        "bench.record:run",
        ("record",),
        "event throughput with and without `cmion-mesh record` attached, the recorder's own pace, nothing lost",
    ),
    Benchmark(
        "webbody",
        "bench.webbody:run",
        ("web",),
        "migration -> the companion's face shown on the target's page (headless Chromium); an open idle page's daemon CPU",
    ),
    Benchmark(
        "growth",
        "bench.growth:run",
        ("fanout", "wildcard", "convergence"),
        "growth curves: event throughput vs subscribers, wildcard get vs blackboard size, discovery vs daemons",
    ),
    Benchmark(
        "mcp",
        "bench.mcp:run",
        ("mcp",),
        "MCP tools/call -> outcome over stdio (the SDK's client spawning `cmion-mesh mcp`), beside MeshClient.act",
        default=False,  # needs the optional `mcp` extra
    ),
    Benchmark(
        "view",
        "bench.view:run",
        ("view",),
        "event at a daemon -> drawn in the `cmion-mesh view` page (headless Chromium), and an idle page's CPU cost to the daemon",
        default=False,
    ),
    Benchmark(
        "llm",
        "bench.llm:run",
        ("llm",),
        "a language-model mind's tool call (stand-in endpoint answering at once) -> the result back at the model, "
        "beside MeshClient.act",
        default=False,
    ),
    Benchmark(
        "soak",
        "bench.soak:run",
        (),
        "three daemons, a migrating companion, actions and writes; nothing lost, nothing growing",
        default=False,
    ),
    Benchmark(
        "migtrace",
        "bench.migtrace:run",
        (),
        "diagnostic: where a migration's time goes (timed calls inside both daemons)",
        default=False,
    ),
    Benchmark(
        "breakdown",
        "bench.breakdown:run",
        (),
        "diagnostic: per-hop timestamps of an event echo and a set request vs raw zenoh",
        default=False,
    ),
    Benchmark(
        "eventcpu",
        "bench.eventcpu:run",
        (),
        "diagnostic: CPU per event on each thread (publisher loop, subscriber worker and loop) vs raw zenoh",
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
