"""An admin manages the master's users on a running ``rce-fleet serve`` (``rce-console`` has no admin token for
serve's master): the HTTP API's ``/api/users`` and ``rce-fleet users``; a changed user's tokens and page sessions
end, the last admin stays one, the fleet's internal user is no one's to manage.

``rce-fleet serve`` runs as a process over TLS on loopback with a users file (a viewer, an operator) beside the
first admin; the clients are urllib, a raw websocket on the page's ``/rce/ws``, and ``rce-fleet`` processes.
"""
from __future__ import annotations

import asyncio
import hashlib
import os
import subprocess

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from tests.fleet.test_fleet_tasks_api import (ADMIN, BIN, CLI_TIMEOUT_S, USERS, basic, bearer, http, login,
                                              start_tls_serve, stop_serve)

STEP_TIMEOUT_S = 15.0


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    f = start_tls_serve(tmp_path_factory.mktemp("users"))
    yield f
    stop_serve(f)


def _roles(fleet) -> dict[str, str]:
    code, lst = http(fleet, "GET", "/api/users")
    assert code == 200, lst
    return {u["name"]: u["role"] for u in lst["users"]}


async def _page_closed(fleet, user: str, token: str, change) -> tuple[int, str]:
    """Open ``user``'s page session with ``token``, run ``change()`` (blocking) beside it; returns the code and
    reason the server closed the session with."""
    digest = hashlib.sha256(token.encode()).hexdigest()
    url = fleet["base"].replace("https://", "wss://") + f"/rce/ws?userID={user}&robotID=operator-{user}1&" \
                                                         f"password={digest}"
    async with connect(url, ssl=fleet["ssl"]) as ws:
        await asyncio.to_thread(change)
        with pytest.raises(ConnectionClosed) as e:
            async with asyncio.timeout(STEP_TIMEOUT_S):
                while True:
                    await ws.recv()
    return e.value.rcvd.code, e.value.rcvd.reason


def test_an_admin_adds_changes_and_removes_users_while_serving(fleet):
    vera = basic("vera", USERS["vera"][1])
    code, err = http(fleet, "GET", "/api/users", auth=vera)
    assert code == 403 and "needs admin" in err["error"], err
    assert _roles(fleet) == {"admin": "admin", "otto": "operator", "vera": "viewer"}     # no fleet-internal
    # a new viewer
    code, u = http(fleet, "POST", "/api/users", {"name": "uma", "password": "uma-pw-123", "role": "viewer"})
    assert code == 201 and u == {"name": "uma", "role": "viewer", "revoked": 0}, u
    for body, want, says in (({"name": "uma", "password": "uma-pw-123"}, 409, "exists"),
                             ({"name": "ulf", "password": "short"}, 400, "password: 8-1024 characters"),
                             ({"name": "u/lf", "password": "ulf-pw-123"}, 400, "name: 1-64 letters"),
                             ({"name": "ulf", "password": "ulf-pw-123", "role": "root"}, 400, "role: viewer")):
        code, err = http(fleet, "POST", "/api/users", body)
        assert code == want and says in err["error"], (body, code, err)
    code, a = login(fleet, "uma", "uma-pw-123")
    assert code == 200 and a["role"] == "viewer", a
    assert http(fleet, "POST", "/api/tasks", {"errands": ["pick1"]}, auth=bearer(a["token"]))[0] == 403
    # made an operator: her token and her page session end with the change; a new login has the new role
    changed: dict = {}

    def promote() -> None:
        changed["answer"] = http(fleet, "PATCH", "/api/users/uma", {"role": "operator"})
    close = asyncio.run(_page_closed(fleet, "uma", a["token"], promote))
    assert changed["answer"] == (200, {"name": "uma", "role": "operator", "revoked": 1}), changed
    assert close[0] == 1008 and "revoked" in close[1], close
    assert http(fleet, "GET", "/api/tasks", auth=bearer(a["token"]))[0] == 401
    code, b = login(fleet, "uma", "uma-pw-123")
    assert code == 200 and b["role"] == "operator", b
    code, t = http(fleet, "POST", "/api/tasks", {"errands": ["pick1"], "earliest_start_s": 3600.0, "id": "u1"},
                   auth=bearer(b["token"]))
    assert code == 201 and t["source"] == "http:uma", t
    assert http(fleet, "DELETE", "/api/tasks/u1", auth=bearer(b["token"]))[0] == 200
    # a new password: the old one is refused, the new one logs in
    code, u = http(fleet, "PATCH", "/api/users/uma", {"password": "uma-new-pw-9"})
    assert code == 200 and u["role"] == "operator" and u["revoked"] == 1, u
    assert login(fleet, "uma", "uma-pw-123")[0] == 401
    assert login(fleet, "uma", "uma-new-pw-9")[0] == 200
    # what an admin may not do
    for method, path, body, want, says in (
            ("PATCH", "/api/users/admin", {"role": "viewer"}, 409, "last admin"),
            ("DELETE", "/api/users/admin", None, 409, "last admin"),
            ("DELETE", "/api/users/fleet-internal", None, 403, "the fleet's own"),
            ("PATCH", "/api/users/fleet-internal", {"role": "admin"}, 403, "the fleet's own"),
            ("POST", "/api/users", {"name": "fleet-internal", "password": "x" * 12}, 403, "the fleet's own"),
            ("PATCH", "/api/users/nobody", {"role": "viewer"}, 404, "no user 'nobody'"),
            ("DELETE", "/api/users/nobody", None, 404, "no user 'nobody'"),
            ("PATCH", "/api/users/uma", {}, 400, "a role, a password or both"),
            ("PATCH", "/api/users/uma", {"rank": "admin"}, 400, "unknown field(s) 'rank'")):
        code, err = http(fleet, method, path, body)
        assert code == want and says in err["error"], (method, path, code, err)
    # removed: her tokens end, she cannot log in
    code, u = http(fleet, "DELETE", "/api/users/uma")
    assert code == 200 and u == {"name": "uma", "role": "", "revoked": 1}, u
    assert login(fleet, "uma", "uma-new-pw-9")[0] == 401
    assert "uma" not in _roles(fleet)


