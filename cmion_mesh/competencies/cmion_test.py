"""Python equivalents of CMION's test competencies (``cmion.level2.competencies.test``).

Driven by CMION's ``CompManagerRulesTest.xml`` unchanged: ``TestAction test`` fails by rule 1
(type 1 always fails), then succeeds by rule 3 (type 2 writes a random number to the blackboard
under the given name, type 3 reads it and adds agent ``TestUser`` with ``test = true`` to the
world model); ``TestAction2`` succeeds through the same-type fallback (type 4: competency 4 fails,
competency 5 succeeds); competency 6 runs in the background.
"""

from __future__ import annotations

import random
from typing import Any

from cmion_mesh import keys
from cmion_mesh.competency import Competency, RunContext
from cmion_mesh.errors import RequestRejected
from cmion_mesh.messages import AddContainer, SetProperty


class TestCompetency1(Competency):
    type = "TestType1"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        return ctx.fail("TestType1 always fails")


class TestCompetency2(Competency):
    type = "TestType2"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        ctx.bb_set(str(parameters["RandomOutName"]), random.random())
        return True


class TestCompetency3(Competency):
    type = "TestType3"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        name = str(parameters["RandomInName"])
        if ctx.bb_get(name) is None:
            return ctx.fail(f"no random number on the blackboard under {name!r}")
        try:
            ctx.write(keys.WORLD_MODEL, AddContainer("", "TestUser", "agent"))
        except RequestRejected as exc:
            if "already exists" not in exc.reason:
                raise
        ctx.write(keys.WORLD_MODEL, SetProperty("TestUser", "test", True))
        return True


class TestCompetency4(Competency):
    type = "TestType4"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        return ctx.fail("TestCompetency4 fails so that another TestType4 competency is tried")


class TestCompetency5(Competency):
    """Same type as 4; CMION's library builds it with the parameters ``Pizza,Pasta``."""

    type = "TestType4"

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        return True


class TestCompetency6(Competency):
    """A background competency: ticks a counter on the blackboard until the embodiment stops."""

    type = "TestType6"
    background = True
    interval = 1.0

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        ticks = 0
        while ctx.wait(self.interval):
            ticks += 1
            ctx.bb_set("TestCompetency6Ticks", ticks)
        return True
