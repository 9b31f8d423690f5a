"""``cmion-mesh doctor``: explains why peers are (or are not) found.

Looks at the network interfaces (up, multicast-capable, addresses), the effective zenoh settings
(mode, multicast scouting, endpoints, config file), then joins the mesh briefly and reports the
zenoh peers it connected to, the embodiments alive in this mesh (and what is wrong there: two
daemons with one name, a companion two embodiments claim), and embodiments alive in *other*
meshes (the most common mistake: a different ``--mesh``); and the ROS 2 nodes (rmw_zenoh) this
session can see, by domain, for a ``ros_robot`` beside a ROS 2 robot; with rclpy installed (the
``ros2`` extra), the ROS 2 graph an rclpy node sees on ``$ROS_DOMAIN_ID`` (DDS robots). Reaching
nobody without ``--certs``, it asks each ``--connect`` endpoint whether it speaks TLS (a TLS
handshake, nothing more): an authenticated mesh's members accept TLS links only, which a plain
session cannot open.
"""

from __future__ import annotations

import importlib.util
import json
import os
import socket
import subprocess
import time
from pathlib import Path
from typing import Any

from cmion_mesh import keys
from cmion_mesh.client import MeshClient, mesh_problems
from cmion_mesh.errors import ExitCode, MeshError
from cmion_mesh.ros2.wire import ADMIN_SPACE, parse_token
from cmion_mesh.transport.base import TransportConfig

IFF_UP, IFF_LOOPBACK, IFF_MULTICAST = 0x1, 0x8, 0x1000


def interfaces() -> list[dict[str, Any]]:
    found = []
    addresses = _addresses()
    for _, name in socket.if_nameindex():
        flags = 0
        try:
            flags = int(Path(f"/sys/class/net/{name}/flags").read_text().strip(), 16)
        except (OSError, ValueError):
            pass
        found.append({
            "name": name,
            "up": bool(flags & IFF_UP),
            "loopback": bool(flags & IFF_LOOPBACK),
            "multicast": bool(flags & IFF_MULTICAST),
            "addresses": addresses.get(name, []),
        })
    return found


def _addresses() -> dict[str, list[str]]:
    try:
        out = subprocess.run(["ip", "-o", "addr", "show"], capture_output=True, text=True, timeout=5, check=False).stdout
    except (OSError, subprocess.TimeoutExpired):
        return {}
    result: dict[str, list[str]] = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) >= 4 and parts[2] in ("inet", "inet6"):
            result.setdefault(parts[1], []).append(parts[3])
    return result


#: How long doctor waits for an endpoint's answer to a TLS hello.
TLS_PROBE_WAIT = 1.0


def speaks_tls(endpoint: str, timeout: float = TLS_PROBE_WAIT) -> bool:
    """Whether the zenoh listener at ``endpoint`` (``tcp/host:port`` or ``tls/host:port``) answers a
    TLS hello: it does when it is a member of an authenticated mesh (mutual TLS, which refuses this
    session's plain links). Only the handshake's first answer counts; nothing is authenticated."""
    import ssl

    proto, _, rest = endpoint.partition("/")
    host, _, port = rest.split("#", 1)[0].split("?", 1)[0].rpartition(":")
    if proto not in ("tcp", "tls") or not port.isdigit() or not host:
        return False
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE  # a probe: whose certificate it is does not matter here
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout) as raw, \
                context.wrap_socket(raw, do_handshake_on_connect=False) as tls:
            tls.do_handshake()
        return True  # the server finished a handshake: TLS
    except ssl.SSLError as exc:
        # A TLS server that wants our certificate says so in TLS (an alert); a plain one says nothing
        # TLS can read (EOF, or bytes that are no TLS record).
        return "ALERT" in str(exc).upper()
    except OSError:
        return False


