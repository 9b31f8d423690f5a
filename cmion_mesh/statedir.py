"""A daemon's state folder: what it keeps across restarts, and that no two daemons share it.

The folder holds the migration records (``migration``), the persistent properties of the stores
(``storage``) and ``daemon.lock``: an exclusive ``flock`` held for the daemon's life (the kernel
drops it when the process dies, however it dies), with the holder's pid inside for the refusal.
"""

from __future__ import annotations

import fcntl
import os
import threading
from pathlib import Path

from cmion_mesh import keys
from cmion_mesh.errors import Refused

LOCK_FILE = "daemon.lock"


def default_state_dir(mesh: str, embodiment: str) -> Path:
    """``$XDG_STATE_HOME/cmion-mesh/<mesh>/<embodiment>`` (``~/.local/state`` when unset)."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(base) / "cmion-mesh" / keys.check_name(mesh, "mesh") / keys.check_name(embodiment, "embodiment")


class StateLock:
    """Holds ``directory`` for this process; ``Refused`` naming the holder if another process does.
    A context manager whose ``close`` is idempotent (as ``transport.base.Handle``, which this ground
    module does not import: it sits below the transport)."""

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        path = self.directory / LOCK_FILE
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise Refused(f"state folder {self.directory} is in use by another daemon (pid {holder}): "
                          "two daemons never share one (give this one its own --state-dir)") from None
        except BaseException:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd: int | None = fd

    def close(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)  # releases the lock

    def __enter__(self) -> StateLock:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def left_by_a_crash(name: str) -> bool:
    """Whether ``name`` is a temporary file of ``write_atomic`` whose writer is gone. A live
    writer's is not (whoever sweeps the folder: its daemon at start-up, or a tool reading it)."""
    if not (name.startswith(".") and name.endswith(".tmp")):
        return False
    parts = name.split(".")
    try:
        pid = int(parts[-3])
    except (IndexError, ValueError):
        return True  # not named by write_atomic: nobody is writing it
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False  # alive, another user's
    return False


def write_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Replace ``path`` with ``data`` so that a crash leaves the old or the new content, never a mix:
    a temporary file (readable by this user only), fsync, rename, fsync of the folder. Temporary
    names carry the process and thread, so concurrent writers never share one; start-up sweeps
    what a crash left (``Records``)."""
    target = Path(path)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, target)
    folder = os.open(target.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)
