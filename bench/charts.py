"""``--png PATH``: the growth curves as charts (matplotlib, optional: ``pip install -e '.[bench]'``)."""

from __future__ import annotations

import importlib
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench.registry import Row


def curves(rows: Sequence[Row]) -> dict[str, list[Row]]:
    out: dict[str, list[Row]] = {}
    for row in rows:
        if "curve" in row.extra:
            out.setdefault(str(row.extra["curve"]), []).append(row)
    return out


def draw(rows: Sequence[Row], path: Path) -> str:
    """Draw every curve among ``rows`` into one PNG; returns a line saying what was done."""
    found = curves(rows)
    if not found:
        return "--png: no growth curve in this run (run growth or migration), no chart drawn"
    try:
        matplotlib = importlib.import_module("matplotlib")
        matplotlib.use("Agg")
        plt = importlib.import_module("matplotlib.pyplot")
    except ImportError:
        return "--png: matplotlib is not installed (pip install -e '.[bench]'); charts skipped"
    cols = min(2, len(found))
    lines = math.ceil(len(found) / cols)
    fig, axes = plt.subplots(lines, cols, figsize=(6.4 * cols, 4.4 * lines), squeeze=False)
    for ax, (_, members) in zip(axes.flat, found.items(), strict=False):
        plot(ax, members)
    for ax in list(axes.flat)[len(found):]:
        ax.set_visible(False)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return f"charts of {len(found)} curve(s) written to {path}"


def plot(ax: Any, members: Sequence[Row]) -> None:
    first = members[0].extra
    series: dict[str, list[Row]] = {}
    for row in members:
        series.setdefault(str(row.extra.get("series", "")), []).append(row)
    for name, points in series.items():
        points = sorted(points, key=lambda r: float(r.extra["x"]))
        xs = [float(r.extra["x"]) for r in points]
        med = [r.summary.median_ms for r in points]
        p99 = [r.summary.p99_ms for r in points]
        (line,) = ax.plot(xs, med, marker="o", label=f"{name} (median)")
        if any(p != m for p, m in zip(p99, med, strict=True)):
            ax.plot(xs, p99, linestyle="--", alpha=0.6, color=line.get_color(), label=f"{name} (p99)")
    xs_all = [float(r.extra["x"]) for r in members]
    if min(xs_all) > 0 and max(xs_all) / min(xs_all) >= 50:
        ax.set_xscale("log")
    values = [r.summary.median_ms for r in members]
    if min(values) > 0 and max(values) / min(values) >= 50:
        ax.set_yscale("log")
    ax.set_title(str(first.get("curve_title", first["curve"])))
    ax.set_xlabel(str(first.get("x_label", "x")))
    ax.set_ylabel(members[0].unit)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
