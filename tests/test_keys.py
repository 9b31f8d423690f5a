from __future__ import annotations

import pytest

from cmion_mesh import keys
from cmion_mesh.errors import InvalidName, MeshError


@pytest.mark.parametrize("bad", ["", "a/b", "a*", "x$y", "#tag", "what?", "@alive", " pad", "tab\t"])
def test_bad_names_are_refused_naming_the_name(bad: str) -> None:
    with pytest.raises(InvalidName) as info:
        keys.check_name(bad, "property")
    assert "property" in str(info.value)
    if bad:
        assert repr(bad) in str(info.value)
    assert isinstance(info.value, MeshError) and isinstance(info.value, ValueError)


def test_grammar() -> None:
    assert keys.storage_key("m", "robot", "bb", ("arm", "left"), "angle") == "cmion/m/robot/bb/arm/left/angle"
    assert keys.storage_key("m", "robot", "wm", (), None) == "cmion/m/robot/wm"
    assert keys.event_key("m", "robot", "manager", "ActionSucceeded") == "cmion/m/robot/ev/manager/ActionSucceeded"
    assert keys.request_key("m", "robot", "bb", "set_property") == "cmion/m/robot/rq/bb/set_property"
    assert keys.alive_key("m", "robot") == "cmion/m/@alive/robot"
    assert keys.event_pattern("m") == "cmion/m/*/ev/*/*"
    with pytest.raises(InvalidName, match="'a/b'"):
        keys.storage_key("m", "robot", "bb", ["x", "a/b"])


def test_parse_round_trips() -> None:
    parsed = keys.parse("cmion/m/robot/bb/arm/angle")
    assert (parsed.mesh, parsed.embodiment, parsed.kind, parsed.rest) == ("m", "robot", "bb", ("arm", "angle"))
    assert keys.parse("cmion/m/@alive/phone").kind == keys.ALIVE
    for bad in ("other/m/robot/bb", "cmion/m/robot/xx/a", "cmion/m/robot/ev/onlyone"):
        with pytest.raises(InvalidName, match="key"):
            keys.parse(bad)


@pytest.mark.parametrize(
    ("pattern", "key", "expected"),
    [
        ("a/*/c", "a/b/c", True),
        ("a/*/c", "a/b/x/c", False),
        ("a/**", "a", True),
        ("a/**", "a/b/c", True),
        ("a/**/c", "a/c", True),
        ("a/**/c", "a/x/y/c", True),
        ("a/**/c", "a/x/y/d", False),
        ("*", "a/b", False),
    ],
)
def test_matches(pattern: str, key: str, expected: bool) -> None:
    assert keys.matches(pattern, key) is expected


@pytest.mark.parametrize(("pattern", "one_chunk", "expected"), [
    ("m/e/rq/**", True, True),
    ("m/e/rq/**", False, True),
    ("m/*/rq/c/x", True, True),
    ("m/e/rq/c/x/y", True, False),  # two chunks below: only ``c/**`` takes it
    ("m/e/rq/c/x/y", False, True),
    ("m/e/rq/c", True, False),  # the prefix itself: ``c/*`` needs one chunk more, ``c/**`` none
    ("m/e/rq/c", False, True),
    ("m/e/rq/*/x", True, True),
    ("m/e/rq/d/*", True, False),  # another component
    ("m/e/rq/c/**/x", True, True),
    ("m/e/rq/c/*/*", True, False),
    ("m/e/rq/c/*/**", True, True),
    ("**", True, True),
])
def test_intersects_below(pattern: str, one_chunk: bool, expected: bool) -> None:
    """Whether a queryable on ``m/e/rq/c/*`` (one chunk) or ``m/e/rq/c/**`` would be reached by a
    query on ``pattern``."""
    assert keys.intersects_below(pattern, "m/e/rq/c", one_chunk=one_chunk) is expected
