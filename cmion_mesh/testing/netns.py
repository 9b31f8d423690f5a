"""Throw-away multi-host networks made of Linux network namespaces, for tests that need real LANs.

A *segment* is one IPv4 subnet: a bridge living in a namespace of its own (the "switch"), so
nothing is ever created in the caller's namespace. A *host* is a namespace with ``lo`` up and
one veth per segment it is attached to (``eth0``, ``eth1``...), the other end of each veth being
a port of that segment's bridge. Hosts on one segment share a LAN with working multicast; hosts
on different segments can only meet through a host attached to both (a router host), which
never forwards IP (``net.ipv4.ip_forward=0``), so the only way across is a process there.

Everything stays inside the namespaces: private addresses assigned here, no default route,
IPv6 disabled (no link-local addresses or router solicitations), no link to the real network.
Every name carries a per-instance random id (``cm-<8 hex>-<name>``) so parallel runs never
collide, and ``close()`` (also on ``with`` exit, on errors while building, and as a last resort
at interpreter exit) stops the processes started here and deletes every namespace, which
destroys the bridges and veths with them.

Needs root (or CAP_NET_ADMIN + CAP_SYS_ADMIN) and ``ip`` from iproute2; ``available()`` tells.

    with Lan(3) as lan:
        a = lan.hosts[0].popen([sys.executable, "-m", "cmion_mesh.cli.main", "up", ...])
        a.wait_line("up in mesh")
        lan.cut(lan.hosts[0]); ...; lan.heal(lan.hosts[0])

    with two_subnets() as net:   # net.left[0] -- net.router -- net.right[0]
        ...
"""

from __future__ import annotations

import functools
import ipaddress
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
import weakref
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from cmion_mesh.errors import MeshError
from cmion_mesh.procs import Daemon

PREFIX = "cm"
#: Subnets used by default: private (RFC 1918) and only ever assigned inside our namespaces.
DEFAULT_SUBNETS = ("10.213.1.0/24", "10.213.2.0/24", "10.213.3.0/24", "10.213.4.0/24")
#: Where multicast goes: the route makes senders that do not pick an interface (IP_MULTICAST_IF)
#: use the LAN interface, since the namespaces have no default route.
MULTICAST_NET = "224.0.0.0/4"
#: The multicast group the self-check uses: administratively scoped, not zenoh's 224.0.0.224:7446,
#: so a check never feeds garbage to a zenoh process scouting on the same LAN.
PROBE_GROUP, PROBE_PORT = "239.255.77.77", 47446
IP_TIMEOUT = 20.0


class NetnsError(MeshError):
    """A namespace, link or address could not be set up or torn down."""


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    try:
        result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=IP_TIMEOUT)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise NetnsError(f"ip {' '.join(args)}: {exc}") from None
    if check and result.returncode != 0:
        raise NetnsError(f"ip {' '.join(args)}: {result.stderr.strip() or f'exit {result.returncode}'}")
    return result


def _sysctl(ns: str, *settings: str) -> None:
    # Per-namespace sysctls (net.*) are only reachable from inside the namespace.
    result = subprocess.run(["ip", "netns", "exec", ns, "sysctl", "-q", "-w", *settings],
                            capture_output=True, text=True, timeout=IP_TIMEOUT)
    if result.returncode != 0:
        raise NetnsError(f"sysctl {' '.join(settings)} in {ns}: {result.stderr.strip()}")


def list_namespaces() -> set[str]:
    """Names of all named network namespaces (``ip netns list``)."""
    out = _ip("netns", "list").stdout
    return {line.split()[0] for line in out.splitlines() if line.strip()}


def _delete_namespaces(namespaces: Iterable[str]) -> list[str]:
    """Kill what still runs in each namespace, then delete it; returns the failures.

    A namespace outlives ``ip netns delete`` while a process is inside it (with its devices and
    addresses, just unnamed), so the processes go first. They are ours: nothing else can enter a
    namespace whose random name only this instance knows.
    """
    failures = []
    for ns in namespaces:
        try:
            for pid in _ip("netns", "pids", ns, check=False).stdout.split():
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            result = _ip("netns", "delete", ns, check=False)
            if result.returncode != 0 and ns in list_namespaces():
                failures.append(f"{ns}: {result.stderr.strip()}")
        except NetnsError as exc:  # keep going: one stuck namespace must not keep the others
            failures.append(f"{ns}: {exc}")
    return failures


