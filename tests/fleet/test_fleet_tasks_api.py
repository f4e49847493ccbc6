"""The operators' task API against a running fleet: ``rce-fleet serve`` as a process (engine
processes, fleet container with the global planner and move_clients, pymunk robots as
rce-ros clients) on the lab map (8x8 cells of 1 m), 2 robots, sped-up simulation, with a
places file; ``rce-fleet task`` as processes (an RCE client, or a client of the HTTP API) and the
JSON HTTP API of ``serve``'s web server, here over TLS with a throw-away CA and with a users file
of a viewer and an operator beside the first admin of ``--admin-password-file``."""
from __future__ import annotations

import base64
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

import pytest

BIN = Path(sys.executable).parent
URL_TIMEOUT_S = 90        # wall s for rce-fleet to start the engine, the fleet and the page
STOP_TIMEOUT_S = 30       # wall s rce-fleet gets to stop after SIGINT
CLI_TIMEOUT_S = 40        # wall s one rce-fleet task command may take
DONE_TIMEOUT_S = 60       # wall s a pick-up -> drop-off task on the lab map takes at speedup 10
PLACES = "places:\n  - {name: pick1, kind: pickup, cell: 16}\n  - {name: drop1, kind: dropoff, cell: 23}\n" \
         "  - {name: charger1, kind: charger, cell: 0}\n  - {name: park1, kind: parking, cell: 56}\n" \
         "  - {name: park2, kind: parking, cell: 7}\n"


USERS = {"vera": ("viewer", "vera-pw"), "otto": ("operator", "otto-pw")}    # name: (role, password)
ADMIN = ("admin", "first-admin-pw")      # the first admin (--admin-password-file)


def write_users(path: Path) -> Path:
    """A master users file (what ``rce-console user add NAME --role ROLE --file PATH`` writes) of USERS."""
    from rce_master.state.master_state import MasterState
    from rce_master.auth.users import UsersFile
    st = MasterState()
    for name, (role, pw) in USERS.items():
        st.add_user(name, pw, role)
    UsersFile(path).save(st)
    return path


def start_serve(d: Path, *extra: str, ca: str | None = None) -> dict:
    """``rce-fleet serve`` on the lab map with the places above; returns {"proc", "page", "base", "master",
    "log", "ssl", "auth"} (``ssl``: a client context trusting ``ca``, for ``--tls-cert``; ``auth``: the
    Authorization header of a token of the first admin)."""
    (d / "places.yaml").write_text(PLACES)
    (d / "admin-pw").write_text(ADMIN[1] + "\n")
    log = d / "serve.log"
    argv = [str(BIN / "rce-fleet"), "serve", "--robots", "2", "--speedup", "10", "--grid", "8x8", "--web-port", "0",
            "--no-live", "--workdir", str(d / "work"), "--timeout", "600", "--places", str(d / "places.yaml"),
            "--start", "Robot1=33", "--start", "Robot2=38", "--admin-password-file", str(d / "admin-pw"), *extra]
    p = subprocess.Popen(argv, stdout=open(log, "wb"), stderr=subprocess.STDOUT, start_new_session=True,
                         env=dict(os.environ, RCE_LOG_JSON="1"))
    deadline = time.monotonic() + URL_TIMEOUT_S
    while time.monotonic() < deadline:
        text = log.read_text(errors="replace")
        page = re.search(r"operator page: (https?://\S+)", text)
        master = re.search(r"rce-fleet: master (http://\S+)", text)
        if page and master:
            u = page.group(1)
            f = {"proc": p, "page": u, "base": u.split("/?")[0], "master": master.group(1), "log": log,
                 "ssl": ssl.create_default_context(cafile=ca) if ca else None, "ca": ca}
            f["auth"] = bearer(login(f, *ADMIN)[1]["token"])
            return f
        if p.poll() is not None:
            break
        time.sleep(0.1)
    p.kill()
    pytest.fail(f"rce-fleet serve did not come up:\n{log.read_text(errors='replace')[-3000:]}")


