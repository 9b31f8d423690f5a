"""Architecture configuration, in CMION's ``ArchitectureConfiguration`` vocabulary.

::

    <ArchitectureConfiguration Embodiment="robot"
        CompetencyManagerRulesFile="rules.xml"
        CompetencyLibraryConfigurationFile="library.xml"
        WorldModelInitFile="worldModel.xml">
      <ArchitectureComponent ClassName="cmion_mesh.planner:PlannerMind" ConstructorParameters="mind,spirit.json"/>
    </ArchitectureConfiguration>

File names are relative to the configuration file. ``ArchitectureComponent`` entries name ION
components (``package.module:Class``, subclasses of ``cmion_mesh.ion.Component``) built with
comma-separated string parameters: minds, monitors, extra stores. A parameter starting with
``./`` or ``../`` is a path relative to the configuration file. ``Embodiment`` (an extension)
names the embodiment; without it the configuration's folder name is used. ``Companion`` (an
extension) names a companion born here on the first start, if this embodiment holds no companion.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from cmion_mesh import keys, signing, xmlsafe
from cmion_mesh.classes import construct, split_parameters
from cmion_mesh.errors import ConfigError, InvalidName, MeshError
from cmion_mesh.ion import Component


@dataclass(frozen=True, slots=True)
class ComponentSpec:
    class_name: str
    parameters: tuple[str, ...]
    line: int | None


@dataclass(frozen=True, slots=True)
class Architecture:
    path: Path
    embodiment: str
    rules: Path
    library: Path
    world_model: Path | None
    components: tuple[ComponentSpec, ...]
    line: int | None = None
    companion: str | None = None
    admit: dict[str, bytes | None] | None = None

    def build_components(self) -> list[Component]:
        built = []
        for spec in self.components:
            parameters = [str((self.path.parent / p).resolve()) if p.startswith(("./", "../")) else p for p in spec.parameters]
            built.append(construct(spec.class_name, Component, parameters, path=str(self.path), line=spec.line))
        return built


def load_architecture(path: str | os.PathLike[str]) -> Architecture:
    """Read and check a configuration: schema, embodiment name, referenced files exist."""
    config = Path(path).resolve()
    tree = xmlsafe.load(config, "ArchitectureConfiguration.xsd")
    root = tree.getroot()
    line = xmlsafe.sourceline(root)

    def referenced(attribute: str, required: bool) -> Path | None:
        value = root.get(attribute)
        if value is None or value.strip() == "":
            if required:
                raise ConfigError(f"{attribute} is required", path=str(config), line=line)
            return None
        try:
            target = (config.parent / value).resolve()
            found = target.is_file()
        except OSError as exc:
            raise ConfigError(f"{attribute} {value[:80]!r}: {exc.strerror or exc}", path=str(config), line=line) from None
        if not found:
            raise ConfigError(f"{attribute} {value!r} not found (looked at {target})", path=str(config), line=line)
        return target

    rules = referenced("CompetencyManagerRulesFile", True)
    library = referenced("CompetencyLibraryConfigurationFile", True)
    assert rules is not None and library is not None
    name = root.get("Embodiment") or config.parent.name
    try:
        keys.check_name(name, "embodiment")
    except InvalidName as exc:
        raise ConfigError(str(exc), path=str(config), line=line) from None
    components = tuple(
        ComponentSpec(el.get("ClassName", ""), split_parameters(el.get("ConstructorParameters")), xmlsafe.sourceline(el))
        for el in root if el.tag == "ArchitectureComponent"
    )
    companion = root.get("Companion") or None
    if companion is not None:
        try:
            keys.check_name(companion, "companion")
        except InvalidName as exc:
            raise ConfigError(str(exc), path=str(config), line=line) from None
    admit: dict[str, bytes | None] | None = None
    for el in root:
        if el.tag == "AdmitCompanion":
            admit = admit or {}
            key = el.get("PublicKey")
            try:
                admit[el.get("Name", "")] = signing.decode_public(key) if key else None
            except MeshError as exc:
                raise ConfigError(str(exc), path=str(config), line=xmlsafe.sourceline(el)) from None
    return Architecture(config, name, rules, library, referenced("WorldModelInitFile", False), components, line, companion, admit)