@functools.cache
def unavailable_reason() -> str | None:
    """Why namespaces cannot be used here (None if they can). Tried once per process, for real."""
    if sys.platform != "linux":
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "network namespaces need root (CAP_NET_ADMIN and CAP_SYS_ADMIN)"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    ns = f"{PREFIX}-{uuid.uuid4().hex[:8]}-check"
    try:
        _ip("netns", "add", ns)
        try:
            # The kernel may lack veth or bridge support even when namespaces work.
            _ip("-n", ns, "link", "add", "br0", "type", "bridge")
            _ip("-n", ns, "link", "add", "v0", "type", "veth", "peer", "name", "v1")
            _ip("-n", ns, "link", "set", "v0", "master", "br0")
            _sysctl(ns, "net.ipv4.ip_forward=0")
        finally:
            _delete_namespaces([ns])
    except NetnsError as exc:
        return f"cannot create network namespaces, veths or bridges: {exc}"
    return None


def available() -> bool:
    """True if this process can build namespaces (root, iproute2, veth and bridge support)."""
    return unavailable_reason() is None


@dataclass(frozen=True)
class Interface:
    """One host's attachment to a segment."""

    host: str  # logical host name
    segment: str  # segment name
    name: str  # device inside the host namespace (eth0, eth1...)
    port: str  # device inside the switch namespace, enslaved to the bridge
    address: str  # IPv4 address, no prefix length
    prefixlen: int


class Segment:
    """One subnet: a bridge in a switch namespace of its own."""

    BRIDGE = "br0"

    def __init__(self, name: str, ns: str, subnet: str) -> None:
        self.name = name
        self.ns = ns
        self.network = ipaddress.ip_network(subnet)
        if not self.network.is_private or self.network.version != 4:
            raise NetnsError(f"segment {name}: {subnet} is not a private IPv4 subnet")
        self._hosts = self.network.hosts()
        self.ports = 0

    def next_address(self) -> str:
        try:
            return str(next(self._hosts))
        except StopIteration:
            raise NetnsError(f"segment {self.name}: no addresses left in {self.network}") from None

    def __repr__(self) -> str:
        return f"Segment({self.name!r}, {self.network}, ns={self.ns!r})"


class Host:
    """A namespace that runs commands; ``address`` is its address on its first segment."""

    def __init__(self, topology: Topology, name: str, ns: str) -> None:
        self.topology = topology
        self.name = name
        self.ns = ns
        self.interfaces: list[Interface] = []

    @property
    def address(self) -> str:
        if not self.interfaces:
            raise NetnsError(f"host {self.name} is attached to no segment")
        return self.interfaces[0].address

    @property
    def interface(self) -> str:
        """Name of its first interface (the one multicast goes out of)."""
        if not self.interfaces:
            raise NetnsError(f"host {self.name} is attached to no segment")
        return self.interfaces[0].name

    def on(self, segment: Segment | str) -> Interface:
        """Its interface on ``segment``."""
        name = segment.name if isinstance(segment, Segment) else segment
        for iface in self.interfaces:
            if iface.segment == name:
                return iface
        raise NetnsError(f"host {self.name} is not on segment {name}")

    def argv(self, argv: Sequence[str]) -> list[str]:
        """``argv`` wrapped to run inside this namespace (``ip netns exec`` execs it: same pid)."""
        return ["ip", "netns", "exec", self.ns, *argv]

    def popen(self, argv: Sequence[str], *, name: str = "", env: dict[str, str] | None = None) -> Daemon:
        """Start ``argv`` here as a ``Daemon`` (output lines can be awaited); stopped on ``close``."""
        return self.topology._track(Daemon(self.argv(argv), env=env, name=f"{self.name}:{name or os.path.basename(argv[0])}"))

    def run(self, argv: Sequence[str], *, timeout: float = 30.0, check: bool = True,
            input: str | None = None) -> subprocess.CompletedProcess[str]:
        """Run ``argv`` here to completion; output captured as text."""
        result = subprocess.run(self.argv(argv), capture_output=True, text=True, timeout=timeout, input=input)
        if check and result.returncode != 0:
            raise NetnsError(f"{self.name}: {' '.join(argv)} exited {result.returncode}: {result.stderr.strip()}")
        return result

    def tcp_reaches(self, address: str, port: int, *, timeout: float = 2.0) -> bool:
        """Whether a TCP connection from here gets an answer from ``address`` (accepted or refused).

        False when there is no route, or nothing answers within ``timeout``: the IP-level check
        that two hosts are (not) on a common network.
        """
        result = self.run([sys.executable, "-c", _TCP_PROBE, address, str(port), str(timeout)], timeout=timeout + 15)
        return result.stdout.strip() in ("open", "refused")

    def __repr__(self) -> str:
        addrs = ", ".join(f"{i.name}={i.address}" for i in self.interfaces)
        return f"Host({self.name!r}, ns={self.ns!r}, {addrs})"


