"""``cmion-mesh router``: a zenoh router, so that embodiments beyond one LAN join one mesh.

Peers find each other by multicast scouting only on their own LAN (multicast does not cross IP
routers). A zenoh router that every LAN can reach over TCP forwards between them: peers
``--connect`` to it, and routers can ``--connect`` to each other to chain sites. The router
holds no cmion state and does not know the mesh names: it routes every key.

Why ``--lan``: since zenoh 1.9 a router puts all the peers connected to it in one region that
it assumes fully connected, and never forwards between two of its peers (the old
``peers_failover_brokering`` is gone). Peers on two different LANs cannot connect to each
other, so the router must know they are in different regions. It does so by interface: the
peers that reach the router through one network interface form one LAN (a zenoh *south
subregion*), and the router forwards between LANs, as it does between its clients, its peers
and other routers. By default every interface of the host is a LAN of its own, which is right
for a host with one interface per LAN; peers arriving by any other interface form one more.

It goes through the transport layer (``ZenohTransport`` in router mode, the regions as config
overrides) like every other process, so ``transport.zenoh`` stays the only module that imports
zenoh. Run it as ``cmion-mesh router ...``.
"""

from __future__ import annotations

import json
import socket
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from cmion_mesh.errors import ExitCode, MeshError, exit_code
from cmion_mesh.signals import Stopper
from cmion_mesh.transport.base import TransportConfig

DEFAULT_LISTEN = "tcp/0.0.0.0:7447"
READY = "router up"
#: Only peers and clients are sorted into LANs: a router matched by no filter stays "north",
#: a router-to-router link, which is what chaining with --connect needs.
_SOUTH_MODES = ["peer", "client"]


def host_interfaces() -> list[str]:
    """This host's network interfaces except loopback, as the kernel names them."""
    return [name for _, name in socket.if_nameindex() if name != "lo"]


def gateway_south(lans: Sequence[str]) -> list[dict[str, Any]]:
    """zenoh's ``gateway/south``: one subregion per LAN interface, then one for every other way in.

    The catch-all keeps peers that arrive by an interface not listed (loopback, one that came up
    later) in the mesh: without it, they would match no subregion and zenoh would refuse them.
    """
    regions: list[dict[str, Any]] = [{"filters": [{"modes": _SOUTH_MODES, "interfaces": [lan]}]} for lan in lans]
    regions.append({"filters": [{"modes": _SOUTH_MODES}]})
    return regions


@dataclass(frozen=True, slots=True)
class RouterOptions:
    """How to run the router. ``lans``: the interfaces whose peers form one LAN each; empty means
    every interface of this host (``host_interfaces``); None leaves zenoh's regions as they are."""

    listen: tuple[str, ...] = (DEFAULT_LISTEN,)
    connect: tuple[str, ...] = ()
    config_file: str | None = None
    multicast: bool = True
    multicast_interface: str | None = None
    lans: tuple[str, ...] | None = ()

    def lan_interfaces(self) -> list[str] | None:
        """The LAN interfaces to configure, or None to leave zenoh's regions alone."""
        if self.lans is None:
            return None
        return list(dict.fromkeys(self.lans or host_interfaces()))


def transport_config(options: RouterOptions) -> TransportConfig:
    lans = options.lan_interfaces()
    # The whole "gateway" object: zenoh refuses to insert below it while "south" is unset (null).
    overrides = () if lans is None else (("gateway", json.dumps({"south": gateway_south(lans)})),)
    return TransportConfig(
        mode="router",
        listen=options.listen or (DEFAULT_LISTEN,),
        connect=options.connect,
        config_file=options.config_file,
        multicast=options.multicast,
        multicast_interface=options.multicast_interface,
        overrides=overrides,
    )


def run(options: RouterOptions, stop: threading.Event | None = None) -> int:
    """Run until SIGINT/SIGTERM (or ``stop`` is set): 0 after a clean close, 1 if it cannot start."""
    from cmion_mesh.transport.zenoh import ZenohTransport  # lazy: the CLI builds its parser without zenoh

    # Signals are blocked before the session's threads start, then collected by the main thread.
    stopper = Stopper() if stop is None else None
    try:
        config = transport_config(options)
        lans = options.lan_interfaces()
        missing = sorted(set(lans or ()) - {name for _, name in socket.if_nameindex()})
        if missing:  # not fatal: an interface may come up later (a VPN)
            print(f"warning: no interface named {', '.join(missing)} on this host (yet)", file=sys.stderr, flush=True)
        with ZenohTransport(config) as transport:
            parts = [f"{READY}, listening on {', '.join(config.listen)}"]
            if config.connect:
                parts.append(f"connecting to {', '.join(config.connect)}")
            parts.append("zenoh's regions" if lans is None else f"LANs: {', '.join(lans) or '(none)'} (+ any other way in)")
            parts.append("multicast scouting on" if config.multicast else "no multicast scouting")
            print(f"{'; '.join(parts)} (zenoh id {transport.id})", flush=True)
            if stopper is not None:
                stopper.wait()
            else:
                assert stop is not None
                stop.wait()
    except MeshError as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return exit_code(exc)
    print("router stopped", flush=True)
    return ExitCode.OK