def stop(p: subprocess.Popen) -> int:
    """SIGINT, as Ctrl-C; killed (its process group) after STOP_TIMEOUT_S. Returns the exit code."""
    if p.poll() is None:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    return p.returncode


def stop_serve(f: dict) -> None:
    stop(f["proc"])


def start_tls_serve(d: Path, *extra: str) -> dict:
    """:func:`start_serve` over TLS (a throw-away CA in ``d``) with the users file of :data:`USERS`."""
    from rce.transport.tls import make_dev_certificates
    certs = make_dev_certificates(d / "tls")
    return start_serve(d, "--tls-cert", str(certs.cert), "--tls-key", str(certs.key), "--users",
                       str(write_users(d / "users.json")), *extra, ca=str(certs.ca))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    f = start_tls_serve(tmp_path_factory.mktemp("tasks"))
    yield f
    stop_serve(f)


def bearer(token: str) -> str:
    return f"Bearer {token}"


def basic(user: str, password: str) -> str:
    return "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode()


def login(fleet, user: str, password: str, **extra) -> tuple[int, dict]:
    """``POST /api/login``: (status, answer)."""
    return http(fleet, "POST", "/api/login", {"user": user, "password": password, **extra}, auth=None)


def cli(fleet, *args: str) -> subprocess.CompletedProcess:
    """``rce-fleet task ARGS`` at the fleet's task API as the first admin (people use the page's doors: the
    master's RCE door is the fleet's own user's)."""
    return subprocess.run([str(BIN / "rce-fleet"), "task", *args, "--api", fleet["page"], "--user", ADMIN[0],
                           *(("--ca-file", fleet["ca"]) if fleet.get("ca") else ())], capture_output=True, text=True,
                          timeout=CLI_TIMEOUT_S, env=dict(os.environ, RCE_PASSWORD=ADMIN[1]))


def http(fleet, method: str, path: str, body: dict | None = None, auth: str | None = "admin",
         headers: dict | None = None) -> tuple[int, dict | str]:
    """One request to the page's server: (status, JSON answer or text). ``auth``: the Authorization
    header ("admin": the fixture's admin token; None: none); ``headers`` (a dict) gets the answer's."""
    data = json.dumps(body).encode() if body is not None else None
    h = {"Content-Type": "application/json"} if data else {}
    if auth:
        h["Authorization"] = fleet["auth"] if auth == "admin" else auth
    req = urllib.request.Request(fleet["base"] + path, data=data, method=method, headers=h)
    try:
        with urllib.request.urlopen(req, timeout=15, context=fleet.get("ssl")) as r:
            raw, code = r.read().decode(), r.status
            seen = r.headers
    except urllib.error.HTTPError as e:
        raw, code, seen = e.read().decode(), e.code, e.headers
    if headers is not None:
        headers.update(seen)
    try:
        return code, json.loads(raw)
    except json.JSONDecodeError:
        return code, raw


def wait_task(fleet, tid: str, states: tuple[str, ...], timeout: float = DONE_TIMEOUT_S) -> dict:
    end = time.monotonic() + timeout
    while True:
        code, t = http(fleet, "GET", f"/api/tasks/{tid}")
        if code == 200 and t["state"] in states:
            return t
        if time.monotonic() > end:
            raise AssertionError(f"task {tid} not {states} within {timeout} s: {t}")
        time.sleep(0.25)


def test_cli_adds_lists_and_cancels_and_refuses_bad_input_with_the_reason(fleet):
    p = cli(fleet, "add", "drop1", "pick1", "--id", "c1", "--priority", "1", "--start-in", "3600")
    assert p.returncode == 0, p.stderr
    assert re.match(r"c1\s+queued\s", p.stdout), p.stdout
    bad = cli(fleet, "add", "pick1", "nowhere")
    assert bad.returncode == 1 and "unknown place 'nowhere' (places: charger1, drop1, park1, park2, pick1)" \
        in bad.stderr, bad.stderr
    gone = cli(fleet, "cancel", "c1")
    assert gone.returncode == 0 and re.match(r"c1\s+cancelled\s", gone.stdout), gone.stdout
    lst = cli(fleet, "list", "--json")
    assert lst.returncode == 0, lst.stderr
    tasks = {t["id"]: t for t in json.loads(lst.stdout)["tasks"]}
    c1 = tasks["c1"]
    assert c1["state"] == "cancelled" and c1["source"] == "http:admin" and c1["cells"] == [23, 16]
    assert c1["reason"] == "cancelled by http:admin" and c1["finished"] >= c1["created"] > 0


