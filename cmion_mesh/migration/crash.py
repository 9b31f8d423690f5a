"""Crash points: where the crash tests ask a daemon to die, hard, in the middle of its work.

``CMION_MESH_CRASH_AT`` names points, comma-separated. The handshake's are ``source:prepared``,
``source:handed``, ``source:released``, ``target:incoming`` and ``target:active`` (right after
that record is durable). The ledger's own (``ledger``) are named after the state of the record
whose entry is being written: ``ledger:torn:<state>`` (half the entry is on disk, the process
dies before the rest: a torn append), ``ledger:compacting:<state>`` (the ledger rewritten after
that entry, the new file synced but not yet in place) and ``ledger:compacted:<state>`` (in place,
its folder not yet synced).
"""

from __future__ import annotations

import logging
import os
import signal

log = logging.getLogger(__name__)

CRASH_ENV = "CMION_MESH_CRASH_AT"


def wanted(point: str) -> bool:
    """Whether the crash tests asked this process to die at ``point``."""
    asked = os.environ.get(CRASH_ENV, "")
    return bool(asked) and point in {p.strip() for p in asked.split(",")}


def die(point: str) -> None:
    """SIGKILL this process, as a power cut or ``kill -9`` would."""
    log.warning("crash point %s: killing this process", point)
    os.kill(os.getpid(), signal.SIGKILL)


def crash_point(point: str) -> None:
    """Die here, hard, if the crash tests asked for it (``CMION_MESH_CRASH_AT``)."""
    if wanted(point):
        die(point)
