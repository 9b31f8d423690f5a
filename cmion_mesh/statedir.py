"""A daemon's state folder: what it keeps across restarts, and that no two daemons share it.

The folder holds the migration records (``migration``), the persistent properties of the stores
(``storage``) and ``daemon.lock``: an exclusive ``flock`` held for the daemon's life (the kernel
drops it when the process dies, however it dies), with the holder's pid inside for the refusal.
A daemon that stored nothing (refused its name, say) takes away the folder and lock it made.
"""

from __future__ import annotations

import fcntl
import os
import threading
from pathlib import Path

from cmion_mesh import keys
from cmion_mesh.errors import ConfigError, Refused

LOCK_FILE = "daemon.lock"
#: Tries at the lock when the folder or the lock file goes as it is taken (another daemon leaving).
ATTEMPTS = 10


def default_state_dir(mesh: str, embodiment: str) -> Path:
    """``$XDG_STATE_HOME/cmion-mesh/<mesh>/<embodiment>`` (``~/.local/state`` when unset)."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(base) / "cmion-mesh" / keys.check_name(mesh, "mesh") / keys.check_name(embodiment, "embodiment")


class StateLock:
    """Holds ``directory`` for this process; ``Refused`` naming the holder if another process does,
    ``ConfigError`` naming the folder if it cannot be made or written. A context manager whose
    ``close`` is idempotent (as ``transport.base.Handle``, which this ground module does not
    import: it sits below the transport).

    What it made (the folder, its missing parents, the lock file) it takes away again on ``close``
    while the folder holds nothing but the lock: a daemon refused its name, or that stored nothing,
    leaves no trace. The lock file is unlinked while still locked, and a lock taken on a file
    that is no longer at its path is let go and taken again, so two daemons never hold one folder.
    """

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = Path(directory)
        self._path = self.directory / LOCK_FILE
        self._made: list[Path] = []  # folders made here, outermost first
        self._made_file = False
        self._fd: int | None = None
        try:
            self._make_folders()
            for _ in range(ATTEMPTS):
                fd, made_file = self._open()
                if fd is None:
                    continue  # the folder went as another daemon left: make it again
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
                    os.close(fd)
                    self._made = []  # the folder is the holder's now
                    raise Refused(f"state folder {self.directory} is in use by another daemon (pid {holder}): "
                                  "two daemons never share one (give this one its own --state-dir)") from None
                if not _still_at(fd, self._path):
                    os.close(fd)  # unlinked by a daemon leaving, after it was opened here
                    continue
                self._fd, self._made_file = fd, made_file
                break
            else:
                raise Refused(f"state folder {self.directory} keeps changing under this daemon: not taken")
            os.ftruncate(self._fd, 0)
            os.pwrite(self._fd, f"{os.getpid()}\n".encode(), 0)
        except BaseException:
            self.close()
            raise

    def _make_folders(self) -> int:
        """Make the folder and its missing parents; how many were made here."""
        missing: list[Path] = []
        folder = self.directory
        for _ in range(len(folder.parts)):
            if folder.exists() or folder.is_symlink():
                break
            missing.append(folder)
            folder = folder.parent
        for folder in reversed(missing):
            try:
                folder.mkdir()
            except FileExistsError:
                continue  # another process made it meanwhile: not ours to take away
            except OSError as exc:
                raise ConfigError(f"state folder {self.directory} cannot be made: {exc.strerror or exc}") from None
            self._made.append(folder)
        return len(missing)

    def _open(self) -> tuple[int | None, bool]:
        """The lock file, opened (None when the folder vanished), and whether it was made here."""
        try:
            return os.open(self._path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644), True
        except FileExistsError:
            pass
        except FileNotFoundError:
            if self._make_folders():
                return None, False  # the folder went as another daemon left it: made again
            raise ConfigError(f"state folder {self.directory} cannot be written: no such folder") from None
        except OSError as exc:
            raise ConfigError(f"state folder {self.directory} cannot be written: {exc.strerror or exc}") from None
        try:
            return os.open(self._path, os.O_RDWR), False
        except FileNotFoundError:
            return None, False  # unlinked by a daemon leaving, between the two opens
        except OSError as exc:
            raise ConfigError(f"state folder {self.directory} cannot be written: {exc.strerror or exc}") from None

    def close(self) -> None:
        fd, self._fd = self._fd, None
        made, self._made = self._made, []
        try:
            if fd is not None and self._made_file and _only_the_lock(self.directory):
                os.unlink(self._path)  # still locked: whoever opened it meanwhile sees it gone (_still_at)
            elif fd is not None:
                made = []  # the folder holds state: it stays, and so do its parents
        except OSError:
            made = []
        finally:
            if fd is not None:
                os.close(fd)  # releases the lock
        for folder in reversed(made):
            try:
                folder.rmdir()  # only while empty: another daemon's lock file keeps it
            except OSError:
                break

    def __enter__(self) -> StateLock:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def _still_at(fd: int, path: Path) -> bool:
    """Whether the file open as ``fd`` is still the one at ``path``."""
    try:
        here = os.stat(path)
    except FileNotFoundError:
        return False
    held = os.fstat(fd)
    return (held.st_dev, held.st_ino) == (here.st_dev, here.st_ino)


def _only_the_lock(directory: Path) -> bool:
    try:
        return [entry.name for entry in os.scandir(directory)] == [LOCK_FILE]
    except OSError:
        return False


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
