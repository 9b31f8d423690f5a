"""``cmion-mesh up`` daemons for the benchmarks: configurations, starting, stopping, /proc readings.

Every daemon listens only on ``tcp/127.0.0.1:<port>``, connects only to the endpoints it is given,
has multicast scouting off and keeps its migration records in a temporary ``--state-dir`` (never
the user's own). The repository is put on ``PYTHONPATH`` so that a daemon can import
``bench.competencies`` and ``bench.minds`` whatever the working directory.
"""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

from bench.harness import REPO_ROOT, loopback_config, loopback_endpoint
from cmion_mesh.client import MeshClient
from cmion_mesh.procs import Daemon, cli_argv
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.zenoh import ZenohTransport

EMBODIMENT = Path(__file__).resolve().parent / "embodiment"
RULES = EMBODIMENT / "rules.xml"
LIBRARY = EMBODIMENT / "library.xml"
CLK_TCK = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")


#: Where the processes a benchmark starts keep cmion_mesh's compiled bytecode (gitignored).
PYCACHE = REPO_ROOT / "bench" / "results" / "pycache"


def bench_env() -> dict[str, str]:
    """The environment of the processes a benchmark times the start of: the repository importable,
    and bytecode cached, as an installed package has it (``pip install`` compiles it). Without
    this, an environment with ``PYTHONDONTWRITEBYTECODE`` set compiles every module at every start,
    which about doubles the import time of a daemon or a one-shot command; zenoh, installed, never
    pays that. The cache lives outside the source tree (``PYTHONPYCACHEPREFIX``)."""
    path = os.pathsep.join(p for p in (str(REPO_ROOT), os.environ.get("PYTHONPATH", "")) if p)
    return {"PYTHONPATH": path, "PYTHONPYCACHEPREFIX": str(PYCACHE), "PYTHONDONTWRITEBYTECODE": ""}


def client_config(*connect: str) -> TransportConfig:
    """A peer that listens nowhere and connects to each of ``connect`` (loopback endpoints only)."""
    for endpoint in connect:
        if not endpoint.startswith("tcp/127.0.0.1:"):
            raise ValueError(f"benchmarks use loopback only, not {endpoint!r}")
    return TransportConfig(connect=tuple(connect), multicast=False, overrides=(("listen/endpoints", "[]"),))


def write_config(folder: Path, name: str, *, minds: Sequence[str] = ("bench.minds:TimingMind", "bench.minds:CarryMind")) -> Path:
    """An ArchitectureConfiguration for embodiment ``name`` with the bench rules, library and minds."""
    folder.mkdir(parents=True, exist_ok=True)
    config = folder / "ArchitectureConfiguration.xml"
    components = "".join(f'  <ArchitectureComponent ClassName="{m}"/>\n' for m in minds)
    config.write_text(
        f'<ArchitectureConfiguration Embodiment="{name}" CompetencyManagerRulesFile="{RULES}"'
        f' CompetencyLibraryConfigurationFile="{LIBRARY}">\n{components}</ArchitectureConfiguration>\n')
    return config


class Stamped(Daemon):
    """A ``Daemon`` that also notes when (``time.perf_counter``) each output line arrived."""

    def __init__(self, argv: Sequence[str], *, env: dict[str, str] | None = None, name: str = "") -> None:
        self.stamps: list[tuple[float, str]] = []
        self.spawned = time.perf_counter()
        super().__init__(argv, env=env, name=name)

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            line = raw.rstrip("\n")
            self.stamps.append((time.perf_counter(), line))
            self.lines.append(line)
            self._queue.put(line)
        self._queue.put(None)

    def stamp_of(self, needle: str) -> float | None:
        for stamp, line in list(self.stamps):
            if needle in line:
                return stamp
        return None


@dataclass
class Node:
    """One daemon: its name, endpoint and state folder; ``start`` spawns ``cmion-mesh up``."""

    name: str
    mesh: str
    workdir: Path
    listen: str = ""
    connect: tuple[str, ...] = ()
    companion: str | None = None
    architecture: str | None = None  # a shipped embodiment (e.g. "robot") instead of the bench config
    extra_env: dict[str, str] | None = None
    launcher: tuple[str, ...] | None = None  # replaces ``python -m cmion_mesh.cli.main`` (e.g. a tracing wrapper)
    extra_args: tuple[str, ...] = ()  # more ``cmion-mesh up`` arguments (e.g. ``--config FILE``)
    daemon: Stamped | None = None

    def __post_init__(self) -> None:
        self.listen = self.listen or loopback_endpoint()

    def argv(self) -> list[str]:
        config = self.architecture or str(write_config(self.workdir / "config", self.name))
        args = ["up", config, "--name", self.name, "--mesh", self.mesh, "--listen", self.listen, "--no-multicast",
                "--state-dir", str(self.workdir / "state")]
        for endpoint in self.connect:
            args += ["--connect", endpoint]
        if self.companion:
            args += ["--companion", self.companion]
        args += self.extra_args
        return [*self.launcher, *args] if self.launcher else cli_argv(*args)

    def start(self) -> Stamped:
        argv = self.argv()
        self.daemon = Stamped(argv, env={**bench_env(), **(self.extra_env or {})}, name=self.name)
        return self.daemon

    def wait_up(self, timeout: float = 60.0) -> float:
        """Wait for the daemon's "up in mesh" line; returns when it arrived (perf_counter)."""
        assert self.daemon is not None
        self.daemon.wait_line("up in mesh", timeout)
        stamp = self.daemon.stamp_of("up in mesh")
        assert stamp is not None
        return stamp

    @property
    def pid(self) -> int:
        assert self.daemon is not None
        return self.daemon.proc.pid


