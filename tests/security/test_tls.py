"""TLS at the front door (docs/SECURITY.md): an engine started with ``--tls-cert``/
``--tls-key`` (a CA and a 127.0.0.1 certificate made at test time, :func:`rce.transport.tls.make_dev_certificates`)
serves login, /metrics and the web page over https and robots and rosbridge clients over wss; login
hands out wss:// URLs; rce_client echoes through a container over wss with the CA file; a plain-text
client cannot talk to the TLS ports; a client that trusts another CA fails with a clear error, and a CA
file pins the cloud's CA (the system's CAs are not trusted beside it); the
operator's web page works over https/wss in Chromium (which trusts only the test certificate)."""
from __future__ import annotations

import hashlib
import json
import os
import socket
import ssl
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from rce.transport import tls
from rce.plumbing.errors import ConfigError, Unavailable
from rce.tools.launch import start_engine
from rce_robot.ws_link import IMPLS as WS_IMPLS
from rce_client.connection import Connection, login

WEB_DIR = Path(__file__).resolve().parents[2] / "rce" / "web"      # echo.html and rce.js: the engine's
CHROMIUM = os.environ.get("RCE_CHROMIUM", "/usr/bin/chromium")
ECHO_TIMEOUT = 30.0          # s for a container, its echo node and the interfaces to come up on a busy machine
PAGE_TIMEOUT_MS = 60_000     # ms the web page's echo test may take (as tests/web/test_web_client.py)


@pytest.fixture(scope="module", params=WS_IMPLS)
def tls_engine(request, tmp_path_factory):
    """The engine over TLS, its rce-robot on each websocket library (``--ws-impl``) in turn."""
    e = start_engine(tmp_path_factory.mktemp("engine"), tls=True, master_args=("--static", f"/ui={WEB_DIR}"),
                     robot_args=("--ws-impl", request.param))
    yield e
    e.stop()


@pytest.fixture(scope="module")
def other_ca(tmp_path_factory) -> Path:
    """A CA that did not sign the engine's certificate."""
    return tls.make_dev_certificates(tmp_path_factory.mktemp("other-ca"), name="not the engine's").ca


def _get(url: str, ca: Path | None) -> tuple[int, bytes]:
    ctx = tls.client_context(ca) if url.startswith("https") else None
    with urllib.request.urlopen(url, timeout=10, context=ctx) as r:
        return r.status, r.read()


def test_login_over_https_hands_out_wss_urls(tls_engine):
    assert tls_engine.master_url.startswith("https://127.0.0.1:")
    status, body = _get(tls_engine.master_url + "?userID=testUser&version=20130902", tls_engine.ca_file)
    url = json.loads(body)["url"]
    assert status == 200 and url == f"wss://127.0.0.1:{tls_engine.robot_ready[0]['ws_port']}/"
    status, metrics = _get(tls_engine.master_url + "metrics", tls_engine.ca_file)
    assert status == 200 and b"rce_master_auth" in metrics
    assert tls_engine.admin("/api/robots") == []               # the admin API (rce.tools.admin_client) over https


async def test_rce_client_echo_over_wss_with_the_ca_file(tls_engine, monkeypatch):
    ctx = tls.client_context(tls_engine.ca_file)
    conn = await Connection.connect(tls_engine.master_url, "testUser", "testUser", "tlsBot", ssl_context=ctx)
    try:
        assert conn.ws_url.startswith("wss://")
        await conn.create_container("tlsC")
        await conn.add_node("tlsC", "strEcho", "Test", "stringEcho.py")
        await conn.add_interface("tlsC", "stringEchoService", "ServiceClientInterface", "Test/StringEcho",
                                 "/stringEchoService")
        await conn.add_interface("tlsBot", "stringEchoService", "ServiceProviderConverter", "Test/StringEcho")
        await conn.connect("tlsC/stringEchoService", "tlsBot/stringEchoService")
        await conn.wait_interfaces_up(["stringEchoService"], timeout=ECHO_TIMEOUT)
        answer = await conn.service("stringEchoService", "Test/StringEcho").call({"data": "over wss"})
        assert answer == {"data": "over wss"}
    finally:
        await conn.close()
    monkeypatch.setenv(tls.CA_FILE_ENV, str(tls_engine.ca_file))      # RCE_CA_FILE instead of ssl_context
    assert (await login(tls_engine.master_url, "testUser")).startswith("wss://")


async def test_a_plain_text_client_cannot_talk_to_the_tls_ports(tls_engine):
    ws_port, rb_port = tls_engine.robot_ready[0]["ws_port"], tls_engine.robot_ready[0]["rosbridge_port"]
    password = hashlib.sha256(b"testUser").hexdigest()
    with pytest.raises(Unavailable):                       # http:// login at the https:// master
        await login(tls_engine.master_url.replace("https:", "http:"), "testUser")
    for port in (ws_port, rb_port):
        with pytest.raises(Unavailable):                   # ws:// at the wss:// endpoint and rosbridge
            await Connection.open(f"ws://127.0.0.1:{port}/", "testUser", "testUser", "plainBot", timeout=5)
    for port in (tls_engine.http_port, ws_port):           # raw plain HTTP gets no HTTP answer
        with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
            s.sendall(f"GET /?userID=testUser&robotID=plainBot&password={password} HTTP/1.1\r\n"
                      f"Host: 127.0.0.1\r\n\r\n".encode())
            assert not _read_all(s).startswith(b"HTTP/")
    assert tls_engine.alive() == []                        # nothing broke


