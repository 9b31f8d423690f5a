"""``cmion-mesh demo``: the core walk-through, each embodiment a separate daemon process.

Starts the ``robot`` embodiment as a daemon with the CMION test world model, then, from this
process, reads its world model over the mesh, writes the blackboard, shows that a plain watcher
sees every change and that conflicting writes in one update are mediated (one wins, every
writer learns its outcome). Ends by itself and stops the daemon.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.messages import Property, SetProperty
from cmion_mesh.procs import Daemon, cli_argv, free_port, unique_mesh, wait_for
from cmion_mesh.resources import embodiment_dir
from cmion_mesh.transport import TransportConfig
from cmion_mesh.zenoh_transport import ZenohTransport


class Timeline:
    def __init__(self) -> None:
        self.t0 = time.monotonic()

    def say(self, text: str) -> None:
        print(f"[{time.monotonic() - self.t0:7.3f} s] {text}", flush=True)


def run_demo(args: argparse.Namespace) -> int:
    tl = Timeline()
    mesh = args.mesh if args.mesh != keys.DEFAULT_MESH else unique_mesh("demo")
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    wm_file = embodiment_dir("cmion_test") / "worldModelInit.xml"
    tl.say(f"mesh {mesh!r}: starting the robot embodiment daemon on {endpoint}")
    argv = cli_argv("up", "--name", "robot", "--mesh", mesh, "--listen", endpoint, "--no-multicast",
                    "--world-model", str(wm_file))
    with Daemon(argv, name="robot") as robot:
        robot.wait_line("up in mesh")
        tl.say("robot is up")
        transport = ZenohTransport(TransportConfig(connect=(endpoint,), multicast=False))
        with transport:
            client = MeshClient(transport, mesh)
            wm = wait_for(lambda: client.read_store("robot", keys.WORLD_MODEL), 10, "robot's world model over the mesh")
            tl.say(f"world model read over zenoh: {sum(1 for k in wm if '/' in k.split('/wm/', 1)[-1])} properties")
            for key, entry in wm.items():
                shown = json.dumps(entry.value) if isinstance(entry, Property) else f"[{entry.kind}]"
                print(f"          {key.split('/wm', 1)[-1] or '/':<24} {shown}")
            seen: list[str] = []
            got = threading.Event()

            def watch(key: str, entry: Any) -> None:
                seen.append(f"{key.split('/bb/', 1)[-1]} -> {getattr(entry, 'value', None)!r}")
                got.set()

            with client.watch(keys.storage_selector(mesh, "robot", keys.BLACKBOARD), watch):
                client.set_property("robot", keys.BLACKBOARD, "", "greeting", "hello, guest")
                got.wait(5)
                tl.say(f"blackboard written; a plain subscriber saw: {seen}")
                writes = [SetProperty("", "mood", m) for m in ("happy", "curious", "sleepy")]
                with ThreadPoolExecutor(3) as pool:
                    outcomes = list(pool.map(lambda w: client.write("robot", keys.BLACKBOARD, w), writes))
                for w, o in zip(writes, outcomes, strict=True):
                    tl.say(f"write mood={w.value!r}: {o.status}{' (' + o.reason + ')' if o.reason else ''}")
                final = client.get_property("robot", keys.BLACKBOARD, "", "mood")
                lost = sum(o.status == "conflict" for o in outcomes)
                tl.say(f"mood is now {final.value!r}; {lost} write(s) lost a conflict (the first write to a name in an update wins);"
                       " every writer got a definite answer")
        tl.say("stopping the robot daemon")
    tl.say("done")
    return 0
