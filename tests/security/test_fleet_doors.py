"""The doors of ``rce-fleet serve`` from the network: serve runs in a network namespace this test makes
(:class:`rce.tools.netlab.NetLab`), its page, task API and Foxglove port on ``--web-bind`` the namespace's
veth address (not loopback) over TLS with a throw-away CA; the clients (urllib, a Python Foxglove client
on ``websockets`` speaking ``foxglove.websocket.v1``, a raw RCE client on the page's ``/rce/ws``) connect
from the root namespace across the veth link.

The users file holds ``testUser`` with a password of its own (an operator), a viewer, and no admin but
the first admin of ``--admin-password-file``.
"""
from __future__ import annotations

import asyncio
import hashlib
import json
import os
import re
import signal
import ssl
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import orjson
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from rce.tools.netlab import NetLab

BIN = Path(sys.executable).parent
START_TIMEOUT_S = 120     # wall s for serve to bring up the engine, the fleet, the page and Foxglove
STOP_TIMEOUT_S = 30
STEP_TIMEOUT_S = 15.0     # one answer
ADMIN_PW = "first-admin-pw-1"
USERS = {"testUser": ("operator", "not-the-dev-pw-7"), "vera": ("viewer", "vera-pw-12")}
SUB = "foxglove.websocket.v1"
PLACES = "places:\n  - {name: pick1, kind: pickup, cell: 16}\n  - {name: drop1, kind: dropoff, cell: 23}\n"


def _users(path: Path) -> Path:
    from rce_master.auth.users import UsersFile
    from rce_master.state.master_state import MasterState
    st = MasterState()
    for name, (role, pw) in USERS.items():
        st.add_user(name, pw, role)
    UsersFile(path).save(st)
    return path


def _serve_argv(d: Path, bind: str, *extra: str) -> list[str]:
    (d / "places.yaml").write_text(PLACES)
    return [str(BIN / "rce-fleet"), "serve", "--robots", "1", "--speedup", "10", "--grid", "8x8", "--web-port", "0",
            "--no-live", "--workdir", str(d / "work"), "--timeout", "600", "--places", str(d / "places.yaml"),
            "--start", "Robot1=33", "--web-bind", bind, *extra]


@pytest.fixture(scope="module")
def lab():
    assert os.geteuid() == 0, "the doors' tests make a network namespace: run them as root (make test does, as CI)"
    with NetLab("fdr") as lab:
        lab.namespace("srv")
        yield lab, lab.link(None, "srv", 1)


@pytest.fixture(scope="module")
def serve(lab, tmp_path_factory):
    from rce.transport.tls import make_dev_certificates
    netlab, link = lab
    d = tmp_path_factory.mktemp("doors")
    certs = make_dev_certificates(d / "tls", (link.b_ip,))
    (d / "admin-pw").write_text(ADMIN_PW + "\n")
    argv = _serve_argv(d, link.b_ip, "--tls-cert", str(certs.cert), "--tls-key", str(certs.key), "--users",
                       str(_users(d / "users.json")), "--admin-password-file", str(d / "admin-pw"),
                       "--foxglove-port", "0")
    log = d / "serve.log"
    p = subprocess.Popen(netlab.wrap("srv", argv), stdout=open(log, "wb"), stderr=subprocess.STDOUT,
                         start_new_session=True)
    deadline = time.monotonic() + START_TIMEOUT_S
    page = fox = None
    while time.monotonic() < deadline and p.poll() is None:
        text = log.read_text(errors="replace")
        page = re.search(r"operator page: (https://\S+?)/", text)
        fox = re.search(r"Foxglove WebSocket: (wss://\S+?)/", text)
        if page and fox:
            break
        time.sleep(0.1)
    if not (page and fox):
        p.kill()
        pytest.fail(f"serve did not come up:\n{log.read_text(errors='replace')[-3000:]}")
    ctx = ssl.create_default_context(cafile=str(certs.ca))
    yield {"base": page.group(1), "fox": fox.group(1), "ssl": ctx, "log": log, "work": d / "work", "ip": link.b_ip}
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def http(serve, method: str, path: str, body: dict | None = None, token: str | None = None,
         headers: dict | None = None) -> tuple[int, object, dict]:
    """One request across the veth link: (status, JSON or text, the answer's headers)."""
    h = {"Content-Type": "application/json"} if body is not None else {}
    if token:
        h["Authorization"] = f"Bearer {token}"
    h.update(headers or {})
    req = urllib.request.Request(serve["base"] + path, data=json.dumps(body).encode() if body is not None else None,
                                 method=method, headers=h)
    try:
        with urllib.request.urlopen(req, timeout=STEP_TIMEOUT_S, context=serve["ssl"]) as r:
            raw, code, seen = r.read().decode(errors="replace"), r.status, dict(r.headers)
    except urllib.error.HTTPError as e:
        raw, code, seen = e.read().decode(errors="replace"), e.code, dict(e.headers)
    try:
        return code, json.loads(raw), seen
    except json.JSONDecodeError:
        return code, raw, seen


