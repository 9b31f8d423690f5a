"""What an MCP client is offered of a companion, decided from describe data (pure)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.body.abilities import abilities
from cmion_mesh.body.embodiment import with_migrate_rule
from cmion_mesh.body.rules import load_rules
from cmion_mesh.errors import InvalidArguments
from cmion_mesh.messages import Container, Property
from cmion_mesh.tools.companion_view import (
    belongs_to,
    companion_resources,
    companion_tools,
    progress_message,
    store_document,
)

EMBODIMENTS = Path(__file__).resolve().parent.parent / "embodiments"


def described(name: str, **more: Any) -> dict[str, Any]:
    rules = with_migrate_rule(load_rules(EMBODIMENTS / name / "CompetencyManagerRules.xml"))
    return {"name": name, "abilities": [a.to_json() for a in abilities(rules)], **more}


def test_the_tools_are_the_bodys_abilities_with_migrate_and_peers() -> None:
    robot = companion_tools("spirit", described("robot"), alive={"robot", "screen", "phone"}, policy=None)
    assert [t.name for t in robot] == ["migrate", "peers", "Say", "GoTo", "Greet", "Express"]  # Migrate: once, as migrate
    assert robot[0].input_schema["properties"]["target"]["enum"] == ["phone", "screen"]
    assert robot[1].read_only and not robot[3].read_only
    assert "GoTo <location>" in robot[3].description and "an action of robot" in robot[3].description
    screen = companion_tools("spirit", described("screen"), alive={"robot", "screen"}, policy=["screen", "phone"])
    assert "GoTo" not in [t.name for t in screen]  # a screen cannot navigate
    assert screen[0].input_schema["properties"]["target"]["enum"] == []  # its policy accepts no embodiment alive


def test_arguments_are_checked_before_anything_is_sent() -> None:
    tools = {t.name: t for t in companion_tools("spirit", described("robot"), alive={"robot", "screen"}, policy=None)}
    assert tools["GoTo"].arguments({"location": "Kitchen"}) == ("Kitchen",)
    assert tools["migrate"].arguments({"target": "screen"}) == ("screen",)
    assert tools["peers"].arguments({}) == ()
    for name, given, message in [("migrate", {"target": "mars"}, "'mars' is not an embodiment the companion may move to"),
                                 ("migrate", {}, "'target' (an embodiment's name) is missing"),
                                 ("migrate", {"target": "screen", "now": True}, "unknown argument(s) now"),
                                 ("peers", {"all": True}, "takes no arguments"),
                                 ("GoTo", {}, "argument 'location' is missing")]:
        with pytest.raises(InvalidArguments, match=re.escape(message)):
            tools[name].arguments(given)


def test_an_ability_named_like_a_companion_tool_keeps_a_name_of_its_own() -> None:
    ability = {"tool": "peers", "action": "peers", "parameters": [], "description": "the body's own", "patterns": ["peers"]}
    tools = companion_tools("spirit", {"name": "odd", "abilities": [ability, {"malformed": 1}]}, alive=(), policy=None)
    assert [t.name for t in tools] == ["migrate", "peers", "peers_body"]  # the malformed one left out, not guessed
    assert tools[2].ability is not None and tools[2].ability.action == "peers"


def test_resources_name_the_companion_and_say_the_body() -> None:
    assert companion_resources("spirit", None) == []
    world, board = companion_resources("spirit", "screen")
    assert (world.uri, board.uri) == ("cmion-mesh://spirit/world-model", "cmion-mesh://spirit/blackboard")
    assert world.title == "spirit's world model (on screen)" and world.store == "wm" and board.store == "bb"
    prefix = "cmion/m/screen/wm"
    text = store_document("screen", "wm", {f"{prefix}/Self": Container("agent"), f"{prefix}/Self/location": Property("Hall"),
                                           "cmion/m/screen/wmx/other": Property(1)}, prefix)
    assert json.loads(text) == {"embodiment": "screen", "store": "wm",
                                "entries": {"Self": {"container": "agent"}, "Self/location": "Hall"}}


def test_progress_lines_come_from_the_runs_events() -> None:
    assert belongs_to("mcp-1", {"run_id": "mcp-1#1/1/1"}) and not belongs_to("mcp-1", {"run_id": "mcp-10#1"})
    assert progress_message("Progress", "nav", {"progress": {"location": "Lab", "step": 2, "steps": 9}}) == "nav: step 2 of 9 to Lab"
    assert progress_message("StepFailed", "execution", {"type": "Navigation", "reason": "blocked"}) == "Navigation failed: blocked"
    assert progress_message("PlanStarted", "execution", {}) is None
