"""Login (``GET master?userID=U&version=V``) against a tiny aiohttp master, then the websocket."""
from __future__ import annotations

import logging

import pytest
from aiohttp import web

from rce.plumbing.errors import AuthError, Unavailable
from rce_client.connection import CLIENT_VERSION, Connection, login

from .fakecloud import FakeEndpoint, login_server, ws_url_answer

pytestmark = pytest.mark.asyncio


@pytest.fixture
async def master():
    """A login server whose answer the test sets: ``state["answer"] = callable(request)``."""
    state: dict = {"requests": []}

    async def handler(request: web.Request) -> web.Response:
        state["requests"].append(dict(request.query))
        return state["answer"](request)
    runner, url = await login_server(handler)
    state["url"] = url
    yield state
    await runner.cleanup()


async def test_login_returns_ws_url_and_sends_user_and_version(master):
    master["answer"] = lambda r: ws_url_answer("ws://127.0.0.1:9010/")
    assert await login(master["url"], "testUser") == "ws://127.0.0.1:9010/"
    assert master["requests"] == [{"userID": "testUser", "version": CLIENT_VERSION}]


async def test_login_outdated_client_is_a_warning(master, caplog):
    master["answer"] = lambda r: ws_url_answer("ws://127.0.0.1:9010/", current="20140101")
    with caplog.at_level(logging.WARNING, logger="rce.client"):
        assert await login(master["url"], "testUser") == "ws://127.0.0.1:9010/"
    assert any("outdated" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("status, exc", [(401, AuthError), (403, AuthError), (400, Unavailable),
                                         (503, Unavailable)])
async def test_login_http_errors_carry_the_reason(master, status, exc):
    master["answer"] = lambda r: web.Response(status=status, text="no such user 'testUser'\n")
    with pytest.raises(exc) as ei:
        await login(master["url"], "testUser")
    assert "no such user 'testUser'" in ei.value.message
    assert master["url"] in ei.value.message


async def test_login_json_error_body(master):
    master["answer"] = lambda r: web.json_response({"error": {"code": "auth", "message": "bad credentials"}},
                                                   status=401)
    with pytest.raises(AuthError, match="bad credentials"):
        await login(master["url"], "testUser")


async def test_login_answer_without_url(master):
    master["answer"] = lambda r: web.json_response({"nope": 1})
    with pytest.raises(Unavailable, match="no websocket 'url'"):
        await login(master["url"], "testUser")


async def test_login_unreachable_master():
    with pytest.raises(Unavailable, match="cannot reach the master at http://127.0.0.1:9/") as e:
        await login("http://127.0.0.1:9/", "testUser", timeout=5)
    assert str(e.value) == "cannot reach the master at http://127.0.0.1:9/: Connection refused"


async def test_connect_logs_in_then_opens_the_websocket(master):
    ep = await FakeEndpoint().start()
    master["answer"] = lambda r: ws_url_answer(ep.url)
    try:
        conn = await Connection.connect(master["url"], "testUser", "testUser", "testRobot")
        assert conn.ws_url == ep.url and conn.robot_id == "testRobot"
        assert ep.query["robotID"] == "testRobot"
        await conn.close()
        assert conn.closed
    finally:
        await ep.stop()


async def test_connect_bad_password_is_auth_error_from_the_handshake(master):
    ep = await FakeEndpoint(refuse=(401, "invalid user ID or password for user 'testUser'")).start()
    master["answer"] = lambda r: ws_url_answer(ep.url)
    try:
        with pytest.raises(AuthError, match="invalid user ID or password"):
            await Connection.connect(master["url"], "testUser", "wrong", "testRobot")
    finally:
        await ep.stop()


async def test_connect_bad_user_is_auth_error_from_the_login(master):
    master["answer"] = lambda r: web.Response(status=401, text=f"unknown user {r.query['userID']!r}\n")
    with pytest.raises(AuthError, match="unknown user 'mallory'"):
        await Connection.connect(master["url"], "mallory", "x", "testRobot")