def test_http_api_creates_gets_cancels_and_says_why_not(fleet):
    code, t = http(fleet, "POST", "/api/tasks", {"errands": ["pick1", 23], "priority": 2})
    assert code == 201 and t["state"] in ("queued", "assigned") and t["errands"] == ["pick1", "23"], t
    tid = t["id"]
    for body, want, text in (({"errands": []}, 400, "at least one errand"),
                             ({"errands": ["pick1", "dock9"]}, 400, "unknown place 'dock9'"),
                             ({"errands": [99]}, 400, "outside the 8x8 grid"),
                             ({"errands": ["pick1"], "deadline_s": "soon"}, 400, "must be numbers"),
                             ({"errands": ["pick1"], "priorty": 5}, 400, "unknown field(s) 'priorty'"),
                             ({"errands": ["drop1"], "id": tid}, 409, "exists already")):
        c, err = http(fleet, "POST", "/api/tasks", body)
        assert c == want and text in err["error"], (body, c, err)
    c, err = http(fleet, "DELETE", "/api/tasks/nosuch")
    assert c == 404 and err["code"] == "not_found"
    code, one = http(fleet, "GET", f"/api/tasks/{tid}")
    assert code == 200 and one["id"] == tid
    # the refusals lost nothing: the task is done by a robot, through the pick-up and the drop-off
    done = wait_task(fleet, tid, ("done", "failed"))
    assert done["state"] == "done" and done["robot"] in ("Robot1", "Robot2") and done["cells"] == [16, 23], done
    assert 0 < done["created"] <= done["assigned"] <= done["active"] <= done["finished"]
    c, err = http(fleet, "DELETE", f"/api/tasks/{tid}")
    assert c == 409 and "is done: it cannot be cancelled" in err["error"]
    code, q = http(fleet, "POST", "/api/tasks", {"errands": ["drop1"], "earliest_start_s": 3600})
    c, gone = http(fleet, "DELETE", f"/api/tasks/{q['id']}")
    assert c == 200 and gone["state"] == "cancelled"
    code, lst = http(fleet, "GET", "/api/tasks")
    assert code == 200 and lst["done"] >= 1 and lst["cancelled"] >= 1
    assert {r["robot"] for r in lst["robots"]} == {"Robot1", "Robot2"}
    code, text = http(fleet, "GET", "/metrics")
    assert code == 200
    m = re.search(r'^rce_fleet_tasks_total\{state="done"\} (\d+)', text, re.M)
    assert m and int(m.group(1)) >= 1, text
    assert re.search(r'^rce_fleet_robot_utilisation\{robot="Robot1"\} [0-9.e-]+$', text, re.M)


def test_cli_without_a_master_says_so_once_and_exits_3():
    import socket
    with socket.socket() as s:        # a loopback port nothing listens on
        s.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{s.getsockname()[1]}/"
    p = subprocess.run([str(BIN / "rce-fleet"), "task", "list", "--master", url, "--timeout", "10"],
                       capture_output=True, text=True, timeout=CLI_TIMEOUT_S)
    assert p.returncode == 3, p.stderr
    assert p.stderr.strip() == f"rce-fleet task: cannot reach the master at {url}: Connection refused", p.stderr


