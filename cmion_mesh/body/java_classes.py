"""The port map: what each CMION Java class named in a configuration file becomes in cmion-mesh.

CMION's ``ArchitectureConfiguration`` and ``CompetencyLibrary`` files name Java classes
(``cmion.level3.fatima.FAtiMAConnector``). cmion-mesh reads those files unchanged and looks every
name that starts with ``cmion.`` up here (Python names, ``package.module:Class``, are imported as
they are). Each entry says what the class was (its ``kind``) and what happens to it:

* **ported**: ``target`` names the cmion-mesh class built in its place, with the same
  constructor parameters (CMION's comma-separated strings);
* **command**: a CMION GUI add-on; its job is done by a ``cmion-mesh`` command (``command``), so
  it is not loaded (``validate`` and ``up`` say so in a note);
* **base class**: abstract in CMION too (CMION could not build one either): naming it is an
  error, and ``target`` is the cmion-mesh class to subclass instead;
* **stand-in**: no equivalent (a robot head, a Kinect, Greta, SAMGAR...): it loads as a stand-in
  that is reported unavailable (``cmion_mesh.body.standin``). So does any ``cmion.`` name that is
  not in the map.

``types`` are the competency types a competency provided in CMION, read from CMION's sources
(each class set ``competencyType`` in its constructor, not always to its own name:
``VirtualEmysConnector`` provided ``VirtualEmys``, both ``Cereproc`` classes ``TTS``): a ported
class provides them too, and a stand-in competency is entered under them, so that a rule's
``Type`` finds what CMION found and a rule needing one fails naming the class.
``file_parameters`` are the positions of constructor parameters that name files (looked for as
CMION opened them, ``classes.locate_file``; ``NAME.xml`` for an Android raw-resource name).

``docs/portmap.md`` is generated from this table: ``python -m cmion_mesh.body.java_classes > docs/portmap.md``.
"""

from __future__ import annotations

import difflib
from typing import Literal

import msgspec

Kind = Literal["competency", "Samgar competency", "mind connector", "component", "GUI add-on", "base class", "example"]

#: The prefix of every CMION Java class name.
JAVA_PREFIX = "cmion."
#: Where stand-in messages send the reader.
DOC = "docs/portmap.md"


class Port(msgspec.Struct, frozen=True):
    java: str
    kind: Kind
    target: str | None
    note: str
    types: tuple[str, ...] = ()
    command: str | None = None
    file_parameters: tuple[int, ...] = ()

    @property
    def action(self) -> Literal["ported", "command", "base class", "stand-in"]:
        if self.kind == "base class":
            return "base class"
        if self.command is not None:
            return "command"
        return "ported" if self.target is not None else "stand-in"

    @property
    def short(self) -> str:
        return self.java.rpartition(".")[2]


def _ports(*ports: Port) -> dict[str, Port]:
    return {p.java: p for p in ports}


_TEST = "cmion_mesh.competencies.cmion_test"
_SUPERSIMPLE = "cmion.level3.supersimplemind."

