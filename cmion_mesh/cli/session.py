"""The zenoh session and the client every one-shot mesh command opens."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator

import msgspec

from cmion_mesh.cli.common import transport_config
from cmion_mesh.client import MeshClient
from cmion_mesh.transport.zenoh import ZenohTransport

NO_WAIT_ON_OPEN = ("open/return_conditions/connect_scouted", "false")


@contextlib.contextmanager
def session(args: argparse.Namespace, name: str | None = None) -> Iterator[MeshClient]:
    """A zenoh session and a ``MeshClient`` on it, both closed on the way out."""
    config = transport_config(args, name)
    # zenoh's open would wait up to its scouting delay (0.5 s) for the peers it scouts; the client's
    # join waits for exactly what the command needs instead.
    config = msgspec.structs.replace(config, overrides=(*config.overrides, NO_WAIT_ON_OPEN))
    with ZenohTransport(config) as transport, MeshClient(transport, args.mesh) as client:
        yield client
