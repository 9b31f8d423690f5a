"""``cmion-mesh validate``: schema and semantic checks for every CMION XML file kind, every problem at once.

Each file is read through ``xmlsafe`` (safe parsing), checked against the XSD of its kind (its
root element, ``KINDS``; every schema violation is reported), then for meaning: rules
(dependency graphs, parameters), libraries (every class imports and is a competency, CMION Java
names through the port map), world models (unique names, typed values), architecture
configurations (the referenced files, the components, built as ``up`` builds them, and whether every competency type the
rules use is provided by the library). Problems are collected (``diagnostics``), not raised one at
a time: errors, warnings (stand-ins for Java classes with no equivalent, rule types nothing
provides) and notes (a file found in the working directory), each naming file and line.

An architecture configuration is checked with the files it references (and the device table its
library's Migration competency names): when those files are validated in the same run they are
not checked again alone, so each problem is reported once, under the file it is in.

A new file kind is one ``KINDS`` entry: its root element -> ``Kind(schema, check)``, where
``check(path, diagnostics, options)`` reports every problem of the (schema-valid) file.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path

import msgspec

from cmion_mesh import xmlsafe
from cmion_mesh.body.architecture import Architecture, embodiment_name, read_architecture
from cmion_mesh.body.java_classes import DOC
from cmion_mesh.body.library import load_library, named_table, table_for_library
from cmion_mesh.body.rules import SCHEMA as RULES_SCHEMA
from cmion_mesh.body.rules import RuleSet, parse_rules
from cmion_mesh.body.standin import StandInCompetency, why_standin
from cmion_mesh.competency import Competency
from cmion_mesh.diagnostics import Diagnostic, Diagnostics, load_xml
from cmion_mesh.errors import ConfigError
from cmion_mesh.migration.devices import read_device_table
from cmion_mesh.resources import data_dir
from cmion_mesh.storage import load_world_model_init


class Options(msgspec.Struct, frozen=True):
    #: Competency types served by other processes (``serve-competency``): provided, though not in the library.
    remote_types: frozenset[str] = frozenset()


class Kind(msgspec.Struct, frozen=True):
    schema: str
    check: Callable[[str, Diagnostics, Options], None]
    #: The check reads the file and checks the schema itself (to say an absent element in CMION's
    #: terms, not twice).
    reads_file: bool = False

    def run(self, path: str, diagnostics: Diagnostics, options: Options) -> None:
        """The schema, then the check when the schema passed (or the check alone, ``reads_file``)."""
        if self.reads_file or load_xml(path, self.schema, diagnostics) is not None:
            self.check(path, diagnostics, options)


def _collected(diagnostics: Diagnostics, load: Callable[[list[ConfigError]], object]) -> object:
    """Run a loader that appends per-item problems to a list; every problem reported."""
    problems: list[ConfigError] = []
    try:
        result = load(problems)
    except ConfigError as exc:
        problems.append(exc)
        result = None
    for problem in problems:
        diagnostics.problem(problem)
    return result


def _world_model(path: str, diagnostics: Diagnostics, options: Options) -> None:
    _collected(diagnostics, lambda problems: load_world_model_init(path, problems))


def _rules(path: str, diagnostics: Diagnostics, options: Options) -> None:
    _load_rules(path, diagnostics)


def _library(path: str, diagnostics: Diagnostics, options: Options) -> None:
    _report_standins(load_library(path, diagnostics), None, diagnostics)


def _architecture(path: str, diagnostics: Diagnostics, options: Options) -> None:
    arch = read_architecture(path, diagnostics)
    if arch is None:
        return
    check_embodiment(arch.rules, arch.library, arch.world_model, remote_types=options.remote_types, diagnostics=diagnostics,
                     check_types=arch.library is not None)
    arch.build_components(diagnostics)  # built, not attached: a constructor refusing its parameters is found here
    if arch.library is not None:
        # The device table its Migration competency names, as ``up`` reads it (``validate_paths``
        # then does not check that file alone: each of its problems is reported once).
        table = table_for_library(arch.library, diagnostics)
        try:
            embodiment_name(table, arch)
        except ConfigError as exc:
            diagnostics.problem(exc)


def _migrationconfig(path: str, diagnostics: Diagnostics, options: Options) -> None:
    read_device_table(path, diagnostics)


#: Root element -> the schema and the semantic check run after the schema passed.
KINDS: dict[str, Kind] = {
    "WorldModel": Kind("WorldModel.xsd", _world_model),
    "CompetencyLibrary": Kind("CompetencyLibrary.xsd", _library),
    "CompetencyManagerRules": Kind("CompetencyManagerRules.xsd", _rules),
    "ArchitectureConfiguration": Kind("ArchitectureConfiguration.xsd", _architecture),
    "migrationconfig": Kind("MigrationConfig.xsd", _migrationconfig, reads_file=True),
}


# --- one embodiment's files -------------------------------------------------------------------------------


def _load_rules(path: str | os.PathLike[str], diagnostics: Diagnostics) -> RuleSet | None:
    name = os.fspath(path)
    tree = load_xml(name, RULES_SCHEMA, diagnostics, comments=True)
    if tree is None:
        return None
    ruleset = _collected(diagnostics, lambda problems: parse_rules(tree, name, problems))
    return ruleset if isinstance(ruleset, RuleSet) else None


def check_embodiment(rules: str | os.PathLike[str] | None, library: str | os.PathLike[str] | None,
                     world_model: str | os.PathLike[str] | None = None, *,
                     remote_types: Iterable[str] = (), diagnostics: Diagnostics | None = None,
                     check_types: bool = True) -> tuple[RuleSet | None, list[Competency]]:
    """The checks ``validate`` and ``up`` both make on an embodiment's files: each file loads, and
    every competency type the rules use is provided by the library or named in ``remote_types``
    (served by another process, ``serve-competency``). Returns the rules and the competencies.

    A stand-in competency provides the types the port map knows for its class (CMION's own, else
    its short name): a rule needing one of them fails naming the class, and the stand-in is warned
    about with the rule types depending on it. A type that nothing provides is a warning at the
    step's line, naming the rule and the closest provided types: CMION loaded such a rule, and the
    action failed when it ran, as it does here (``validate --strict`` makes it an error).
    Without ``diagnostics`` the first error raises its ``ConfigError`` (warnings are logged)."""
    diag = Diagnostics.raising() if diagnostics is None else diagnostics
    ruleset = _load_rules(rules, diag) if rules is not None else None
    competencies = load_library(library, diag) if library is not None else []
    if world_model is not None and load_xml(world_model, "WorldModel.xsd", diag) is not None:
        _collected(diag, lambda problems: load_world_model_init(world_model, problems))
    if ruleset is not None and check_types:
        # Loaded as CMION loaded it: the action fails when it runs, with these words.
        for problem in ruleset.type_problems({c.type for c in competencies} | set(remote_types)):
            diag.warning(f"{problem.detail}: loaded as CMION loaded it, the action fails when it runs "
                         "(--remote-type TYPE if another process serves it)", problem.path, problem.line)
    _report_standins(competencies, ruleset, diag)
    return ruleset, competencies


def _report_standins(competencies: list[Competency], ruleset: RuleSet | None, diagnostics: Diagnostics) -> None:
    """One warning per stand-in entry of a library, at its line, with the rule types that depend on it."""
    by_entry: dict[str, list[StandInCompetency]] = {}
    for competency in competencies:
        if isinstance(competency, StandInCompetency):
            by_entry.setdefault(competency.where, []).append(competency)
    lines = ruleset.type_lines() if ruleset is not None else {}
    for where, standins in by_entry.items():
        first = standins[0]
        path, _, line = where.rpartition(":")
        samgar = f" (a SamgarCompetency on port {first.samgar_port!r}: cmion-mesh has no SAMGAR)" if first.samgar_port is not None else ""
        types = [s.type for s in standins]
        if ruleset is None:
            depends = f"its types: {', '.join(types)} (no rules checked with it)"
        else:
            used = [f"{t} ({os.path.basename(ruleset.path)}:{', '.join(str(n) for n in lines[t])})" for t in types if t in lines]
            depends = f"rule types depending on it: {'; '.join(used)}" if used else f"no rule uses its types ({', '.join(types)})"
        diagnostics.warning(f"{why_standin(first.java, first.port)}{samgar}: loaded as a stand-in competency, reported "
                            f"unavailable; {depends}; see {DOC}", path, int(line) if line.isdigit() else None)


# --- files ----------------------------------------------------------------------------------------------------


class FileReport(msgspec.Struct):
    """The outcome of one file: its kind (root element; None if unreadable) and its problems."""

    path: str
    kind: str | None = None
    diagnostics: Diagnostics = msgspec.field(default_factory=Diagnostics)
    #: The architecture configuration this file was checked with, if any.
    checked_with: str | None = None

    def ok(self, strict: bool = False) -> bool:
        return not self.diagnostics.errors and not (strict and self.diagnostics.warnings)


def _kind(path: str, diagnostics: Diagnostics) -> str | None:
    try:
        root = xmlsafe.load(path, None).getroot().tag
    except ConfigError as exc:
        diagnostics.problem(exc)
        return None
    if not isinstance(root, str) or root not in KINDS:
        diagnostics.error(f"unknown document kind <{root}>; expected one of {', '.join(sorted(KINDS))}", path, 1)
        return None
    return root


def check_file(path: str | os.PathLike[str], diagnostics: Diagnostics, options: Options = Options()) -> str | None:
    """Check one file, reporting every problem; its kind (root element), or None if unreadable."""
    name = os.fspath(path)
    kind = _kind(name, diagnostics)
    if kind is None:
        return None
    KINDS[kind].run(name, diagnostics, options)
    return kind


def validate_file(path: str | os.PathLike[str], *, remote_types: Iterable[str] = ()) -> str:
    """Check one file; returns its kind (root element) or raises ``ConfigError`` naming file and
    line (every error of the file in its text)."""
    diagnostics = Diagnostics()
    kind = check_file(path, diagnostics, Options(frozenset(remote_types)))
    diagnostics.raise_if_errors()
    assert kind is not None
    return kind


def validate_paths(paths: Iterable[str], *, remote_types: Iterable[str] = ()) -> list[FileReport]:
    """Check files, architecture configurations first (with the files they reference); one report
    per file, in the order given, each holding the problems found in that file."""
    options = Options(frozenset(remote_types))
    reports = [FileReport(p) for p in paths]
    by_real = {os.path.realpath(r.path): r for r in reports}
    for report in reports:
        report.kind = _kind(report.path, report.diagnostics)
    for report in reports:
        if report.kind != "ArchitectureConfiguration":
            continue
        found = Diagnostics()
        check_file(report.path, found, options)
        arch = read_architecture(report.path, Diagnostics())
        for referenced in _referenced(arch):
            other = by_real.get(os.path.realpath(referenced))
            if other is not None and other is not report and other.kind is not None:
                other.checked_with = report.path
        _distribute(found, report, by_real)
    for report in reports:
        if report.kind is not None and report.kind != "ArchitectureConfiguration" and report.checked_with is None:
            found = Diagnostics()
            KINDS[report.kind].run(report.path, found, options)
            _distribute(found, report, by_real)
    return reports


def _referenced(arch: Architecture | None) -> list[Path]:
    """The files checked with a configuration: its rules, library, world model and device table."""
    if arch is None:
        return []
    table = named_table(arch.library, Diagnostics()) if arch.library is not None else None
    return [p for p in (arch.rules, arch.library, arch.world_model, table) if p is not None]


def _distribute(found: Diagnostics, owner: FileReport, by_real: dict[str, FileReport]) -> None:
    """Each problem goes to the report of the file it is in, if that file is being validated."""
    for item in found:
        target = by_real.get(os.path.realpath(item.path)) if item.path is not None else None
        (target or owner).diagnostics.add(item)


def expand(path: str) -> list[str]:
    """What ``validate PATH`` checks: a file; every ``*.xml`` of a folder and its subfolders (a
    project with a folder per embodiment); or, as ``up`` takes it, the folder of a shipped
    embodiment named by itself (``robot``)."""
    candidate = Path(path)
    if not candidate.exists() and "/" not in path and (data_dir("embodiments") / path).is_dir():
        candidate = data_dir("embodiments") / path
    if candidate.is_dir():
        found = sorted(str(p) for p in candidate.rglob("*.xml") if p.is_file())
        if not found:
            raise ConfigError("no *.xml file in this folder or below it", path=str(candidate))
        return found
    return [path]


def render(diagnostic: Diagnostic, *, strict: bool = False) -> str:
    """A diagnostic as the command line prints it: ``error: file:line: message``."""
    if strict and diagnostic.severity == "warning":
        return f"error: {diagnostic} (a warning, an error with --strict)"
    return f"{'note' if diagnostic.severity == 'info' else diagnostic.severity}: {diagnostic}"