#: Every CMION class name known to cmion-mesh (all classes named in real CMION 2011 configuration
#: files, the generic bases and the test competencies), by full Java name.
PORT_MAP: dict[str, Port] = _ports(
    # --- generic infrastructure -------------------------------------------------------------------
    Port("cmion.level2.competencies.Migration", "competency", "cmion_mesh.migration.manager:MigrationCompetency",
         "TCP migration and invitations; its parameter names the device table (a migrationconfig file)",
         ("Migration",), file_parameters=(0,)),
    Port("cmion.level2.competencies.AndroidMigration", "competency", "cmion_mesh.migration.manager:MigrationCompetency",
         "Android subclass of Migration: its parameter is a raw-resource name, read as NAME.xml",
         ("Migration",), file_parameters=(0,)),
    Port("cmion.level3.fatima.FAtiMAConnector", "mind connector", "cmion_mesh.minds.fatima.connector:FAtiMAConnector",
         "the FAtiMA agent mind over CMION's TCP line protocol (port 46874); migrates the mind's state"),
    Port(_SUPERSIMPLE + "SuperSimpleMindConnector", "mind connector", "cmion_mesh.minds.supersimple:SuperSimpleMind",
         "demonstration mind"),
    Port(_SUPERSIMPLE + "SuperSimpleMigratingMindConnector", "mind connector", "cmion_mesh.minds.supersimple:SuperSimpleMigratingMind",
         "demonstration mind that migrates its state (mindstate)"),
    Port(_SUPERSIMPLE + "SuperSimpleMigratingByInviteMindConnector", "mind connector",
         "cmion_mesh.minds.supersimple:SuperSimpleMigratingByInviteMind",
         "demonstration mind that invites the companion over and follows invitations"),
    Port("cmion.addOns.samgar.SamgarConnector", "component", None,
         "YARP/SAMGAR bridge: cmion-mesh has no SAMGAR; its competencies are stand-ins too"),
    # --- GUI add-ons: commands do their job ---------------------------------------------------------
    Port("cmion.addOns.monitors.CmionEventMonitor", "GUI add-on", None, "Swing list of CMION events",
         command="cmion-mesh events"),
    Port("cmion.addOns.monitors.IonEventMonitor", "GUI add-on", None, "Swing list of ION events",
         command="cmion-mesh events"),
    Port("cmion.addOns.manipulators.WorldModelManipulator", "GUI add-on", None, "Swing world-model editor",
         command="cmion-mesh wm get|tree|set|add|remove|watch"),
    Port("cmion.addOns.manipulators.AgentSimulator", "GUI add-on", None,
         "Swing editor adding agents to the world model: `wm add robot Visitor present=true` adds one with its "
         "properties (minds hear it added), `wm remove robot Visitor` takes it away; in code, "
         "`MeshClient.add_entity` / `RunContext.wm_add`", command="cmion-mesh wm add|remove"),
    Port("cmion.addOns.simulators.WorldModelSimulator", "GUI add-on", None, "Swing world-model simulator",
         command="cmion-mesh wm add|set|remove"),
    Port("cmion.addOns.manipulators.RemoteActionSimulator", "GUI add-on", None,
         "Swing GUI raising remote actions: `remote-action robot Greet Spirit --subject Visitor` makes the embodiment's "
         "minds perceive another agent's action (FAtiMA hears ACTION-FINISHED Visitor Greet Spirit); in code, "
         "`MeshClient.remote_action` / `RunContext.remote_action`", command="cmion-mesh remote-action"),
    # --- abstract bases: subclass the cmion-mesh class instead --------------------------------------
    Port("cmion.architecture.CmionComponent", "base class", "cmion_mesh.ion:Component", "every CMION component"),
    Port("cmion.level2.Competency", "base class", "cmion_mesh.competency:Competency", "every competency"),
    Port("cmion.level2.RemoteCompetency", "base class", "cmion_mesh.competency:Competency",
         "a competency run by another program: host a Competency there with `cmion-mesh serve-competency`"),
    Port("cmion.level2.RemoteTCPCompetency", "base class", "cmion_mesh.competency:Competency",
         "RemoteCompetency over a TCP line connection: serve the competency over the mesh instead "
         "(`cmion-mesh serve-competency`), or write a Competency speaking the device's lines"),
    Port("cmion.addOns.level2.RemoteAirCompetency", "base class", "cmion_mesh.competency:Competency",
         "RemoteCompetency over Psyclone/AIR: no AIR in cmion-mesh; `cmion-mesh serve-competency`"),
    Port("cmion.level3.AgentMindConnector", "base class", "cmion_mesh.mind:Mind",
         "every mind connector; a mind in another process: `cmion-mesh serve-mind`"),
    Port("cmion.addOns.samgar.SamgarCompetency", "base class", None, "competency behind a SAMGAR port: no SAMGAR in cmion-mesh"),
    # --- examples -----------------------------------------------------------------------------------
    Port("cmion.level2.competencies.ExampleCompetency", "example", None, "template of a competency: write a Competency subclass",
         ("DetectPerson",)),
    Port("cmion.level2.competencies.ExampleTCPCompetency", "example", None,
         "RemoteTCPCompetency example (client to localhost:453, type DetectPerson): not ported; serve the competency "
         "over the mesh instead", ("DetectPerson",)),
    # --- test competencies --------------------------------------------------------------------------
    *(Port(f"cmion.level2.competencies.test.TestCompetency{n}", "competency", f"{_TEST}:TestCompetency{n}",
           f"execution-system test competency (type {t})", (t,))
      for n, t in ((1, "TestType1"), (2, "TestType2"), (3, "TestType3"), (4, "TestType4"), (5, "TestType4"), (6, "TestType6"))),
    Port("cmion.level2.competencies.test.TestCompetency7", "competency", None, "execution-system test competency (cancellation)",
         ("TestType7",)),
    Port("cmion.level2.competencies.test.TestCompetency8", "competency", None, "execution-system test competency (cancellation)",
         ("TestType8",)),
    Port("cmion.addOns.samgar.competencies.test.TestSamgarCompetency", "Samgar competency", None, "SAMGAR test competency",
         ("SamgarTester",)),
    Port("cmion.addOns.samgar.competencies.test.TestSamgarCompetency2", "Samgar competency", None, "SAMGAR test competency",
         ("SamgarTester2",)),
    Port("cmion.addOns.samgar.competencies.player.LocalizeSamgarCompetency", "Samgar competency", None,
         "Player/Stage robot localisation via SAMGAR", ("DefaultLocalization",)),
    Port("cmion.addOns.samgar.competencies.player.NavigationSamgarCompetency", "Samgar competency", None,
         "Player/Stage robot navigation via SAMGAR", ("DefaultNavigation",)),
    # --- scenario classes with no equivalent (stand-ins) --------------------------------------------
    Port("cmion.inTheWild.competencies.GretaBMLCreator", "competency", None,
         "InTheWild: mind action to Greta BML on the blackboard", ("GretaBMLCreator",)),
    Port("cmion.inTheWild.competencies.GretaBMLSender", "competency", None,
         "InTheWild: sends BML to the Greta agent through Psyclone", ("GretaBMLSender",)),
    Port("cmion.inTheWild.competencies.SMSReceiver", "competency", None, "InTheWild: SMS through a GSM modem", ("SMSReceiver",)),
    Port("cmion.inTheWild.competencies.SMSSender", "competency", None, "InTheWild: SMS through a GSM modem", ("SMSSender",)),
    Port("cmion.inTheWild.competencies.EmysAskQuestion", "competency", None, "InTheWild: asks the user through the EMYS head",
         ("EmysAskQuestion",)),
    Port("cmion.inTheWild.competencies.KinectTrackerConnector", "Samgar competency", None, "InTheWild: Kinect tracking via SAMGAR",
         ("Kinect",)),
    Port("cmion.inTheWild.competencies.VirtualEmysConnector", "Samgar competency", None, "InTheWild: virtual EMYS head via SAMGAR",
         ("VirtualEmys",)),
    Port("cmion.inTheWild.competencies.EmysEmotion", "competency", None, "InTheWild: EMYS head emotion", ("EmysEmotion",)),
    Port("cmion.inTheWild.competencies.EmysGaze", "competency", None, "InTheWild: EMYS head gaze", ("EmysGaze",)),
    Port("cmion.inTheWild.competencies.Cereproc", "competency", None, "InTheWild: CereProc speech synthesis", ("TTS",)),
    Port("cmion.inTheWild.competencies.FaceDetect", "competency", None, "InTheWild: face detection", ("FaceDetect",)),
    Port("cmion.inTheWild.competencies.ProcessTextInput", "competency", None, "InTheWild: typed user input", ("ProcessTextInput",)),
    Port("cmion.emysTK.SimpleTalk", "competency", None, "EMYS toolkit: one-shot TCP speech command", ("SimpleTalk",)),
    Port("cmion.emysTK.SimpleAnimation", "competency", None, "EMYS toolkit: one-shot TCP animation command", ("SimpleAnimation",)),
    Port("cmion.inTheWild.ai.DIAgent", "mind connector", None, "InTheWild dialogue mind (Java-serialised server on 5228)"),
    Port("cmion.inTheWild.ai.ReviewAgent", "mind connector", None, "InTheWild scripted mind"),
    Port("cmion.inTheWild.ai.SimpleAutonomousAgent", "mind connector", None, "InTheWild autonomous mind"),
    Port("cmion.inTheWild.woz.InTheWildWoz", "mind connector", None, "Wizard-of-Oz GUI mind"),
    Port("cmion.inTheWild.woz.ITWEmysWoz", "mind connector", None, "Wizard-of-Oz GUI mind for EMYS"),
    Port("cmion.TeamBuddy.woz.TBWoz", "mind connector", None, "TeamBuddy Wizard-of-Oz GUI mind"),
    Port("cmion.TeamBuddy.competencies.DeskMonitor", "Samgar competency", None, "TeamBuddy: TCP desk-presence server",
         ("DeskMonitor",)),
    Port("cmion.TeamBuddy.competencies.RobotFaceControl", "competency", None, "TeamBuddy: robot face over TCP (port 498)",
         ("RobotFaceControl",)),
    Port("cmion.TeamBuddy.competencies.Speak", "competency", None, "TeamBuddy: speech", ("Speak",)),
    Port("cmion.TeamBuddy.competencies.MoveToUser", "competency", None, "TeamBuddy: robot navigation", ("MoveToUser",)),
    # TeamBuddy classes known by their name and type only (read from CMION's sources)
    *(Port(f"cmion.TeamBuddy.competencies.{c}", "competency", None, "TeamBuddy scenario competency", (t,))
      for c, t in (("BlackBoardRemover", "BlackBoardRemover"), ("DoorMotion", "DoorMotion"), ("EMYSHead", "EMYSHead"),
                   ("ExecutionMonitor", "ExecutionMonitor"), ("GoogleCalendarChecker", "GoogleCalendarChecker"),
                   ("IdleDream", "IdleDream"), ("IdleSpeak", "IdleSpeak"), ("Navigate", "Navigation"), ("PhoneRing", "PhoneRing"),
                   ("PowerMonitor", "PowerMonitor"), ("TestCommSAM", "Test"), ("UserMonitor", "UserMonitor"), ("Wait", "Wait"),
                   ("WaitBoolean", "WaitBoolean"), ("WaitTimeout", "WaitTimeout"), ("WebUIProxy", "WebUIProxy"),
                   ("WorldModelRemover", "WorldModelRemover"))),
    Port("cmion.TeamBuddy.competencies.FaceDetect", "Samgar competency", None, "TeamBuddy: face detection via SAMGAR",
         ("FaceDetect",)),
    Port("cmion.TeamBuddy.competencies.Motion", "Samgar competency", None, "TeamBuddy: motion detection via SAMGAR", ("Motion",)),
    Port("cmion.TeamBuddy.competencies.Cereproc", "competency", None, "TeamBuddy: CereProc speech synthesis", ("TTS",)),
    Port("teambuddyInterface.InterfaceCompetency", "competency", None, "TeamBuddy interface competency (a class outside cmion.)",
         ("InterfaceCompetency",)),
    Port("cmion.personalguide.mind.SimpleMind", "mind connector", None, "PersonalGuide (Android) mind"),
    Port("cmion.personalguide.competencies.FaceAnimator", "competency", None, "PersonalGuide (Android): face animation",
         ("FaceAnimator",)),
    Port("cmion.personalguide.competencies.TalkCompetency", "competency", None, "PersonalGuide (Android): speech",
         ("TalkCompetency",)),
)


