"""rce.js, the browser RCE client library, against the plain engine (real processes on loopback):
the page is served by rce-master itself (``--static /ui=WEB``, same origin), logs in, creates a
container with the Test package's stringEcho.py and gets echoes back through converters (topic and
service) and forwarders (binary parts); a bad request comes back as the ER; a wrong password is
shown as an error; with ``reconnect`` the page's Client resumes a link a TCP proxy cut, with its session
token. Without an engine (the web directory on a local server): the SHA-256 fallback for non-secure
contexts matches crypto.subtle, and the session's binary parts with random ids."""
from __future__ import annotations

import pytest

from web_paths import ENGINE_WEB
from rce.tools.launch import start_engine


@pytest.fixture(scope="module")
def ui_engine(tmp_path_factory):
    e = start_engine(tmp_path_factory.mktemp("engine"), master_args=("--static", f"/ui={ENGINE_WEB}"))
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


def test_unknown_user_is_refused_as_a_wrong_password(ui_engine, page, tmp_path):
    # no user enumeration (docs/SECURITY.md): the page cannot tell an unknown user from a wrong password
    _login(page, ui_engine.master_url + "ui/echo.html", "nobody", "x")
    page.wait_for_function("window.echoTest.error", timeout=20_000)
    page.screenshot(path=str(tmp_path / "unknown-user.png"))
    assert "refused" in page.text_content("#error")
    assert page.evaluate("window.echoTest.steps") == []


def test_sha256_fallback_matches_subtle(web_root, page):
    page.goto(web_root)
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


def test_session_binary_parts_with_random_ids(web_root, page):
    """The session takes a message's binary parts before or after its JSON frame (nested keys and
    lists of ids too) and hands them over as Uint8Array; outgoing bytes become parts under fresh
    random ids (the shared vectors fix the ids; this checks the default id source)."""
    page.goto(web_root)
    out = page.evaluate("""async () => {
        const m = await import('./rce.js');
        const enc = (s) => new TextEncoder().encode(s);
        const s = new m.ClientSession();
        const id1 = 'a'.repeat(32), id2 = 'b'.repeat(32), id3 = 'c'.repeat(32);
        const frame = (id, t) => {
            const b = new Uint8Array(32 + t.length); b.set(enc(id)); b.set(enc(t), 32); return b.buffer; };
        const early = s.receiveBinary(frame(id1, 'one'));                      // part before its message
        const dm = {type: 'DM', data: {iTag: 't', msg: {'x*': id1, inner: {'y*': [id2, id3]}}}};
        const none = s.receiveText(JSON.stringify(dm));
        const mid = s.receiveBinary(frame(id2, 'two'));
        const done = s.receiveBinary(frame(id3, 'three'));                     // completes the message
        const d = new TextDecoder();
        const msg = done[0].msg;
        const sent = s.send('DM', {msg: new Uint8Array([1, 2, 3]), list: [new Uint8Array([4])]});
        const text = JSON.parse(sent[0].frame.text);
        const ids = [text.data['msg*'], text.data['list*'][0]];
        return {early: early.length, none: none.length, mid: mid.length, event: done[0].event, x: d.decode(msg.x),
                y: msg.inner.y.map(v => d.decode(v)), left: s.assembler.parts.size + s.assembler.waiting.length,
                sentKeys: Object.keys(text.data).sort(), nframes: sent.length, frameLen: sent[1].frame.binary.length,
                ids, framedIds: sent.slice(1).map(o => d.decode(o.frame.binary.subarray(0, 32)))};
    }""")
    assert out["early"] == 0 and out["none"] == 0 and out["mid"] == 0 and out["event"] == "message"
    assert out["x"] == "one" and out["y"] == ["two", "three"] and out["left"] == 0
    assert out["sentKeys"] == ["list*", "msg*"] and out["nframes"] == 3 and out["frameLen"] == 35
    assert out["ids"] == out["framedIds"] and len(set(out["ids"])) == 2
    assert all(len(i) == 32 and int(i, 16) >= 0 for i in out["ids"])


class ThreadedProxy:
    """rce.transport.tcpproxy's TcpProxy on an event loop of its own thread (the browser tests are synchronous)."""

    def __init__(self, target: int):
        import asyncio
        import threading

        from rce.transport.tcpproxy import TcpProxy
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="proxy", daemon=True)
        self.thread.start()
        self.proxy = self.run(TcpProxy(target).start())

    def run(self, coro):
        import asyncio
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def call(self, fn) -> None:
        self.loop.call_soon_threadsafe(fn)

    def stop(self) -> None:
        self.run(self.proxy.close())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


