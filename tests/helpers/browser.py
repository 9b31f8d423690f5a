"""A real browser for the tests of the web pages: headless Chromium driven by Playwright.

The system's Chromium is used (Debian's ``chromium`` package; ``$CMION_MESH_CHROMIUM`` names
another executable), never a browser downloaded by Playwright. Where there is none, the tests
that need it skip, saying how to get it. Screenshots go to ``tests/screenshots/`` (not in git),
so a person can look at what the tests saw.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

SCREENSHOTS = Path(__file__).parents[1] / "screenshots"
CHROMIUM_ENV = "CMION_MESH_CHROMIUM"
HOW_TO_GET = ("no Chromium for the browser tests: install it (Debian/Ubuntu: sudo apt-get install chromium; "
              f".ci/run does it when it can) or name its executable in ${CHROMIUM_ENV}")


def chromium_path() -> str | None:
    configured = os.environ.get(CHROMIUM_ENV)
    if configured:
        return configured if os.access(configured, os.X_OK) else None
    for candidate in ("/usr/bin/chromium", "/usr/bin/chromium-browser"):
        if os.access(candidate, os.X_OK):
            return candidate
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture
def chromium_browser() -> Iterator[Any]:
    """A headless Chromium (Playwright's sync ``Browser``), one per test: Playwright's own threads
    end with it, so every test still ends with the threads it started stopped."""
    executable = chromium_path()
    if executable is None:
        pytest.skip(HOW_TO_GET)
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("the browser tests need Playwright: pip install -e '.[test]'")
    with sync_playwright() as playwright:
        # Sound plays without a click, as it does once a visitor has touched the page.
        browser = playwright.chromium.launch(executable_path=executable, headless=True,
                                             args=["--autoplay-policy=no-user-gesture-required", "--no-sandbox"])
        try:
            yield browser
        finally:
            browser.close()


def screenshot(page: Any, name: str) -> Path:
    """Save what ``page`` shows as ``tests/screenshots/<name>.png``."""
    SCREENSHOTS.mkdir(exist_ok=True)
    path = SCREENSHOTS / f"{name}.png"
    page.screenshot(path=str(path), full_page=True)
    return path
