"""Every answer of ``rce-fleet serve``'s web server keeps the API's contract, whatever an outsider sends: no
answer echoes more than a short prefix of its input (a megabyte task id or place name, on the API and through
the page's session into the planner's answers), odd JSON (a 5,000-digit integer, nesting 2,000 and 100,000
deep, a lone surrogate) gets a 400 at once, every error is the documented ``{"error", "code"}`` JSON (405, 413,
404, ``GET /api/login``), and the OpenAPI document lists every status each operation gives.

``rce-fleet serve`` runs as a process over TLS on loopback with a users file (a viewer, an operator) beside the
first admin. Bodies go as raw bytes (``http.client``), so nothing client-side normalises them.
"""
from __future__ import annotations

import asyncio
import hashlib
import http.client as httpc
import json
import time

import orjson
import pytest
from websockets.asyncio.client import connect

from tests.fleet.test_fleet_tasks_api import USERS, http, login, start_tls_serve, stop_serve

SHORT = 1024                  # bytes: an answer that quotes input quotes a short prefix of it, well under this
MEGA = 1_000_000              # characters of the megabyte inputs
STEP_TIMEOUT_S = 15.0


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    f = start_tls_serve(tmp_path_factory.mktemp("contract"))
    yield f
    stop_serve(f)


def raw(fleet, method: str, path: str, body: bytes = b"", auth: str | None = "admin",
        headers: dict | None = None) -> tuple[int, dict, bytes]:
    """One request with ``body`` as it is: (status, the answer's headers, its body)."""
    host, port = fleet["base"].split("//")[1].rsplit(":", 1)
    c = httpc.HTTPSConnection(host, int(port), context=fleet["ssl"], timeout=STEP_TIMEOUT_S)
    h = {"Content-Type": "application/json", **(headers or {})}
    if auth:
        h["Authorization"] = fleet["auth"] if auth == "admin" else auth
    try:
        c.request(method, path, body=body, headers=h)
        r = c.getresponse()
        return r.status, dict(r.getheaders()), r.read()
    finally:
        c.close()


def contract(status: int, headers: dict, body: bytes, want: int) -> dict:
    """The answer is ``want`` and the API's error form: JSON ``{"error", "code"}`` fitting ``ApiError``."""
    from rce_fleet.operations.api_models import ApiError
    assert status == want, (status, body[:300])
    assert headers.get("Content-Type", "").startswith("application/json"), (headers, body[:300])
    err = json.loads(body)
    ApiError.model_validate(err)
    assert set(err) == {"error", "code"}, err
    return err


# -- a megabyte is never echoed ----------------------------------------------------------------------------
def test_no_answer_echoes_more_than_a_short_prefix_of_its_input(fleet):
    big = "x" * MEGA
    for body, says in ((json.dumps({"errands": [big]}), "unknown place 'xxx"),
                       (json.dumps({"errands": ["pick1"], "id": big}), "id: use 1-64 letters"),
                       (json.dumps({"errands": ["pick1"], big: 1}), "unknown field(s) 'xxx")):
        status, h, answer = raw(fleet, "POST", "/api/tasks", body.encode())
        err = contract(status, h, answer, 400)
        assert len(answer) < SHORT and says in err["error"], (len(answer), err["error"][:200])
    status, h, answer = raw(fleet, "GET", "/api/tasks/" + "y" * 8000)
    assert contract(status, h, answer, 404) and len(answer) < SHORT


def _page_frames(robot: str, ctag: str = "cTag_01") -> list[dict]:
    """An operator's page: a task publisher and the task lists, each a container interface and a converter."""
    return [{"type": "CN", "data": {"addInterfaces": [
                {"endpointTag": ctag, "interfaceTag": f"{robot}_task", "interfaceType": "PublisherInterface",
                 "className": "fleet/Task", "addr": "/fleet/task"},
                {"endpointTag": robot, "interfaceTag": "task", "interfaceType": "SubscriberConverter",
                 "className": "fleet/Task"},
                {"endpointTag": ctag, "interfaceTag": f"{robot}_tasks", "interfaceType": "SubscriberInterface",
                 "className": "fleet/TaskList", "addr": "/fleet/tasks"},
                {"endpointTag": robot, "interfaceTag": "tasks", "interfaceType": "PublisherConverter",
                 "className": "fleet/TaskList"}]}},
            {"type": "CX", "data": {"connect": [{"tagA": f"{ctag}/{robot}_task", "tagB": f"{robot}/task"},
                                                {"tagA": f"{ctag}/{robot}_tasks", "tagB": f"{robot}/tasks"}]}}]