SETUP_RESUME_JS = """async ({url, rid}) => {
    const m = await import('./rce.js');
    const c = new m.Client({userID: 'testUser', robotID: rid, password: 'testUser', endpoint: url, reconnect: true,
                            maxLag: 0});
    const t = window.resumeTest = {got: [], events: [], c};
    c.on('disconnected', () => t.events.push('disconnected'));
    c.on('reconnected', () => t.events.push('reconnected'));
    c.on('resumed', (st) => t.events.push(`resumed ${st.dropped}`));
    await c.connect();
    const I = (e, i, type, cls, addr) => ({endpointTag: e, interfaceTag: i, interfaceType: type, className: cls,
                                           ...(addr ? {addr} : {})});
    await c.createContainer('webResumeC');
    await c.configure({addNodes: [{containerTag: 'webResumeC', nodeTag: 'echo', pkg: 'Test', exe: 'stringEcho.py'}]});
    const S = 'std_msgs/String';
    await c.configure({addInterfaces: [I('webResumeC', 'req', 'PublisherInterface', S, '/stringEchoReq'),
        I('webResumeC', 'resp', 'SubscriberInterface', S, '/stringEchoResp'),
        I(rid, 'req', 'SubscriberConverter', S), I(rid, 'resp', 'PublisherConverter', S)]});
    c.subscribe('resp', (msg) => t.got.push(msg.data));
    await c.connectInterfaces([['webResumeC/req', `${rid}/req`], ['webResumeC/resp', `${rid}/resp`]]);
    await c.waitUp(['req', 'resp']);
    for (let i = 0; i < 100 && !t.got.length; i++) {      // the node subscribes a moment after the interfaces are up
        c.publish('req', 'std_msgs/String', {data: 'warm'});
        await new Promise((r) => setTimeout(r, 200));
    }
    return t.got.length > 0;
}"""


def test_the_page_resumes_a_lost_link_with_its_token(ui_engine, web_root, page, tmp_path):
    """The page's Client (reconnect) rides out a 3 s cut of its link (a TCP proxy): what it sent meanwhile
    and what the cloud sent meanwhile arrive once each; the resume carries the session token, not the password."""
    import time
    px = ThreadedProxy(ui_engine.robot_ready[0]["ws_port"])
    try:
        page.goto(web_root)
        assert page.evaluate(SETUP_RESUME_JS, {"url": px.proxy.url, "rid": "webResumeBot"})
        page.evaluate("() => { window.resumeTest.got.length = 0; }")
        px.call(px.proxy.cut)
        page.wait_for_function("window.resumeTest.events.includes('disconnected')", timeout=10_000)
        page.evaluate("""() => { for (let i = 0; i < 5; i++)
                                   window.resumeTest.c.publish('req', 'std_msgs/String', {data: `page${i}`}); }""")
        for i in range(3):          # the cloud's own messages during the gap: into the container, echoed to the page
            ui_engine.admin("/api/containers/testUser/webResumeC/publish",
                            {"topic": "/stringEchoReq", "type": "std_msgs/String", "msg": {"data": f"cloud{i}"}})
        time.sleep(3.0)             # the cut's duration
        px.call(px.proxy.restore)
        page.wait_for_function("window.resumeTest.got.length >= 8", timeout=15_000)
        st = page.evaluate("({got: window.resumeTest.got, events: window.resumeTest.events})")
        page.screenshot(path=str(tmp_path / "resumed.png"))
        assert sorted(st["got"]) == sorted([f"page{i}" for i in range(5)] + [f"cloud{i}" for i in range(3)])
        assert [g for g in st["got"] if g.startswith("page")] == [f"page{i}" for i in range(5)]
        assert st["events"] == ["disconnected", "reconnected", "resumed 0"]
        resume = px.proxy.requests[-1].decode()
        assert "session=" in resume and "password" not in resume and "resume=1" not in resume
        assert "password=" in px.proxy.requests[0].decode() and "resume=1" in px.proxy.requests[0].decode()
        assert "maxLag=0" in px.proxy.requests[0].decode() and "maxLag=0" in resume     # kept across the resume
        bad = page.evaluate("""async () => { const m = await import('./rce.js');
            try { new m.Client({userID: 'u', robotID: 'r', password: 'p', maxLag: -1}); return null; }
            catch (e) { return e.message; } }""")
        assert bad and "maxLag must be null or a number of seconds >= 0" in bad
        assert page.evaluate("window.resumeTest.c._password") is None
    finally:
        page.evaluate("() => window.resumeTest && window.resumeTest.c.close()")
        px.stop()
