"""The operator's page against the real fleet: ``rce-fleet serve`` as a process (engine processes,
fleet container with the global planner and move_clients, pymunk robots as rce-ros clients) on
the project's lab map (8x8 cells of 1 m), 3 robots, sped-up simulation. The page is served by
rce-fleet on its own port, and its RCE session goes through that server (``/rce/ws``, as the fleet's own
user), so the master and the robot endpoint stay on loopback. The person logs in as the first admin,
whose password the run made and wrote to a 0600 file.

What the tests read is the page's own model (``window.fleetView``), which is built from the
fleet's ``/fleet/state`` only; recorders added with ``fleetView.listeners`` see every state."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from tests.fleet.test_fleet_tasks_api import stop

BIN = Path(sys.executable).parent
STARTS = {"Robot1": 32, "Robot2": 7, "Robot3": 63}
URL_RE = re.compile(r"operator page: (http://\S+)")
URL_TIMEOUT_S = 90        # wall s for rce-fleet to start the engine, the fleet and the page and print its URL
LOG_POLL_S = 0.1          # wall s between reads of rce-fleet's output while waiting for the URL
STATES_TIMEOUT_MS = 30_000     # logged in, fleet states arriving
LOG_TIMEOUT_S = 15.0           # a request the page sent is settled in its log (ok or error)
STOP_LOG_TIMEOUT_S = 20.0      # the mission's stop is settled (a goal drop for every robot)
MOVE_TIMEOUT_MS = 60_000       # every robot has moved 0.5 m on the random mission
ARRIVE_TIMEOUT_MS = 90_000     # a robot reaches a goal several cells away (sped-up simulation)
PATH_TIMEOUT_MS = 20_000       # a new goal's path is shown
HTTP_TIMEOUT_S = 10            # one request to the page's server
DEMO_TIMEOUT_S = 120           # wall s for the two-robot demo to run to its end


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """``rce-fleet serve`` (no mission); yields {"url", "proc", "log"}; stopped with SIGINT."""
    d = tmp_path_factory.mktemp("fleet")
    log = d / "serve.log"
    argv = [str(BIN / "rce-fleet"), "serve", "--robots", str(len(STARTS)), "--speedup", "5", "--seed", "3",
            "--grid", "8x8", "--web-port", "0", "--no-live", "--workdir", str(d / "work"), "--timeout", "600",
            "--report", str(d / "report.json"), *[a for r, c in STARTS.items() for a in ("--start", f"{r}={c}")]]
    out = open(log, "wb")
    p = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                         env=dict(os.environ, RCE_LOG_JSON="1"))
    url = wait_url(log, p)
    if url is None:
        p.kill()
        pytest.fail(f"rce-fleet serve printed no page URL:\n{log.read_text(errors='replace')[-3000:]}")
    yield {"url": url, "proc": p, "log": log, "dir": d}
    stop(p)


def wait_url(log: Path, proc: subprocess.Popen) -> str | None:
    """The page's URL once rce-fleet has printed it to ``log``; None when it exits first or
    takes over URL_TIMEOUT_S."""
    deadline = time.monotonic() + URL_TIMEOUT_S
    while time.monotonic() < deadline:
        m = URL_RE.search(log.read_text(errors="replace"))
        if m:
            return m.group(1)
        if proc.poll() is not None:
            return None
        time.sleep(LOG_POLL_S)
    return None


def admin_password(log: Path) -> str:
    """The first admin's password a loopback run made: read from the 0600 file whose path it printed (the
    password itself is printed nowhere)."""
    text = log.read_text(errors="replace")
    path = Path(re.search(r"log in as admin; the password is in (\S+?)\)", text).group(1))
    assert oct(path.stat().st_mode & 0o777) == "0o600"
    password = path.read_text().strip()
    assert password and password not in text
    return password


def login(page, fleet, password=None):
    page.goto(fleet["url"])
    # fleet.js fills the form after its config.json arrives: wait for that, then check it
    page.wait_for_function("document.querySelector('#user').value !== ''", timeout=STATES_TIMEOUT_MS)
    assert page.input_value("#user") == "admin"             # prefilled from the URL
    assert page.input_value("#password") == ""              # never the password
    page.fill("#password", admin_password(fleet["log"]) if password is None else password)
    page.click("#login-btn")


@pytest.fixture
def op(page, fleet):
    """A logged-in page with the fleet state flowing; a recorder of every state in window.rec."""
    login(page, fleet)
    page.wait_for_function("fleetView.connected && fleetView.updates >= 2 && Object.keys(fleetView.robots).length == 3",
                           timeout=STATES_TIMEOUT_MS)
    page.evaluate("""() => { window.rec = [];
        fleetView.listeners.push((st) => rec.push({t: Date.now(), blocked: st.blocked.slice(),
            robots: Object.fromEntries(st.robots.map(r => [r.robot, {cell: r.cell, x: r.x, y: r.y, goal: r.goal,
                                                                     path: r.path.slice(), state: r.state}]))})); }""")
    return page


def robots(page) -> dict:
    return page.evaluate("fleetView.robots")


def click_cell(page, cell: int) -> None:
    c = page.evaluate(f"fleetView.cellCenterClient({cell})")
    page.mouse.click(c["x"], c["y"])


def last_log(page, needle: str, timeout: float = LOG_TIMEOUT_S) -> dict:
    """The page's log entry about ``needle`` once it is settled (ok or error), within ``timeout`` s."""
    page.wait_for_function("(n) => fleetView.log.some(l => l.text.includes(n) && l.kind !== 'pending')",
                           arg=needle, timeout=timeout * 1000)
    return page.evaluate("(n) => fleetView.log.filter(l => l.text.includes(n) && l.kind !== 'pending').pop()", needle)


