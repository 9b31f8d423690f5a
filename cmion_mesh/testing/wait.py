"""Waiting, with a deadline, on a condition nothing signals: ``wait_for`` (``procs.wait_for``, which
the demo uses too), and ``migrate_once_seen``."""

from __future__ import annotations

from typing import Any

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import RequestRejected
from cmion_mesh.procs import wait_for

__all__ = ["migrate_once_seen", "wait_for"]


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
