"""``cmion-mesh validate``: schema and semantic checks for every CMION XML file kind.

Each file is read through ``xmlsafe`` (safe parsing, XSD validation by its root element), then
checked for meaning: rules (dependency graphs, parameters), libraries (every class imports and
is a competency), world models (unique names, typed values), architecture configurations (the
referenced files, the component classes, and that every competency type the rules use is
provided by the library). Errors name file and line.
"""

from __future__ import annotations

import os
from collections.abc import Callable

from cmion_mesh import xmlsafe
from cmion_mesh.architecture import load_architecture
from cmion_mesh.classes import import_class
from cmion_mesh.competency import load_library
from cmion_mesh.errors import ConfigError
from cmion_mesh.ion import Component
from cmion_mesh.rules import load_rules
from cmion_mesh.storage import load_world_model_init


def _world_model(path: str) -> None:
    load_world_model_init(path)


def _rules(path: str) -> None:
    load_rules(path)


def _library(path: str) -> None:
    load_library(path)


def _architecture(path: str) -> None:
    arch = load_architecture(path)
    rules = load_rules(arch.rules)
    library = load_library(arch.library)
    if arch.world_model is not None:
        _world_model(str(arch.world_model))
    rules.check_types({c.type for c in library})
    for spec in arch.components:
        import_class(spec.class_name, Component, path=str(arch.path), line=spec.line)


#: Root element -> (schema, semantic check run after the schema passed).
KINDS: dict[str, tuple[str, Callable[[str], None]]] = {
    "WorldModel": ("WorldModel.xsd", _world_model),
    "CompetencyLibrary": ("CompetencyLibrary.xsd", _library),
    "CompetencyManagerRules": ("CompetencyManagerRules.xsd", _rules),
    "ArchitectureConfiguration": ("ArchitectureConfiguration.xsd", _architecture),
}


def validate_file(path: str | os.PathLike[str]) -> str:
    """Check one file; returns its kind (root element) or raises ``ConfigError`` naming file and line."""
    name = os.fspath(path)
    root = xmlsafe.load(name, None).getroot().tag
    if not isinstance(root, str) or root not in KINDS:
        raise ConfigError(f"unknown document kind <{root}>; expected one of {', '.join(sorted(KINDS))}", path=name, line=1)
    schema, check = KINDS[root]
    xmlsafe.load(name, schema)
    check(name)
    return root
