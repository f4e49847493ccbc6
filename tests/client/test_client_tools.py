"""rce-topic / rce-service: on a local bus (served in the test, with the Test package's nodes as
real processes) and through a stand-in for the master's admin API."""
from __future__ import annotations

import asyncio
import os
import sys
import tempfile
import time
from pathlib import Path

import pytest
from aiohttp import web

from rce.tools.admin_client import AdminClient, find_token, refusal
from rce.bus.core import Bus
from rce.bus.server import BusServer
from rce.plumbing.errors import AuthError, MessageError, NotFound, RequestError, Throttled, Timeout, Unavailable
from rce.node.package_path import BUILTIN_DIR
from rce_client import tools

BIN = Path(sys.executable).parent


async def until(cond, timeout: float = 10.0, what: str = "condition") -> None:
    """Wait until ``cond()`` is true (checked every 20 ms), or fail after ``timeout`` s."""
    deadline = asyncio.get_running_loop().time() + timeout
    while not cond():
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.02)


@pytest.fixture
async def bus():
    """A local bus with the Test package's stringEcho and paramTest nodes connected."""
    d = tempfile.mkdtemp(prefix="rce-t-")
    path = os.path.join(d, "bus.sock")
    b = Bus("test")
    server = BusServer(b)
    await server.listen(path)
    b.set_param("int", 99)
    b.set_param("str", "foo")
    env = dict(os.environ, RCE_BUS=path)
    procs = [await asyncio.create_subprocess_exec(sys.executable, str(BUILTIN_DIR / "Test" / exe), env=env)
             for exe in ("stringEcho.py", "paramTest.py")]
    await until(lambda: {"/stringEchoService", "/parameterTest"} <= set(b.services), what="Test nodes")
    yield b, path
    for p in procs:
        p.terminate()
        await p.wait()
    await server.close()
    os.unlink(path)
    os.rmdir(d)


async def run(cmd: str, argv: list[str], capsys) -> tuple[str, str]:
    """Run one rce-topic/rce-service command in-process; returns (stdout, stderr)."""
    parser = tools.topic_parser() if cmd == "topic" else tools.service_parser()
    args = parser.parse_args(argv)
    backend = tools.pick_backend(args)
    await backend.open()
    try:
        code = await (tools.topic_cmd if cmd == "topic" else tools.service_cmd)(args, backend)
    finally:
        await backend.close()
    assert code == 0
    return capsys.readouterr()


def test_yaml_helpers():
    assert tools.parse_yaml("{data: hello}", "message") == {"data": "hello"}
    assert tools.parse_yaml("", "message") == {} and tools.parse_yaml("~", "message") == {}
    with pytest.raises(MessageError, match="must be a YAML mapping"):
        tools.parse_yaml("[1, 2]", "message")
    with pytest.raises(MessageError, match="not valid YAML"):
        tools.parse_yaml("{data: [", "message")
    assert tools.to_yaml({"data": "hello"}) == "data: hello"
    assert tools.to_yaml({"msg": "a:   1\nb:   2"}) == "msg: |-\n  a:   1\n  b:   2"
    assert tools.to_yaml({"p": {"x": 1.5, "v": [1, 2]}}) == "p:\n  x: 1.5\n  v:\n  - 1\n  - 2"


async def test_list_and_types(bus, capsys):
    _, path = bus
    out, _ = await run("topic", ["--bus", path, "list"], capsys)
    assert out.split() == ["/stringEchoReq", "/stringEchoResp"]
    out, _ = await run("topic", ["list", "-v", "--bus", path], capsys)      # options after the command
    assert "/stringEchoReq [std_msgs/String] 0 publisher(s), 1 subscriber(s)" in out
    out, _ = await run("topic", ["--bus", path, "type", "stringEchoResp"], capsys)
    assert out == "std_msgs/String\n"
    out, _ = await run("topic", ["--bus", path, "info", "/stringEchoResp"], capsys)
    assert "Type: std_msgs/String" in out and " * /stringEcho" in out
    out, _ = await run("service", ["--bus", path, "list"], capsys)
    assert out.split() == ["/parameterTest", "/stringEchoService"]
    out, _ = await run("service", ["--bus", path, "type", "parameterTest"], capsys)
    assert out == "Test/ParameterTest\n"


