"""Headless Chromium for the page tests: Debian's ``chromium`` driven by Playwright.

The system browser is used (``/usr/bin/chromium``, or ``CMION_MESH_CHROMIUM``), never one that
Playwright downloads; where there is none the tests skip, saying how to get it.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

SCREENSHOTS = Path(__file__).parent / "screenshots"


def chromium_path() -> str | None:
    path = os.environ.get("CMION_MESH_CHROMIUM") or "/usr/bin/chromium"
    return path if os.access(path, os.X_OK) else None


@pytest.fixture(scope="module")
def chromium_browser() -> Iterator[Any]:
    path = chromium_path()
    if path is None:
        pytest.skip("no Chromium: `apt-get install chromium` (or set CMION_MESH_CHROMIUM to a Chromium binary)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("no Playwright: pip install -e '.[test]'")
    manager = sync_playwright()
    with manager as playwright:
        # Playwright writes files through its loop's default executor, whose threads start on first
        # use and stay: one thread, started here, so that no test seems to leave one running.
        loop = getattr(manager, "_loop", None)
        if loop is not None:
            loop.set_default_executor(ThreadPoolExecutor(max_workers=1, thread_name_prefix="playwright-io"))
        browser = playwright.chromium.launch(executable_path=path, headless=True)
        warm = browser.new_page()
        with tempfile.TemporaryDirectory() as folder:
            warm.screenshot(path=str(Path(folder) / "warm.png"))
        warm.close()
        try:
            yield browser
        finally:
            browser.close()


def screenshot(page: Any, name: str) -> Path:
    SCREENSHOTS.mkdir(exist_ok=True)
    path = SCREENSHOTS / f"{name}.png"
    page.screenshot(path=str(path), full_page=True)
    return path
