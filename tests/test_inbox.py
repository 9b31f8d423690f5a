"""The session's one dispatch thread (``transport.inbox``): order per entity, batches, closing, no thread while idle."""

from __future__ import annotations

import threading
from typing import Any

from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import MAX_BATCH
from cmion_mesh.transport.inbox import Dispatch


def test_no_thread_before_the_first_item_and_none_after_close() -> None:
    with Dispatch(name="dispatch-test") as dispatch:
        got: list[Any] = []
        sink = dispatch.sink("a", got.extend)
        assert dispatch.thread is None, "an entity that never receives costs no thread"
        sink.put(1)
        wait_for(lambda: got == [1], 5, "delivered")
        thread = dispatch.thread
        assert thread is not None and thread.is_alive()
    assert not thread.is_alive()


def test_each_entity_gets_its_items_in_order_in_batches_of_at_most_max_batch() -> None:
    release = threading.Event()
    got: dict[str, list[list[int]]] = {"a": [], "b": []}

    def handler(name: str) -> Any:
        def handle(items: list[int]) -> None:
            got[name].append(list(items))
            release.wait(10)  # a slow handler: what comes meanwhile waits in the queue
        return handle

    with Dispatch() as dispatch:
        a, b = dispatch.sink("a", handler("a")), dispatch.sink("b", handler("b"))
        a.put(0)
        wait_for(lambda: got["a"] == [[0]], 5, "the first item")
        for i in range(1, 2000):
            (a if i % 3 else b).put(i)
        release.set()
        wait_for(lambda: sum(map(len, got["a"])) + sum(map(len, got["b"])) == 2000, 10, "every item")
    assert [i for batch in got["a"] for i in batch] == [i for i in range(2000) if i % 3 or i == 0]
    assert [i for batch in got["b"] for i in batch] == [i for i in range(1, 2000) if not i % 3]
    assert max(len(batch) for batch in got["a"]) > 1, "what waited came in batches"
    assert all(len(batch) <= MAX_BATCH for batches in got.values() for batch in batches)


def test_a_closed_entity_runs_no_more_and_its_queued_items_are_discarded() -> None:
    release = threading.Event()
    ran: list[int] = []
    discarded: list[int] = []

    def slow(items: list[int]) -> None:
        release.wait(10)

    with Dispatch() as dispatch:
        blocker = dispatch.sink("blocker", slow)
        sink = dispatch.sink("queries", ran.extend, discard=discarded.append)
        blocker.put(0)
        wait_for(lambda: dispatch.thread is not None, 5, "the thread")
        for i in range(5):
            sink.put(i)
        sink.close()
        release.set()
        sink.put(99)  # after close: never queued
        wait_for(lambda: discarded == [0, 1, 2, 3, 4], 5, "the queued items discarded (a query is finalized)")
    assert ran == []


def test_a_failing_handler_stops_nothing_else() -> None:
    got: list[int] = []

    def fails(items: list[int]) -> None:
        raise RuntimeError("this one fails")

    with Dispatch() as dispatch:
        bad, good = dispatch.sink("bad", fails), dispatch.sink("good", got.extend)
        for i in range(10):
            bad.put(i)
            good.put(i)
        wait_for(lambda: got == list(range(10)), 5, "the others")


def test_an_entity_closed_from_its_own_handler_does_not_wait_for_itself() -> None:
    closed = threading.Event()

    with Dispatch() as dispatch:
        def handle(items: list[int]) -> None:
            sink.close()
            closed.set()

        sink = dispatch.sink("self", handle)
        sink.put(1)
        wait_for(closed.is_set, 5, "closed from its handler")