async def test_pub_echo_through_string_echo(bus, capsys):
    b, path = bus
    echo = asyncio.create_task(run("topic", ["--bus", path, "echo", "/stringEchoResp", "-n", "2"], capsys))
    await until(lambda: any(s.owner.startswith("/rce_tool") for s in b.topics["/stringEchoResp"].subscriptions),
                what="echo subscribed")
    pub_args = ["--bus", path, "pub", "/stringEchoReq"]
    # the commands share one capsys: whatever echo printed meanwhile shows up in the pubs' capture
    o1, e1 = await run("topic", pub_args + ["std_msgs/String", "{data: hello}"], capsys)
    o2, e2 = await run("topic", pub_args + ["{data: 'second one'}", "--once"], capsys)   # type from the bus
    o3, e3 = await asyncio.wait_for(echo, 10)
    assert o1 + o2 + o3 == "data: hello\n---\ndata: second one\n---\n"
    assert "subscribed to /stringEchoResp [std_msgs/String]" in e1 + e2 + e3
    assert "published 1 message on /stringEchoReq [std_msgs/String]" in e1 + e2 + e3


async def test_pub_at_a_rate_and_hz(bus, capsys):
    b, path = bus
    hz = asyncio.create_task(run("topic", ["--bus", path, "hz", "/stringEchoResp", "--reports", "2"], capsys))
    await until(lambda: any(s.owner.startswith("/rce_tool") for s in b.topics["/stringEchoResp"].subscriptions),
                what="hz subscribed")
    t0 = time.monotonic()
    pub = asyncio.create_task(run("topic", ["--bus", path, "pub", "/stringEchoReq", "{data: x}",
                                            "-r", "50", "-n", "150"], capsys))
    out, _ = await asyncio.wait_for(hz, 10)
    out += (await asyncio.wait_for(pub, 10))[0]
    # -r paces the publisher: 150 messages at 50 Hz cannot take less than 149 periods (a busy
    # machine only makes it slower). What hz measures is arrivals, which a busy machine bunches,
    # so its figure is checked for form, not for 50 Hz.
    assert time.monotonic() - t0 >= 149 / 50
    assert "average rate: " in out and "window:" in out
    assert float(out.split("average rate: ")[-1].split()[0]) > 0, out


async def test_service_calls(bus, capsys):
    _, path = bus
    out, _ = await run("service", ["--bus", path, "call", "stringEchoService", "{data: hello}"], capsys)
    assert out == "data: hello\n"
    out, _ = await run("service", ["--bus", path, "call", "/parameterTest", "{}", "--type", "Test/ParameterTest"],
                       capsys)
    assert out == "msg: |-\n  int:   99\n  str:   foo\n  float: <not set>\n  bool:  <not set>\n"


async def test_failures_name_what_was_wrong(bus, capsys):
    _, path = bus
    with pytest.raises(MessageError, match="std_msgs/String: field 'data' must be a string, got int"):
        await run("topic", ["--bus", path, "pub", "/stringEchoReq", "{data: 5}"], capsys)
    with pytest.raises(MessageError, match="unknown field 'nope'"):
        await run("service", ["--bus", path, "call", "stringEchoService", "{nope: 1}"], capsys)
    with pytest.raises(NotFound, match=r"service /nothing is not on the bus \(waited 0.5 s\); the bus has .*"
                                       r"/stringEchoService"):
        await run("service", ["--bus", path, "call", "nothing", "{}", "--timeout", "0.5"], capsys)
    assert "WARNING: service [/nothing] is not on the bus yet; waiting up to 0.5 s" in capsys.readouterr().err
    with pytest.raises(NotFound, match="topic /nothing is not on the bus"):
        await run("topic", ["--bus", path, "pub", "nothing", "{data: x}"], capsys)
    with pytest.raises(Unavailable, match="cannot reach the bus at /nonexistent.sock"):
        await run("topic", ["--bus", "/nonexistent.sock", "list"], capsys)


