"""Event throughput of a mesh with and without a recorder attached (``cmion-mesh record``).

Processes (loopback): the fan-out benchmark's publisher (``bench.fanout pub``: a raw zenoh
session and a cmion ``Simulation`` raising bursts of events back to back, blocking congestion
control), one of its subscribers (``bench.fanout sub``, index 0: it follows groups 1 and 2), and a
``cmion-mesh record`` process recording only group 2's key (``fan-pub/ev/src/burst2``), and a second
plain subscriber process following only group 3. So in one run, alternating: raw zenoh bursts
(group 1, the baseline), mesh bursts to the one subscriber (group 1), to it and a second plain
subscriber process (group 3: what any second process costs on the machine) and to it and the
recorder (group 2), each measured at the slowest subscriber as in the fan-out curve
(events / (last received - first published)).

The recorder's own pace is read back from its file: per burst, events / (last ``log_time`` -
first), the times at which its subscription received them. Nothing may be lost: the file must
hold every group-2 event published (warm-ups and end markers included) and say it dropped none;
otherwise the row is a failure.
"""

from __future__ import annotations

import json
import re
import signal
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

from bench.core import open_session
from bench.fanout import DONE, control_key
from bench.harness import loopback_config, loopback_endpoint, start_child, stop_child
from bench.registry import Options, Row, compare
from bench.stats import summarize
from cmion_mesh.procs import Daemon, cli_argv, unique_mesh
from cmion_mesh.tools.recording import FLUSH_INTERVAL
from cmion_mesh.tools.recording_format import EVENT_SCHEMA
from cmion_mesh.tools.recording_reader import RecordingReader, info

LABELS = {
    "record_raw": "raw zenoh events/s, 1 subscriber (baseline)",
    "record_mesh": "mesh events/s, 1 subscriber, no recorder",
    "record_mesh_second": "mesh events/s, 1 subscriber + a second plain subscriber process",
    "record_mesh_recorded": "mesh events/s, 1 subscriber + `cmion-mesh record` attached",
    "record_recorder_rate": "events/s received by the recorder (from its file's log times)",
}
UNRECORDED, RECORDED, SECOND = 1, 2, 3


