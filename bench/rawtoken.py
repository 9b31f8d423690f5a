"""The raw zenoh process of the ``discovery`` and ``convergence`` benchmarks: one session, one
liveliness token, nothing else.

Deliberately imports zenoh and the standard library only: what it measures is "a Python process
joins a zenoh mesh", so it must not pay for importing cmion_mesh or the benchmark harness (it did
once, which made the raw baseline about 100 ms slower than raw). Its session gets exactly the
settings ``ZenohTransport`` would apply, computed by the parent and passed as JSON::

    python -m bench.rawtoken KEY SETTINGS_JSON PARENT_PID

It prints ``ready`` once the token is declared and runs until SIGTERM/SIGINT or its parent is gone.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading

import zenoh


def main(argv: list[str]) -> int:
    key, settings, parent = argv[0], json.loads(argv[1]), int(argv[2])
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    config = zenoh.Config()
    for name, value in settings:
        config.insert_json5(name, value)
    session = zenoh.open(config)
    try:
        token = session.liveliness().declare_token(key)
        print(f"ready token {key}", flush=True)
        while not stop.wait(1.0):  # a watchdog for an orphan, not a readiness wait
            if os.getppid() != parent:
                break
        token.undeclare()  # type: ignore[no-untyped-call]
    finally:
        session.close()  # type: ignore[no-untyped-call]
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
