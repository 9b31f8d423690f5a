"""A competency of your own: ``Blink`` blinks the body's light.

The light is the blackboard: ``light/on`` is on or off, ``light/blinks`` counts every blink of
this body, ``light/last`` is how many times the last run blinked. A real body would switch a
GPIO pin where this writes ``light/on``; everything else stays as it is.
"""

from __future__ import annotations

from typing import Any

from cmion_mesh import Competency, RunContext

#: Most blinks one action may ask for: a typo (``Blink 300``) must not keep the light busy for minutes.
MAX_TIMES = 20


def blink_times(value: Any) -> int:
    """The number of blinks a run's ``Times`` parameter asks for; ``ValueError`` saying why not."""
    try:
        times = int(str(value))
    except ValueError:
        raise ValueError(f"Times must be a whole number of blinks, not {value!r}") from None
    if not 1 <= times <= MAX_TIMES:
        raise ValueError(f"Times must be 1 to {MAX_TIMES}, not {times}")
    return times


class Blink(Competency):
    """Blinks the light ``Times`` times (a competency of type ``Light``). Its one constructor
    parameter is how long the light stays on, in seconds."""

    type = "Light"

    def __init__(self, seconds_on: str = "0.05") -> None:
        super().__init__(seconds_on)
        self.seconds_on = float(seconds_on)

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        try:
            times = blink_times(parameters.get("Times"))
        except ValueError as exc:
            return ctx.fail(str(exc))  # the action fails with this reason
        blinks = int(ctx.bb_get("light/blinks", 0))
        for _ in range(times):
            ctx.bb_set("light/on", True)
            cancelled = not ctx.wait(self.seconds_on)  # returns early when the action is cancelled
            ctx.bb_set("light/on", False)
            if cancelled:
                return False
            blinks += 1
            ctx.bb_set("light/blinks", blinks)
        ctx.bb_set("light/last", times)
        return True
