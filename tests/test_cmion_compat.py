"""CMION 2011 projects as they are: Java class names (the port map), stand-ins, every problem in one
``validate`` run, and what CMION's loaders accepted (element order, Android names, parameters).

Mostly in-process checks on the in-memory transport; one real ``cmion-mesh up`` per configuration
kind, in its own process, driven by ``cmion-mesh act`` and by a stand-in FAtiMA.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from cmion_mesh.body import java_classes as portmap
from cmion_mesh.body.architecture import load_architecture, read_architecture
from cmion_mesh.body.embodiment import Embodiment
from cmion_mesh.body.library import load_library
from cmion_mesh.body.rules import load_rules
from cmion_mesh.body.standin import StandInCompetency, StandInComponent
from cmion_mesh.body.validate import check_embodiment, validate_paths
from cmion_mesh.classes import split_parameters
from cmion_mesh.cli import main as cli
from cmion_mesh.client import MeshClient
from cmion_mesh.diagnostics import Diagnostics
from cmion_mesh.errors import ConfigError
from cmion_mesh.procs import Daemon, cli_argv, free_port, unique_mesh
from cmion_mesh.storage import load_world_model_init
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

from .conftest import DATA

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parent.parent
INTHEWILD = DATA / "cmion2011-inthewild"
ANDROID = DATA / "cmion2011-android"
INVITE = DATA / "cmion2011-invite"
#: Every folder of CMION-shaped files, found rather than listed so that none is left out: the
#: committed copy of the 2011 originals and our own.
FOLDERS = sorted({p.parent for p in DATA.rglob("*.xml")})
#: Every architecture configuration among them.
CONFIGURATIONS = [p for p in sorted(DATA.rglob("*.xml")) if "<ArchitectureConfiguration" in p.read_text(errors="replace")]

#: Every class named in CMION 2011's real configuration files (protocols.md section 5), the
#: generic bases and the test competencies.
SECTION_5 = [
    "cmion.level2.competencies.Migration", "cmion.level2.competencies.AndroidMigration",
    "cmion.level3.fatima.FAtiMAConnector", "cmion.level3.supersimplemind.SuperSimpleMigratingMindConnector",
    "cmion.level3.supersimplemind.SuperSimpleMigratingByInviteMindConnector", "cmion.level3.supersimplemind.SuperSimpleMindConnector",
    "cmion.addOns.monitors.CmionEventMonitor", "cmion.addOns.manipulators.WorldModelManipulator",
    "cmion.addOns.manipulators.RemoteActionSimulator", "cmion.addOns.monitors.IonEventMonitor", "cmion.addOns.samgar.SamgarConnector",
    *(f"cmion.level2.competencies.test.TestCompetency{n}" for n in range(1, 7)),
    "cmion.addOns.samgar.competencies.test.TestSamgarCompetency", "cmion.addOns.samgar.competencies.test.TestSamgarCompetency2",
    "cmion.inTheWild.competencies.GretaBMLCreator", "cmion.inTheWild.competencies.GretaBMLSender",
    "cmion.inTheWild.competencies.SMSReceiver", "cmion.inTheWild.competencies.SMSSender", "cmion.inTheWild.competencies.EmysAskQuestion",
    "cmion.inTheWild.competencies.KinectTrackerConnector", "cmion.inTheWild.competencies.VirtualEmysConnector",
    "cmion.emysTK.SimpleTalk", "cmion.emysTK.SimpleAnimation", "cmion.inTheWild.ai.DIAgent", "cmion.inTheWild.ai.ReviewAgent",
    "cmion.inTheWild.woz.InTheWildWoz", "cmion.inTheWild.woz.ITWEmysWoz", "cmion.TeamBuddy.competencies.DeskMonitor",
    "cmion.personalguide.mind.SimpleMind", "cmion.personalguide.competencies.FaceAnimator",
    "cmion.personalguide.competencies.TalkCompetency",
    "cmion.level2.RemoteCompetency", "cmion.level2.RemoteTCPCompetency", "cmion.level3.AgentMindConnector", "cmion.level2.Competency",
]


def run_cli(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(args))
    return code, out.getvalue(), err.getvalue()


# --- the port map ---------------------------------------------------------------------------------------------


def test_port_map_covers_every_class_of_real_configurations() -> None:
    missing = [name for name in SECTION_5 if name not in portmap.PORT_MAP]
    assert not missing, missing
    targets = {name: port.target for name, port in portmap.PORT_MAP.items()}
    for n in range(1, 7):
        assert targets[f"cmion.level2.competencies.test.TestCompetency{n}"] == f"cmion_mesh.competencies.cmion_test:TestCompetency{n}"
    assert targets["cmion.level2.competencies.Migration"] == targets["cmion.level2.competencies.AndroidMigration"] == \
        "cmion_mesh.migration.manager:MigrationCompetency"
    assert targets["cmion.level3.fatima.FAtiMAConnector"] == "cmion_mesh.minds.fatima.connector:FAtiMAConnector"
    assert targets["cmion.level3.supersimplemind.SuperSimpleMigratingByInviteMindConnector"] == \
        "cmion_mesh.minds.supersimple:SuperSimpleMigratingByInviteMind"
    gui = [p for p in portmap.PORT_MAP.values() if p.kind == "GUI add-on"]
    assert gui and all(p.action == "command" and p.command and p.command.startswith("cmion-mesh ") for p in gui)
    for port in portmap.PORT_MAP.values():
        # one class of CMION's sources lived outside its package (TeamBuddy's interface)
        assert (port.java.startswith(portmap.JAVA_PREFIX) or port.java == "teambuddyInterface.InterfaceCompetency") and port.note, port
        assert portmap.is_java_name(port.java), port
        if port.action == "ported" and port.target is not None:
            module, _, name = port.target.partition(":")
            assert hasattr(importlib.import_module(module), name), port.target


def test_port_map_document_is_generated_from_the_table() -> None:
    text = (ROOT / "docs" / "portmap.md").read_text()
    assert text == portmap.markdown(), "docs/portmap.md is stale: python -m cmion_mesh.body.java_classes > docs/portmap.md"
    for name in portmap.PORT_MAP:
        assert f"`{name}`" in text, name


# --- every CMION file ------------------------------------------------------------------------------------------


def data_id(path: Path) -> str:
    return path.relative_to(DATA).as_posix()


def test_the_data_is_all_found() -> None:
    assert len(FOLDERS) >= 6 and DATA / "invite" / "send" in FOLDERS and DATA / "cmion2011" in FOLDERS
    assert len(CONFIGURATIONS) >= 7 and DATA / "invite" / "receive" / "ArchitectureConfiguration.xml" in CONFIGURATIONS


@pytest.mark.parametrize("folder", FOLDERS, ids=data_id)
def test_every_file_validates(folder: Path) -> None:
    files = sorted(str(p) for p in folder.glob("*.xml"))
    reports = validate_paths(files)
    assert [r.path for r in reports] == files
    for report in reports:
        assert not report.diagnostics.errors, [str(d) for d in report.diagnostics.errors]
    kinds = {r.kind for r in reports}
    assert "ArchitectureConfiguration" in kinds and "CompetencyLibrary" in kinds and "CompetencyManagerRules" in kinds


def test_validate_takes_the_whole_test_data_tree_in_one_run() -> None:
    """Every XML file under tests/data (subfolders too: a project with a folder per embodiment)."""
    code, out, err = run_cli("validate", str(DATA))
    assert code == 0, err
    every = sorted(DATA.rglob("*.xml"))
    assert f"{len(every)} files: 0 failed; 0 errors" in err, err
    assert "(migrationconfig)" in out and "(ArchitectureConfiguration" in out


@pytest.mark.parametrize("config", CONFIGURATIONS, ids=data_id)
def test_each_configuration_starts(config: Path, tmp_path: Path, mesh: str) -> None:
    name = re.sub(r"[^A-Za-z0-9_-]", "-", config.stem)  # the invitation pair shares a folder: one name each
    with MemoryTransport(MemoryNetwork(), "local") as transport, \
            Embodiment.from_architecture(config, mesh=mesh, transport=transport, name=name, state_dir=tmp_path) as body:
        described = body.describe()
        assert described["name"] == name
        real = {c.type for c in body.execution.competencies if not isinstance(c, StandInCompetency)}
        assert set(described["competency_types"]) == real, "stand-ins are listed apart, not offered as competency types"


# --- stand-ins --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def inthewild() -> Iterator[tuple[Embodiment, MeshClient]]:
    network = MemoryNetwork()
    with MemoryTransport(network, "body") as body_net, MemoryTransport(network, "tester") as tester, \
            Embodiment.from_architecture(INTHEWILD / "ArchitectureConfiguration.xml", mesh="inthewild", transport=body_net) as body, \
            MeshClient(tester, "inthewild") as client:
        client.wait_for_embodiment(body.name, timeout=10)  # its watchers start here, not in a test
        client.watch_actions(body.name)  # which act() keeps open from its first call on
        yield body, client


def test_unknown_java_classes_load_as_standins_and_are_listed(inthewild: tuple[Embodiment, MeshClient]) -> None:
    body, client = inthewild
    assert body.name == "cmion2011-inthewild", "no Embodiment attribute: the folder's name"
    listed = {s["class"]: s for s in client.describe(body.name)["stand_ins"]}
    assert set(listed) == {
        "cmion.inTheWild.ai.DIAgent", "cmion.addOns.samgar.SamgarConnector", "cmion.inTheWild.competencies.KinectTrackerConnector",
        "cmion.inTheWild.competencies.VirtualEmysConnector", "cmion.inTheWild.competencies.GretaBMLCreator",
        "cmion.inTheWild.competencies.GretaBMLSender", "cmion.inTheWild.competencies.SMSSender",
        "cmion.inTheWild.competencies.MoodLamp"}, "GUI add-ons are replaced by commands, not stood in for"
    assert listed["cmion.inTheWild.ai.DIAgent"]["kind"] == "mind connector"
    assert listed["cmion.inTheWild.ai.DIAgent"]["where"].endswith("ArchitectureConfiguration.xml:15")
    assert listed["cmion.inTheWild.competencies.KinectTrackerConnector"]["samgar_port"] == "Kinect"
    assert listed["cmion.inTheWild.competencies.GretaBMLSender"]["types"] == ["GretaBMLSender"], "its own type, no other"
    assert listed["cmion.inTheWild.competencies.MoodLamp"]["kind"] == "not in the port map"
    components = {c.name: c for c in body.sim.components}
    assert isinstance(components["DIAgent"], StandInComponent) and components["DIAgent"].parameters == ("5228", "dialogue.xml")
    sms = next(c for c in body.execution.competencies if c.name == "SMSSender")
    assert sms.constructor_parameters == ("modem.a", "ttyS1", "9600", "MODEM NAME"), "split as CMION split them"
    assert "GretaBMLSender" not in client.describe(body.name)["competency_types"]


def test_an_action_needing_a_standin_fails_naming_the_class(inthewild: tuple[Embodiment, MeshClient]) -> None:
    body, client = inthewild
    talk = client.act(body.name, "talk", ["hello"], timeout=20)
    assert talk.status == "failed"
    assert ("competency type 'GretaBMLCreator' is provided only by stand-in cmion.inTheWild.competencies.GretaBMLCreator "
            "(no cmion-mesh equivalent; see docs/portmap.md)") in talk.reason, talk.reason
    look = client.act(body.name, "look", ["door"], timeout=20)
    assert look.status == "failed"
    assert "stand-in cmion.inTheWild.competencies.MoodLamp (not in the port map; see docs/portmap.md)" in look.reason, look.reason
    remember = client.act(body.name, "Remember", ["note"], timeout=20)
    assert remember.status == "succeeded", remember.reason


# --- validate: every problem, one run ------------------------------------------------------------------------


BROKEN = {
    "rules.xml": """<CompetencyManagerRules>
