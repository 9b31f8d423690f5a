"""Competencies that tests host in separate processes (importable as ``tests.remote_helpers``)."""

from __future__ import annotations

from typing import Any

from cmion_mesh.competency import Competency, RunContext


class Arm(Competency):
    """Waves for ``steps`` steps of 50 ms, reporting progress; writes the blackboard over the mesh."""

    type = "Arm"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        steps = int(parameters.get("steps", 1))
        for i in range(steps):
            if not ctx.wait(0.05):
                return False
            ctx.progress({"step": i + 1, "of": steps})
        if parameters.get("fail") == "yes":
            return ctx.fail("arm jammed")
        ctx.bb_set("waved", {"speed": parameters.get("speed"), "steps": steps, "by": self.name})
        return True
