"""The outbox: publications queued without waiting, sent in order, dropped and counted only when full.

The sender here is a function that can be held (a link that takes nothing); no network: what
crosses processes is in ``test_slow_subscriber``.
"""

from __future__ import annotations

import logging
import threading

import pytest

from cmion_mesh.errors import ClosedError
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.outbox import OVERHEAD, Outbox

pytestmark = pytest.mark.timeout(30)


class Link:
    """A sender that records what it sends and, while ``held``, takes nothing."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, bytes | None]] = []
        self.open = threading.Event()
        self.open.set()
        self.busy = threading.Event()  # a send is under way

    def hold(self) -> None:
        self.open.clear()

    def release(self) -> None:
        self.open.set()

    def send(self, key: str, payload: bytes | None, attachment: bytes | None) -> None:
        self.busy.set()
        self.open.wait(20.0)
        self.sent.append((key, payload))


def test_a_held_link_never_holds_the_caller_and_a_full_queue_drops_the_newest(caplog: pytest.LogCaptureFixture) -> None:
    link = Link()
    link.hold()
    with caplog.at_level(logging.WARNING, logger="cmion_mesh.transport.outbox"), Outbox(link.send, max_items=4) as box:
        assert box.put("k/0", b"0")
        link.busy.wait(10.0)  # the thread holds k/0: it counts until it is sent
        taken = [box.put(f"k/{i}", str(i).encode()) for i in range(1, 10)]
        assert taken == [True] * 3 + [False] * 6
        assert (box.dropped, box.waiting) == (6, 4)
        link.release()
        wait_for(lambda: box.waiting == 0, 10, "the queue sent")
        assert box.put("k/10", b"10")  # room again
    assert link.sent == [("k/0", b"0"), ("k/1", b"1"), ("k/2", b"2"), ("k/3", b"3"), ("k/10", b"10")]
    reports = [r.getMessage() for r in caplog.records if "dropped" in r.getMessage()]
    assert len(reports) == 1 and "k/4" in reports[0], reports  # one line, not one per drop


def test_the_bound_counts_bytes_and_a_publication_bigger_than_it_still_goes() -> None:
    link = Link()
    link.hold()
    with Outbox(link.send, max_bytes=2 * (1000 + OVERHEAD)) as box:
        assert box.put("big/0", b"x" * 5000)  # alone: taken
        link.busy.wait(10.0)
        assert not box.put("big/1", b"y")  # 5000 bytes wait already
        link.release()
        wait_for(lambda: box.waiting == 0, 10, "the queue sent")
        assert box.put("small/0", b"x" * 900) and box.put("small/1", None)  # a delete
    assert [key for key, _ in link.sent] == ["big/0", "small/0", "small/1"]
    assert link.sent[-1] == ("small/1", None)
    assert box.dropped == 1


def test_close_sends_what_is_queued_then_refuses_more() -> None:
    link = Link()
    box = Outbox(link.send)
    for i in range(1000):
        box.put(f"k/{i}", b"x")
    box.close()
    box.close()  # idempotent
    assert [key for key, _ in link.sent] == [f"k/{i}" for i in range(1000)]
    assert not box.sending and box.dropped == 0
    with pytest.raises(ClosedError, match="k/x"):
        box.put("k/x", b"x")


def test_close_gives_up_on_a_link_that_takes_nothing_and_counts_what_it_drops() -> None:
    link = Link()
    link.hold()
    box = Outbox(link.send, drain=0.2)
    for i in range(5):
        box.put(f"k/{i}", b"x")
    link.busy.wait(10.0)
    box.close()  # returns after drain: the link still holds k/0
    assert box.sending
    link.release()  # what closing the session does to a put under way
    box.join(10.0)
    assert not box.sending
    assert link.sent == [("k/0", b"x")]
    assert (box.dropped, box.waiting) == (4, 0)


def test_a_failed_publication_loses_no_other(caplog: pytest.LogCaptureFixture) -> None:
    sent: list[str] = []

    def send(key: str, payload: bytes | None, attachment: bytes | None) -> None:
        if key.startswith("bad/"):
            raise ValueError(f"refused {key}")
        sent.append(key)

    with caplog.at_level(logging.WARNING, logger="cmion_mesh.transport.outbox"), Outbox(send) as box:
        for i in range(10):
            box.put(f"bad/{i}", b"x")
            box.put(f"good/{i}", b"x")
    assert sent == [f"good/{i}" for i in range(10)]
    assert box.failed == 10 and box.dropped == 0
    assert len([r for r in caplog.records if "could not publish" in r.getMessage()]) == 1
