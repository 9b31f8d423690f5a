"""``cmion-mesh demo``: the Spirit of the Building, end to end.

Three embodiments, each a daemon in its own process, find each other on the mesh: the robot
(where the companion "spirit" lives), the screen at the building entrance and a phone, all
empty but the robot. The operator types "greet Guest" on the robot's console; the command
reaches the companion's mind through the world model; the mind plans: migrate to the screen,
ask the person there whether they are the guest, greet them, migrate to the phone to accompany
them, and come back home to the robot, carrying its memory of the visit all the way.

The demo plays the world: the guest is at the entrance when the companion arrives there and
answers the question with a "yes" gesture. It prints a timeline and ends by itself.

``demo --web``: the screen and the phone serve their pages (``web.body``) and a live view of the
mesh runs (``view``), on free loopback ports whose addresses it prints; nobody plays the guest: a
person at the screen's page says "I am here" and answers "yes" (or "no"), and watches the companion
go on to the phone's page. The daemons keep running after the story, for a look at the pages, until
Ctrl-C or SIGTERM; either way the demo stops its daemons (they live in sessions of their own).
A signal before the story's end stops it too (exit 130 for SIGINT, 143 for SIGTERM), even in a
background job that inherited SIGINT ignored.
"""

from __future__ import annotations

import contextlib
import os
import queue
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cmion_mesh import keys
from cmion_mesh.client import MeshClient
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.messages import Event, MindState
from cmion_mesh.procs import Daemon, cli_argv, free_port, unique_mesh, wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

if TYPE_CHECKING:
    from cmion_mesh.tools.recording import Recorder

BODIES = ("robot", "screen", "phone")
COMPANION = "spirit"
GUEST = "Guest"


class Timeline:
    def __init__(self, out: Callable[[str], None] = print) -> None:
        self.t0 = time.monotonic()
        self.out = out

    def say(self, text: str) -> None:
        self.out(f"[{time.monotonic() - self.t0:6.2f} s] {text}")


@dataclass
class Hop:
    """One arrival of the companion: where, and its mind's state right after."""

    embodiment: str
    epoch: int
    mind: dict[str, Any]


@dataclass
class Scenario:
    """The running demo: daemons, a client, and what happened."""

    mesh: str
    endpoints: dict[str, str]
    daemons: dict[str, Daemon] = field(default_factory=dict)
    hops: list[Hop] = field(default_factory=list)


def start_bodies(mesh: str, state: Path, *, extra: tuple[str, ...] = (), per_body: dict[str, tuple[str, ...]] | None = None,
                 die_with_parent: bool = False) -> Scenario:
    """The three daemons, each with ``extra`` arguments and its own from ``per_body``;
    ``die_with_parent``: they get SIGTERM if this process dies, even SIGKILLed (``procs.child_setup``)."""
    ports = {name: free_port() for name in BODIES}
    scenario = Scenario(mesh, {name: f"tcp/127.0.0.1:{port}" for name, port in ports.items()})
    try:
        for name in BODIES:
            argv = ["up", name, "--mesh", mesh, "--listen", scenario.endpoints[name], "--no-multicast",
                    "--state-dir", str(state / name), *extra, *(per_body or {}).get(name, ())]
            for other in BODIES:
                if other != name:
                    argv += ["--connect", scenario.endpoints[other]]
            scenario.daemons[name] = Daemon(cli_argv(*argv), name=name, die_with_parent=die_with_parent)
        for daemon in scenario.daemons.values():
            daemon.wait_line("up in mesh", 30)
    except BaseException:
        stop_bodies(scenario)
        raise
    return scenario


def web_address(daemon: Daemon, timeout: float = 30.0) -> str:
    """The address of the page a daemon started with ``--web`` serves (it prints it before it is up)."""
    line = daemon.wait_line("web body of", timeout)
    return line.split(" at ", 1)[1].split()[0]


def stop_bodies(scenario: Scenario) -> None:
    # All told at once, then each waited for: they stop side by side, not one after the other.
    for daemon in scenario.daemons.values():
        if daemon.proc.poll() is None:
            daemon.proc.send_signal(signal.SIGTERM)
    for daemon in scenario.daemons.values():
        daemon.stop()


