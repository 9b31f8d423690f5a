"""Recordings of a mesh: ``record`` (and ``record info``) and ``replay``; and ``foxglove``, the
same channels live (docs/record.md)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import threading
import time
from typing import Any

from cmion_mesh.cli.common import join_timeout_option, json_option, mesh_options
from cmion_mesh.cli.session import session
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError, ExitCode
from cmion_mesh.signals import Stopper
from cmion_mesh.tools.foxglove import DEFAULT_PORT, INSTALL_HINT, FoxgloveServer
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
                        "(default: the whole mesh; liveliness is always recorded); `record info FILE...` summarises recordings")
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
    check_filters(args.filters)
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
        print(json.dumps({"files": stats.files, "messages": stats.messages, "samples": stats.samples, "dropped": stats.dropped,
                          "embodiments": sorted(stats.embodiments)}))
    else:
        print(f"recorded {stats.messages} messages to {', '.join(stats.files)}"
              + (f"; DROPPED {stats.dropped} samples (the writer fell behind)" if stats.dropped else ""))
    return ExitCode.OK


def check_filters(filters: list[str]) -> None:
    """A word that is no key filter is a usage error, said before anything is recorded: a typo of
    ``info`` (``record infoo x.mcap`` would otherwise record, its words taken as filters) or a file."""
    import difflib

    for text in filters:
        if "/" in text or "*" in text:
            continue
        if difflib.get_close_matches(text, ["info"], n=1, cutoff=0.6):
            raise ConfigError(f"record: {text!r} is no key filter (did you mean 'info'? cmion-mesh record info FILE)")
        if text.endswith(".mcap"):
            raise ConfigError(f"record: {text!r} is no key filter (to write it: record -o {text}; to read it: record info {text})")


def record_info_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Summarise recordings made by `cmion-mesh record`: the mesh, when the file (or the part of a "
                     "split recording) started, its duration, counts per channel, the migrations and their steps, "
                     "the embodiments and what they said of themselves, requests answered, drops, and whether the "
                     "file is truncated (a killed recorder: read up to its last complete chunk). See docs/record.md.")
    p.add_argument("files", nargs="+", metavar="FILE", help="a recording (.mcap); several: one summary each")
    json_option(p)


def cmd_record_info(args: argparse.Namespace) -> int:
    summaries = [info(path) for path in args.files]
    if args.json:
        print(json.dumps(summaries[0] if len(summaries) == 1 else summaries))
    else:
        print("\n\n".join(format_info(s) for s in summaries))
    return ExitCode.OK


def replay_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Publish the events of an MCAP recording (cmion-mesh record) into --mesh, their keys "
                     "rewritten to it, in order, spaced as recorded divided by --rate. Storage, liveliness "
                     "and raw samples are not replayed. Waits (--join) for a subscriber of the first "
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


def foxglove_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Serve the mesh live to Foxglove over the Foxglove WebSocket protocol, on the channels and "
                     "schemas of a recording: events (migration steps and actions among them), storage changes, "
                     "liveliness, requests answered, and the story as log lines (Foxglove's Log panel). In Foxglove: "
                     f"Open connection, Foxglove WebSocket, ws://HOST:PORT. Read-only. Needs {INSTALL_HINT}. "
                     "Until Ctrl-C or --duration. See docs/record.md.")
    p.add_argument("filters", nargs="*", metavar="FILTER",
                   help="key expressions of what to serve, relative to cmion/<mesh>/ (e.g. robot/ev/** */wm/**) or absolute "
                        "(default: the whole mesh; liveliness is always served)")
    p.add_argument("--web", default=f"127.0.0.1:{DEFAULT_PORT}", metavar="HOST:PORT",
                   help="where Foxglove connects (default: %(default)s, Foxglove's own; loopback unless an address says otherwise)")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (default: at Ctrl-C)")
    mesh_options(p, json_output=False)


def cmd_foxglove(args: argparse.Namespace) -> int:
    # Here, not at the top: the web server's module loads uvicorn, which record and replay never need.
    from cmion_mesh.web.server import LOOPBACK_NAMES, parse_bind

    host, port = parse_bind(args.web)
    stop = Stopper()  # before any thread starts
    with session(args) as client, FoxgloveServer(client.transport, args.mesh, host=host, port=port,
                                                 filters=args.filters or ()) as server:
        print(f"serving mesh {args.mesh!r} to Foxglove at {server.url} (in Foxglove: Open connection, Foxglove WebSocket; "
              "Ctrl-C to stop)", flush=True)
        if host not in LOOPBACK_NAMES:
            print(f"warning: anyone who reaches {server.url} reads mesh {args.mesh!r}", file=sys.stderr, flush=True)
        deadline = time.monotonic() + args.duration if args.duration else None
        for _ in range(1_000_000):  # bounded; each round ends on a signal or the duration
            left = None if deadline is None else deadline - time.monotonic()
            if (left is not None and left <= 0) or stop.wait(left) is not None:
                break
    print(f"served {server.messages} messages on {len(server.topics())} channels"
          + (f"; DROPPED {server.dropped} samples (the server fell behind)" if server.dropped else ""), flush=True)
    return ExitCode.OK
