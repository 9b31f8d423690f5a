"""The daemon as a systemd service: readiness, the watchdog, stopping, and the unit file.

systemd's notification protocol (``sd_notify``) is one datagram of ``KEY=VALUE`` lines sent to the
unix socket named by ``$NOTIFY_SOCKET`` (``@name``: the abstract namespace). It is spoken here
with the standard library; without ``$NOTIFY_SOCKET`` (not run by systemd) every call does nothing.

* ``READY=1`` (with ``STATUS=``) only once the embodiment has joined the mesh, holds its name and
  its update loop turns: ``Type=notify`` makes ``systemctl start`` and the units ordered after
  this one wait until then, and a daemon refused its name never reports ready.
* ``WATCHDOG=1`` every half of ``$WATCHDOG_USEC`` (``WatchdogSec=``), and only if the update loop
  has beaten since the previous ping (``ops.heartbeat``): a loop stuck in a handler stops the
  pings, and systemd kills and restarts the daemon (``Restart=on-failure``).
* ``STOPPING=1`` when SIGTERM (or SIGINT) has been collected and the daemon starts closing.

Wiring (the daemon, ``cli`` ``_run_daemon``): one context manager around the daemon's wait, entered
right after ``with embodiment:`` (``Embodiment.start`` has returned: the claim on the name was
decided in ``Embodiment.__init__``, through ``claim.Joining.result()``, and the ``@alive`` token
is declared), exited before the embodiment closes::

    with embodiment, systemd.Service(embodiment) as service:
        ...                  # the lines ending in "up in mesh"
        stop.wait()          # SIGTERM collected here (signals.Stopper); leaving sends STOPPING=1

``cmion-mesh service unit NAME [--mesh M] [--metrics HOST:PORT] [--settings FILE] [--watchdog S]``
prints ``unit(NAME, mesh=..., metrics=..., settings=..., watchdog_sec=...)`` (``print(..., end="")``:
the text ends with a newline).
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, Self

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError
from cmion_mesh.ion import Simulation
from cmion_mesh.ops.heartbeat import PERIOD, Heartbeat
from cmion_mesh.transport.base import Handle

if TYPE_CHECKING:
    import socket

log = logging.getLogger(__name__)

#: ``WatchdogSec=`` of the unit file ``unit`` writes: a loop stuck this long is restarted.
WATCHDOG_SEC = 30
#: The account the service runs as (``DynamicUser=yes``: made by systemd while the service runs).
USER = "cmion-mesh"
#: Where ``unit`` points the daemon's settings file by default (``{name}``: the embodiment).
SETTINGS_PATH = "/etc/cmion-mesh/{name}.toml"
#: The option of ``cmion-mesh up`` naming the settings file.
SETTINGS_OPTION = "--settings"
#: How long ``Service`` waits for the update loop's first beat before it gives up reporting ready.
FIRST_BEAT_WAIT = 10.0


def _address(path: str) -> str:
    """The socket address of ``$NOTIFY_SOCKET``: a path, or ``@name`` in the abstract namespace."""
    return "\0" + path[1:] if path.startswith("@") else path


def _line(text: str) -> str:
    # One assignment per line: a newline in a status would start a field of its own.
    return " ".join(text.split())


class Notifier(Handle):
    """``sd_notify`` to ``$NOTIFY_SOCKET`` (or ``socket_path``); a no-op when neither is set.

    Thread-safe (one datagram per call); a failed send is logged once and never raised: the
    daemon runs on whether or not systemd hears it. ``close`` is idempotent.
    """

    def __init__(self, socket_path: str | None = None, *, environ: Mapping[str, str] = os.environ) -> None:
        path = socket_path if socket_path is not None else environ.get("NOTIFY_SOCKET", "")
        self.path = path or None
        self._socket: socket.socket | None = None
        self._lock = threading.Lock()
        self._warned = False
        self._closed = False
        self.sent = 0

    @property
    def enabled(self) -> bool:
        return self.path is not None

    def notify(self, *fields: str) -> bool:
        """Send ``KEY=VALUE`` fields in one datagram; whether it was sent."""
        if self.path is None or not fields:
            return False
        data = "\n".join(fields).encode()
        with self._lock:
            if self._closed:
                return False
            try:
                if self._socket is None:
                    import socket  # here: only a daemon systemd started (NOTIFY_SOCKET) needs it

                    self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._socket.sendto(data, _address(self.path))
            except OSError as exc:
                if not self._warned:
                    self._warned = True
                    log.warning("cannot notify systemd at %s: %s (said once)", self.path, exc)
                return False
            self.sent += 1
        return True

    def ready(self, status: str = "") -> bool:
        return self.notify("READY=1", *([f"STATUS={_line(status)}"] if status else []))

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={_line(text)}")

    def stopping(self, status: str = "") -> bool:
        return self.notify("STOPPING=1", *([f"STATUS={_line(status)}"] if status else []))

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def __enter__(self) -> Self:
        return self

    def close(self) -> None:
        with self._lock:
            self._closed = True
            sock, self._socket = self._socket, None
        if sock is not None:
            sock.close()


def watchdog_interval(environ: Mapping[str, str] = os.environ) -> float | None:
    """How often to ping the watchdog: half of ``$WATCHDOG_USEC``, in seconds, when systemd asks
    this process for pings (``$WATCHDOG_PID`` unset or ours, as ``sd_watchdog_enabled``); else None."""
    pid = environ.get("WATCHDOG_PID")
    if pid and pid != str(os.getpid()):
        return None
    try:
        usec = int(environ.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    return usec / 2e6 if usec > 0 else None


class Watchdog(Handle):
    """Pings systemd's watchdog every ``interval`` seconds from a thread of its own, only when the
    update loop has beaten (``heartbeat``) since the previous ping. Closing stops it (idempotent).

    ``pings`` and ``missed`` count the pings sent and withheld; ``wait(predicate, timeout)`` waits
    for them (each round of the thread wakes it).
    """

    def __init__(self, notifier: Notifier, heartbeat: Heartbeat, interval: float) -> None:
        if not interval > 0 or math.isinf(interval):
            raise ValueError(f"watchdog interval must be a positive number of seconds, not {interval!r}")
        if heartbeat.period >= interval:
            # A healthy loop must beat between two pings, or healthy daemons would be killed.
            raise ValueError(f"the heartbeat ({heartbeat.period:g} s) must beat more often than the watchdog pings ({interval:g} s)")
        self.notifier = notifier
        self.heartbeat = heartbeat
        self.interval = interval
        self.pings = 0
        self.missed = 0
        self._seen = 0  # beats at the previous ping: none yet
        self._stalled = False  # only the watchdog's thread reads and writes it
        self._stop = threading.Event()
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="sd-watchdog", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self._round()

    def _round(self) -> None:
        beats = self.heartbeat.beats
        if beats != self._seen:
            self._seen = beats
            self._stalled = False
            sent = self.notifier.watchdog()
            with self._cond:
                self.pings += sent
                self._cond.notify_all()
            return
        with self._cond:
            self.missed += 1
            self._cond.notify_all()
        if not self._stalled:  # said once per stall
            self._stalled = True
            age = self.heartbeat.age()
            log.error("the update loop has not turned for %s: the systemd watchdog is not pinged, and systemd restarts "
                      "the daemon once WatchdogSec passes", "ever" if age is None else f"{age:.1f} s")

    def wait(self, predicate: Callable[[Watchdog], bool], timeout: float) -> bool:
        """Wait until ``predicate(self)`` holds (checked after each round); False at the timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self), timeout)

    def __enter__(self) -> Self:
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(5.0)


