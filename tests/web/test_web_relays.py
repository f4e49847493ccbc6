"""The operator's page draws a line from a robot out of coverage to the robot that relays for it:
``rce-fleet serve --out-of-coverage Robot2`` as a process on the lab map with 2 robots, Robot2 (cell
31) next to Robot1 (cell 30). Robot2's link goes through Robot1's relay; the master knows it, the
page asks (``relays.json``) and draws a dashed line in Robot1's colour from Robot2 to Robot1. The test
reads what the last frame drew (``fleetView.relayLines``) and the canvas's pixels along the line."""
from __future__ import annotations

import pytest

from tests.fleet.test_fleet_tasks_api import start_serve, stop_serve
from tests.web.test_web_fleet import STATES_TIMEOUT_MS

RELAY_COLOUR = (0x1F, 0x77, 0xB4)     # PALETTE[0] of fleet.js: Robot1's colour
COLOUR_TOL = 40                       # per channel, for anti-aliased line pixels
LINE_TIMEOUT_MS = 30_000              # the master knows the relay, the page has asked (every 1 s) and drawn


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    f = start_serve(tmp_path_factory.mktemp("relays"), "--out-of-coverage", "Robot2", "--radio-range", "4",
                    "--start", "Robot1=30", "--start", "Robot2=31")
    yield f
    stop_serve(f)


def test_the_page_draws_a_line_from_a_follower_to_its_relay(page, fleet):
    page.goto(fleet["page"])
    page.wait_for_function("document.querySelector('#user').value !== ''", timeout=STATES_TIMEOUT_MS)
    page.fill("#password", "testUser")
    page.click("#login-btn")
    page.wait_for_function("fleetView.connected && Object.keys(fleetView.robots).length == 2",
                           timeout=STATES_TIMEOUT_MS)
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
