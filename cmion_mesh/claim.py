"""A daemon's claim on its name.

One name, one body: before it declares ``@alive/<name>``, a daemon declares a claim
``cmion/<mesh>/@claim/<name>/<rank>`` (``rank``: its start time in ns, then its zenoh id, so claims
sort by age the same way everywhere), joins the mesh and refuses to start when ``@alive/<name>``
is already there or an older claim is (two started at the same moment: the older wins). The
winner keeps its claim for its life; a claim that appears later and stays longer than a
newcomer needs to decide (``DUPLICATE_GRACE``) is a duplicate: two parts of a mesh that could
not see each other have joined. ``NameClaim.duplicates`` names them; the embodiment says so loudly.

Joining does not wait a fixed time for tokens to arrive: once linked, it *asks* (liveliness
queries on ``@alive/*`` and on its name's claims), and a liveliness query ends when every peer
linked to the session has answered. Only when the answer is that nobody is alive does it wait
(``SETTLE``) and ask again: just after a link comes up, its declarations may not have been
exchanged, and the query then reaches nobody. Of two newcomers claiming one name through a common peer, at
least one sees the other's claim (each declares its claim before it asks, and the peer answers
in the order it hears them). The younger withdraws as soon as it sees an older claim; the older,
when it sees a younger one, waits until that one withdraws (it saw the older) or shows alive (it
did not: then the older refuses). So neither starts unseen by the other.

``Joining`` makes that claim on a thread of its own, on a session opened as soon as the name and
the endpoints are known: a daemon loads the rest (imports, rules, library, components) while it
waits for the mesh's answer (a round trip, or ``SETTLE`` when nobody is alive), and declares
``@alive/<name>`` once both are done. Nothing of the embodiment is on the mesh before the claim is
decided: only the claim token.

The claim asks the daemons it sees through a ``MeshClient`` (where the holder runs, whom they see
alive); ``Presence`` (``presence.py``) is only the live set, which the client keeps.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from cmion_mesh import keys
from cmion_mesh.errors import MeshError, Refused
from cmion_mesh.transport.base import Closeable, Handle, Transport

#: Longest wait for the peers linked to a joining daemon to answer its liveliness queries (they
#: answer in a round trip: this bounds a peer that does not).
ASK_TIMEOUT = 1.0
#: When the linked peers answer that no embodiment is alive, how long a joining daemon still waits
#: for tokens before it believes them (a link's declarations may not have been exchanged yet).
SETTLE = 0.15
#: How long a joining daemon waits for the token of a same-named embodiment that the others say is
#: alive, to say where it runs (it refuses either way).
REPORTED_WAIT = 3.0
#: How long a joining daemon that sees a younger claim on its name waits for that newcomer to
#: withdraw or to show alive (it decides once it has asked the mesh, which takes moments; a
#: newcomer that did not see this claim shows alive once its components are loaded).
YOUNGER_WAIT = 30.0
#: How often a joining daemon looks whether its session has connected to anyone (zenoh gives no
#: event for it); tokens wake it at once.
POLL = 0.02
#: A foreign claim on our name older than this is not a newcomer deciding: it is a duplicate.
DUPLICATE_GRACE = 5.0

#: How long closing an undecided ``Joining`` waits for its thread (the claim's own waits are bounded).
JOINING_CLOSE_WAIT = 5.0


class NameClaim(Handle):
    """This daemon's claim on ``name`` in ``mesh``; raises ``Refused`` if the name is taken.

    ``window``: how long to look for the rest of the mesh when nobody has been seen yet (0 when
    this session has no way to find anyone: it can only be found); ``connected()`` says whether the
    session has a link to anyone, which ends that wait early. ``views(names)`` asks those daemons
    which embodiments they see alive (they have been in the mesh longer than this session).
    ``describe(name)`` words where the other holder runs, for the refusal.
    """

    def __init__(self, transport: Transport, mesh: str, name: str, *, window: float,
                 describe: Callable[[str], str] = lambda name: "", connected: Callable[[], bool] | None = None,
                 views: Callable[[set[str]], set[str]] = lambda asked: set()) -> None:
        self.name = keys.check_name(name, "embodiment")
        self.rank = f"{time.time_ns():020d}-{transport.id}"
        self._cond = threading.Condition()
        self._claims: dict[str, float] = {}  # foreign rank -> when it was first seen (monotonic)
        self._alive: set[str] = set()  # embodiments seen alive while joining
        self._reported: set[str] = set()
        self._on_duplicate: Callable[[list[str]], None] | None = None
        self._timers: list[threading.Timer] = []
        self._closed = False
        self._transport = transport
        self._token = transport.declare_token(keys.claim_key(mesh, name, self.rank))
        self._watch: Closeable | None = None
        alive_pattern = f"{keys.mesh_prefix(mesh)}/{keys.ALIVE}/*"
        joining = transport.watch_liveliness(alive_pattern, self._on_alive)
        try:
            self._watch = transport.watch_liveliness(keys.claim_pattern(mesh, name), self._on_claim)
            deadline = time.monotonic() + window
            found = False
            with self._cond:
                for _ in range(int(window / POLL) + 2):  # bounded: ends on a sign of the mesh or the window's end
                    if self._claims or self._alive or (connected is not None and connected()):
                        found = True
                        break
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(min(POLL, left))  # woken at once by any token; links have no event
            if found:
                # Someone is there: ask every linked peer for the tokens it holds rather than wait for them.
                answered = transport.alive(alive_pattern, timeout=ASK_TIMEOUT)
                if not answered:
                    # Nothing: a mesh with no embodiment yet, or a link whose declarations are still on
                    # their way (under load, the query can find no route yet): wait for tokens, then ask again.
                    with self._cond:
                        self._cond.wait_for(lambda: bool(self._alive), SETTLE)
                    answered = transport.alive(alive_pattern, timeout=ASK_TIMEOUT)
                for key in answered:
                    self._on_alive(key, True)
                self._ask_claims(mesh, name)
            with self._cond:
                seen = set(self._alive)
            # Daemons this session is not linked to yet answered nothing: the daemons it sees know the
            # whole mesh. Ask them.
            reported = name not in seen and bool(seen) and name in views(seen)
            if reported:
                with self._cond:
                    self._cond.wait_for(lambda: name in self._alive, REPORTED_WAIT)
            self._decide(mesh, name, reported, describe)
        except BaseException:
            self.close()
            raise
        finally:
            joining.close()

    def _decide(self, mesh: str, name: str, reported: bool, describe: Callable[[str], str]) -> None:
        """Keep the claim, or raise ``Refused``: the name is alive, or an older claim holds it."""
        for _ in range(3):  # bounded: a round ends in a decision, or in the name freed by a daemon that stopped
            with self._cond:
                taken = reported or name in self._alive
                older = sorted(rank for rank in self._claims if rank < self.rank)
            if taken:
                where = describe(name)  # waits for the live one to answer
                if reported or where or self._transport.alive(keys.alive_key(mesh, name), timeout=ASK_TIMEOUT):
                    raise Refused(f"embodiment {name!r} is already alive in mesh {mesh!r}{f' ({where})' if where else ''}: "
                                  "one name, one body (stop that one first, or choose another --name)")
                with self._cond:  # its token was a daemon's that has just stopped: decide again
                    self._alive.discard(name)
                continue
            if older:
                # An older claim is a daemon still starting, or (its token delayed under load) one
                # already running: this one yields at once (withdrawing its claim lets a starting
                # older one go on), then lets it show which before telling the user.
                self._token.close()
                with self._cond:
                    self._cond.wait_for(lambda: name in self._alive or not any(rank < self.rank for rank in self._claims),
                                        REPORTED_WAIT)
                self._ask_claims(mesh, name)  # what is still there (a claim seen only by asking never says it left)
                with self._cond:
                    if name not in self._alive and any(rank < self.rank for rank in self._claims):
                        raise Refused(f"another {name!r} is starting in mesh {mesh!r} at the same moment (zenoh id "
                                      f"{older[0].partition('-')[2]}), and it started first: one name, one body")
                if name not in self._alive:
                    # the older claims were withdrawn (daemons refused or stopped): claim again
                    self._token = self._transport.declare_token(keys.claim_key(mesh, name, self.rank))
                continue
            # A younger claim is a newcomer that either saw this claim (it withdraws) or did not (it
            # shows alive, and then this one yields): wait for it to say which.
            for _ in range(int(YOUNGER_WAIT / REPORTED_WAIT)):
                with self._cond:
                    if self._cond.wait_for(lambda: name in self._alive or not any(rank > self.rank for rank in self._claims),
                                           REPORTED_WAIT):
                        break
                self._ask_claims(mesh, name)  # still there? (a claim seen only by asking never says it left)
            with self._cond:
                if name not in self._alive:
                    return
        raise Refused(f"embodiment {name!r} in mesh {mesh!r}: claimed and released by others three times while "
                      "this one joined; try again")

    def _ask_claims(self, mesh: str, name: str) -> None:
        """The claims on ``name`` now, asked of every linked peer (replacing what the watch gathered)."""
        ranks = {key.rsplit("/", 1)[-1] for key in self._transport.alive(keys.claim_pattern(mesh, name), timeout=ASK_TIMEOUT)}
        with self._cond:
            for rank in list(self._claims):
                if rank not in ranks:
                    self._claims.pop(rank, None)
        for rank in ranks:
            self._on_claim(keys.claim_key(mesh, name, rank), True)

    def _on_alive(self, key: str, alive: bool) -> None:
        with self._cond:
            (self._alive.add if alive else self._alive.discard)(key.rsplit("/", 1)[-1])
            self._cond.notify_all()

    def _on_claim(self, key: str, alive: bool) -> None:
        rank = key.rsplit("/", 1)[-1]
        if rank == self.rank:
            return
        with self._cond:
            if alive:
                self._claims.setdefault(rank, time.monotonic())
                self._schedule_check()
            else:
                self._claims.pop(rank, None)
                self._reported.discard(rank)
            self._cond.notify_all()

    def _schedule_check(self) -> None:
        # Under the lock. A newcomer withdraws its claim within its window; one still here after the
        # grace is a duplicate.
        if self._on_duplicate is None or self._closed:
            return
        timer = threading.Timer(DUPLICATE_GRACE, self._check_duplicates)
        timer.daemon = True
        self._timers = [t for t in self._timers if t.is_alive()]
        self._timers.append(timer)
        timer.start()

    def watch_duplicates(self, on_duplicate: Callable[[list[str]], None]) -> None:
        """From now on, call ``on_duplicate(zenoh ids)`` when another daemon holds this name for longer
        than a newcomer needs to decide (two parts of a mesh joined). Claims already here count too."""
        with self._cond:
            self._on_duplicate = on_duplicate
            if self._claims:
                self._schedule_check()

    def duplicates(self) -> list[str]:
        """Zenoh ids of the other daemons holding this name (beyond the grace), oldest first."""
        now = time.monotonic()
        with self._cond:
            return [rank.partition("-")[2] for rank, seen in sorted(self._claims.items()) if now - seen >= DUPLICATE_GRACE]

    def keeps_name(self) -> bool:
        """The documented rule: of two daemons holding one name, the older claim keeps it."""
        with self._cond:
            return all(rank > self.rank for rank in self._claims)

    def _check_duplicates(self) -> None:
        now = time.monotonic()
        with self._cond:
            fresh = sorted(r for r, seen in self._claims.items() if now - seen >= DUPLICATE_GRACE - 0.05 and r not in self._reported)
            self._reported.update(fresh)
            notify = self._on_duplicate if not self._closed else None
        if fresh and notify is not None:
            notify([rank.partition("-")[2] for rank in fresh])

    def close(self) -> None:
        with self._cond:
            if self._closed:
                return
            self._closed = True
            timers, self._timers = self._timers, []
        for timer in timers:
            timer.cancel()
        if self._watch is not None:
            self._watch.close()
        self._token.close()


def where(transport: Transport, mesh: str, name: str) -> str:
    """Where the live embodiment ``name`` runs, for a refusal (host, pid, zenoh id, up since)."""
    # Start time: a daemon joins before it loads the rest; the client is needed only when someone holds the name.
    from cmion_mesh.client import MeshClient

    with MeshClient(transport, mesh) as client:
        try:
            client.wait_for_embodiment(name, timeout=3.0)  # its token may still be on its way
            found = client.describe(name, timeout=3.0)
        except MeshError:
            return ""
    since = time.strftime("%H:%M:%S", time.localtime(found.get("started_at", 0))) if found.get("started_at") else "?"
    return f"on host {found.get('host', '?')}, pid {found.get('pid', '?')}, zenoh id {found.get('zenoh_id', '?')}, up since {since}"


def views(transport: Transport, mesh: str, asked: set[str]) -> set[str]:
    """The embodiments that the daemons ``asked`` see alive."""
    from cmion_mesh.client import MeshClient  # start time, as in ``where``: asked only when someone is seen

    with MeshClient(transport, mesh) as client:
        return client.reported_alive(asked, time.monotonic() + 2.0)


def claim_name(transport: Transport, mesh: str, name: str, window: float) -> NameClaim:
    """A daemon's ``NameClaim`` on ``transport``: asking the daemons it sees, and naming the holder when refused."""
    # Only the zenoh adapter knows its links (``peers``); a transport without it waits the window.
    links = getattr(transport, "peers", None)
    return NameClaim(transport, mesh, name, window=window, describe=lambda n: where(transport, mesh, n),
                     connected=None if links is None else lambda: bool(links()),
                     views=lambda asked: views(transport, mesh, asked))