class Topology:
    """Namespaces, switches and hosts, built step by step; a context manager that deletes them all."""

    def __init__(self) -> None:
        self.id = uuid.uuid4().hex[:8]
        self.hosts: list[Host] = []
        self.segments: list[Segment] = []
        self._namespaces: list[str] = []
        self._daemons: list[Daemon] = []
        self._lock = threading.Lock()
        self._closed = False
        # Last resort if the owner forgets close() or the interpreter exits first: the finalizer
        # holds the (shared, mutated) list of names, not self.
        self._finalizer = weakref.finalize(self, _delete_namespaces, self._namespaces)

    # --- building -----------------------------------------------------------------------------

    def _new_namespace(self, name: str) -> str:
        if self._closed:
            raise NetnsError("topology already closed")
        ns = f"{PREFIX}-{self.id}-{name}"
        _ip("netns", "add", ns)
        self._namespaces.append(ns)
        _ip("-n", ns, "link", "set", "lo", "up")
        # No IPv6 at all: no link-local addresses, DAD or router solicitations, so the only
        # addresses in play are the private IPv4 ones assigned here. No forwarding, ever.
        _sysctl(ns, "net.ipv6.conf.all.disable_ipv6=1", "net.ipv6.conf.default.disable_ipv6=1",
                "net.ipv4.ip_forward=0")
        return ns

    def add_segment(self, name: str, subnet: str) -> Segment:
        """A new subnet: its bridge lives in namespace ``cm-<id>-<name>``."""
        self._check_name(name)
        segment = Segment(name, self._new_namespace(name), subnet)
        # Multicast snooping off: with no IGMP querier on this LAN the bridge would otherwise
        # learn groups from stray reports and could stop flooding groups it has not seen; no STP
        # and no forward delay, so a port forwards as soon as it is up (also after heal()).
        _ip("-n", segment.ns, "link", "add", Segment.BRIDGE, "type", "bridge",
            "mcast_snooping", "0", "stp_state", "0", "forward_delay", "0")
        _ip("-n", segment.ns, "link", "set", Segment.BRIDGE, "multicast", "on", "up")
        self.segments.append(segment)
        return segment

    def add_host(self, name: str, *segments: Segment) -> Host:
        """A new host namespace ``cm-<id>-<name>``, with one interface on each segment."""
        self._check_name(name)
        host = Host(self, name, self._new_namespace(name))
        self.hosts.append(host)
        for segment in segments:
            self.attach(host, segment)
        return host

    def attach(self, host: Host, segment: Segment, address: str | None = None) -> Interface:
        """Give ``host`` an interface on ``segment``: a veth whose other end is a bridge port."""
        ifname = f"eth{len(host.interfaces)}"
        port = f"p{segment.ports}"
        segment.ports += 1
        address = address or segment.next_address()
        # Created from the switch side with the peer born straight in the host namespace:
        # the pair never exists in the caller's namespace, not even for a moment.
        _ip("-n", segment.ns, "link", "add", port, "type", "veth", "peer", "name", ifname, "netns", host.ns)
        _ip("-n", segment.ns, "link", "set", port, "master", Segment.BRIDGE)
        _ip("-n", segment.ns, "link", "set", port, "multicast", "on", "up")
        _ip("-n", host.ns, "addr", "add", f"{address}/{segment.network.prefixlen}", "dev", ifname)
        _ip("-n", host.ns, "link", "set", ifname, "multicast", "on", "up")
        iface = Interface(host.name, segment.name, ifname, port, address, segment.network.prefixlen)
        host.interfaces.append(iface)
        if len(host.interfaces) == 1:
            self._multicast_route(host)
        return iface

    @staticmethod
    def _multicast_route(host: Host) -> None:
        # Multicast leaves by the first interface: with no default route, a sender that does not
        # name an interface would get ENETUNREACH. Only one: a router host must not be a bridge
        # for multicast between its segments (and does not forward anything anyway).
        _ip("-n", host.ns, "route", "replace", MULTICAST_NET, "dev", host.interface)

    def _check_name(self, name: str) -> None:
        if not name or not name.replace("-", "").isalnum() or len(name) > 20:
            raise NetnsError(f"bad name {name!r}: letters, digits and '-' only, at most 20")
        if any(h.name == name for h in self.hosts) or any(s.name == name for s in self.segments):
            raise NetnsError(f"name {name!r} already used in this topology")

    def _track(self, daemon: Daemon) -> Daemon:
        with self._lock:
            closed = self._closed
            if not closed:
                self._daemons.append(daemon)
        if closed:
            daemon.kill()
            raise NetnsError("topology already closed")
        return daemon

    # --- looking up ---------------------------------------------------------------------------

    def host(self, name: str) -> Host:
        for host in self.hosts:
            if host.name == name:
                return host
        raise KeyError(name)

    def segment(self, name: str) -> Segment:
        for segment in self.segments:
            if segment.name == name:
                return segment
        raise KeyError(name)

    def namespaces(self) -> list[str]:
        """Every namespace this instance created (and has not deleted yet)."""
        return list(self._namespaces)

    # --- faults -------------------------------------------------------------------------------

    def _port(self, host: Host, segment: Segment | str | None) -> tuple[Interface, Segment]:
        iface = host.interfaces[0] if segment is None else host.on(segment)
        return iface, self.segment(iface.segment)

    def cut(self, host: Host, segment: Segment | str | None = None, *, side: str = "switch") -> None:
        """Disconnect ``host`` from ``segment`` (default: its first).

        ``side="switch"`` (default) takes the bridge port down, like pulling the cable at the
        switch: the host keeps its interface, address and routes but its packets are silently
        dropped, so peers only notice by timeouts (leases). ``side="host"`` takes the host's own
        interface down instead: sends then fail at once (no route), like ``ifdown``.
        """
        iface, seg = self._port(host, segment)
        if side == "switch":
            _ip("-n", seg.ns, "link", "set", iface.port, "down")
        elif side == "host":
            _ip("-n", host.ns, "link", "set", iface.name, "down")
        else:
            raise ValueError(f"side must be 'switch' or 'host', not {side!r}")

    def heal(self, host: Host, segment: Segment | str | None = None) -> None:
        """Undo ``cut`` (either side): both ends up, routes restored."""
        iface, seg = self._port(host, segment)
        _ip("-n", seg.ns, "link", "set", iface.port, "up")
        _ip("-n", host.ns, "link", "set", iface.name, "up")
        # The kernel drops routes through an interface taken down and restores only the subnet's.
        if iface is host.interfaces[0]:
            self._multicast_route(host)

    # --- checking -----------------------------------------------------------------------------

    def multicast_reaches(self, sender: Host, receivers: Sequence[Host], *, timeout: float = 5.0) -> set[str]:
        """Names of the ``receivers`` that hear a UDP multicast datagram ``sender`` sends.

        The sender names no interface, so this also checks the multicast route; receivers join
        the group on their own first interface, as zenoh's scouting does.
        """
        token = uuid.uuid4().hex
        listeners = []
        try:
            for host in receivers:
                listeners.append((host, host.popen([sys.executable, "-c", _MCAST_RECV, PROBE_GROUP, str(PROBE_PORT),
                                                    host.address, token, str(timeout)], name="mcast-recv")))
            for _, daemon in listeners:
                daemon.wait_line("ready", timeout)
            sender.run([sys.executable, "-c", _MCAST_SEND, PROBE_GROUP, str(PROBE_PORT), token], timeout=timeout + 10)
            # The sender is done: a receiver that has not heard within a moment never will.
            deadline = time.monotonic() + 1.0
            heard = set()
            for host, daemon in listeners:
                try:
                    daemon.wait_line("heard", max(0.0, deadline - time.monotonic()))
                    heard.add(host.name)
                except TimeoutError:
                    pass
            return heard
        finally:
            for _, daemon in listeners:
                daemon.kill()

    # --- teardown -----------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the processes started here, delete every namespace (and so every device). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            daemons, self._daemons = self._daemons, []
        # Signal them all first, then wait: they shut down in parallel, not one grace after another.
        for daemon in daemons:
            if daemon.proc.poll() is None:
                try:
                    daemon.proc.send_signal(signal.SIGTERM)
                except ProcessLookupError:
                    pass
        for daemon in daemons:
            try:
                daemon.stop(grace=5.0)
            except Exception:
                daemon.kill()
        failures = _delete_namespaces(list(self._namespaces))
        self._namespaces.clear()
        self._finalizer.detach()
        if failures:
            raise NetnsError("could not delete: " + "; ".join(failures))

    def __enter__(self) -> Topology:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *_: object) -> None:
        try:
            self.close()
        except NetnsError as exc:
            if exc_type is None:
                raise
            # The exception already on its way matters more; still say what was left behind.
            print(f"warning: {exc}", file=sys.stderr)


