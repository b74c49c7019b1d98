"""Fixtures of the browser tests: one real service (token on), Debian's chromium through Playwright,
and a page that already holds the token (as the token form leaves it: in sessionStorage)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from ..server.conftest import client  # noqa: F401  (an SDK client of the `server` below)
from ..server.harness import TOKEN, ServerProcess

CHROMIUM = os.environ.get("CANONICAL_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def browser():
    # one per test file: Playwright's sync API keeps its event loop marked as running in this thread
    # while the browser lives, and a later test file's asyncio.run() in the same worker would fail
    playwright = pytest.importorskip("playwright.sync_api")
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"no chromium at {CHROMIUM} (apt-get install chromium)")
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer_server")
    proc = ServerProcess(root / "data", root / "server.log", token=TOKEN, snapshot_every_seconds=3600,
                         max_image_pixels=640 * 480)
    proc.start()
    yield proc
    proc.stop()


def token_page(browser, **context_args):
    """A page in a fresh browser context whose tab holds the token (as the token form leaves it),
    and the list its uncaught page errors go to."""
    context = browser.new_context(viewport={"width": 900, "height": 520}, **context_args)
    context.add_init_script(f"sessionStorage.setItem('canonical.token', {TOKEN!r})")
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    return page, errors


@pytest.fixture
def page(browser, server):
    """A page holding the token; an uncaught error in the page fails the test."""
    page, errors = token_page(browser)
    yield page
    page.context.close()
    assert not errors, errors


@pytest.fixture
def touch_page(browser, server):
    """The same on a touch screen."""
    page, errors = token_page(browser, has_touch=True)
    yield page
    page.context.close()
    assert not errors, errors


@pytest.fixture
def shots(tmp_path) -> Path:
    """Where a test saves its screenshots (the pytest tmp dir: kept as test artefacts)."""
    path = tmp_path / "screenshots"
    path.mkdir()
    return path
