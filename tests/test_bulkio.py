"""Large files around the page cache (``migration/bulkio.py``): every byte lands where it was written,
whatever the offsets, the file system or a refusal midway."""

from __future__ import annotations

import errno
import fcntl
import itertools
import os
from pathlib import Path
from typing import Any

import pytest

from cmion_mesh.migration import bulkio
from cmion_mesh.migration.bulkio import BLOCK, BOUNCE, DIRECT_MIN, BulkFile

MIB = 1024 * 1024


def takes_direct(folder: Path) -> bool:
    probe = folder / "probe"
    probe.touch()
    try:
        os.close(os.open(probe, os.O_WRONLY | getattr(os, "O_DIRECT", 0)))
        return hasattr(os, "O_DIRECT")
    except OSError:
        return False
    finally:
        probe.unlink()


def pieces(data: bytes) -> list[tuple[int, bytes]]:
    """Pieces of ``data`` out of order: a large aligned one, a large unaligned one, small ones, the tail."""
    cuts = [0, 100, 2 * MIB, 2 * MIB + 5, 3 * MIB + 1234, len(data)]
    parts = [(a, data[a:b]) for a, b in itertools.pairwise(cuts)]
    return parts[::-1]


def test_every_byte_lands_and_large_pieces_go_around_the_page_cache(tmp_path: Path) -> None:
    data = os.urandom(5 * MIB + 777)
    path = tmp_path / "section"
    with BulkFile(path) as file:
        for offset, piece in pieces(data):
            file.write(offset, piece)
        direct = file.direct_bytes
    assert path.read_bytes() == data
    if takes_direct(tmp_path):
        # the aligned middles of the two large pieces; never the small ones or the ends
        assert 4 * MIB < direct <= len(data) and direct % BLOCK == 0
    else:
        assert direct == 0


def test_small_pieces_and_direct_false_use_the_page_cache(tmp_path: Path) -> None:
    data = os.urandom(DIRECT_MIN - 1)
    with BulkFile(tmp_path / "small") as file:
        file.write(0, data)
        assert file.direct_bytes == 0
    big = os.urandom(2 * MIB)
    with BulkFile(tmp_path / "big", direct=False) as file:
        file.write(0, big)
        assert file.direct_bytes == 0
    assert (tmp_path / "small").read_bytes() == data and (tmp_path / "big").read_bytes() == big


def test_a_file_system_that_refuses_o_direct_gets_the_page_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real_open = os.open

    def no_direct(path: Any, flags: int, *args: Any) -> int:
        if flags & getattr(os, "O_DIRECT", 0):
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_open(path, flags, *args)

    monkeypatch.setattr(os, "open", no_direct)
    data = os.urandom(3 * MIB)
    with BulkFile(tmp_path / "f") as file:
        file.write(0, data)
        assert file.direct_bytes == 0
    assert (tmp_path / "f").read_bytes() == data


@pytest.mark.skipif(not hasattr(os, "O_DIRECT"), reason="O_DIRECT is Linux's")
def test_a_direct_write_refused_midway_is_finished_through_the_page_cache(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    if not takes_direct(tmp_path):
        pytest.skip("this file system does not take O_DIRECT")
    real_pwrite = os.pwrite
    calls = {"direct": 0}

    def refuse_second(fd: int, data: Any, offset: int) -> int:
        if fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_DIRECT:
            calls["direct"] += 1
            if calls["direct"] == 2:
                raise OSError(errno.EINVAL, "Invalid argument")
        return real_pwrite(fd, data, offset)

    monkeypatch.setattr(os, "pwrite", refuse_second)
    data = os.urandom(4 * MIB + 10)
    with BulkFile(tmp_path / "f") as file:
        file.write(0, data)
        assert file.direct_bytes == BOUNCE, "the first turn went direct, the rest through the page cache"
        file.write(len(data), b"tail")  # and later pieces too
        assert file.direct_bytes == BOUNCE
    assert (tmp_path / "f").read_bytes() == data + b"tail"


def test_aligned_buffers_are_reused_and_bounded(tmp_path: Path) -> None:
    data = os.urandom(2 * MIB)
    for i in range(8):
        with BulkFile(tmp_path / f"f{i}") as file:
            file.write(0, data)
    assert bulkio.kept() <= bulkio.KEEP
    assert bulkio.kept() >= 1 or not takes_direct(tmp_path)
