"""Batteries in the live fleet: ``rce-fleet demo --lifelong`` as a process (engine, fleet
container, pymunk robots with small simulated batteries, generated pick-up -> drop-off
tasks) on the lab map; the report's ground truth comes from the simulator's batteries."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BIN = Path(sys.executable).parent
RUN_TIMEOUT_S = 120       # wall s the run may take (its --timeout)
# sim s per wall s: a stall of the machine costs the batteries SPEEDUP times its length, and these
# batteries are small (at 12, one robot ran flat once in a full suite run: a charge came too late)
SPEEDUP = "6"
# a 0.05 Wh battery starting at 30 %: the 25 % threshold comes within seconds, a charge to 60 %
# takes ~25 s at 3 W, and 0.5 W idle drain would empty a robot left alone in ~30 s
BATTERY = "capacity_wh=0.05,drain_wh_per_m=0.0005,idle_w=0.5,charge_w=3,threshold=0.25,recharge=0.6,initial=0.3"
PLACES = """places:
  - {name: pick1, kind: pickup, cell: 16}
  - {name: pick2, kind: pickup, cell: 58}
  - {name: drop1, kind: dropoff, cell: 23}
  - {name: drop2, kind: dropoff, cell: 47}
  - {name: charger1, kind: charger, cell: 0}
  - {name: charger2, kind: charger, cell: 63}
  - {name: park1, kind: parking, cell: 56}
  - {name: park2, kind: parking, cell: 7}
"""


def test_low_batteries_lead_to_charging_and_no_robot_runs_flat(tmp_path):
    (tmp_path / "places.yaml").write_text(PLACES)
    report = tmp_path / "report.json"
    argv = [str(BIN / "rce-fleet"), "demo", "--lifelong", "--duration", "70", "--robots", "2", "--task-rate", "6/min",
            "--speedup", SPEEDUP, "--grid", "8x8", "--places", str(tmp_path / "places.yaml"), "--battery", BATTERY,
            "--headless", "--no-live", "--report", str(report), "--plot", "", "--workdir", str(tmp_path / "run"),
            "--timeout", str(RUN_TIMEOUT_S)]
    p = subprocess.run(argv, capture_output=True, text=True, timeout=RUN_TIMEOUT_S + 60, cwd=tmp_path)
    out = (p.stdout + p.stderr)[-3000:]
    assert p.returncode == 0 and report.exists(), out
    rep = json.loads(report.read_text())
    assert rep["ok"] and rep["reason"] == "70 s simulated"
    tasks = rep["tasks"]
    assert set(tasks) >= {"done", "failed", "cancelled", "per_hour", "mean_s", "p95_s", "deadline_missed"}
    assert tasks["generated"] >= 3 and tasks["failed"] == 0
    for robot, v in rep["per_robot"].items():
        # each robot was sent to a charger and charged; none ever reached 0. The dispatcher sends a robot
        # below 25 %, or sooner when the task it was offered would leave it short of a charger, so a trip
        # begins under the 60 % it charges to (the simulator's battery, sampled each second)
        assert v["charges"] >= 1 and v["charge_trips"], (robot, v, out)
        assert all(pct < 60 for _, pct in v["charge_trips"]), (robot, v["charge_trips"])
        assert 0 < v["battery_min_pct"] < 30 and not v["ran_flat"], (robot, v)
        assert 0 <= v["utilisation"] <= 1 and v["distance_m"] > 0
