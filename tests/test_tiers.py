"""The test tiers of tests/conftest.py: every test file has one, the exceptions name real tests, a
test has exactly one tier, and a unit test that starts a process or a zenoh session fails."""

from __future__ import annotations

import ast
import functools
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import zenoh

from . import conftest

TESTS = Path(__file__).parent
ROOT = TESTS.parent


@functools.cache
def functions_in(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    return {node.name for node in ast.walk(tree)
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.name.startswith("test_")}


def test_every_test_file_has_a_tier_and_every_tier_names_a_test_file() -> None:
    files = {path.stem for path in TESTS.glob("test_*.py")}
    assert sorted(files - conftest.TIERS.keys()) == [], "test files with no tier (collection fails for them)"
    assert sorted(conftest.TIERS.keys() - files) == [], "tiers of test files that are gone"
    assert set(conftest.TIERS.values()) <= set(conftest.TIER_NAMES)


def test_every_exception_names_a_test_of_its_file_and_another_tier_than_the_files() -> None:
    for entry, tier in conftest.TIER_OF_TEST.items():
        stem, _, function = entry.partition("::")
        assert stem in conftest.TIERS, entry
        assert function in functions_in(TESTS / f"{stem}.py"), f"{entry}: no such test"
        assert tier in conftest.TIER_NAMES and tier != conftest.TIERS[stem], f"{entry}: {tier} is its file's tier already"


class Item:
    """What ``tier_of`` reads of a collected test."""

    def __init__(self, stem: str, function: str, *marks: str) -> None:
        self.path = TESTS / f"{stem}.py"
        self.originalname = function
        self.name = f"{function}[x]"
        self.nodeid = f"tests/{stem}.py::{self.name}"
        self.marks = [getattr(pytest.mark, mark).mark for mark in marks]

    def iter_markers(self) -> list[pytest.Mark]:
        return self.marks


def tier(item: Item) -> str:
    found: Any = item
    return conftest.tier_of(found)


def test_a_test_has_its_own_mark_or_its_listed_tier_or_its_files(request: pytest.FixtureRequest) -> None:
    assert conftest.tier_of(request.node) == "unit" and request.node.get_closest_marker("unit") is not None
    assert tier(Item("test_launch", "test_spirit_starts_three_daemons_that_find_each_other_and_sigint_stops_them_all")) == "mesh"
    assert tier(Item("test_launch", "test_a_bad_file_is_refused_with_every_problem_by_line")) == "unit"
    assert tier(Item("test_launch", "test_a_new_one", "system")) == "system"
    assert tier(Item("test_launch", "test_a_bad_file_is_refused_with_every_problem_by_line", "unit")) == "unit"


@pytest.mark.parametrize(("item", "message"), [
    (Item("test_launch", "test_a", "mesh", "system"), "more than one test tier (mesh, system)"),
    (Item("test_launch", "test_a_bad_file_is_refused_with_every_problem_by_line", "mesh"), "more than one test tier (mesh, unit)"),
    (Item("test_nowhere", "test_a"), "test_nowhere.py has no test tier"),
])
def test_two_tiers_or_none_is_an_error(item: Item, message: str) -> None:
    with pytest.raises(pytest.UsageError, match=message.replace("(", r"\(").replace(")", r"\)")):
        tier(item)


def test_a_unit_test_may_not_start_a_process_nor_open_a_zenoh_session() -> None:
    try:
        with pytest.raises(conftest.StartedInUnitTest, match=r"a process \(subprocess.Popen: .*'-c', 'pass'\]\)"):
            subprocess.run([sys.executable, "-c", "pass"], check=False)
        with pytest.raises(conftest.StartedInUnitTest, match=r"a process \(os.system: b'true'\)"):
            os.system("true")
        with pytest.raises(conftest.StartedInUnitTest, match=r"a zenoh session"):
            zenoh.open(zenoh.Config())
        assert len(conftest.started_in_unit_test) == 3
    finally:
        conftest.started_in_unit_test.clear()  # refused, as this test wants: not a failure of this test


UNIT_FILE = '''
import subprocess, sys
import pytest
import zenoh

def test_quiet():
    pass

def test_swallows_a_process():
    try:
        subprocess.run([sys.executable, "-c", "pass"])
    except Exception:
        pass

def test_swallows_a_zenoh_session():
    try:
        zenoh.open(zenoh.Config())
    except Exception:
        pass

@pytest.mark.mesh
def test_marked_mesh():
    subprocess.run([sys.executable, "-c", "pass"], check=True)
'''


def run_pytest(folder: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """pytest on ``folder`` with tests/conftest.py as a plugin (a fresh process: the guard is per process)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "tests.conftest", "-p", "no:cacheprovider", "-q",
                           "--rootdir", str(folder), *args, str(folder)], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=60)


@pytest.mark.mesh
def test_an_untiered_file_fails_collection_and_a_unit_test_that_starts_something_fails_even_if_it_swallows_the_error(
        tmp_path: Path) -> None:
    untiered = tmp_path / "untiered"
    untiered.mkdir()
    (untiered / "test_brand_new.py").write_text("def test_x():\n    pass\n")
    refused = run_pytest(untiered)
    assert refused.returncode == 2, refused.stdout + refused.stderr
    assert 'test_brand_new.py has no test tier: add "test_brand_new": "unit" (or "mesh", "system") to TIERS in ' \
           "tests/conftest.py" in refused.stdout

    unit = tmp_path / "unit"
    unit.mkdir()
    (unit / "test_keys.py").write_text(UNIT_FILE)  # a file named as one the table says is unit
    ran = run_pytest(unit, "-rf")
    assert ran.returncode == 1, ran.stdout + ran.stderr
    assert "2 failed, 2 passed" in ran.stdout
    assert "test_swallows_a_process is a unit test but started a process (subprocess.Popen: " in ran.stdout
    assert "test_swallows_a_zenoh_session is a unit test but started a zenoh session (zenoh.open)" in ran.stdout