class Lan(Topology):
    """``hosts`` hosts (``h1``, ``h2``... or the names given) on one segment ``lan``."""

    def __init__(self, hosts: int | Sequence[str] = 2, subnet: str = DEFAULT_SUBNETS[0]) -> None:
        super().__init__()
        names = [f"h{i + 1}" for i in range(hosts)] if isinstance(hosts, int) else list(hosts)
        try:
            self.lan = self.add_segment("lan", subnet)
            for name in names:
                self.add_host(name, self.lan)
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Lan:
        return self


class RoutedSubnets(Topology):
    """Two subnets (``lan1``, ``lan2``) joined only through host ``router``, which has an
    interface on each and forwards nothing: ``left`` hosts are on ``lan1``, ``right`` on ``lan2``.
    The router's address is ``.1`` on both; the hosts follow."""

    def __init__(self, left: int = 1, right: int = 1,
                 subnets: tuple[str, str] = (DEFAULT_SUBNETS[0], DEFAULT_SUBNETS[1])) -> None:
        super().__init__()
        try:
            self.lan1 = self.add_segment("lan1", subnets[0])
            self.lan2 = self.add_segment("lan2", subnets[1])
            self.router = self.add_host("router", self.lan1, self.lan2)
            self.left = [self.add_host(f"l{i + 1}", self.lan1) for i in range(left)]
            self.right = [self.add_host(f"r{i + 1}", self.lan2) for i in range(right)]
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> RoutedSubnets:
        return self