<Rule><MindAction Name="A"/><CompetencyExecutionPlan>
<Competency ID="1" Type="T" Dependency="9"/>
</CompetencyExecutionPlan></Rule>
<Rule><MindAction Name="B"/><MindAction Name="C"/><CompetencyExecutionPlan/></Rule>
<Rule><MindAction Name="D"/><CompetencyExecutionPlan>
<Competency ID="1" Type="Fly"/>
</CompetencyExecutionPlan></Rule>
</CompetencyManagerRules>""",
    "library.xml": """<CompetencyLibrary>
<Competency ClassName="no.such.module:X"/>
<Competency ClassName="builtins:dict"/>
<Competency ClassName="cmion.level2.RemoteTCPCompetency"/>
<Competency ClassName="cmion.level2.competencies.test.TestCompetency1"/>
</CompetencyLibrary>""",
    "schema.xml": """<CompetencyManagerRules>
<Rule><MindAction/><CompetencyExecutionPlan/></Rule>
<Rule><MindAction Name="x"><Parameter No="zero" Value="1"/></MindAction><CompetencyExecutionPlan/></Rule>
</CompetencyManagerRules>""",
    "world.xml": """<WorldModel>
<Agent Name="a/b"/>
<Object Name="ok"><Property Name="n" Value="x" Type="int"/></Object>
</WorldModel>""",
    "ArchitectureConfiguration.xml": """<ArchitectureConfiguration CompetencyManagerRulesFile="rules.xml"
 CompetencyLibraryConfigurationFile="library.xml" WorldModelInitFile="nowhere">