def test_the_planners_answers_hold_no_megabyte(fleet):
    """A megabyte task id through the page's session (an operator's) reaches the planner, whose answer (kept
    among the last 100 of every task list, sent twice a second) names it by a short prefix at most."""
    code, a = login(fleet, "otto", USERS["otto"][1])
    assert code == 200, a
    digest = hashlib.sha256(a["token"].encode()).hexdigest()
    url = fleet["base"].replace("https://", "wss://") + f"/rce/ws?userID=otto&robotID=operator-big1&password={digest}"

    async def run() -> tuple[dict, int]:
        async with connect(url, ssl=fleet["ssl"], max_size=None) as ws:
            for f in _page_frames("operator-big1"):
                await ws.send(json.dumps(f))
            up: set[str] = set()
            async with asyncio.timeout(STEP_TIMEOUT_S):
                while up != {"task", "tasks"}:
                    m = orjson.loads(await ws.recv())
                    if m["type"] == "ST" and m["data"].get("status") is True:
                        up.add(m["data"].get("iTag"))
            await ws.send(json.dumps({"type": "DM", "data": {"iTag": "task", "type": "fleet/Task", "msgID": "1",
                                      "msg": {"request": "big-1", "id": "x" * MEGA, "errands": ["pick1"],
                                              "priority": 0.0, "earliest_start_s": 0.0, "deadline_s": 0.0}}}))
            async with asyncio.timeout(STEP_TIMEOUT_S):
                while True:
                    frame = await ws.recv()
                    m = orjson.loads(frame)
                    if m["type"] == "DM" and m["data"].get("iTag") == "tasks":
                        mine = [x for x in m["data"]["msg"]["answers"] if x["request"] == "big-1"]
                        if mine:
                            return mine[0], len(frame)
    answer, frame_len = asyncio.run(run())
    assert answer["ok"] is False and answer["code"] == "bad_request", answer
    assert answer["id"] == "" and "use 1-64 letters" in answer["error"] and len(answer["error"]) < 300, answer
    assert frame_len < 64 * 1024, frame_len           # the whole task list, the answer in it


# -- odd JSON is a 400 at once ------------------------------------------------------------------------------
ODD = {"a 5,000-digit integer": (b'{"errands": [' + b"7" * 5000 + b"]}", "number"),
       "nesting 2,000 deep": (b'{"errands": ' + b"[" * 2000 + b"]" * 2000 + b"}", "deeper than 64 levels"),
       "nesting 100,000 deep": (b'{"errands": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", "deeper than 64 levels"),
       "a lone surrogate": (b'{"errands": ["\\ud800"]}', "surrogate"),
       "bytes that are not UTF-8": (b'{"errands": ["\xff"]}', "not UTF-8")}


@pytest.mark.parametrize("path", ["/api/tasks", "/api/login"])
def test_odd_json_gets_a_400_at_once_and_no_traceback(fleet, path):
    for what, (body, says) in ODD.items():
        if path == "/api/login":
            body = body.replace(b'"errands"', b'"user"')
        t0 = time.monotonic()
        status, h, answer = raw(fleet, "POST", path, body, auth="admin" if path == "/api/tasks" else None)
        err = contract(status, h, answer, 400)
        assert err["code"] == "bad_request" and says in err["error"], (what, err)
        assert time.monotonic() - t0 < 5.0, what          # the surrogate was a 10 s wait, then a 504
    assert http(fleet, "GET", "/api/tasks")[0] == 200
    assert "Traceback" not in fleet["log"].read_text(errors="replace")


# -- every error in the contract ----------------------------------------------------------------------------
def test_every_error_is_the_documented_json_error(fleet):
    status, h, answer = raw(fleet, "PUT", "/api/tasks", b"{}")
    err = contract(status, h, answer, 405)
    assert err["code"] == "method_not_allowed" and "POST" in h["Allow"] and "GET" in h["Allow"], (err, h)
    status, h, answer = raw(fleet, "GET", "/api/login", auth=None)
    assert contract(status, h, answer, 405)["code"] == "method_not_allowed" and h["Allow"] == "POST", h
    for path in ("/api/tasks", "/api/login"):
        status, h, answer = raw(fleet, "POST", path, b" " * (2 << 20), auth="admin" if path == "/api/tasks" else None)
        err = contract(status, h, answer, 413)
        assert err["code"] == "too_large" and "1048576 bytes" in err["error"], err
    for path in ("/api/nosuch", "/nosuch.html"):
        status, h, answer = raw(fleet, "GET", path)
        assert contract(status, h, answer, 404)["code"] == "not_found"
    status, h, answer = raw(fleet, "GET", "/rce/ws?userID=otto&robotID=operator-x1&password=00", auth=None,
                            headers={"Upgrade": "websocket", "Connection": "Upgrade", "Sec-WebSocket-Version": "13",
                                     "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ=="})
    assert contract(status, h, answer, 401)["code"] == "unauthorized"
    # the hardening headers are on the errors too
    assert h.get("X-Content-Type-Options") == "nosniff" and h.get("Server") == "rce-fleet", h


def test_openapi_lists_every_status_each_operation_gives(fleet):
    from openapi_spec_validator import validate
    code, doc = http(fleet, "GET", "/api/openapi.json", auth=None)
    assert code == 200
    validate(doc)
    ops = {(p, m): set(o["responses"]) for p, item in doc["paths"].items() for m, o in item.items()
           if m in ("get", "post", "patch", "delete")}
    assert all("500" in statuses for statuses in ops.values()), ops
    assert ops[("/api/login", "post")] >= {"200", "400", "401", "413", "429", "500", "503"}
    assert ops[("/api/tasks", "post")] >= {"201", "400", "401", "403", "409", "413", "429", "503", "504"}
    for (path, method), statuses in ops.items():
        body = "requestBody" in doc["paths"][path][method]
        assert not body or {"400", "413"} <= statuses, (path, method)
        open_ = doc["paths"][path][method].get("security") == []
        assert open_ or {"401", "403", "429", "503"} <= statuses, (path, method)
    assert {("/api/users", "get"), ("/api/users", "post"), ("/api/users/{name}", "patch"),
            ("/api/users/{name}", "delete")} <= set(ops)
    assert {"method_not_allowed", "too_large", "internal"} <= set(
        doc["components"]["schemas"]["ApiError"]["properties"]["code"]["enum"])
