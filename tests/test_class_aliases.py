"""Configuration files written before the package was arranged in folders (issue 25) still load:
a class named by its old module (``MOVED_MODULES``) is the class of the new one."""

from __future__ import annotations

import importlib
import re
import shutil
from pathlib import Path

import pytest

from cmion_mesh.body.architecture import load_architecture
from cmion_mesh.body.library import load_library
from cmion_mesh.classes import MOVED_MODULES, current_name, import_class
from cmion_mesh.migration.devices import MIGRATION_CLASSES, is_migration_class
from cmion_mesh.resources import data_dir

OLD_NAMES = {new: old for old, new in MOVED_MODULES.items()}
SHIPPED = sorted(p.name for p in data_dir("embodiments").iterdir() if (p / "ArchitectureConfiguration.xml").is_file())


def classes_of(module: str) -> list[str]:
    found = importlib.import_module(module)
    return sorted(name for name, value in vars(found).items() if isinstance(value, type) and value.__module__ == module)


def as_before(spec: str) -> str:
    """``spec`` with its module named as it was before it moved."""
    module, sep, attr = spec.partition(":")
    if not sep:
        module, sep, attr = spec.rpartition(".")
    return f"{OLD_NAMES.get(module, module)}{sep}{attr}"


@pytest.mark.parametrize(("old", "new"), sorted(MOVED_MODULES.items()))
def test_an_old_module_name_loads_the_class_of_the_new_one(old: str, new: str) -> None:
    module = importlib.import_module(new)
    for name in classes_of(new):
        cls = getattr(module, name)
        assert import_class(f"{old}:{name}") is cls
        assert import_class(f"{old}.{name}") is cls
        assert current_name(f"{old}:{name}") == f"{new}:{name}"


@pytest.mark.parametrize("old", sorted(MOVED_MODULES))
def test_an_old_name_hides_no_class_of_today(old: str) -> None:
    # an old name may be a package today (cmion_mesh.migration.manager): it must define no class its alias would hide
    try:
        classes = classes_of(old)
    except ImportError:
        classes = []
    assert classes == [], f"{old} defines {classes}: an old name of MOVED_MODULES must not be a module with classes"


def test_names_of_today_pass_unchanged() -> None:
    assert current_name("cmion_mesh.competency:Competency") == "cmion_mesh.competency:Competency"
    assert current_name("cmion.level3.fatima.FAtiMAConnector") == "cmion.level3.fatima.FAtiMAConnector"


def written_before(source: Path, target: Path) -> None:
    """Copy an embodiment's folder with every ClassName written with the old module names."""
    shutil.copytree(source, target)
    for path in target.glob("*.xml"):
        text = path.read_text()
        path.write_text(re.sub(r'ClassName="([^"]+)"', lambda m: f'ClassName="{as_before(m.group(1))}"', text))


@pytest.mark.parametrize("name", SHIPPED)
def test_a_configuration_written_with_the_old_names_loads_as_the_shipped_one(name: str, tmp_path: Path) -> None:
    shutil.copy(data_dir("embodiments") / "spirit.json", tmp_path / "spirit.json")
    written_before(data_dir("embodiments") / name, tmp_path / name)
    shipped = load_architecture(data_dir("embodiments") / name / "ArchitectureConfiguration.xml")
    before = load_architecture(tmp_path / name / "ArchitectureConfiguration.xml")
    assert [c.class_name for c in before.components] == [as_before(c.class_name) for c in shipped.components]
    assert [type(c) for c in before.build_components()] == [type(c) for c in shipped.build_components()]
    assert shipped.library is not None and before.library is not None
    assert [type(c) for c in load_library(before.library)] == [type(c) for c in load_library(shipped.library)]


def test_a_library_naming_the_migration_competency_by_its_old_module_still_names_a_device_table() -> None:
    ours = sorted(c for c in MIGRATION_CLASSES if c.startswith("cmion_mesh."))
    assert ours
    for spec in ours:
        assert is_migration_class(as_before(spec)), as_before(spec)


def test_what_components_import_from_ion_still_loads() -> None:
    # Component stays in ion; a request and call_later's timers moved to requests and timers (issue
    # 25), and users' components written before import them from ion.
    from cmion_mesh import ion, requests, timers

    assert import_class("cmion_mesh.ion:Component") is ion.Component
    assert ion.IncomingRequest is requests.IncomingRequest
    assert ion.Timer is timers.Timer
