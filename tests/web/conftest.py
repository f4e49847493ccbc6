"""Browser fixtures for the web page tests: Debian's chromium driven by Playwright (sync API).

Never ``playwright install``: the browser is the system's ``/usr/bin/chromium``."""
from __future__ import annotations

import functools
import os
import shutil
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from web_paths import ENGINE_WEB
CHROMIUM = os.environ.get("RCE_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-quic",
                 "--no-first-run", "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def browser():
    """Chromium for one test module. Not per session: Playwright's sync API runs an event loop in
    the thread while it is open, and a parallel worker runs other modules' asyncio tests after."""
    if not shutil.which(CHROMIUM) and not Path(CHROMIUM).exists():
        pytest.fail(f"no chromium at {CHROMIUM}: `make setup` installs Debian's chromium when run as root "
                    "(apt-get install chromium)")
    from playwright import sync_api
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()


class _QuietHandler(SimpleHTTPRequestHandler):
    def log_message(self, format, *args):     # no request lines in the test output
        pass


@pytest.fixture(scope="session")
def web_root():
    """The engine's web directory (rce.js, echo.html) served over HTTP on 127.0.0.1 (a free port; a secure
    context, so ``crypto.subtle`` exists), for tests of rce.js that need no engine; yields its URL, ending in /."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_QuietHandler, directory=str(ENGINE_WEB)))
    thread = threading.Thread(target=server.serve_forever, name="web-root", daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/"
    server.shutdown()
    server.server_close()
    thread.join()


@pytest.fixture
def page(browser, tmp_path):
    """A fresh page (own context); console messages and page errors are kept in ``page.rce_log``
    and shown when a test fails; a screenshot is left in the test's tmp dir either way."""
    ctx = browser.new_context(viewport={"width": 1400, "height": 900})
    pg = ctx.new_page()
    pg.rce_log = []
    pg.on("console", lambda m: pg.rce_log.append(f"console.{m.type}: {m.text}"))
    pg.on("pageerror", lambda e: pg.rce_log.append(f"pageerror: {e}"))
    yield pg
    try:
        pg.screenshot(path=str(tmp_path / "final.png"))
    except Exception:
        pass
    ctx.close()


def pytest_runtest_makereport(item, call):
    if call.when == "call" and call.excinfo is not None:
        pg = getattr(item, "funcargs", {}).get("page")
        if pg is not None and getattr(pg, "rce_log", None):
            item.add_report_section("call", "browser console", "\n".join(pg.rce_log[-200:]))
