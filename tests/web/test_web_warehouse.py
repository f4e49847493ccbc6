"""The operator page at warehouse size, in Chromium at 1600 x 1000: ``rce-fleet serve`` on the shared
warehouse map (about 1,100 cells, places generated) as a process. The cells carry no drawn numbers
(they would bury the map); hovering a cell shows its number (and place) next to the pointer; the map
fills the space beside the side panel. The screenshot is left in the test's tmp dir."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.fleet.test_fleet_tasks_api import ADMIN

BIN = Path(sys.executable).parent
WAREHOUSE = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "maps" / "warehouse.yaml"
URL_TIMEOUT_S = 120
STATES_TIMEOUT_MS = 60_000


@pytest.fixture(scope="module")
def warehouse(tmp_path_factory):
    d = tmp_path_factory.mktemp("warehouse")
    log = d / "serve.log"
    (d / "admin-pw").write_text(ADMIN[1] + "\n")
    argv = [str(BIN / "rce-fleet"), "serve", "--map", str(WAREHOUSE), "--robots", "4", "--web-port", "0",
            "--no-live", "--workdir", str(d / "work"), "--timeout", "600", "--admin-password-file", str(d / "admin-pw")]
    p = subprocess.Popen(argv, stdout=open(log, "wb"), stderr=subprocess.STDOUT, start_new_session=True,
                         env=dict(os.environ, RCE_LOG_JSON="1"))
    deadline = time.monotonic() + URL_TIMEOUT_S
    url = None
    while time.monotonic() < deadline and p.poll() is None:
        m = re.search(r"operator page: (http://\S+)", log.read_text(errors="replace"))
        if m:
            url = m.group(1)
            break
        time.sleep(0.1)                 # polling the log: the process tells nothing else
    if url is None:
        p.kill()
        pytest.fail(f"rce-fleet serve did not come up:\n{log.read_text(errors='replace')[-3000:]}")
    yield url
    p.send_signal(signal.SIGINT)
    try:
        p.wait(30)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)


def test_the_page_is_readable_on_the_warehouse(browser, warehouse, tmp_path):
    ctx = browser.new_context(viewport={"width": 1600, "height": 1000})
    page = ctx.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(warehouse)
        page.wait_for_function("document.querySelector('#user').value !== ''", timeout=STATES_TIMEOUT_MS)
        page.fill("#password", ADMIN[1])
        page.click("#login-btn")
        page.wait_for_function("fleetView.connected && fleetView.updates >= 2 && fleetView.grid",
                               timeout=STATES_TIMEOUT_MS)
        page.wait_for_function("fleetView.numbersDrawn !== null", timeout=STATES_TIMEOUT_MS)
        cells = page.evaluate("fleetView.grid.rows * fleetView.grid.cols")
        assert cells > 900 and page.evaluate("fleetView.numbersDrawn") is False
        # a free cell's number shows on hover, next to the pointer
        cell = page.evaluate("fleetView.grid.free.findIndex((f, i) => f && i > fleetView.grid.cols * 5)")
        at = page.evaluate(f"fleetView.cellCenterClient({cell})")
        assert page.is_hidden("#cell-info")
        page.mouse.move(at["x"], at["y"])
        page.wait_for_selector("#cell-info", state="visible")
        assert page.inner_text("#cell-info").startswith(f"cell {cell}")
        box = page.locator("#cell-info").bounding_box()
        assert abs(box["x"] - at["x"]) < 60 and abs(box["y"] - at["y"]) < 60
        # the map fills its box: the grid spans nearly the whole canvas in one direction
        canvas = page.locator("#map").bounding_box()
        first, last = page.evaluate("[fleetView.cellCenterClient(0), "
                                    "fleetView.cellCenterClient(fleetView.grid.rows * fleetView.grid.cols - 1)]")
        span_x, span_y = last["x"] - first["x"], last["y"] - first["y"]
        assert canvas["width"] > 0.65 * 1600
        assert span_x > 0.9 * canvas["width"] or span_y > 0.9 * canvas["height"]
        page.mouse.move(at["x"] + 200, at["y"] + 100)
        page.screenshot(path=str(os.environ.get("RCE_SCREENSHOT") or tmp_path / "operator-page-warehouse.png"))
        assert errors == []
    finally:
        ctx.close()
