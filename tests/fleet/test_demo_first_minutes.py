"""The first minute of ``make demo`` (``rce-fleet demo``: 12 robots by tasks on the warehouse, batteries)
as a newcomer sees it, as a process, cut to 45 simulated seconds: a task is done within the first 30
simulated seconds, more follow, and no robot leaves its work for a charger while its battery holds
plenty."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BIN = Path(sys.executable).parent
RUN_TIMEOUT_S = 240       # wall s the run may take (its --timeout)
FIRST_DONE_S = 30.0       # simulated s by which the first task is done
LOW_PCT = 35.0            # a robot heads for a charger only below this battery level (threshold 20 %, or a task
                          # whose energy with the way to a charger it lacks, a third of a 10 Wh battery at most)


def test_the_demo_finishes_tasks_within_its_first_30_simulated_seconds_and_charges_only_low_robots(tmp_path):
    report = tmp_path / "report.json"
    argv = [str(BIN / "rce-fleet"), "demo", "--duration", "45", "--headless", "--no-live", "--report", str(report),
            "--plot", "", "--workdir", str(tmp_path / "run"), "--timeout", str(RUN_TIMEOUT_S)]
    p = subprocess.run(argv, capture_output=True, text=True, timeout=RUN_TIMEOUT_S + 60, cwd=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 0 and report.exists(), out[-3000:]
    rep = json.loads(report.read_text())
    assert rep["robots"] == 12 and rep["map"].endswith("warehouse.yaml"), rep["map"]
    tasks = rep["tasks"]
    assert tasks["first_done_s"] is not None and tasks["first_done_s"] <= FIRST_DONE_S, tasks
    assert tasks["done"] >= 2 and tasks["failed"] == 0, tasks
    assert f"first done at {tasks['first_done_s']:.0f} s sim" in out
    trips = {r: w["charge_trips"] for r, w in rep["per_robot"].items() if w["charge_trips"]}
    assert all(pct < LOW_PCT for t in trips.values() for _, pct in t), trips
    assert not rep["alerts"], rep["alerts"]