def _read_all(s: socket.socket) -> bytes:
    out = b""
    try:
        while chunk := s.recv(4096):
            out += chunk
    except (ConnectionResetError, TimeoutError):
        pass
    return out


async def test_a_client_trusting_another_ca_fails_clearly(tls_engine, other_ca):
    ctx = tls.client_context(other_ca)
    with pytest.raises(Unavailable, match=r"certificate of https://127\.0\.0\.1:\d+/ is not trusted.*--ca-file"):
        await login(tls_engine.master_url, "testUser", ssl_context=ctx)
    ws_url = f"wss://127.0.0.1:{tls_engine.robot_ready[0]['ws_port']}/"
    with pytest.raises(Unavailable, match=r"certificate of wss://127\.0\.0\.1:\d+/ is not trusted.*RCE_CA_FILE"):
        await Connection.open(ws_url, "testUser", "testUser", "caBot", ssl_context=ctx)
    with pytest.raises(urllib.error.URLError, match="CERTIFICATE_VERIFY_FAILED"):
        _get(tls_engine.master_url, None)                  # the system's CAs do not know the test CA either


async def test_a_ca_file_pins_the_clouds_ca_and_the_systems_cas_are_not_trusted_beside_it(tls_engine, other_ca,
                                                                                          monkeypatch):
    """The engine's CA made one of the system's CAs (OpenSSL's ``SSL_CERT_FILE``): a client without a CA
    file then trusts the engine, and one given another CA's file does not."""
    monkeypatch.setenv("SSL_CERT_FILE", str(tls_engine.ca_file))
    monkeypatch.delenv("SSL_CERT_DIR", raising=False)
    monkeypatch.delenv(tls.CA_FILE_ENV, raising=False)
    status, _ = _get(tls_engine.master_url + "metrics", None)     # the system's CAs: the engine's among them
    assert status == 200
    with pytest.raises(Unavailable, match=r"certificate of https://127\.0\.0\.1:\d+/ is not trusted"):
        await login(tls_engine.master_url, "testUser", ssl_context=tls.client_context(other_ca))
    with pytest.raises(urllib.error.URLError, match="CERTIFICATE_VERIFY_FAILED"):
        _get(tls_engine.master_url, other_ca)
    monkeypatch.setenv(tls.CA_FILE_ENV, str(other_ca))           # the same pin from the environment
    with pytest.raises(urllib.error.URLError, match="CERTIFICATE_VERIFY_FAILED"):
        _get(tls_engine.master_url, None)


async def test_rosbridge_serves_wss(tls_engine):
    port = tls_engine.robot_ready[0]["rosbridge_port"]
    q = f"userID=testUser&robotID=rbBot&password={'0' * 64}&container=none"
    with pytest.raises(InvalidStatus) as ei:               # the TLS handshake and HTTP work: the password is checked
        await connect(f"wss://127.0.0.1:{port}/?{q}", ssl=tls.client_context(tls_engine.ca_file), open_timeout=10)
    assert ei.value.response.status_code == 401


def test_the_web_page_over_https_and_wss(tls_engine, tmp_path):
    from playwright.sync_api import sync_playwright
    pin = tls.spki_sha256(tls_engine.ca_file.with_name("server.pem").read_bytes())
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True,
                                    args=["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                                          f"--ignore-certificate-errors-spki-list={pin}"])
        try:
            page = browser.new_page()
            log: list[str] = []
            page.on("console", lambda m: log.append(m.text))
            page.goto(tls_engine.master_url + "ui/echo.html")
            page.fill("#user", "testUser")
            page.fill("#password", "testUser")
            page.click("#run")
            page.wait_for_function("window.echoTest.done || window.echoTest.error", timeout=PAGE_TIMEOUT_MS)
            st = page.evaluate("window.echoTest")
            page.screenshot(path=str(tmp_path / "echo-tls.png"))
        finally:
            browser.close()
    assert st["error"] is None, (st, log[-20:])
    assert st["results"]["topic"] == "hello from the browser"
    assert st["results"]["service"] == "service from the browser"


def test_tls_options_are_checked(tmp_path):
    with pytest.raises(ConfigError, match="--tls-cert .*no such file"):
        tls.server_context(tmp_path / "missing.pem", tmp_path / "missing.key")
    (tmp_path / "bad.pem").write_text("not a certificate")
    with pytest.raises(ConfigError, match="--ca-file .*bad.pem: cannot load"):
        tls.client_context(tmp_path / "bad.pem")
    assert tls.client_context().verify_mode == ssl.CERT_REQUIRED       # no CA file: the system's CAs, verified
