"""Where the shipped data lives: ``schemas/`` and ``embodiments/``.

A wheel carries them inside the package (``cmion_mesh/schemas``...); a source checkout or an
editable install has them at the repository's top level.
"""

from __future__ import annotations

from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def data_dir(name: str) -> Path:
    for candidate in (_PACKAGE / name, _PACKAGE.parent / name):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(f"cmion-mesh data folder {name!r} not found beside {_PACKAGE}")


def embodiment_dir(name: str) -> Path:
    return data_dir("embodiments") / name
