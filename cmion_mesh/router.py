"""``cmion-mesh router``: a zenoh router, so that embodiments beyond one LAN join one mesh.

Peers find each other by multicast scouting only on their own LAN (multicast does not cross IP
routers). A zenoh router that every site can reach over TCP forwards between them: peers
``--connect`` to it, and routers can ``--connect`` to each other to chain sites. The router
holds no cmion state and does not know the mesh names: it routes every key.

It goes through the transport layer (``ZenohTransport`` in router mode) like every other
process, so ``zenoh_transport`` stays the only module that imports zenoh.

Run it as ``cmion-mesh router ...`` or ``python -m cmion_mesh.router ...``.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence
from types import FrameType

from cmion_mesh.errors import MeshError
from cmion_mesh.transport import TransportConfig

EXIT_OK, EXIT_FAILED = 0, 1
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"
READY = "router up"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the router's options; they replace the common mesh options (a router has no mesh)."""
    parser.add_argument("--listen", action="append", metavar="ENDPOINT",
                        help=f"endpoint to accept peers and routers on; repeatable (default: {DEFAULT_LISTEN})")
    parser.add_argument("--connect", action="append", metavar="ENDPOINT",
                        help="another router to connect to (chaining sites), e.g. tcp/10.0.0.5:7447; repeatable")
    parser.add_argument("--config", metavar="FILE", help="zenoh JSON5 configuration file (the options above override it)")
    parser.add_argument("--no-multicast", action="store_true",
                        help="do not answer or send multicast scouting (peers must --connect to the router)")
    parser.add_argument("--multicast-interface", metavar="IFACE",
                        help="interface for multicast scouting (default: zenoh's choice, 'auto')")


def transport_config(args: argparse.Namespace) -> TransportConfig:
    return TransportConfig(
        mode="router",
        listen=tuple(args.listen or (DEFAULT_LISTEN,)),
        connect=tuple(args.connect or ()),
        config_file=args.config,
        multicast=not args.no_multicast,
        multicast_interface=getattr(args, "multicast_interface", None),
    )


def _stop_on_signals(stop: threading.Event) -> dict[int, object]:
    """Set ``stop`` on SIGINT/SIGTERM; returns the previous handlers (to restore them)."""
    if threading.current_thread() is not threading.main_thread():
        return {}  # signal handlers can only be installed from the main thread; the caller sets stop

    def handler(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    previous: dict[int, object] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, handler)
    return previous


def run(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """Run until SIGINT/SIGTERM (or ``stop`` is set); 0 after a clean close, 1 if it cannot start."""
    from cmion_mesh.zenoh_transport import ZenohTransport  # lazy: the CLI builds its parser without zenoh

    stop = stop or threading.Event()
    # Handlers go in before the session opens, so a signal during the (slow) open is not lost.
    previous = _stop_on_signals(stop)
    config = transport_config(args)
    try:
        with ZenohTransport(config) as transport:
            connecting = f", connecting to {', '.join(config.connect)}" if config.connect else ""
            scouting = "multicast scouting on" if config.multicast else "no multicast scouting"
            print(f"{READY}, listening on {', '.join(config.listen)}{connecting}; {scouting} "
                  f"(zenoh id {transport.id})", flush=True)
            stop.wait()
    except MeshError as exc:  # the CLI would catch it too; handled here so both entry points behave alike
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return EXIT_FAILED
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)  # type: ignore[arg-type]  # whatever signal.signal returned before
    print("router stopped", flush=True)
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="cmion-mesh router", description=__doc__.splitlines()[0] if __doc__ else None)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
