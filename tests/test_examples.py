"""examples/ and docs/tutorial.md: every code block of the tutorial is the text of a file of
examples/ or of a marked region of one (so the two cannot drift), and the examples' pure logic.
That the tutorial's commands run: tests/test_tutorial.py."""

from __future__ import annotations

from collections.abc import Iterator
from types import ModuleType

import pytest

from tests.helpers.tutorial import EXAMPLES, TUTORIAL, code_blocks, quotable, regions


@pytest.fixture
def blink(monkeypatch: pytest.MonkeyPatch) -> Iterator[ModuleType]:
    monkeypatch.syspath_prepend(str(EXAMPLES))
    import blink.competency

    yield blink.competency


def test_every_code_block_of_the_tutorial_is_a_file_or_region_of_examples() -> None:
    texts = quotable()
    blocks = code_blocks(TUTORIAL.read_text())
    assert len(blocks) >= 8, "the tutorial's code blocks were not found"
    stray = [block for block in blocks if block not in texts.values()]
    assert not stray, "code blocks of docs/tutorial.md that are no file or region of examples/:\n" + "\n---\n".join(stray)


def test_the_tutorial_quotes_the_example_competency_rules_and_mind() -> None:
    texts = quotable()
    blocks = code_blocks(TUTORIAL.read_text())
    for name in ("blink/competency.py", "blink/mind.py", "blink/CompetencyManagerRules.xml",
                 "blink/CompetencyLibrary.xml", "blink/lamp/ArchitectureConfiguration.xml"):
        assert texts[name] in blocks, f"the tutorial does not show {name}"


def test_regions_are_read_as_marked_and_bad_marks_name_their_line() -> None:
    text = "a\n# tutorial: begin one\nb\n  <!-- tutorial: begin two -->\nc\n# tutorial: end two\n# tutorial: end one\n"
    assert regions(text) == {"one": "b\nc\n", "two": "c\n"}  # a region's text has no marks, its own or others'
    with pytest.raises(ValueError, match=r"f:2: region 'x' never ends"):
        regions("a\n# tutorial: begin x\n", "f")
    with pytest.raises(ValueError, match=r"f:1: region 'x' ends without beginning"):
        regions("# tutorial: end x\n", "f")
    assert code_blocks("text\n```sh\nls\n```\nmore\n```\nx\ny\n```\n") == ["ls\n", "x\ny\n"]


def test_blink_times_are_whole_numbers_in_range(blink: ModuleType) -> None:
    assert blink.blink_times("3") == 3 and blink.blink_times(blink.MAX_TIMES) == blink.MAX_TIMES
    for bad, why in (("three", "whole number"), ("0", "1 to 20"), ("21", "1 to 20"), (None, "whole number"), ("2.5", "whole number")):
        with pytest.raises(ValueError, match=why):
            blink.blink_times(bad)


def test_the_keeper_remembers_its_visits(blink: ModuleType) -> None:
    from blink.mind import Keeper

    keeper = Keeper()
    assert keeper.name == "keeper" and keeper.state() == {"visits": 0}
    moved = Keeper()
    moved.restore({"visits": 2})
    assert moved.state() == {"visits": 2} and Keeper("3", "watcher").name == "watcher"