def stop_and_report(nodes: Iterable[Node], log: Callable[[str], None]) -> None:
    """``stop_all`` for an ``ExitStack`` callback: problems are logged, not raised."""
    for problem in stop_all(nodes):
        log(problem)


def up_with_client(stack: ExitStack, node: Node, log: Callable[[str], None]) -> MeshClient:
    """``node`` started and up (stopped, problems logged, when ``stack`` closes) and a client
    connected to it alone that has seen its embodiment."""
    node.start()
    stack.callback(stop_and_report, [node], log)
    node.wait_up(60.0)
    transport = ZenohTransport(loopback_config(connect=node.listen))
    stack.callback(transport.close)
    client = MeshClient(transport, node.mesh)
    stack.callback(client.close)
    client.wait_for_embodiment(node.name, timeout=20.0)
    return client


def stop_all(nodes: Iterable[Node], grace: float = 10.0) -> list[str]:
    """SIGTERM every running daemon at once, then wait for each (SIGKILL after ``grace``).

    Returns a line per daemon that did not stop cleanly (exit code and the end of its output).
    """
    daemons = [n.daemon for n in nodes if n.daemon is not None]
    for d in daemons:
        if d.proc.poll() is None:
            try:
                d.proc.send_signal(signal.SIGTERM)
            except ProcessLookupError:
                pass
    problems: list[str] = []
    deadline = time.monotonic() + grace
    for d in daemons:
        try:
            d.proc.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            d.kill()
            problems.append(f"{d.name}: killed after {grace:g} s")
            continue
        d._reader.join(5.0)
        code = d.proc.returncode
        if code != 0:
            tail = " | ".join(d.lines[-5:])
            problems.append(f"{d.name}: exit {code}: {tail}")
    return problems


# --- /proc ------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ProcSample:
    at: float  # time.monotonic()
    cpu_s: float  # utime + stime of the whole process (all threads, also those that ended), seconds; 1/CLK_TCK steps
    run_s: float  # time on CPU of the threads alive now (sum of /proc/<pid>/task/*/schedstat), ns precision
    rss_mb: float  # VmRSS, MiB
    threads: int


def _task_run_seconds(pid: int) -> float:
    total = 0
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return 0.0
    for tid in tasks:
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                total += int(f.read().split()[0])
        except (OSError, ValueError, IndexError):
            pass  # the thread ended meanwhile
    return total / 1e9


def proc_sample(pid: int) -> ProcSample:
    """CPU time, resident memory and thread count of ``pid`` from ``/proc`` (Linux)."""
    at = time.monotonic()
    with open(f"/proc/{pid}/stat") as f:
        stat = f.read()
    run_s = _task_run_seconds(pid)
    # the command name (field 2) may hold spaces: split after its closing parenthesis
    fields = stat[stat.rindex(")") + 2:].split()
    utime, stime = int(fields[11]), int(fields[12])
    rss_kb = 0
    threads = 0
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                rss_kb = int(line.split()[1])
            elif line.startswith("Threads:"):
                threads = int(line.split()[1])
    return ProcSample(at, (utime + stime) / CLK_TCK, run_s, rss_kb / 1024.0, threads)


def cpu_percent(first: ProcSample, last: ProcSample) -> float:
    """CPU used between two samples as a percentage of one core: from the threads' schedstat
    (precise) when the process kept the same number of threads, else from utime + stime."""
    wall = last.at - first.at
    if wall <= 0:
        return 0.0
    used = last.run_s - first.run_s if first.threads == last.threads and last.run_s >= first.run_s else last.cpu_s - first.cpu_s
    return 100.0 * used / wall


class Sampler:
    """Samples processes every ``interval`` seconds on a thread, until ``stop``."""

    def __init__(self, pids: dict[str, int], interval: float = 1.0) -> None:
        self.pids = pids
        self.interval = interval
        self.samples: dict[str, list[ProcSample]] = {name: [] for name in pids}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-sampler", daemon=True)

    def start(self) -> Sampler:
        self.take()
        self._thread.start()
        return self

    def take(self) -> None:
        for name, pid in self.pids.items():
            try:
                self.samples[name].append(proc_sample(pid))
            except (OSError, ValueError, IndexError):
                pass  # exited

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self.take()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.take()
