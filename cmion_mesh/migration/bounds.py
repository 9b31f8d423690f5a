"""What others may cost an embodiment: a sender's rate (``TokenBucket``), log lines about one peer
(``Quiet``), and the numbers an operator sets for those bounds in the environment (``env_limit``).

``TokenBucket`` is not locked: each is used on one thread (the loop, where requests are handled).
``Quiet`` is locked: any thread may ask it.
"""

from __future__ import annotations

import os
import threading
import time

from cmion_mesh.errors import ConfigError

#: Prepares a sender may have refused or dropped in a burst, and how many more per second: a
#: stranger's flood of prepares costs it ``rejected: busy``, not this embodiment's disk or time.
PREPARE_BURST = 20
PREPARE_RATE = 5.0
#: Seconds between two log lines about the same key (``Quiet``).
QUIET = 60.0


def env_limit(name: str, default: float, *, low: float, high: float, unit: str = "seconds") -> float:
    """The number in the environment variable ``name``, else ``default``; ``ConfigError`` naming
    the variable and the range when it is not a number of ``unit`` between ``low`` and ``high``
    (a whole number for bytes)."""
    raw = os.environ.get(name, "").strip()
    if not raw:
        return default
    try:
        value = float(int(raw)) if unit == "bytes" else float(raw)
    except ValueError:
        value = float("nan")
    if not low <= value <= high:  # NaN fails too
        shown = [str(int(x)) if float(x).is_integer() else f"{x:g}" for x in (low, high)]
        raise ConfigError(f"{name}={raw[:40]!r}: not a number of {unit} between {shown[0]} and {shown[1]}")
    return value


class TokenBucket:
    """A token bucket: ``take()`` is False once a sender has used its burst faster than the rate."""

    def __init__(self, burst: int = PREPARE_BURST, rate: float = PREPARE_RATE) -> None:
        self.burst = burst
        self.rate = rate
        self.tokens = float(burst)
        self.at = time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.at) * self.rate)
        self.at = now
        if self.tokens < 1:
            return False
        self.tokens -= 1
        return True


class Quiet:
    """Says whether to log about ``key`` now: at most once per ``QUIET`` seconds each (any thread)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}
        self._muted: dict[str, int] = {}

    def allow(self, key: str) -> int | None:
        """None to keep quiet, else how many lines about ``key`` were left out since the last."""
        now = time.monotonic()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last < QUIET:
                self._muted[key] = self._muted.get(key, 0) + 1
                return None
            if len(self._last) > 1024:
                self._last.clear()  # bounded: strangers are forgotten
            self._last[key] = now
            return self._muted.pop(key, 0)
