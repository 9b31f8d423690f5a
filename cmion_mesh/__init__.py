"""cmion-mesh: CMION's mind-body middleware rebuilt as a zenoh peer-to-peer embodiment mesh.

What code written against cmion-mesh uses, importable from here::

    from cmion_mesh import MeshClient, Component, Competency, RunContext, Mind, MeshError

* ``MeshClient``: a session's view of a mesh (ask, set, watch, migrate);
* ``Component`` and ``Simulation``: an ION component and the update loop it runs in;
* ``Competency`` and ``RunContext``: a unit of work a body can do, and what a run of it sees;
* ``Mind``: the agent mind interface; ``Embodiment``: a whole body, run in this process;
* ``MeshError``, the root of every error cmion-mesh raises, and its families (``ConfigError``,
  ``RequestRejected``, ``OutcomeUnknown``...).

Each name is loaded when first used: importing ``cmion_mesh`` loads none of the modules behind
them (nor zenoh), so a program pays only for what it uses. The names live in their own modules
(``cmion_mesh.client``, ``cmion_mesh.ion``...), which is where the package's own modules import them.
"""

from __future__ import annotations

import importlib

# Not ``typing.TYPE_CHECKING``: typing costs milliseconds this import would spend on nothing (type
# checkers treat any ``TYPE_CHECKING`` name as true).
TYPE_CHECKING = False

__version__ = "0.1.0"

#: Each name of the face -> the module it lives in.
_EXPORTS: dict[str, str] = {
    "MeshClient": "cmion_mesh.client",
    "Component": "cmion_mesh.ion",
    "Simulation": "cmion_mesh.ion",
    "Competency": "cmion_mesh.competency",
    "RunContext": "cmion_mesh.competency",
    "Mind": "cmion_mesh.mind",
    "Embodiment": "cmion_mesh.body.embodiment",
    **{name: "cmion_mesh.errors" for name in (
        "MeshError", "ClosedError", "ConfigError", "InvalidArguments", "InvalidName", "NotAlive", "NotReached", "OutcomeUnknown",
        "PlanError", "ProtocolError", "Refused", "RequestError", "RequestRejected", "StorageError", "TransportError", "Vanished",
        "WebServerError", "XmlError")},
}

__all__ = [
    "ClosedError",
    "Competency",
    "Component",
    "ConfigError",
    "Embodiment",
    "InvalidArguments",
    "InvalidName",
    "MeshClient",
    "MeshError",
    "Mind",
    "NotAlive",
    "NotReached",
    "OutcomeUnknown",
    "PlanError",
    "ProtocolError",
    "Refused",
    "RequestError",
    "RequestRejected",
    "RunContext",
    "Simulation",
    "StorageError",
    "TransportError",
    "Vanished",
    "WebServerError",
    "XmlError",
    "__version__",
]

if TYPE_CHECKING:
    from cmion_mesh.body.embodiment import Embodiment
    from cmion_mesh.client import MeshClient
    from cmion_mesh.competency import Competency, RunContext
    from cmion_mesh.errors import (
        ClosedError,
        ConfigError,
        InvalidArguments,
        InvalidName,
        MeshError,
        NotAlive,
        NotReached,
        OutcomeUnknown,
        PlanError,
        ProtocolError,
        Refused,
        RequestError,
        RequestRejected,
        StorageError,
        TransportError,
        Vanished,
        WebServerError,
        XmlError,
    )
    from cmion_mesh.ion import Component, Simulation
    from cmion_mesh.mind import Mind


def __getattr__(name: str) -> object:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'cmion_mesh' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # the next use is a plain attribute read
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
