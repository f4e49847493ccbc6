"""A robot stuck for real: ``rce-fleet demo --lifelong`` as a process (engine, fleet container, pymunk
robots, the operator page in Chromium) on the lab map, 2 robots, one pick-up (cell 34) and one drop-off
(cell 36). Robot1 stands in
cell 32, two cells from the pick-up, boxed in by unannounced boxes in cells 24, 33 and 40 (the map's
wall is on its left), and the planner ignores what the lidars see (``--no-lidar-blocking``: obstacles
the fleet cannot know, as ones below the lidar's plane). Robot1, the nearest, takes the first task and
cannot leave its cell. The fleet must not leave it so: a stall alert (on the page, in the log, in the
fleet's task list and the report) and the task given to Robot2, which comes from the other side and does it.

The lab grid (8x8 cells of 1 m; ## = not free)::

     0  1  2  3  4  5  6  7
     8  9 10 11 12 13 ## 15
    16 17 18 19 20 21 22 23
    24 25 26 27 28 ## 30 31
    32 33 34 35 36 37 38 39      Robot1 at 32, boxes in 24, 33, 40, pick1 at 34, drop1 at 36, Robot2 at 39
    40 41 ## 43 44 ## 46 47
    48 49 ## 51 52 ## 54 55
    56 57 58 59 60 61 62 63
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.fleet.test_fleet_tasks_api import ADMIN

BIN = Path(sys.executable).parent
RUN_TIMEOUT_S = 150       # wall s the run may take (its --timeout)
URL_TIMEOUT_S = 90        # wall s until the page is up
ALERT_TIMEOUT_MS = 90_000  # the page shows the alert (60 s simulated after the first task, at speed-up 15)
PLACES = """places:
  - {name: pick1, kind: pickup, cell: 34}
  - {name: drop1, kind: dropoff, cell: 36}
  - {name: charger1, kind: charger, cell: 0}
  - {name: park1, kind: parking, cell: 32}
  - {name: park2, kind: parking, cell: 39}
"""


def test_a_robot_held_by_an_obstacle_it_cannot_pass_raises_an_alert_and_its_task_goes_to_another(tmp_path, page):
    (tmp_path / "places.yaml").write_text(PLACES)
    (tmp_path / "admin-pw").write_text(ADMIN[1] + "\n")
    report, log = tmp_path / "report.json", tmp_path / "demo.log"
    # tasks (seed 1, 1 a minute): T1 at 8.7 s, T2 at 16.2 s, then 79.4 s, ... simulated
    argv = [str(BIN / "rce-fleet"), "demo", "--lifelong", "--duration", "200", "--robots", "2", "--task-rate", "1/min",
            "--speedup", "15", "--grid", "8x8", "--places", str(tmp_path / "places.yaml"), "--start", "Robot1=32",
            "--start", "Robot2=39", "--obstacle", "24@0", "--obstacle", "33@0", "--obstacle", "40@0",
            "--no-lidar-blocking", "--web-port", "0", "--admin-password-file", str(tmp_path / "admin-pw"), "--no-live",
            "--report", str(report), "--plot", "", "--workdir", str(tmp_path / "run"), "--timeout", str(RUN_TIMEOUT_S)]
    p = subprocess.Popen(argv, stdout=open(log, "wb"), stderr=subprocess.STDOUT, start_new_session=True, cwd=tmp_path,
                         env=dict(os.environ, RCE_LOG_JSON="1"))
    try:
        deadline = time.monotonic() + URL_TIMEOUT_S
        while not (url := re.search(r"operator page: (http://\S+)", log.read_text(errors="replace"))):
            assert p.poll() is None and time.monotonic() < deadline, log.read_text(errors="replace")[-3000:]
            time.sleep(0.1)     # polling the log for a line, with a deadline
        # the page: the alert in Robot1's row and in the page's log
        page.goto(url.group(1))
        page.wait_for_function("document.querySelector('#user').value !== ''", timeout=ALERT_TIMEOUT_MS)
        page.fill("#password", ADMIN[1])
        page.click("#login-btn")
        page.wait_for_function("fleetView.log.some(l => l.kind == 'error' && "
                               "l.text.startsWith('ALERT Robot1 made no progress'))", timeout=ALERT_TIMEOUT_MS)
        act = page.locator("#work tbody tr[data-robot=Robot1] .act")
        assert "stalled" in act.inner_text() and "alert" in act.get_attribute("class")
        assert "task T1 goes back to the queue" in act.get_attribute("title")
        code = p.wait(RUN_TIMEOUT_S + 60)
    finally:
        if p.poll() is None:
            p.send_signal(signal.SIGKILL)
            p.wait()
    out = log.read_text(errors="replace")
    assert code == 0 and report.exists(), out[-3000:]
    rep = json.loads(report.read_text())
    # the alert: in the report, in the fleet's task list (per robot) and in the log
    alerts = [a for a in rep["alerts"] if a["robot"] == "Robot1"]
    assert alerts, (rep["alerts"], out[-3000:])
    first = alerts[0]["text"]
    # 60 s of fleet time (the dispatcher looks at every planner tick: 0.2 s wall, 3 s simulated here)
    held = re.match(r"Robot1 made no progress for (\d+) s at cell 32 on task T1 \(goal 34\)", first)
    assert held and 60 <= int(held.group(1)) <= 70, first
    assert "task T1 goes back to the queue for another robot" in first, first
    assert rep["per_robot"]["Robot1"]["stalls"] >= 1, rep["per_robot"]
    assert '"robot stalled"' in out and "task T1 goes back to the queue" in out, out[-3000:]
    # the recovery: the task was done, by the other robot; nothing failed
    tasks = {t["id"]: t for t in rep["tasks"]["list"]}
    assert tasks["T1"]["state"] == "done" and tasks["T1"]["robot"] == "Robot2", tasks
    assert rep["tasks"]["failed"] == 0, rep["tasks"]
    # Robot1 stayed where the boxes held it
    assert [c for _, c in rep["per_robot"]["Robot1"]["cells"]] == [32], rep["per_robot"]["Robot1"]["cells"]