def diagnose(config: TransportConfig, mesh: str, timeout: float, *, certs: bool = False) -> dict[str, Any]:
    from cmion_mesh.transport.zenoh import ZenohTransport

    report: dict[str, Any] = {"mesh": mesh, "interfaces": interfaces(), "problems": [], "hints": []}
    report["zenoh"] = {
        "mode": config.mode, "multicast_scouting": config.multicast, "multicast_interface": config.multicast_interface or "auto",
        "connect": list(config.connect), "listen": list(config.listen) or ["(zenoh default: all interfaces, random port)"],
        "config_file": config.config_file,
    }
    usable = [i for i in report["interfaces"] if i["up"] and not i["loopback"] and i["multicast"]]
    if config.multicast and not usable:
        report["problems"].append("multicast scouting is on but no interface is up and multicast-capable besides loopback")
        report["hints"].append("connect explicitly: --connect tcp/<peer-or-router>:7447 (and --listen on the other side)")
    if not config.multicast and not config.connect:
        report["problems"].append("multicast scouting is off and no --connect endpoint is given: this session can only be found by others")
    started = time.monotonic()
    with ZenohTransport(config) as transport, MeshClient(transport, mesh) as client:
        opened = time.monotonic() - started
        # Join this mesh the way every command does (complete: every embodiment any daemon sees),
        # then look at the other meshes this session reached.
        described = client.describe_all(timeout=timeout)
        seen = set(transport.alive(f"{keys.ROOT}/*/{keys.ALIVE}/*", timeout=max(0.1, min(1.0, timeout))))
        ros_tokens = transport.alive(f"{ADMIN_SPACE}/**", timeout=max(0.1, min(1.0, timeout)))
        report["session"] = {"open_seconds": round(opened, 3), "zenoh_id": transport.id, "connected_to": transport.peers()}
    here = sorted({str(d["name"]) for d in described})
    elsewhere: dict[str, list[str]] = {}
    for key in sorted(seen):
        parts = key.split("/")
        if parts[1] != mesh:
            elsewhere.setdefault(parts[1], []).append(parts[3])
    report["descriptions"] = described
    report["problems"].extend(mesh_problems(described))
    report["problems"].extend(f"{d['name']} does not answer: {d['error']}" for d in described if d.get("error"))
    report["embodiments"] = here
    report["ros2"] = ros2_nodes(ros_tokens)
    report["ros2_rclpy"] = rclpy_graph(timeout)
    report["other_meshes"] = elsewhere
    if not report["session"]["connected_to"]:
        report["problems"].append("no zenoh peer or router reached")
        tls = [endpoint for endpoint in config.connect if not certs and speaks_tls(endpoint)]
        if tls:
            report["problems"].append(f"{', '.join(tls)} speak{'s' if len(tls) == 1 else ''} TLS only: members of an "
                                      "authenticated mesh, which this session without --certs cannot join")
            report["hints"].append("give the mesh's certificates: --certs DIR (and --identity NAME, an operator's "
                                   "certificate: cmion-mesh certs issue DIR NAME --role operator); see docs/security.md")
    if not here and elsewhere:
        first = sorted(elsewhere)[0]
        report["hints"].append(f"embodiments exist in other meshes {sorted(elsewhere)}: did you mean --mesh {first}?")
    if not here and not elsewhere and report["session"]["connected_to"]:
        report["hints"].append("zenoh peers answer but no embodiment is up: start one with `cmion-mesh up`")
    return report


def ros2_nodes(tokens: list[str]) -> dict[str, list[str]]:
    """The ROS 2 nodes that rmw_zenoh liveliness tokens show, by domain: ``{"0": ["/nav2 (zenoh ab12...)"]}``."""
    found: dict[str, set[str]] = {}
    for token in tokens:
        entity = parse_token(token)
        if entity is not None and entity.kind == "NN":
            found.setdefault(str(entity.domain), set()).add(f"{entity.node_path} (zenoh {entity.zid})")
    return {domain: sorted(nodes) for domain, nodes in sorted(found.items(), key=lambda kv: int(kv[0]))}


def rclpy_graph(timeout: float) -> dict[str, Any] | None:
    """What an rclpy node sees on ``$ROS_DOMAIN_ID`` (its RMW's discovery), or None without rclpy."""
    if importlib.util.find_spec("rclpy") is None:
        return None
    from cmion_mesh.ros2.rclpy_link import graph

    try:
        return graph(int(os.environ.get("ROS_DOMAIN_ID") or 0), timeout=max(5.0, timeout))
    except (MeshError, ValueError) as exc:
        return {"error": f"ROS 2 through rclpy: {exc}"}


def run_doctor(config: TransportConfig, *, mesh: str, timeout: float, as_json: bool = False, certs: bool = False) -> int:
    """Print the diagnosis (``as_json``: one JSON document); 0 when embodiments were found and no
    duplicate (of a name or of a companion), else 1. ``certs``: the session has certificates."""
    report = diagnose(config, mesh, timeout, certs=certs)
    healthy = bool(report["embodiments"]) and not any("DUPLICATE" in p for p in report["problems"])
    code = ExitCode.OK if healthy else ExitCode.FAILED
    if as_json:
        print(json.dumps(report))
        return code
    print("interfaces:")
    for i in report["interfaces"]:
        flags = ", ".join(f for f, on in (("up", i["up"]), ("loopback", i["loopback"]), ("multicast", i["multicast"])) if on)
        print(f"  {i['name']:<12} {flags:<28} {' '.join(i['addresses'])}")
    z = report["zenoh"]
    print(f"zenoh: mode {z['mode']}, multicast scouting {'on' if z['multicast_scouting'] else 'off'} "
          f"(interface {z['multicast_interface']}), connect {z['connect'] or '-'}, listen {z['listen']}"
          + (f", config {z['config_file']}" if z["config_file"] else ""))
    s = report["session"]
    print(f"session {s['zenoh_id']} opened in {s['open_seconds']} s; connected to {len(s['connected_to'])} zenoh node(s)")
    print(f"embodiments in mesh {mesh!r}: {', '.join(report['embodiments']) or 'none'}")
    for other, names in report["other_meshes"].items():
        print(f"  (mesh {other!r}: {', '.join(names)})")
    if report["ros2"]:
        for domain, nodes in report["ros2"].items():
            print(f"ROS 2 nodes (rmw_zenoh) on domain {domain}: {', '.join(nodes)}")
    else:
        print("ROS 2 nodes (rmw_zenoh): none visible (for a ROS 2 robot, connect to its zenoh router: docs/ros2.md)")
    graph = report["ros2_rclpy"]
    if graph is not None and "error" in graph:
        print(graph["error"])
    elif graph is not None:
        print(f"ROS 2 graph (rclpy, {graph['rmw']}) on domain {graph['domain']}: nodes {', '.join(graph['nodes']) or 'none'}; "
              f"actions {', '.join(graph['actions']) or 'none'}; topics {', '.join(graph['topics']) or 'none'}")
    for problem in report["problems"]:
        print(f"problem: {problem}")
    for hint in report["hints"]:
        print(f"hint: {hint}")
    return code
