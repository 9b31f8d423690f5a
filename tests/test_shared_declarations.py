"""Handlers sharing one declaration (``transport.shared``): every handler gets every delivery, a
liveliness handler that joins later gets the keys alive first and then every change, none lost or
out of order, and closing one handler leaves the others running."""

from __future__ import annotations

import random
import threading
from typing import Any

from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import Handle
from cmion_mesh.transport.inbox import Dispatch
from cmion_mesh.transport.shared import Declarations, Shared, SharedLiveliness, SharedSamples


def _change(item: tuple[str, bool]) -> tuple[str, bool]:
    return item


class _Owner:
    """What the adapter does when the last handler leaves: notes it."""

    def __init__(self) -> None:
        self.emptied: list[Shared] = []

    def on_empty(self, shared: Shared) -> None:
        self.emptied.append(shared)


def test_every_handler_gets_every_batch_and_closing_one_keeps_the_others() -> None:
    owner = _Owner()
    a: list[int] = []
    b: list[int] = []
    with Dispatch() as dispatch:
        shared = SharedSamples(dispatch, "sub:t", lambda items: [i * 10 for i in items], owner.on_empty)
        first, second = shared.add(a.extend), shared.add(b.extend)
        assert first is not None and second is not None
        for i in range(5):
            shared.sink.put(i)
        wait_for(lambda: len(a) == 5 and len(b) == 5, 5, "both handlers")
        first.close()
        first.close()  # idempotent
        for i in range(5, 8):
            shared.sink.put(i)
        wait_for(lambda: len(b) == 8, 5, "the handler left")
        assert owner.emptied == [], "a handler is left: the declaration stays"
        second.close()
        assert owner.emptied == [shared], "the last one out undeclares"
        assert shared.add(a.extend) is None, "a finished declaration takes no handler: the caller declares afresh"
    assert a == [0, 10, 20, 30, 40] and b == [i * 10 for i in range(8)]


def test_each_handler_gets_a_list_of_its_own() -> None:
    kept: list[list[int]] = []

    def greedy(batch: list[int]) -> None:
        batch.append(-1)  # changes what it was given

    with Dispatch() as dispatch:
        shared = SharedSamples(dispatch, "sub:t", list, _Owner().on_empty)
        shared.add(greedy)
        shared.add(kept.append)
        shared.sink.put(1)
        wait_for(lambda: bool(kept), 5, "the batch")
    assert kept == [[1]]


def test_a_closed_handler_runs_no_more_once_close_returns() -> None:
    running = threading.Event()
    release = threading.Event()
    calls: list[int] = []

    def slow(batch: list[int]) -> None:
        calls.extend(batch)
        running.set()
        release.wait(10)

    with Dispatch() as dispatch:
        shared = SharedSamples(dispatch, "sub:t", list, _Owner().on_empty)
        member = shared.add(slow)
        other: list[int] = []
        shared.add(other.extend)
        assert member is not None
        shared.sink.put(1)
        running.wait(5)
        closing = threading.Thread(target=member.close)
        closing.start()
        shared.sink.put(2)
        release.set()
        closing.join(5)
        assert not closing.is_alive()
        wait_for(lambda: other == [1, 2], 5, "the other handler")
    assert calls == [1]


def _state(events: list[tuple[str, bool]]) -> set[str]:
    alive: set[str] = set()
    for key, up in events:
        (alive.add if up else alive.discard)(key)
    return alive


def _consistent(seen: list[tuple[str, bool]], stream: list[tuple[str, bool]]) -> bool:
    """``seen`` is the keys alive after some prefix of ``stream`` (as puts, in any order), then
    the rest of ``stream`` exactly: nothing lost, nothing twice, nothing out of order."""
    before: set[str] = set()
    for k in range(len(stream) + 1):
        if k:
            key, up = stream[k - 1]
            (before.add if up else before.discard)(key)
        if len(seen) - len(before) != len(stream) - k:
            continue
        head, tail = seen[:len(before)], seen[len(before):]
        if all(up for _, up in head) and {key for key, _ in head} == before and tail == stream[k:]:
            return True
    return False


