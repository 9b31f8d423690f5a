"""The update loop's timers (``Simulation.call_later``): a ``Timer`` for each call, and ``Timers``,
the heap of one loop, soonest first. The loop sleeps until the soonest is due (it does not poll)
and runs what is due at the start of an update; the loop alone arms, cancels and runs them.
"""

from __future__ import annotations

import heapq
import itertools
import time
from collections.abc import Callable

#: Longest timer delay: queue.get cannot wait past threading.TIMEOUT_MAX, and a later timer is 'never'.
MAX_TIMER_DELAY = 30 * 24 * 3600.0
#: Cancelled timers beyond which the heap is rebuilt, if they are most of it.
REBUILD_AFTER = 64


class Timer:
    """A pending ``call_later``; ``cancel`` must be called on the loop (as timers are armed there)."""

    __slots__ = ("due", "fn", "id", "timers")

    def __init__(self, timers: Timers, due: float, timer_id: int, fn: Callable[[], None]) -> None:
        self.timers = timers
        self.due = due
        self.id = timer_id
        self.fn: Callable[[], None] | None = fn

    def cancel(self) -> None:
        if self.fn is not None:
            self.fn = None
            self.timers.cancelled()

    def fire(self) -> Callable[[], None] | None:
        fn, self.fn = self.fn, None
        return fn


class Timers:
    """The timers of one loop. ``timer`` may be called from any thread; the rest on the loop."""

    __slots__ = ("_cancelled", "_heap", "_ids")

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, Timer]] = []
        self._cancelled = 0
        self._ids = itertools.count()

    def timer(self, delay: float, fn: Callable[[], None]) -> Timer:
        """A timer running ``fn`` in ``delay`` seconds (0 to ``MAX_TIMER_DELAY``; NaN is 0), to ``arm``."""
        return Timer(self, time.monotonic() + min(max(0.0, delay), MAX_TIMER_DELAY), next(self._ids), fn)

    def arm(self, timer: Timer) -> None:
        if timer.fn is not None:  # not cancelled before the loop got to it
            heapq.heappush(self._heap, (timer.due, timer.id, timer))

    def next_due(self) -> float | None:
        """When the soonest timer is due (``time.monotonic``), or None when none is armed."""
        heap = self._heap
        return heap[0][0] if heap else None

    def pop_due(self) -> list[Callable[[], None]]:
        """What the timers due now run, soonest first (cancelled ones left out), taken off the heap."""
        heap = self._heap
        if not heap:
            return []
        now = time.monotonic()
        due = []
        while heap and heap[0][0] <= now:
            fn = heapq.heappop(heap)[2].fire()
            if fn is not None:
                due.append(fn)
        return due

    @property
    def armed(self) -> int:
        """Timers armed and not cancelled."""
        return sum(1 for entry in self._heap if entry[2].fn is not None)

    def cancelled(self) -> None:
        # Cancelled timers stay in the heap until due; rebuild it when they are most of it.
        self._cancelled += 1
        if self._cancelled > REBUILD_AFTER and self._cancelled * 2 > len(self._heap):
            self._heap = [t for t in self._heap if t[2].fn is not None]
            heapq.heapify(self._heap)
            self._cancelled = 0
