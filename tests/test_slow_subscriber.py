"""A subscriber that stops reading stalls nobody: the daemon keeps answering everyone else at its pace.

Real processes on loopback: a daemon (CMION's test scenario); a *stalled* process whose
subscription to the daemon's events blocks in its handler until told to go on, so that its
channel, then its link, fill up and stay full; a *flooder* that writes big blackboard values back
to back, so that the daemon publishes far more events than the stalled link can hold. Meanwhile
this process acts (``TestAction2``: a request, a plan, an end event) again and again for 10 s:
every act must end within 1 s. And with zenoh left to wait long for the stuck link, requests
(``describe``) must still be answered within 1 s: the update loop never waits for the network.
Run as a child: ``python -m tests.test_slow_subscriber stall|flood ...`` (``quit`` on stdin ends it).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import pytest

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.messages import Event, decode
from cmion_mesh.procs import Daemon
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import Sample, TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

from .conftest import CMION_2011, start_daemon

pytestmark = pytest.mark.timeout(180)

NAME = "cmion"
#: How long this process acts while the stalled subscriber holds its link full.
PROBE_SECONDS = 10.0
#: The longest an act may take (request, plan, end event) while a subscriber is stalled.
ANSWER_WITHIN = 1.0
#: Bytes of each blackboard value the flooder writes: each write is published twice (the value,
#: and the event with the value in its data), so a few dozen fill a stalled link's buffers.
VALUE_BYTES = 64 * 1024


def config(connect: str) -> TransportConfig:
    return TransportConfig(connect=(connect,), multicast=False, overrides=(("listen/endpoints", "[]"),))


def until_quit(stop: threading.Event) -> threading.Thread:
    """A thread setting ``stop`` when ``quit`` (or the end) comes on standard input."""

    def read() -> None:
        for line in sys.stdin:
            if line.strip() == "quit":
                break
        stop.set()

    thread = threading.Thread(target=read, name="stdin", daemon=True)
    thread.start()
    return thread


# --- the children -----------------------------------------------------------------------------------


def stall(args: argparse.Namespace) -> int:
    """Subscribe to the daemon's events and stop reading at the first one, until ``go`` (then say
    which actions ended) or ``quit``."""
    release, stop = threading.Event(), threading.Event()

    def commands() -> None:
        for line in sys.stdin:
            if line.strip() == "go":
                release.set()
            elif line.strip() == "quit":
                break
        release.set()
        stop.set()

    reader = threading.Thread(target=commands, name="stdin", daemon=True)
    reader.start()
    with ZenohTransport(config(args.connect)) as transport:
        said = threading.Event()

        def on_sample(sample: Sample) -> None:
            if not said.is_set():
                said.set()
                print("stalled", flush=True)
            release.wait()  # a reader that stopped reading: its channel fills, then its link
            event = decode(sample.payload, Event, where=sample.key)
            if (event.component, event.name) == ("manager", "ActionSucceeded") and isinstance(event.data, dict):
                print(f"ended {event.data.get('action_id')}", flush=True)

        with transport.subscribe(f"cmion/{args.mesh}/{args.embodiment}/ev/**", on_sample):
            print("ready", flush=True)
            stop.wait()
    reader.join()
    return 0


def flood(args: argparse.Namespace) -> int:
    """Write big blackboard values back to back until ``quit``; print how many were accepted."""
    stop = threading.Event()
    reader = until_quit(stop)
    value = "x" * VALUE_BYTES
    written = 0
    with ZenohTransport(config(args.connect)) as transport, MeshClient(transport, args.mesh) as client:
        client.join(args.embodiment, timeout=10.0)
        print("ready", flush=True)
        for i in range(10_000_000):
            if stop.is_set():
                break
            try:
                client.set_property(args.embodiment, "bb", "", f"flood{i % 16}", value)
                written += 1
            except MeshError as exc:
                print(f"refused {exc}", flush=True)
            if written % 100 == 0:
                print(f"written {written}", flush=True)
        reader.join()
    print(f"done {written}", flush=True)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.test_slow_subscriber")
    parser.add_argument("role", choices=("stall", "flood"))
    parser.add_argument("--connect", required=True)
    parser.add_argument("--mesh", required=True)
    parser.add_argument("--embodiment", required=True)
    args = parser.parse_args(argv)
    return stall(args) if args.role == "stall" else flood(args)


# --- the tests ------------------------------------------------------------------------------------


@contextlib.contextmanager
def stalled(mesh: str, *daemon_args: str) -> Iterator[tuple[MeshClient, Daemon]]:
    """The daemon, its stalled subscriber and its flooder, all running; a client of the daemon from
    this process. Every process is stopped on the way out."""
    library = embodiment_dir("cmion_test") / "CompetencyLibrary.xml"
    daemon, endpoint = start_daemon(mesh, NAME, "--rules", str(CMION_2011 / "CompManagerRulesTest.xml"),
                                    "--library", str(library), *daemon_args)
    child = [sys.executable, "-m", "tests.test_slow_subscriber"]
    where = ["--connect", endpoint, "--mesh", mesh, "--embodiment", NAME]
    children: list[Daemon] = []
    try:
        with ZenohTransport(config(endpoint)) as transport, MeshClient(transport, mesh) as client:
            client.join(NAME, timeout=10.0)
            assert client.act(NAME, "TestAction2", timeout=30).status == "succeeded"  # warm: the watch is open
            staller = Daemon([*child, "stall", *where], name="stall", stdin=True)
            children.append(staller)
            staller.wait_line("ready", 30)
            flooder = Daemon([*child, "flood", *where], name="flood", stdin=True)
            children.append(flooder)
            flooder.wait_line("ready", 30)
            staller.wait_line("stalled", 30)
            flooder.wait_line("written 100", 60)  # the stalled link is full by now, many times over
            yield client, staller
            flooder.send("quit")
            print(f"flooder: {int(flooder.wait_line('done ', 30).split()[1])} writes accepted")
            assert staller.proc.poll() is None, "\n".join(staller.lines)  # stalled all along, not gone
    finally:
        for p in children:
            try:
                p.send("quit")
            except (OSError, ValueError):
                pass  # gone already
        for p in [*children, daemon]:
            p.stop()
    assert daemon.proc.returncode == 0, "\n".join(daemon.lines[-30:])


def probe(ask: Callable[[], object], what: str) -> list[float]:
    """``ask()`` back to back for ``PROBE_SECONDS``: how long each took."""
    took: list[float] = []
    started = time.monotonic()
    for _ in range(100_000):
        if time.monotonic() - started >= PROBE_SECONDS:
            break
        t0 = time.monotonic()
        ask()
        took.append(time.monotonic() - t0)
    print(f"{what}: {len(took)}, slowest {max(took):.3f} s, mean {sum(took) / len(took) * 1000:.1f} ms")
    return took


def within(took: list[float], what: str) -> None:
    slow = [round(t, 3) for t in took if t > ANSWER_WITHIN]
    assert not slow, f"{len(slow)} of {len(took)} {what} took over {ANSWER_WITHIN} s: {slow}"
    assert len(took) >= PROBE_SECONDS / ANSWER_WITHIN


def test_a_stalled_subscriber_delays_no_one_else(mesh: str) -> None:
    """Acts end in time: requests are answered and the other subscribers' events keep coming. The
    stalled subscriber, once it reads again, hears new events again."""
    with stalled(mesh) as (client, staller):

        def act() -> None:
            report = client.act(NAME, "TestAction2", timeout=30)
            assert report.status == "succeeded", report

        took = probe(act, "acts")
        assert isinstance(client.describe(NAME)["publications_dropped"], int)
        staller.send("go")

        def heard() -> bool:
            ended = client.act(NAME, "TestAction2", timeout=30).action_id
            try:
                staller.wait_line(f"ended {ended}", 1.0)
            except TimeoutError:
                return False  # its link was given up: zenoh links it again by itself
            return True

        wait_for(heard, 60, "the subscriber that reads again hears actions end", interval=0.0)
    within(took, "acts")


def test_the_update_loop_never_waits_for_a_stalled_link(mesh: str, tmp_path: Path) -> None:
    """With zenoh left to wait 4 s for a stuck link (a file of the user's), requests are still
    answered at once: no publication is made from the update loop."""
    patient = tmp_path / "zenoh.json5"
    patient.write_text('{"transport": {"link": {"tx": {"queue": {"congestion_control": {"block": '
                       '{"wait_before_close": 4000000}}}}}}}\n')
    with stalled(mesh, "--config", str(patient)) as (client, _):
        took = probe(lambda: client.describe(NAME, timeout=30), "describes")
    within(took, "describes")


if __name__ == "__main__":
    sys.exit(main())
