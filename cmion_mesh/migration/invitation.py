"""Migration invitations (CMION's ``InviteMigration``): an empty embodiment asks the companion over.

The ``invitation`` component of every embodiment that can host a companion does both sides:

**Receiving** (``.../rq/invitation/invite/<inviter>``, ``Invite``): the answer is definite.
Rejected, with a ``Code``, when the inviter is not the key's sender (``invalid``), when it is not
alive in the mesh as this embodiment sees it (``not_found``: only a live embodiment invites), when
the inviter sends faster than ``INVITE_BURST`` / ``INVITE_RATE`` allow or all inviters together
faster than ``HOST_BURST`` / ``HOST_RATE`` (``busy``: however many names a flood uses, the mind
sees at most the host's budget), when no companion lives here (``not_found``), when this
embodiment has a device table that does not list the inviter (``invalid``), or while the
companion is migrating (``busy``). Otherwise the invitation becomes the remote action
``MigrationInvitation`` for the companion's mind(s): a ``RemoteAction`` event (``name``
``MigrationInvitation``, ``subject`` the inviter as CMION set it, and the inviter as parameter 1,
so rules and planner operators match ``MigrationInvitation <embodiment>``), and the answer is
accepted. Whether the mind follows it is the mind's choice.

**Sending** (a round): asked by the request ``.../rq/invitation/send`` (``SendInvitations``, what
``cmion-mesh invite`` sends) or by the ION event ``InviteMigration`` raised by any component here
(a mind: ``self.raise_event("InviteMigration")``), or by ``invite()``. Only an embodiment that
hosts no companion invites, one round at a time. The round goes to the embodiments of its device
table, or without a table to every embodiment alive in the mesh, all at once, and each answer is
an ``InvitationAnswered`` event; the round ends with ``InvitationsDone`` (``round``,
``accepted_by``, ``answers``: target -> ``{status, reason, code}``). A round that cannot start
raises ``InvitationsNotSent`` with the reason (the ``send`` request is then rejected with it).

Unlike CMION, no TCP invite port is opened (the ``inviteport`` of a device table is read and
ignored): invitations are mesh requests, so none is lost unread and each has an answer.
"""

from __future__ import annotations

import functools
import logging
import threading
import uuid
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from cmion_mesh import keys
from cmion_mesh.errors import MeshError, NotReached, OutcomeUnknown, RequestRejected
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.messages import Code, Event, Invite, Outcome, SendInvitations
from cmion_mesh.migration.bounds import TokenBucket
from cmion_mesh.migration.devices import DeviceTable
from cmion_mesh.migration.manager import MigrationManager
from cmion_mesh.mind import Mind
from cmion_mesh.presence import Presence
from cmion_mesh.requests import IncomingRequest, send_request
from cmion_mesh.transport.base import Closeable

log = logging.getLogger(__name__)

#: Invitations one inviter may send in a burst, and how many more per second, before it is
#: answered ``busy``.
INVITE_BURST = 3
INVITE_RATE = 0.5
#: The same for all inviters together: the most invitations the mind sees. In plain mode a name is
#: only a claim, so the per-inviter budget alone would not bound a flood sent under many names.
HOST_BURST = 10
HOST_RATE = 1.0
#: Inviters whose budget is remembered; beyond it the least recently seen is forgotten (it starts
#: again with a full budget, which the host's budget still bounds).
MAX_INVITERS = 1024
#: The remote action an accepted invitation becomes.
INVITATION_ACTION = "MigrationInvitation"
#: The ION event that asks this embodiment to invite (CMION's ``InviteMigration``).
INVITE_EVENT = "InviteMigration"
#: Most targets asked at once in a round.
MAX_PARALLEL = 8


