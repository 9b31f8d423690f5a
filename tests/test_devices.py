"""Device tables (CMION's ``migrationconfig``): loading, errors at file:line, how a library names
one, what they give an embodiment (name, endpoints, birth), and ``validate``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cmion_mesh.body.architecture import embodiment_name, load_architecture
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.library import table_for_library
from cmion_mesh.body.validate import validate_file
from cmion_mesh.cli.main import main
from cmion_mesh.client import MeshClient
from cmion_mesh.diagnostics import Diagnostics
from cmion_mesh.errors import ConfigError
from cmion_mesh.migration import devices
from cmion_mesh.migration.manager import MigrationCompetency
from cmion_mesh.testing.wait import wait_for
from cmion_mesh.transport.base import TransportConfig
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .conftest import CMION_2011, DATA

pytestmark = pytest.mark.timeout(60)

INVITE = DATA / "invite"
OURS = {"cmion.level2.competencies.Migration": "cmion_mesh.migration.manager:MigrationCompetency",
        "cmion.level3.supersimplemind.SuperSimpleMigratingByInviteMindConnector":
            "cmion_mesh.minds.supersimple:SuperSimpleMigratingByInviteMind"}


def table_xml(*, config: str = "", devices_xml: str = "") -> str:
    return (f'<?xml version="1.0"?>\n<migrationconfig>\n  <configuration>\n{config}\n  </configuration>\n'
            f"  <devices>\n{devices_xml}\n  </devices>\n</migrationconfig>\n")


GOOD_CONFIG = '    <devicename value="A"/>\n    <listenport value="4000"/>\n    <agent active="TRUE"/>'


def test_cmions_own_tables_load_as_they_are() -> None:
    send = devices.load_device_table(CMION_2011 / "MigrationConfigSend.xml")
    receive = devices.load_device_table(CMION_2011 / "MigrationConfigReceive.xml")
    assert (send.name, send.listen_port, send.invite_port, send.born_here) == ("A", 34871, 34872, True)
    assert (receive.name, receive.born_here, receive.names) == ("B", False, ["A"])
    [b] = send.devices
    assert (b.name, b.host, b.port, b.invite_port, b.line) == ("B", "localhost", 34873, 34874, 10)
    assert send.connect_endpoints() == ("tcp/localhost:34873",)
    # every device on loopback: a one-machine setup listens on loopback only
    assert send.listen_endpoints() == ("tcp/127.0.0.1:34871",)
    assert send.knows("B") and not send.knows("C")


def test_validate_takes_device_tables(capsys: pytest.CaptureFixture[str]) -> None:
    for name in ("MigrationConfigSend.xml", "MigrationConfigReceive.xml"):
        assert validate_file(CMION_2011 / name) == "migrationconfig"
    assert main(["validate", str(INVITE / "send" / "MigrationConfig.xml"), str(CMION_2011 / "MigrationConfigReceive.xml")]) == 0
    assert capsys.readouterr().out.count("(migrationconfig)") == 2


@pytest.mark.parametrize(("config", "devices_xml", "line", "words"), [
    ('    <devicename value="A"/>\n    <agent active="true"/>', "", 3, "listenport"),
    ('    <listenport value="70000"/>\n    <agent active="true"/>', "", 4, "70000"),
    ('    <listenport value="4000"/>\n    <agent active="yes"/>', "", 5, "yes"),
    (GOOD_CONFIG, '    <device name="B" host="h" port="x"/>', 9, "'x'"),
    (GOOD_CONFIG, '    <device name="B" port="1"/>', 9, "host"),
    (GOOD_CONFIG, '    <device name="B" host="h" port="1"/>\n    <device name="B" host="i" port="2"/>', 10,
     "listed twice (first at line 9)"),
    (GOOD_CONFIG, '    <device name="A" host="h" port="1"/>', 9, "own devicename"),
    (GOOD_CONFIG, '    <device name="a/b" host="h" port="1"/>', 9, "'/'"),
    ('    <devicename value=" A"/>\n    <listenport value="4000"/>\n    <agent active="true"/>', "", 4, "white space"),
])
def test_malformed_tables_are_refused_at_their_line(tmp_path: Path, config: str, devices_xml: str, line: int, words: str) -> None:
    path = tmp_path / "MigrationConfig.xml"
    path.write_text(table_xml(config=config, devices_xml=devices_xml))
    with pytest.raises(ConfigError) as caught:
        devices.load_device_table(path)
    assert str(caught.value).startswith(f"{path}:{line}: ") and words in str(caught.value)


BROKEN_DEVICES = ('    <device name="B" host="h" port="1"/>\n    <device name="B" host="i" port="2"/>\n'
                  '    <device name="A" host="h" port="3"/>\n    <device name="a/b" host="h" port="4"/>')
#: (line, words) of every problem of a table with GOOD_CONFIG and BROKEN_DEVICES.
BROKEN_LINES = [(10, "'B' is listed twice (first at line 9)"), (11, "own devicename"), (12, "'/'")]


def test_every_problem_of_a_table_is_reported(tmp_path: Path) -> None:
    path = tmp_path / "MigrationConfig.xml"
    path.write_text(table_xml(config=GOOD_CONFIG, devices_xml=BROKEN_DEVICES))
    found = Diagnostics()
    assert devices.read_device_table(path, found) is None
    assert [(d.path, d.line) for d in found.errors] == [(str(path), line) for line, _ in BROKEN_LINES]
    assert all(words in d.message for d, (_, words) in zip(found.errors, BROKEN_LINES, strict=True))
    with pytest.raises(ConfigError) as caught:
        devices.load_device_table(path)
    text = str(caught.value)
    assert text.startswith(f"{path}:10: ") and all(f"{path}:{line}: " in text for line, _ in BROKEN_LINES[1:]), text
    # and every schema problem, not the first one only
    path.write_text(table_xml(config='    <listenport value="70000"/>\n    <agent active="yes"/>'))
    found = Diagnostics()
    assert devices.read_device_table(path, found) is None
    assert [d.line for d in found.errors] == [4, 5]


def broken_table_configuration(tmp_path: Path) -> Path:
    """The invitation pair's sending side, its table broken in three places and a rule file broken too."""
    folder = configuration_copy(INVITE / "send", tmp_path / "send")
    table_path = folder / "MigrationConfig.xml"
    table_path.write_text(table_xml(config=GOOD_CONFIG, devices_xml=BROKEN_DEVICES))
    rules = folder / "CompManagerRules.xml"
    rules.write_text(rules.read_text().replace('Type="Migration"', 'Type="Migraton"'))
    return folder


