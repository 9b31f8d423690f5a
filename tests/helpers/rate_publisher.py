"""A publisher at a known rate, in a process of its own, for the ``hz`` and ``echo`` tests.

``python -m tests.helpers.rate_publisher MESH ENDPOINT RATE`` listens on ENDPOINT (loopback) and, on an
absolute clock schedule (the i-th tick at start + i / RATE, so a late tick does not shift the
next ones), publishes on each tick an ``Event`` on ``cmion/MESH/pub/ev/test/Tick`` and a raw
payload on ``cmion/MESH/raw/bytes``: UTF-8 text and binary bytes in turn. It prints ``READY`` once
its session is open and runs until it is terminated.
"""

from __future__ import annotations

import sys
import threading
import time

from cmion_mesh.messages import Event, encode
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

TICK_KEY = "pub/ev/test/Tick"
RAW_KEY = "raw/bytes"
TEXT = b"plain text payload"
BINARY = b"\x00\xff\x10binary"


def main() -> None:
    mesh, endpoint, rate = sys.argv[1], sys.argv[2], float(sys.argv[3])
    with ZenohTransport(TransportConfig(listen=(endpoint,), multicast=False)) as transport:
        print("READY", flush=True)
        start = time.monotonic()
        pause = threading.Event()  # never set: its wait is the clock
        for i in range(10_000_000):
            delay = start + i / rate - time.monotonic()
            if delay > 0:
                pause.wait(delay)
            transport.publish(f"cmion/{mesh}/{TICK_KEY}", encode(Event("pub", "test", "Tick", {"i": i}, seq=i, time=time.time())))
            transport.publish(f"cmion/{mesh}/{RAW_KEY}", TEXT if i % 2 == 0 else BINARY)


if __name__ == "__main__":
    main()
