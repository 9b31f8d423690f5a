"""Competency manager rules: CMION 2011 files load unchanged, matching and specificity, plan graphs,
substitution, and every refused file names its file and the offending line."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from cmion_mesh import xmlsafe
from cmion_mesh.body.rules import Plan, Rule, RuleSet, Step, load_rules, parse_rules, substitute, substitute_step
from cmion_mesh.errors import ConfigError, PlanError, StorageError, XmlError
from cmion_mesh.mind import MindAction

from .conftest import CMION_2011

pytestmark = pytest.mark.timeout(30)

TEST_RULES = CMION_2011 / "CompManagerRulesTest.xml"
EXAMPLE_RULES = CMION_2011 / "CompManagerRulesExample.xml"


def rules_file(tmp_path: Path, body: str, name: str = "rules.xml") -> Path:
    path = tmp_path / name
    path.write_text(f'<?xml version="1.0" ?>\n<CompetencyManagerRules>\n{body}\n</CompetencyManagerRules>\n', encoding="utf-8")
    return path


def line_of(path: Path, marker: str) -> int:
    """1-based line of the only line of ``path`` containing ``marker``."""
    hits = [n for n, text in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1) if marker in text]
    assert len(hits) == 1, (marker, hits)
    return hits[0]


def refused(path: Path, marker: str) -> ConfigError:
    """Loading ``path`` fails with a ConfigError located at the line holding ``marker``."""
    with pytest.raises(ConfigError) as info:
        load_rules(path)
    exc = info.value
    line = line_of(path, marker)
    assert exc.path == str(path) and exc.line == line, str(exc)
    assert str(exc).startswith(f"{path}:{line}: "), str(exc)
    assert path.name in str(exc)
    return exc


def no_bb(name: str) -> Any:
    raise KeyError(name)


def no_wm(entity: str, prop: str) -> Any:
    raise KeyError(f"{entity}.{prop}")


# --- the CMION 2011 files -------------------------------------------------------------------------


def test_cmion_test_rules_load_unchanged() -> None:
    rules = load_rules(TEST_RULES)
    assert [(r.index, r.name, r.parameters, r.subject, r.line) for r in rules.rules] == [
        (0, "TestAction", ("test",), None, 15),
        (1, "TestAction", ("someValueThatWillNotMatch",), None, 31),
        (2, "TestAction", ("*",), None, 47),
        (3, "TestAction2", (), None, 67),
    ]
    assert rules.path == str(TEST_RULES) and all(r.path == str(TEST_RULES) for r in rules.rules)
    plan = rules.rules[2].plans[0]
    assert plan.steps == (
        Step("1", "TestType2", (), (("RandomOutName", "$parameter1"),), 54),
        Step("2", "TestType3", ("1",), (("RandomInName", "$parameter1"),), 58),
    )
    assert rules.actions() == ["TestAction test", "TestAction someValueThatWillNotMatch", "TestAction *", "TestAction2"]
    assert rules.types() == {"TestType1", "TestType2", "TestType3", "TestType4"}
    rules.check_types(["TestType1", "TestType2", "TestType3", "TestType4", "Unused"])


def test_more_specific_rule_first_and_non_matching_value_excluded() -> None:
    rules = load_rules(TEST_RULES)
    found = rules.candidates(MindAction("TestAction", ("test",)))
    # Rule 1 (no wildcard) before rule 3 (one); rule 2 wants another value.
    assert [r.index for r in found] == [0, 2]
    assert [r.wildcards for r in found] == [0, 1]


def test_parameterless_action_and_parameter_count_must_be_equal() -> None:
    rules = load_rules(TEST_RULES)
    assert [r.index for r in rules.candidates(MindAction("TestAction2"))] == [3]
    assert rules.candidates(MindAction("TestAction", ("test", "extra"))) == []
    assert rules.candidates(MindAction("TestAction")) == []
    assert rules.candidates(MindAction("TestAction2", ("x",))) == []
    assert rules.candidates(MindAction("Unknown", ("test",))) == []


def test_example_plan_graph() -> None:
    rules = load_rules(EXAMPLE_RULES)
    (rule,) = rules.rules
    assert rule.name == "Talk" and rule.parameters == ("*", "*") and rule.wildcards == 2
    (plan,) = rule.plans
    assert plan.line == 30
    assert [s.id for s in plan.steps] == ["1", "2", "3", "4", "5", "6", "7"]
    assert plan.step("6").dependencies == ("2", "4", "5") == plan.step("7").dependencies
    assert plan.step("2").dependencies == ("1",) and plan.step("4").dependencies == ("3",)
    assert [s.id for s in plan.roots()] == ["1", "3", "5"]
    assert plan.step("3").parameters == (("SpeechActID", "$parameter2"), ("TextOutName", "TextVariable"))
    with pytest.raises(KeyError):
        plan.step("8")

    order = [s.id for s in plan.topological_order()]
    assert sorted(order) == [s.id for s in plan.steps]
    position = {step_id: i for i, step_id in enumerate(order)}
    for s in plan.steps:
        assert all(position[d] < position[s.id] for d in s.dependencies), order
    for last in ("6", "7"):
        assert all(position[d] < position[last] for d in ("2", "4", "5"))
    assert order == ["1", "3", "5", "2", "4", "6", "7"]  # deterministic: ready steps in file order

    assert [r.index for r in rules.candidates(MindAction("Talk", ("UserA", "greet")))] == [0]
    assert rules.actions() == ["Talk * *"]


def test_example_step_parameters_substituted() -> None:
    plan = load_rules(EXAMPLE_RULES).rules[0].plans[0]
    action = MindAction("Talk", ("UserA", "greet"), subject="Greta")
    assert substitute_step(plan.step("1"), action, bb=no_bb, wm=no_wm) == {"PersonID": "UserA"}
    assert substitute_step(plan.step("3"), action, bb=no_bb, wm=no_wm) == {"SpeechActID": "greet", "TextOutName": "TextVariable"}


# --- matching and specificity ---------------------------------------------------------------------


def test_specificity_ties_in_file_order_and_name_wildcard(tmp_path: Path) -> None:
    path = rules_file(
        tmp_path,
        """
        <Rule><MindAction Name="*"><Parameter No="1" Value="*"/><Parameter No="2" Value="b"/></MindAction>
          <CompetencyExecutionPlan><Competency ID="1" Type="AnyTwo"/></CompetencyExecutionPlan></Rule>
        <Rule><MindAction Name="Go"><Parameter No="1" Value="*"/><Parameter No="2" Value="b"/></MindAction>
          <CompetencyExecutionPlan><Competency ID="1" Type="FirstTie"/></CompetencyExecutionPlan></Rule>
        <Rule><MindAction Name="Go"><Parameter No="1" Value="a"/><Parameter No="2" Value="*"/></MindAction>
          <CompetencyExecutionPlan><Competency ID="1" Type="SecondTie"/></CompetencyExecutionPlan></Rule>
        <Rule><MindAction Name="Go"><Parameter No="1" Value="*"/><Parameter No="2" Value="*"/></MindAction>
          <CompetencyExecutionPlan><Competency ID="1" Type="Loose"/></CompetencyExecutionPlan></Rule>
        <Rule><MindAction Name="Go"><Parameter No="2" Value="b"/><Parameter No="1" Value="a"/></MindAction>
          <CompetencyExecutionPlan><Competency ID="1" Type="Exact"/></CompetencyExecutionPlan></Rule>
        <Rule><MindAction Name="*"/>
          <CompetencyExecutionPlan><Competency ID="1" Type="AnyNoParams"/></CompetencyExecutionPlan></Rule>
        """,
    )
    rules = load_rules(path)
    # Parameters are ordered by No, not by file order.
    assert rules.rules[4].parameters == ("a", "b")
    assert [r.wildcards for r in rules.rules] == [2, 1, 1, 2, 0, 1]
    found = rules.candidates(MindAction("Go", ("a", "b")))
    assert [r.plans[0].steps[0].type for r in found] == ["Exact", "FirstTie", "SecondTie", "AnyTwo", "Loose"]
    assert [r.plans[0].steps[0].type for r in rules.candidates(MindAction("Stop", ("x", "b")))] == ["AnyTwo"]
    assert [r.plans[0].steps[0].type for r in rules.candidates(MindAction("Anything"))] == ["AnyNoParams"]
    assert rules.actions() == ["* * b", "Go * b", "Go a *", "Go * *", "Go a b", "*"]


def test_subject_and_alternative_plans(tmp_path: Path) -> None:
    path = rules_file(
        tmp_path,
        """
        <Rule><MindAction Name="Wave" Subject="Greta"/>
          <CompetencyExecutionPlan><Competency ID="1" Type="RobotArm"/></CompetencyExecutionPlan>
          <CompetencyExecutionPlan><Competency ID="1" Type="ScreenAvatar"/></CompetencyExecutionPlan>
        </Rule>
        <Rule><MindAction Name="Wave" Subject="*"/>
          <CompetencyExecutionPlan/></Rule>
        <Rule><MindAction Name="Say it"><Parameter No="1" Value=""/></MindAction>
          <CompetencyExecutionPlan/></Rule>
        """,
    )
    rules = load_rules(path)
    greta, anyone, say = rules.rules
    assert [p.steps[0].type for p in greta.plans] == ["RobotArm", "ScreenAvatar"]
    assert greta.matches(MindAction("Wave", subject="Greta"))
    assert not greta.matches(MindAction("Wave", subject="Max"))
    assert anyone.matches(MindAction("Wave", subject="Max"))
    assert [r.index for r in rules.candidates(MindAction("Wave", subject="Greta"))] == [0, 1]
    # An empty plan is allowed: nothing to run, so it trivially succeeds.
    assert anyone.plans[0].steps == () and anyone.plans[0].roots() == () and anyone.plans[0].topological_order() == ()
    assert say.matches(MindAction("Say it", ("",)))
    assert rules.actions() == ["Wave (subject Greta)", "Wave (subject *)", '"Say it" ""']
    assert rules.types() == {"RobotArm", "ScreenAvatar"}


def test_mind_action_accepts_a_list_but_stays_hashable() -> None:
    action = MindAction("Go", ["a", "b"])  # type: ignore[arg-type]
    assert action.parameters == ("a", "b")
    assert hash(action) == hash(MindAction("Go", ("a", "b")))


def test_parse_rules_validates_the_schema_too() -> None:
    tree = xmlsafe.load(TEST_RULES, None)
    assert parse_rules(tree, "given.xml").rules[0].path == "given.xml"
    bad = xmlsafe.loads(b"<CompetencyManagerRules><Rule/></CompetencyManagerRules>", None, name="bad.xml")
    with pytest.raises(XmlError, match=r"^bad\.xml:1: "):
        parse_rules(bad, "bad.xml")


def test_hand_built_plan_with_cycle_has_no_topological_order() -> None:
    plan = Plan((Step("a", "T", ("b",), (), 1), Step("b", "T", ("a",), (), 2)), 1)
    with pytest.raises(PlanError, match="cycle"):
        plan.topological_order()


# --- substitution ---------------------------------------------------------------------------------


def test_parameter_tokens_are_exact_with_ten_or_more_parameters(tmp_path: Path) -> None:
    params = "".join(f'<Parameter No="{n}" Value="*"/>' for n in range(1, 12))
    path = rules_file(
        tmp_path,
        f"""
        <Rule><MindAction Name="Many">{params}</MindAction>
          <CompetencyExecutionPlan><Competency ID="1" Type="T">
            <CompetencyParameter Name="one" Value="$parameter1"/>
            <CompetencyParameter Name="ten" Value="$parameter10"/>
            <CompetencyParameter Name="eleven" Value="$parameter11"/>
            <CompetencyParameter Name="mixed" Value="$parameter1,$parameter10;$parameter1$parameter11"/>
          </Competency></CompetencyExecutionPlan></Rule>
        """,
    )
    rule = load_rules(path).rules[0]
    action = MindAction("Many", tuple(f"v{n}" for n in range(1, 12)))
    assert rule.matches(action)
    assert substitute_step(rule.plans[0].steps[0], action, bb=no_bb, wm=no_wm) == {
        "one": "v1",
        "ten": "v10",
        "eleven": "v11",
        "mixed": "v1,v10;v1v11",
    }


def test_subject_action_and_literal_text() -> None:
    action = MindAction("Talk", ("UserA",), subject="Greta")
    assert substitute("$subject", action, bb=no_bb, wm=no_wm) == "Greta"
    assert substitute("$action by $subject to $parameter1.", action, bb=no_bb, wm=no_wm) == "Talk by Greta to UserA."
    # Not tokens: a longer word, an unknown name, a missing number.
    assert substitute("$subjects $other $parameter price $5", action, bb=no_bb, wm=no_wm) == "$subjects $other $parameter price $5"
    assert substitute("plain", action, bb=no_bb, wm=no_wm) == "plain"


def test_substituted_text_is_not_substituted_again() -> None:
    action = MindAction("Echo", ("$parameter2", "secret"), subject="$BB(x)")
    assert substitute("$parameter1 $subject", action, bb=no_bb, wm=no_wm) == "$parameter2 $BB(x)"


def test_blackboard_and_world_model_lookups_typed_alone_text_embedded() -> None:
    blackboard: dict[str, Any] = {"battery": 87, "robot/pose": [1.5, 2.0]}
    world: dict[tuple[str, str], Any] = {("UserA", "speaksEnglish"): True, ("Vase", "colour.hue"): "blue"}
    calls: list[tuple[str, ...]] = []

    def bb(name: str) -> Any:
        calls.append((name,))
        return blackboard[name]

    def wm(entity: str, prop: str) -> Any:
        calls.append((entity, prop))
        return world[(entity, prop)]

    action = MindAction("Check")
    assert substitute("$BB(battery)", action, bb=bb, wm=wm) == 87
    assert substitute("$BB(robot/pose)", action, bb=bb, wm=wm) == [1.5, 2.0]
    assert substitute("$WM(UserA.speaksEnglish)", action, bb=bb, wm=wm) is True
    # The first dot splits entity from property.
    assert substitute("$WM(Vase.colour.hue)", action, bb=bb, wm=wm) == "blue"
    assert substitute("level $BB(battery)% english=$WM(UserA.speaksEnglish)", action, bb=bb, wm=wm) == "level 87% english=True"
    assert substitute(" $BB(battery)", action, bb=bb, wm=wm) == " 87"
    assert ("robot/pose",) in calls and ("Vase", "colour.hue") in calls


def test_missing_lookups_raise_plan_error_naming_token_and_step() -> None:
    action = MindAction("Check", ("only",))
    with pytest.raises(PlanError, match=r"\$BB\(nothing\)"):
        substitute("$BB(nothing)", action, bb=no_bb, wm=no_wm)
    with pytest.raises(PlanError, match=r"\$WM\(Ghost\.name\)"):
        substitute("hello $WM(Ghost.name)", action, bb=no_bb, wm=no_wm)

    def storage_bb(name: str) -> Any:
        raise StorageError(f"blackboard: no property {name!r}")

    with pytest.raises(PlanError, match=r"\$BB\(a/b\).*no property"):
        substitute("$BB(a/b)", action, bb=storage_bb, wm=no_wm)
    with pytest.raises(PlanError, match=r"\$parameter2"):
        substitute("$parameter2", action, bb=no_bb, wm=no_wm)

    step = Step("7", "PlayAudio", (), (("ok", "$parameter1"), ("AudioInName", "$BB(audio)")), 3)
    with pytest.raises(PlanError) as info:
        substitute_step(step, action, bb=no_bb, wm=no_wm)
    message = str(info.value)
    assert "step 7" in message and "PlayAudio" in message and "AudioInName" in message and "$BB(audio)" in message


def test_other_callback_errors_are_not_hidden() -> None:
    def broken(name: str) -> Any:
        raise RuntimeError("bug")

    with pytest.raises(RuntimeError):
        substitute("$BB(x)", MindAction("a"), bb=broken, wm=no_wm)


# --- refused files --------------------------------------------------------------------------------

ONE_PARAM_RULE = (
    '<Rule><MindAction Name="A"><Parameter No="1" Value="*"/></MindAction>\n'
    "<CompetencyExecutionPlan>\n{steps}\n</CompetencyExecutionPlan></Rule>"
)


def plan_file(tmp_path: Path, steps: str) -> Path:
    return rules_file(tmp_path, ONE_PARAM_RULE.format(steps=steps))


def test_dependency_cycle_refused_and_named(tmp_path: Path) -> None:
    path = plan_file(
        tmp_path,
        """<Competency ID="0" Type="T"/>
        <Competency ID="1" Type="T" Dependency="0, 2"/> <!-- first of the cycle -->
        <Competency ID="2" Type="T" Dependency="1"/>""",
    )
    exc = refused(path, "first of the cycle")
    assert "dependency cycle 1 -> 2 -> 1" in str(exc) and "'A *'" in str(exc)


def test_plan_without_root_refused(tmp_path: Path) -> None:
    path = plan_file(
        tmp_path,
        """<Competency ID="x" Type="T" Dependency="y"/> <!-- here -->
        <Competency ID="y" Type="T" Dependency="x"/>""",
    )
    exc = refused(path, "here")
    assert "no step without dependencies" in str(exc) and "x -> y -> x" in str(exc)


def test_self_dependency_refused(tmp_path: Path) -> None:
    path = plan_file(tmp_path, '<Competency ID="1" Type="T"/>\n<Competency ID="2" Type="T" Dependency="1,2"/>')
    assert "step 2 depends on itself" in str(refused(path, 'ID="2"'))


def test_unknown_dependency_refused(tmp_path: Path) -> None:
    path = plan_file(tmp_path, '<Competency ID="1" Type="T"/>\n<Competency ID="2" Type="T" Dependency="1,9"/>')
    assert "unknown step 9" in str(refused(path, 'ID="2"'))


def test_empty_dependency_item_refused_but_empty_attribute_is_none(tmp_path: Path) -> None:
    ok = plan_file(tmp_path, '<Competency ID="1" Type="T" Dependency=" "/>\n<Competency ID="2" Type="T" Dependency=" 1 , 1 "/>')
    plan = load_rules(ok).rules[0].plans[0]
    assert plan.step("1").dependencies == () and plan.step("2").dependencies == ("1",)
    steps = '<Competency ID="1" Type="T"/>\n<Competency ID="2" Type="T" Dependency="1,"/>'
    bad = rules_file(tmp_path, ONE_PARAM_RULE.format(steps=steps), "bad.xml")
    assert "empty item" in str(refused(bad, 'ID="2"'))


def test_duplicate_step_ids_refused(tmp_path: Path) -> None:
    path = plan_file(tmp_path, '<Competency ID="1" Type="T"/>\n<Competency ID="1" Type="U"/>')
    exc = refused(path, 'Type="U"')
    assert "step ID 1 already used at line" in str(exc)


def test_same_step_id_in_two_plans_is_fine(tmp_path: Path) -> None:
    path = rules_file(
        tmp_path,
        '<Rule><MindAction Name="A"/><CompetencyExecutionPlan><Competency ID="1" Type="T"/></CompetencyExecutionPlan>'
        '<CompetencyExecutionPlan><Competency ID="1" Type="U"/></CompetencyExecutionPlan></Rule>',
    )
    assert len(load_rules(path).rules[0].plans) == 2


def test_gap_in_parameter_numbers_refused(tmp_path: Path) -> None:
    path = rules_file(
        tmp_path,
        '<Rule><MindAction Name="A">\n<Parameter No="1" Value="x"/>\n<Parameter No="3" Value="y"/>\n</MindAction>'
        '<CompetencyExecutionPlan/></Rule>',
    )
    assert "No 3" in str(refused(path, 'No="3"'))


def test_duplicate_parameter_number_refused(tmp_path: Path) -> None:
    path = rules_file(
        tmp_path,
        '<Rule><MindAction Name="A">\n<Parameter No="1" Value="x"/>\n<Parameter No="01" Value="y"/>\n</MindAction>'
        '<CompetencyExecutionPlan/></Rule>',
    )
    assert "No 1 already used at line" in str(refused(path, 'No="01"'))


def test_parameter_beyond_rule_count_refused(tmp_path: Path) -> None:
    path = plan_file(
        tmp_path,
        '<Competency ID="1" Type="T">\n<CompetencyParameter Name="ok" Value="$parameter1"/>\n'
        '<CompetencyParameter Name="bad" Value="to $parameter3"/>\n</Competency>',
    )
    exc = refused(path, "$parameter3")
    assert "$parameter3 can never be substituted" in str(exc) and "1 parameter" in str(exc)


def test_parameter_zero_refused(tmp_path: Path) -> None:
    path = plan_file(tmp_path, '<Competency ID="1" Type="T">\n<CompetencyParameter Name="p" Value="$parameter0"/>\n</Competency>')
    assert "$parameter0" in str(refused(path, "$parameter0"))


@pytest.mark.parametrize(
    ("value", "complaint"),
    [
        ("$WM(NoDot)", "$WM(entity.property)"),
        ("$BB()", "names no blackboard"),
        ("$BB(open", "unterminated"),
        ("$WM(a.(b))", "unterminated"),
    ],
)
def test_malformed_lookup_tokens_refused(tmp_path: Path, value: str, complaint: str) -> None:
    path = plan_file(tmp_path, f'<Competency ID="1" Type="T">\n<CompetencyParameter Name="p" Value="{value}"/>\n</Competency>')
    assert complaint in str(refused(path, 'Name="p"'))


def test_duplicate_step_parameter_name_refused(tmp_path: Path) -> None:
    path = plan_file(
        tmp_path,
        '<Competency ID="1" Type="T">\n<CompetencyParameter Name="p" Value="a"/>\n'
        '<CompetencyParameter Name="p" Value="b"/>\n</Competency>',
    )
    assert "'p' already given" in str(refused(path, 'Value="b"'))


def test_missing_type_attribute_refused_by_schema(tmp_path: Path) -> None:
    path = plan_file(tmp_path, '<Competency ID="1" Type="T"/>\n<Competency ID="2" Dependency="1"/>')
    exc = refused(path, 'ID="2"')
    assert isinstance(exc, XmlError) and "Type" in str(exc)


def test_check_types_names_step_rule_and_type(tmp_path: Path) -> None:
    rules = load_rules(TEST_RULES)
    with pytest.raises(ConfigError) as info:
        rules.check_types({"TestType1", "TestType2", "TestType4"})
    exc = info.value
    assert exc.path == str(TEST_RULES) and exc.line == 58
    message = str(exc)
    assert message.startswith(f"{TEST_RULES}:58: ")
    assert "step 2" in message and "'TestAction *'" in message and "'TestType3'" in message


def test_rule_and_ruleset_are_frozen() -> None:
    rule = load_rules(TEST_RULES).rules[0]
    assert isinstance(rule, Rule)
    with pytest.raises(AttributeError):
        rule.name = "x"  # type: ignore[misc]
    assert isinstance(load_rules(TEST_RULES), RuleSet)
