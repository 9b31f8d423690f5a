"""What the parts of the ``migration`` component ask of the manager that owns them (``Host``), and
the crash points both sides of the handshake share.

``MigrationManager`` (``manager``) is the one ``Host``. Its parts (``outgoing``, ``incoming``,
``uploads``, ``claims``, ``forks``) are given it when they are built, and reach what they share
through it only: the records, the inhabitant and its minds, this embodiment's custody token, the
handshake threads and the way back to the loop. Typing them against this protocol rather than the
manager keeps the modules in one order (the parts below the manager, never importing it back).

Threads: ``post``, ``spawn`` and ``ask`` may be called from any thread (``ask`` blocks: never on
the loop); ``records`` and ``quiet`` are locked, ``stopping`` is an event. ``memo`` is not locked:
a source's handshake thread packs with it while the minds sleep and the loop leaves it alone (an
embodiment holding a companion refuses every offer before it reaches the memo). Everything else,
and every write to ``identity``, is the loop's.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any, Protocol

from cmion_mesh.ion import Simulation
from cmion_mesh.messages import Outcome
from cmion_mesh.migration.bounds import Quiet
from cmion_mesh.migration.crash import crash_point
from cmion_mesh.migration.identity import Identity, SectionMemo
from cmion_mesh.migration.ledger import Record, Records
from cmion_mesh.mind import Mind

__all__ = ["Host", "crash_point"]

log = logging.getLogger(__name__)


class Host(Protocol):
    """The manager as its parts see it."""

    #: The component's name (``migration``), in answers that name it.
    name: str
    #: The durable records, documents, keys and sections of this embodiment (locked: any thread).
    records: Records
    #: Which companions may enter (name -> trusted identity key, or None); None admits any.
    admit: dict[str, bytes | None] | None
    #: Companions whose stored identity is unusable: reported, never run (loop).
    damaged: dict[str, str]
    #: The companion living here, when inhabited (loop).
    identity: Identity | None
    #: The companion's section bytes last packed or received, with their hashes (not locked).
    memo: SectionMemo
    #: The first and the longest pause between two tries of a handshake request (seconds).
    retry: tuple[float, float]
    #: Set when the component detaches: handshake threads end at their next wait.
    stopping: threading.Event
    #: Log lines about one peer at most once a minute (any thread).
    quiet: Quiet

    @property
    def sim(self) -> Simulation: ...

    def raise_event(self, name: str, data: Any = None) -> None: ...

    def post(self, fn: Callable[..., None], *args: Any) -> None:
        """Run ``fn(*args)`` on the loop (from any thread); dropped once the simulation closes."""

    def spawn(self, name: str, fn: Callable[..., None], *args: Any) -> bool:
        """Run ``fn(*args)`` on a handshake thread (``workers.Workers``), joined at ``detach``;
        False (nothing runs) once the host is stopping."""

    def ask(self, peer: str, op: str, message: Any, timeout: float | None = None) -> Outcome:
        """Send the handshake request ``op`` to ``peer``'s migration component and wait for its
        answer (a handshake thread; ``OutcomeUnknown`` when none comes)."""

    def ask_later(self, peer: str, op: str, message: Any) -> Callable[[], Outcome]:
        """``ask`` in two steps: sent when this returns, answered by the function returned (once)."""

    def step(self, record: Record) -> None:
        """Raise ``MigrationStep`` for a durable record of a handshake (loop)."""

    def claim(self, companion: str, epoch: int) -> None:
        """Declare this embodiment's custody token for ``companion`` at ``epoch`` (loop)."""

    def withdraw_claim(self) -> None:
        """Withdraw this embodiment's custody token, if any (loop)."""

    def minds(self) -> list[Mind]: ...

    def sleep_minds(self) -> None: ...

    def wake_minds(self) -> None:
        """Wake every mind and tell it the companion arrived, with the world model (loop)."""

    def refresh_sections(self, identity: Identity) -> None:
        """Put each mind's current state into ``identity`` as its section (loop)."""

    def resume(self, companion: str, why: str) -> None:
        """Inhabit ``companion`` again from its stored identity (loop), or report it damaged."""

    def inhabit(self, identity: Identity, event: str, why: str) -> None:
        """Make ``identity`` the one living here and raise ``event`` (loop)."""
