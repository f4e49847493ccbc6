"""The operator's page draws a line from a robot out of coverage to the robot that relays for it:
``rce-fleet serve --out-of-coverage Robot2 --edge-hosts`` as a process on the lab map with 2 robots,
Robot2 (cell 31) next to Robot1 (cell 30). Robot2's link goes through Robot1's relay; the master knows it, the
page asks (``relays.json``) and draws a dashed line in Robot1's colour from Robot2 to Robot1. The test
reads what the last frame drew (``fleetView.relayLines``) and the canvas's pixels along the line.
With ``--edge-hosts`` each move_client has a container of its own: the page's placement table shows
where each runs (Robot2's on its own computer: it is out of coverage) and the placer's reason."""
from __future__ import annotations

import pytest

from tests.fleet.test_fleet_tasks_api import ADMIN, start_serve, stop_serve
from tests.web.test_web_fleet import STATES_TIMEOUT_MS

RELAY_COLOUR = (0x1F, 0x77, 0xB4)     # PALETTE[0] of fleet.js: Robot1's colour
COLOUR_TOL = 40                       # per channel, for anti-aliased line pixels
LINE_TIMEOUT_MS = 30_000              # the master knows the relay, the page has asked (every 1 s) and drawn


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    f = start_serve(tmp_path_factory.mktemp("relays"), "--out-of-coverage", "Robot2", "--radio-range", "4",
                    "--start", "Robot1=30", "--start", "Robot2=31", "--edge-hosts")
    yield f
    stop_serve(f)


def log_in(page, fleet) -> None:
    page.goto(fleet["page"])
    page.wait_for_function("document.querySelector('#user').value !== ''", timeout=STATES_TIMEOUT_MS)
    page.fill("#password", ADMIN[1])
    page.click("#login-btn")
    page.wait_for_function("fleetView.connected && Object.keys(fleetView.robots).length == 2",
                           timeout=STATES_TIMEOUT_MS)


def test_the_page_draws_a_line_from_a_follower_to_its_relay(page, fleet):
    log_in(page, fleet)
    page.wait_for_function("fleetView.relayLines.some(l => l.follower === 'Robot2')", timeout=LINE_TIMEOUT_MS)
    assert page.evaluate("fleetView.relays") == {"Robot2": "Robot1"}
    (line,) = page.evaluate("fleetView.relayLines")
    assert line["follower"] == "Robot2" and line["relay"] == "Robot1", line
    (x1, y1), (x2, y2) = line["from"], line["to"]
    assert abs(x2 - x1) > 10, line      # the robots are 1 m apart, side by side (same row)
    # the canvas has the relay's colour along the line, between the two robots' discs
    hits = page.evaluate("""([x1, y1, x2, y2, rgb, tol]) => {
        const ctx = document.getElementById('map').getContext('2d');
        let hits = 0;
        for (const f of [0.35, 0.5, 0.65]) {
          const x = Math.round(x1 + (x2 - x1) * f), y = Math.round(y1 + (y2 - y1) * f);
          const d = ctx.getImageData(x - 4, y - 4, 9, 9).data;
          const near = (i) => [0, 1, 2].every(k => Math.abs(d[i + k] - rgb[k]) < tol);
          for (let i = 0; i < d.length; i += 4) if (near(i)) { hits++; break; }
        }
        return hits; }""", [x1, y1, x2, y2, list(RELAY_COLOUR), COLOUR_TOL])
    assert hits == 3, (line, hits)


def test_the_page_shows_where_each_move_client_runs_and_why(page, fleet):
    log_in(page, fleet)
    page.wait_for_function("document.querySelectorAll('#placement tbody tr').length == 2", timeout=LINE_TIMEOUT_MS)
    rows = page.evaluate("[...document.querySelectorAll('#placement tbody tr')].map(tr => "
                         "[...tr.children].map(td => td.textContent))")
    by = {r[0]: r for r in rows}
    assert set(by) == {"mc_Robot1", "mc_Robot2"}, rows
    assert by["mc_Robot2"][1].startswith("robot:Robot2"), "out of coverage: its move_client stays on board"
    assert "pinned to robot" in by["mc_Robot2"][5]
    assert by["mc_Robot1"][1].split(" ")[0] in ("cloud", "robot:Robot1") and by["mc_Robot1"][5], rows
    assert page.is_visible("#placement")
