"""Small ROS 2 robot embodiments written into a folder, for the tests and the bench.

The rules are those of the shipped ``ros_robot`` (Say, Drive) and a goal of whatever action the
library's ``RobotGoal`` competency serves; a test or benchmark picks the rules it needs and writes
its own library (which transport, which action), so that both ways run the same rules.
"""

from __future__ import annotations

from pathlib import Path

SAY = """  <Rule>
    <MindAction Name="Say"><Parameter No="1" Value="*" /><Parameter No="2" Value="*" /></MindAction>
    <CompetencyExecutionPlan>
      <Competency ID="1" Type="LanguageGeneration">
        <CompetencyParameter Name="SpeechActID" Value="$parameter1" />
        <CompetencyParameter Name="Addressee" Value="$parameter2" />
        <CompetencyParameter Name="TextOutName" Value="text/$parameter1-$parameter2" />
      </Competency>
      <Competency ID="2" Type="SpeechSynthesis" Dependency="1">
        <CompetencyParameter Name="TextInName" Value="text/$parameter1-$parameter2" />
      </Competency>
    </CompetencyExecutionPlan>
  </Rule>
"""

DRIVE = """  <Rule>
    <MindAction Name="Drive"><Parameter No="1" Value="*" /><Parameter No="2" Value="*" /><Parameter No="3" Value="*" /></MindAction>
    <CompetencyExecutionPlan>
      <Competency ID="1" Type="Velocity">
        <CompetencyParameter Name="Linear" Value="$parameter1" />
        <CompetencyParameter Name="Angular" Value="$parameter2" />
        <CompetencyParameter Name="Duration" Value="$parameter3" />
      </Competency>
    </CompetencyExecutionPlan>
  </Rule>
"""

#: Goal <JSON object of goal fields>
GOAL = """  <Rule>
    <MindAction Name="Goal"><Parameter No="1" Value="*" /></MindAction>
    <CompetencyExecutionPlan>
      <Competency ID="1" Type="RobotGoal"><CompetencyParameter Name="goal" Value="$parameter1" /></Competency>
    </CompetencyExecutionPlan>
  </Rule>
"""

#: FibonacciFrom <blackboard path of the order>
FIBONACCI_FROM = """  <Rule>
    <MindAction Name="FibonacciFrom"><Parameter No="1" Value="*" /></MindAction>
    <CompetencyExecutionPlan>
      <Competency ID="1" Type="RobotGoal"><CompetencyParameter Name="orderInName" Value="$parameter1" /></Competency>
    </CompetencyExecutionPlan>
  </Rule>
"""

EMPTY_WORLD = '<?xml version="1.0" encoding="UTF-8"?>\n<WorldModel />\n'


def write_embodiment(folder: Path, name: str, *, rules: tuple[str, ...], library: str, world: str = EMPTY_WORLD) -> Path:
    """The four files of embodiment ``name`` in ``folder`` (made); returns its ArchitectureConfiguration.xml."""
    folder.mkdir(parents=True)
    (folder / "CompetencyManagerRules.xml").write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<CompetencyManagerRules>\n' + "".join(rules) + "</CompetencyManagerRules>\n")
    (folder / "CompetencyLibrary.xml").write_text(library)
    (folder / "WorldModel.xml").write_text(world)
    architecture = folder / "ArchitectureConfiguration.xml"
    architecture.write_text(f'<?xml version="1.0" encoding="UTF-8"?>\n<ArchitectureConfiguration Embodiment="{name}" '
                            'CompetencyManagerRulesFile="CompetencyManagerRules.xml" '
                            'CompetencyLibraryConfigurationFile="CompetencyLibrary.xml" WorldModelInitFile="WorldModel.xml" />\n')
    return architecture
