"""Browser fixtures: Debian's headless Chromium driven by Playwright (its Python package).

Chromium is looked up on PATH (``chromium``, ``chromium-browser``) or in
``POSECAST_CHROMIUM``; when it is missing and the tests run as root on a machine
with apt, it is installed (``apt-get install chromium``, what ``.ci/run`` does).
Only when it can neither be found nor installed do these tests skip, saying so.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import AsyncIterator

import pytest
import pytest_asyncio
from playwright.async_api import Browser, Page, async_playwright
from support import CHROMIUM_ARGS, find_chromium


def _install_chromium() -> str | None:
    """apt-get install chromium, when we may (root, apt present); its path or None."""
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        return None
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for cmd in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", "chromium"]):
        if subprocess.run(cmd, env=env, capture_output=True, check=False).returncode != 0:
            return None
    return find_chromium()


@pytest.fixture(scope="session")
def chromium_path() -> str:
    path = find_chromium() or _install_chromium()
    if path is None:
        pytest.skip("chromium not found (PATH, POSECAST_CHROMIUM) and apt-get cannot install it")
    return path


@pytest_asyncio.fixture
async def browser(chromium_path: str) -> AsyncIterator[Browser]:
    async with async_playwright() as p:
        b = await p.chromium.launch(executable_path=chromium_path, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            await b.close()


@pytest_asyncio.fixture
async def page(browser: Browser) -> AsyncIterator[Page]:
    """A 1000x700 page that records its console errors and uncaught exceptions."""
    pg = await browser.new_page(viewport={"width": 1000, "height": 700})
    errors: list[str] = []
    pg.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.errors = errors  # type: ignore[attr-defined]
    yield pg
    await pg.close()
