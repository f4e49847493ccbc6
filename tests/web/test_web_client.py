"""rce.js, the browser RCE client library, against the plain engine (real processes on loopback):
the page is served by rce-master itself (``--static /ui=WEB``, same origin), logs in, creates a
container with the Test package's stringEcho.py and gets echoes back through converters (topic and
service) and forwarders (binary parts); a bad request comes back as the ER; a wrong password is
shown as an error; the SHA-256 fallback for non-secure contexts matches crypto.subtle."""
from __future__ import annotations

import pytest

from conftest import WEB_DIR
from engine import start_engine


@pytest.fixture(scope="module")
def ui_engine(tmp_path_factory):
    e = start_engine(tmp_path_factory.mktemp("engine"), master_args=("--static", f"/ui={WEB_DIR}"))
    yield e
    e.stop()


def _login(page, url, user, password):
    page.goto(url)
    page.fill("#user", user)
    page.fill("#password", password)
    page.click("#run")


def test_echo_through_converters_and_forwarders(ui_engine, page, tmp_path):
    _login(page, ui_engine.master_url + "ui/echo.html", "testUser", "testUser")
    page.wait_for_function("window.echoTest.done || window.echoTest.error", timeout=60_000)
    st = page.evaluate("window.echoTest")
    page.screenshot(path=str(tmp_path / "echo.png"))
    assert st["error"] is None, st
    assert st["results"]["topic"] == "hello from the browser"
    assert st["results"]["service"] == "service from the browser"
    assert st["results"]["forwarder"] == 100_004             # serialized std_msgs/String: 4 + 100000 bytes
    assert "no_such/Type" in st["results"]["refused"]        # the ER the cloud returned
    assert page.input_value("#password") == ""               # the page does not keep the password around


def test_wrong_password_is_an_error(ui_engine, page, tmp_path):
    _login(page, ui_engine.master_url + "ui/echo.html", "testUser", "not-the-password")
    page.wait_for_function("window.echoTest.error", timeout=20_000)
    page.screenshot(path=str(tmp_path / "wrong-password.png"))
    assert "refused" in page.text_content("#error")
    assert page.evaluate("window.echoTest.steps") == []


def test_unknown_user_shows_the_masters_reason(ui_engine, page, tmp_path):
    _login(page, ui_engine.master_url + "ui/echo.html", "nobody", "x")
    page.wait_for_function("window.echoTest.error", timeout=20_000)
    page.screenshot(path=str(tmp_path / "unknown-user.png"))
    assert "HTTP 401" in page.text_content("#error") and "nobody" in page.text_content("#error")


def test_sha256_fallback_matches_subtle(ui_engine, page):
    page.goto(ui_engine.master_url + "ui/echo.html")
    ok = page.evaluate("""async () => {
        const m = await import('./rce.js');
        const hex = (b) => Array.from(b, x => x.toString(16).padStart(2, '0')).join('');
        const out = [];
        for (const s of ['', 'testUser', 'a'.repeat(55), 'a'.repeat(56), 'a'.repeat(64), 'päss wörd ✓'.repeat(20)]) {
            const d = new Uint8Array(await crypto.subtle.digest('SHA-256', new TextEncoder().encode(s)));
            out.push(hex(d) === hex(m.sha256Fallback(new TextEncoder().encode(s))));
        }
        return out;
    }""")
    assert all(ok), ok
