"""An operator creates, watches and cancels tasks on the fleet page, for real: ``rce-fleet
serve`` as a process (engine processes, fleet container with the global planner and
move_clients, pymunk robots with batteries as rce-ros clients) on the lab map, the page in
Chromium. What the test reads is the page's own model (``fleetView.tasks``, built from
``/fleet/tasks`` only) and its DOM; the fleet's HTTP API confirms the fleet's side."""
from __future__ import annotations

import pytest

from tests.fleet.test_fleet_tasks_api import ADMIN, basic, http, start_serve, stop_serve

STATES_TIMEOUT_MS = 30_000     # logged in, fleet states and task lists arriving
ANSWER_TIMEOUT_MS = 15_000     # a request is answered in the page's log
ASSIGN_TIMEOUT_MS = 20_000     # a task gets a robot
DONE_TIMEOUT_MS = 60_000       # a pick-up -> drop-off task is done (lab map, speedup 10)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    f = start_serve(tmp_path_factory.mktemp("webtasks"), "--battery", "", "--metrics-public")
    yield f
    stop_serve(f)


@pytest.fixture
def op(page, fleet):
    page.goto(fleet["page"])
    page.wait_for_function("document.querySelector('#user').value !== ''", timeout=STATES_TIMEOUT_MS)
    page.fill("#password", ADMIN[1])
    page.click("#login-btn")
    page.wait_for_function("fleetView.connected && fleetView.updates >= 2 && fleetView.tasks.lists >= 2 && "
                           "Object.keys(fleetView.tasks.robots).length == 2", timeout=STATES_TIMEOUT_MS)
    return page


def settled(page, needle: str) -> dict:
    page.wait_for_function("(n) => fleetView.log.some(l => l.text.includes(n) && l.kind !== 'pending')",
                           arg=needle, timeout=ANSWER_TIMEOUT_MS)
    return page.evaluate("(n) => fleetView.log.filter(l => l.text.includes(n) && l.kind !== 'pending').pop()", needle)


def click_cell(page, cell: int) -> None:
    c = page.evaluate(f"fleetView.cellCenterClient({cell})")
    page.mouse.click(c["x"], c["y"])