class Served(Protocol):
    """What ``Service`` needs of an embodiment (``body.embodiment.Embodiment``)."""

    name: str
    mesh: str
    sim: Simulation


class Service(Handle):
    """The embodiment as a systemd service, for as long as it is open (a context manager).

    Opening it (the embodiment started: joined, its name held) waits for the update loop's first
    beat, sends ``READY=1`` with ``STATUS=status`` (by default "embodiment NAME up in mesh MESH"),
    and starts the watchdog when systemd asks for one. A loop that does not turn within
    ``first_beat_wait`` is never reported ready (``STATUS=`` says why). ``close`` (idempotent) sends ``STOPPING=1``
    and stops the watchdog. Without ``$NOTIFY_SOCKET`` it sends nothing and starts no thread.

    ``heartbeat``: one to share (with ``ops.metrics``' health check); else one of its own, closed with it.
    """

    def __init__(self, embodiment: Served, *, status: str | None = None, notifier: Notifier | None = None,
                 heartbeat: Heartbeat | None = None, environ: Mapping[str, str] = os.environ,
                 first_beat_wait: float = FIRST_BEAT_WAIT) -> None:
        self.notifier = notifier if notifier is not None else Notifier(environ=environ)
        self.ready = False
        self._owns_notifier = notifier is None
        self.watchdog: Watchdog | None = None
        self._owned_heartbeat: Heartbeat | None = None
        self._closed = False
        if not self.notifier.enabled:
            self.heartbeat = heartbeat
            return
        interval = watchdog_interval(environ)
        if heartbeat is None or (interval is not None and heartbeat.period >= interval):
            # It beats more often than the watchdog pings (twice per ping), and shows the loop turns before READY=1.
            heartbeat = self._owned_heartbeat = Heartbeat(embodiment.sim, PERIOD if interval is None else min(PERIOD, interval / 2))
        self.heartbeat = heartbeat
        try:
            if not heartbeat.wait_first(first_beat_wait):
                # Not ready: systemd fails the start when TimeoutStartSec passes, and starts it again.
                why = f"the update loop of {embodiment.name!r} did not turn within {first_beat_wait:g} s: not ready"
                log.error("%s", why)
                self.notifier.status(why)
                return
            self.ready = self.notifier.ready(
                status if status is not None else f"embodiment {embodiment.name!r} up in mesh {embodiment.mesh!r}")
            if interval is not None:
                self.watchdog = Watchdog(self.notifier, heartbeat, interval)
        except BaseException:
            self.close()
            raise

    def status(self, text: str) -> None:
        self.notifier.status(text)

    def __enter__(self) -> Self:
        return self

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.notifier.stopping()
        for handle in (self.watchdog, self._owned_heartbeat):
            if handle is not None:
                handle.close()
        if self._owns_notifier:
            self.notifier.close()


