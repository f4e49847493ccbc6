"""rce.js, the browser RCE client library, against the plain engine (real processes on loopback):
the page is served by rce-master itself (``--static /ui=WEB``, same origin), logs in, creates a
container with the Test package's stringEcho.py and gets echoes back through converters (topic and
service) and forwarders (binary parts); a bad request comes back as the ER; a wrong password is
shown as an error; the SHA-256 fallback for non-secure contexts matches crypto.subtle."""
from __future__ import annotations

import pytest

from conftest import WEB_DIR
from rce.launch import start_engine


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


def test_binary_parts_and_nan_tolerant_json(ui_engine, page):
    """The Assembler takes a message's binary parts before or after its JSON frame (nested keys
    and lists of ids too), and the JSON reader takes Python's NaN/Infinity (as null)."""
    page.goto(ui_engine.master_url + "ui/echo.html")
    out = page.evaluate("""async () => {
        const m = await import('./rce.js');
        const enc = (s) => new TextEncoder().encode(s);
        const a = new m.Assembler(60);
        const id1 = 'a'.repeat(32), id2 = 'b'.repeat(32), id3 = 'c'.repeat(32);
        const frame = (id, s) => { const b = new Uint8Array(32 + s.length); b.set(enc(id)); b.set(enc(s), 32); return b.buffer; };
        const early = a.addPart(frame(id1, 'one'));                      // part before its message
        const none = a.addMessage({type: 'DM', data: {iTag: 't', msg: {'x*': id1, inner: {'y*': [id2, id3]}}}});
        const mid = a.addPart(frame(id2, 'two'));
        const done = a.addPart(frame(id3, 'three'));                     // completes the message
        const d = new TextDecoder();
        const msg = done[0].data.msg;
        const [text, frames] = m.encodeMessage({type: 'DM', data: {msg: new Uint8Array([1, 2, 3]), list: [new Uint8Array([4])]}});
        const sent = JSON.parse(text);
        const parsed = m.parseJSON('{"x": NaN, "y": -Infinity, "s": "NaN \\\\" Infinity", "z": [Infinity, 1.5]}');
        return {early: early.length, none, mid: mid.length, x: d.decode(msg.x), y: msg.inner.y.map(v => d.decode(v)),
                left: a.parts.size + a.waiting.length, sentKeys: Object.keys(sent.data).sort(), nframes: frames.length,
                frameLen: frames[0].length, parsed};
    }""")
    assert out["early"] == 0 and out["none"] is None and out["mid"] == 0
    assert out["x"] == "one" and out["y"] == ["two", "three"] and out["left"] == 0
    assert out["sentKeys"] == ["list*", "msg*"] and out["nframes"] == 2 and out["frameLen"] == 35
    assert out["parsed"] == {"x": None, "y": None, "s": 'NaN " Infinity', "z": [None, 1.5]}
