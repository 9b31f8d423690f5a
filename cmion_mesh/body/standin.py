"""Stand-ins: what a CMION Java class with no cmion-mesh equivalent loads as.

A configuration naming a robot head, a Kinect or Greta still starts: each such class (see
``body.java_classes``) becomes a stand-in, reported unavailable, and listed by ``validate``, ``up`` and
``describe``.

* A **stand-in competency** is in the library under the competency types the port map knows for
  the class (CMION's own, read from its sources; else its short name, CMION's usual convention),
  and under no other: a rule type that nothing provides is a warning (``validate.check_embodiment``)
  and fails its action when it runs. A stand-in is never available, so a plan step
  of its type fails with a reason naming the class: "competency type 'GretaBMLSender' is provided
  only by stand-in cmion.inTheWild.competencies.GretaBMLSender (no cmion-mesh equivalent; see
  docs/portmap.md)".
* A **stand-in component** (a mind connector, the SAMGAR connector) is an inert component: it
  handles no request and raises no event.

``resolve`` is the one place where a configured class name becomes what is built: a Python class,
the port map's target (with file-name parameters resolved), a stand-in, or nothing (a GUI add-on
replaced by a command, an abstract base: reported).
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from typing import Any

import msgspec

from cmion_mesh.body import java_classes as portmap
from cmion_mesh.body.java_classes import Port
from cmion_mesh.classes import locate_file
from cmion_mesh.competency import Competency, Done, RunContext, RunResult
from cmion_mesh.diagnostics import Diagnostics
from cmion_mesh.ion import Component, Simulation
from cmion_mesh.migration.devices import is_migration_class, table_parameter


def unavailable_reason(stand_ins: Sequence[StandIn]) -> str:
    """Why these stand-ins never run: ``stand-in JAVA (no cmion-mesh equivalent; see docs/portmap.md)``."""
    classes = list(dict.fromkeys(s.java for s in stand_ins))
    whys = dict.fromkeys("no cmion-mesh equivalent" if s.port is not None else "not in the port map" for s in stand_ins)
    return f"stand-in{'s' if len(classes) > 1 else ''} {', '.join(classes)} ({' or '.join(whys)}; see {portmap.DOC})"


def why_standin(java: str, port: Port | None) -> str:
    """How warnings say why a class is a stand-in: ``cmion.x.Y (what it did) has no cmion-mesh equivalent``."""
    if port is None:
        close = portmap.close_match(java)
        return f"{java} is not in the port map" + (f" (did you mean {close!r}?)" if close else "")
    return f"{java} ({port.note}) has no cmion-mesh equivalent"


class StandIn:
    """What stand-in competencies and components share: the class they stand for and where it was named."""

    java: str
    port: Port | None
    where: str
    samgar_port: str | None = None

    @property
    def reason(self) -> str:
        return unavailable_reason([self])


class StandInCompetency(StandIn, Competency):
    """Never available; runs nothing (no worker thread)."""

    def __init__(self, java: str, port: Port | None, *, name: str, type: str, parameters: Sequence[str] = (),
                 where: str = "", samgar_port: str | None = None) -> None:
        super().__init__(*parameters, name=name, type=type)
        self.java, self.port, self.where, self.samgar_port = java, port, where, samgar_port
        self.available = False

    def start(self, sim: Simulation) -> None:
        self._sim = sim

    def stop(self, timeout: float = 10.0) -> None:
        self._stopping.set()

    def execute(self, run_id: str, parameters: dict[str, Any], done: Done) -> RunContext:
        ctx = RunContext(self, run_id, parameters)
        done(RunResult(run_id, "failed", self.reason))
        return ctx

    def run(self, parameters: dict[str, Any], ctx: RunContext) -> bool:
        return ctx.fail(self.reason)


class StandInComponent(StandIn, Component):
    """An inert component in place of a CMION architecture component."""

    def __init__(self, java: str, port: Port | None, *, name: str, parameters: Sequence[str] = (), where: str = "") -> None:
        super().__init__(name)
        self.java, self.port, self.where = java, port, where
        self.parameters = tuple(parameters)


def summary(objects: Sequence[object]) -> list[dict[str, Any]]:
    """The stand-ins among ``objects``, one entry per configuration entry (file and line), as plain
    data: ``class``, ``kind``, ``where``, ``names`` and, for competencies, ``types`` (and the SAMGAR ``port``)."""
    entries: dict[tuple[str, str], dict[str, Any]] = {}
    for o in objects:
        if not isinstance(o, StandIn):
            continue
        entry = entries.setdefault((o.java, o.where), {
            "class": o.java, "kind": o.port.kind if o.port is not None else "not in the port map", "where": o.where, "names": []})
        entry["names"].append(getattr(o, "name", ""))
        if isinstance(o, Competency):
            entry.setdefault("types", []).append(o.type)
        if o.samgar_port is not None:
            entry["samgar_port"] = o.samgar_port
    return list(entries.values())


class Resolved(msgspec.Struct, frozen=True):
    """What to build for a configured class: ``target`` (``package.module:Class``) with
    ``parameters``, or a stand-in when ``target`` is None."""

    class_name: str
    target: str | None
    port: Port | None
    parameters: tuple[str, ...]

    @property
    def label(self) -> str:
        """The class as the configuration named it, with its port when it has one."""
        if self.target is not None and self.target != self.class_name:
            return f"{self.class_name} (ported as {self.target})"
        return self.class_name


def resolve(class_name: str, parameters: Sequence[str], *, path: str | os.PathLike[str], line: int | None,
            diagnostics: Diagnostics) -> Resolved | None:
    """What the class ``class_name`` named at ``path:line`` becomes; None (reported) when nothing is
    built: an abstract base (error), a GUI add-on whose job a command does (note), a file
    parameter naming no file beside ``path`` nor in the working directory (error; one found in
    the working directory is said in a note)."""
    name = os.fspath(path)
    if not portmap.is_java_name(class_name):
        return Resolved(class_name, class_name, None, tuple(parameters))
    port = portmap.lookup(class_name)
    if port is None:
        return Resolved(class_name, None, None, tuple(parameters))
    if port.action == "base class":
        instead = f"; subclass {port.target} instead" if port.target else ""
        diagnostics.error(f"{class_name} is an abstract base class, which CMION could not build either ({port.note}){instead}",
                          name, line)
        return None
    if port.action == "command":
        diagnostics.info(f"{class_name} ({port.note}) is not loaded: `{port.command}` does its job", name, line)
        return None
    if port.action == "stand-in":
        return Resolved(class_name, None, port, tuple(parameters))
    resolved = list(parameters)
    for index in port.file_parameters:
        if index >= len(resolved):
            continue
        located = locate_file(name, resolved[index])
        # A Migration competency's table: the words ``library.named_table`` says too, so that the
        # daemon's early read of the table and this loader report a missing table once.
        what = table_parameter(class_name) if index == 0 and is_migration_class(class_name) else f"{class_name}: parameter {index + 1}"
        note = located.note(what)
        if note is not None:
            diagnostics.info(note, name, line)
        if located.path is None:
            diagnostics.error(located.missing(what), name, line)
            return None
        resolved[index] = str(located.path)
    return Resolved(class_name, port.target, port, tuple(resolved))


def unique(name: str, taken: set[str]) -> str:
    """``name``, or ``name-2``, ``name-3``... if taken (CMION allowed a class twice); added to ``taken``."""
    candidate, number = name, 1
    while candidate in taken:
        number += 1
        candidate = f"{name}-{number}"
    taken.add(candidate)
    return candidate


def competency_types(resolved: Resolved) -> tuple[str, ...]:
    """The types a stand-in competency is entered under: the port map's, else the class's short name."""
    if resolved.port is not None and resolved.port.types:
        return resolved.port.types
    return (short_name(resolved.class_name),)


def short_name(class_name: str) -> str:
    """``GretaBMLSender`` for ``cmion.inTheWild.competencies.GretaBMLSender`` (or ``pkg.mod:GretaBMLSender``)."""
    return re.split(r"[.:]", class_name)[-1] or class_name
