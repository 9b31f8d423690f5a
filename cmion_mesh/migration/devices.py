"""Device tables: CMION's ``migrationconfig`` files, read as who this embodiment is and whom it knows.

::

    <migrationconfig>
      <configuration>
        <devicename value="A"/>          <!-- this embodiment's name -->
        <listenport value="34871"/>      <!-- a zenoh listen endpoint -->
        <inviteport value="34872"/>      <!-- read, not used: invitations travel on the mesh -->
        <agent active="true"/>           <!-- the companion is born here -->
      </configuration>
      <devices>
        <device name="B" host="localhost" port="34873" inviteport="34874"/>
      </devices>
    </migrationconfig>

CMION found the file through the Migration competency's ``ConstructorParameters`` in the
competency library (``table_for_library``); the name is looked for beside the library, then in the
working directory (where CMION opened it), and an Android raw-resource name without ``.xml``
(``migrationconfig``) means ``<name>.xml``.

What each part becomes (``docs/invitations.md`` says it for users):

* ``devicename`` is the embodiment's name;
* each device's ``host:port`` is a zenoh **connect** endpoint ``tcp/<host>:<port>``; discovery
  (multicast scouting, unless turned off) still finds embodiments the table does not list;
* ``listenport`` is a **listen** endpoint: on loopback (``tcp/127.0.0.1:<port>``) when every
  device the table lists is on loopback (a one-machine setup, as CMION's own sample files), else
  on all interfaces (``tcp/0.0.0.0:<port>``), as CMION's server socket listened;
* ``agent active="true"``: the companion is born here on the first start (if no live embodiment
  of the mesh hosts it already);
* the devices are the embodiments this one accepts invitations from (``invitation``) and sends
  its own to.

Options given on the command line win over the table (``--name``, ``--connect``, ``--listen``,
``--companion``).
"""

from __future__ import annotations

import ipaddress
import os
from pathlib import Path

import msgspec
from lxml import etree

from cmion_mesh import keys, xmlsafe
from cmion_mesh.classes import Located, current_name, locate_file
from cmion_mesh.diagnostics import Diagnostics
from cmion_mesh.errors import ConfigError, InvalidName
from cmion_mesh.transport.base import TransportConfig

SCHEMA = "MigrationConfig.xsd"
#: Competency classes whose first constructor parameter names a device table: CMION's Java
#: names and our own class. (A port map may map more Java names to our class; these are the ones
#: that, named in a library, make its first parameter a device table.)
MIGRATION_CLASSES = frozenset({
    "cmion.level2.competencies.Migration",
    "cmion.level2.competencies.AndroidMigration",
    "cmion_mesh.migration.manager:MigrationCompetency",
    "cmion_mesh.migration.manager.MigrationCompetency",
})
#: Android's migration competency named its table as a raw resource: no folder, no ``.xml``.
ANDROID_MIGRATION = "cmion.level2.competencies.AndroidMigration"
#: The companion an active ``agent`` gives birth to, when the configuration names none (CMION had one
#: agent per device table and no name for it; every table of one deployment must agree on it).
DEFAULT_COMPANION = "companion"
LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback"})


class Device(msgspec.Struct, frozen=True):
    """An embodiment the table knows."""

    name: str
    host: str
    port: int
    invite_port: int | None
    line: int | None

    @property
    def endpoint(self) -> str:
        host = f"[{self.host}]" if ":" in self.host and not self.host.startswith("[") else self.host
        return f"tcp/{host}:{self.port}"


class DeviceTable(msgspec.Struct, frozen=True):
    path: Path
    name: str | None  # devicename (None when absent or empty)
    listen_port: int
    invite_port: int | None
    born_here: bool  # agent active="true"
    devices: tuple[Device, ...]

    def knows(self, embodiment: str) -> bool:
        return any(d.name == embodiment for d in self.devices)

    @property
    def names(self) -> list[str]:
        return [d.name for d in self.devices]

    def connect_endpoints(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(d.endpoint for d in self.devices))

    def listen_endpoints(self) -> tuple[str, ...]:
        local = bool(self.devices) and all(is_loopback(d.host) for d in self.devices)
        return (f"tcp/{'127.0.0.1' if local else '0.0.0.0'}:{self.listen_port}",)


def is_loopback(host: str) -> bool:
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _int(value: str | None) -> int | None:
    """A port the schema already checked; ``None`` when absent or CMION's ``-1`` (none)."""
    if value is None:
        return None
    number = int(value)
    return number if number > 0 else None


def load_device_table(path: str | os.PathLike[str]) -> DeviceTable:
    """Read and check a ``migrationconfig`` file; one ``ConfigError`` at the first problem's file and
    line otherwise, its text listing every problem."""
    found = Diagnostics()
    table = read_device_table(path, found)
    found.raise_if_errors()
    assert table is not None  # None only after reporting why
    return table


