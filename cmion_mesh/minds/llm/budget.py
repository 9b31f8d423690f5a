"""What the language-model mind may spend, as pure decisions: requests and tokens per minute,
tool calls per turn, and how long to wait after a failure.

``Budget`` keeps the requests sent in the last minute (when, and how many tokens each cost: an
estimate when sent, corrected by the ``usage`` the endpoint reports) and answers how long the next
request must wait so that neither the request nor the token rate is exceeded. Time is given by the
caller (``now``: any monotonic clock), so every decision is testable without a clock.

``backoff(failures)``: the delay before retrying after that many consecutive failures, doubling
from ``first`` up to ``cap`` (a ``Retry-After`` the endpoint sent wins when longer).
"""

from __future__ import annotations

import itertools
from collections import deque
from dataclasses import dataclass

#: The window the per-minute rates are counted over (seconds).
WINDOW = 60.0
#: Characters per token when the size of a request is estimated before it is sent (the usual rule
#: of thumb for English text and JSON with the common tokenizers; ``usage`` corrects it after).
CHARS_PER_TOKEN = 4


@dataclass(frozen=True, slots=True)
class Limits:
    """The budget and safety settings (``[budget]`` in the mind's settings file)."""

    requests_per_minute: int = 20
    tokens_per_minute: int = 60_000
    tool_calls_per_turn: int = 8
    backoff_first: float = 1.0
    backoff_cap: float = 60.0

    def problem(self) -> str:
        """Why these limits cannot work, or ""."""
        if self.requests_per_minute < 1 or self.tokens_per_minute < 1 or self.tool_calls_per_turn < 1:
            return "requests_per_minute, tokens_per_minute and tool_calls_per_turn must be at least 1"
        if not 0 < self.backoff_first <= self.backoff_cap <= 86_400:
            return "backoff_first must be above 0 and at most backoff_cap, itself at most 86400 seconds"
        return ""


def estimate_tokens(characters: int) -> int:
    """Tokens a request of that many characters of JSON is taken to cost before the endpoint says."""
    return max(1, characters // CHARS_PER_TOKEN)


@dataclass(slots=True)
class _Spent:
    when: float
    tokens: int  # estimated when sent, corrected by ``settle``
    handle: int


class Budget:
    """Requests and tokens spent in the last ``WINDOW`` seconds (see the module's description)."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self._spent: deque[_Spent] = deque()
        self._handles = itertools.count(1)

    def _forget(self, now: float) -> None:
        while self._spent and self._spent[0].when <= now - WINDOW:
            self._spent.popleft()

    def wait(self, now: float, tokens: int) -> float:
        """Seconds before a request of ``tokens`` may be sent (0: now). A request larger than the
        whole token budget waits for an empty window, then goes: refusing it forever would stall
        the mind, and the rate still holds over any minute but that one."""
        self._forget(now)
        waits = [0.0]
        if len(self._spent) >= self.limits.requests_per_minute:
            waits.append(self._spent[len(self._spent) - self.limits.requests_per_minute].when + WINDOW - now)
        used = sum(s.tokens for s in self._spent)
        if used + tokens > self.limits.tokens_per_minute and self._spent:
            # Wait until enough of the oldest requests leave the window.
            need = used + tokens - self.limits.tokens_per_minute
            freed = 0.0
            for spent in self._spent:
                freed += spent.tokens
                if freed >= need:
                    waits.append(spent.when + WINDOW - now)
                    break
            else:
                waits.append(self._spent[-1].when + WINDOW - now)
        return max(waits)

    def spend(self, now: float, tokens: int) -> int:
        """Count a request sent now; returns its handle for ``settle``."""
        self._forget(now)
        spent = _Spent(now, tokens, next(self._handles))
        self._spent.append(spent)
        return spent.handle

    def settle(self, handle: int, tokens: int) -> None:
        """The endpoint said what the request cost (``usage.total_tokens``)."""
        for spent in self._spent:
            if spent.handle == handle:
                spent.tokens = tokens
                return

    def requests(self, now: float) -> int:
        self._forget(now)
        return len(self._spent)

    def tokens(self, now: float) -> int:
        self._forget(now)
        return sum(s.tokens for s in self._spent)


def backoff(failures: int, limits: Limits, retry_after: float | None = None) -> float:
    """Seconds to wait after ``failures`` (>= 1) consecutive failures: ``first``, doubling, at most
    ``cap``; a ``Retry-After`` the endpoint gave wins when it is longer (still at most ``cap``)."""
    delay = min(limits.backoff_cap, limits.backoff_first * (2.0 ** max(0, min(failures, 64) - 1)))
    if retry_after is not None and retry_after > delay:
        delay = min(limits.backoff_cap, retry_after)
    return delay


@dataclass(slots=True)
class TurnCount:
    """Tool calls made in the current turn (a turn: from the perceptions that woke the mind until
    the model answers without calling a tool). Past the cap, calls are refused and the mind waits
    for new perceptions before asking the model again: a model calling tools in a loop stops."""

    limit: int
    made: int = 0

    def take(self) -> bool:
        """Whether one more call fits in this turn (counting it if so)."""
        if self.made >= self.limit:
            return False
        self.made += 1
        return True

    @property
    def exhausted(self) -> bool:
        return self.made >= self.limit

    def new_turn(self) -> None:
        self.made = 0
