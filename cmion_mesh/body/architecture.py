"""Architecture configuration, in CMION's ``ArchitectureConfiguration`` vocabulary.

::

    <ArchitectureConfiguration Embodiment="robot"
        CompetencyManagerRulesFile="rules.xml"
        CompetencyLibraryConfigurationFile="library.xml"
        WorldModelInitFile="worldModel.xml">
      <ArchitectureComponent ClassName="cmion_mesh.minds.planner.mind:PlannerMind" ConstructorParameters="mind,spirit.json"/>
    </ArchitectureConfiguration>

A file name is looked for beside the configuration file, then in the working directory, where
CMION opened it (``new File(name)``; ``classes.locate_file``): a file found there is said in a note,
a file found nowhere is an error naming both places. ``ArchitectureComponent`` entries name ION
components (``package.module:Class``, subclasses of ``cmion_mesh.ion.Component``) built with
comma-separated string parameters: minds, monitors, extra stores. A parameter starting with
``./`` or ``../`` is a path relative to the configuration file. ``Embodiment`` (an extension)
names the embodiment; without it the configuration's folder name is used, which must then be a
valid embodiment name (else an error asks for ``Embodiment``). ``Companion`` (an extension) names
a companion born here on the first start, if this embodiment holds no companion.

CMION's own files load unchanged: Java class names go through the port map (``body.java_classes``; a class
with no equivalent is an inert stand-in component, ``standin``), components and ``AdmitCompanion``
may come in any order, and a referenced file name without a suffix that is not found as given is
looked up as ``NAME.xml`` (CMION for Android named raw resources so).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec

from cmion_mesh import keys, xmlsafe
from cmion_mesh.classes import construct, import_class, locate_file, split_parameters
from cmion_mesh.diagnostics import Diagnostics, load_xml
from cmion_mesh.errors import ConfigError, InvalidName, MeshError
from cmion_mesh.migration import signing
from cmion_mesh.migration.devices import DeviceTable

if TYPE_CHECKING:
    from cmion_mesh.ion import Component


class ComponentSpec(msgspec.Struct, frozen=True):
    class_name: str
    parameters: tuple[str, ...]
    line: int | None


class Architecture(msgspec.Struct, frozen=True):
    path: Path
    embodiment: str
    rules: Path | None
    library: Path | None
    world_model: Path | None
    components: tuple[ComponentSpec, ...]
    line: int | None = None
    companion: str | None = None
    admit: dict[str, bytes | None] | None = None

    def build_components(self, diagnostics: Diagnostics | None = None) -> list[Component]:
        """The components, built in file order: ported or Python classes, inert stand-ins for Java
        classes with no equivalent (each warned about). With ``diagnostics`` every problem is
        reported there and the faulty components left out; without, the first error raises.

        ``validate`` builds them too, so that a constructor refusing its parameters is found before
        ``up``: building one has no effect outside it (servers bind in ``attach``), and the
        components the embodiment builds itself (``built_by_embodiment``) are refused unbuilt."""
        # Imported here: reading a configuration (``up`` does, to know its name and endpoints before
        # it joins the mesh) needs none of the component machinery.
        from cmion_mesh.body.java_classes import DOC
        from cmion_mesh.body.standin import StandInComponent, resolve, unique, why_standin
        from cmion_mesh.ion import Component

        diag = Diagnostics.raising() if diagnostics is None else diagnostics
        where = str(self.path)
        built: list[Component] = []
        names: set[str] = set()
        for spec in self.components:
            parameters = [str((self.path.parent / p).resolve()) if p.startswith(("./", "../")) else p for p in spec.parameters]
            resolved = resolve(spec.class_name, parameters, path=where, line=spec.line, diagnostics=diag)
            if resolved is None:
                continue
            if resolved.target is None:
                try:
                    standin = StandInComponent(spec.class_name, resolved.port, name=unique(spec.class_name.rpartition(".")[2], names),
                                               parameters=resolved.parameters, where=f"{where}:{spec.line}")
                except MeshError as exc:
                    diag.error(f"{spec.class_name}: {exc}", where, spec.line)
                    continue
                diag.warning(f"{why_standin(spec.class_name, resolved.port)}: loaded as an inert stand-in component "
                             f"{standin.name!r}, reported unavailable; see {DOC}", where, spec.line)
                built.append(standin)
                continue
            try:
                cls = import_class(resolved.target, Component, path=where, line=spec.line)
                if cls.built_by_embodiment:
                    raise ConfigError(f"{resolved.target} is built by every embodiment itself (one per embodiment): "
                                      "remove it from the configuration", path=where, line=spec.line)
                component = construct(resolved.target, Component, resolved.parameters, path=where, line=spec.line)
            except ConfigError as exc:
                diag.problem(_ported(exc, resolved.class_name, resolved.target))
                continue
            if component.name in names:  # the embodiment would refuse the second one when adding it
                diag.error(f"{resolved.label}: a component named {component.name!r} is already in this configuration "
                           "(give it another name)", where, spec.line)
                continue
            names.add(component.name)
            built.append(component)
        return built


def _ported(exc: ConfigError, class_name: str, target: str) -> ConfigError:
    """Name the configured Java class too when its cmion-mesh equivalent failed (once: not the
    target's name again after it)."""
    if class_name == target:
        return exc
    detail = exc.detail.removeprefix(f"{target}: ")
    return ConfigError(f"{class_name} (ported as {target}): {detail}", path=exc.path, line=exc.line)


def load_architecture(path: str | os.PathLike[str], *, name: str | None = None) -> Architecture:
    """Read and check a configuration: schema, embodiment name, referenced files exist; the first
    problem raises its ``ConfigError``. ``name`` replaces the configuration's embodiment name."""
    arch = read_architecture(path, Diagnostics.raising(), name=name)
    assert arch is not None  # a raising collector raised instead
    return arch


def read_architecture(path: str | os.PathLike[str], diagnostics: Diagnostics, *, name: str | None = None) -> Architecture | None:
    """``load_architecture`` reporting every problem to ``diagnostics``; None when the file itself
    is unusable (unreadable, not matching the schema)."""
    config = Path(path).resolve()
    where = str(config)
    tree = load_xml(config, "ArchitectureConfiguration.xsd", diagnostics)
    if tree is None:
        return None
    root = tree.getroot()
    line = xmlsafe.sourceline(root)

    def referenced(attribute: str, required: bool) -> Path | None:
        value = root.get(attribute)
        if value is None or value.strip() == "":
            if required:
                diagnostics.error(f"{attribute} is required", where, line)
            return None
        located = locate_file(config, value)
        if located.path is None:
            diagnostics.error(located.missing(attribute), where, line)
        note = located.note(attribute)
        if note is not None:
            diagnostics.info(note, where, line)
        return located.path

    rules = referenced("CompetencyManagerRulesFile", True)
    library = referenced("CompetencyLibraryConfigurationFile", True)
    world_model = referenced("WorldModelInitFile", False)
    name = name or root.get("Embodiment")
    try:
        if name:
            keys.check_name(name, "embodiment")
        else:
            name = config.parent.name
            try:
                keys.check_name(name, "embodiment")
            except InvalidName as exc:
                raise InvalidName(f"no Embodiment attribute, and the folder name cannot be the embodiment's name ({exc}): "
                                  "add Embodiment=\"NAME\" or start it with --name") from None
    except InvalidName as exc:
        diagnostics.error(str(exc), where, line)
    components = tuple(
        ComponentSpec(el.get("ClassName", ""), split_parameters(el.get("ConstructorParameters")), xmlsafe.sourceline(el))
        for el in root if el.tag == "ArchitectureComponent"
    )
    companion = root.get("Companion") or None
    if companion is not None:
        try:
            keys.check_name(companion, "companion")
        except InvalidName as exc:
            diagnostics.error(str(exc), where, line)
    admit: dict[str, bytes | None] | None = None
    for el in root:
        if el.tag == "AdmitCompanion":
            admit = admit or {}
            key = el.get("PublicKey")
            try:
                admit[el.get("Name", "")] = signing.decode_public(key) if key else None
            except MeshError as exc:
                diagnostics.error(str(exc), where, xmlsafe.sourceline(el))
    return Architecture(config, name, rules, library, world_model, components, line, companion, admit)


def embodiment_name(table: DeviceTable | None, arch: Architecture) -> str:
    """The table's devicename, else the configuration's name. A configuration that names its
    embodiment (``Embodiment="..."``, not just its folder's name) differently from the table is a
    ``ConfigError``: the command line's ``--name`` settles it."""
    if table is None or table.name is None:
        return arch.embodiment
    explicit = arch.embodiment != arch.path.parent.name
    if explicit and arch.embodiment != table.name:
        raise ConfigError(f"Embodiment={arch.embodiment!r} but its device table {table.path.name} names this embodiment "
                          f"{table.name!r} (give --name to choose)", path=str(arch.path), line=arch.line)
    return table.name
