"""The operators' task API against a running fleet: ``rce-fleet serve`` as a process (engine
processes, fleet container with the global planner and move_clients, pymunk robots as
rce-ros clients) on the lab map (8x8 cells of 1 m), 2 robots, sped-up simulation, with a
places file; ``rce-fleet task`` as processes (each logs in as an RCE client) and the JSON
HTTP API of ``serve``'s web server."""
from __future__ import annotations

import json
import os
import re
import signal
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


def start_serve(d: Path, *extra: str) -> dict:
    """``rce-fleet serve`` on the lab map with the places above; returns {"proc", "page", "master", "log"}."""
    (d / "places.yaml").write_text(PLACES)
    log = d / "serve.log"
    argv = [str(BIN / "rce-fleet"), "serve", "--robots", "2", "--speedup", "10", "--grid", "8x8", "--web-port", "0",
            "--no-live", "--workdir", str(d / "work"), "--timeout", "600", "--places", str(d / "places.yaml"),
            "--start", "Robot1=33", "--start", "Robot2=38", *extra]
    p = subprocess.Popen(argv, stdout=open(log, "wb"), stderr=subprocess.STDOUT, start_new_session=True,
                         env=dict(os.environ, RCE_LOG_JSON="1"))
    deadline = time.monotonic() + URL_TIMEOUT_S
    while time.monotonic() < deadline:
        text = log.read_text(errors="replace")
        page = re.search(r"operator page: (http://\S+)", text)
        master = re.search(r"rce-fleet: master (http://\S+)", text)
        if page and master:
            u = page.group(1)
            return {"proc": p, "page": u, "base": u.split("/?")[0], "master": master.group(1), "log": log}
        if p.poll() is not None:
            break
        time.sleep(0.1)
    p.kill()
    pytest.fail(f"rce-fleet serve did not come up:\n{log.read_text(errors='replace')[-3000:]}")


def stop_serve(f: dict) -> None:
    p = f["proc"]
    p.send_signal(signal.SIGINT)
    try:
        p.wait(STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    f = start_serve(tmp_path_factory.mktemp("tasks"))
    yield f
    stop_serve(f)


def cli(fleet, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "rce-fleet"), "task", *args, "--master", fleet["master"]],
                          capture_output=True, text=True, timeout=CLI_TIMEOUT_S)


def http(fleet, method: str, path: str, body: dict | None = None) -> tuple[int, dict | str]:
    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(fleet["base"] + path, data=data, method=method,
                                 headers={"Content-Type": "application/json"} if data else {})
    try:
        with urllib.request.urlopen(req, timeout=15) as r:
            raw, code = r.read().decode(), r.status
    except urllib.error.HTTPError as e:
        raw, code = e.read().decode(), e.code
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
    assert c1["state"] == "cancelled" and c1["source"].startswith("cli:") and c1["cells"] == [23, 16]
    assert c1["reason"].startswith("cancelled by cli:") and c1["finished"] >= c1["created"] > 0


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
