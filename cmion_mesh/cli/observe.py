"""Following what the mesh says: ``events``, ``hz`` and ``echo``."""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Callable

import msgspec

from cmion_mesh.cli.common import join_timeout_option, mesh_options
from cmion_mesh.cli.session import session
from cmion_mesh.errors import ConfigError, ExitCode
from cmion_mesh.messages import Event
from cmion_mesh.signals import Stopper
from cmion_mesh.tools import hz_echo as tap

KEYS_HELP = ("a key expression: relative to the mesh (robot/ev/**, robot/bb/**, @alive/*, ** for all it publishes) "
             "or absolute (cmion/MESH/..., or any zenoh key expression after a leading /)")


def events_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--follow", "-f", action="store_true", help="keep following (the default; for familiarity)")
    p.add_argument("--embodiment", default="*", help="only this embodiment's events (default: all)")
    p.add_argument("--component", default="*", help="only this component's events (default: all)")
    p.add_argument("--event", default="*", help="only events of this name (default: all)")
    p.add_argument("--count", type=int, default=0, help="stop after exactly this many events")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    join_timeout_option(p)
    mesh_options(p)


def cmd_events(args: argparse.Namespace) -> int:
    stop = Stopper()
    lock = threading.Lock()
    seen = [0]

    def show(event: Event) -> None:
        with lock:  # exactly --count events, however many arrive before the main thread stops
            if args.count and seen[0] >= args.count:
                return
            seen[0] += 1
            if args.json:
                print(json.dumps(msgspec.to_builtins(event)), flush=True)
            else:
                stamp = time.strftime("%H:%M:%S", time.localtime(event.time)) + f".{int(event.time * 1000) % 1000:03d}"
                data = json.dumps(event.data) if event.data is not None else ""
                print(f"{stamp} {event.embodiment}/{event.component} {event.name} {data}", flush=True)
            if args.count and seen[0] == args.count:
                stop.stop()

    with session(args) as client, client.events(show, embodiment=args.embodiment, component=args.component, event=args.event):
        if args.embodiment != "*":
            client.join(args.embodiment, timeout=args.join_timeout)
        else:
            client.presence.wait(bool, args.join_timeout)
        if not args.json:
            print(f"following events of {args.embodiment}/{args.component}/{args.event} in mesh {args.mesh!r} (Ctrl-C to stop)",
                  file=sys.stderr, flush=True)
        deadline = time.monotonic() + args.duration if args.duration else None
        for _ in range(1_000_000):  # bounded; each round ends on a signal, the count or the duration
            left = None if deadline is None else deadline - time.monotonic()
            if (left is not None and left <= 0) or stop.wait(left) is not None:
                break
            with lock:
                if args.count and seen[0] >= args.count:
                    break
    return ExitCode.OK


def hz_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Print, every second, the rate of what is published on KEY (average rate, min, max and "
                     "standard deviation of the period, over the last --window periods), as ros2 topic hz "
                     "does; a final report at the end. Exit 1 when fewer than two messages came.")
    p.add_argument("key", metavar="KEY", help=KEYS_HELP)
    p.add_argument("--window", "-w", type=int, default=10_000, help="periods the statistics cover (default: %(default)s)")
    p.add_argument("--per-key", action="store_true", help="one rate per key rather than one for the whole expression")
    p.add_argument("--count", type=int, default=0, help="stop after this many messages")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    p.add_argument("--liveliness", action="store_true", help="count liveliness tokens appearing and going (automatic "
                                                              "when a chunk of KEY starts with @, but @outcome)")
    mesh_options(p)


def cmd_hz(args: argparse.Namespace) -> int:
    if args.window < 1 or args.count < 0 or args.duration < 0:
        raise ConfigError("--window must be at least 1, --count and --duration at least 0")
    stop = Stopper()
    expression = tap.resolve(args.mesh, args.key)
    hz = tap.Hz(args.window, per_key=args.per_key)
    done = threading.Event()
    shown: dict[str, int] = {}

    def on_seen(seen: tap.Seen) -> None:
        if done.is_set():
            return
        if hz.add(seen, expression) >= (args.count or sys.maxsize):
            done.set()
            stop.stop()

    def report(final: bool = False) -> None:
        for name, stats in hz.report().items():
            if not final and shown.get(name) == stats["count"]:
                continue  # nothing new on it since the last report
            shown[name] = stats["count"]
            if args.json:
                print(json.dumps({"key": name, **stats, **({"final": True} if final else {})}), flush=True)
            else:
                print(tap.format_rate(name, stats, with_name=args.per_key or final), flush=True)

    with session(args) as client, tap.Tap(client.transport, expression, on_seen, liveliness=args.liveliness or None):
        print(f"rate of {expression} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        run_until(stop, done, args.duration, 1.0, report)
    if not hz.report():
        print(f"error: fewer than two messages on {expression}: no rate", file=sys.stderr)
        return ExitCode.FAILED
    report(final=True)
    return ExitCode.OK


def echo_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Print what is published on KEY: mesh messages (events, storage values and changes...) "
                     "decoded, anything else raw (UTF-8 text, or hex); liveliness tokens as they appear and go.")
    p.add_argument("key", metavar="KEY", help=KEYS_HELP)
    p.add_argument("--count", type=int, default=0, help="stop after exactly this many messages")
    p.add_argument("--once", action="store_true", help="stop after the first message (--count 1)")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    p.add_argument("--raw", action="store_true", help="never decode: show every payload raw")
    p.add_argument("--liveliness", action="store_true",
                   help="watch liveliness tokens (automatic when a chunk of KEY starts with @, but @outcome)")
    mesh_options(p)


def cmd_echo(args: argparse.Namespace) -> int:
    if args.count < 0 or args.duration < 0:
        raise ConfigError("--count and --duration must be at least 0")
    stop = Stopper()
    expression = tap.resolve(args.mesh, args.key)
    printer = tap.Printer(as_json=args.json, raw=args.raw)
    count = 1 if args.once else args.count
    done = threading.Event()
    lock = threading.Lock()
    seen_so_far = [0]

    def on_seen(seen: tap.Seen) -> None:
        with lock:  # exactly --count, however many arrive before the main thread stops
            if done.is_set():
                return
            seen_so_far[0] += 1
            printer.show(seen)
            if count and seen_so_far[0] >= count:
                done.set()
                stop.stop()

    with session(args) as client, tap.Tap(client.transport, expression, on_seen, liveliness=args.liveliness or None):
        if not args.json:
            print(f"echo of {expression} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        run_until(stop, done, args.duration)
    return ExitCode.OK


def run_until(stop: Stopper, done: threading.Event, duration: float, every: float | None = None,
              tick: Callable[[], None] | None = None) -> None:
    """Wait for a signal, ``done`` or ``duration`` seconds (0: no limit), calling ``tick`` every ``every`` s."""
    now = time.monotonic()
    deadline = now + duration if duration else None
    next_tick = now + every if every else None
    for _ in range(10_000_000):  # bounded; each round ends on a signal, ``done``, a tick or the deadline
        now = time.monotonic()
        if done.is_set() or (deadline is not None and now >= deadline):
            return
        if next_tick is not None and tick is not None and now >= next_tick:
            tick()
            next_tick += every or 1.0
        ends = [t for t in (deadline, next_tick) if t is not None]
        if stop.wait(max(0.0, min(ends) - now) if ends else None) is not None:
            return