def mind_state(client: MeshClient, embodiment: str) -> dict[str, Any]:
    value = client.request(embodiment, "mind", "state", MindState(), timeout=5).value
    return value if isinstance(value, dict) else {}


#: Longest the story's loop sleeps between events: a Ctrl-C (``KeyboardInterrupt``, raised when the
#: main thread next runs) must not wait for the next event while a person takes their time.
INTERRUPT_CHECK = 0.25

#: Bodies serving a page in ``demo --web``.
WEB_BODIES = ("screen", "phone")


def web_pages(scenario: Scenario, stack: contextlib.ExitStack) -> dict[str, str]:
    """The pages ``demo --web`` shows, name -> address: the bodies' own, and whatever else is
    started here for the demo's mesh (closed by ``stack``)."""
    from cmion_mesh.web.view import spawn_view

    pages = {name: web_address(scenario.daemons[name]) for name in WEB_BODIES}
    # die_with_parent, as the daemons: a SIGKILLed demo leaves no view serving behind (called from the main thread).
    view, pages["view"] = spawn_view(scenario.mesh, scenario.endpoints.values(), die_with_parent=True)
    stack.enter_context(view)
    return pages


def run_scenario(client: MeshClient, scenario: Scenario, tl: Timeline, *, timeout: float = 90.0, play: bool = True) -> None:
    """Drive the story to its end (the companion home with the guest welcomed and accompanied).
    ``play``: the demo plays the guest (present at the entrance, nodding yes); otherwise a person
    does, on the screen's page."""
    events: queue.SimpleQueue[Event] = queue.SimpleQueue()
    with client.events(events.put):
        wait_for(lambda: {d.get("name"): d.get("inhabitant") for d in client.describe_all(timeout=1.0)}
                 == {"robot": COMPANION, "screen": None, "phone": None}, 30, "the three embodiments, spirit on the robot")
        tl.say(f"robot, screen and phone found each other in mesh {scenario.mesh!r}; {COMPANION!r} lives on the robot")
        tl.say(f'operator types "greet {GUEST}" on the robot\'s console')
        client.set_property("robot", keys.BLACKBOARD, "sim", "command", f"greet {GUEST}")
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise MeshError(f"the demo did not finish within {timeout:g} s")
            try:
                event = events.get(timeout=min(left, INTERRUPT_CHECK))
            except queue.Empty:
                continue
            if _react(client, scenario, tl, event, play):
                return


