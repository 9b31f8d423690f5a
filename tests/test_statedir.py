"""A daemon's state folder (statedir.StateLock): one daemon per folder, and no trace of one that
stored nothing; a folder that cannot be made is a configuration error naming it. Pure: no network."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from cmion_mesh.errors import ConfigError, ExitCode, Refused, exit_code
from cmion_mesh.statedir import LOCK_FILE, StateLock


def test_a_lock_that_stored_nothing_takes_away_what_it_made_and_nothing_else(tmp_path: Path) -> None:
    folder = tmp_path / "state" / "mesh" / "robot"
    with StateLock(folder):
        assert (folder / LOCK_FILE).read_text() == f"{os.getpid()}\n"
        with pytest.raises(Refused, match=rf"state folder {folder} is in use by another daemon \(pid {os.getpid()}\)"):
            StateLock(folder)
        assert (folder / LOCK_FILE).is_file(), "a refused second lock leaves the holder's folder alone"
    assert not (tmp_path / "state").exists(), "the folder and the parents it made are gone with the lock"
    # A folder holding state stays, lock and parents with it.
    with StateLock(folder):
        (folder / "spirit.record.json").write_text("{}")
    assert sorted(p.name for p in folder.iterdir()) == [LOCK_FILE, "spirit.record.json"]
    # A folder made by someone else (systemd's StateDirectory) stays: only the lock file made here goes.
    given = tmp_path / "given"
    given.mkdir()
    with StateLock(given):
        pass
    assert given.is_dir() and list(given.iterdir()) == []
    # A lock file left by an earlier run is not this lock's to take away.
    (given / LOCK_FILE).write_text("1\n")
    with StateLock(given):
        pass
    assert [p.name for p in given.iterdir()] == [LOCK_FILE]


@pytest.mark.parametrize("where", ["under-a-file", "proc"])
def test_a_folder_that_cannot_be_made_is_a_configuration_error_naming_it(tmp_path: Path, where: str) -> None:
    (tmp_path / "file").write_text("x")
    folder = {"under-a-file": tmp_path / "file" / "state", "proc": Path("/proc/forbidden/state")}[where]
    with pytest.raises(ConfigError) as caught:
        StateLock(folder)
    assert str(caught.value).startswith(f"state folder {folder} cannot be made: ")
    assert "\n" not in str(caught.value) and exit_code(caught.value) == ExitCode.USAGE
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
