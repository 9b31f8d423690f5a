"""Competencies for the benchmark embodiment (``bench/embodiment/library.xml``).

A daemon imports them as ``bench.competencies:Instant``: the benchmarks start daemons with the
repository on ``PYTHONPATH``.
"""

from __future__ import annotations

from typing import Any

from cmion_mesh.competency import Competency, RunContext


class Instant(Competency):
    """Succeeds at once: a plan of these times the manager, the execution system and the loop."""

    type = "Instant"

    def __init__(self, name: str = "instant") -> None:
        super().__init__(name, name=name)

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        return True