def test_cli_exit_codes_and_no_bus(monkeypatch, tmp_path, capsys):
    monkeypatch.delenv("RCE_BUS", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))       # no running buses there
    with pytest.raises(SystemExit) as ei:
        tools.topic_main(["list"])
    assert ei.value.code == 1
    assert "rce-topic: no bus: pass --bus PATH or set RCE_BUS" in capsys.readouterr().err
    with pytest.raises(SystemExit) as ei:
        tools.service_main(["frobnicate"])
    assert ei.value.code == 2
    with pytest.raises(SystemExit) as ei:
        tools.topic_main(["--container", "c", "list"])
    assert ei.value.code == 1 and "--container needs --master and --user" in capsys.readouterr().err


# -- the admin API path ------------------------------------------------------------------------------
@pytest.fixture
async def admin(monkeypatch, tmp_path):
    """A stand-in for the master's admin routes, recording what it was asked."""
    seen: list = []
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    monkeypatch.delenv("RCE_ADMIN_TOKEN", raising=False)
    desc = {"topics": [{"name": "/stringEchoResp", "type": "std_msgs/String", "publishers": ["/strEcho"],
                        "subscribers": []}],
            "services": [{"name": "/parameterTest", "type": "Test/ParameterTest", "provider": "/paramTest"}],
            "params": ["/int"], "nodes": []}

    def guard(request):
        if request.headers.get("Authorization") != "Bearer s3cret":
            raise web.HTTPUnauthorized(text="admin API: missing or wrong bearer token\n")
        if request.match_info["ctag"] != "cTag_01":
            raise web.HTTPNotFound(text=f"container {request.match_info['ctag']!r} does not exist\n")

    async def bus(request):
        guard(request)
        seen.append(("bus", request.match_info["user"]))
        return web.json_response(desc)

    async def post(request):
        guard(request)
        body = await request.json()
        op = request.path.rsplit("/", 1)[1]
        seen.append((op, body))
        if op == "publish":
            return web.json_response({"delivered": 1})
        if op == "call":
            return web.json_response({"msg": "int:   99\nstr:   foo"})
        return web.json_response([{"data": f"m{i}"} for i in range(body["count"])])

    app = web.Application()
    app.router.add_get("/api/containers/{user}/{ctag}/bus", bus)
    for op in ("publish", "call", "sample"):
        app.router.add_post("/api/containers/{user}/{ctag}/" + op, post)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    url = f"http://127.0.0.1:{site._server.sockets[0].getsockname()[1]}/"
    yield url, seen, tmp_path
    await runner.cleanup()


