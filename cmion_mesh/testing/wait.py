"""Waiting, with a deadline, on a condition nothing signals."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def wait_for(condition: Callable[[], T], timeout: float, what: str, interval: float = 0.02) -> T:
    """Return ``condition()``'s first truthy value, or raise ``TimeoutError`` naming ``what``.

    For conditions that cannot be waited on directly (another process's state): bounded in
    time, and each try is cheap.
    """
    deadline = time.monotonic() + timeout
    tries = 0
    while True:
        tries += 1
        value = condition()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise TimeoutError(f"{what}: not true after {timeout:g} s ({tries} tries)")
        threading.Event().wait(interval)