def two_subnets(left: int = 1, right: int = 1) -> RoutedSubnets:
    """``left`` hosts on one subnet, ``right`` hosts on another, a non-forwarding router between."""
    return RoutedSubnets(left, right)


# Tiny programs for the multicast self-check, run inside the namespaces by the interpreter in use.
_MCAST_RECV = """
import socket, sys
group, port, address, token, timeout = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4], float(sys.argv[5])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(("", port))
s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(group) + socket.inet_aton(address))
s.settimeout(timeout)
print("ready", flush=True)
try:
    while True:
        data, src = s.recvfrom(2048)
        if data.decode(errors="replace") == token:
            print("heard", src[0], flush=True)
            break
except TimeoutError:
    print("silence", flush=True)
"""

_MCAST_SEND = """
import socket, sys, time
group, port, token = sys.argv[1], int(sys.argv[2]), sys.argv[3]
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
# A few datagrams, spaced, in case the first is lost while a port settles; UDP needs no answer.
deadline = time.monotonic() + 1.0
while time.monotonic() < deadline:
    s.sendto(token.encode(), (group, port))
    time.sleep(0.1)
print("sent", flush=True)
"""

_TCP_PROBE = """
import socket, sys
address, port, timeout = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
try:
    socket.create_connection((address, port), timeout=timeout).close()
    print("open")
except ConnectionRefusedError:
    print("refused")
except OSError as exc:  # no route (ENETUNREACH, EHOSTUNREACH) or timeout
    print("unreachable", exc)
"""