def test_a_liveliness_handler_joining_later_gets_the_keys_alive_then_every_change() -> None:
    owner = _Owner()
    first: list[tuple[str, bool]] = []
    later: list[tuple[str, bool]] = []
    with Dispatch() as dispatch:
        shared = SharedLiveliness(dispatch, "live:t", _change, owner.on_empty)
        shared.add(lambda key, up: first.append((key, up)))
        for item in [("a", True), ("b", True), ("c", True), ("b", False)]:
            shared.sink.put(item)
        wait_for(lambda: len(first) == 4, 5, "the first handler")
        # Nothing more comes from the network: the snapshot must reach the new handler anyway.
        member = shared.add(lambda key, up: later.append((key, up)))
        wait_for(lambda: len(later) == 2, 5, "the snapshot")
        assert sorted(later) == [("a", True), ("c", True)]
        shared.sink.put(("a", False))
        wait_for(lambda: len(later) == 3, 5, "a change after it")
        assert later[-1] == ("a", False) and first[-1] == ("a", False)
        assert member is not None
        member.close()
        shared.sink.put(("d", True))
        wait_for(lambda: len(first) == 6, 5, "the first handler goes on")
    assert len(later) == 3


def test_handlers_joining_while_changes_stream_in_lose_and_reorder_nothing() -> None:
    """Changes and new handlers race (handlers added from another thread, and from a handler on
    the dispatch thread): each handler sees a snapshot of some moment and every change after it."""
    rng = random.Random(7)
    stream = [(f"k{rng.randrange(12)}", rng.random() < 0.6) for _ in range(3000)]
    seen: list[list[tuple[str, bool]]] = []
    lock = threading.Lock()

    def new_handler() -> Any:
        log: list[tuple[str, bool]] = []
        with lock:
            seen.append(log)
        return lambda key, up: log.append((key, up))

    with Dispatch() as dispatch:
        shared = SharedLiveliness(dispatch, "live:t", _change, _Owner().on_empty)
        shared.add(new_handler())
        joined_inside = threading.Event()

        def joins_from_a_handler(key: str, up: bool) -> None:
            if key == "k3" and not joined_inside.is_set():
                joined_inside.set()
                shared.add(new_handler())

        shared.add(joins_from_a_handler)

        def feed() -> None:
            for item in stream:
                shared.sink.put(item)

        feeder = threading.Thread(target=feed)
        feeder.start()
        for _ in range(20):
            shared.add(new_handler())
        feeder.join(10)
        shared.add(new_handler())  # after the last change: the final state, as a snapshot
        wait_for(lambda: len(seen) == 23 and all(log and _state(log) == _state(stream) for log in seen), 10,
                 "every handler at the final state")
    assert joined_inside.is_set()
    assert seen[0] == stream, "the first handler saw the stream as it came"
    for log in seen:
        assert _consistent(log, stream)


def test_a_failing_handler_is_not_the_others_loss() -> None:
    got: list[tuple[str, bool]] = []

    def fails(key: str, up: bool) -> None:
        raise RuntimeError("this one fails")

    with Dispatch() as dispatch:
        shared = SharedLiveliness(dispatch, "live:t", _change, _Owner().on_empty)
        shared.add(fails)
        shared.add(lambda key, up: got.append((key, up)))
        shared.sink.put(("a", True))
        shared.sink.put(("a", False))
        wait_for(lambda: len(got) == 2, 5, "both changes")
    assert got == [("a", True), ("a", False)]


class _Declared(Handle):
    def __init__(self) -> None:
        self.closed = False

    def close(self) -> None:
        self.closed = True


def test_the_register_declares_once_per_key_and_again_after_the_last_handler_left() -> None:
    declared: list[_Declared] = []

    def declare(shared: Shared) -> _Declared:
        declared.append(_Declared())
        return declared[-1]

    def refuse(shared: Shared) -> _Declared:
        raise ValueError("refused")

    with Dispatch() as dispatch:
        register = Declarations()

        def make(on_empty: Any) -> Shared:
            return SharedSamples(dispatch, "sub:t", list, on_empty)

        try:
            register.join("k", print, make, refuse)
        except ValueError:
            pass
        a = register.join("k", print, make, declare)
        b = register.join("k", print, make, declare)
        other = register.join("other", print, make, declare)
        assert len(declared) == 2, "one declaration per key, none kept of the one refused"
        a.close()
        assert not declared[0].closed
        b.close()
        assert declared[0].closed, "the last handler out undeclares"
        register.join("k", print, make, declare)
        assert len(declared) == 3 and not declared[1].closed
        other.close()
