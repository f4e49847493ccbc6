"""``rce-fleet demo`` as a newcomer runs it (``make demo``), under a pseudo-terminal: the warehouse by
tasks (12 robots, batteries), the operator page's URL first, the live table (no JSON log lines), and
at the end the KPIs and the PNG of tasks done and activity; exit 0. Cut to 45 simulated seconds, its
first minute as a newcomer sees it: a task is done within the first 30 simulated seconds, more follow,
and no robot leaves its work for a charger while its battery holds plenty."""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from ptyrun import run_on_a_terminal

BIN = Path(sys.executable).parent
RUN_TIMEOUT_S = 240
DURATION_S = 45           # simulated s of the run
FIRST_DONE_S = 30.0       # simulated s by which the first task is done
LOW_PCT = 35.0            # a robot heads for a charger only below this battery level (threshold 20 %, or a task
                          # whose energy with the way to a charger it lacks, a third of a 10 Wh battery at most)


def test_default_demo_runs_the_warehouse_by_tasks_and_prints_its_kpis(tmp_path):
    png, report = tmp_path / "tasks.png", tmp_path / "report.json"
    code, out = run_on_a_terminal([str(BIN / "rce-fleet"), "demo", "--duration", str(DURATION_S), "--web-port", "0",
                                   "--plot", str(png), "--report", str(report), "--workdir", str(tmp_path / "run")],
                                  tmp_path, RUN_TIMEOUT_S)
    assert code == 0, out[-4000:]
    lines = [ln.strip() for ln in out.splitlines() if ln.strip()]
    assert not [ln for ln in lines if ln.startswith("{")], "no JSON log lines on a terminal"
    url = next(i for i, ln in enumerate(lines) if "operator page: http://" in ln)
    table = next(i for i, ln in enumerate(lines) if "robots by tasks on warehouse" in ln)
    assert url < table, "the page's URL comes before the live table"
    assert "Robot12" in out and re.search(r"\b(driving|at errand|idle|charging|to charger|parking)\b", out)
    kpi = re.search(r"tasks done \d+ in (\d+) s sim \(\d+ per hour\)", out)
    assert kpi and DURATION_S <= int(kpi.group(1)) <= DURATION_S + 5, out[-2000:]   # the last tick may pass the cut
    assert re.search(r"task time mean [\d.]+ s, p95 [\d.]+ s; utilisation \d+ %; charges \d+", out)
    assert f"tasks done and activity plotted to {png}" in out and png.stat().st_size > 10_000
    # the first minute: tasks done early, chargers only for low batteries, no robot stuck
    rep = json.loads(report.read_text())
    assert rep["robots"] == 12 and rep["map"].endswith("warehouse.yaml"), rep["map"]
    tasks = rep["tasks"]
    assert tasks["first_done_s"] is not None and tasks["first_done_s"] <= FIRST_DONE_S, tasks
    assert tasks["done"] >= 2 and tasks["failed"] == 0, tasks
    assert f"first done at {tasks['first_done_s']:.0f} s sim" in out
    trips = {r: w["charge_trips"] for r, w in rep["per_robot"].items() if w["charge_trips"]}
    assert all(pct < LOW_PCT for t in trips.values() for _, pct in t), trips
    assert not rep["alerts"], rep["alerts"]