class Joining(Handle):
    """``claim_name`` on a thread of its own, started at once: ``result()`` waits for the decision
    (the ``NameClaim``, or the ``Refused`` raised). Closing it before ``result()`` withdraws the claim."""

    def __init__(self, transport: Transport, mesh: str, name: str, *, window: float) -> None:
        self.transport = transport
        self.name = keys.check_name(name, "embodiment")
        self._claim: NameClaim | None = None
        self._error: BaseException | None = None
        self._taken = False
        self._thread = threading.Thread(target=self._run, args=(mesh, window), name=f"claim-{name}", daemon=True)
        self._thread.start()

    def _run(self, mesh: str, window: float) -> None:
        try:
            self._claim = claim_name(self.transport, mesh, self.name, window)
        except BaseException as exc:  # handed to result(): raised in the thread that waits for it
            self._error = exc

    def result(self) -> NameClaim:
        """The claim once decided (the caller then owns it); raises what the claim raised."""
        self._thread.join()  # bounded: every wait of NameClaim has a deadline
        if self._error is not None:
            raise self._error
        assert self._claim is not None
        self._taken = True
        return self._claim

    def close(self) -> None:
        self._thread.join(JOINING_CLOSE_WAIT)
        claim = self._claim
        if claim is not None and not self._taken:
            claim.close()
