"""Every role sees the live view its role allows, in a real browser: ``rce-fleet serve`` as a process with a users
file (a viewer, an operator) beside the first admin, the page in Chromium, one login per role. The page's RCE
session goes through the page's server as the fleet's internal user, so a person's own user needs no container
(a viewer's or an operator's live view once got ``CN: container 'cTag_01' does not exist``). What the test reads
is the page's own model (``fleetView``, from ``/fleet/state`` and ``/fleet/tasks``) and the fleet's HTTP API."""
from __future__ import annotations

import pytest

from tests.fleet.test_fleet_tasks_api import ADMIN, USERS, http, start_serve, stop_serve, write_users

LIVE_TIMEOUT_MS = 30_000       # logged in, fleet states and task lists arriving
ANSWER_TIMEOUT_MS = 15_000     # a request is answered in the page's log
ROLES = {"viewer": ("vera", USERS["vera"][1]), "operator": ("otto", USERS["otto"][1]), "admin": ADMIN}


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    d = tmp_path_factory.mktemp("webroles")
    f = start_serve(d, "--battery", "", "--users", str(write_users(d / "users.json")))
    yield f
    stop_serve(f)


def _live(page, fleet, user: str, password: str) -> None:
    page.goto(fleet["page"])
    page.wait_for_function("document.querySelector('#user').value !== ''", timeout=LIVE_TIMEOUT_MS)
    page.fill("#user", user)
    page.fill("#password", password)
    page.click("#login-btn")
    page.wait_for_function("fleetView.connected && fleetView.updates >= 3 && fleetView.tasks.lists >= 2 && "
                           "Object.keys(fleetView.robots).length == 2", timeout=LIVE_TIMEOUT_MS)


@pytest.mark.parametrize("role", list(ROLES))
def test_each_role_sees_the_live_fleet_and_does_what_it_may(page, fleet, role):
    user, password = ROLES[role]
    _live(page, fleet, user, password)
    errors = page.evaluate("fleetView.cloudErrors.concat(fleetView.log.filter(l => l.kind == 'error')"
                           ".map(l => l.text))")
    assert not [e for e in errors if "does not exist" in e or "refused" in e], errors
    assert page.input_value("#container") == "cTag_01"
    if role == "viewer":
        # it watches on: later states and task lists keep arriving on the same session, never closed for a frame
        n = page.evaluate("fleetView.updates")
        page.wait_for_function("(n) => fleetView.updates >= n + 3 && fleetView.connected", arg=n,
                               timeout=LIVE_TIMEOUT_MS)
        assert page.evaluate("fleetView.robotID").startswith("operator-")
        return
    # an operator and an admin add a task from the page; who did it is the server's to say
    page.fill("#task-errands", "pick1")
    page.click("#task-add")
    page.wait_for_function("fleetView.log.some(l => l.text.includes('task pick1') && l.kind !== 'pending')",
                           timeout=ANSWER_TIMEOUT_MS)
    entry = page.evaluate("fleetView.log.filter(l => l.text.includes('task pick1') && l.kind !== 'pending').pop()")
    assert entry["kind"] == "ok", entry
    tid = entry["text"].split("task ")[-1].split()[0]
    code, t = http(fleet, "GET", f"/api/tasks/{tid}")
    assert code == 200 and t["source"] == f"page:{user}", t
    assert http(fleet, "DELETE", f"/api/tasks/{tid}")[0] in (200, 409)      # done already, or cancelled now