def token(serve, user: str, password: str) -> str:
    code, a, _ = http(serve, "POST", "/api/login", {"user": user, "password": password})
    assert code == 200, (user, code, a)
    return a["token"]


# -- 1. no well-known admin; the fleet's own user is no login; no password printed ------------------------
def test_no_well_known_login_and_the_internal_user_is_no_login(serve):
    code, a, _ = http(serve, "POST", "/api/login", {"user": "testUser", "password": "testUser"})
    assert code == 401, a
    # the users file's testUser, with its own password, is an operator (serve started with it)
    code, a, _ = http(serve, "POST", "/api/login", {"user": "testUser", "password": USERS["testUser"][1]})
    assert code == 200 and a["role"] == "operator", a
    assert token(serve, "admin", ADMIN_PW)
    # the robots' own login (the fleet's internal user) opens no door for a person
    cfg = json.loads((serve["work"] / "configs" / "robot1.config").read_text())
    assert oct((serve["work"] / "configs" / "robot1.config").stat().st_mode & 0o777) == "0o600"
    code, a, _ = http(serve, "POST", "/api/login", {"user": cfg["userID"], "password": cfg["password"]})
    assert code == 401, a
    text = serve["log"].read_text(errors="replace")
    for secret in (cfg["password"], ADMIN_PW, "password testUser"):
        assert secret not in text


def test_serve_beyond_loopback_without_an_admin_refuses_to_start(lab, tmp_path):
    netlab, link = lab
    p = subprocess.run(netlab.wrap("srv", _serve_argv(tmp_path, link.b_ip, "--timeout", "5")), capture_output=True,
                       text=True, timeout=START_TIMEOUT_S)
    assert p.returncode == 2, (p.returncode, p.stdout[-2000:], p.stderr[-2000:])
    assert "--admin-password-file" in p.stderr and "beyond loopback" in p.stderr, p.stderr


# -- 2. who did what is the server's to say, on every door ----------------------------------------------------
async def _fox(serve, query: str) -> tuple:
    ws = await connect(f"{serve['fox']}/?{query}", subprotocols=[SUB], ssl=serve["ssl"], max_size=None)
    channels: dict[str, dict] = {}
    async with asyncio.timeout(STEP_TIMEOUT_S):
        while "/fleet/tasks" not in channels:
            m = orjson.loads(await ws.recv())
            if m["op"] == "advertise":
                channels.update({c["topic"]: c for c in m["channels"]})
    return ws, channels


async def _fox_publish(ws, cid: int, topic: str, schema: str, msg: dict) -> None:
    await ws.send(json.dumps({"op": "advertise", "channels": [{"id": cid, "topic": topic, "encoding": "json",
                                                               "schemaName": schema}]}))
    await ws.send(b"\x01" + cid.to_bytes(4, "little") + json.dumps(msg).encode())


def _task(serve, tok: str, tid: str, want=lambda t: True) -> dict:
    end = time.monotonic() + STEP_TIMEOUT_S
    while True:
        code, t, _ = http(serve, "GET", f"/api/tasks/{tid}", token=tok)
        if code == 200 and want(t):
            return t
        assert time.monotonic() < end, (code, t)
        time.sleep(0.2)


def test_foxglove_stamps_the_task_source_and_canceller_from_the_token(serve):
    op = token(serve, "testUser", USERS["testUser"][1])

    async def run() -> None:
        ws, _ = await _fox(serve, f"token={op}")
        await _fox_publish(ws, 1, "/fleet/task", "fleet/Task",
                           {"request": "f1", "id": "fx1", "errands": ["drop1"], "priority": 0.0,
                            "earliest_start_s": 3600.0, "deadline_s": 0.0, "source": "http:someone-else"})
        t = await asyncio.to_thread(_task, serve, op, "fx1")
        assert t["source"] == "foxglove:testUser", t
        await _fox_publish(ws, 2, "/fleet/task_cancel", "fleet/TaskCancel",
                           {"request": "f2", "id": "fx1", "source": "http:mallory"})
        t = await asyncio.to_thread(_task, serve, op, "fx1", lambda t: t["state"] == "cancelled")
        assert t["cancelled_by"] == "foxglove:testUser", t
        await ws.close()
    asyncio.run(run())


