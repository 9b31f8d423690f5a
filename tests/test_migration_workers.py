"""The handshake's reused threads (``migration.workers.Workers``)."""

from __future__ import annotations

import logging
import threading

import pytest

from cmion_mesh.migration.workers import Workers
from cmion_mesh.testing.wait import wait_for


def test_a_finished_worker_takes_the_next_job() -> None:
    ran: list[int] = []
    done = threading.Event()
    with Workers("t") as workers:
        first = threading.Event()
        assert workers.spawn("one", lambda: (ran.append(threading.get_ident()), first.set()))
        assert first.wait(5.0)
        # The worker counts itself idle just after its job: wait until the next job finds it so.
        wait_for(lambda: workers.idle == 1, 5.0, "the worker idle again")
        assert workers.spawn("two", lambda: (ran.append(threading.get_ident()), done.set()))
        assert done.wait(5.0)
        assert ran[0] == ran[1] and workers.threads == 1


def test_jobs_that_wait_do_not_delay_each_other() -> None:
    release = threading.Event()
    started = [threading.Event() for _ in range(3)]
    with Workers("t") as workers:
        try:
            for event in started:
                workers.spawn("wait", lambda e=event: (e.set(), release.wait(10.0)))
            assert all(event.wait(5.0) for event in started)  # each on a thread of its own, at once
            assert workers.threads == 3
        finally:
            release.set()


def test_a_failing_job_is_logged_and_the_worker_serves_on(caplog: pytest.LogCaptureFixture) -> None:
    done = threading.Event()

    def fail() -> None:
        raise ValueError("boom")

    with caplog.at_level(logging.ERROR, logger="cmion_mesh.migration.workers"), Workers("t") as workers:
        workers.spawn("failing", fail)
        workers.spawn("next", done.set)
        assert done.wait(5.0)
    assert "migration job failing failed" in caplog.text


def test_close_joins_the_workers_and_refuses_new_jobs() -> None:
    workers = Workers("t")
    done = threading.Event()
    workers.spawn("one", done.set)
    assert done.wait(5.0)
    assert workers.alive == 1
    workers.close()
    workers.close()  # idempotent
    assert workers.alive == 0
    assert workers.spawn("late", done.set) is False
