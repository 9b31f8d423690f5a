"""One exception root, with families by meaning.

Every message names the thing at fault: a file and line, a key, a peer, a component.
Callers catch a family (``ConfigError``, ``RequestError``...) or the root ``MeshError``.
"""

from __future__ import annotations

from enum import IntEnum


class MeshError(Exception):
    """Root of every error cmion-mesh raises on purpose."""


class InvalidName(MeshError, ValueError):
    """A name that cannot be carried in one key chunk (mesh, embodiment, component, property...)."""



class InvalidArguments(MeshError, ValueError):
    """A call's arguments do not fit what it accepts (a tool call to a body ability: a parameter
    missing, unknown or outside its choices); nothing was sent."""


class ConfigError(MeshError):
    """A file or setting is unusable: malformed, hostile, oversized, or semantically wrong.

    ``path`` and ``line`` locate the fault when it comes from a file.
    """

    def __init__(self, message: str, *, path: str | None = None, line: int | None = None) -> None:
        self.path = path
        self.line = line
        where = ""
        if path is not None:
            where = f"{path}:{line}: " if line is not None else f"{path}: "
        super().__init__(f"{where}{message}")
        self.detail = message


class XmlError(ConfigError):
    """An XML file was refused: unsafe construct, size cap, syntax or schema violation."""


class ProtocolError(MeshError):
    """Bytes from the network do not decode to the message the key expects."""


class TransportError(MeshError):
    """The zenoh session could not be opened or used."""


class RequestError(MeshError):
    """A request did not end in acceptance."""

    def __init__(self, message: str, *, key: str = "") -> None:
        self.key = key
        super().__init__(message)


class RequestRejected(RequestError):
    """The component answered: rejected (with its reason) or lost a conflict.

    ``code`` is the outcome's machine-readable reason (``messages.Code``): test it, not the text.
    """

    def __init__(self, message: str, *, key: str = "", status: str = "rejected", reason: str = "", code: str = "") -> None:
        self.status = status
        self.reason = reason
        self.code = code
        super().__init__(message, key=key)


class OutcomeUnknown(RequestError):
    """No definite answer: nobody answered, the link broke, or the deadline passed.

    Never treat this as success: the request may or may not have been applied.
    """


class NotReached(OutcomeUnknown):
    """No component was reached at all (zero replies before the deadline): the request was not
    delivered, so sending it again is safe. A session that has just opened sees this until it has
    joined the mesh."""


class Vanished(OutcomeUnknown):
    """The embodiment asked left the mesh (its liveliness token went) before answering."""


class NotAlive(MeshError):
    """A named embodiment is not alive in the mesh: nothing was sent to it."""


class Refused(MeshError):
    """A daemon refused to start: it would break "one name, one body" or share a state folder."""


class StorageError(MeshError):
    """A blackboard or world-model operation cannot be applied: it refers to a container or
    property that is not there, or clashes with what is.

    ``code`` says which for programs (a ``messages.Code`` value: ``not_found``, ``exists``,
    ``invalid``); it becomes the refused request's ``Outcome.code``.
    """

    def __init__(self, message: str, *, code: str = "not_found") -> None:
        self.code = code
        super().__init__(message)


class WebServerError(MeshError):
    """A web page server could not listen on its address or did not start."""


class ClosedError(MeshError):
    """The object was used after ``close()``."""


class PlanError(MeshError):
    """A plan step cannot run: a substitution has no value, no competency of its type exists..."""


class ExitCode(IntEnum):
    """The command line's exit codes, the same for every command."""

    OK = 0
    FAILED = 1  # failed, or refused (a definite "no")
    USAGE = 2  # usage or configuration error: nothing was tried
    CANCELLED = 3
    UNKNOWN = 4  # outcome unknown: no answer, the target vanished
    INTERRUPTED = 130  # left on a second Ctrl-C without waiting for the outcome


def exit_code(exc: BaseException) -> ExitCode:
    """The exit code that tells what an error means."""
    if isinstance(exc, OutcomeUnknown):
        return ExitCode.UNKNOWN
    if isinstance(exc, ConfigError | InvalidName):
        return ExitCode.USAGE
    return ExitCode.FAILED