class Invitations(Component):
    """The ``invitation`` component (see the module doc)."""

    requests = {"invite": Invite, "send": SendInvitations}
    # The inviter is known from the key: in secure mode only its certificate may invite as it.
    sender_requests = frozenset({"invite"})
    built_by_embodiment = True

    def __init__(self, migration: MigrationManager, devices: DeviceTable | None = None, *, request_timeout: float = 5.0,
                 presence: Presence | None = None) -> None:
        """``presence``: the embodiment's view of who is alive, already current when it has joined
        the mesh; without it the component watches liveliness itself from ``attach`` on."""
        super().__init__("invitation")
        self.migration = migration
        self.devices = devices
        self.request_timeout = request_timeout
        self._buckets: OrderedDict[str, TokenBucket] = OrderedDict()  # inviter -> its budget, least recent first (loop)
        self._host_bucket = TokenBucket(HOST_BURST, HOST_RATE)  # every inviter's (loop)
        self._round: str | None = None  # the round under way from here (loop)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._presence = presence
        self._own_presence: Presence | None = None
        self._watch: Closeable | None = None

    # --- life cycle (loop) ----------------------------------------------------------------------

    def attach(self, sim: Simulation) -> None:
        if self._presence is None:
            self._presence = self._own_presence = Presence(sim.transport, sim.mesh)
        self._watch = sim.on_event(self._on_invite_event, event=INVITE_EVENT)

    def detach(self) -> None:
        for handle in (self._watch, self._own_presence):
            if handle is not None:
                handle.close()
        self._stop.set()
        with self._lock:
            threads, self._threads = self._threads, []
        for thread in threads:
            thread.join(self.request_timeout + 5.0)

    def alive(self) -> set[str]:
        """The embodiments alive in the mesh, as this one sees them."""
        return self._presence.alive() if self._presence is not None else set()

    # --- requests (loop) ------------------------------------------------------------------------

    def handle_requests(self, batch: list[IncomingRequest]) -> None:
        for request in batch:
            match request.payload:
                case Invite() as payload:
                    request.answer(self._receive(request.requester, payload.inviter))
                case SendInvitations() as payload:
                    try:
                        round_id, targets = self.invite(payload.to)
                    except MeshError as exc:
                        request.reject(str(exc), Code(exc.code) if isinstance(exc, RequestRejected) else Code.INVALID)
                    else:
                        request.accept({"round": round_id, "targets": targets})
                case other:
                    request.reject(f"invitation has no request of type {type(other).__name__}", Code.UNKNOWN_REQUEST)

    def _receive(self, requester: str, inviter: str) -> Outcome:
        me = self.sim.embodiment
        if requester != inviter:
            return Outcome("rejected", f"{requester!r} cannot invite on behalf of {inviter!r}", code=Code.INVALID)
        if inviter != me and inviter not in self.alive():
            # Only a live embodiment can take the companion in: a ghost's invitation would send it nowhere.
            return Outcome("rejected", f"{inviter!r} is not alive in mesh {self.sim.mesh!r}: only a live embodiment invites",
                           code=Code.NOT_FOUND)
        if not self._budget(inviter).take():
            return Outcome("rejected", f"busy: too many invitations from {inviter!r}; try again later", code=Code.BUSY)
        if not self._host_bucket.take():
            return Outcome("rejected", f"busy: too many invitations to {me!r} from all inviters; try again later", code=Code.BUSY)
        companion = self.migration.inhabitant
        if companion is None:
            return Outcome("rejected", f"{me!r} hosts no companion", code=Code.NOT_FOUND)
        if inviter == me:
            return Outcome("rejected", f"{companion!r} already lives on {me!r}", code=Code.INVALID)
        if self.devices is not None and not self.devices.knows(inviter):
            return Outcome("rejected", f"{inviter!r} is not in {me!r}'s device table {self.devices.path.name} "
                                       f"(known: {', '.join(self.devices.names) or 'none'})", code=Code.INVALID)
        target = self.migration.migrating_to
        if target is not None:
            return Outcome("rejected", f"busy: {companion!r} is migrating to {target!r}", code=Code.BUSY)
        minds = [c.name for c in self.sim.components if isinstance(c, Mind) and c.awake]
        log.info("invitation from %s passed to %s's mind(s) %s", inviter, companion, minds)
        self.raise_event("RemoteAction", {"name": INVITATION_ACTION, "subject": inviter, "parameters": [inviter],
                                          "companion": companion})
        return Outcome("accepted", "", {"companion": companion, "host": me, "minds": minds})

    def _budget(self, inviter: str) -> TokenBucket:
        bucket = self._buckets.get(inviter)
        if bucket is None:
            if len(self._buckets) >= MAX_INVITERS:
                self._buckets.popitem(last=False)
            bucket = self._buckets[inviter] = TokenBucket(INVITE_BURST, INVITE_RATE)
        else:
            self._buckets.move_to_end(inviter)
        return bucket

    # --- sending a round (loop, then a round thread) --------------------------------------------

    def _on_invite_event(self, event: Event) -> None:
        try:
            self.invite()
        except MeshError as exc:
            log.info("no invitations sent from %s: %s", self.sim.embodiment, exc)

    def invite(self, to: list[str] | None = None) -> tuple[str, list[str]]:
        """Start a round of invitations from here (loop thread); returns its id and targets.
        ``RequestRejected`` (with a ``code``) when it cannot start, also raised as ``InvitationsNotSent``."""
        try:
            round_id, targets = self._start(list(to or ()))
        except MeshError as exc:
            self.raise_event("InvitationsNotSent", {"inviter": self.sim.embodiment, "reason": str(exc)})
            raise
        return round_id, targets

    def _start(self, to: list[str]) -> tuple[str, list[str]]:
        me = self.sim.embodiment
        companion = self.migration.inhabitant or (self.migration.identity.companion if self.migration.identity else None)
        if companion is not None:
            raise _refused(f"{me!r} hosts {companion!r}: an inhabited embodiment does not invite", Code.INVALID)
        if self._round is not None:
            raise _refused(f"a round of invitations from {me!r} is under way", Code.BUSY)
        for name in to:
            keys.check_name(name, "invited embodiment")
        if to:
            targets = to
        elif self.devices is not None:
            targets = self.devices.names
        else:
            targets = sorted(self.alive())
        targets = [t for t in dict.fromkeys(targets) if t != me]
        if not targets:
            where = f"its device table {self.devices.path.name} lists none" if self.devices is not None and not to \
                else f"no other embodiment is alive in mesh {self.sim.mesh!r}"
            raise _refused(f"{me!r} has nobody to invite: {where}", Code.NOT_FOUND)
        round_id = uuid.uuid4().hex[:12]
        self._round = round_id
        self.raise_event("InvitationsSent", {"round": round_id, "inviter": me, "targets": targets})
        thread = threading.Thread(target=self._send_round, args=(round_id, targets), name=f"invitation-{round_id}", daemon=True)
        with self._lock:
            self._threads = [t for t in self._threads if t.is_alive()]
            self._threads.append(thread)
        thread.start()
        return round_id, targets

    def _send_round(self, round_id: str, targets: list[str]) -> None:
        """Round thread: ask every target at once; each answer goes to the loop as it comes."""
        answers: dict[str, dict[str, Any]] = {}
        with ThreadPoolExecutor(max_workers=min(MAX_PARALLEL, len(targets)), thread_name_prefix=f"invite-{round_id}") as pool:
            for target, outcome in zip(targets, pool.map(self._ask, targets), strict=True):
                answer = {"status": outcome.status, "reason": outcome.reason, "code": outcome.code}
                answers[target] = answer
                self.sim.post(functools.partial(self.raise_event, "InvitationAnswered", {"round": round_id, "target": target, **answer}))
        self.sim.post(lambda: self._done(round_id, answers))

    def _ask(self, target: str) -> Outcome:
        me = self.sim.embodiment
        if self._stop.is_set():
            return Outcome("rejected", f"{me!r} is shutting down", code=Code.SHUTTING_DOWN)
        if target not in self.alive():
            return Outcome("rejected", f"{target!r} is not alive in mesh {self.sim.mesh!r}", code=Code.NOT_FOUND)
        key = keys.request_key(self.sim.mesh, target, self.name, "invite", me)
        try:
            return send_request(self.sim.transport, key, Invite(me), timeout=self.request_timeout)
        except NotReached:
            return Outcome("rejected", f"nobody answered {key}: {target!r} cannot host a companion", code=Code.NOT_FOUND)
        except OutcomeUnknown as exc:
            return Outcome("rejected", f"outcome unknown: {exc}", code=Code.OUTCOME_UNKNOWN)

    def _done(self, round_id: str, answers: dict[str, dict[str, Any]]) -> None:
        if self._round == round_id:
            self._round = None
        accepted = sorted(t for t, a in answers.items() if a["status"] == "accepted")
        log.info("invitations from %s: accepted by %s; answers %s", self.sim.embodiment, accepted or "nobody", answers)
        self.raise_event("InvitationsDone", {"round": round_id, "inviter": self.sim.embodiment, "accepted_by": accepted,
                                             "answers": answers})


def _refused(reason: str, code: Code) -> RequestRejected:
    return RequestRejected(reason, reason=reason, code=code)
