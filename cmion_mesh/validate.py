"""``cmion-mesh validate``: schema and semantic checks for every CMION XML file kind.

Each file is read through ``xmlsafe`` (safe parsing, XSD validation by its root element), then
checked for meaning: rules (dependency graphs, parameters), libraries (every class imports and
is a competency), world models (unique names, typed values), architecture configurations (the
referenced files, the component classes, and that every competency type the rules use is
provided by the library). Errors name file and line.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path

from cmion_mesh import xmlsafe
from cmion_mesh.architecture import load_architecture
from cmion_mesh.classes import import_class
from cmion_mesh.competency import Competency, load_library
from cmion_mesh.errors import ConfigError
from cmion_mesh.ion import Component
from cmion_mesh.resources import data_dir
from cmion_mesh.rules import RuleSet, load_rules
from cmion_mesh.storage import load_world_model_init


def _world_model(path: str, remote_types: Iterable[str] = ()) -> None:
    load_world_model_init(path)


def _rules(path: str, remote_types: Iterable[str] = ()) -> None:
    load_rules(path)


def _library(path: str, remote_types: Iterable[str] = ()) -> None:
    load_library(path)


def check_embodiment(rules: str | os.PathLike[str] | None, library: str | os.PathLike[str] | None,
                     world_model: str | os.PathLike[str] | None = None, *,
                     remote_types: Iterable[str] = ()) -> tuple[RuleSet | None, list[Competency]]:
    """The checks ``validate`` and ``up`` both make on an embodiment's files: each file loads, and
    every competency type the rules use is provided by the library or named in ``remote_types``
    (served by another process, ``serve-competency``). Returns the rules and the competencies."""
    ruleset = load_rules(rules) if rules is not None else None
    competencies = load_library(library) if library is not None else []
    if world_model is not None:
        load_world_model_init(world_model)
    if ruleset is not None:
        ruleset.check_types({c.type for c in competencies} | set(remote_types))
    return ruleset, competencies


def _architecture(path: str, remote_types: Iterable[str] = ()) -> None:
    arch = load_architecture(path)
    check_embodiment(arch.rules, arch.library, arch.world_model, remote_types=remote_types)
    for spec in arch.components:
        import_class(spec.class_name, Component, path=str(arch.path), line=spec.line)


def _migrationconfig(path: str, remote_types: Iterable[str] = ()) -> None:
    from cmion_mesh.devices import load_device_table

    load_device_table(path)


#: Root element -> (schema, semantic check run after the schema passed).
KINDS: dict[str, tuple[str, Callable[[str, Iterable[str]], None]]] = {
    "WorldModel": ("WorldModel.xsd", _world_model),
    "CompetencyLibrary": ("CompetencyLibrary.xsd", _library),
    "CompetencyManagerRules": ("CompetencyManagerRules.xsd", _rules),
    "ArchitectureConfiguration": ("ArchitectureConfiguration.xsd", _architecture),
    "migrationconfig": ("MigrationConfig.xsd", _migrationconfig),
}


def validate_file(path: str | os.PathLike[str], *, remote_types: Iterable[str] = ()) -> str:
    """Check one file; returns its kind (root element) or raises ``ConfigError`` naming file and line."""
    name = os.fspath(path)
    root = xmlsafe.load(name, None).getroot().tag
    if not isinstance(root, str) or root not in KINDS:
        raise ConfigError(f"unknown document kind <{root}>; expected one of {', '.join(sorted(KINDS))}", path=name, line=1)
    schema, check = KINDS[root]
    xmlsafe.load(name, schema)
    check(name, remote_types)
    return root


def expand(path: str) -> list[str]:
    """What ``validate PATH`` checks: a file; every ``*.xml`` of a folder; or, as ``up`` takes it, the
    folder of a shipped embodiment named by itself (``robot``)."""
    candidate = Path(path)
    if not candidate.exists() and "/" not in path and (data_dir("embodiments") / path).is_dir():
        candidate = data_dir("embodiments") / path
    if candidate.is_dir():
        found = sorted(str(p) for p in candidate.glob("*.xml"))
        if not found:
            raise ConfigError("no *.xml file in this folder", path=str(candidate))
        return found
    return [path]