def test_no_credential_401_viewer_403_operator_201_with_the_user_recorded(fleet):
    assert fleet["page"].startswith("https://127.0.0.1:")          # TLS, trusted through the test CA
    seen: dict = {}
    for method, path in (("GET", "/api/tasks"), ("POST", "/api/tasks"), ("DELETE", "/api/tasks/T1"),
                         ("GET", "/config.json"), ("GET", "/map.png"), ("GET", "/metrics")):
        code, err = http(fleet, method, path, {"errands": ["pick1"]} if method == "POST" else None, auth=None,
                         headers=seen)
        assert code == 401 and err["code"] == "unauthorized" and "credential is needed" in err["error"], (path, err)
        assert seen["WWW-Authenticate"] == 'Bearer realm="rce fleet", Basic realm="rce fleet"'
    code, page = http(fleet, "GET", "/", auth=None)
    assert code == 200 and 'src="fleet.js"' in page                  # the page itself shows its login form
    vera, otto = basic("vera", USERS["vera"][1]), basic("otto", USERS["otto"][1])
    code, lst = http(fleet, "GET", "/api/tasks", auth=vera)          # HTTP Basic over TLS
    assert code == 200 and {r["robot"] for r in lst["robots"]} == {"Robot1", "Robot2"}
    assert http(fleet, "GET", "/metrics", auth=vera)[0] == 200
    code, err = http(fleet, "POST", "/api/tasks", {"errands": ["pick1", "drop1"]}, auth=vera)
    assert code == 403 and err == {"error": "user 'vera' is viewer: this needs operator or above", "code": "forbidden"}
    # pick1, not drop1: an earlier test's task ends on drop1, and its robot may still stand there
    code, t = http(fleet, "POST", "/api/tasks", {"errands": ["pick1"], "earliest_start_s": 3600.0, "id": "o1"},
                   auth=otto)
    assert code == 201 and t["id"] == "o1" and t["source"] == "http:otto", t
    assert http(fleet, "DELETE", "/api/tasks/o1", auth=vera)[0] == 403
    code, gone = http(fleet, "DELETE", "/api/tasks/o1", auth=otto)
    assert code == 200 and gone["state"] == "cancelled" and gone["cancelled_by"] == "http:otto", gone
    assert gone["reason"] == "cancelled by http:otto"
    code, err = http(fleet, "GET", "/api/tasks", auth=basic("otto", "wrong"))
    assert code == 401 and err["error"] == "invalid user or password"
    code, err = http(fleet, "GET", "/api/tasks", auth="Digest x")
    assert code == 401 and "use 'Bearer TOKEN'" in err["error"]


def test_tokens_expire_are_revoked_and_failed_logins_are_throttled(fleet):
    t0 = time.monotonic()                 # before the login: the token's second counts from its issue, after this
    code, a = login(fleet, "otto", USERS["otto"][1], ttl_s=1.0)
    assert code == 200 and a["role"] == "operator" and a["token_type"] == "Bearer" and a["expires_in"] == 1.0
    assert http(fleet, "GET", "/api/tasks", auth=bearer(a["token"]))[0] == 200
    while (code := http(fleet, "GET", "/api/tasks", auth=bearer(a["token"]))[0]) == 200:
        assert time.monotonic() - t0 < 10, "the token did not expire"
        time.sleep(0.1)                   # polling the server's clock: the expiry is the behaviour under test
    assert code == 401 and time.monotonic() - t0 >= 1.0
    _, b = login(fleet, "otto", USERS["otto"][1])
    assert 28000 < b["expires_in"] <= 28800                          # the default: 8 h
    assert http(fleet, "POST", "/api/logout", auth=bearer(b["token"])) == (200, {"revoked": 1})
    code, err = http(fleet, "GET", "/api/tasks", auth=bearer(b["token"]))
    assert code == 401 and "unknown, expired or revoked" in err["error"]
    _, v = login(fleet, "vera", USERS["vera"][1])
    assert http(fleet, "DELETE", "/api/tokens/otto", auth=bearer(v["token"]))[0] == 403   # a viewer may not
    assert http(fleet, "DELETE", "/api/tokens/vera") == (200, {"revoked": 1})             # an admin may
    assert http(fleet, "GET", "/api/tasks", auth=bearer(v["token"]))[0] == 401
    code, err = http(fleet, "POST", "/api/login", {"user": "vera", "pasword": "x"}, auth=None)
    assert code == 400 and "unknown field(s) 'pasword'" in err["error"]
    # failed logins back off as robots' do (5 free per user and address), even for a user that does not exist
    seen: dict = {}
    codes = [login(fleet, "mallory", "guess")[0] for _ in range(5)]
    code, err = http(fleet, "POST", "/api/login", {"user": "mallory", "password": "guess"}, auth=None, headers=seen)
    assert codes == [401] * 5 and code == 429 and err["code"] == "throttled" and int(seen["Retry-After"]) >= 1