# --- the unit file ------------------------------------------------------------------------------


def default_command() -> list[str]:
    """How systemd should start ``cmion-mesh``: the console script of this installation (beside the
    running interpreter, else on ``PATH``), else the interpreter running the package's module."""
    beside = Path(sys.executable).with_name("cmion-mesh")
    if beside.is_file() and os.access(beside, os.X_OK):
        return [str(beside)]
    found = shutil.which("cmion-mesh")
    if found:
        return [os.path.abspath(found)]
    return [sys.executable, "-m", "cmion_mesh.cli.main"]


def _exec_arg(arg: str, *, what: str) -> str:
    """One word of ``ExecStart=``: ``%`` and ``$`` escaped (systemd would expand them), quoted when needed."""
    if not arg or any(ord(c) < 32 or c == "\x7f" for c in arg):
        raise ConfigError(f"{what} {arg!r}: empty, or holds a control character a unit file cannot carry")
    escaped = arg.replace("%", "%%").replace("$", "$$")
    if any(c in escaped for c in " \t\"'\\;"):
        escaped = '"' + escaped.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return escaped


def unit(name: str, *, command: Sequence[str] | None = None, settings: str | None = None, mesh: str | None = None,
         metrics: str | None = None, watchdog_sec: int = WATCHDOG_SEC, user: str = USER) -> str:
    """The systemd unit running ``cmion-mesh up`` for embodiment ``name`` (save it as
    ``/etc/systemd/system/cmion-mesh-NAME.service``; docs/deploy.md walks through it).

    ``command``: how to start cmion-mesh (``default_command()``); ``settings``: the daemon's settings
    file (``SETTINGS_PATH``); ``mesh``, ``metrics``: given to ``up`` when set. The state folder is
    systemd's ``StateDirectory=cmion-mesh/NAME`` (``/var/lib/cmion-mesh/NAME``), given to ``up`` as
    ``--state-dir``: owned by the service's own user and kept across restarts.
    """
    name = keys.check_name(name, "embodiment")
    if mesh is not None:
        mesh = keys.check_name(mesh, "mesh")
    if not isinstance(watchdog_sec, int) or watchdog_sec < 2:
        raise ConfigError(f"watchdog {watchdog_sec!r} s: give a whole number of seconds, at least 2")
    if not user or not all(c.isalnum() or c in "-_" for c in user) or user[0].isdigit():
        raise ConfigError(f"user {user!r}: letters, digits, '-' and '_', not starting with a digit")
    cmd = list(command) if command is not None else default_command()
    if not cmd or not os.path.isabs(cmd[0]):
        raise ConfigError(f"command {cmd!r}: systemd needs the program's absolute path")
    settings_path = settings if settings is not None else SETTINGS_PATH.format(name=name)
    if not os.path.isabs(settings_path):
        raise ConfigError(f"settings file {settings_path!r}: give an absolute path (the service does not start in this folder)")
    words = [_exec_arg(cmd[0], what="command"), *(_exec_arg(a, what="argument") for a in cmd[1:]),
             "up", "--name", name, SETTINGS_OPTION, _exec_arg(settings_path, what="settings file"),
             # %S: /var/lib for the system manager (the StateDirectory's root); not escaped, systemd expands it.
             "--state-dir", f"%S/cmion-mesh/{name}"]
    if mesh is not None:
        words += ["--mesh", mesh]
    if metrics is not None:
        words += ["--metrics", _exec_arg(metrics, what="metrics address")]
    home = any(cmd[0].startswith(prefix) for prefix in ("/home/", "/root/", "/run/user/"))
    lines = [
        f"# cmion-mesh embodiment {name!r} as a systemd service (printed by `cmion-mesh service unit {name}`).",
        f"# Install: save as /etc/systemd/system/cmion-mesh-{name}.service, then",
        f"#   systemctl daemon-reload && systemctl enable --now cmion-mesh-{name}",
        "# See docs/deploy.md, section \"systemd\".",
        "",
        "[Unit]",
        f"Description=cmion-mesh embodiment {name}",
        "Wants=network-online.target",
        "After=network-online.target",
        # A daemon that keeps failing at start (its name held elsewhere, say) is retried 5 times in 5 minutes, then left failed.
        "StartLimitIntervalSec=300",
        "StartLimitBurst=5",
        "",
        "[Service]",
        "# Ready only once it has joined the mesh and holds its name (READY=1); the main process alone may say so.",
        "Type=notify",
        "NotifyAccess=main",
        f"ExecStart={' '.join(words)}",
        "# Joining waits for the mesh to answer; a slow network may take a while.",
        "TimeoutStartSec=120",
        "# The update loop pings the watchdog (WATCHDOG=1) while it turns: a stuck loop is killed and restarted.",
        f"WatchdogSec={watchdog_sec}",
        "Restart=on-failure",
        "RestartSec=5",
        "# Exit status 2 is a configuration error: restarting would not fix it.",
        "RestartPreventExitStatus=2",
        "# SIGTERM: the daemon answers what is queued, closes its session and its files (STOPPING=1), then exits.",
        "TimeoutStopSec=30",
        "",
        "# A user of its own, made by systemd while the service runs (or the system user of that name, if there is",
        "# one); it owns the state folder, which outlives it. Nothing else on the machine is writable.",
        "DynamicUser=yes",
        f"User={user}",
        f"StateDirectory=cmion-mesh/{name}",
        "StateDirectoryMode=0700",
        "UMask=0077",
        "Environment=PYTHONUNBUFFERED=1",
        "",
        "# Hardening: the daemon needs the network (zenoh: TCP/UDP, interface lists over netlink), its state folder,",
        "# its settings and certificate files (readable), and nothing else.",
        "NoNewPrivileges=yes",
        "ProtectSystem=strict",
        *(["# The program lives under a home folder: it stays readable (better: install it under /opt).",
           "ProtectHome=read-only"] if home else ["ProtectHome=yes"]),
        "PrivateTmp=yes",
        "PrivateDevices=yes",
        "ProtectKernelTunables=yes",
        "ProtectKernelModules=yes",
        "ProtectKernelLogs=yes",
        "ProtectControlGroups=yes",
        "ProtectClock=yes",
        "ProtectHostname=yes",
        "ProtectProc=invisible",
        "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_NETLINK",
        "RestrictNamespaces=yes",
        "RestrictRealtime=yes",
        "RestrictSUIDSGID=yes",
        "LockPersonality=yes",
        "RemoveIPC=yes",
        "CapabilityBoundingSet=",
        "AmbientCapabilities=",
        "SystemCallArchitectures=native",
        "SystemCallFilter=@system-service",
        "SystemCallFilter=~@privileged @resources",
        "SystemCallErrorNumber=EPERM",
        "# MemoryDenyWriteExecute is not set: libffi closures (cffi, ctypes) need memory both written and run.",
        "",
        "[Install]",
        "WantedBy=multi-user.target",
        "",
    ]
    return "\n".join(lines)