def _react(client: MeshClient, scenario: Scenario, tl: Timeline, event: Event, play: bool = True) -> bool:
    """Print what matters and play the world; True once the story has ended."""
    where, data = event.embodiment, event.data if isinstance(event.data, dict) else {}
    name = event.name
    if name == "MindDecision":
        decision = data.get("decision")
        if decision == "goal_added":
            tl.say(f"{where}: the mind takes up the goal {data.get('goal')!r}")
        elif decision == "plan":
            steps = [" ".join([s.get("action", ""), *s.get("parameters", [])]) for s in data.get("steps", [])]
            tl.say(f"{where}: plan -> {' ; '.join(steps)}")
        elif decision == "goal_achieved":
            tl.say(f"{where}: goal {data.get('goal')!r} achieved")
            return where == "robot"
        elif decision in ("goal_abandoned", "goal_unreachable"):
            raise MeshError(f"{where}: goal {data.get('goal')!r} {decision}: {data.get('reason')}")
    elif name == "ActionStarted" and event.component == "manager":
        tl.say(f"{where}: action {' '.join([data.get('name', ''), *data.get('parameters', [])])}")
    elif name == "ActionFailed" and event.component == "manager":
        tl.say(f"{where}: action {data.get('name')} failed: {data.get('reason')}")
    elif name == "MigrationStarting":
        tl.say(f"{where}: migration of {data.get('companion')!r} to {data.get('target')} begins (the mind sleeps here)")
        if data.get("target") == "screen" and play:
            tl.say(f"   (a visitor is standing at the entrance: the screen's camera will see {GUEST})")
            client.set_property("screen", keys.BLACKBOARD, "sim", "userPresent", GUEST)
        elif data.get("target") == "screen":
            tl.say(f"   (at the screen's page: say \"I am here\" as {GUEST}, and answer its question)")
    elif name == "MigrationOccurred":
        state = mind_state(client, where)
        scenario.hops.append(Hop(where, int(data.get("epoch", 0)), state))
        memory = state.get("memory", [])
        tl.say(f"{where}: {data.get('companion')!r} arrived (epoch {data.get('epoch')}), mind awake with "
               f"{len(memory)} memories")
    elif name == "MigrationSucceeded":
        tl.say(f"{where}: handed over to {data.get('target')}; nothing of {data.get('companion')!r} runs here any more")
    elif name == "StepStarted" and data.get("type") == "GestureDetect" and play:
        tl.say(f"{where}: asks {GUEST} whether they are the guest; {GUEST} nods: yes")
        client.set_property(where, keys.BLACKBOARD, "sim", "gesture", "yes")
    elif name == "StepStarted" and data.get("type") == "GestureDetect":
        tl.say(f"{where}: asks {GUEST} whether they are the guest: answer yes or no on the {where}'s page")
    elif name == "RemoteAction" and data.get("name") == "Gesture" and not play:
        tl.say(f"{where}: {data.get('subject')} answered {' '.join(data.get('parameters', []))}")
    elif name == "Spoke":
        tl.say(f"{where} says: {data.get('text')!r}")
    return False


def _record(client: MeshClient, path: str, stack: contextlib.ExitStack) -> Recorder:
    """A recorder of the demo's mesh, closed by ``stack`` at the latest, with the three bodies
    described in its file. Describing them also joins: their answers come after they learnt of
    the recorder's subscriptions (one link, in order), so nothing of the story is missed."""
    from cmion_mesh.tools.recording import Recorder

    recorder = stack.enter_context(Recorder(client.transport, client.mesh, path, overwrite=False))
    described: list[dict[str, Any]] = []

    def all_described() -> bool:
        described[:] = client.describe_all(timeout=1.0)
        return len(described) == len(BODIES)

    wait_for(all_described, 30, "the three embodiments described")
    recorder.describe(described)
    return recorder


def attach_commands(mesh: str, endpoint: str, *, foxglove: bool | None = None, recording: str | None = None) -> list[str]:
    """What ``demo --web`` prints so that tools in another terminal join its mesh: the demo's daemons
    scout nobody (a mesh of their own), so a tool connects to one of them, which brings the rest.
    The recording's name is not the demo's own ``recording`` (``record`` refuses a file that exists); the ``foxglove``
    line only where Foxglove's SDK is installed (``foxglove``: None looks), else how to install it."""
    import importlib.util

    join = f"--mesh {mesh} --no-multicast --connect {endpoint}"
    output = "attach.mcap" if recording is None or Path(recording).name != "attach.mcap" else "attach-2.mcap"
    if foxglove is None:
        foxglove = importlib.util.find_spec("foxglove") is not None
    if foxglove:
        live = f"  cmion-mesh foxglove {join}"
    else:
        from cmion_mesh.tools.foxglove import INSTALL_HINT

        live = f"  (cmion-mesh foxglove, the mesh live in Foxglove, needs Foxglove's SDK: {INSTALL_HINT})"
    return ["attach from another terminal:",
            f"  cmion-mesh record {join} -o {output}",
            f"  cmion-mesh view {join} --web 127.0.0.1:8091",
            live,
            f"  cmion-mesh peers {join}"]


#: The demo's daemons keep their state in a temporary folder named with the demo's process id: a
#: demo that could not remove its own (SIGKILLed) leaves it to the next one (``remove_stale_state``).
STATE_PREFIX = "cmion-demo-"