def is_java_name(class_name: str) -> bool:
    """A CMION Java class name (``cmion.x.Y``, or a class of the map outside ``cmion.``: TeamBuddy's
    ``teambuddyInterface.InterfaceCompetency``), as opposed to a Python ``package.module:Class``."""
    return class_name in PORT_MAP or (class_name.startswith(JAVA_PREFIX) and ":" not in class_name)


def lookup(class_name: str) -> Port | None:
    return PORT_MAP.get(class_name)


def close_match(class_name: str) -> str | None:
    """The known class ``class_name`` is probably a misspelling of, if any. Compared without case
    (``FatimaConnector``), and the class's own name too: names of one package share a long
    prefix, so the whole names alone would offer a known class for every unknown one beside it."""
    if class_name in PORT_MAP:
        return None
    by_lower = {name.lower(): name for name in PORT_MAP}
    wanted = class_name.lower()
    if wanted in by_lower:
        return by_lower[wanted]
    short = wanted.rpartition(".")[2]
    for close in difflib.get_close_matches(wanted, list(by_lower), n=3, cutoff=0.85):
        if difflib.SequenceMatcher(None, short, close.rpartition(".")[2]).ratio() >= 0.8:
            return by_lower[close]
    return None


def markdown() -> str:
    """``docs/portmap.md``: the table, for people."""
    lines = [
        "# Port map: CMION Java classes in cmion-mesh",
        "",
        "<!-- Generated from cmion_mesh/body/java_classes.py: python -m cmion_mesh.body.java_classes > docs/portmap.md -->",
        "",
        "CMION configuration files name Java classes. cmion-mesh reads those files unchanged and looks",
        "each `cmion.` name up in this table:",
        "",
        "- **ported**: the cmion-mesh class is built in its place, with the same constructor parameters;",
        "- **command**: a CMION GUI add-on; a `cmion-mesh` command does its job, so it is not loaded",
        "  (`validate` and `up` say so in a note);",
        "- **base class**: abstract in CMION too: naming it is an error; subclass the cmion-mesh class instead;",
        "- **stand-in**: no equivalent. It loads as a stand-in reported unavailable: `validate` and `up` warn",
        "  with the file, line, class and the rule types depending on it; the embodiment runs, and an action",
        "  whose plan needs it fails naming the class. A `cmion.` name not in this table is a stand-in too",
        "  (the warning names the class of this table it is probably a misspelling of, if one is close).",
        "",
        "The types are CMION's own, read from its sources (each class set `competencyType` in its",
        "constructor, not always to its own name: `VirtualEmysConnector` provided `VirtualEmys`, both",
        "`Cereproc` classes `TTS`; a SAMGAR class could take another from a parameter, the one listed is",
        "its default), so a rule's `Type` finds what CMION found. A ported class provides them, a",
        "stand-in competency is entered under them (a class not in this table: under its short name,",
        "CMION's usual convention), and under no other. A competency type that rules use and nothing",
        "provides loads, as in CMION: `validate` and `up` warn at the rule's step with the closest types",
        "provided, and the action fails when it runs, with the same words. `validate --strict` makes",
        "every stand-in, and every such rule, an error.",
        "",
        "| CMION class | kind | cmion-mesh | types | note |",
        "|---|---|---|---|---|",
    ]
    for port in PORT_MAP.values():
        if port.action == "command":
            where = f"command `{port.command}`"
        elif port.action == "stand-in":
            where = "stand-in"
        elif port.action == "base class":
            where = f"base class: subclass `{port.target}`" if port.target else "base class: no equivalent"
        else:
            where = f"`{port.target}`"
        types = ", ".join(port.types) or "-"
        lines.append(f"| `{port.java}` | {port.kind} | {where} | {types} | {port.note.replace('|', '/')} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(markdown(), end="")
