"""A mesh client in a process of its own, for tests whose mesh lives inside network namespaces.

The test process stays in the caller's namespace, so it cannot open a zenoh session with daemons
inside the namespaces; it runs this probe inside one (``host.popen([sys.executable, "-m",
"tests.helpers.mesh_probe", SPEC])``) and talks to it through a FIFO on the shared file system:

* ``SPEC`` (JSON): ``mesh``; ``connect`` (endpoints); ``multicast`` and ``interface`` (scouting);
  ``gossip`` (false keeps the session to its own endpoints: no auto-connection to the peers the
  others tell of); ``watch`` (embodiment names sampled continuously) and ``interval`` (seconds
  between two rounds of samples); ``fifo`` (path of the command FIFO, created by the test).
* Output, one line each: ``READY {...}`` once the session is open, ``S {...}`` per sample
  (``name``, ``inhabitant`` or null, or ``"?"`` when no answer, and ``t0``/``t1``: the
  ``time.monotonic()`` before sending and after the answer, a clock all processes share),
  ``E {...}`` per describe that got no answer (why), and ``R {...}`` per command (``id``,
  ``ok``, ``value`` or ``error``).
* Commands, one JSON line each on the FIFO: ``{"id", "op", ...}`` with ``op`` one of
  ``request`` (``embodiment``, ``component``, ``name``, ``payload``: for ``migration/migrate``
  ``{"companion", "target"}``, else a ``mind_message``'s data), ``migrate`` (``companion``,
  ``target``, ``timeout``: ``MeshClient.migrate``), ``memory`` (``embodiment``: the Diary mind's
  state), ``inhabitants`` (``names``: each one's inhabitant, as sampled), ``embodiments`` and
  ``quit``.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from typing import Any

import msgspec

from cmion_mesh.client import MeshClient
from cmion_mesh.errors import MeshError
from cmion_mesh.messages import Message, Migrate, MindMessage, MindState
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

_print_lock = threading.Lock()


def emit(tag: str, data: dict[str, Any]) -> None:
    with _print_lock:
        print(f"{tag} {json.dumps(data)}", flush=True)


def inhabitant(client: MeshClient, name: str, timeout: float = 1.0) -> Any:
    """The companion ``name`` says it hosts (None when empty), or ``"?"`` when it does not answer."""
    t0 = time.monotonic()
    try:
        return client.describe(name, timeout=timeout).get("inhabitant")
    except MeshError as exc:
        emit("E", {"name": name, "error": str(exc), "t0": t0, "t1": time.monotonic()})  # why, for the test's messages
        return "?"


def sample(client: MeshClient, names: list[str], interval: float, stop: threading.Event) -> None:
    """Describe each watched embodiment in turn, forever: one ``S`` line per answer (or silence)."""
    while not stop.is_set():
        for name in names:
            t0 = time.monotonic()
            # Patient: a daemon may not answer for a moment (about a second, under load) while its
            # zenoh session gives up a peer whose lease expired; a late answer is still an answer.
            found = inhabitant(client, name, 3.0)
            emit("S", {"name": name, "inhabitant": found, "t0": t0, "t1": time.monotonic()})
        stop.wait(interval)


def execute(client: MeshClient, command: dict[str, Any]) -> Any:
    op = command["op"]
    if op == "request":
        payload: Any = command.get("payload") or {}
        message: Message = (Migrate(payload["companion"], payload["target"]) if (command["component"], command["name"]) ==
                            ("migration", "migrate") else MindMessage(payload))
        outcome = client.request(command["embodiment"], command["component"], command["name"], message,
                                 timeout=float(command.get("timeout", 5.0)))
        return msgspec.to_builtins(outcome)
    if op == "migrate":
        return client.migrate(command["companion"], command["target"], timeout=float(command.get("timeout", 30.0)))
    if op == "memory":
        outcome = client.request(command["embodiment"], "mind", "state", MindState(), timeout=5.0)
        if outcome.status != "accepted" or not isinstance(outcome.value, dict):
            raise MeshError(f"mind state of {command['embodiment']}: {outcome.status} {outcome.reason}")
        return outcome.value
    if op == "inhabitants":
        return {name: inhabitant(client, name, float(command.get("timeout", 5.0))) for name in command["names"]}
    if op == "embodiments":
        return client.embodiments(timeout=float(command.get("timeout", 1.0)))
    raise ValueError(f"unknown op {op!r}")


def main(spec: dict[str, Any]) -> int:
    overrides: list[tuple[str, str]] = [("listen/endpoints", "[]")]  # a client: nobody needs to reach it
    if not spec.get("gossip", True):
        overrides.append(("scouting/gossip/enabled", "false"))
    config = TransportConfig(connect=tuple(spec.get("connect", ())), multicast=bool(spec.get("multicast", False)),
                             multicast_interface=spec.get("interface"), overrides=tuple(overrides))
    # O_RDWR: opening never waits for a writer, and reading never sees end-of-file between writers.
    fifo = os.fdopen(os.open(spec["fifo"], os.O_RDWR), "r", encoding="utf-8")
    stop = threading.Event()
    with ZenohTransport(config) as transport:
        client = MeshClient(transport, spec["mesh"])
        sampler = threading.Thread(target=sample, args=(client, list(spec.get("watch", [])), float(spec.get("interval", 0.02)), stop),
                                   name="sampler", daemon=True)
        sampler.start()
        emit("READY", {"zid": transport.id})
        try:
            for line in fifo:
                command = json.loads(line)
                if command.get("op") == "quit":
                    break
                try:
                    emit("R", {"id": command["id"], "ok": True, "value": execute(client, command)})
                except Exception as exc:  # reported to the test, which decides
                    emit("R", {"id": command["id"], "ok": False, "error": f"{type(exc).__name__}: {exc}"})
        finally:
            stop.set()
            sampler.join(5.0)
    return 0


if __name__ == "__main__":
    sys.exit(main(json.loads(sys.argv[1])))