<ArchitectureComponent ClassName="nowhere.at.all:Mind"/>
<ArchitectureComponent ClassName="cmion.level3.AgentMindConnector"/>
</ArchitectureConfiguration>""",
}
#: (file, line, words) of every problem in BROKEN.
EXPECTED = [
    ("rules.xml", 3, "9"), ("rules.xml", 5, "exactly one <MindAction>"),
    ("library.xml", 2, "cannot import module 'no.such.module'"), ("library.xml", 3, "not a cmion_mesh.competency.Competency"),
    ("library.xml", 4, "abstract base class"),
    ("schema.xml", 2, "'Name' is required"), ("schema.xml", 3, "'zero'"),
    ("world.xml", 2, "'a/b'"), ("world.xml", 3, "property 'n'"),
    ("ArchitectureConfiguration.xml", 2, "WorldModelInitFile 'nowhere' not found"),
    ("ArchitectureConfiguration.xml", 3, "cannot import module 'nowhere.at.all'"),
    ("ArchitectureConfiguration.xml", 4, "subclass cmion_mesh.mind:Mind instead"),
]


def test_validate_lists_every_problem_of_every_file_in_one_run(tmp_path: Path) -> None:
    for name, text in BROKEN.items():
        (tmp_path / name).write_text(text)
    code, out, err = run_cli("validate", str(tmp_path), "--json")
    assert code == 1
    found = [(Path(d["path"]).name, d["line"], d["message"]) for r in json.loads(out) for d in r["diagnostics"]
             if d["severity"] == "error"]
    for name, line, words in EXPECTED:
        assert any(f == name and n == line and words in m for f, n, m in found), (name, line, words, found)
    # rule D's step needs type Fly, which nothing provides: it loads as in CMION, a warning at its line
    warned = [(Path(d["path"]).name, d["line"], d["message"]) for r in json.loads(out) for d in r["diagnostics"]
              if d["severity"] == "warning"]
    assert any(f == "rules.xml" and n == 7 and "'Fly'" in m for f, n, m in warned), warned
    assert not any("'Fly'" in m for _, _, m in found), "a warning, not an error"
    code, out, err = run_cli("validate", str(tmp_path))
    assert code == 1 and "Traceback" not in err
    assert all(f"{tmp_path / name}:{line}:" in err for name, line, _ in EXPECTED if name != "ArchitectureConfiguration.xml")


def test_warnings_pass_unless_strict(tmp_path: Path) -> None:
    (tmp_path / "library.xml").write_text('<CompetencyLibrary>\n<Competency ClassName="cmion.emysTK.SimpleTalk"/>\n</CompetencyLibrary>')
    code, out, err = run_cli("validate", str(tmp_path / "library.xml"))
    assert code == 0 and "1 warning" in out
    assert f"warning: {tmp_path / 'library.xml'}:2: cmion.emysTK.SimpleTalk" in err and "SimpleTalk" in err
    code, out, err = run_cli("validate", "--strict", str(tmp_path / "library.xml"))
    assert code == 1 and f"error: {tmp_path / 'library.xml'}:2: cmion.emysTK.SimpleTalk" in err and "--strict" in err


def test_up_refuses_on_errors_and_lists_them_all(tmp_path: Path, mesh: str) -> None:
    for name, text in BROKEN.items():
        (tmp_path / name).write_text(text)
    code, out, err = run_cli("up", str(tmp_path), "--mesh", mesh, "--no-multicast", "--state-dir", str(tmp_path / "state"))
    assert code == 2, (out, err)
    for name, line, words in EXPECTED:
        if name in ("rules.xml", "library.xml", "ArchitectureConfiguration.xml"):
            assert f"{tmp_path / name}:{line}:" in err and words in err, (name, line, words, err)
    assert "up in mesh" not in out


def test_validate_builds_the_components_as_up_does(tmp_path: Path, mesh: str) -> None:
    """A constructor refusing its parameters fails ``validate`` as it fails ``up``, at the entry's
    line, naming the class; building them opens nothing (a component that would is refused unbuilt)."""
    (tmp_path / "r.xml").write_text("<CompetencyManagerRules/>")
    (tmp_path / "l.xml").write_text("<CompetencyLibrary/>")
    state = tmp_path / "never-made"
    (tmp_path / "ArchitectureConfiguration.xml").write_text(
        '<ArchitectureConfiguration Embodiment="x" CompetencyManagerRulesFile="r.xml" CompetencyLibraryConfigurationFile="l.xml">\n'
        '<ArchitectureComponent ClassName="cmion.level3.fatima.FAtiMAConnector" ConstructorParameters="modular, bogus"/>\n'
        '<ArchitectureComponent ClassName="cmion_mesh.minds.planner.mind:PlannerMind" ConstructorParameters="mind,nowhere.json"/>\n'
        '<ArchitectureComponent ClassName="cmion_mesh.minds.supersimple:SuperSimpleMind" ConstructorParameters="too,many"/>\n'
        f'<ArchitectureComponent ClassName="cmion_mesh.migration.manager:MigrationManager" ConstructorParameters="{state}"/>\n'
        '<ArchitectureComponent ClassName="cmion_mesh.mind:Mind" ConstructorParameters="twin"/>\n'
        '<ArchitectureComponent ClassName="cmion_mesh.mind:Mind" ConstructorParameters="twin"/>\n'
        '<ArchitectureComponent ClassName="cmion.level3.fatima.FAtiMAConnector" ConstructorParameters="modular, port:0"/>\n'
        "</ArchitectureConfiguration>")
    config = str(tmp_path / "ArchitectureConfiguration.xml")
    expected = [
        (2, "cmion.level3.fatima.FAtiMAConnector (ported as cmion_mesh.minds.fatima.connector:FAtiMAConnector): unknown option 'bogus'"),
        (3, "cmion_mesh.minds.planner.mind:PlannerMind: "),
        (4, "cannot construct cmion_mesh.minds.supersimple:SuperSimpleMind with parameters ['too', 'many']: TypeError"),
        (5, "cmion_mesh.migration.manager:MigrationManager is built by every embodiment itself"),
        (7, "cmion_mesh.mind:Mind: a component named 'twin' is already in this configuration"),
    ]
    code, out, err = run_cli("validate", config, "--json")
    assert code == 1
    [report] = json.loads(out)
    errors = [(d["line"], d["message"]) for d in report["diagnostics"] if d["severity"] == "error"]
    assert len(errors) == len(expected), errors
    for (line, message), (want_line, words) in zip(errors, expected, strict=True):
        assert line == want_line and message.startswith(words), (line, message)
    assert "nowhere.json" in errors[1][1]
    assert not state.exists(), "validate opened nothing"
    code, out, err = run_cli("up", config, "--mesh", mesh, "--no-multicast", "--state-dir", str(tmp_path / "state"))
    assert code == 2 and "up in mesh" not in out
    for line, words in expected:
        assert f"error: {config}:{line}: {words}" in err, (line, words, err)
    assert not state.exists()


# --- what CMION's loaders read -----------------------------------------------------------------------------------


def test_element_order_is_free_where_cmion_ignored_it(tmp_path: Path) -> None:
    library = INTHEWILD / "CompetencyLibraryInTheWild.xml"
    assert library.read_text().index("<SamgarCompetency") < library.read_text().index("<Competency ")
    loaded = load_library(library)
    assert [c.name for c in loaded if not isinstance(c, StandInCompetency)] == ["TestCompetency2"]
    rules = load_rules(INTHEWILD / "CompManagerRulesInTheWild.xml")
    assert rules.rules[0].name == "talk", "the plan came before the MindAction"
    (tmp_path / "r.xml").write_text("<CompetencyManagerRules/>")
    (tmp_path / "l.xml").write_text("<CompetencyLibrary/>")
    (tmp_path / "a.xml").write_text('<ArchitectureConfiguration Embodiment="x" CompetencyManagerRulesFile="r.xml" '
                                    'CompetencyLibraryConfigurationFile="l.xml">\n<AdmitCompanion Name="spirit"/>\n'
                                    '<ArchitectureComponent ClassName="cmion.addOns.monitors.CmionEventMonitor"/>\n'
                                    '</ArchitectureConfiguration>')
    arch = load_architecture(tmp_path / "a.xml")
    assert arch.admit == {"spirit": None} and [c.class_name for c in arch.components] == ["cmion.addOns.monitors.CmionEventMonitor"]


def test_android_resource_names_resolve_to_xml_files() -> None:
    found = Diagnostics()
    arch = read_architecture(ANDROID / "architectureconfiguration_migrationsend.xml", found)
    assert arch is not None and not found.errors, [str(d) for d in found]
    assert arch.rules == (ANDROID / "compmanagerrules_migrationtest.xml").resolve()
    assert arch.library == (ANDROID / "competencylibrary_migrationtestsend.xml").resolve()
    [migration] = load_library(arch.library)
    assert type(migration).__name__ == "MigrationCompetency"
    assert migration.constructor_parameters == (str((ANDROID / "migrationconfig_send.xml").resolve()),)
    [migration] = load_library(INVITE / "CompetencyLibraryMigrationTestSend.xml")
    assert migration.constructor_parameters == (str((INVITE / "MigrationConfigSend.xml").resolve()),)


def test_a_file_parameter_naming_no_file_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "l.xml").write_text('<CompetencyLibrary>\n<Competency ClassName="cmion.level2.competencies.AndroidMigration" '
                                    'ConstructorParameters="migrationconfig_elsewhere"/>\n</CompetencyLibrary>')
    with pytest.raises(ConfigError, match=r"l\.xml:2: .*AndroidMigration: parameter 1 \(its device table\) "
                                          r"'migrationconfig_elsewhere' not found \(looked beside this file"):
        load_library(tmp_path / "l.xml")


def test_world_model_names_and_values_are_trimmed_as_cmion_trimmed_them(tmp_path: Path) -> None:
    (tmp_path / "wm.xml").write_text('<WorldModel>\n<Agent Name=" Visitor ">\n<Property Name=" present " Value=" yes "/>\n'
                                     "</Agent>\n</WorldModel>")
    [entity] = load_world_model_init(tmp_path / "wm.xml")
    assert (entity.name, entity.properties[0].name, entity.properties[0].value) == ("Visitor", "present", "yes")


def test_parameters_split_as_cmion_split_them() -> None:
    assert split_parameters(None) == split_parameters("") == split_parameters(" , ,") == ()
    assert split_parameters(" Pizza ,Pasta,, ") == ("Pizza", "Pasta")


def test_embodiment_name_falls_back_to_a_valid_folder_name(tmp_path: Path) -> None:
    folder = tmp_path / "bad#name"
    folder.mkdir()
    (folder / "r.xml").write_text("<CompetencyManagerRules/>")
    (folder / "l.xml").write_text("<CompetencyLibrary/>")
    (folder / "ArchitectureConfiguration.xml").write_text(
        '<ArchitectureConfiguration CompetencyManagerRulesFile="r.xml" CompetencyLibraryConfigurationFile="l.xml"/>')
    with pytest.raises(ConfigError, match=r"no Embodiment attribute.*add Embodiment=\"NAME\" or start it with --name"):
        load_architecture(folder / "ArchitectureConfiguration.xml")
    assert load_architecture(folder / "ArchitectureConfiguration.xml", name="fine").embodiment == "fine"


def test_a_rule_type_nothing_provides_is_a_warning_beside_standins_too(tmp_path: Path) -> None:
    """A stand-in provides the types the port map knows for its class, and no other: a misspelt
    type loads (CMION loaded it, and the action failed when it ran), with a warning at its step
    naming the rule and the closest provided type, not blamed on the stand-ins."""
    (tmp_path / "r.xml").write_text('<CompetencyManagerRules>\n<Rule><MindAction Name="Say"/><CompetencyExecutionPlan>\n'
                                    '<Competency ID="1" Type="Speek"/>\n</CompetencyExecutionPlan></Rule>\n'
                                    '<Rule><MindAction Name="Talk"/><CompetencyExecutionPlan>\n'
                                    '<Competency ID="1" Type="Speak"/>\n</CompetencyExecutionPlan></Rule>\n</CompetencyManagerRules>')
    (tmp_path / "robot.xml").write_text('<CompetencyLibrary>\n<Competency ClassName="cmion.TeamBuddy.competencies.Speak"/>\n'
                                        '<Competency ClassName="cmion.inTheWild.competencies.MoodLamp"/>\n</CompetencyLibrary>')
    found = Diagnostics()
    _, competencies = check_embodiment(tmp_path / "r.xml", tmp_path / "robot.xml", diagnostics=found)
    assert {c.type for c in competencies} == {"Speak", "MoodLamp"}, "the port map's type, and the unknown class's short name"
    assert not found.errors
    [warning] = [d for d in found.warnings if "Speek" in d.message]
    assert (warning.path, warning.line) == (str(tmp_path / "r.xml"), 3)
    assert warning.message.startswith("rule 'Say', plan 1: step 1 needs competency type 'Speek', which no competency of this "
                                      "embodiment provides (closest: 'Speak')"), warning.message
    assert any("rule types depending on it: Speak (r.xml:6)" in d.message and d.line == 2 for d in found.warnings)
    assert any("no rule uses its types (MoodLamp)" in d.message and d.line == 3 for d in found.warnings)
    # with --remote-type, the type is served by another process: nothing to say
    found = Diagnostics()
    check_embodiment(tmp_path / "r.xml", tmp_path / "robot.xml", remote_types=["Speek"], diagnostics=found)
    assert not any("Speek" in d.message for d in found)


def test_a_misspelt_java_class_is_named_with_the_one_meant(tmp_path: Path, mesh: str) -> None:
    """A ``cmion.`` name close to one of the port map is a stand-in (as any unknown class), and
    ``validate`` and ``up`` say which class it probably meant."""
    (tmp_path / "r.xml").write_text("<CompetencyManagerRules/>")
    (tmp_path / "l.xml").write_text('<CompetencyLibrary>\n<Competency ClassName="cmion.level2.competencies.test.TestCompetecy1"/>\n'
                                    "</CompetencyLibrary>")
    config = tmp_path / "ArchitectureConfiguration.xml"
    config.write_text('<ArchitectureConfiguration Embodiment="x" CompetencyManagerRulesFile="r.xml" '
                      'CompetencyLibraryConfigurationFile="l.xml">\n'
                      '<ArchitectureComponent ClassName="cmion.level3.fatima.FatimaConnector"/>\n</ArchitectureConfiguration>')
    meant = [(config, 2, "cmion.level3.fatima.FatimaConnector is not in the port map "
                         "(did you mean 'cmion.level3.fatima.FAtiMAConnector'?)"),
             (tmp_path / "l.xml", 2, "cmion.level2.competencies.test.TestCompetecy1 is not in the port map "
                                     "(did you mean 'cmion.level2.competencies.test.TestCompetency1'?)")]
    code, _, err = run_cli("validate", str(tmp_path))
    assert code == 0, err
    for path, line, words in meant:
        assert f"warning: {path}:{line}: {words}" in err, (words, err)
    assert run_cli("validate", "--strict", str(tmp_path))[0] == 1
    code, _, err = run_cli("validate", str(INTHEWILD / "CompetencyLibraryInTheWild.xml"))
    assert code == 0 and "cmion.inTheWild.competencies.MoodLamp is not in the port map: " in err, "nothing close: no guess"
    with Daemon(cli_argv("up", str(config), "--mesh", mesh, "--no-multicast", "--state-dir", str(tmp_path / "state")),
                name="misspelt") as daemon:
        daemon.wait_line("up in mesh", 30)
        for path, line, words in meant:
            assert any(f"warning: {path}:{line}: {words}" in text for text in daemon.lines), (words, daemon.lines)


# --- the real daemon ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def wild_daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Daemon, list[str]]]:
    """``cmion-mesh up`` on the InTheWild-shaped configuration, in a process of its own; the
    options that reach it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    net = ["--mesh", unique_mesh(), "--no-multicast"]
    state = tmp_path_factory.mktemp("wild")
    with Daemon(cli_argv("up", str(INTHEWILD), *net, "--listen", endpoint, "--state-dir", str(state)), name="inthewild") as daemon:
        daemon.wait_line("up in mesh", 30)
        yield daemon, [*net, "--connect", endpoint]