def log(text: str) -> None:
    print(f"  [record] {text}", flush=True)


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    count, rounds = (5000, 2) if options.quick else (20000, 4)
    mesh = unique_mesh("bench")
    raw_ep, mesh_ep = loopback_endpoint(), loopback_endpoint()
    rates: dict[str, list[float]] = {m: [] for m in LABELS}
    published = 0
    ids = iter(range(1, 1_000_000))
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-record-")))
        output = tmp / "bench.mcap"
        pub = start_child("bench.fanout", "pub", "--raw-listen", raw_ep, "--mesh-listen", mesh_ep, "--mesh", mesh, "--tag", mesh,
                          name="fan-pub")
        stack.callback(stop_child, pub)
        pub.wait_line("ready", 30.0)
        sub = start_child("bench.fanout", "sub", "--index", "0", "--raw-connect", raw_ep, "--mesh-connect", mesh_ep, "--mesh", mesh,
                          "--tag", mesh, "--groups", f"{UNRECORDED},{RECORDED},{SECOND}", name="fan-sub0")
        stack.callback(stop_child, sub)
        # A plain subscriber process on group 3 only (a subscriber follows the groups above its index).
        second = start_child("bench.fanout", "sub", "--index", str(SECOND - 1), "--raw-connect", raw_ep, "--mesh-connect", mesh_ep,
                             "--mesh", mesh, "--tag", mesh, "--groups", str(SECOND), name="fan-sub2")
        stack.callback(stop_child, second)
        sub.wait_line("ready", 60.0)
        second.wait_line("ready", 60.0)
        recorder = Daemon(cli_argv("record", "--mesh", mesh, "--connect", mesh_ep, "--no-multicast", "--join-timeout", "0.2",
                                   "-o", str(output), f"fan-pub/ev/src/burst{RECORDED}"), name="recorder")
        stack.callback(recorder.kill)
        recorder.wait_line("recording mesh", 30.0)
        session = open_session(loopback_config(connect=raw_ep))
        stack.callback(session.close)

        def burst(kind: str, group: int, n: int) -> tuple[str, int]:
            burst_id = f"b{next(ids)}"
            request = json.dumps({"kind": kind, "group": group, "count": n, "id": burst_id}).encode()
            replies = [r.ok.payload.to_bytes() for r in session.get(control_key(mesh), payload=request, timeout=120.0)
                       if r.ok is not None]
            if not replies:
                raise TimeoutError(f"publisher did not answer the burst {burst_id}")
            return burst_id, int(json.loads(replies[0])["t_start"])

        def done(burst_id: str, timeout: float, group: int = UNRECORDED) -> re.Match[str]:
            """The done line of the slowest subscriber of ``group``."""
            found = []
            for child in (sub, second) if group == SECOND else (sub,):
                match = DONE.search(child.wait_line(f"id={burst_id} ", timeout))
                assert match is not None
                found.append(match)
            return max(found, key=lambda m: int(m.group(8)))

        for kind, group in (("raw", UNRECORDED), ("mesh", UNRECORDED), ("mesh", RECORDED), ("mesh", SECOND)):
            for _attempt in range(10):  # until the subscription has reached the publisher
                burst_id, _ = burst(kind, group, 100)
                published += 101 if group == RECORDED else 0
                try:
                    if int(done(burst_id, 5.0, group).group(4)) == 100:
                        break
                except TimeoutError:
                    continue
            else:
                raise TimeoutError(f"{kind} group {group}: the subscriber never received a warm-up burst")
        # The recorder's subscription must have reached the publisher too before a measured burst
        # (its file shows it once the chunk is written out, within its flush interval).
        for _attempt in range(10):
            burst_id, _ = burst("mesh", RECORDED, 100)
            published += 101
            done(burst_id, 5.0)
            if _file_holds(output, 101, 3.0):
                break
        else:
            raise TimeoutError("the recorder never wrote a warm-up burst")
        log(f"publisher, subscriber and recorder ready; {rounds} round(s) of {count} events per run")
        lost = 0
        for r in range(rounds):
            for metric, kind, group in (("record_raw", "raw", UNRECORDED), ("record_mesh", "mesh", UNRECORDED),
                                        ("record_mesh_second", "mesh", SECOND), ("record_mesh_recorded", "mesh", RECORDED)):
                burst_id, t_start = burst(kind, group, count)
                match = done(burst_id, 120.0, group)
                rates[metric].append(count / ((int(match.group(8)) - t_start) / 1e9))
                lost += int(match.group(5)) + max(0, count - int(match.group(4)))
                if group == RECORDED:
                    published += count + 1
            log(f"round {r + 1}/{rounds} done")
        # The recorder may lag behind (zenoh's and the socket's buffers hold what it has not taken
        # yet, and blocking congestion control slows the publisher once they are full): stop it once
        # it has caught up, i.e. once its file has stopped growing for a few of its flush intervals.
        lag = _caught_up(output, time.monotonic())
        log(f"recorder caught up {lag:.2f} s after the last burst reached the subscriber")
        code = recorder.stop(signal.SIGINT, grace=120.0)
        summary = info(output)
        in_file = summary["channels"].get(f"cmion/{mesh}/fan-pub/ev/src/burst{RECORDED}", 0)
        rates["record_recorder_rate"] = _recorder_rates(output, count)
        size = output.stat().st_size
    failures = []
    if code != 0:
        failures.append(f"the recorder exited with {code}")
    if summary["dropped"] or in_file != published:
        failures.append(f"recorder: {in_file} of {published} events in the file, {summary['dropped']} dropped")
    if lost:
        failures.append(f"the subscriber lost {lost} events")
    extra = {"events_per_run": count, "catch_up_s": round(lag, 3), "recorded": in_file,
             "published": published, "dropped": summary["dropped"],
             "file_bytes_per_event": round(size / max(1, in_file), 1)}
    rows = [Row(m, LABELS[m], summarize(rates[m], 1.0), unit="events/s", extra=extra) for m in LABELS]
    compare(rows, {m: "record_raw" for m in LABELS if m != "record_raw"}, None)
    for row in rows:
        if row.metric in ("record_mesh_recorded", "record_recorder_rate"):
            row.failures = list(failures)
    log(f"recorder: {in_file}/{published} events in the file, {summary['dropped']} dropped, {extra['file_bytes_per_event']} B/event")
    return rows


def _caught_up(path: Path, since: float, quiet: float = 4 * FLUSH_INTERVAL, timeout: float = 120.0) -> float:
    """Seconds from ``since`` until ``path`` last grew, once it has not grown for ``quiet`` seconds."""
    size, grew = path.stat().st_size, since
    for _ in range(int(timeout / 0.05)):  # bounded in time
        time.sleep(0.05)
        now, current = time.monotonic(), path.stat().st_size
        if current != size:
            size, grew = current, now
        elif now - grew >= quiet:
            break
    return grew - since


def _file_holds(path: Path, events: int, timeout: float) -> bool:
    """Whether ``path`` holds at least ``events`` events, within ``timeout`` (read every 0.1 s)."""
    deadline = time.monotonic() + timeout
    for _ in range(int(timeout / 0.1) + 1):  # bounded in time
        if _recorded(path) >= events:
            return True
        if time.monotonic() >= deadline:
            break
        time.sleep(0.1)
    return False


def _recorded(path: Path) -> int:
    with RecordingReader(path) as reader:
        return sum(1 for m in reader.messages() if m.schema == EVENT_SCHEMA)


def _recorder_rates(path: Path, count: int) -> list[float]:
    """Per measured burst (``count`` events, then its end marker), events / its span of log times."""
    out: list[float] = []
    times: list[int] = []
    with RecordingReader(path) as reader:
        for message in reader.messages():
            if message.schema != EVENT_SCHEMA:
                continue
            if isinstance(message.decoded().get("data"), dict):  # the end marker
                if len(times) == count and times[-1] > times[0]:
                    out.append(count / ((times[-1] - times[0]) / 1e9))
                times = []
            else:
                times.append(message.log_time)
    return out
