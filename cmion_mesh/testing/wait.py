"""Waiting, with a deadline, on a condition nothing signals."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import RequestRejected

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


def migrate_once_seen(client: MeshClient, companion: str, target: str, *, timeout: float = 30.0) -> dict[str, Any]:
    """``client.migrate``, asked again while the companion's host does not see ``target`` alive yet.

    A client that sees two daemons over its own links knows nothing of the link between them: the
    host learns that the target is alive over that link, which may come up later, and refuses
    until then ("is not alive").
    """

    def attempt() -> dict[str, Any] | None:
        try:
            return client.migrate(companion, target, timeout=timeout)
        except RequestRejected as exc:
            if "is not alive" in exc.reason:
                return None
            raise

    migrated = wait_for(attempt, timeout, f"the host of {companion} sees {target} and migrates {companion} to it")
    assert migrated is not None  # wait_for returns a true value
    return migrated