def test_validate_reports_each_table_problem_once(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The table is checked with the configuration naming it (as ``up`` reads it), not again alone."""
    folder = broken_table_configuration(tmp_path)
    assert main(["validate", str(folder)]) == 1
    err = capsys.readouterr().err
    for line, words in BROKEN_LINES:
        assert err.count(f"MigrationConfig.xml:{line}: ") == 1 and words in err, (line, err)
    # the misspelt rule type loads, as in CMION (a warning naming the closest type), beside the table's errors
    assert "warning: " in err and "needs competency type 'Migraton'" in err and "(closest: 'Migration')" in err
    assert main(["validate", str(folder), "--json"]) == 1
    [table] = [r for r in json.loads(capsys.readouterr().out) if r["kind"] == "migrationconfig"]
    assert table["checked_with"] == str(folder / "ArchitectureConfiguration.xml") and len(table["diagnostics"]) == 3


def test_up_lists_the_tables_problems_with_the_others(tmp_path: Path, mesh: str, capsys: pytest.CaptureFixture[str]) -> None:
    folder = broken_table_configuration(tmp_path)
    assert main(["up", str(folder), "--mesh", mesh, "--no-multicast", "--state-dir", str(tmp_path / "state")]) == 2
    captured = capsys.readouterr()
    errors = [line for line in captured.err.splitlines() if line.startswith("error: ")]
    for line, words in BROKEN_LINES:
        assert any(f"{folder / 'MigrationConfig.xml'}:{line}: " in e and words in e for e in errors), (line, errors)
    warnings = [line for line in captured.err.splitlines() if line.startswith("warning: ")]
    assert any("CompManagerRules.xml" in w and "'Migraton'" in w for w in warnings), "the other files' problems too"
    assert len(errors) == 3 and "up in mesh" not in captured.out


def test_element_order_is_free_and_optional_parts_may_be_left_out(tmp_path: Path) -> None:
    # CMION's loader looked elements up by name: order never mattered; devicename and inviteport are optional.
    path = tmp_path / "t.xml"
    path.write_text('<migrationconfig><devices><device name="B" host="10.0.0.2" port="7000" inviteport="-1"/></devices>'
                    '<configuration><agent active="false"/><listenport value="7001"/><inviteport value="-1"/>'
                    "</configuration></migrationconfig>")
    table = devices.load_device_table(path)
    assert (table.name, table.invite_port, table.devices[0].invite_port, table.born_here) == (None, None, None, False)
    # a device elsewhere: listen on every interface, as CMION's server socket did
    assert table.listen_endpoints() == ("tcp/0.0.0.0:7001",)
    ipv6 = tmp_path / "v6.xml"
    ipv6.write_text(table_xml(config=GOOD_CONFIG, devices_xml='<device name="B" host="::1" port="7"/>'))
    assert devices.load_device_table(ipv6).connect_endpoints() == ("tcp/[::1]:7",)
    assert devices.load_device_table(ipv6).listen_endpoints() == ("tcp/127.0.0.1:4000",)


def library(folder: Path, class_name: str, parameters: str | None) -> Path:
    path = folder / "CompetencyLibrary.xml"
    extra = "" if parameters is None else f' ConstructorParameters="{parameters}"'
    path.write_text(f'<CompetencyLibrary><Competency ClassName="{class_name}"{extra}/></CompetencyLibrary>')
    return path


@pytest.mark.parametrize("class_name", sorted(devices.MIGRATION_CLASSES))
def test_the_library_names_the_table_relative_to_itself(tmp_path: Path, class_name: str) -> None:
    (tmp_path / "conf").mkdir()
    (tmp_path / "conf" / "Send.xml").write_bytes((CMION_2011 / "MigrationConfigSend.xml").read_bytes())
    table = table_for_library(library(tmp_path, class_name, "conf/Send.xml"))
    assert table is not None and table.name == "A" and table.path == tmp_path / "conf" / "Send.xml"


def test_android_raw_names_and_missing_tables(tmp_path: Path) -> None:
    (tmp_path / "migrationconfig.xml").write_bytes((CMION_2011 / "MigrationConfigReceive.xml").read_bytes())
    table = table_for_library(library(tmp_path, "cmion.level2.competencies.AndroidMigration", "migrationconfig"))
    assert table is not None and table.name == "B"
    # no parameter (our own class, used plainly), or another competency: no table
    assert table_for_library(library(tmp_path, "cmion_mesh.migration.manager:MigrationCompetency", None)) is None
    assert table_for_library(library(tmp_path, "cmion_mesh.competencies.cmion_test:TestCompetency1", "x.xml")) is None
    lib = library(tmp_path, "cmion.level2.competencies.Migration", "Nowhere.xml")
    with pytest.raises(ConfigError, match=rf"^{lib}:1: cmion.level2.competencies.Migration: parameter 1 \(its device table\) "
                                          r"'Nowhere.xml' not found \(looked beside this file"):
        table_for_library(lib)


def test_the_migration_competency_takes_cmions_parameter() -> None:
    competency = MigrationCompetency("MigrationConfigSend.xml")
    assert (competency.type, competency.device_table, competency.constructor_parameters) == \
        ("Migration", "MigrationConfigSend.xml", ("MigrationConfigSend.xml",))
    assert MigrationCompetency().device_table == "" and MigrationCompetency().constructor_parameters == ()


def test_precedence_explicit_settings_win_over_the_table(tmp_path: Path) -> None:
    table = devices.load_device_table(CMION_2011 / "MigrationConfigSend.xml")
    filled = devices.with_table_endpoints(TransportConfig(multicast=False), table)
    assert (filled.connect, filled.listen, filled.multicast) == (("tcp/localhost:34873",), ("tcp/127.0.0.1:34871",), False)
    mine = devices.with_table_endpoints(TransportConfig(connect=("tcp/127.0.0.1:1",)), table)
    assert (mine.connect, mine.listen) == (("tcp/127.0.0.1:1",), ("tcp/127.0.0.1:34871",))
    zenoh_file = TransportConfig(config_file="zenoh.json5")
    assert devices.with_table_endpoints(zenoh_file, table) == zenoh_file
    assert devices.birth(table, None) == devices.DEFAULT_COMPANION and devices.birth(table, "spirit") == "spirit"
    receive = devices.load_device_table(CMION_2011 / "MigrationConfigReceive.xml")
    assert devices.birth(receive, "spirit") is None and devices.birth(None, "spirit") == "spirit"
    folder = tmp_path / "plain"
    folder.mkdir()
    for name in ("CompManagerRules.xml", "CompetencyLibrary.xml"):
        (folder / name).write_bytes((INVITE / "send" / name).read_bytes())
    arch_path = folder / "ArchitectureConfiguration.xml"
    arch_path.write_text('<ArchitectureConfiguration CompetencyManagerRulesFile="CompManagerRules.xml" '
                         'CompetencyLibraryConfigurationFile="CompetencyLibrary.xml"/>')
    assert embodiment_name(table, load_architecture(arch_path)) == "A"  # the folder's name yields
    assert embodiment_name(None, load_architecture(arch_path)) == "plain"
    arch_path.write_text('<ArchitectureConfiguration Embodiment="robot" CompetencyManagerRulesFile="CompManagerRules.xml" '
                         'CompetencyLibraryConfigurationFile="CompetencyLibrary.xml"/>')
    with pytest.raises(ConfigError, match=r"Embodiment='robot' but its device table .* names this embodiment 'A' \(give --name"):
        embodiment_name(table, load_architecture(arch_path))


def configuration_copy(source: Path, target: Path, values: dict[str, str] | None = None, *, java_names: bool = False) -> Path:
    """A copy of a test configuration folder with other attribute ``values`` (ports, names) and,
    unless ``java_names``, our class names for CMION's."""
    target.mkdir(parents=True)
    for path in source.iterdir():
        text = path.read_text()
        for old, new in {**({} if java_names else OURS), **(values or {})}.items():
            text = text.replace(f'"{old}"', f'"{new}"')
        (target / path.name).write_text(text)
    return target


def test_an_embodiment_built_from_a_configuration_with_a_table(network: MemoryNetwork, tmp_path: Path, mesh: str) -> None:
    send = configuration_copy(INVITE / "send", tmp_path / "send")
    receive = configuration_copy(INVITE / "receive", tmp_path / "receive")
    config = "ArchitectureConfiguration.xml"
    a = Embodiment.from_architecture(send / config, mesh=mesh, transport=MemoryTransport(network, "a"), state_dir=tmp_path / "A")
    b = Embodiment.from_architecture(receive / config, mesh=mesh, transport=MemoryTransport(network, "b"), state_dir=tmp_path / "B")
    try:
        with a, b, MemoryTransport(network, "cli") as t, MeshClient(t, mesh) as client:
            assert (a.name, b.name) == ("A", "B")
            wait_for(lambda: a.inhabitant == devices.DEFAULT_COMPANION, 5, "the companion born where agent is active")
            assert b.inhabitant is None and a.describe()["devices"] == ["B"]
            # CMION's rule "Migration *" -> competency Migration with DeviceName works unchanged
            report = client.act("A", "Migration", ["B"], timeout=20)
            assert report.status == "succeeded", report
            wait_for(lambda: b.inhabitant == devices.DEFAULT_COMPANION, 5, "moved by DeviceName")
    finally:
        a.transport.close()
        b.transport.close()
