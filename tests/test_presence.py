"""One name, one body: the claim a joining daemon makes on its name (``claim.NameClaim``).

On the in-memory transport, so that the other claimant can be played exactly (a claim older or
younger than the one joining, withdrawn or shown alive at a chosen moment); the real processes
are in ``test_cli_truth.py`` (a second robot, two started at the same moment, a duplicate later).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import pytest

from cmion_mesh import keys
from cmion_mesh.claim import Joining, NameClaim
from cmion_mesh.errors import Refused
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import Closeable
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

OLDEST = "0" * 20 + "-elder"
YOUNGEST = "9" * 20 + "-newcomer"


def claims(transport: MemoryTransport, mesh: str, name: str) -> list[str]:
    return sorted(k.rsplit("/", 1)[-1] for k in transport.alive(keys.claim_pattern(mesh, name)))


def joining(transport: MemoryTransport, mesh: str, name: str) -> tuple[ThreadPoolExecutor, Future[NameClaim]]:
    pool = ThreadPoolExecutor(max_workers=1)
    return pool, pool.submit(NameClaim, transport, mesh, name, window=0.2)


def finished(future: Future[NameClaim], check: Callable[[], bool] = lambda: True) -> None:
    wait_for(lambda: future.done() and check(), 10.0, "the claim decided")


def test_alone_the_claim_is_made_at_once(network: MemoryNetwork, mesh: str) -> None:
    with MemoryTransport(network, "a") as a, NameClaim(a, mesh, "robot", window=0.0) as claim:
        assert claims(a, mesh, "robot") == [claim.rank]


def test_a_claim_made_on_its_own_thread_is_decided_the_same(network: MemoryNetwork, mesh: str) -> None:
    # what `up` does (Joining): the claim is under way while the daemon loads; result() gives the
    # decision, a refusal included; closing an untaken one withdraws its claim
    with MemoryTransport(network, "a") as a, MemoryTransport(network, "b") as b, MemoryTransport(network, "c") as c:
        with Joining(a, mesh, "robot", window=0.0) as first:
            claim = first.result()
            assert claims(b, mesh, "robot") == [claim.rank]
            alive = a.declare_token(keys.alive_key(mesh, "robot"))
            with Joining(b, mesh, "robot", window=0.2) as second, pytest.raises(Refused, match="already alive"):
                second.result()
            assert claims(b, mesh, "robot") == [claim.rank], "the refused one's claim is gone"
            alive.close()
            claim.close()
        with Joining(c, mesh, "robot", window=0.0):
            wait_for(lambda: len(claims(c, mesh, "robot")) == 1, 10.0, "the claim made")
        assert claims(c, mesh, "robot") == [], "closing an untaken claim withdraws it"


def test_an_older_claim_makes_the_newcomer_yield_at_once(network: MemoryNetwork, mesh: str) -> None:
    with MemoryTransport(network, "elder") as elder, MemoryTransport(network, "new") as new:
        older = elder.declare_token(keys.claim_key(mesh, "robot", OLDEST))
        pool, future = joining(new, mesh, "robot")
        with pool:
            # it withdraws its own claim before anything else (so that a starting older one goes on) ...
            wait_for(lambda: claims(elder, mesh, "robot") == [OLDEST], 10.0, "the newcomer's claim withdrawn")
            assert not future.done()  # ... and waits for the older one to show alive or to withdraw
            older.close()  # it withdrew (refused, or stopped): the name is free
            finished(future)
        with future.result() as claim:
            assert claims(new, mesh, "robot") == [claim.rank], "claimed again"


def test_an_older_claim_that_stays_refuses_the_newcomer(network: MemoryNetwork, mesh: str) -> None:
    with MemoryTransport(network, "elder") as elder, MemoryTransport(network, "new") as new:
        elder.declare_token(keys.claim_key(mesh, "robot", OLDEST))
        with pytest.raises(Refused, match=r"another .robot. is starting .* \(zenoh id elder\)"):
            NameClaim(new, mesh, "robot", window=0.2)
        assert claims(elder, mesh, "robot") == [OLDEST]


def test_the_token_of_a_daemon_that_just_stopped_does_not_refuse_its_successor(network: MemoryNetwork, mesh: str) -> None:
    # a restart: the old daemon's tokens may still be there when the new one asks
    with MemoryTransport(network, "old") as old, MemoryTransport(network, "new") as new:
        token = old.declare_token(keys.alive_key(mesh, "robot"))
        claim_token = old.declare_token(keys.claim_key(mesh, "robot", OLDEST))

        def old_one_finishes_stopping(name: str) -> str:  # asked where the live one runs: nobody answers
            token.close()
            claim_token.close()
            return ""

        with NameClaim(new, mesh, "robot", window=0.2, describe=old_one_finishes_stopping) as claim:
            assert claims(new, mesh, "robot") == [claim.rank]


def test_an_older_claim_shown_alive_is_named_as_running(network: MemoryNetwork, mesh: str) -> None:
    with MemoryTransport(network, "elder") as elder, MemoryTransport(network, "new") as new:
        elder.declare_token(keys.claim_key(mesh, "robot", OLDEST))
        pool, future = joining(new, mesh, "robot")
        with pool:
            wait_for(lambda: claims(elder, mesh, "robot") == [OLDEST], 10.0, "the newcomer's claim withdrawn")
            elder.declare_token(keys.alive_key(mesh, "robot"))
            finished(future)
        with pytest.raises(Refused, match="'robot' is already alive"):
            future.result()


def test_a_younger_claim_that_withdraws_lets_the_older_start(network: MemoryNetwork, mesh: str) -> None:
    with MemoryTransport(network, "young") as young, MemoryTransport(network, "old") as old:
        younger = young.declare_token(keys.claim_key(mesh, "robot", YOUNGEST))
        pool, future = joining(old, mesh, "robot")
        with pool:
            wait_for(lambda: len(claims(young, mesh, "robot")) == 2, 10.0, "the older claim declared")
            assert not future.done()  # the younger newcomer may not have seen this claim: wait for its decision
            younger.close()
            finished(future)
        with future.result() as claim:
            assert claims(old, mesh, "robot") == [claim.rank]


def test_a_younger_claim_that_shows_alive_keeps_the_name(network: MemoryNetwork, mesh: str) -> None:
    # the newcomer's query was answered before this claim reached it: it saw no rival and started
    with MemoryTransport(network, "young") as young, MemoryTransport(network, "old") as old:
        young.declare_token(keys.claim_key(mesh, "robot", YOUNGEST))
        pool, future = joining(old, mesh, "robot")
        with pool:
            wait_for(lambda: len(claims(young, mesh, "robot")) == 2, 10.0, "the older claim declared")
            young.declare_token(keys.alive_key(mesh, "robot"))
            finished(future)
        with pytest.raises(Refused, match="'robot' is already alive"):
            future.result()
        assert claims(young, mesh, "robot") == [YOUNGEST]


def race(network: MemoryNetwork, mesh: str, name: str) -> tuple[list[NameClaim], list[Refused]]:
    """Two daemons claim ``name`` at the same moment; the one that wins shows alive, as a daemon
    would. Which won (their claims closed by now), which were refused."""
    barrier = threading.Barrier(2)
    won: list[NameClaim] = []
    refused: list[Refused] = []
    tokens: list[Closeable] = []
    lock = threading.Lock()

    def start(transport: MemoryTransport) -> None:
        barrier.wait(5.0)
        try:
            claim = NameClaim(transport, mesh, name, window=0.2)
        except Refused as exc:
            with lock:
                refused.append(exc)
            return
        with lock:
            won.append(claim)
            tokens.append(transport.declare_token(keys.alive_key(mesh, name)))

    with MemoryTransport(network, "a") as a, MemoryTransport(network, "b") as b:
        threads = [threading.Thread(target=start, args=(t,)) for t in (a, b)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(10.0)
        for handle in (*tokens, *won):
            handle.close()
    return won, refused


def test_of_two_started_together_exactly_one_keeps_the_name(network: MemoryNetwork, mesh: str) -> None:
    for attempt in range(20):
        won, refused = race(network, mesh, f"twin{attempt}")
        assert len(won) == 1 and len(refused) == 1, (attempt, won, refused)
        assert "started first" in str(refused[0]) or "already alive" in str(refused[0]), refused[0]