async def test_admin_api_path(admin, capsys, monkeypatch):
    url, seen, cfg_home = admin
    opts = ["--container", "cTag_01", "--master", url, "--user", "testUser"]
    with pytest.raises(AuthError, match="no admin token"):
        await run("topic", opts + ["list"], capsys)
    (cfg_home / "rce").mkdir()
    (cfg_home / "rce" / "admin-token").write_text("s3cret\n")               # the master's token file
    out, _ = await run("topic", opts + ["list"], capsys)
    assert out == "/stringEchoResp\n" and seen[-1] == ("bus", "testUser")
    await run("topic", opts + ["pub", "/stringEchoResp", "{data: hi}"], capsys)
    assert seen[-1] == ("publish", {"topic": "/stringEchoResp", "type": "std_msgs/String", "msg": {"data": "hi"}})
    out, _ = await run("topic", opts + ["echo", "stringEchoResp", "-n", "2"], capsys)
    assert out == "data: m0\n---\ndata: m1\n---\n"
    assert seen[-1] == ("sample", {"topic": "/stringEchoResp", "count": 2, "timeout": 5.0})
    out, _ = await run("service", opts + ["call", "parameterTest", "--timeout", "7"], capsys)
    assert out == "msg: |-\n  int:   99\n  str:   foo\n"
    assert seen[-1] == ("call", {"service": "/parameterTest", "request": {}, "timeout": 7.0})
    monkeypatch.setenv("RCE_ADMIN_TOKEN", "wrong")
    with pytest.raises(AuthError, match="missing or wrong bearer token"):
        await run("topic", opts + ["list"], capsys)
    with pytest.raises(NotFound, match="container 'other' does not exist"):
        await run("topic", ["--container", "other", "--master", url, "--user", "u", "--admin-token", "s3cret",
                            "list"], capsys)
    with pytest.raises(Unavailable, match="hz needs a live subscription"):
        await run("topic", opts + ["--admin-token", "s3cret", "hz", "/stringEchoResp"], capsys)


# -- the one admin-API client (rce.tools.admin_client) ----------------------------------------------------
def test_admin_token_is_found_in_order(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    monkeypatch.delenv("RCE_ADMIN_TOKEN", raising=False)
    with pytest.raises(AuthError, match=f"no admin token: .* write it to {tmp_path}/rce/admin-token"):
        find_token()
    (tmp_path / "rce").mkdir()
    (tmp_path / "rce" / "admin-token").write_text("from-file\n")      # what the master writes
    assert find_token() == "from-file"
    other = tmp_path / "other-token"
    other.write_text("other\n")
    assert find_token(path=other) == "other"                          # --admin-token-file
    monkeypatch.setenv("RCE_ADMIN_TOKEN", "from-env")
    assert find_token(path=other) == "from-env" and find_token("given") == "given"


@pytest.mark.parametrize("status, cls", [(400, RequestError), (401, AuthError), (403, AuthError), (404, NotFound),
                                         (409, RequestError), (429, Throttled), (500, Unavailable), (503, Unavailable),
                                         (504, Timeout)])
def test_admin_refusals_carry_the_masters_reason(status, cls):
    e = refusal("POST", "/api/users", status, b"\nuser 'x' already exists\nmore\n")
    assert type(e) is cls and e.status == status
    assert e.message == f"POST /api/users: HTTP {status}: user 'x' already exists"


async def test_admin_client_blocking_and_asyncio(admin):
    url, seen, _ = admin
    client = AdminClient(url, "s3cret")
    bus = await asyncio.to_thread(client.request, "GET", "/api/containers/u/cTag_01/bus")
    assert bus["topics"][0]["name"] == "/stringEchoResp" and seen[-1] == ("bus", "u")
    assert await client.arequest("POST", "api/containers/u/cTag_01/publish", {"topic": "/t", "msg": {}}) == \
        {"delivered": 1}
    for call in (lambda: asyncio.to_thread(client.request, "GET", "/api/containers/u/nope/bus"),
                 lambda: client.arequest("GET", "/api/containers/u/nope/bus")):
        with pytest.raises(NotFound, match="GET /api/containers/u/nope/bus: HTTP 404: container 'nope' does not exist"):
            await call()
    wrong = AdminClient(url, "wrong")
    with pytest.raises(AuthError, match="HTTP 401: admin API: missing or wrong bearer token"):
        await wrong.arequest("GET", "/api/containers/u/cTag_01/bus")
    await wrong.aclose()
    await client.aclose()
    gone = AdminClient("http://127.0.0.1:9/", "t")
    with pytest.raises(Unavailable, match="cannot reach the master at http://127.0.0.1:9/"):
        await asyncio.to_thread(gone.request, "GET", "/api/state")
    with pytest.raises(Unavailable, match="cannot reach the master at http://127.0.0.1:9/"):
        await gone.arequest("GET", "/api/state")
    await gone.aclose()