def _page_url(serve, user: str, tok: str, robot: str) -> str:
    digest = hashlib.sha256(tok.encode()).hexdigest()
    return f"{serve['base'].replace('https://', 'wss://')}/rce/ws?userID={user}&robotID={robot}&password={digest}"


async def _page_frames(ws, frames: list[dict]) -> None:
    for f in frames:
        await ws.send(json.dumps(f))


def _page_task_frames(robot: str, ctag: str = "cTag_01") -> list[dict]:
    tag = f"{robot}_task"
    return [{"type": "CN", "data": {"addInterfaces": [
                {"endpointTag": ctag, "interfaceTag": tag, "interfaceType": "PublisherInterface",
                 "className": "fleet/Task", "addr": "/fleet/task"},
                {"endpointTag": robot, "interfaceTag": "task", "interfaceType": "SubscriberConverter",
                 "className": "fleet/Task"}]}},
            {"type": "CX", "data": {"connect": [{"tagA": f"{ctag}/{tag}", "tagB": f"{robot}/task"}]}}]


async def _wait_up(ws, itag: str) -> None:
    async with asyncio.timeout(STEP_TIMEOUT_S):
        while True:
            m = await ws.recv()
            if isinstance(m, str):
                d = json.loads(m)
                if d["type"] == "ST" and d["data"].get("iTag") == itag and d["data"].get("status") is True:
                    return


def test_page_session_stamps_the_source_and_refuses_what_the_role_may_not(serve):
    op = token(serve, "testUser", USERS["testUser"][1])
    viewer = token(serve, "vera", USERS["vera"][1])

    async def run() -> None:
        async with connect(_page_url(serve, "testUser", op, "operator-t1"), ssl=serve["ssl"]) as ws:
            await _page_frames(ws, _page_task_frames("operator-t1"))
            await _wait_up(ws, "task")
            await ws.send(json.dumps({"type": "DM", "data": {"iTag": "task", "type": "fleet/Task", "msgID": "1",
                                      "msg": {"request": "p1", "id": "pg1", "errands": ["drop1"], "priority": 0.0,
                                              "earliest_start_s": 3600.0, "deadline_s": 0.0,
                                              "source": "http:someone-else"}}}))
            t = await asyncio.to_thread(_task, serve, op, "pg1")
            assert t["source"] == "page:testUser", t
            await ws.send(json.dumps({"type": "CC", "data": {"containerTag": "mine"}}))
            with pytest.raises(ConnectionClosed) as e:
                async with asyncio.timeout(STEP_TIMEOUT_S):
                    while True:
                        await ws.recv()
            assert e.value.rcvd.code == 1008 and "CC" in e.value.rcvd.reason
        # a viewer's page may not add what publishes into the fleet
        async with connect(_page_url(serve, "vera", viewer, "operator-v1"), ssl=serve["ssl"]) as ws:
            await _page_frames(ws, _page_task_frames("operator-v1")[:1])
            with pytest.raises(ConnectionClosed) as e:
                async with asyncio.timeout(STEP_TIMEOUT_S):
                    while True:
                        await ws.recv()
            assert e.value.rcvd.code == 1008 and "viewer" in e.value.rcvd.reason
        # a token of one user does not open another's session; no token opens none
        for url in (_page_url(serve, "admin", viewer, "operator-x1"),
                    _page_url(serve, "vera", "nothing", "operator-x2")):
            with pytest.raises(InvalidStatus) as e:
                await connect(url, ssl=serve["ssl"])
            assert e.value.response.status_code == 401
    asyncio.run(run())


# -- 3. the Foxglove port follows the page's bind, TLS and credentials --------------------------------------
def test_foxglove_port_is_on_the_page_address_over_tls_with_its_tokens(serve):
    assert serve["fox"].startswith(f"wss://{serve['ip']}:")
    viewer = token(serve, "vera", USERS["vera"][1])
    metrics = serve["fox"].replace("wss://", "https://") + "/metrics"

    def get(headers: dict) -> int:
        try:
            with urllib.request.urlopen(urllib.request.Request(metrics, headers=headers), timeout=STEP_TIMEOUT_S,
                                        context=serve["ssl"]) as r:
                return r.status
        except urllib.error.HTTPError as e:
            return e.code
    assert get({}) == 401
    assert get({"Authorization": f"Bearer {viewer}"}) == 200

    async def run() -> None:
        digest = hashlib.sha256(USERS["testUser"][1].encode()).hexdigest()
        for query in (f"userID=testUser&password={digest}", "token=wrong"):
            with pytest.raises(InvalidStatus) as e:
                await connect(f"{serve['fox']}/?{query}", subprotocols=[SUB], ssl=serve["ssl"])
            assert e.value.response.status_code == 401, query
        ws, channels = await _fox(serve, f"token={viewer}")
        assert "/fleet/tasks" in channels
        # a viewer watches; publishing is an operator's
        await _fox_publish(ws, 1, "/fleet/task", "fleet/Task", {"request": "v", "errands": ["drop1"]})
        async with asyncio.timeout(STEP_TIMEOUT_S):
            while True:
                m = await ws.recv()
                if isinstance(m, str) and (s := orjson.loads(m))["op"] == "status" and "operator" in s["message"]:
                    break
        await ws.close()
    asyncio.run(run())