def test_the_openapi_document_validates_and_names_the_models(fleet):
    from openapi_spec_validator import validate
    code, doc = http(fleet, "GET", "/api/openapi.json", auth=None)
    assert code == 200
    validate(doc)                                                    # OpenAPI 3.1, with its JSON Schema dialect
    assert doc["openapi"] == "3.1.0" and doc["servers"] == [{"url": "/"}]      # relative: Host names nothing
    schemas = doc["components"]["schemas"]
    assert {"TaskRequest", "FleetTask", "TaskList", "RobotWork", "ApiError", "LoginRequest",
            "LoginAnswer"} <= set(schemas)
    assert schemas["TaskRequest"]["additionalProperties"] is False
    assert "cancelled_by" in schemas["FleetTask"]["properties"]
    post = doc["paths"]["/api/tasks"]["post"]
    assert set(post["responses"]) >= {"201", "400", "401", "403", "409"} and "operator" in post["summary"]
    assert doc["paths"]["/api/login"]["post"]["security"] == [] and doc["security"] == [{"bearer": []}, {"basic": []}]
    # what the API answers fits the document's models
    from rce_fleet.operations.api_models import TaskList
    TaskList.model_validate(http(fleet, "GET", "/api/tasks")[1])


def test_cli_speaks_the_http_api_as_a_user_with_a_role(fleet):
    def task(user: str, *args: str) -> subprocess.CompletedProcess:
        return subprocess.run([str(BIN / "rce-fleet"), "task", *args, "--api", fleet["page"], "--user", user,
                               "--ca-file", fleet["ca"]], capture_output=True, text=True, timeout=CLI_TIMEOUT_S,
                              env=dict(os.environ, RCE_PASSWORD=USERS[user][1]))
    p = task("otto", "add", "pick1", "--id", "h1", "--start-in", "3600")
    assert p.returncode == 0 and re.match(r"h1\s+queued\s", p.stdout), p.stderr
    denied = task("vera", "cancel", "h1")
    assert denied.returncode == 1 and "refused (forbidden): user 'vera' is viewer" in denied.stderr, denied.stderr
    got = task("vera", "get", "h1", "--json")
    assert got.returncode == 0 and json.loads(got.stdout)["source"] == "http:otto", got.stderr
    assert task("otto", "cancel", "h1").returncode == 0


def test_task_cli_whose_reader_stops_reading_ends_quietly(fleet):
    """``rce-fleet task list | head -1``, with the reader gone before the first line: no traceback."""
    p = subprocess.Popen([str(BIN / "rce-fleet"), "task", "list", "--api", fleet["page"], "--user", ADMIN[0],
                          "--ca-file", fleet["ca"]], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         env=dict(os.environ, RCE_PASSWORD=ADMIN[1]))
    p.stdout.close()                         # the reader stops reading: every write to stdout is EPIPE
    err = p.stderr.read().decode(errors="replace")
    assert p.wait(CLI_TIMEOUT_S) == 141, err
    assert "Traceback" not in err and "BrokenPipeError" not in err, err


def test_task_get_of_an_id_with_a_slash_says_there_is_no_such_task(fleet):
    p = cli(fleet, "get", "a/b")
    assert p.returncode == 1, (p.stdout, p.stderr)
    assert p.stderr.strip() == "rce-fleet task: refused (not_found): no task 'a/b' among the open and recent tasks", \
        p.stderr
