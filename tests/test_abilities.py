"""A body's actions as tools (body/abilities.py): names, parameters, choices and descriptions."""

from __future__ import annotations

from pathlib import Path

import pytest

from cmion_mesh.body.abilities import Ability, abilities
from cmion_mesh.body.embodiment import with_migrate_rule
from cmion_mesh.body.rules import load_rules, parse_rules
from cmion_mesh.errors import InvalidArguments
from cmion_mesh.xmlsafe import loads

ROOT = Path(__file__).resolve().parent.parent


def _rules(xml: str):  # type: ignore[no-untyped-def]
    return parse_rules(loads(xml.encode(), None, comments=True), "<test>")


def test_the_robot_rules_become_named_described_tools() -> None:
    found = {a.tool: a for a in abilities(with_migrate_rule(load_rules(ROOT / "embodiments/robot/CompetencyManagerRules.xml")))}
    assert list(found) == ["Say", "GoTo", "Greet", "Express", "Migrate"]
    assert [p.name for p in found["Say"].parameters] == ["speechAct", "addressee"]
    assert found["GoTo"].description.startswith("GoTo <location>: drive there")
    assert found["GoTo"].input_schema() == {
        "type": "object", "properties": {"location": {"type": "string"}}, "required": ["location"], "additionalProperties": False}
    assert found["Migrate"].parameters[0].name == "target"
    assert found["GoTo"].positional({"location": "Kitchen"}) == ("Kitchen",)


def test_literal_parameters_become_choices_and_step_names_name_parameters() -> None:
    rules = _rules("""<CompetencyManagerRules>
      <Rule><MindAction Name="Light"><Parameter No="1" Value="on"/></MindAction>
        <CompetencyExecutionPlan><Competency ID="1" Type="Lamp">
          <CompetencyParameter Name="State" Value="$parameter1"/></Competency></CompetencyExecutionPlan></Rule>
      <Rule><MindAction Name="Light"><Parameter No="1" Value="off"/></MindAction>
        <CompetencyExecutionPlan><Competency ID="1" Type="Lamp">
          <CompetencyParameter Name="State" Value="$parameter1"/></Competency></CompetencyExecutionPlan></Rule>
      <Rule><MindAction Name="Light"><Parameter No="1" Value="*"/><Parameter No="2" Value="*"/></MindAction>
        <CompetencyExecutionPlan><Competency ID="1" Type="Lamp"/>
          <Competency ID="2" Type="Sound" Dependency="1"/></CompetencyExecutionPlan></Rule>
      <Rule><MindAction Name="*"/><CompetencyExecutionPlan/></Rule>
      <Rule><MindAction Name="say hello!"/><CompetencyExecutionPlan/></Rule>
    </CompetencyManagerRules>""")
    found = abilities(rules)
    assert [a.tool for a in found] == ["Light_1", "Light_2", "say_hello_"]
    light = found[0]
    assert light.action == "Light" and light.parameters[0].name == "state" and light.parameters[0].choices == ("on", "off")
    assert light.input_schema()["properties"]["state"] == {"type": "string", "enum": ["on", "off"]}
    assert found[1].parameters[0].name == "parameter1" and found[1].description == "Light: runs Lamp then Sound"
    assert found[2].action == "say hello!" and found[2].positional({}) == ()


@pytest.mark.parametrize(("arguments", "message"), [
    ({}, "argument 'state' is missing"),
    ({"state": "dim"}, "one of on, off"),
    ({"state": "on", "colour": "red"}, "unknown argument(s) colour"),
    ({"state": ["on"]}, "must be text"),
])
def test_bad_arguments_are_refused_naming_the_parameter(arguments: dict[str, object], message: str) -> None:
    from cmion_mesh.body.abilities import Parameter

    light = Ability("Light", "Light", (Parameter("state", ("on", "off")),), "")
    with pytest.raises(InvalidArguments, match=message.replace("(", r"\(").replace(")", r"\)")):
        light.positional(arguments)


def test_numbers_are_taken_as_text_and_abilities_survive_json() -> None:
    from cmion_mesh.body.abilities import Parameter

    wait = Ability("Wait", "Wait", (Parameter("seconds"),), "Wait <seconds>", ("Wait *",))
    assert wait.positional({"seconds": 3}) == ("3",)
    assert Ability.from_json(wait.to_json()) == wait
    with pytest.raises(InvalidArguments, match="malformed ability"):
        Ability.from_json({"tool": "x"})