def free_cells(page) -> list[int]:
    g = page.evaluate("fleetView.grid")
    blocked = set(page.evaluate("fleetView.blocked"))
    return [i for i, f in enumerate(g["free"]) if f and i not in blocked]


def manhattan(a: int, b: int, cols: int = 8) -> int:
    return abs(a // cols - b // cols) + abs(a % cols - b % cols)


def far_goal(page, robot: str, min_dist: int) -> int:
    """A free cell at least ``min_dist`` from ``robot`` that no robot is in or heading to
    (the lower rows: the partition wall's side of the lab is reached through the door)."""
    rs = robots(page)
    here = rs[robot]["cell"]
    taken = {r["cell"] for r in rs.values()} | {r["goal"] for r in rs.values()}
    cands = [c for c in free_cells(page) if c not in taken and manhattan(c, here) >= min_dist and c >= 24]
    assert cands, (robot, here, rs)
    return max(cands, key=lambda c: (manhattan(c, here), -c))


def test_login_through_the_page_server_and_every_robot_moves(op, fleet, tmp_path):
    page = op
    said = page.evaluate("fleetView.log.map(l => l.text).filter(t => t.includes('robot endpoint'))")
    netloc = urlsplit(fleet["url"]).netloc
    assert said and said[-1].endswith(f"robot endpoint ws://{netloc}/rce/ws"), said   # the page's own server
    assert page.evaluate("fleetView.map.loaded") and page.evaluate("fleetView.map.width") > 0
    before = robots(page)
    assert {r: v["cell"] for r, v in before.items()} == STARTS
    page.click("#mission-start")
    assert last_log(page, "mission start")["kind"] == "ok"
    # positions come in continuously, and the page drew them: every robot away from its start, with a trail
    # of at least 5 points (the trail grows with the positions drawn, so wait for both, not the first alone)
    page.wait_for_function("""(b) => Object.entries(fleetView.robots).every(([n, r]) =>
        Math.hypot(r.x - b[n].x, r.y - b[n].y) > 0.5 && (fleetView.trails[n] || []).length >= 5)""",
                           arg=before, timeout=MOVE_TIMEOUT_MS)
    page.screenshot(path=str(tmp_path / "mission.png"))
    moved = page.evaluate("Object.fromEntries(Object.entries(fleetView.trails).map(([n, t]) => [n, t.length]))")
    assert set(moved) == set(STARTS) and all(v >= 5 for v in moved.values()), moved
    assert page.evaluate("document.querySelectorAll('#robots tbody tr').length") == 3
    page.click("#mission-stop")
    assert last_log(page, "mission stop", timeout=STOP_LOG_TIMEOUT_S)["kind"] == "ok"
    assert all(r["goal"] == -1 for r in robots(page).values())


def test_goal_by_clicking(op, tmp_path):
    page = op
    # pick the robot by clicking it on the map, then click the goal cell
    page.wait_for_function("fleetView.robotClient('Robot2') !== null")
    p = page.evaluate("fleetView.robotClient('Robot2')")
    page.mouse.click(p["x"], p["y"])
    assert page.evaluate("fleetView.selected") == "Robot2"
    # a cell robots cannot use (a table stands in it): the planner's refusal is shown
    g = page.evaluate("fleetView.grid")
    wall = next(i for i, f in enumerate(g["free"]) if not f)
    click_cell(page, wall)
    entry = last_log(page, f"Robot2 -> cell {wall}")
    assert entry["kind"] == "error" and "unreachable" in entry["text"], entry
    goal = far_goal(page, "Robot2", 3)
    click_cell(page, goal)
    entry = last_log(page, f"Robot2 -> cell {goal}")
    assert entry["kind"] == "ok", entry
    page.keyboard.press("Escape")
    assert page.evaluate("fleetView.selected") is None
    # arrived: the planner has it in the goal cell, its move_client says so, and it stands near the centre
    page.wait_for_function(f"""(() => {{ const r = fleetView.robots.Robot2, g = fleetView.grid;
        const cx = g.grid_x + ({goal} % g.cols + 0.5) * g.cell_w;
        const cy = g.grid_y - (Math.floor({goal} / g.cols) + 0.5) * g.cell_h;
        return r.state === 'arrived' && r.clientState === 'arrived' && r.cell === {goal}
            && Math.hypot(r.x - cx, r.y - cy) < 0.3;
        }})()""", timeout=ARRIVE_TIMEOUT_MS)
    assert any(f"Robot2 arrived at cell {goal}" in e["text"] for e in page.evaluate("fleetView.log"))
    page.screenshot(path=str(tmp_path / "goal.png"))
    page.click("#logout")
    page.wait_for_selector("#login", state="visible")
    assert page.evaluate("fleetView.connected") is False


def test_block_a_cell_on_the_path(op, tmp_path):
    page = op
    page.click("#robots tr[data-robot=Robot1]")               # pick the robot in the status table
    goal = far_goal(page, "Robot1", 5)
    click_cell(page, goal)
    assert last_log(page, f"Robot1 -> cell {goal}")["kind"] == "ok"
    page.click("#deselect")
    # a free cell on its planned path, a few cells ahead, not the goal and not where a robot is
    page.wait_for_function("fleetView.robots.Robot1.path.length >= 5", timeout=PATH_TIMEOUT_MS)
    path = robots(page)["Robot1"]["path"]
    occupied = {r["cell"] for r in robots(page).values()}
    cell = next(c for c in path[3:-1] if c not in occupied)
    click_cell(page, cell)
    entry = last_log(page, f"block cell {cell}")
    assert entry["kind"] == "ok", entry
    t_block = page.evaluate(f"rec.find(s => s.blocked.includes({cell})).t")
    page.screenshot(path=str(tmp_path / "blocked.png"))
    page.wait_for_function(f"fleetView.robots.Robot1.state === 'arrived' && fleetView.robots.Robot1.cell === {goal} "
                           "&& fleetView.robots.Robot1.clientState === 'arrived'", timeout=ARRIVE_TIMEOUT_MS)
    page.screenshot(path=str(tmp_path / "rerouted.png"))
    after = page.evaluate(f"rec.filter(s => s.t >= {t_block}).map(s => s.robots.Robot1)")
    assert len(after) > 5
    g = page.evaluate("fleetView.grid")
    r0, c0 = divmod(cell, g["cols"])
    x0, y1 = g["grid_x"] + c0 * g["cell_w"], g["grid_y"] - r0 * g["cell_h"]
    for s in after:                                            # never planned through, never in it
        assert cell not in s["path"], s
        assert s["cell"] != cell, s
        assert not (x0 <= s["x"] <= x0 + g["cell_w"] and y1 - g["cell_h"] <= s["y"] <= y1), s
    assert any("Robot1" in e["text"] and "re-routed" in e["text"] for e in page.evaluate("fleetView.log")) or \
        page.evaluate("fleetView.robots.Robot1.replans") > 0
    # unblock it again by clicking
    click_cell(page, cell)
    assert last_log(page, f"unblock cell {cell}")["kind"] == "ok"
    assert cell not in page.evaluate("fleetView.blocked")


def test_wrong_password_shows_an_error(page, fleet, tmp_path):
    login(page, fleet, password="wrong")
    page.wait_for_function("document.getElementById('login-error').textContent.length > 0", timeout=20_000)
    page.screenshot(path=str(tmp_path / "wrong-password.png"))
    assert "refused" in page.text_content("#login-error")
    assert page.evaluate("fleetView.connected") is False
    assert page.is_visible("#login") and not page.is_visible("#controls")


def test_demo_prints_and_serves_the_page(tmp_path):
    """``rce-fleet demo`` without --headless prints the page's URL and serves the page, and to a
    logged-in user its config (no password in it) and the map image while the mission runs to its end."""
    import json
    import urllib.error
    import urllib.request
    log = tmp_path / "demo.log"
    argv = [str(BIN / "rce-fleet"), "demo", "--mission", "--robots", "2", "--speedup", "5",
            "--start", "Robot1=33", "--start", "Robot2=7", "--goal", "Robot1=35", "--goal", "Robot2=5",
            "--web-port", "0", "--no-live", "--plot", str(tmp_path / "paths.png"), "--timeout", str(DEMO_TIMEOUT_S),
            "--workdir", str(tmp_path / "work")]
    p = subprocess.Popen(argv, stdout=open(log, "wb"), stderr=subprocess.STDOUT, start_new_session=True)
    try:
        url = wait_url(log, p)
        assert url, log.read_text(errors="replace")[-3000:]
        base = url.split("?")[0]
        with pytest.raises(urllib.error.HTTPError) as no:
            urllib.request.urlopen(base + "config.json", timeout=HTTP_TIMEOUT_S)
        assert no.value.code == 401
        req = urllib.request.Request(base + "api/login", data=json.dumps({"user": "admin",
                                                                          "password": admin_password(log)})
                                     .encode(), headers={"Content-Type": "application/json"}, method="POST")
        with urllib.request.urlopen(req, timeout=HTTP_TIMEOUT_S) as r:
            auth = {"Authorization": "Bearer " + json.loads(r.read())["token"]}
        with urllib.request.urlopen(urllib.request.Request(base + "config.json", headers=auth),
                                    timeout=HTTP_TIMEOUT_S) as r:
            cfg = json.loads(r.read())
        assert cfg["container"] == "cTag_01" and cfg["master"].startswith("http://") and "password" not in cfg
        with urllib.request.urlopen(urllib.request.Request(base + "map.png", headers=auth),
                                    timeout=HTTP_TIMEOUT_S) as r:
            assert r.read(8) == b"\x89PNG\r\n\x1a\n"
        with urllib.request.urlopen(url, timeout=HTTP_TIMEOUT_S) as r:
            assert b'src="fleet.js"' in r.read()
        assert p.wait(DEMO_TIMEOUT_S) == 0, log.read_text(errors="replace")[-3000:]
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
