"""Problems found in configuration files, collected rather than raised one at a time.

``validate`` and ``up`` check many files and want every problem in one run: loaders take a
``Diagnostics`` and report to it (an error, a warning or a note, each with file and
line). A loader called without one gets ``Diagnostics.raising()``: the first error raises its
``ConfigError`` as before, and warnings go to the log.

* **error**: the file cannot be used as written (``up`` refuses to start);
* **warning**: it loads, but something does not work as in CMION (a stand-in for a Java class
  with no cmion-mesh equivalent); ``validate --strict`` counts warnings as errors;
* **info** (printed as ``note``): worth knowing, nothing to fix (a CMION GUI add-on replaced by a command).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator
from typing import Any, Literal

import msgspec

from cmion_mesh import xmlsafe
from cmion_mesh.errors import ConfigError

log = logging.getLogger(__name__)

Severity = Literal["error", "warning", "info"]


class Diagnostic(msgspec.Struct, frozen=True):
    severity: Severity
    path: str | None
    line: int | None
    message: str

    def __str__(self) -> str:
        if self.path is None:
            return self.message
        where = f"{self.path}:{self.line}" if self.line is not None else self.path
        return f"{where}: {self.message}"

    def as_dict(self) -> dict[str, Any]:
        return {"severity": self.severity, "path": self.path, "line": self.line, "message": self.message}


class Diagnostics:
    """An ordered, duplicate-free list of problems; ``raise_errors`` makes the first error raise."""

    def __init__(self, *, raise_errors: bool = False) -> None:
        self.raise_errors = raise_errors
        self._items: dict[Diagnostic, None] = {}

    @classmethod
    def raising(cls) -> Diagnostics:
        return cls(raise_errors=True)

    def __iter__(self) -> Iterator[Diagnostic]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def add(self, item: Diagnostic) -> None:
        if item.severity == "error" and self.raise_errors:
            raise ConfigError(item.message, path=item.path, line=item.line)
        if self.raise_errors and item not in self._items:
            (log.warning if item.severity == "warning" else log.info)("%s", item)
        self._items[item] = None

    def error(self, message: str, path: str | os.PathLike[str] | None = None, line: int | None = None) -> None:
        self.add(Diagnostic("error", _name(path), line, message))

    def warning(self, message: str, path: str | os.PathLike[str] | None = None, line: int | None = None) -> None:
        self.add(Diagnostic("warning", _name(path), line, message))

    def info(self, message: str, path: str | os.PathLike[str] | None = None, line: int | None = None) -> None:
        self.add(Diagnostic("info", _name(path), line, message))

    def problem(self, exc: ConfigError) -> None:
        """Record a ``ConfigError`` a loader raised (re-raised as it is when raising)."""
        if self.raise_errors:
            raise exc
        self.add(Diagnostic("error", exc.path, exc.line, exc.detail))

    def extend(self, items: Iterable[Diagnostic]) -> None:
        for item in items:
            self.add(item)

    def of(self, severity: Severity) -> list[Diagnostic]:
        return [d for d in self._items if d.severity == severity]

    @property
    def errors(self) -> list[Diagnostic]:
        return self.of("error")

    @property
    def warnings(self) -> list[Diagnostic]:
        return self.of("warning")

    def raise_if_errors(self) -> None:
        """One ``ConfigError`` at the first error's file and line, its text listing every error."""
        errors = self.errors
        if errors:
            first, rest = errors[0], errors[1:]
            raise ConfigError(first.message + "".join(f"\n{d}" for d in rest), path=first.path, line=first.line)


def _name(path: str | os.PathLike[str] | None) -> str | None:
    return None if path is None else os.fspath(path)


def load_xml(path: str | os.PathLike[str], schema: str, diagnostics: Diagnostics, *, comments: bool = False) -> Any:
    """Parse ``path`` safely and check it against ``schema``, reporting every schema violation;
    the tree, or None when the file cannot be used (the reasons reported). ``comments``: as for
    ``xmlsafe.load``."""
    name = os.fspath(path)
    try:
        tree = xmlsafe.load(name, None, comments=comments)
    except ConfigError as exc:
        diagnostics.problem(exc)
        return None
    problems = xmlsafe.schema_problems(tree, schema, name)
    for problem in problems:
        diagnostics.problem(problem)
    return None if problems else tree