def test_up_starts_with_standins_listed(wild_daemon: tuple[Daemon, list[str]]) -> None:
    daemon, net = wild_daemon
    assert any("stand-ins, reported unavailable (see docs/portmap.md): 8" in line for line in daemon.lines), daemon.lines
    assert any("cmion.inTheWild.ai.DIAgent (mind connector)" in line for line in daemon.lines)
    assert any(line.startswith("warning: ") and "CompetencyLibraryInTheWild.xml:14: cmion.inTheWild.competencies.GretaBMLSender"
               in line for line in daemon.lines)
    assert any(line.startswith("note: ") and "cmion-mesh events" in line for line in daemon.lines)
    code, out, err = run_cli("act", "cmion2011-inthewild", "sendSMS", "0123", "hi", *net)
    assert code == 1
    assert "provided only by stand-in cmion.inTheWild.competencies.SMSSender (no cmion-mesh equivalent" in out + err, (out, err)
    code, out, err = run_cli("act", "cmion2011-inthewild", "Remember", "note", *net)
    assert code == 0, (out, err)


def test_up_starts_cmion_own_test_configuration(wild_daemon: tuple[Daemon, list[str]], tmp_path: Path) -> None:
    """CMION 2011's ArchitectureConfiguration.xml as it is (FAtiMA connector, GUI add-ons, SAMGAR),
    joined to the running daemon's mesh."""
    from cmion_mesh.minds.fatima.protocol import PORT_VARIABLE
    from cmion_mesh.testing.fatima_peer import PeerProcess

    _, net = wild_daemon
    mesh_options = net[:3]
    mind_port = free_port()  # the file leaves FAtiMA on CMION's fixed 46874; a test takes a free one
    with Daemon(cli_argv("up", str(DATA / "cmion2011"), *net, "--state-dir", str(tmp_path), "--companion", "spirit"),
                env={PORT_VARIABLE: str(mind_port)}, name="cmion2011") as original:
        original.wait_line("up in mesh", 30)
        assert any("cmion.addOns.samgar.SamgarConnector (component)" in line for line in original.lines), original.lines
        code, out, err = run_cli("act", "cmion2011", "TestAction2", *net)
        assert code == 0, (out, err)
        # The mind CMION was built for, on the file's own FAtiMAConnector entry: the rules of
        # CompManagerRulesTest.xml answer its action (rule 1 fails, rule 3 succeeds).
        with contextlib.closing(PeerProcess(mind_port, "--agent", "SpiritOfTheBuilding", "--prop", "role:TestAgent")) as mind:
            mind.got("OK", timeout=15)
            start = mind.mark()
            mind.command("act TestAction test")
            mind.got("ACTION-FINISHED SpiritOfTheBuilding TestAction test", timeout=15, start=start)
        code, out, err = run_cli("peers", *mesh_options, "--connect", net[-1], "--json")
        assert {p["name"] for p in json.loads(out)} >= {"cmion2011", "cmion2011-inthewild"}