def test_operator_creates_watches_and_cancels_tasks_on_the_page(op, fleet):
    page = op
    # the page logged in at the fleet's server first (config.json and map.png need a credential), then at
    # the master: the map arrived with its token, the master's URL came from the config
    page.wait_for_function("fleetView.map.loaded", timeout=STATES_TIMEOUT_MS)
    assert page.evaluate("fleetView.config.master") == fleet["master"]
    # each robot's battery (full) and activity are shown
    page.wait_for_function("document.querySelectorAll('#work tbody tr').length == 2")
    assert page.inner_text("#work tbody tr[data-robot=Robot1] .bat b") == "100 %"
    # a task by clicking cells: pick1 (cell 16) then drop1 (cell 23), priority 3
    page.click("#task-pick")
    click_cell(page, 16)
    click_cell(page, 23)
    assert page.input_value("#task-errands") == "pick1, drop1"     # cells of places show as their names
    page.fill("#task-priority", "3")
    page.click("#task-add")
    entry = settled(page, "task pick1 -> drop1")
    assert entry["kind"] == "ok", entry
    tid = entry["text"].split("task ")[-1].split()[0]
    page.wait_for_function("(id) => fleetView.tasks.list.some(t => t.id == id && t.robot)", arg=tid,
                           timeout=ASSIGN_TIMEOUT_MS)
    row = f"#task-queue tr[data-task='{tid}']"
    assert page.inner_text(f"{row} .robot") in ("Robot1", "Robot2")
    assert page.inner_text(f"{row} .state") in ("assigned", "active", "done")
    # a second one from the places menu and typed cells: a long trip, cancelled with its button
    page.select_option("#task-place", "drop1")
    page.fill("#task-errands", page.input_value("#task-errands") + ", 63, 0")
    page.click("#task-add")
    long = settled(page, "task drop1 -> 63 -> 0")
    assert long["kind"] == "ok", long
    lid = long["text"].split("task ")[-1].split()[0]
    page.wait_for_selector(f"#task-queue tr[data-task='{lid}'] button[data-cancel]")
    page.click(f"#task-queue tr[data-task='{lid}'] button[data-cancel]")
    assert settled(page, f"cancel task {lid}")["kind"] == "ok"
    page.wait_for_function("(id) => fleetView.tasks.list.some(t => t.id == id && t.state == 'cancelled')", arg=lid)
    assert page.inner_text(f"#task-queue tr[data-task='{lid}'] .state") == "cancelled"
    assert page.locator(f"#task-queue tr[data-task='{lid}'] button").count() == 0
    code, t = http(fleet, "GET", f"/api/tasks/{lid}")
    # who did it is the server's to say: the person logged in at the page, whatever the page wrote
    assert code == 200 and t["state"] == "cancelled" and t["source"] == "page:admin"
    assert t["cancelled_by"] == "page:admin"
    # bad input: the fleet's reason in the page's log, nothing else lost
    page.fill("#task-errands", "pick1, dock9")
    page.click("#task-add")
    bad = settled(page, "task pick1 -> dock9")
    assert bad["kind"] == "error" and "unknown place 'dock9'" in bad["text"], bad
    # the first task is watched to its end; the plots have data
    page.wait_for_function("(id) => fleetView.tasks.list.some(t => t.id == id && t.state == 'done')", arg=tid,
                           timeout=DONE_TIMEOUT_MS)
    assert page.inner_text(f"{row} .state") == "done"
    # the table is updated in place: task lists that change no order move no row (a row moved under the
    # pointer between press and release would lose the operator's click)
    page.evaluate("""() => { window.rowMoves = 0; new MutationObserver((ms) => { for (const m of ms)
        window.rowMoves += m.addedNodes.length; }).observe(document.querySelector('#task-queue tbody'),
        {childList: true}); }""")
    lists = page.evaluate("fleetView.tasks.lists")
    page.wait_for_function("(n) => fleetView.tasks.lists >= n + 2", arg=lists, timeout=STATES_TIMEOUT_MS)
    assert page.evaluate("window.rowMoves") == 0
    # a click on the task shows its history: created, assigned, opened, each errand, done, with times
    assert page.is_hidden("#task-history")
    page.click(f"{row} .id")
    page.wait_for_selector("#task-history", state="visible")
    hist = page.inner_text("#task-history")
    for said in ("created by page:admin", "assigned to Robot", "opened (first errand reached)",
                 "errand 2 (drop1) reached", "done"):
        assert said in hist, hist
    page.click(f"{row} .id")
    page.wait_for_selector("#task-history", state="hidden")
    # the plots sample every few seconds of fleet time: wait for the first sample after the task was done
    page.wait_for_function("fleetView.tasks.history.length && fleetView.tasks.history.at(-1).done >= 1",
                           timeout=ANSWER_TIMEOUT_MS)
    h = page.evaluate("fleetView.tasks.history")
    assert len(h) >= 2 and h[-1]["done"] >= 1 and 0 < h[-1]["util"] <= 1
    assert "done 1" in page.inner_text("#task-stats")


def test_plain_http_takes_tokens_not_basic_and_metrics_public_needs_none(fleet):
    code, err = http(fleet, "GET", "/api/tasks", auth=basic("testUser", "testUser"))
    assert code == 401 and "HTTP Basic only over TLS" in err["error"], err
    code, text = http(fleet, "GET", "/metrics", auth=None)              # --metrics-public
    assert code == 200 and "rce_fleet_tasks_open" in text
    assert http(fleet, "GET", "/api/tasks", auth=None)[0] == 401         # the rest still needs a credential
