"""The update loop's heartbeat: proof, for the watchdog and ``/healthz``, that the loop still turns.

A ``Heartbeat`` arms a recurring timer on the simulation (``Simulation.call_later``): each time
the loop runs it, the heartbeat counts a beat and notes when. Timers run at the start of an
update, so a busy loop still beats, an idle one wakes once per ``period`` (nothing else), and a
loop stuck in a handler stops beating: whoever reads ``beats`` or ``age()`` from another thread
sees it. Nothing is added to the loop's work but that one timer.

``ops.systemd.Service`` makes one when run by systemd (beating twice per watchdog ping) and
``ops.metrics.Metrics`` takes it (``heartbeat=service.heartbeat``), or makes its own: no wiring
of its own.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Self

from cmion_mesh.ion import Simulation
from cmion_mesh.timers import Timer
from cmion_mesh.transport.base import Handle

#: Default time between two beats (an idle loop wakes this often for the heartbeat, and no more).
PERIOD = 1.0


class Heartbeat(Handle):
    """Beats on ``sim``'s update loop every ``period`` seconds until closed (idempotent ``close``).

    ``beats`` and ``last`` are written on the loop only and read from any thread (an int and a
    float: reads never see half a write).
    """

    def __init__(self, sim: Simulation, period: float = PERIOD) -> None:
        if not period > 0 or math.isinf(period):
            raise ValueError(f"heartbeat period must be a positive number of seconds, not {period!r}")
        self.sim = sim
        self.period = period
        #: Beats so far (0 until the loop first ran the heartbeat).
        self.beats = 0
        #: ``time.monotonic()`` of the latest beat; None before the first.
        self.last: float | None = None
        self._timer: Timer | None = None
        self._closed = False
        self._first = threading.Event()
        sim.call(self._beat)  # the first beat at the loop's next update

    def _beat(self) -> None:
        if self._closed:
            return
        self.last = time.monotonic()
        self.beats += 1
        self._first.set()
        self._timer = self.sim.call_later(self.period, self._beat)

    def wait_first(self, timeout: float) -> bool:
        """Wait until the loop has beaten once; False when ``timeout`` passes first."""
        return self._first.wait(timeout)

    def age(self) -> float | None:
        """Seconds since the latest beat, or None before the first."""
        last = self.last
        return None if last is None else time.monotonic() - last

    def __enter__(self) -> Self:
        return self

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        # The next beat would not re-arm anyway; cancelling (on the loop) drops the pending timer now.
        self.sim.post(self._cancel)  # False once the simulation closed: its timers went with it

    def _cancel(self) -> None:
        timer, self._timer = self._timer, None
        if timer is not None:
            timer.cancel()
