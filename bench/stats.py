"""Summaries of samples: latencies in seconds come out in milliseconds; other quantities
(CPU %, MiB, events/s, seconds) are summarized as they are with ``scale=1``."""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass


def percentile(ordered: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (0..100) of sorted samples, linearly interpolated (numpy's default)."""
    if not ordered:
        raise ValueError("no samples")
    pos = (len(ordered) - 1) * q / 100.0
    lo, hi = math.floor(pos), math.ceil(pos)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (pos - lo)


@dataclass(frozen=True, slots=True)
class Summary:
    """Field names say ``_ms`` because most rows are latencies; a row's ``unit`` says what they hold."""

    n: int
    median_ms: float
    p99_ms: float
    p90_ms: float
    mean_ms: float
    min_ms: float
    max_ms: float


def summarize(samples: Sequence[float], scale: float = 1000.0) -> Summary:
    """Sorted-sample statistics of ``samples`` multiplied by ``scale`` (default: seconds to ms)."""
    ordered = sorted(samples)
    ms = scale
    return Summary(
        n=len(ordered),
        median_ms=percentile(ordered, 50) * ms,
        p99_ms=percentile(ordered, 99) * ms,
        p90_ms=percentile(ordered, 90) * ms,
        mean_ms=statistics.fmean(ordered) * ms,
        min_ms=ordered[0] * ms,
        max_ms=ordered[-1] * ms,
    )
