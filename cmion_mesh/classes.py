"""Classes named in configuration files (``package.module:Class``), as CMION named Java classes.

Libraries, architecture configurations and the ``serve-*`` commands build competencies, minds and
components this way, with CMION's comma-separated string constructor parameters.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

import msgspec

from cmion_mesh.errors import ConfigError, MeshError

T = TypeVar("T")

# Modules moved when the package was arranged in folders (issue 25): old name -> new name.
# Configuration files written before name classes by the old module (ClassName="<old>:<Class>"),
# and users keep them: import_class reads an old module name as its new one. Kept in step with
# the moves; an old name is never given to another module.
MOVED_MODULES: dict[str, str] = {
    "cmion_mesh.transport": "cmion_mesh.transport.base",
    "cmion_mesh.zenoh_transport": "cmion_mesh.transport.zenoh",
    "cmion_mesh.memory_transport": "cmion_mesh.transport.memory",
    "cmion_mesh.security": "cmion_mesh.transport.security",
    "cmion_mesh.certs": "cmion_mesh.transport.certs",
    "cmion_mesh.outbox": "cmion_mesh.transport.outbox",
    "cmion_mesh.migration": "cmion_mesh.migration.manager",
    "cmion_mesh.handshake": "cmion_mesh.migration.handshake",
    "cmion_mesh.custody": "cmion_mesh.migration.custody",
    "cmion_mesh.signing": "cmion_mesh.migration.signing",
    "cmion_mesh.identity": "cmion_mesh.migration.identity",
    "cmion_mesh.records": "cmion_mesh.migration.ledger",
    "cmion_mesh.invitation": "cmion_mesh.migration.invitation",
    "cmion_mesh.devices": "cmion_mesh.migration.devices",
    "cmion_mesh.embodiment": "cmion_mesh.body.embodiment",
    "cmion_mesh.architecture": "cmion_mesh.body.architecture",
    "cmion_mesh.standin": "cmion_mesh.body.standin",
    "cmion_mesh.portmap": "cmion_mesh.body.java_classes",
    "cmion_mesh.remote": "cmion_mesh.body.remote",
    "cmion_mesh.execution": "cmion_mesh.body.execution",
    "cmion_mesh.manager": "cmion_mesh.body.manager",
    "cmion_mesh.rules": "cmion_mesh.body.rules",
    "cmion_mesh.validate": "cmion_mesh.body.validate",
    "cmion_mesh.supersimple": "cmion_mesh.minds.supersimple",
    "cmion_mesh.planner": "cmion_mesh.minds.planner.mind",
    "cmion_mesh.planner_spec": "cmion_mesh.minds.planner.spec",
    "cmion_mesh.planner_search": "cmion_mesh.minds.planner.search",
    "cmion_mesh.fatima": "cmion_mesh.minds.fatima.connector",
    "cmion_mesh.webserver": "cmion_mesh.web.server",
    "cmion_mesh.webbody": "cmion_mesh.web.body",
    "cmion_mesh.view": "cmion_mesh.web.view",
    "cmion_mesh.competencies.web": "cmion_mesh.web.competencies",
    "cmion_mesh.speech": "cmion_mesh.web.speech",
    "cmion_mesh.ros2": "cmion_mesh.ros2.wire",
    "cmion_mesh.competencies.ros2": "cmion_mesh.ros2.competencies",
    "cmion_mesh.record": "cmion_mesh.tools.recording",
    "cmion_mesh.replay": "cmion_mesh.tools.replay",
    "cmion_mesh.tap": "cmion_mesh.tools.hz_echo",
    "cmion_mesh.doctor": "cmion_mesh.tools.doctor",
    "cmion_mesh.launch": "cmion_mesh.tools.launch",
    "cmion_mesh.demo": "cmion_mesh.tools.demo",
    "cmion_mesh.router": "cmion_mesh.tools.router",
    "cmion_mesh.cli": "cmion_mesh.cli.main",
}


def current_name(spec: str) -> str:
    """``spec`` (``package.module:Class`` or ``package.module.Class``) as named today: an old module
    name (``MOVED_MODULES``) becomes its new one; anything else is returned as it is."""
    module_name, sep, attr = spec.partition(":")
    if not sep:
        module_name, sep, attr = spec.rpartition(".")
    new = MOVED_MODULES.get(module_name)
    return spec if new is None else f"{new}{sep}{attr}"


def import_class(spec: str, base: type[T] | None = None, *, path: str | None = None, line: int | None = None) -> type[T]:
    """Import ``package.module:Class`` (or ``package.module.Class``), a subclass of ``base`` if given;
    ``ConfigError`` naming the file and line otherwise."""
    module_name, sep, attr = spec.partition(":")
    if not sep:
        module_name, _, attr = spec.rpartition(".")
    if not module_name or not attr:
        raise ConfigError(f"class name {spec!r} is not of the form package.module:Class", path=path, line=line)
    module_name = MOVED_MODULES.get(module_name, module_name)  # a file written before a move
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # ImportError; TypeError for a relative name; whatever the module raised
        raise ConfigError(f"cannot import module {module_name!r} for {spec!r}: {exc}", path=path, line=line) from None
    try:
        cls = getattr(module, attr)
    except AttributeError:
        raise ConfigError(f"module {module_name!r} has no class {attr!r}", path=path, line=line) from None
    if not isinstance(cls, type):
        raise ConfigError(f"{spec!r} is not a class", path=path, line=line)
    if base is not None and not issubclass(cls, base):
        raise ConfigError(f"{spec!r} is not a {base.__module__}.{base.__name__} subclass", path=path, line=line)
    found: type[T] = cls
    return found


def construct(spec: str, base: type[T], parameters: Sequence[str] = (), *, path: str | None = None, line: int | None = None) -> T:
    """Import and build ``spec`` with string parameters; every failure a ``ConfigError`` at the line.

    ``validate`` builds what it checks, so a constructor must have no effect outside its object:
    sockets, threads, files and subscriptions belong in ``attach`` / ``start``."""
    cls = import_class(spec, base, path=path, line=line)
    try:
        instance: Any = cls(*parameters)
    except MeshError as exc:
        raise ConfigError(f"{spec}: {exc}", path=path, line=line) from None
    except Exception as exc:  # a wrong number of parameters (TypeError), a bad value, a bug: the entry's fault either way
        raise ConfigError(f"cannot construct {spec} with parameters {list(parameters)}: {type(exc).__name__}: {exc}",
                          path=path, line=line) from None
    built: T = instance
    return built


def split_parameters(raw: str | None) -> tuple[str, ...]:
    """CMION's comma-separated constructor parameters, split as CMION split them (a
    ``StringTokenizer`` on ``,``): each trimmed, empty ones dropped; absent means none."""
    if raw is None:
        return ()
    return tuple(p.strip() for p in raw.split(",") if p.strip())


def find_file(folder: str | Path, value: str) -> Path | None:
    """The file a configuration names, relative to ``folder``: ``value`` itself, else ``value.xml``
    when ``value`` has no suffix (CMION for Android named raw resources without ``.xml``:
    ``compmanagerrules`` is ``compmanagerrules.xml``); None when neither is a file."""
    for candidate in _candidates(Path(folder), value):
        try:
            if candidate.is_file():
                return candidate.resolve()
        except (OSError, ValueError):  # a name too long for the file system, a NUL
            continue
    return None


def _candidates(folder: Path, value: str) -> list[Path]:
    candidates = [folder / value]
    if not Path(value).suffix:
        candidates.append(folder / f"{value}.xml")
    return candidates


class Located(msgspec.Struct, frozen=True):
    """Where a file a configuration names was found (``locate_file``): ``path``, None when nowhere;
    ``folders``, the folders looked in, in order; ``in_working_dir`` when it was not beside the
    file naming it but in the working directory."""

    value: str
    path: Path | None
    folders: tuple[Path, ...]
    in_working_dir: bool = False

    def note(self, what: str) -> str | None:
        """What ``validate`` and ``up`` say of a file found in the working directory (once, as a note)."""
        if not self.in_working_dir:
            return None
        return (f"{what} {_shown(self.value)!r} is not beside this file: found in the working directory, {self.path} "
                "(CMION opened file names relative to its working directory)")

    def missing(self, what: str) -> str:
        """The error for a file found nowhere, naming every place looked at."""
        places = [" or ".join(str(c) for c in _candidates(folder, self.value[:200])) for folder in self.folders]
        if len(self.folders) == 2:
            looked = f"looked beside this file, at {places[0]}, and in the working directory, at {places[1]}"
        else:
            looked = f"looked at {places[0]}"
        return f"{what} {_shown(self.value)!r} not found ({looked})"


def _shown(value: str) -> str:
    return value if len(value) <= 80 else value[:80] + "..."


def locate_file(naming_file: str | os.PathLike[str], value: str) -> Located:
    """The file ``value`` names, as CMION found it: beside ``naming_file`` (the configuration
    naming it), then in the working directory (CMION opened every name with ``new File(name)``,
    relative to the folder it was started from, and projects kept files there). An absolute name
    is looked for where it says; ``find_file`` gives the ``.xml`` of an Android raw-resource name."""
    beside = Path(naming_file).resolve().parent
    if Path(value).is_absolute():
        return Located(value, find_file(beside, value), (Path(value).parent,))
    try:
        cwd = Path.cwd().resolve()
    except OSError:  # the working directory was removed: there is nothing to find there
        cwd = beside
    found = find_file(beside, value)
    if found is not None or cwd == beside:
        return Located(value, found, (beside,) if cwd == beside else (beside, cwd))
    found = find_file(cwd, value)
    return Located(value, found, (beside, cwd), in_working_dir=found is not None)