def test_a_new_role_closes_the_users_foxglove_sessions(serve):
    """An operator demoted to viewer loses its Foxglove session at once (1008, the reason named), and its
    old token opens none again: no one keeps a role they no longer have until they reconnect."""
    admin = token(serve, "admin", ADMIN_PW)
    code, a, _ = http(serve, "POST", "/api/users", {"name": "olga", "password": "olga-pw-123", "role": "operator"},
                      token=admin)
    assert code == 201, a
    olga = token(serve, "olga", "olga-pw-123")

    async def run() -> None:
        ws, _ = await _fox(serve, f"token={olga}")
        code, a, _ = await asyncio.to_thread(http, serve, "PATCH", "/api/users/olga", {"role": "viewer"}, admin)
        assert code == 200 and a["revoked"] >= 1, a
        with pytest.raises(ConnectionClosed) as e:
            async with asyncio.timeout(STEP_TIMEOUT_S):
                while True:
                    await ws.recv()
        assert e.value.rcvd.code == 1008 and "revoked" in e.value.rcvd.reason, e.value.rcvd
        with pytest.raises(InvalidStatus) as e:
            await connect(f"{serve['fox']}/?token={olga}", subprotocols=[SUB], ssl=serve["ssl"])
        assert e.value.response.status_code == 401
        again = await asyncio.to_thread(token, serve, "olga", "olga-pw-123")
        ws, channels = await _fox(serve, f"token={again}")         # the new role's session
        assert "/fleet/tasks" in channels
        await ws.close()
    asyncio.run(run())


# -- 4. tokens: bounded per user, and the login says they end with a restart ---------------------------------
def test_tokens_are_bounded_per_user_and_say_they_end_with_a_restart(serve):
    from rce_fleet.operations.api_auth import MAX_PER_USER
    op = token(serve, "testUser", USERS["testUser"][1])
    code, a, _ = http(serve, "POST", "/api/login", {"user": "vera", "password": USERS["vera"][1]})
    assert code == 200 and a["survives_restart"] is False, a
    first = a["token"]
    for _ in range(MAX_PER_USER):
        token(serve, "vera", USERS["vera"][1])
    assert http(serve, "GET", "/api/tasks", token=first)[0] == 401          # vera's oldest ended
    assert http(serve, "GET", "/api/tasks", token=op)[0] == 200             # testUser's lives on


def test_ten_thousand_logins_of_one_user_leave_the_others_tokens():
    from rce_fleet.operations.api_auth import MAX_PER_USER, TokenBook
    book = TokenBook()
    theirs = book.issue("otto", "operator", 0.0)[0]
    mine = [book.issue("mallory", "viewer", 0.0)[0] for _ in range(10_000)]
    assert book.check(theirs, 1.0) is not None
    assert book.check(mine[-1], 1.0) is not None and book.check(mine[0], 1.0) is None
    assert len(book.tokens) == MAX_PER_USER + 1 and book.evicted_user == 10_000 - MAX_PER_USER


# -- 5. hardening -----------------------------------------------------------------------------------------
def test_answers_are_hardened(serve):
    code, _, h = http(serve, "GET", "/")
    assert code == 200
    assert h.get("X-Frame-Options") == "DENY" and "frame-ancestors 'none'" in h.get("Content-Security-Policy", "")
    assert h.get("X-Content-Type-Options") == "nosniff" and h.get("Referrer-Policy") == "no-referrer"
    assert h.get("Strict-Transport-Security", "").startswith("max-age=")
    assert h.get("Server") == "rce-fleet"
    viewer = token(serve, "vera", USERS["vera"][1])
    code, _, h = http(serve, "GET", "/api/tasks", token=viewer)
    assert code == 200 and h.get("Cache-Control") == "no-store" and h.get("Server") == "rce-fleet"
    code, doc, _ = http(serve, "GET", "/api/openapi.json", headers={"Host": "evil.example"})
    assert code == 200 and doc["servers"][0]["url"] == "/", doc["servers"]
