"""A body's competency library: the file that names its competencies, read and built.

The library file uses CMION's ``CompetencyLibrary`` vocabulary with Python classes named
``package.module:Class`` (or dotted ``package.module.Class``) and comma-separated constructor
parameters, passed as strings. ``read_library`` gives its entries as written (what ``up`` needs to
find the device table a Migration competency names, before it opens its session);
``load_library`` builds the competencies, CMION's Java class names going through the port map
(``body.standin``).
"""

from __future__ import annotations

import os
from pathlib import Path

import msgspec

from cmion_mesh import xmlsafe
from cmion_mesh.classes import construct, split_parameters
from cmion_mesh.competency import Competency
from cmion_mesh.diagnostics import Diagnostics, load_xml
from cmion_mesh.errors import ConfigError, MeshError
from cmion_mesh.migration.devices import DeviceTable, is_migration_class, locate_table, read_device_table, table_parameter


class LibraryEntry(msgspec.Struct, frozen=True):
    class_name: str
    parameters: tuple[str, ...]
    line: int | None
    #: A ``SamgarCompetency`` entry's ``Port``; None for a ``Competency`` entry.
    samgar_port: str | None = None


def read_library(path: str | os.PathLike[str], diagnostics: Diagnostics | None = None) -> list[LibraryEntry]:
    """The entries of a library file, ``Competency`` and ``SamgarCompetency`` alike, in file order."""
    tree = load_xml(path, "CompetencyLibrary.xsd", Diagnostics.raising() if diagnostics is None else diagnostics)
    if tree is None:
        return []
    return [
        LibraryEntry(element.get("ClassName", ""), split_parameters(element.get("ConstructorParameters")),
                     xmlsafe.sourceline(element), element.get("Port") if element.tag == "SamgarCompetency" else None)
        for element in tree.getroot() if element.tag in ("Competency", "SamgarCompetency")
    ]


def load_library(path: str | os.PathLike[str], diagnostics: Diagnostics | None = None) -> list[Competency]:
    """Build the competencies a library file names, in file order; errors name file and line.

    CMION class names go through the port map (``standin.resolve``): a class with no equivalent,
    and every ``SamgarCompetency`` entry (cmion-mesh has no SAMGAR), is a stand-in, reported
    unavailable (``validate.check_embodiment`` warns about each, with the rule types needing it).
    With ``diagnostics`` every problem is reported there and the faulty entries are left out;
    without, the first error raises its ``ConfigError``.
    """
    # Start time: ``up`` reads the library for its device table (``read_library``) before it opens its
    # session; the stand-ins bring the update loop and the messages, needed only once it builds.
    from cmion_mesh.body.standin import StandInCompetency, competency_types, resolve, short_name, unique

    diag = Diagnostics.raising() if diagnostics is None else diagnostics
    name = os.fspath(path)
    competencies: list[Competency] = []
    names: set[str] = set()
    for entry in read_library(path, diag):
        resolved = resolve(entry.class_name, entry.parameters, path=name, line=entry.line, diagnostics=diag)
        if resolved is None:
            continue
        if resolved.target is None or entry.samgar_port is not None:
            where = f"{name}:{entry.line}"
            for competency_type in competency_types(resolved):
                try:
                    competencies.append(StandInCompetency(
                        entry.class_name, resolved.port, name=unique(short_name(entry.class_name), names), type=competency_type,
                        parameters=resolved.parameters, where=where, samgar_port=entry.samgar_port))
                except MeshError as exc:  # a class name that cannot be a competency name
                    diag.error(f"{entry.class_name}: {exc}", name, entry.line)
            continue
        try:
            competency = construct(resolved.target, Competency, resolved.parameters, path=name, line=entry.line)
        except ConfigError as exc:
            diag.problem(exc)
            continue
        if competency.name in names:
            diag.error(f"a competency named {competency.name!r} is already in the library", name, entry.line)
            continue
        names.add(competency.name)
        competencies.append(competency)
    return competencies


# --- the device table a library names (CMION: the Migration competency's parameter) -----------


def table_for_library(library: str | os.PathLike[str], diagnostics: Diagnostics | None = None) -> DeviceTable | None:
    """The device table the library's Migration competency names, or None when it names none.
    Errors (reported to ``diagnostics``, every one; without it one ``ConfigError`` lists them all):
    the table is missing (at the library's line), invalid (at its own lines), or two Migration
    competencies name different tables."""
    found = Diagnostics() if diagnostics is None else diagnostics
    path = named_table(library, found)
    table = read_device_table(path, found) if path is not None else None
    if diagnostics is None:
        found.raise_if_errors()
    return table


def named_table(library: str | os.PathLike[str], diagnostics: Diagnostics) -> Path | None:
    """Where the library's Migration competency says its device table is (not read); None when it
    names none, or (reported to ``diagnostics``) a table that is not there or two different ones."""
    lib = os.fspath(library)
    found: tuple[Path, int | None] | None = None
    for entry in read_library(lib, diagnostics):
        if not is_migration_class(entry.class_name) or not entry.parameters or not entry.parameters[0]:
            continue
        # The words of the library's loader (``standin.resolve``): one problem, one report.
        located = locate_table(lib, entry.parameters[0])
        what = table_parameter(entry.class_name)
        note = located.note(what)
        if note is not None:
            diagnostics.info(note, lib, entry.line)
        path = located.path
        if path is None:
            diagnostics.error(located.missing(what), lib, entry.line)
            return None
        if found is not None and found[0] != path:
            diagnostics.error(f"two Migration competencies name different device tables ({found[0].name} at line "
                       f"{found[1]}, {path.name})", lib, entry.line)
            return None
        found = (path, entry.line)
    return found[0] if found is not None else None
