"""Recordings of a mesh: ``record`` (and ``record info``) and ``replay``."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import threading
import time
from typing import Any

from cmion_mesh.cli.common import join_timeout_option, mesh_options
from cmion_mesh.cli.session import session
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError, ExitCode
from cmion_mesh.signals import Stopper
from cmion_mesh.tools.recording import Recorder, parse_size
from cmion_mesh.tools.recording_reader import format_info, info
from cmion_mesh.tools.replay import replay


def record_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Record the mesh to an MCAP file (Foxglove, the mcap CLI and any MCAP reader open it): "
                     "events (migration steps and actions among them), storage changes and liveliness, one "
                     "channel per key pattern, JSON messages with JSON schemas, a metadata record per embodiment. "
                     "Until Ctrl-C or --duration; a killed recorder leaves a file readable up to its last "
                     "chunk (at most about 0.5 s lost). `cmion-mesh record info FILE` summarises a recording "
                     "(duration, counts per channel, migrations, embodiments, drops, truncation). See docs/record.md.")
    p.add_argument("filters", nargs="*", metavar="FILTER",
                   help="key expressions of what to record, relative to cmion/<mesh>/ (e.g. robot/ev/** */wm/**) or absolute "
                        "(default: the whole mesh; liveliness is always recorded); `info FILE...` summarises recordings instead")
    p.add_argument("-o", "--output", metavar="FILE", help="the file (default: cmion-<mesh>-<date>-<time>.mcap here)")
    p.add_argument("--force", action="store_true", help="overwrite FILE if it exists (default: refuse)")
    p.add_argument("--split-size", metavar="SIZE",
                   help="start a new file (FILE-0001.mcap...) with the first message past this size, e.g. 100M, 1G")
    p.add_argument("--split-time", type=float, metavar="SECONDS",
                   help="start a new file with the first message after this many seconds")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (default: at Ctrl-C)")
    join_timeout_option(p)
    mesh_options(p)


def cmd_record(args: argparse.Namespace) -> int:
    if args.filters[:1] == ["info"]:
        return record_info(args.filters[1:], args.json)
    if args.split_time is not None and args.split_time <= 0:
        raise ConfigError(f"--split-time {args.split_time:g} must be more than 0 seconds")
    stop = Stopper()  # before any thread starts
    output = args.output or f"cmion-{args.mesh}-{time.strftime('%Y%m%d-%H%M%S')}.mcap"
    split_bytes = parse_size(args.split_size) if args.split_size else 0
    with session(args) as client, Recorder(client.transport, args.mesh, output, filters=args.filters or (),
                                           split_bytes=split_bytes, split_seconds=args.split_time or 0.0,
                                           overwrite=args.force) as recorder:
        # Join before saying we record: the daemons' answers to describe come after they learnt of
        # this session's subscriptions (one link, in order), and describe what they are, in the file.
        alive: list[str] = []
        if client.presence.wait(bool, args.join_timeout):
            described = client.describe_all(timeout=args.join_timeout)
            recorder.describe(described)
            alive = sorted({str(d.get("name")) for d in described})
        print(f"recording mesh {args.mesh!r} to {recorder.stats.files[0]} (alive: {', '.join(alive) or 'none yet'}; "
              "Ctrl-C to stop)", file=sys.stderr, flush=True)
        deadline = time.monotonic() + args.duration if args.duration else None
        for _ in range(1_000_000):  # bounded; each round ends on a signal or the duration
            left = None if deadline is None else deadline - time.monotonic()
            if (left is not None and left <= 0) or stop.wait(left) is not None:
                break
    stats = recorder.stats
    if args.json:
        print(json.dumps({"files": stats.files, "messages": stats.messages, "dropped": stats.dropped,
                          "embodiments": sorted(stats.embodiments)}))
    else:
        print(f"recorded {stats.messages} messages to {', '.join(stats.files)}"
              + (f"; DROPPED {stats.dropped} samples (the writer fell behind)" if stats.dropped else ""))
    return ExitCode.OK


def record_info(files: list[str], as_json: bool) -> int:
    if not files:
        raise ConfigError("record info: name the recording (cmion-mesh record info FILE.mcap)")
    summaries = [info(path) for path in files]
    if as_json:
        print(json.dumps(summaries[0] if len(summaries) == 1 else summaries))
    else:
        print("\n\n".join(format_info(s) for s in summaries))
    return ExitCode.OK


def replay_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Publish the events of an MCAP recording (cmion-mesh record) into --mesh, their keys "
                     "rewritten to it, in order, spaced as recorded divided by --rate. Storage, liveliness "
                     "and raw samples are not replayed. Waits (--join-timeout) for a subscriber of the first "
                     "event before publishing. See docs/record.md.")
    p.add_argument("file", metavar="FILE", help="the recording (.mcap)")
    p.add_argument("--rate", type=float, default=1.0,
                   help="speed: 1 as recorded, 10 ten times faster, 0 (or inf) as fast as possible (default: %(default)s)")
    p.add_argument("--filter", action="append", metavar="PATTERN",
                   help="only events whose key matches, relative to cmion/<mesh>/ (e.g. robot/ev/manager/*); repeatable")
    p.add_argument("--wait-for", action="append", metavar="EMBODIMENT", help="wait for this embodiment to be alive first; repeatable")
    join_timeout_option(p)
    mesh_options(p)


def cmd_replay(args: argparse.Namespace) -> int:
    stop = Stopper()  # before any thread starts
    halt = threading.Event()
    outcome: dict[str, Any] = {}

    def run(client: MeshClient) -> None:
        try:
            outcome["stats"] = replay(client, args.file, rate=args.rate, filters=args.filter or (), join_timeout=args.join_timeout,
                                      wait_for=args.wait_for or (), stop=halt,
                                      warn=lambda text: print(text, file=sys.stderr, flush=True))
        except BaseException as exc:
            outcome["error"] = exc
        finally:
            stop.stop()

    with session(args) as client:
        worker = threading.Thread(target=run, args=(client,), name="replay", daemon=True)
        worker.start()
        for _ in range(1_000_000):  # bounded; each round ends on a signal or the replay's end
            if stop.wait(1.0) is not None:
                halt.set()
            if not worker.is_alive():
                break
        worker.join()
    if "error" in outcome:
        raise outcome["error"]
    stats = outcome["stats"]
    if args.json:
        print(json.dumps(dataclasses.asdict(stats)))
    else:
        print(f"replayed {stats.published} events into mesh {args.mesh!r} in {stats.seconds:.2f} s"
              + (" (stopped)" if halt.is_set() else "")
              + (f"; {stats.undecodable} undecodable skipped" if stats.undecodable else "")
              + ("; the recording is truncated: replayed up to its last complete chunk" if stats.truncated else ""))
    return ExitCode.INTERRUPTED if halt.is_set() else ExitCode.OK