def read_device_table(path: str | os.PathLike[str], diagnostics: Diagnostics) -> DeviceTable | None:
    """``load_device_table`` reporting every problem to ``diagnostics``; None when there is one."""
    name = os.fspath(path)
    try:
        tree = xmlsafe.load(name, None)
    except ConfigError as exc:
        diagnostics.problem(exc)
        return None
    root = tree.getroot()
    absent = _absent(root)
    for parent, child in absent:
        why, add = CMION_NEEDED[child]
        diagnostics.error(f"no <{child}> in <{parent.tag}>: CMION 2011 could not run this table either ({why}); add {add}",
                          name, xmlsafe.sourceline(parent))
    # The schema says the same of an absent element in its own words: each problem is reported once.
    said = {xmlsafe.sourceline(parent) for parent, _ in absent}
    schema = [p for p in xmlsafe.schema_problems(tree, SCHEMA, name) if not (p.line in said and "Missing child element" in p.detail)]
    for violation in schema:
        diagnostics.problem(violation)
    if absent or schema:
        return None
    usable = True

    def problem(message: str, line: int | None) -> None:
        nonlocal usable
        usable = False
        diagnostics.error(message, name, line)

    config = root.find("configuration")
    assert config is not None  # the schema requires it
    listen = config.find("listenport")
    agent = config.find("agent")
    assert listen is not None and agent is not None
    devicename = config.find("devicename")
    embodiment = devicename.get("value", "") if devicename is not None else ""
    if embodiment:
        why = _invalid(embodiment, "devicename")
        if why:
            problem(why, xmlsafe.sourceline(devicename))
    invite = config.find("inviteport")
    devices: list[Device] = []
    seen: dict[str, int | None] = {}
    devices_el = root.find("devices")
    assert devices_el is not None
    for el in devices_el.iter("device"):
        line = xmlsafe.sourceline(el)
        device = el.get("name", "")
        why = _invalid(device, "device name")
        if why:
            problem(why, line)
        elif device in seen:
            problem(f"device {device!r} is listed twice (first at line {seen[device]})", line)
        elif device == embodiment:
            problem(f"device {device!r} is this embodiment's own devicename", line)
        else:
            seen[device] = line
        port = _int(el.get("port"))
        assert port is not None
        devices.append(Device(device, el.get("host", "").strip(), port, _int(el.get("inviteport")), line))
    listen_port = _int(listen.get("value"))
    assert listen_port is not None
    if not usable:
        return None
    return DeviceTable(Path(name), embodiment or None, listen_port, _int(invite.get("value")) if invite is not None else None,
                       agent.get("active", "").lower() == "true", tuple(devices))


#: The elements CMION's Migration competency could not run without: what it read there, and what
#: to add. (``devicename`` and ``inviteport`` it could: an empty name and no invitation port.)
CMION_NEEDED: dict[str, tuple[str, str]] = {
    "configuration": ("its Migration competency read its own settings there",
                      "<configuration> holding <listenport> and <agent>"),
    "devices": ("its Migration competency read the devices it knew there", "<devices/> (empty when it knows none)"),
    "listenport": ("its Migration competency listened on that port", '<listenport value="PORT"/>'),
    "agent": ("its Migration competency read there whether the companion is born here",
              '<agent active="false"/> (or "true" on the embodiment where the companion is born)'),
}


def _absent(root: etree._Element) -> list[tuple[etree._Element, str]]:
    """The elements of ``CMION_NEEDED`` missing, each with the element that should hold it."""
    if root.tag != "migrationconfig":
        return []  # not a device table at all: the schema says so
    missing = [(root, child) for child in ("configuration", "devices") if root.find(child) is None]
    config = root.find("configuration")
    if config is not None:
        missing += [(config, child) for child in ("listenport", "agent") if config.find(child) is None]
    return missing


def _invalid(value: str, what: str) -> str:
    """Why ``value`` cannot be a name, or ``""``."""
    try:
        keys.check_name(value, what)
    except InvalidName as exc:
        return str(exc)
    return ""


def is_migration_class(class_name: str) -> bool:
    return current_name(class_name.strip()) in MIGRATION_CLASSES


def table_parameter(class_name: str) -> str:
    """How problems name a Migration competency's table parameter: the library's loader and the
    daemon's early read of the table say the same words, so a problem is reported once."""
    return f"{class_name.strip()}: parameter 1 (its device table)"


def locate_table(library: str | os.PathLike[str], parameter: str) -> Located:
    """Where a Migration competency's parameter points: beside the library, else in the working
    directory (as CMION opened it, ``classes.locate_file``); an Android raw-resource name (no
    suffix) is ``<name>.xml``."""
    return locate_file(library, parameter)


def birth(table: DeviceTable | None, configured: str | None) -> str | None:
    """The companion born here: with a table, ``DEFAULT_COMPANION`` (or the configuration's
    ``Companion``) when its agent is active, else none; without one, the configuration's."""
    if table is None:
        return configured
    return (configured or DEFAULT_COMPANION) if table.born_here else None


def with_table_endpoints(config: TransportConfig, table: DeviceTable | None) -> TransportConfig:
    """``config`` with the table's connect and listen endpoints where it has none of its own:
    endpoints given explicitly, or a zenoh configuration file, win over the table's."""
    if table is None or config.config_file is not None:
        return config
    return msgspec.structs.replace(config, connect=config.connect or table.connect_endpoints(),
                                   listen=config.listen or table.listen_endpoints())
