"""Every configuration CMION 2011 started, starts: competency types as CMION's classes set them,
rules naming a type nothing provides (loaded, failing when they run), files found beside the file
naming them or in the working directory, each problem said once, and device tables as CMION read
them. Every file here is written for the test.
"""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
from pathlib import Path

import pytest

from cmion_mesh.body import java_classes as portmap
from cmion_mesh.body.architecture import embodiment_name, load_architecture
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.standin import StandInCompetency
from cmion_mesh.body.validate import check_embodiment
from cmion_mesh.classes import construct
from cmion_mesh.cli import main as cli
from cmion_mesh.client import MeshClient
from cmion_mesh.competency import Competency
from cmion_mesh.diagnostics import Diagnostics
from cmion_mesh.migration import devices
from cmion_mesh.procs import Daemon, cli_argv, free_port, unique_mesh
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parent.parent


def run_cli(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(args))
    return code, out.getvalue(), err.getvalue()


def child_env() -> dict[str, str]:
    """A child started in another folder still imports this tree's package."""
    return {"PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)}


def rule(name: str, competency_type: str, parameters: int = 0, **run_parameters: str) -> str:
    """A rule of one plan of one step (its ``<Competency>`` on the rule's second line)."""
    params = "".join(f'<Parameter No="{n}" Value="*"/>' for n in range(1, parameters + 1))
    run = "".join(f'<CompetencyParameter Name="{k}" Value="{v}"/>' for k, v in run_parameters.items())
    return (f'<Rule><MindAction Name="{name}">{params}</MindAction><CompetencyExecutionPlan>\n'
            f'<Competency ID="1" Type="{competency_type}">{run}</Competency>\n</CompetencyExecutionPlan></Rule>\n')


#: CMION's TestCompetency2 (type TestType2) writes a random number to the blackboard property named.
REMEMBER = rule("Remember", "TestType2", 1, RandomOutName="$parameter1")


def configuration(folder: Path, *, rules: str, library: str, name: str = "", rules_file: str = "rules.xml",
                  library_file: str = "library.xml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    embodiment = f'Embodiment="{name}" ' if name else ""
    config = folder / "ArchitectureConfiguration.xml"
    config.write_text(f'<ArchitectureConfiguration {embodiment}CompetencyManagerRulesFile="{rules_file}" '
                      f'CompetencyLibraryConfigurationFile="{library_file}"/>\n')
    if rules:
        (folder / rules_file).write_text(f"<CompetencyManagerRules>\n{rules}</CompetencyManagerRules>\n")
    if library:
        (folder / library_file).write_text(f"<CompetencyLibrary>\n{library}</CompetencyLibrary>\n")
    return config


# --- 1. competency types as CMION's classes set them ------------------------------------------------------------

#: Class -> the type its CMION constructor set (a library written for the test, one class a line).
TYPED = {
    "cmion.inTheWild.competencies.VirtualEmysConnector": "VirtualEmys",
    "cmion.inTheWild.competencies.KinectTrackerConnector": "Kinect",
    "cmion.inTheWild.competencies.Cereproc": "TTS",
    "cmion.TeamBuddy.competencies.Cereproc": "TTS",
    "cmion.addOns.samgar.competencies.test.TestSamgarCompetency": "SamgarTester",
    "cmion.addOns.samgar.competencies.test.TestSamgarCompetency2": "SamgarTester2",
    "cmion.level2.competencies.test.TestCompetency7": "TestType7",
    "cmion.level2.competencies.test.TestCompetency8": "TestType8",
    "cmion.TeamBuddy.competencies.Navigate": "Navigation",
    "cmion.level2.competencies.ExampleCompetency": "DetectPerson",
    "teambuddyInterface.InterfaceCompetency": "InterfaceCompetency",
}
SAMGAR = {"VirtualEmysConnector", "KinectTrackerConnector", "TestSamgarCompetency", "TestSamgarCompetency2"}


def typed_library() -> str:
    lines = []
    for java in TYPED:
        short = java.rpartition(".")[2]
        element = f'SamgarCompetency ClassName="{java}" Port="{short.lower()}"' if short in SAMGAR else f'Competency ClassName="{java}"'
        lines.append(f"<{element}/>\n")
    return "".join(lines) + '<Competency ClassName="cmion.level2.competencies.test.TestCompetency5"/>\n'


def typed_rules() -> str:
    wanted = dict.fromkeys([*TYPED.values(), "TestType4"])
    return "".join(rule(f"do{t}", t) for t in wanted).replace('Name="doVirtualEmys"', 'Name="wozTalk"')


def test_standins_provide_the_types_cmions_classes_set(tmp_path: Path) -> None:
    config = configuration(tmp_path, rules=typed_rules(), library=typed_library(), name="typed")
    found = Diagnostics()
    _, competencies = check_embodiment(tmp_path / "rules.xml", tmp_path / "library.xml", diagnostics=found)
    assert not found.errors, [str(d) for d in found.errors]
    assert not [d for d in found.warnings if "needs competency type" in d.message], "every rule's type is provided"
    by_class = {c.java: c.type for c in competencies if isinstance(c, StandInCompetency)}
    assert by_class == TYPED
    [ported] = [c for c in competencies if not isinstance(c, StandInCompetency)]
    assert ported.type == "TestType4", "TestCompetency5 provided TestType4 in CMION"
    # the stand-in's warning names the rule lines depending on its CMION type
    [emys] = [d for d in found.warnings if "VirtualEmysConnector" in d.message]
    assert emys.line == 2 and "rule types depending on it: VirtualEmys (rules.xml:3)" in emys.message, emys.message
    assert load_architecture(config).embodiment == "typed"


def test_every_competency_of_the_port_map_has_its_cmion_type() -> None:
    for port in portmap.PORT_MAP.values():
        if port.kind in ("competency", "Samgar competency"):
            assert port.types, f"{port.java}: no competency type"
        if port.action == "ported" and port.kind == "competency":
            assert port.target is not None
            assert construct(port.target, Competency).type in port.types, f"{port.target} provides what {port.java} did"
    assert portmap.is_java_name("teambuddyInterface.InterfaceCompetency"), "a class of CMION outside cmion. is Java too"
    assert not portmap.is_java_name("teambuddyInterface.Other"), "a Python name otherwise"


def test_an_action_on_a_typed_standin_fails_naming_the_class(tmp_path: Path) -> None:
    """``wozTalk`` needs ``VirtualEmys``: it is found (the stand-in), and the action fails naming the
    class, not "no competency of type VirtualEmys"."""
    config = configuration(tmp_path, rules=typed_rules(), library=typed_library(), name="typed")
    network = MemoryNetwork()
    with MemoryTransport(network, "body") as body_net, MemoryTransport(network, "tester") as tester, \
            Embodiment.from_architecture(config, mesh="typed", transport=body_net) as body, MeshClient(tester, "typed") as client:
        client.wait_for_embodiment(body.name, timeout=10)
        talk = client.act(body.name, "wozTalk", timeout=20)
        assert talk.status == "failed"
        assert ("competency type 'VirtualEmys' is provided only by stand-in cmion.inTheWild.competencies.VirtualEmysConnector "
                "(no cmion-mesh equivalent; see docs/portmap.md)") in talk.reason, talk.reason
        say = client.act(body.name, "doTTS", timeout=20)
        assert "stand-ins cmion.inTheWild.competencies.Cereproc, cmion.TeamBuddy.competencies.Cereproc" in say.reason, say.reason


# --- 2. a rule needing a type nothing provides: loaded, failing when it runs --------------------------------------

SMS_RULES = rule("sendSMS", "SMSSender", 2) + REMEMBER
SMS_LIBRARY = ('<Competency ClassName="cmion.inTheWild.competencies.SMSReceiver"/>\n'
               '<Competency ClassName="cmion.level2.competencies.test.TestCompetency2"/>\n')
WHY_SMS = ("step 1 needs competency type 'SMSSender', which no competency of this embodiment provides "
           "(closest: 'SMSReceiver')")


def test_a_rule_needing_an_absent_type_loads_and_its_action_fails_with_the_reason(tmp_path: Path) -> None:
    folder = tmp_path / "sms"
    configuration(folder, rules=SMS_RULES, library=SMS_LIBRARY, name="sms")
    rules = folder / "rules.xml"
    code, _, err = run_cli("validate", str(folder))
    assert code == 0, err
    warned = f"warning: {rules}:3: rule 'sendSMS * *', plan 1: {WHY_SMS}: loaded as CMION loaded it, the action fails when it runs"
    assert err.count(warned) == 1, err
    code, _, err = run_cli("validate", "--strict", str(folder))
    assert code == 1 and f"error: {rules}:3: rule 'sendSMS * *', plan 1: {WHY_SMS}" in err, err
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    net = ["--mesh", unique_mesh(), "--no-multicast"]
    with Daemon(cli_argv("up", str(folder), *net, "--listen", endpoint, "--state-dir", str(tmp_path / "state")), name="sms") as daemon:
        daemon.wait_line("up in mesh", 30)
        assert any(warned in line for line in daemon.lines), daemon.lines
        code, out, err = run_cli("act", "sms", "sendSMS", "0123", "hello", *net, "--connect", endpoint)
        assert code == 1 and f"no executable plan for 'sendSMS 0123 hello': rule at line 2, plan 1: {WHY_SMS}" in out + err, \
            (out, err)
        code, out, err = run_cli("act", "sms", "Remember", "note", *net, "--connect", endpoint)
        assert code == 0, (out, err)


# --- 3. files found where CMION found them ---------------------------------------------------------------------

TABLE_WITHOUT_NAME = """<migrationconfig>
<configuration>
<listenport value="{port}"/>
<agent active="false"/>
</configuration>
<devices>
<device name="elsewhere" host="127.0.0.1" port="{other}"/>
</devices>
</migrationconfig>
"""


def launcher_and_scenario(tmp_path: Path) -> tuple[Path, Path]:
    """A scenario folder whose configuration names rules and a device table that live in the
    launcher's folder, as real projects started from their launcher folder had them."""
    launcher, scenario = tmp_path / "launcher", tmp_path / "scenario"
    configuration(scenario, rules="", name="scene",
                  library='<Competency ClassName="cmion.level2.competencies.Migration" ConstructorParameters="table.xml"/>\n'
                          '<Competency ClassName="cmion.level2.competencies.test.TestCompetency2"/>\n')
    launcher.mkdir()
    (launcher / "rules.xml").write_text(f"<CompetencyManagerRules>\n{REMEMBER}</CompetencyManagerRules>\n")
    (launcher / "table.xml").write_text(TABLE_WITHOUT_NAME.format(port=free_port(), other=free_port()))
    return launcher, scenario


def test_a_configuration_started_from_another_folder_finds_its_files_in_the_working_directory(tmp_path: Path) -> None:
    launcher, scenario = launcher_and_scenario(tmp_path)
    checked = subprocess.run(cli_argv("validate", "../scenario"), cwd=launcher, env={**os.environ, **child_env()},
                             capture_output=True, text=True, timeout=60)
    assert checked.returncode == 0, checked
    rules_note = (f"note: {scenario / 'ArchitectureConfiguration.xml'}:1: CompetencyManagerRulesFile 'rules.xml' is not beside "
                  f"this file: found in the working directory, {launcher / 'rules.xml'}")
    table_note = (f"note: {scenario / 'library.xml'}:2: cmion.level2.competencies.Migration: parameter 1 (its device table) "
                  f"'table.xml' is not beside this file: found in the working directory, {launcher / 'table.xml'}")
    assert checked.stderr.count(rules_note) == 1 and checked.stderr.count(table_note) == 1, checked.stderr
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    net = ["--mesh", unique_mesh(), "--no-multicast"]
    with Daemon(cli_argv("up", "../scenario", *net, "--listen", endpoint, "--state-dir", str(tmp_path / "state")),
                env=child_env(), cwd=launcher, name="scene") as daemon:
        daemon.wait_line("up in mesh", 30)
        # a table with no devicename: the name is the configuration's (CMION's devicename was "")
        daemon.wait_line(f"device table {launcher / 'table.xml'}: embodiment 'scene', knows elsewhere", 5)
        assert sum(rules_note in line for line in daemon.lines) == 1, daemon.lines
        code, out, err = run_cli("act", "scene", "Remember", "note", *net, "--connect", endpoint)
        assert code == 0, (out, err)


def test_a_file_found_nowhere_names_both_places(tmp_path: Path) -> None:
    _, scenario = launcher_and_scenario(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    checked = subprocess.run(cli_argv("validate", str(scenario)), cwd=elsewhere, env={**os.environ, **child_env()},
                             capture_output=True, text=True, timeout=60)
    assert checked.returncode == 1, checked
    errors = [line for line in checked.stderr.splitlines() if line.startswith("error: ")]
    assert f"error: {scenario / 'ArchitectureConfiguration.xml'}:1: CompetencyManagerRulesFile 'rules.xml' not found (looked " \
           f"beside this file, at {scenario / 'rules.xml'}, and in the working directory, at {elsewhere / 'rules.xml'})" in errors
    assert f"error: {scenario / 'library.xml'}:2: cmion.level2.competencies.Migration: parameter 1 (its device table) " \
           f"'table.xml' not found (looked beside this file, at {scenario / 'table.xml'}, and in the working directory, " \
           f"at {elsewhere / 'table.xml'})" in errors
    assert len(errors) == 2, errors


# --- 4. each problem once ---------------------------------------------------------------------------------------


def test_a_library_naming_a_missing_table_is_one_error(tmp_path: Path, mesh: str) -> None:
    folder = tmp_path / "lost"
    configuration(folder, rules=REMEMBER, name="lost",
                  library='<Competency ClassName="cmion.level2.competencies.Migration" ConstructorParameters="gone.xml"/>\n'
                          '<Competency ClassName="cmion.level2.competencies.test.TestCompetency2"/>\n')
    code, _, err = run_cli("validate", str(folder))
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert code == 1 and len(errors) == 1 and f"{folder / 'library.xml'}:2: " in errors[0] and "'gone.xml' not found" in errors[0], err
    code, _, err = run_cli("up", str(folder), "--mesh", mesh, "--no-multicast", "--state-dir", str(tmp_path / "state"))
    assert code == 2 and [line for line in err.splitlines() if line.startswith("error: ")] == errors, err


def test_a_table_without_agent_is_one_error_saying_cmion_could_not_run_it(tmp_path: Path) -> None:
    table = tmp_path / "MigrationConfig.xml"
    table.write_text('<migrationconfig>\n<configuration>\n<devicename value="A"/>\n<listenport value="4000"/>\n</configuration>\n'
                     "<devices/>\n</migrationconfig>\n")
    code, _, err = run_cli("validate", str(table))
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert code == 1 and errors == [
        f"error: {table}:2: no <agent> in <configuration>: CMION 2011 could not run this table either (its Migration competency "
        'read there whether the companion is born here); add <agent active="false"/> (or "true" on the embodiment where the '
        "companion is born)"], err


# --- 5. device tables read as CMION read them --------------------------------------------------------------------


@pytest.mark.parametrize("devicename", ["", '<devicename value=""/>'])
def test_a_table_without_devicename_takes_the_configurations_or_the_command_lines_name(tmp_path: Path, devicename: str) -> None:
    folder = tmp_path / "robot"
    configuration(folder, rules="", library='<Competency ClassName="cmion.level2.competencies.Migration" '
                                            'ConstructorParameters="table.xml"/>\n')
    (folder / "rules.xml").write_text("<CompetencyManagerRules/>")
    (folder / "table.xml").write_text(TABLE_WITHOUT_NAME.format(port=4000, other=4001).replace(
        "<configuration>", f"<configuration>{devicename}"))
    table = devices.load_device_table(folder / "table.xml")
    assert table.name is None
    config = folder / "ArchitectureConfiguration.xml"
    assert embodiment_name(table, load_architecture(config)) == "robot", "the folder's name"
    assert embodiment_name(table, load_architecture(config, name="given")) == "given", "the command line's"
    config.write_text(config.read_text().replace("<ArchitectureConfiguration ", '<ArchitectureConfiguration Embodiment="named" '))
    assert embodiment_name(table, load_architecture(config)) == "named", "the configuration's"