def remove_stale_state(where: str | None = None) -> list[Path]:
    """Remove the state folders of demos that are gone (their process id in the name no longer
    runs); return them. Folders of running demos, of other users, or not named so are left."""
    removed: list[Path] = []
    for folder in Path(where or tempfile.gettempdir()).glob(f"{STATE_PREFIX}*-*"):
        pid = folder.name[len(STATE_PREFIX):].split("-", 1)[0]
        if not pid.isdigit() or not folder.is_dir() or folder.stat().st_uid != os.getuid():
            continue
        try:
            os.kill(int(pid), 0)
            continue  # that demo still runs
        except ProcessLookupError:
            pass
        except PermissionError:  # another user's process
            continue
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(folder)
    return removed


def run_demo(*, mesh: str | None = None, web: bool = False, wait: Callable[[], object] | None = None,
             record: str | None = None) -> int:
    """Run the demo in ``mesh`` (default: a mesh of its own, so that it never meets other daemons).
    ``web``: with the pages (see the module's doc); ``wait`` blocks until the person is done looking
    (the command line's Ctrl-C); ``record``: an MCAP file to record the demo's mesh into (``record``)."""
    tl = Timeline()
    mesh = mesh if mesh and mesh != keys.DEFAULT_MESH else unique_mesh("demo")
    if record is not None and Path(record).exists():  # refused before any daemon starts
        raise ConfigError("exists already: not overwritten (another name)", path=record)
    serve = ("--web", "127.0.0.1:0")
    remove_stale_state()
    with tempfile.TemporaryDirectory(prefix=f"{STATE_PREFIX}{os.getpid()}-") as state, contextlib.ExitStack() as stack:
        tl.say(f"starting three embodiment daemons (robot, screen, phone) in mesh {mesh!r}")
        # From the main thread, which lives as long as the demo: a SIGKILLed demo leaves no daemon behind.
        scenario = start_bodies(mesh, Path(state), per_body=dict.fromkeys(WEB_BODIES, serve) if web else None, die_with_parent=True)
        try:
            config = TransportConfig(connect=tuple(scenario.endpoints.values()), multicast=False)
            with ZenohTransport(config) as transport:
                client = MeshClient(transport, mesh)
                if record is not None:
                    recorder = _record(client, record, stack)
                    tl.say(f"recording mesh {mesh!r} to {record}")
                if web:
                    for name, address in web_pages(scenario, stack).items():
                        tl.say(f"{name}: {address}")
                    for line in attach_commands(mesh, scenario.endpoints["robot"], recording=record):
                        tl.say(line)
                    if sys.stdin.isatty():
                        input("open the screen's page, then press Enter: the operator types the command ")
                run_scenario(client, scenario, tl, play=not web, timeout=900.0 if web else 90.0)
                final = mind_state(client, "robot")
                kinds: dict[str, int] = {}
                for episode in final.get("memory", []):
                    kinds[episode.get("kind", "?")] = kinds.get(episode.get("kind", "?"), 0) + 1
                guest = final.get("beliefs", {}).get(GUEST, {})
                facts = ", ".join(k for k in ("confirmed", "welcomed", "accompanied") if guest.get(k))
                episodes = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items()))
                tl.say(f"back on the robot; it remembers the visit: {GUEST} {facts}; {sum(kinds.values())} episodes ({episodes})")
                hosts = [h.embodiment for h in scenario.hops]
                tl.say(f"journey: robot -> {' -> '.join(hosts)}; exactly one embodiment inhabited at every step")
                if record is not None:
                    recorder.close()
                    stats = recorder.stats
                    tl.say(f"recorded {stats.messages} messages to {record}" + (f"; DROPPED {stats.dropped}" if stats.dropped else "")
                           + f" (cmion-mesh record info {record})")
                if web and wait is not None:
                    tl.say("the pages stay open until Ctrl-C")
                    with contextlib.suppress(KeyboardInterrupt):  # a Ctrl-C just before the wait is the same stop
                        wait()
        finally:
            tl.say("stopping the daemons")
            stop_bodies(scenario)
            if sys.exc_info()[0] in (None, KeyboardInterrupt):  # ended, or stopped by a signal: its last line
                tl.say("done")
    return 0
