"""``cmion-mesh validate``: schema and semantic checks for every CMION XML file kind."""

from __future__ import annotations

import os
from collections.abc import Callable

from cmion_mesh import xmlsafe
from cmion_mesh.errors import ConfigError

#: Root element -> (schema, semantic check run after the schema passed).
_KINDS: dict[str, tuple[str, Callable[[str], object] | None]] = {}


def register(root: str, schema: str, check: Callable[[str], object] | None = None) -> None:
    _KINDS[root] = (schema, check)


def _world_model(path: str) -> object:
    from cmion_mesh.storage import load_world_model_init

    return load_world_model_init(path)


register("WorldModel", "WorldModel.xsd", _world_model)
register("CompetencyLibrary", "CompetencyLibrary.xsd")
register("CompetencyManagerRules", "CompetencyManagerRules.xsd")
register("ArchitectureConfiguration", "ArchitectureConfiguration.xsd")


def validate_file(path: str | os.PathLike[str]) -> str:
    """Check one file; returns its kind (root element) or raises ``ConfigError`` naming file and line."""
    name = os.fspath(path)
    root = xmlsafe.load(name, None).getroot().tag
    if not isinstance(root, str) or root not in _KINDS:
        raise ConfigError(f"unknown document kind <{root}>; expected one of {', '.join(sorted(_KINDS))}", path=name, line=1)
    schema, check = _KINDS[root]
    xmlsafe.load(name, schema)
    if check is not None:
        check(name)
    return root