def _users_cli(fleet, *args: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    """``rce-fleet users ARGS`` as the first admin."""
    return subprocess.run([str(BIN / "rce-fleet"), "users", *args, "--api", fleet["page"], "--user", ADMIN[0],
                           "--ca-file", fleet["ca"]], input=stdin, capture_output=True, text=True,
                          timeout=CLI_TIMEOUT_S, env=dict(os.environ, RCE_PASSWORD=ADMIN[1]))


def test_rce_fleet_users_manages_the_users_from_a_shell(fleet):
    p = _users_cli(fleet, "add", "cleo", "--role", "viewer", "--new-password-stdin", stdin="cleo-pw-123\n")
    assert p.returncode == 0 and p.stdout.strip() == "user 'cleo' added, is viewer", (p.stdout, p.stderr)
    p = _users_cli(fleet, "list")
    assert p.returncode == 0 and {"cleo", "viewer"} <= set(p.stdout.split()) and "fleet-internal" not in p.stdout
    p = _users_cli(fleet, "role", "cleo", "--role", "operator")
    assert p.returncode == 0 and "user 'cleo' is now operator" in p.stdout, p.stderr
    p = _users_cli(fleet, "password", "cleo", "--new-password-stdin", stdin="cleo-pw-456\n")
    assert p.returncode == 0 and "has a new password" in p.stdout, p.stderr
    code, a = login(fleet, "cleo", "cleo-pw-456")
    assert code == 200 and a["role"] == "operator", a
    p = _users_cli(fleet, "remove", "cleo")
    assert p.returncode == 0 and "user 'cleo' removed; 1 token(s) ended" in p.stdout, (p.stdout, p.stderr)
    p = _users_cli(fleet, "role", "admin", "--role", "viewer")
    assert p.returncode == 1 and "the last admin" in p.stderr, p.stderr
    p = _users_cli(fleet, "add", "dora", "--new-password-stdin", stdin="short\n")
    assert p.returncode == 2 and "8 characters at least" in p.stderr, p.stderr
